"""Engine speed: the batched engine beside the plain DISKF oracle, the full
Table II, and a 1,000-agent random geometric network.

    python benchmarks/engine_bench.py              # the table of docs/performance.md
    python benchmarks/engine_bench.py --quick      # smaller, for a smoke run

Prints markdown tables. Rates are agent-steps (one agent, one tick) per
second of CPU time. On a shared, noisy machine only numbers measured side by
side in one run compare: engine and oracle timings are interleaved and the
best of ``--repeat`` rounds is kept for each. The large-network runs each happen in a
fresh child process, so their peak resident memory is their own.
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time
import tracemalloc

from diskf_mesh import estimators as algorithms
from diskf_mesh.data.argtypes import add_ticks
from diskf_mesh.engine import batch as engine
from diskf_mesh.studies import experiment
from diskf_mesh.engine import oracle
from diskf_mesh.data.scenario import load_scenario, simulate

TOPOLOGIES = ("all", "ring", "none")


def best_time(fn, repeat: int) -> float:
    """Shortest CPU time (this process, all threads) of ``repeat`` calls of
    fn(). CPU rather than wall time: on a shared machine wall time also counts
    the time other processes held the cores."""
    best = float("inf")
    for _ in range(repeat):
        t = time.process_time()
        fn()
        best = min(best, time.process_time() - t)
    return best


def agent_steps(traces) -> int:
    return sum(t.has.size for t in traces)


def quadrant_tables(seeds: int, scaling_seeds, steps: int, oracle_seeds: int, repeat: int) -> str:
    """Engine rates on quadrants beside the plain oracle (DISKF), measured in
    the same interleaved rounds so that both see the same machine load:

    * every algorithm on the Table II batch (3 topologies x ``seeds``);
    * DISKF by batch size (``scaling_seeds`` per topology): the engine pays a
      fixed cost per tick, so its rate, unlike the oracle's, grows with the
      batch.
    """
    scn = load_scenario("quadrants").with_overrides(steps=steps)
    batch = lambda n: [simulate(scn.with_overrides(topology=t), range(n)) for t in TOPOLOGIES]  # noqa: E731
    table2, small = batch(seeds), batch(oracle_seeds)
    scaling = {n: batch(n) for n in scaling_seeds}
    runs = {("alg", a): (table2, a) for a in algorithms.NAMES}
    runs.update({("seeds", n): (traces, "diskf") for n, traces in scaling.items()})
    t_engine = {key: float("inf") for key in runs}
    t_oracle = float("inf")
    for _ in range(repeat):
        for key, (traces, a) in runs.items():
            t_engine[key] = min(t_engine[key], best_time(lambda: engine.run_many(traces, a, scn.params), 1))
        t_oracle = min(t_oracle, best_time(lambda: [oracle.run_diskf(t, scn.params) for t in small], 1))
    o_rate = agent_steps(small) / t_oracle
    n2 = agent_steps(table2)
    lines = [
        f"Quadrants (4 agents), {len(TOPOLOGIES)} topologies x {seeds} seeds x {steps} ticks = {n2:,} agent-steps "
        f"per algorithm (engine); plain oracle: DISKF on {len(TOPOLOGIES)} x {oracle_seeds} seeds "
        f"= {agent_steps(small):,} agent-steps. Best of {repeat} interleaved rounds, CPU time.",
        "",
        "| algorithm | engine CPU (s) | engine agent-steps/s | plain oracle agent-steps/s | speed-up |",
        "|---|---:|---:|---:|---:|",
    ]
    for a in algorithms.NAMES:
        t = t_engine["alg", a]
        cells = f"{o_rate:,.0f} | {n2 / t / o_rate:.0f}x" if a == "diskf" else "(DISKF only) | -"
        lines.append(f"| {experiment.LABELS[a]} | {t:.3f} | {n2 / t:,.0f} | {cells} |")
    total = sum(t_engine["alg", a] for a in algorithms.NAMES)
    lines += [f"| all {len(algorithms.NAMES)} | {total:.3f} | {len(algorithms.NAMES) * n2 / total:,.0f} | | |", "",
              "DISKF by batch size: seeds per topology, 3 topologies stacked (12 x seeds filters per tick).", "",
              "| seeds | filters per tick | engine agent-steps/s | plain oracle agent-steps/s | speed-up |",
              "|---:|---:|---:|---:|---:|"]
    for n, traces in scaling.items():
        rate = agent_steps(traces) / t_engine["seeds", n]
        lines.append(f"| {n} | {12 * n} | {rate:,.0f} | {o_rate:,.0f} | {rate / o_rate:.0f}x |")
    return "\n".join(lines)


def large_ratio_table(agents: int, engine_steps: int, oracle_steps: int, repeat: int) -> str:
    """DISKF on the random geometric network, engine and oracle side by side
    (the oracle on fewer ticks: it needs about a millisecond per agent-step)."""
    scn = load_scenario("random-geometric", agents=agents)
    tr_engine = simulate(scn.with_overrides(steps=engine_steps), [0])
    tr_oracle = simulate(scn.with_overrides(steps=oracle_steps), [0])
    engine_t = oracle_t = float("inf")
    for _ in range(repeat):
        engine_t = min(engine_t, best_time(lambda: engine.run(tr_engine, "diskf", scn.params), 1))
        oracle_t = min(oracle_t, best_time(lambda: oracle.run_diskf(tr_oracle, scn.params), 1))
    e_rate, o_rate = tr_engine.has.size / engine_t, tr_oracle.has.size / oracle_t
    return "\n".join([
        f"Random geometric network, {agents} agents, one seed: engine {engine_steps} ticks, oracle {oracle_steps} ticks.",
        "",
        "| algorithm | engine agent-steps/s | plain oracle agent-steps/s | speed-up |",
        "|---|---:|---:|---:|",
        f"| DISKF | {e_rate:,.0f} | {o_rate:,.0f} | {e_rate / o_rate:.0f}x |",
    ])


PAPER = ("diskf", "cdrkf", "ldrkf", "kcf", "diffkf", "gdkf")  # the paper's six estimators, its Table II's columns


def table2_line(seeds: int, steps: int, repeat: int, oracle_seeds: int = 2) -> str:
    """The whole Table II of the paper's six estimators: in this process
    through ``experiment.run_experiment`` (simulation, three topologies,
    metrics), and as the one command a user types, start-up included (CPU
    of the child: ``diskf-mesh experiment --scenario quadrants --seeds S
    --estimators <the six>``), beside the plain DISKF oracle's time for the
    same agent-steps (every estimator costed as the oracle's DISKF), all
    interleaved in the same rounds, best of ``repeat``."""
    scn = load_scenario("quadrants").with_overrides(steps=steps)
    settings = experiment.settings_for(TOPOLOGIES)
    small = [simulate(scn.with_overrides(topology=t), range(oracle_seeds)) for t in TOPOLOGIES]
    command = [sys.executable, "-m", "diskf_mesh.cli.main", "experiment", "--scenario", "quadrants",
               "--seeds", str(seeds), "--estimators", ",".join(PAPER)]
    same_horizon = steps == load_scenario("quadrants").steps  # the command runs the scenario's own
    wall = cpu = child = oracle_t = float("inf")
    for _ in range(repeat):
        t, c = time.perf_counter(), time.process_time()
        experiment.run_experiment(scn, settings, list(PAPER), range(seeds), steps)
        wall, cpu = min(wall, time.perf_counter() - t), min(cpu, time.process_time() - c)
        if same_horizon:
            before = resource.getrusage(resource.RUSAGE_CHILDREN)
            subprocess.run(command, check=True, capture_output=True)
            after = resource.getrusage(resource.RUSAGE_CHILDREN)
            child = min(child, after.ru_utime - before.ru_utime + after.ru_stime - before.ru_stime)
        oracle_t = min(oracle_t, best_time(lambda: [oracle.run_diskf(tr, scn.params) for tr in small], 1))
    plain = len(PAPER) * len(TOPOLOGIES) * seeds * steps * scn.N * oracle_t / agent_steps(small)
    line = (f"Full Table II ({len(PAPER)} algorithms x {len(TOPOLOGIES)} topologies x {seeds} seeds x {steps} ticks, "
            f"simulation and metrics included): **{cpu:.2f} s CPU**, {wall:.2f} s wall (best of {repeat}); "
            f"the plain oracle would take {plain:.1f} s: {plain / cpu:.0f}x.")
    if same_horizon:
        line += (f" As one command, start-up included (`{' '.join(['diskf-mesh'] + command[3:])}`): "
                 f"**{child:.2f} s CPU**, **{plain / child:.0f}x** the plain oracle.")
    return line


def big_child(algorithm: str, agents: int, steps: int) -> dict:
    """One large run in this (fresh) process: simulate, engine, peak memory."""
    t, c = time.perf_counter(), time.process_time()
    scn = load_scenario("random-geometric", agents=agents).with_overrides(steps=steps)
    trace = simulate(scn, [0])
    t_sim, c_sim = time.perf_counter() - t, time.process_time() - c
    t, c = time.perf_counter(), time.process_time()
    engine.run(trace, algorithm, scn.params)
    t_run, c_run = time.perf_counter() - t, time.process_time() - c
    tracemalloc.start()  # a second, traced run for the peak of numpy allocations
    engine.run(trace, algorithm, scn.params)
    traced_peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    links = trace.links[0, 0]
    return {
        "sim": t_sim, "run": t_run, "cpu": c_sim + c_run, "run_cpu": c_run, "maxrss": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024,
        "traced_peak": traced_peak, "degree": float(links.sum(axis=1).mean()), "max_degree": int(links.sum(axis=1).max()),
        "has": float(trace.has.mean()),
    }


def big_table(names, agents: int, steps: int) -> str:
    lines = [
        f"Random geometric network (`--scenario random-geometric --agents {agents}`), {steps} ticks, one seed; "
        "each row a fresh process; simulate and engine columns are wall time, agent-steps/s is per engine CPU second.",
        "",
        "| algorithm | simulate (s) | engine (s) | total wall (s) | total CPU (s) | agent-steps/s | peak RSS (MiB) "
        "| peak numpy, traced (MiB) |",
        "|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    info = None
    for a in names:
        cmd = [sys.executable, os.path.abspath(__file__), "--child", a, "--agents", str(agents), "--ticks", str(steps)]
        info = json.loads(subprocess.run(cmd, check=True, capture_output=True, text=True).stdout)
        total = info["sim"] + info["run"]
        lines.append(f"| {experiment.LABELS[a]} | {info['sim']:.2f} | {info['run']:.2f} | {total:.2f} "
                     f"| {info['cpu']:.2f} "
                     f"| {agents * steps / info['run_cpu']:,.0f} | {info['maxrss'] / 2**20:.0f} "
                     f"| {info['traced_peak'] / 2**20:.0f} |")
    if info is not None:
        lines += ["", f"Mean neighbourhood {info['degree']:.1f} agents (max {info['max_degree']}, self included); "
                      f"{100 * info['has']:.1f}% of agent-ticks have a measurement."]
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=20)
    add_ticks(ap, type=int, default=200, help="ticks per run (default 200)")
    ap.add_argument("--oracle-seeds", type=int, default=2, help="seeds per topology for the (slow) plain oracle")
    ap.add_argument("--repeat", type=int, default=5, help="rounds; the best of them is reported")
    ap.add_argument("--agents", type=int, default=1000)
    ap.add_argument("--ratio-steps", type=int, default=20, help="engine ticks of the large-network speed-up row")
    ap.add_argument("--big", default="all", help="algorithms for the large network: 'all', a list, or 'none'")
    ap.add_argument("--quick", action="store_true", help="5 seeds, 1 round, 300 agents")
    ap.add_argument("--child", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child:
        print(json.dumps(big_child(args.child, args.agents, args.ticks)))
        return 0
    if args.quick:
        args.seeds, args.repeat, args.agents = 5, 1, 300
    print(f"numpy engine benchmark, {os.cpu_count()} CPUs, python {sys.version.split()[0]}\n")
    print(quadrant_tables(args.seeds, sorted({1, 5 * args.seeds}), args.ticks, args.oracle_seeds, args.repeat))
    print()
    print(large_ratio_table(args.agents, args.ratio_steps, 2, args.repeat))
    print()
    print(table2_line(args.seeds, args.ticks, args.repeat))
    if args.big != "none":
        print()
        print(big_table(algorithms.parse_list(args.big), args.agents, args.ticks))
    return 0


if __name__ == "__main__":
    sys.exit(main())
