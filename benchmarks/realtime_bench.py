"""Error and deadline misses against the tick rate, in real-time mode.

    python benchmarks/realtime_bench.py [--rates 10,25,50,100,200] [--ticks 100]
                                        [--algorithms diskf,kcf] [--sizes dynamic,25]

For each size (``dynamic``: Scenario 2's 9 agents; a number N: the
``random-geometric`` scenario with N agents), estimator and rate, one
``diskf-mesh up --rate HZ`` (``diskf_mesh.mesh.clock``: the world ticks on the
wall clock, each agent fuses what arrived by its deadline, half the period)
and prints, in one Markdown table: the miss rate (messages not fused in time
and reports not in by the tick's end, over both), the state error of the run
beside the lockstep's (the engine, in-process, same seed: what the run would
give with no deadline), and the actual tick period (mean, p99 of the jitter).
Then, per size and estimator, the highest rate with under 1 % misses.

Every run's estimates are exact for what it fused (``diskf-mesh replay`` of
its recording reproduces them bit for bit); the misses are the cost of the
clock. The machine is shared and noisy: the figures are those of one
invocation on it.
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))

MISS_OK = 0.01


def scenario_args(size: str) -> list:
    return ["--scenario", "dynamic"] if size == "dynamic" else ["--scenario", "random-geometric", "--agents", size]


def lockstep_mae(size: str, algorithm: str, ticks: int) -> float:
    """The engine's MAE(state) on the same run (mesh == engine in lockstep)."""
    from diskf_mesh.data import metrics
    from diskf_mesh.data.scenario import simulate
    from diskf_mesh.engine import batch as engine
    from diskf_mesh.mesh.runspec import RunSpec

    spec = RunSpec(scenario="dynamic" if size == "dynamic" else "random-geometric", algorithm=algorithm,
                   agents=None if size == "dynamic" else int(size))
    scn = spec.load(ticks)
    trace = simulate(scn, [0])
    return float(metrics.compute(trace, engine.run(trace, algorithm, scn.params))["mae_state"])


def run_one(size: str, algorithm: str, rate: float, ticks: int, workdir: Path) -> dict:
    out = workdir / f"{size}-{algorithm}-{rate:g}-{time.monotonic_ns()}.json"
    cmd = [sys.executable, "-m", "sim.launcher", *scenario_args(size), "--algorithm", algorithm,
           "--ticks", str(ticks), "--rate", repr(rate), "--tick-timeout", "5", "--json", str(out), "--quiet"]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    if done.returncode != 0 or not out.exists():
        return {"error": (done.stderr.strip().splitlines() or ["?"])[-1][:120]}
    row = next(iter(next(iter(json.loads(out.read_text()).values())).values()))
    dm, tp = row["deadline_misses"], row["tick_period"]
    return {"miss_rate": dm["miss_rate"], "message_miss_rate": dm["message_miss_rate"],
            "report_miss_rate": dm["report_miss_rate"], "mae_state": row["mae_state"],
            "period_ms": 1e3 * tp.get("mean_s", float("nan")), "jitter_ms": 1e3 * tp.get("p99_jitter_s", float("nan"))}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--rates", default="10,25,50,100,200", help="comma list of tick rates (Hz)")
    p.add_argument("--ticks", type=int, default=100)
    p.add_argument("--algorithms", default="diskf,kcf", help="comma list of estimators (default: diskf and the "
                                                              "KCF baseline)")
    p.add_argument("--sizes", default="dynamic,25",
                   help="comma list: 'dynamic' (Scenario 2, 9 agents) or an agent count (random-geometric)")
    args = p.parse_args(argv)
    rates = [float(r) for r in args.rates.split(",")]
    rows = []
    with tempfile.TemporaryDirectory(prefix="realtime-bench-") as tmp:
        for size in args.sizes.split(","):
            for alg in args.algorithms.split(","):
                ref = lockstep_mae(size, alg, args.ticks)
                for rate in rates:
                    r = run_one(size, alg, rate, args.ticks, Path(tmp))
                    r.update(size=size, algorithm=alg, rate=rate, lockstep_mae=ref)
                    rows.append(r)
                    print(f"{size} {alg} {rate:g} Hz: " + (r.get("error") or
                          f"misses {100 * r['miss_rate']:.1f} %, MAE {r['mae_state']:.2f}"), file=sys.stderr, flush=True)
    print(f"\nreal time (--rate), {args.ticks} ticks, deadline half the period, one process per agent, "
          "zenoh on loopback\n")
    print("| agents | estimator | rate (Hz) | misses % (messages, reports) | MAE(state) | lockstep MAE(state) "
          "| period mean (ms) | p99 jitter (ms) |")
    print("|---|---|---|---|---|---|---|---|")
    for r in rows:
        n = "9 (dynamic)" if r["size"] == "dynamic" else r["size"]
        if "error" in r:
            print(f"| {n} | {r['algorithm']} | {r['rate']:g} | failed: {r['error']} | | {r['lockstep_mae']:.2f} | | |")
            continue
        print(f"| {n} | {r['algorithm']} | {r['rate']:g} | {100 * r['miss_rate']:.1f} "
              f"({100 * r['message_miss_rate']:.1f}, {100 * r['report_miss_rate']:.1f}) | {r['mae_state']:.2f} "
              f"| {r['lockstep_mae']:.2f} | {r['period_ms']:.1f} | {r['jitter_ms']:.1f} |")
    print()
    for size in args.sizes.split(","):
        for alg in args.algorithms.split(","):
            ok = [r["rate"] for r in rows if r["size"] == size and r["algorithm"] == alg
                  and "error" not in r and r["miss_rate"] < MISS_OK]
            n = "9 agents (dynamic)" if size == "dynamic" else f"{size} agents"
            print(f"{n}, {alg}: highest rate with under 1 % misses: " + (f"{max(ok):g} Hz" if ok else "none of the rates tried"))
    return 0


if __name__ == "__main__":
    sys.exit(main())
