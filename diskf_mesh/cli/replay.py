"""``diskf-mesh replay``: run one estimator on recorded data.

Reads a ``diskf-trace/1`` JSON file, runs the estimator on it in-process and
writes ``diskf-estimates/1`` (with ``metrics`` when the trace has truth).
The estimator settings are those the trace carries (``simulate`` writes its
scenario's ``[estimator]`` table into it), so ``simulate`` + ``replay`` gives
``experiment``'s estimates bit for bit; ``Params()`` where the trace has
none, and the estimator options (--window, --eps, ...) override them. A trace that breaks
its schema (docs/formats.md) ends in one line naming the field, exit 2. An
estimator that diverges on the trace (its covariance stops being positive
definite, or an estimate leaves what a message may carry) ends in one line
saying whose and at which tick, exit 1, nothing written.

``--fused EST.json`` replays a mesh run (``up`` or ``world --estimates``, a
real-time or faulty run included) from its estimates document: the engine runs
the trace (``simulate`` with the run's scenario, seed and ticks) on exactly the
messages each agent fused at each tick, each restarted agent from the state it
was handed, with the run's estimator and settings, and compares every
reported estimate with the run's (``engine.verify``): the run's status and its
exit status (``diskf_mesh.core.exits``: 0 exact or as planned, 3 incomplete,
5 degraded, 6 diverged, e.g. the wrong trace; ``--allow-missing`` and
``--allow-degraded`` accept as a run does; a real-time run's deadline
misses were judged by the run, against its ``--max-miss-rate``, and are
accepted). ``replay RUN.mcap`` checks a recording the same way.
"""
from __future__ import annotations

import argparse
import sys

from diskf_mesh.engine import batch as engine
from diskf_mesh.data import metrics, provenance
from diskf_mesh.core import exits
from diskf_mesh.core.errors import InputError
from diskf_mesh.mesh.protocol.run_status import add_tolerances
from diskf_mesh.data.trace import estimates_to_json, estimator_from_json, read_json, read_trace_file
from diskf_mesh.cli.options import (
    add_command,
    add_estimator_choice,
    add_estimator_options,
    check_output,
    estimator_params,
    human_stream,
    json_safe,
    save_json,
)


def register(subparsers) -> None:
    p = add_command(subparsers, "replay", "run an estimator on a recorded diskf-trace/1 file", __doc__)
    p.add_argument("trace", metavar="TRACE.json", help="a diskf-trace/1 file, or RUN.mcap: a recording of up --record "
                   "(re-run on what each agent fused; --estimator and the estimator options are the recording's)")
    add_estimator_choice(p)
    add_estimator_options(p)  # default: the trace's "estimator" settings
    p.add_argument("--fused", metavar="EST.json", help="a mesh run's estimates (up --estimates): replay it on what each "
                   "agent fused and compare bit for bit (the run's status and exit status, diverged "
                   f"{exits.DIVERGED} if any estimate differs); the run's estimator and settings")
    add_tolerances(p)  # a replayed run's status, accepted as the run's would be
    p.add_argument("--out", metavar="EST.json", help="where to write diskf-estimates/1 (- for standard output; required for a trace)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    if str(args.trace).endswith(".mcap"):
        from diskf_mesh.recording.command import replay_recording
        check_output(args.out, "out")
        return replay_recording(args.trace, args.out, argv=args.argv, allow_missing=args.allow_missing,
                                allow_degraded=args.allow_degraded, accept_unverifiable=args.accept_unverifiable)
    if args.fused is not None:
        return replay_run(args)
    if args.out is None:
        raise InputError("out", "is required: where to write diskf-estimates/1")
    check_output(args.out, "out")
    started = provenance.now()
    doc, trace = read_trace_file(args.trace)
    params = estimator_params(estimator_from_json(doc), args)
    try:
        est = engine.run(trace, args.estimator, params)
    except engine.Diverged as e:
        return failed(f"{e}; nothing written")
    from diskf_mesh.studies.experiment import diverged_tick
    k = diverged_tick(est)
    if k is not None:
        return failed(f"{args.estimator}, tick {k}: an estimate is not finite or beyond what a message may carry "
                      "(it diverged); nothing written")
    scores = metrics.compute(trace, est) if trace.truth_x is not None else None
    prov = trace_provenance(args, doc, trace, params, "done", started)
    save_json(args.out, provenance.attach(estimates_to_json(est, args.estimator, 0, scores, ids=trace.agent_labels),
                                          prov))
    B, K, N = trace.shape
    text = human_stream(args.out)
    print(f"{args.estimator}: {K} ticks, {N} agents -> {args.out}", file=text)
    for key, value in json_safe(scores or {}).items():
        print(f"  {key:<15}{'-' if value is None else f'{value:.4f}'}", file=text)
    return 0


def failed(line: str) -> int:
    """A replay whose estimator diverged: one line, exit 1, nothing written."""
    print(f"error: {line}", file=sys.stderr)
    return exits.FAILED


def trace_provenance(args, doc: dict, trace, params, status: str, started: str, estimator=None) -> dict:
    """A replay's provenance: its input is the trace (its scenario's name,
    the SHA-256 of the trace's content)."""
    return provenance.record(scenario={"name": doc.get("scenario"), "sha256": provenance.content_hash(doc)},
                             seeds=[doc.get("seed", 0)], ticks=trace.shape[1], estimator=estimator or args.estimator,
                             settings=params, faults=doc.get("faults"), status=status, started=started,
                             argv=args.argv)


def replay_run(args: argparse.Namespace) -> int:
    """``replay TRACE.json --fused EST.json``: the run checked by the engine
    (``engine.verify``) and its exit status (``recording.command.report_replay``;
    ``--allow-missing``, ``--allow-degraded``)."""
    from diskf_mesh.recording.command import report_replay
    from diskf_mesh.recording.replay import fused_record_from_json, fused_status, replay_fused

    check_output(args.out, "out")
    started = provenance.now()
    doc, trace = read_trace_file(args.trace)
    try:
        run = fused_record_from_json(read_json(args.fused), trace.agent_labels)
    except InputError as e:
        raise InputError(e.field, f"{e.message} (in {args.fused})") from None
    K = run.fused.shape[0]
    if K > trace.shape[1]:
        raise InputError("fused", f"the run has {K} ticks, the trace only {trace.shape[1]}")
    params = run.params if run.params is not None else estimator_params(estimator_from_json(doc), args)
    status = fused_status(run, trace, params)
    est = replay_fused(trace, run.fused, run.reported, run.algorithm, params, run.restarts, run.estimates)
    prov = trace_provenance(args, doc, trace, params, status.status, started, run.algorithm)
    return report_replay(status, est, trace, run.algorithm, trace.agent_labels, prov, args.out,
                         miss_rate=run.miss_rate, allow_missing=args.allow_missing,
                         allow_degraded=args.allow_degraded, accept_unverifiable=args.accept_unverifiable,
                         hint="not this run's trace, scenario, seed or settings?")
