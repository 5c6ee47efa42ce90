"""``diskf-mesh experiment``: the paper's Table II on a scenario.

Runs every estimator on seeds 0..S-1 (or F..F+S-1 with ``--first-seed F``;
a seed's figures are the same bits whichever seeds run beside it) for every
topology (default: a
range-gated scenario's own range, e.g. dynamic at 120, as up and simulate
run it; any other scenario on the paper's all, ring, none), prints a table
shaped like Table II and optionally writes the numbers as JSON
``{estimator: {topology: {mae_state, rmse_state, mae_input, rmse_input,
input_coverage, nees, <metric>_std ...}}}``. An estimator that diverges in
a setting is ``"diverged": true`` there, ``diverged`` in the table, and one
line on standard error.
"""
from __future__ import annotations

import argparse
import sys

from diskf_mesh.studies import experiment
from diskf_mesh.data import lies, provenance
from diskf_mesh.data.scenario import load_scenario
from diskf_mesh.cli.options import (
    add_command,
    add_estimator_choice,
    add_estimator_options,
    add_scenario_options,
    check_output,
    estimator_params,
    human_stream,
    positive_int,
    save_json,
    seed_value,
)
from diskf_mesh.cli.progress import Progress

DEFAULT_TOPOLOGIES = ("all", "ring", "none")
STATUS_EVERY_S = 10.0  # a run's ticks are shown at most this often (a run of 10,000 agents takes minutes)


def topology_list(text: str) -> list[str]:
    """Comma list of topology names; checked by ``experiment.settings_for``."""
    return [t.strip() for t in text.split(",") if t.strip()]


def default_topologies(scn, topologies, comm_range):
    """(topologies, range) to run: as given; else only ``range`` when
    --range is given; else a range-gated scenario's own topology and range
    (as ``up`` and ``simulate`` run it); else the paper's three."""
    if topologies is not None:
        return topologies, comm_range
    if comm_range is not None:
        return ["range"], comm_range
    if scn.topology == "range":
        return ["range"], scn.comm_range
    return list(DEFAULT_TOPOLOGIES), None


def register(subparsers) -> None:
    p = add_command(subparsers, "experiment", "reproduce Table II: estimators x topologies x seeds", __doc__)
    add_scenario_options(p)
    p.add_argument("--topology", type=topology_list, metavar="T[,T...]",
                   help="comma list of all, ring, none, range (default: only range when --range is given "
                        "or the scenario is range-gated, e.g. dynamic at its own range; else all,ring,none)")
    add_estimator_choice(p, many=True)
    p.add_argument("--seeds", type=positive_int, default=20, metavar="S", help="run seeds 0..S-1 (default 20)")
    p.add_argument("--first-seed", type=seed_value, default=0, metavar="F",
                   help="run seeds F..F+S-1 instead: a seed's figures are the same whichever seeds run beside it "
                        "(default 0)")
    add_estimator_options(p)
    lies.add_arguments(p)
    p.add_argument("--json", metavar="OUT", help="also write the results as JSON (- for standard output)")
    p.add_argument("--quiet", action="store_true", help="no progress (a bar on a terminal, else a line per run)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    check_output(args.json, "json")
    started = provenance.now()
    scn = load_scenario(args.scenario, agents=args.agents)
    if args.lie is not None:
        scn = scn.with_lies(args.lie)
    settings = experiment.settings_for(*default_topologies(scn, args.topology, args.comm_range))
    params = estimator_params(scn.params, args)
    for st in settings:  # fail on a bad override before the long run
        st.apply(scn, args.ticks)
    runs = len(settings) * len(args.estimators)
    seeds = range(args.first_seed, args.first_seed + args.seeds)
    with Progress("experiment", args.quiet, total=runs, unit="run") as shown:
        shown.note(f"{runs} runs ({len(args.estimators)} estimators x {len(settings)} settings), "
                   f"{args.seeds} seeds x {args.ticks or scn.steps} ticks each")
        results = experiment.run_experiment(
            scn, settings, args.estimators, seeds, args.ticks, params,
            progress=lambda n: shown.step(f"runs of {args.seeds} seeds", n=n),
            ticks=lambda name, k: shown.status(f"{experiment.LABELS.get(name, name)}: tick {k} done",
                                               STATUS_EVERY_S))
    steps = args.ticks or scn.steps
    if args.json:
        prov = provenance.record(scenario=scn, seeds=seeds, ticks=steps, estimator=args.estimators,
                                 settings=params, faults=scn.faults, status="done", started=started, argv=args.argv)
        save_json(args.json, provenance.attach(results, prov), "json")
    text = human_stream(args.json)
    named = f" ({seeds.start}..{seeds.stop - 1})" if seeds.start else ""
    print(f"Scenario {scn.name}: {args.seeds} seeds{named} x {steps} ticks, {scn.N} agents"
          + ("; * marks the best value of each row" if len(args.estimators) > 1 else ""), file=text)
    print(experiment.format_table(results), file=text)
    for name, rows in results.items():
        gone = [experiment.TOPOLOGY_LABELS.get(st, st) for st, row in rows.items() if row.get("diverged")]
        if gone:
            print(f"diverged: {experiment.LABELS.get(name, name)} in {', '.join(gone)} (its covariance stopped being "
                  "positive definite, or an estimate left what a message may carry): no metrics there",
                  file=sys.stderr)
    return 0
