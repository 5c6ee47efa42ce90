"""Cost per agent-tick of diskf-auto against diskf and diskf-r, side by side.

Three measurements, in CPU time (this process), each repeated with the
estimators taking turns and the best kept (the least disturbed by other
load):

engine S1  the batched engine (``engine.batch.run``) on Scenario 1,
           all-to-all, 20 seeds x 200 ticks x 4 agents
engine S2  the same on Scenario 2 at range 120, 20 seeds x 200 ticks x 9 agents
check      the engine on one seed of Scenario 2 (9 agents, 200 ticks), tick by tick
           (``engine.batch.Stepper``, a batch of 9): what the mesh's world replays
           each tick to check the agents' reports (``engine.verify.Online``)
agent      one agent as an agent process runs it (``mesh.protocol.estimator.lockstep``:
           every agent of Scenario 2 a batch of one, local + fuse), 100 ticks
2 channels the engine on two input channels of different kinds (the held-out case
           "m=2 all, step | sine fast": G = I, all-to-all, 20 seeds x 200 ticks x 4
           agents), where ``diskf-auto`` runs a bank per channel; a last line gives
           it with one bank for both channels (``[estimator.auto] per_channel = false``)

Three last lines give ``diskf-auto`` with ``[estimator.auto] noise_level = 10``
(three more filters, ``input_models.at_noise_level``), with
``evidence_dof = 4`` (a Student-t's evidence) and with ``noise_span = 10``
(the noise weighed at three levels, ``input_models.level_posterior``) on
engine S1, engine S2 and one agent, against ``diskf-auto`` without them.

    .venv/bin/python benchmarks/auto_cost.py [--repeat 3]

Prints microseconds per (seed, agent, tick) and the ratio to diskf. The
ratios are what carries over between machines; absolute times depend on the
machine and its load. Nothing is started per run: no start-up to subtract.
"""
from __future__ import annotations

import argparse
import time

from dataclasses import replace

from diskf_mesh.core.model import AutoOptions
from diskf_mesh.data.scenario import load_scenario, simulate
from diskf_mesh.engine import batch as engine
from diskf_mesh.mesh.protocol.estimator import lockstep
from diskf_mesh.studies import heldout

NAMES = ("diskf", "diskf-r", "diskf-auto")


def cpu(fn) -> float:
    t = time.process_time()
    fn()
    return time.process_time() - t


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeat", type=int, default=3)
    a = ap.parse_args(argv)
    s1 = load_scenario("quadrants")
    s2 = load_scenario("dynamic").with_overrides(comm_range=120)
    tr1, tr2 = simulate(s1, range(20)), simulate(s2, range(20))
    s3 = load_scenario("dynamic").with_overrides(steps=100)
    tr3 = simulate(s3, [0])
    s4 = load_scenario("dynamic")
    tr4 = simulate(s4, [0])
    s5, tr5 = next(c for c in heldout.selected(None) if c.label == "m=2 all, step | sine fast").simulate(range(20), None)
    one_bank = replace(s5.params, auto=AutoOptions(per_channel=False))
    # diskf-auto with one of its opt-in settings, on engine S1, engine S2 and one agent
    variants = {"noise_level = 10": {"noise_level": 10.0}, "evidence_dof = 4": {"evidence_dof": 4.0},
                "noise_span = 10": {"noise_span": 10.0}}

    def with_variant(fields):
        v1, v2, v3 = (s.with_overrides(params=s.params.with_setting("auto", **fields)) for s in (s1, s2, s3))
        return {"engine S1": lambda: engine.run(tr1, "diskf-auto", v1.params),
                "engine S2": lambda: engine.run(tr2, "diskf-auto", v2.params),
                "agent": lambda: sum(1 for _ in lockstep(v3, "diskf-auto", tr3))}

    variant_runs = {label: with_variant(fields) for label, fields in variants.items()}
    runs = {
        "engine S1": (lambda name: engine.run(tr1, name, s1.params), tr1.has.size),
        "engine S2": (lambda name: engine.run(tr2, name, s2.params), tr2.has.size),
        "check": (lambda name: engine.run(tr4, name, s4.params), tr4.has.size),
        "agent": (lambda name: sum(1 for _ in lockstep(s3, name, tr3)), tr3.has.size),
        "2 channels": (lambda name: engine.run(tr5, name, s5.params), tr5.has.size),
    }
    best = {}
    for _ in range(a.repeat):
        for what, (run, steps) in runs.items():
            for name in NAMES:
                best[what, name] = min(best.get((what, name), float("inf")), cpu(lambda: run(name)) / steps)
        shared = cpu(lambda: engine.run(tr5, "diskf-auto", one_bank)) / tr5.has.size
        best["one bank"] = min(best.get("one bank", float("inf")), shared)
        for label, level in variant_runs.items():
            for what, run in level.items():
                best[label, what] = min(best.get((label, what), float("inf")), cpu(run) / runs[what][1])
    head = "".join(f" {what + ' us':>14} {'x diskf':>8}" for what in runs)
    print(f"{'estimator':<12}{head}")
    for name in NAMES:
        cells = "".join(f" {1e6 * best[w, name]:>14.2f} {best[w, name] / best[w, 'diskf']:>8.1f}" for w in runs)
        print(f"{name:<12}{cells}")
    print(f"2 channels, diskf-auto with one bank: {1e6 * best['one bank']:.2f} us, "
          f"{best['one bank'] / best['2 channels', 'diskf']:.1f} x diskf")
    for label, level in variant_runs.items():
        print(f"diskf-auto with {label}: " + ", ".join(
            f"{what} {1e6 * best[label, what]:.2f} us ({best[label, what] / best[what, 'diskf']:.1f} x diskf, "
            f"{best[label, what] / best[what, 'diskf-auto']:.2f} x diskf-auto)" for what in level))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
