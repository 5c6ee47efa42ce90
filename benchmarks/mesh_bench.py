"""Mesh benchmark: ``diskf-mesh up`` with 4, 9, 25 and 50 agent processes in
lockstep. Prints a markdown table; not a test.

    python benchmarks/mesh_bench.py [--agents 4,9,25,50] [--ticks 200]
                                    [--scenario random-geometric] [--algorithm diskf]

Columns:
    first tick   seconds from starting ``up`` to the world opening tick 1
                 (process start, imports, zenoh sessions, discovery)
    ticks/s      ticks per second from tick 1 to the last report
    CPU ms/tick  CPU time of all processes (world, agents, launcher) over
                 the whole run, per tick: what bounds ticks/s on a loaded
                 machine (2 cores give at most 2000 CPU ms per second)
    msg bytes    size of one agent message on the wire (n = 2, m = 1)
    fused/tick   neighbour messages an agent fused per tick, on average

Other work on the machine slows every figure but the message size; run it
on an idle machine.
"""
from __future__ import annotations

import argparse
import json
import re
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from diskf_mesh import wire
from diskf_mesh.messages import Message


def message_bytes(n: int = 2, m: int = 1) -> int:
    P = np.eye(n)[None, None]
    msg = Message(np.zeros((1, 1, n)), P, np.zeros((1, 1, n)), P, np.zeros((1, 1, m)), np.eye(m)[None, None],
                  np.array([[True]]))
    return len(wire.encode("a1b2c3d4", 50, 200, msg))


def cpu_seconds() -> float:
    ru = resource.getrusage(resource.RUSAGE_CHILDREN)
    return ru.ru_utime + ru.ru_stime


def run_one(scenario: str, agents: int | None, ticks: int, algorithm: str, workdir: Path) -> dict:
    est, res = workdir / f"est-{agents}.json", workdir / f"res-{agents}.json"
    cmd = [sys.executable, "-m", "sim.launcher", "--scenario", scenario, "--ticks", str(ticks),
           "--algorithm", algorithm, "--estimates", str(est), "--json", str(res), "--quiet",
           "--logs", str(workdir / f"logs-{agents}"), "--startup-timeout", "120"]
    if agents is not None:
        cmd += ["--agents", str(agents)]
    cpu0, t0 = cpu_seconds(), time.monotonic()
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=1800)
    wall, cpu = time.monotonic() - t0, cpu_seconds() - cpu0
    if done.returncode != 0:
        return {"agents": agents, "error": (done.stderr.strip().splitlines() or ["?"])[-1]}
    doc = json.loads(est.read_text())
    first = re.search(r"first tick after ([0-9.]+) s", done.stdout)
    counters = doc["agent_counters"].values()
    return {
        "agents": len(doc["ids"]),
        "ticks": ticks,
        "first_tick_s": float(first.group(1)) if first else float("nan"),
        "ticks_per_s": ticks / doc["ticks_s"],
        "cpu_ms_per_tick": 1000.0 * cpu / ticks,
        "wall_s": wall,
        "fused_per_tick": float(np.mean([c["fused"] for c in counters])) / ticks,
        "complete": bool(np.array(doc["reported"]).all()),
    }


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--agents", default="4,9,25,50",
                   help="comma list of agent counts, or 'scenario' for a listed scenario's own agents")
    p.add_argument("--ticks", type=int, default=200)
    p.add_argument("--scenario", default="random-geometric",
                   help="a generated scenario (takes --agents), default random-geometric")
    p.add_argument("--algorithm", default="diskf")
    p.add_argument("--json", help="also write the rows as JSON")
    args = p.parse_args(argv)
    size = message_bytes()
    rows = []
    with tempfile.TemporaryDirectory(prefix="mesh-bench-") as tmp:
        counts = [None] if args.agents == "scenario" else [int(a) for a in args.agents.split(",")]
        for n in counts:
            row = run_one(args.scenario, n, args.ticks, args.algorithm, Path(tmp))
            row["message_bytes"] = size
            rows.append(row)
            print(json.dumps(row), file=sys.stderr, flush=True)
    print(f"\n{args.algorithm} on {args.scenario}, {args.ticks} ticks, one process per agent, zenoh on loopback\n")
    print("| agents | first tick (s) | ticks/s | CPU ms/tick | msg bytes | fused/tick | complete |")
    print("|---:|---:|---:|---:|---:|---:|:---:|")
    for r in rows:
        if "error" in r:
            print(f"| {r['agents']} | failed: {r['error']} | | | | | |")
            continue
        print(f"| {r['agents']} | {r['first_tick_s']:.2f} | {r['ticks_per_s']:.0f} | {r['cpu_ms_per_tick']:.1f} "
              f"| {r['message_bytes']} | {r['fused_per_tick']:.1f} | {'yes' if r['complete'] else 'no'} |")
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
