"""What the screen before fusion (``defence``) costs diskf-auto on clean runs.

Two measurements, the screen on and off side by side in one process:

clean   Table II's four cells (Scenario 1 all, ring, none; Scenario 2 at
        range 120) and the held-out suite's 148 cases, seeds 0..S-1: the
        state MAE with the screen against without, and whether the estimates
        are the same bits (nothing failed the screen)
engine  CPU time of ``engine.batch.run`` on Scenario 2 and the 25-agent random
        geometric network, 8 seeds x 200 ticks, on and off taking turns, the
        best of ``--repeat`` kept, for diskf-auto and diskf-r

    .venv/bin/python benchmarks/defence_cost.py [--seeds 1] [--repeat 3] [--only clean|engine]

Prints one line per cell, then the count of cells bit-identical and beyond 2 %.
"""
from __future__ import annotations

import argparse
import dataclasses
import time

import numpy as np

from diskf_mesh.data import metrics
from diskf_mesh.data.scenario import load_scenario, simulate
from diskf_mesh.engine import batch
from diskf_mesh.studies import heldout


def clean(seeds) -> None:
    rows = [(f"Table II S1 {t}", load_scenario("quadrants").with_overrides(topology=t)) for t in ("all", "ring", "none")]
    rows.append(("Table II S2 range 120", load_scenario("dynamic")))
    rows += [(c.label, c.scenario) for c in heldout.cases()]
    same = beyond = 0
    for label, scn in rows:
        trace = simulate(scn, seeds)
        off = batch.run(trace, "diskf-auto", dataclasses.replace(scn.params, defence=False))
        on = batch.run(trace, "diskf-auto", dataclasses.replace(scn.params, defence=True))
        mo, mn = metrics.compute(trace, off)["mae_state"], metrics.compute(trace, on)["mae_state"]
        equal = bool(np.array_equal(off.x, on.x) and np.array_equal(off.P, on.P))
        rel = (mn - mo) / mo if mo else 0.0
        same += equal
        beyond += abs(rel) > 0.02
        print(f"{label:40s} off {mo:.4f} on {mn:.4f} ({100 * rel:+.2f} %) {'same bits' if equal else 'differs'}",
              flush=True)
    print(f"cells {len(rows)}: the same bits {same}, beyond 2 % {beyond}")


def engine(repeat: int) -> None:
    for name, agents in (("dynamic", None), ("random-geometric", 25)):
        scn = load_scenario(name, agents=agents)
        trace = simulate(scn, list(range(8)))
        for alg in ("diskf-auto", "diskf-r"):
            best = {False: np.inf, True: np.inf}
            for _ in range(repeat):
                for on in (False, True):
                    t0 = time.process_time()
                    batch.run(trace, alg, dataclasses.replace(scn.params, defence=on))
                    best[on] = min(best[on], time.process_time() - t0)
            print(f"{name} {alg}: off {best[False]:.2f} s, on {best[True]:.2f} s, ratio {best[True] / best[False]:.3f}")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seeds", type=int, default=1, help="seeds 0..S-1 of every clean cell (default 1)")
    p.add_argument("--repeat", type=int, default=3, help="alternated timings of the engine (default 3)")
    p.add_argument("--only", choices=("clean", "engine"), help="one of the two measurements (default: both)")
    args = p.parse_args(argv)
    if args.only != "engine":
        clean(list(range(args.seeds)))
    if args.only != "clean":
        engine(args.repeat)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
