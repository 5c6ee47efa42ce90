"""Mesh benchmark: ``diskf-mesh up`` with 4, 9, 25 and 50 agent processes in
lockstep. Prints markdown tables; not a test.

    python benchmarks/mesh_bench.py [--agents 4,9,25,50] [--ticks 200]
                                    [--scenario random-geometric] [--algorithm diskf]
                                    [--profile] [--repeat R]

Columns of the first table:
    first tick   seconds from starting ``up`` to the world opening tick 1
                 (process start, imports, zenoh sessions, discovery)
    ticks/s      ticks per second from tick 1 to the last report (with
                 --repeat: the median run, and the lowest and highest)
    CPU ms/tick  CPU time of all processes (world, agents, launcher) over
                 the whole run (start-up included), per tick
    msg bytes    size of one agent message on the wire (n = 2, m = 1)
    fused/tick   neighbour messages an agent fused per tick, on average
    heard/tick   neighbour messages that reached an agent process per tick
                 (fused or not: out of range, late), on average

With ``--profile`` every process measures where its ticks go
(``up --profile``, ``diskf_mesh.mesh.protocol.profile``) and the benchmark adds:

* how the tick rate falls as agents are added: the CPU all processes spend
  per tick once ticking (start-up excluded), split into agents and world,
  and the rate two cores could sustain at that CPU per tick
  (2000 ms / CPU ms per tick): where the measured rate is close to it, the
  run is bound by CPU, and the per-phase tables say whose;
* per agent count, one per-phase table for an average agent and one for
  the world (wall and CPU ms per tick: waiting, decode, guard, local, fuse,
  encode, publish, other; and the process CPU outside them: zenoh's own
  threads and the kernel).

``--repeat R`` runs every agent count R times, interleaved, and reports the
run with the median rate: the machine is shared and noisy, so compare
figures of one invocation, not across invocations. ``--baseline DIR`` runs
the same from another checkout (e.g. ``git archive REV | tar -x -C DIR``)
back to back with each run of this one, the two taking turns at going
first, and prints both rates, their ratio and the ratio by which went
first. ``--baseline`` may be given more than once (e.g. the commits between
two trees, to find which one changed the rate): every repeat runs this tree
and each baseline in turn, in reverse order on every other repeat, and the
side-by-side table has one row per baseline.
"""
from __future__ import annotations

import argparse
import glob
import json
import re
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from diskf_mesh.mesh.wire import codec as wire
from diskf_mesh.mesh.protocol import profile
from diskf_mesh.core.messages import Message

CORES = 2


def message_bytes(n: int = 2, m: int = 1) -> int:
    P = np.eye(n)[None, None]
    msg = Message(np.zeros((1, 1, n)), P, np.zeros((1, 1, n)), P, np.zeros((1, 1, m)), np.eye(m)[None, None],
                  np.array([[True]]))
    return len(wire.encode("a1b2c3d4", 50, 200, msg))


def spread(runs: list) -> str:
    """" (min–max)" of the ticks/s of repeated runs, "" for one run."""
    rates = sorted(r["ticks_per_s"] for r in runs if "error" not in r)
    return f" ({rates[0]:.0f}–{rates[-1]:.0f})" if len(rates) > 1 else ""


def cpu_seconds() -> float:
    ru = resource.getrusage(resource.RUSAGE_CHILDREN)
    return ru.ru_utime + ru.ru_stime


def run_one(scenario: str, agents: int | None, ticks: int, algorithm: str, workdir: Path,
            with_profile: bool = False, tree: Path | None = None, insecure: bool = False) -> dict:
    """One ``up`` run; ``tree``: the checkout to run it from (default: this one);
    ``insecure``: ``up --insecure`` (default: TLS and access control, as up runs)."""
    tag = f"{agents}-{time.monotonic_ns()}"
    est, res, prof = workdir / f"est-{tag}.json", workdir / f"res-{tag}.json", workdir / f"prof-{tag}"
    cmd = [sys.executable, "-m", "sim.launcher", "--scenario", scenario, "--ticks", str(ticks),
           "--algorithm", algorithm, "--estimates", str(est), "--json", str(res), "--quiet",
           "--logs", str(workdir / f"logs-{tag}"), "--startup-timeout", "120"]
    if agents is not None:
        cmd += ["--agents", str(agents)]
    if with_profile:
        cmd += ["--profile", str(prof)]
    if insecure:
        cmd.append("--insecure")
    cpu0, t0 = cpu_seconds(), time.monotonic()
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=1800, cwd=tree)
    wall, cpu = time.monotonic() - t0, cpu_seconds() - cpu0
    if done.returncode != 0:
        return {"agents": agents, "error": (done.stderr.strip().splitlines() or ["?"])[-1]}
    doc = json.loads(est.read_text())
    first = re.search(r"first tick after ([0-9.]+) s", done.stdout)
    counters = list(doc["agent_counters"].values())
    row = {
        "agents": len(doc["ids"]),
        "ticks": ticks,
        "first_tick_s": float(first.group(1)) if first else float("nan"),
        "ticks_per_s": ticks / doc["ticks_s"],
        "cpu_ms_per_tick": 1000.0 * cpu / ticks,
        "wall_s": wall,
        "fused_per_tick": float(np.mean([c["fused"] for c in counters])) / ticks,
        "heard_per_tick": float(np.mean([c["sent"] + c["out_of_range"] for c in counters])) / ticks,
        "complete": bool(np.array(doc["reported"]).all()),
    }
    if with_profile:
        agents_p = [json.loads(Path(f).read_text()) for f in sorted(glob.glob(str(prof / "agent-*.json")))]
        world_p = json.loads((prof / "world.json").read_text())
        row["profile"] = {"agent": profile.merge(agents_p), "world": profile.merge([world_p])}
        agent_cpu = sum(1e3 * s["process_cpu_s"] / max(s["ticks"], 1) for s in agents_p)
        world_cpu = 1e3 * world_p["process_cpu_s"] / max(world_p["ticks"], 1)
        row["ticking_cpu_ms_per_tick"] = agent_cpu + world_cpu
        row["world_cpu_ms_per_tick"] = world_cpu
        row["agent_cpu_ms_per_tick"] = agent_cpu / max(len(agents_p), 1)
        row["cpu_bound_ticks_per_s"] = CORES * 1000.0 / (agent_cpu + world_cpu)
    return row


