"""Cost per agent-tick of diskf-auto against diskf and diskf-r, side by side.

Two measurements, each repeated and the best kept (the least disturbed by
other load):

engine   the batched engine (``engine.batch.run``) on Scenario 1, all-to-all,
         20 seeds x 200 ticks x 4 agents: seconds per (seed, agent, tick)
agent    one agent as an agent process runs it (``mesh.protocol.estimator.lockstep``:
         every agent of Scenario 2 a batch of one, local + fuse), 100 ticks:
         seconds per agent-tick

    .venv/bin/python benchmarks/auto_cost.py [--repeat 3]

Prints one row per estimator with the ratio to diskf. The ratios are what
carries over between machines; absolute times depend on the machine and
its load.
"""
from __future__ import annotations

import argparse
import time

from diskf_mesh.data.scenario import load_scenario, simulate
from diskf_mesh.engine import batch as engine
from diskf_mesh.mesh.protocol.estimator import lockstep

NAMES = ("diskf", "diskf-r", "diskf-auto")


def best_of(fn, repeat: int) -> float:
    out = []
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        out.append(time.perf_counter() - t)
    return min(out)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeat", type=int, default=3)
    a = ap.parse_args(argv)
    s1 = load_scenario("quadrants")
    tr1 = simulate(s1, range(20))
    B, K, N = tr1.has.shape
    s2 = load_scenario("dynamic").with_overrides(steps=100)
    tr2 = simulate(s2, [0])
    rows = {}
    for name in NAMES:
        t_engine = best_of(lambda: engine.run(tr1, name, s1.params), a.repeat) / (B * K * N)
        t_agent = best_of(lambda: sum(1 for _ in lockstep(s2, name, tr2)), a.repeat) / (100 * s2.N)
        rows[name] = (t_engine, t_agent)
    base = rows["diskf"]
    print(f"{'estimator':<12} {'engine us/agent-tick':>22} {'x diskf':>8} {'agent us/agent-tick':>21} {'x diskf':>8}")
    for name, (te, ta) in rows.items():
        print(f"{name:<12} {1e6 * te:>22.2f} {te / base[0]:>8.1f} {1e6 * ta:>21.1f} {ta / base[1]:>8.1f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
