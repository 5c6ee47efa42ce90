"""What recording costs: ``diskf-mesh up`` with and without ``--record``,
side by side in one invocation. Prints a markdown table; not a test.

    python benchmarks/record_bench.py [--scenario dynamic] [--ticks 300] [--repeat 5] [--algorithm diskf]

Each repeat runs the pair back to back (which goes first alternates), so
both see the same load of a shared machine; the ratios are per pair.

    ticks/s      from tick 1 to the last report (the world's ticks_s)
    CPU ms/tick  CPU of all processes (world, agents, launcher) per tick,
                 start-up included
"""
from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from mesh_bench import cpu_seconds


def run_one(args, workdir: Path, record: bool, tag: str) -> dict:
    est, res, rec = workdir / f"est-{tag}.json", workdir / f"res-{tag}.json", workdir / f"run-{tag}.mcap"
    cmd = [sys.executable, "-m", "sim.launcher", "--scenario", args.scenario, "--ticks", str(args.ticks),
           "--algorithm", args.algorithm, "--estimates", str(est), "--json", str(res), "--quiet",
           "--logs", str(workdir / f"logs-{tag}"), "--startup-timeout", "120", *args.flags]
    if record:
        cmd += ["--record", str(rec)]
    cpu0, t0 = cpu_seconds(), time.monotonic()
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=1800)
    cpu = cpu_seconds() - cpu0
    if done.returncode != 0:
        raise SystemExit(f"up failed: {done.stderr.strip().splitlines()[-1:]}")
    doc = json.loads(est.read_text())
    return {"record": record, "ticks_per_s": args.ticks / doc["ticks_s"], "cpu_ms_per_tick": 1e3 * cpu / args.ticks,
            "wall_s": time.monotonic() - t0, "bytes": rec.stat().st_size if record else 0}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--scenario", default="dynamic")
    p.add_argument("--ticks", type=int, default=300)
    p.add_argument("--algorithm", default="diskf")
    p.add_argument("--repeat", type=int, default=5)
    p.add_argument("--flags", nargs=argparse.REMAINDER, default=[], help="more flags for up (e.g. --loss 0.3)")
    args = p.parse_args(argv)
    pairs = []
    with tempfile.TemporaryDirectory(prefix="record-bench-") as tmp:
        for r in range(args.repeat):
            order = (False, True) if r % 2 == 0 else (True, False)
            runs = {rec: run_one(args, Path(tmp), rec, f"{r}-{int(rec)}") for rec in order}
            pairs.append(runs)
            print(json.dumps([runs[False], runs[True]]), file=sys.stderr, flush=True)
    med = lambda rows, key: statistics.median(x[key] for x in rows)  # noqa: E731
    plain, recorded = [pr[False] for pr in pairs], [pr[True] for pr in pairs]
    ratios = sorted(pr[True]["ticks_per_s"] / pr[False]["ticks_per_s"] for pr in pairs)
    cpu = sorted(pr[True]["cpu_ms_per_tick"] / pr[False]["cpu_ms_per_tick"] for pr in pairs)
    print(f"\n{args.algorithm} on {args.scenario}, {args.ticks} ticks {' '.join(args.flags)}, "
          f"{args.repeat} pairs (median; range)\n")
    print("| | ticks/s | CPU ms/tick | recording |")
    print("|---|---:|---:|---:|")
    rng = lambda rows, key: f"{min(x[key] for x in rows):.0f}–{max(x[key] for x in rows):.0f}"  # noqa: E731
    print(f"| without --record | {med(plain, 'ticks_per_s'):.0f} ({rng(plain, 'ticks_per_s')}) "
          f"| {med(plain, 'cpu_ms_per_tick'):.1f} | |")
    print(f"| with --record | {med(recorded, 'ticks_per_s'):.0f} ({rng(recorded, 'ticks_per_s')}) "
          f"| {med(recorded, 'cpu_ms_per_tick'):.1f} | {med(recorded, 'bytes') / 1e3:.0f} kB |")
    print(f"\nrate with / without, per pair: median {statistics.median(ratios):.3f} "
          f"({ratios[0]:.3f}–{ratios[-1]:.3f}); CPU per tick with / without: median {statistics.median(cpu):.3f} "
          f"({cpu[0]:.3f}–{cpu[-1]:.3f})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
