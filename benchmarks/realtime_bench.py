"""Error and deadline misses against the tick rate, in real-time mode.

    python benchmarks/realtime_bench.py [--rates 10,25,50,100,200,400] [--ticks 100]
                                        [--algorithms all|diskf,kcf] [--sizes dynamic,25]
                                        [--figure PNG] [--json OUT]

For each size (``dynamic``: Scenario 2's 9 agents; a number N: the
``random-geometric`` scenario with N agents), estimator and rate, one
``diskf-mesh up --rate HZ`` (``diskf_mesh.mesh.protocol.clock``: the world ticks on the
wall clock, each agent fuses what arrived by its deadline, half the period)
and prints, in one Markdown table: the miss rate (messages not fused in time
and reports not in by the tick's end, over both), the state error of the run
beside the lockstep's (the engine, in-process, same seed: what the run would
give with no deadline), and the actual tick period (mean, p99 of the jitter).
Then, per size and estimator, the highest rate with under 1 % misses, and
the machine's load average before and after (other processes' load shows
as misses). ``--figure`` draws the miss rate and the state error against
the rate, one column per size, one line per estimator (its plot colour);
``--json`` writes the rows.

Every run's estimates are exact for what it fused (``diskf-mesh replay`` of
its recording reproduces them bit for bit); the misses are the cost of the
clock. The machine is shared and noisy: the figures are those of one
invocation on it.
"""
from __future__ import annotations

import argparse
import json
import os
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
    from diskf_mesh.mesh.process.runspec import RunSpec

    spec = RunSpec(scenario="dynamic" if size == "dynamic" else "random-geometric", algorithm=algorithm,
                   agents=None if size == "dynamic" else int(size))
    scn = spec.load(ticks)
    trace = simulate(scn, [0])
    return float(metrics.compute(trace, engine.run(trace, algorithm, scn.params))["mae_state"])


def run_one(size: str, algorithm: str, rate: float, ticks: int, workdir: Path) -> dict:
    out = workdir / f"{size}-{algorithm}-{rate:g}-{time.monotonic_ns()}.json"
    cmd = [sys.executable, "-m", "sim.launcher", *scenario_args(size), "--algorithm", algorithm,
           "--ticks", str(ticks), "--rate", repr(rate), "--tick-timeout", "5", "--json", str(out), "--quiet",
           "--max-miss-rate", "1"]  # the sweep measures the misses: any rate of them is a result
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
    p.add_argument("--rates", default="10,25,50,100,200,400", help="comma list of tick rates (Hz)")
    p.add_argument("--ticks", type=int, default=100)
    p.add_argument("--algorithms", "--estimators", default="diskf,kcf",
                   help="'all' or a comma list of estimators (default: diskf and the KCF baseline)")
    p.add_argument("--figure", metavar="PNG", help="draw misses and error against rate")
    p.add_argument("--json", metavar="OUT", help="write the rows as JSON")
    p.add_argument("--sizes", default="dynamic,25",
                   help="comma list: 'dynamic' (Scenario 2, 9 agents) or an agent count (random-geometric)")
    args = p.parse_args(argv)
    rates = [float(r) for r in args.rates.split(",")]
    if args.algorithms == "all":
        from diskf_mesh import estimators
        args.algorithms = ",".join(estimators.NAMES)
    load0 = os.getloadavg()
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
    load1 = os.getloadavg()
    print(f"\nload average (1 min) before {load0[0]:.1f}, after {load1[0]:.1f}, on {os.cpu_count()} cores")
    if args.json:
        Path(args.json).write_text(json.dumps({"ticks": args.ticks, "load_before": load0, "load_after": load1,
                                               "rows": rows}, indent=1))
    if args.figure:
        draw(rows, args.sizes.split(","), args.algorithms.split(","), args.ticks, args.figure)
        print(f"figure -> {args.figure}")
    return 0


def draw(rows: list, sizes: list, algorithms: list, ticks: int, path: str) -> None:
    """Miss rate (top) and MAE(state) (bottom) against the rate, per size."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.ticker

    from diskf_mesh import estimators

    fig, axes = plt.subplots(2, len(sizes), figsize=(5.2 * len(sizes), 7), squeeze=False, sharex=True)
    for c, size in enumerate(sizes):
        top, bottom = axes[0, c], axes[1, c]
        for alg in algorithms:
            ok = sorted((r for r in rows if r["size"] == size and r["algorithm"] == alg and "error" not in r),
                        key=lambda r: r["rate"])
            if not ok:
                continue
            style = dict(color=estimators.color(alg), label=estimators.label(alg), marker="o", ms=4)
            top.plot([r["rate"] for r in ok], [100 * r["miss_rate"] for r in ok], **style)
            bottom.plot([r["rate"] for r in ok], [r["mae_state"] for r in ok], **style)
            bottom.axhline(ok[0]["lockstep_mae"], color=style["color"], lw=0.8, ls=":")
        top.axhline(100 * MISS_OK, color="grey", lw=0.8, ls="--")
        top.set_title("Scenario 2 (9 agents)" if size == "dynamic" else f"random geometric, {size} agents")
        top.set_ylabel("deadline misses (%)")
        bottom.set_ylabel("MAE(state); dotted: lockstep")
        bottom.set_xlabel("tick rate (Hz)")
        rates = sorted({r["rate"] for r in rows if r["size"] == size})
        for ax in (top, bottom):
            ax.set_xscale("log")
            ax.set_xticks(rates, [f"{r:g}" for r in rates])
            ax.minorticks_off()
            ax.grid(True, alpha=0.3)
        bottom.set_yscale("log")
        bottom.yaxis.set_major_formatter(matplotlib.ticker.ScalarFormatter())
        bottom.yaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
    axes[0, 0].legend(fontsize=8)
    fig.suptitle(f"real time: misses and error against the tick rate\n({ticks} ticks a run, deadline half the period)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)


if __name__ == "__main__":
    sys.exit(main())
