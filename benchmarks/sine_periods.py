"""Sines of periods the held-out suite does not hold: does ``diskf-auto``'s
bank of oscillating models (periods 4 to 32 ticks in quarter octaves) hold
where the period falls between its models, or beyond them? Prints a table;
not a test.

    python benchmarks/sine_periods.py [--seeds 20] [--first-seed 0] [--periods 6,7,13,17,25,40]

Every period as a sine of amplitude 10 on Scenario 1 (all-to-all, ring,
isolated) and Scenario 2 at range 120; every estimator through the engine,
measured as the held-out suite measures (``heldout.case_row``), and
``diskf-auto`` once more with ``[estimator.auto] oscillating = false``.
A row: ``diskf-auto``'s state MAE, the same without its oscillating
models, the case's best estimator and its MAE, the ratio, and
``diskf-auto``'s mean NEES; the last lines count the cases within 10 % of
the best and the NEES inside the chi-square band of the suite.
"""
from __future__ import annotations

import argparse

from diskf_mesh import estimators as algorithms
from diskf_mesh.data.scenario import load_scenario, simulate
from diskf_mesh.studies import heldout
from diskf_mesh.studies.suite import observed

NETWORKS = (("quadrants", "S1", "all", None), ("quadrants", "S1", "ring", None), ("quadrants", "S1", "none", None),
            ("dynamic", "S2", "range", 120.0))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", type=int, default=20)
    ap.add_argument("--first-seed", type=int, default=0)
    ap.add_argument("--periods", default="6,7,13,17,25,40", help="periods in ticks, comma-separated")
    a = ap.parse_args(argv)
    periods = [float(p) for p in a.periods.split(",")]
    seeds = range(a.first_seed, a.first_seed + a.seeds)
    band = heldout.chi2_band(2, a.seeds)
    print(f"sines of amplitude 10, seeds {seeds.start}..{seeds.stop - 1}; NEES band [{band[0]:.2f}, {band[1]:.2f}]\n")
    print("| case | period | diskf-auto | without oscillating models | best | best MAE | ratio | NEES |")
    print("|---|---:|---:|---:|---|---:|---:|---:|")
    within = in_band = total = 0
    for scenario, tag, topology, comm_range in NETWORKS:
        base = load_scenario(scenario)
        for period in periods:
            scn = heldout._topo(heldout._with_input(base, dict(kind="sine", amplitude=10.0, period=period)),
                                topology, comm_range)
            tr = simulate(scn, seeds)
            seen = observed(tr)
            rows = {name: heldout.case_row(tr, name, scn.params, seen) for name in algorithms.NAMES}
            plain = scn.params.with_setting("auto", oscillating=False)
            without = heldout.case_row(tr, heldout.AUTO, plain, seen)["mae_state"]
            best_mae, best = min((v["mae_state"], k) for k, v in rows.items() if not v["diverged"])
            auto = rows[heldout.AUTO]
            ratio = auto["mae_state"] / best_mae
            total += 1
            within += ratio <= 1.10
            in_band += band[0] <= auto["nees"] <= band[1]
            label = f"{tag} {heldout._topo_label(topology, comm_range)}"
            print(f"| {label} | {period:g} | {auto['mae_state']:.3g} | {without:.3g} | {best} | {best_mae:.3g} "
                  f"| {ratio:.2f} | {auto['nees']:.2f} |", flush=True)
    print(f"\ndiskf-auto within 10 % of the best in {within} of {total}; its mean NEES in the band in {in_band}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
