"""``diskf-mesh replay``: run one algorithm on recorded data.

Reads a ``diskf-trace/1`` JSON file, runs the algorithm on it in-process and
writes ``diskf-estimates/1`` (with ``metrics`` when the trace has truth).
The estimator options default to ``Params()``, the settings of the shipped
quadrants scenario.
"""
from __future__ import annotations

import argparse

from .. import algorithms, engine, metrics
from ..errors import InputError
from ..model import Params
from ..trace import estimates_to_json, load_trace
from .options import add_command, add_estimator_options, algorithm_name, estimator_params, json_safe, save_json


def register(subparsers) -> None:
    p = add_command(subparsers, "replay", "run an algorithm on a recorded diskf-trace/1 file", __doc__)
    p.add_argument("trace", metavar="TRACE.json", help="a diskf-trace/1 file, or RUN.mcap: a recording of up --record "
                   "(re-run on what each agent fused; --algorithm and the estimator options are the recording's)")
    p.add_argument("--algorithm", type=algorithm_name, default="diskf",
                   help=f"one of {', '.join(algorithms.NAMES)} (default diskf)")
    add_estimator_options(p)
    p.add_argument("--out", metavar="EST.json", help="where to write diskf-estimates/1 (required for a trace)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    if str(args.trace).endswith(".mcap"):
        from ..recording.command import replay_recording
        return replay_recording(args.trace, args.out)
    if args.out is None:
        raise InputError("out", "is required: where to write diskf-estimates/1")
    params = estimator_params(Params(), args)
    trace = load_trace(args.trace)
    est = engine.run(trace, args.algorithm, params)
    scores = metrics.compute(trace, est) if trace.truth_x is not None else None
    save_json(args.out, estimates_to_json(est, args.algorithm, 0, scores))
    B, K, N = trace.shape
    print(f"{args.algorithm}: {K} ticks, {N} agents -> {args.out}")
    for key, value in json_safe(scores or {}).items():
        print(f"  {key:<15}{'-' if value is None else f'{value:.4f}'}")
    return 0