def median_run(runs: list) -> dict:
    """The run with the median rate (the last failure if none completed)."""
    ok = sorted((r for r in runs if "error" not in r), key=lambda r: r["ticks_per_s"])
    return ok[len(ok) // 2] if ok else runs[-1]


def bound_note(r: dict) -> str:
    """What bounds the rate of one profiled run, in words."""
    share = r["ticks_per_s"] / r["cpu_bound_ticks_per_s"]
    a = r["profile"]["agent"]
    zenoh = a["process_cpu_ms_per_tick"] - a["python_cpu_ms_per_tick"]
    math_ms = a["phases"]["local"]["cpu_ms_per_tick"] + a["phases"]["fuse"]["cpu_ms_per_tick"]
    what = ("CPU: the processes' work per tick fills both cores" if share > 0.75 else
            "latency more than CPU: the cores idle while a tick waits on its slowest path")
    return (f"{r['agents']} agents: {r['ticks_per_s']:.0f} ticks/s = {100 * share:.0f} % of the {CORES}-core CPU bound "
            f"({r['cpu_bound_ticks_per_s']:.0f}/s at {r['ticking_cpu_ms_per_tick']:.1f} CPU ms/tick); {what}. "
            f"An agent spends {a['process_cpu_ms_per_tick']:.2f} CPU ms/tick: math {math_ms:.2f}, the rest of "
            f"its Python {a['python_cpu_ms_per_tick'] - math_ms:.2f}, zenoh and the kernel {zenoh:.2f}; "
            f"it hears {r['heard_per_tick']:.1f} neighbour messages a tick and fuses {r['fused_per_tick']:.1f}.")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--agents", default="4,9,25,50",
                   help="comma list of agent counts, or 'scenario' for a listed scenario's own agents")
    p.add_argument("--ticks", type=int, default=200)
    p.add_argument("--scenario", default="random-geometric",
                   help="a generated scenario (takes --agents), default random-geometric")
    p.add_argument("--algorithm", default="diskf")
    p.add_argument("--profile", action="store_true",
                   help="also measure where each tick's time goes, per phase, and what bounds the rate")
    p.add_argument("--repeat", type=int, default=1, help="runs per agent count, the median rate is kept")
    p.add_argument("--baseline", metavar="DIR", type=Path, action="append", default=[],
                   help="another checkout to run the same from, interleaved, for a side-by-side ratio (repeatable)")
    p.add_argument("--insecure", action="store_true",
                   help="every tree runs up --insecure: no TLS, no access control")
    p.add_argument("--json", help="also write the rows as JSON")
    args = p.parse_args(argv)
    size = message_bytes()
    counts = [None] if args.agents == "scenario" else [int(a) for a in args.agents.split(",")]
    runs = {n: [] for n in counts}
    base_runs = {b: {n: [] for n in counts} for b in args.baseline}
    trees = [None] + args.baseline  # None: this tree
    with tempfile.TemporaryDirectory(prefix="mesh-bench-") as tmp:
        for rep in range(max(args.repeat, 1)):
            for n in counts:
                # the trees take turns at going first (ABBA): none always runs on another's heels
                for tree in (trees if rep % 2 == 0 else trees[::-1]):
                    if tree is None:
                        row = run_one(args.scenario, n, args.ticks, args.algorithm, Path(tmp), args.profile,
                                      insecure=args.insecure)
                        row["message_bytes"] = size
                        runs[n].append(row)
                        print(json.dumps({k: v for k, v in row.items() if k != "profile"}), file=sys.stderr,
                              flush=True)
                    else:
                        base = run_one(args.scenario, n, args.ticks, args.algorithm, Path(tmp), tree=tree,
                                       insecure=args.insecure)
                        base_runs[tree][n].append(base)
                        print(f"baseline {tree} " + json.dumps(base), file=sys.stderr, flush=True)
    rows = [{**median_run(runs[n]), "n": n} for n in counts]
    print(f"\n{args.algorithm} on {args.scenario}, {args.ticks} ticks, one process per agent, zenoh on loopback"
          + (f", median of {args.repeat} runs" if args.repeat > 1 else "") + "\n")
    print("| agents | first tick (s) | ticks/s | CPU ms/tick | msg bytes | fused/tick | heard/tick | complete |")
    print("|---:|---:|---:|---:|---:|---:|---:|:---:|")
    for r in rows:
        if "error" in r:
            print(f"| {r['agents']} | failed: {r['error']} | | | | | | |")
            continue
        print(f"| {r['agents']} | {r['first_tick_s']:.2f} | {r['ticks_per_s']:.0f}{spread(runs[r['n']])} "
              f"| {r['cpu_ms_per_tick']:.1f} "
              f"| {r['message_bytes']} | {r['fused_per_tick']:.1f} | {r['heard_per_tick']:.1f} "
              f"| {'yes' if r['complete'] else 'no'} |")
    if args.baseline:
        print(f"\nSide by side with {', '.join(map(str, args.baseline))} (each repeat runs every tree back to back, "
              "the trees taking turns at going first"
              + ("; only this tree runs with --profile, so its rate pays the profiler's cost and the ratio "
                 "is low: compare rates without --profile" if args.profile else "") + ")\n")
        print("| agents | baseline | baseline ticks/s | ticks/s | ratio of medians | ratio per pair: median (range) "
              "| baseline CPU ms/tick | CPU ms/tick |")
        print("|---:|---|---:|---:|---:|---:|---:|---:|")
        order_notes = []
        for n, r in zip(counts, rows):
            for tree in args.baseline:
                b = median_run(base_runs[tree][n])
                if "error" in r or "error" in b:
                    print(f"| {r['agents']} | {tree} | {b.get('error', '')} | {r.get('error', '')} | | | | |")
                    continue
                ratios = [x["ticks_per_s"] / y["ticks_per_s"] if "error" not in x and "error" not in y else None
                          for x, y in zip(runs[n], base_runs[tree][n])]
                pairs = sorted(q for q in ratios if q is not None)
                if len(args.baseline) == 1:
                    for first, half in (("this tree", ratios[0::2]), ("the baseline", ratios[1::2])):
                        half = [q for q in half if q is not None]
                        if half:
                            order_notes.append(f"{r['agents']} agents, {first} first: median ratio "
                                               f"{statistics.median(half):.2f} over {len(half)} pairs")
                per_pair = (f"{statistics.median(pairs):.2f} ({pairs[0]:.2f}–{pairs[-1]:.2f})" if pairs
                            else "no pair where both completed")
                print(f"| {r['agents']} | {tree} | {b['ticks_per_s']:.0f}{spread(base_runs[tree][n])} "
                      f"| {r['ticks_per_s']:.0f}{spread(runs[n])} | {r['ticks_per_s'] / b['ticks_per_s']:.2f} "
                      f"| {per_pair} "
                      f"| {b['cpu_ms_per_tick']:.1f} | {r['cpu_ms_per_tick']:.1f} |")
        if order_notes:
            print()
            for note in order_notes:
                print(f"- {note}")
    profiled = [r for r in rows if "profile" in r]
    if profiled:
        print("\nOnce ticking (start-up excluded): CPU per tick of all processes, and the rate two cores could "
              "sustain at that CPU\n")
        print("| agents | ticks/s | CPU ms/tick | agent CPU ms/tick | world CPU ms/tick | 2-core bound ticks/s "
              "| share of bound |")
        print("|---:|---:|---:|---:|---:|---:|---:|")
        for r in profiled:
            print(f"| {r['agents']} | {r['ticks_per_s']:.0f} | {r['ticking_cpu_ms_per_tick']:.1f} "
                  f"| {r['agent_cpu_ms_per_tick']:.2f} | {r['world_cpu_ms_per_tick']:.2f} "
                  f"| {r['cpu_bound_ticks_per_s']:.0f} | {100 * r['ticks_per_s'] / r['cpu_bound_ticks_per_s']:.0f} % |")
        print()
        for r in profiled:
            print("- " + bound_note(r))
        for r in profiled:
            print()
            print(profile.format_table(r["profile"]["agent"], f"{r['agents']} agents: one agent (mean of "
                                                                f"{r['profile']['agent']['processes']})"))
            print()
            print(profile.format_table(r["profile"]["world"], f"{r['agents']} agents: the world"))
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1))
    failed = [f"{n} agents" for n, r in zip(counts, rows) if "error" in r]
    failed += [f"{n} agents from {tree}" for tree in args.baseline for n in counts
               if "error" in median_run(base_runs[tree][n])]
    if failed:
        print(f"mesh_bench: every run failed at {', '.join(failed)} (the tables say why)", file=sys.stderr)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
