"""``diskf-mesh simulate``: draw one seed of a scenario as a diskf-trace/1 file.

Seed S draws the noise from ``numpy.random.default_rng(S)``, exactly as the
experiment's seed S does, and the file carries the scenario's name and its
``[estimator]`` settings, so ``replay`` of the file reproduces the engine run
of ``experiment`` bit for bit.
"""
from __future__ import annotations

import argparse

from diskf_mesh.studies.experiment import settings_for
from diskf_mesh.data.scenario import TOPOLOGIES, load_scenario, simulate
from diskf_mesh.data.trace import trace_to_json
from diskf_mesh.cli.options import (
    add_command,
    add_scenario_options,
    check_output,
    human_stream,
    save_json,
    seed_value,
)


def register(subparsers) -> None:
    p = add_command(subparsers, "simulate", "write a diskf-trace/1 file from a scenario", __doc__)
    add_scenario_options(p)
    p.add_argument("--topology", metavar="T", help=f"one of {', '.join(TOPOLOGIES)} (default: the scenario's)")
    p.add_argument("--seed", type=seed_value, default=0, metavar="S", help="noise seed (default 0)")
    p.add_argument("--out", required=True, metavar="TRACE.json", help="where to write the trace (- for standard output)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    check_output(args.out, "out")
    scn = load_scenario(args.scenario, agents=args.agents)
    topology = args.topology or ("range" if args.comm_range is not None else scn.topology)
    setting, = settings_for([topology], args.comm_range)
    scn = setting.apply(scn, args.ticks)
    trace = simulate(scn, [args.seed])
    save_json(args.out, trace_to_json(trace, 0, scenario=scn.name, params=scn.params))
    B, K, N = trace.shape
    print(f"{scn.name} seed {args.seed}: {K} ticks, {N} agents, topology {setting.label} -> {args.out}",
          file=human_stream(args.out))
    return 0
