"""What ``up --live`` costs when nobody watches: ticks/s of ``up`` and of
``up --live`` with no viewer connected, run in turns in one invocation.

    python benchmarks/live_cost.py [--ticks 300] [--repeat 5] [--scenario dynamic]

The rate is the world's own (``ticks_s`` of ``--estimates``: tick 1 to the
last report), so start-up is not in it. Prints every run and the medians.
"""
from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from sim.launcher import free_port  # noqa: E402


def one(tmp: Path, name: str, ticks: int, scenario: str, live: bool) -> float:
    est = tmp / f"{name}.json"
    cmd = [sys.executable, "-m", "sim.launcher", "--scenario", scenario, "--algorithm", "diskf", "--ticks", str(ticks), "--quiet",
           "--estimates", str(est), "--json", str(tmp / f"{name}-res.json"), "--logs", str(tmp / f"{name}-logs"),
           "--startup-timeout", "120"]
    if live:
        cmd += ["--live", str(free_port())]
    subprocess.run(cmd, check=True, capture_output=True, cwd=ROOT, timeout=600)
    doc = json.loads(est.read_text())
    return ticks / doc["ticks_s"]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--ticks", type=int, default=300)
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--scenario", default="dynamic")
    args = ap.parse_args()
    rates = {"up": [], "up --live": []}
    with tempfile.TemporaryDirectory(prefix="live-cost-") as d:
        for r in range(args.repeat):
            for live in (False, True) if r % 2 == 0 else (True, False):  # alternate which goes first
                name = "up --live" if live else "up"
                rate = one(Path(d), f"{r}-{int(live)}", args.ticks, args.scenario, live)
                rates[name].append(rate)
                print(f"run {r + 1}: {name:10s} {rate:7.1f} ticks/s", flush=True)
    a, b = statistics.median(rates["up"]), statistics.median(rates["up --live"])
    print(f"median of {args.repeat}: up {a:.1f} ticks/s, up --live (no viewer) {b:.1f} ticks/s, ratio {b / a:.3f}")


if __name__ == "__main__":
    main()
