"""The simulated network's cost next to the engine's on the same run.

For each agent count, runs, as child processes and alternating them, the
engine (``diskf-mesh experiment --scenario S --agents N --steps K --seeds 1
--estimators E``) and the simulated network (``diskf-mesh up --network
simulated`` with the same scenario, agents, ticks, seed and estimator), and
prints one markdown table: each one's CPU time (user + system of the child,
start-up included), the ratio, the simulated run's peak resident memory and
its status. Not a test; the machine may be shared, so compare the ratios of
one invocation.

    python benchmarks/simnet_bench.py [--agents 100,1000] [--ticks 20]
                                      [--scenario random-geometric] [--estimator diskf-auto]
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path


def child(argv) -> tuple:
    """(CPU seconds, peak RSS in MB, exit status) of ``diskf-mesh argv``."""
    p = subprocess.Popen([sys.executable, "-m", "diskf_mesh.cli.main", *argv], stdout=subprocess.DEVNULL,
                         stderr=subprocess.PIPE, text=True)
    _, status, usage = os.wait4(p.pid, 0)
    p.returncode = os.waitstatus_to_exitcode(status)
    err = p.stderr.read()
    p.stderr.close()
    if p.returncode not in (0,):
        sys.stderr.write(err[-2000:])
    return usage.ru_utime + usage.ru_stime, usage.ru_maxrss / 1024, p.returncode


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--agents", default="100,1000")
    ap.add_argument("--ticks", type=int, default=20)
    ap.add_argument("--scenario", default="random-geometric")
    ap.add_argument("--estimator", default="diskf-auto")
    args = ap.parse_args()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for n in [int(a) for a in args.agents.split(",")]:
            common = ["--scenario", args.scenario, "--agents", str(n)]
            engine = child(["experiment", *common, "--steps", str(args.ticks), "--seeds", "1", "--estimators",
                            args.estimator, "--quiet"])
            out = Path(tmp) / f"up-{n}.json"
            sim = child(["up", "--network", "simulated", *common, "--ticks", str(args.ticks), "--estimator",
                         args.estimator, "--quiet", "--json", str(out)])
            status = "failed"
            if out.exists():
                status = next(iter(json.loads(out.read_text())[args.estimator].values()))["status"]
            rows.append((n, engine, sim, status))
            print(f"{n} agents: engine {engine[0]:.1f} s, simulated {sim[0]:.1f} s ({sim[0] / engine[0]:.1f}x), "
                  f"{sim[1]:.0f} MB, {status}", file=sys.stderr, flush=True)
    print(f"| agents x ticks | engine CPU | simulated network CPU | ratio | simulated peak RSS | status |")
    print("|---|---|---|---|---|---|")
    for n, engine, sim, status in rows:
        print(f"| {n:,} x {args.ticks} | {engine[0]:.1f} s | {sim[0]:.1f} s | {sim[0] / engine[0]:.1f}x | "
              f"{sim[1]:,.0f} MB | {status} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
