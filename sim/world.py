"""``diskf-mesh world``: the world process of a mesh run.

It owns the ground truth (``scenario.simulate`` with ``--seed``) and the
agents' motion. It waits until every agent of the scenario is ready (their
liveliness tokens; after ``--startup-timeout`` it gives up, naming the
missing ones: the run ends ``incomplete``, its results written, exit 3;
with ``--allow-missing`` it starts without them), then runs the ticks in lockstep: for tick k it sends each live agent
its own measurement (or none) on that agent's key, broadcasts every agent's
position and the live set, and waits for every live agent's fused estimate
of tick k, or ``--tick-timeout`` seconds. A report of a past tick is counted
("stale") and dropped. At the end it says stop, computes the metrics and
writes the same result JSON as ``experiment``:
``{algorithm: {setting: {mae_state, ...}}}``, plus, per setting, the link
faults of the run, every agent's message counters (``diskf_mesh.mesh.wire.counters``)
and the ticks each agent did not report (``missing_ticks``: killed, or
rejoining); ``--estimates`` writes every agent's fused estimates, what was
missing, and every agent's counters.

An agent whose liveliness token goes (a crash, ``kill -9``, a freeze past
zenoh's lease) drops out of the live set from the next tick on; the world
goes on with the others. An agent that comes back (same id: a restart, or a
frozen process that woke) is live again from the tick after next once it is
ready with a new token; an old ready token that reappears (a frozen
process's, re-announced by zenoh when it reconnects) does not count. It
starts from the estimate the world answers to its query on ``Keys.start``
once the tick before is over: the most certain fused estimate of that tick
an agent in range reported, or the prior (``WorldMachine.start_state``).

The world does not run on alone. If it was frozen itself (its main thread
wakes long after it should), or every agent is gone, it pauses: it keeps the
open tick open and waits up to ``--startup-timeout`` for the agents that were
live to come back (an agent that comes back while it pauses is live again at
once), then sends that tick again (agents that had reported it send their
report again). If none comes back the run ends early.

As the run goes the world checks each tick once its reports are in
(``mesh.protocol.run_status.OnlineCheck``; in lockstep in a thread of its
own beside the world's callbacks, ``mesh.process.checker``) and cuts off an agent it
proves lied: the ticks leave it out of the live set. At the end it checks the
whole run (``checked_status``, ``diskf_mesh.engine.verify``): the engine
replays it from what each agent
said it fused, restarts re-initialised agents from the states handed to
them, recomputes every fused message's digest and compares every reported
estimate bit for bit. Exit status (``diskf_mesh.core.exits``): 0 when the run
is ``exact`` or ``as planned``; 3 ``incomplete`` (one line: how many
agent-ticks are missing, of which agents, and why: never joined, left,
rejoining, no report, rejected, not run; 0 within ``--allow-missing``); 5
``degraded`` (0 with ``--allow-degraded``, or in real time within
``--max-miss-rate``); 6 ``diverged``; 8 ``unverifiable`` (reported
agent-ticks built on a state the run did not report; 0 only with
``--accept-unverifiable``); 4 a real-time run beyond
``--max-miss-rate``; 2 another world already runs this run id (``mesh.wire.keys``
nonces). The result JSON holds what was measured either way, with the
status, its reason and evidence, ``complete``, the missing counts, the
rejoins (tick and re-initialisation source), duplicate processes and pauses.

The protocol is ``diskf_mesh.mesh.protocol.world_machine.WorldMachine`` (no I/O);
``World`` runs it in a ``mesh.process.shell.Shell`` over zenoh and the wall clock:
the report that completes tick k opens tick k+1 in zenoh's callback itself
(``mesh.process``'s docstring follows one tick world -> agent -> neighbour
-> world through the code); ``--profile DIR`` writes where each tick's time
went (``mesh.protocol.profile``).
"""
from __future__ import annotations

import argparse
import math
import signal
import sys
import time
from collections import Counter
from dataclasses import asdict, dataclass, replace

import numpy as np

from diskf_mesh.data import metrics
from diskf_mesh import estimators
from diskf_mesh.data.argtypes import add_ticks, seconds, seed_value
from diskf_mesh.data import provenance
from diskf_mesh.data.outputs import check_output, save_json
from diskf_mesh.core import exits
from diskf_mesh.data.outputs import json_safe
from diskf_mesh.engine.verify import RunStatus
from diskf_mesh.mesh.wire.counters import Counters
from diskf_mesh.mesh.protocol.agent_machine import AgentTiming
from diskf_mesh.mesh.protocol.run_status import OnlineCheck, accept, add_tolerances, run_status
from diskf_mesh.data.faults import FaultConfig
from diskf_mesh.data.faults import add_arguments as add_fault_arguments
from diskf_mesh.data.faults import from_args as faults_from_args
from diskf_mesh.mesh.protocol import clock as realtime
from diskf_mesh.mesh.security import credentials
from diskf_mesh.mesh.process import runspec
from diskf_mesh.mesh.process import zenoh_config
from diskf_mesh.mesh.wire.keys import Keys, new_nonce
from diskf_mesh.mesh.protocol.log import Log
from diskf_mesh.mesh.protocol.profile import NO_PHASES, WORLD_PHASES, Phases
from diskf_mesh.mesh.process.checker import CheckThread
from diskf_mesh.mesh.process.shell import Shell
from diskf_mesh.mesh.protocol.world_machine import DUPLICATE, WorldMachine, WorldRecord, WorldTiming
from diskf_mesh.mesh.process.transport import DuplicateProcess, MeshError, Transport, ZenohTransport
from diskf_mesh.recording.writer import NO_RECORDER, NoRecorder, failure_line
from diskf_mesh import live as live_server
from diskf_mesh.data.scenario import Scenario, simulate
from diskf_mesh.data.trace import MESH_ESTIMATES_FORMAT, Trace, estimates_to_json



LINES_EVERY_S = 0.1  # --progress lines: at most one line this often (and ticks 1 and K)
HOLD_MS = 5   # a measurement waits at most this long in zenoh's batch for its tick (it comes at once)


class World:
    """The world process: its protocol (``mesh.protocol.world_machine.WorldMachine``)
    run by a ``mesh.process.shell.Shell`` over ``transport`` on the wall clock.
    ``run`` returns the ``WorldRecord``; a run that could not go on raises
    ``MeshError`` (``DuplicateProcess``: another world holds the run id).
    ``interrupted = why`` (a signal handler) ends the run early at the
    shell's next look."""

    def __init__(self, scn: Scenario, trace: Trace, algorithm: str, seed: int, keys: Keys, transport: Transport,
                 timing: WorldTiming = WorldTiming(), progress=None, log: Log | None = None,
                 profile: Phases = NO_PHASES, recorder: NoRecorder = NO_RECORDER, online=None):
        self.machine = WorldMachine(scn, trace, algorithm, seed, keys, new_nonce(), timing,
                                    log=log, progress=progress, profile=profile, recorder=recorder, online=online)
        self.shell = Shell(self.machine, transport, profile)

    @property
    def record(self) -> WorldRecord:
        return self.machine.record

    @property
    def done(self) -> bool:
        """Tick K is closed."""
        return self.machine.done

    @property
    def interrupted(self) -> str:
        return self.shell._interrupt

    @interrupted.setter
    def interrupted(self, why: str) -> None:
        if why:
            self.shell.interrupt(why)

    def run(self, allow_missing: bool = False) -> WorldRecord:
        """The whole run; ``allow_missing``: start without the agents not
        ready after ``--startup-timeout`` (they never joined)."""
        self.machine.allow_missing = allow_missing
        error = failure(self.shell.run(), self.machine.record)
        if error is not None:
            raise error
        return self.machine.record


def failure(end, rec: WorldRecord) -> MeshError | None:
    """The error of a world that could not go on (its ``Finish``'s code:
    ``DuplicateProcess`` when another world holds the run id), None when
    the run ended, or gave up with its reason in ``rec`` (``ended_early``:
    the agents not ready after ``--startup-timeout``), a run that ends
    with a status (``incomplete``) like any other."""
    if end.code == DUPLICATE:
        return DuplicateProcess(end.reason)
    return MeshError(end.reason) if end.code and not rec.ended_early else None


# --------------------------------------------------------------------------
# results
# --------------------------------------------------------------------------
def result_metrics(trace: Trace, rec: WorldRecord) -> dict:
    """The metrics of ``experiment`` over the agent-ticks that were reported
    (a single seed, so every spread ``<metric>_std`` is 0)."""
    row = metrics.summarize(*metrics.errors(trace, rec.estimates(fill=True)), mask=rec.reported[None])
    row.update({f"{k}_std": 0.0 for k in metrics.METRIC_KEYS})
    return row


def completeness(rec: WorldRecord) -> dict:
    """Whether every agent reported every tick, and if not what is missing,
    per agent and why: ``never joined`` (not ready at the start), ``left``
    (its token went), ``rejoining`` (back, not live yet), ``no report``
    (live, nothing within ``--tick-timeout``), ``rejected`` (its report
    failed the decoder), ``not run`` (the run ended before that tick). With
    the rejoins (tick, re-initialisation source: an agent id or None for the
    prior), the duplicate processes seen, the pauses."""
    K, N = rec.reported.shape
    missing = {}
    for j, i in enumerate(rec.ids):
        miss = ~rec.reported[:, j]
        if miss.any():
            why = Counter(w or "not run" for w in rec.why[miss, j])
            missing[str(rec.label(i))] = {"ticks": int(miss.sum()), "why": dict(sorted(why.items()))}
    n = int((~rec.reported).sum())
    return {"complete": n == 0, "agent_ticks": K * N, "missing_agent_ticks": n, "missing_fraction": n / (K * N),
            "missing": missing, "rejoins": {str(rec.label(i)): [{**r, "source": rec.label(r["source"])} for r in v]
                                            for i, v in sorted(rec.rejoins.items())},
            "duplicate_ids": {str(rec.label(i)): c for i, c in rec.duplicates.items()}, "pauses": list(rec.pauses),
            "ended_early": rec.ended_early}


def missing_line(c: dict) -> str:
    """One line of what ``completeness`` found missing; a run that ended
    before any tick ran (a start-up that failed): why, first."""
    if c.get("ended_early") and c["missing_agent_ticks"] == c["agent_ticks"] \
            and all(m["why"].keys() == {"not run"} for m in c["missing"].values()):
        return f"{c['ended_early']}: no tick ran ({c['missing_agent_ticks']} agent-ticks missing)"
    agents = "; ".join(f"agent {i}: {m['ticks']} ({', '.join(f'{w} {n}' for w, n in m['why'].items())})"
                       for i, m in c["missing"].items())
    early = f"; the run ended early: {c['ended_early']}" if c.get("ended_early") else ""
    return (f"{c['missing_agent_ticks']} of {c['agent_ticks']} agent-ticks missing "
            f"({100 * c['missing_fraction']:.1f} %): {agents}{early}")


def miss_problem(row: dict, max_miss_rate: float) -> str:
    """One line if a real-time run's miss rate exceeds ``max_miss_rate``."""
    dm = row["deadline_misses"]
    if dm["miss_rate"] <= max_miss_rate:
        return ""
    return f"{miss_line(row)}, above --max-miss-rate {max_miss_rate:g}: the run did not keep up with its rate"


def miss_line(row: dict) -> str:
    """What a real-time run missed, in one line."""
    dm = row["deadline_misses"]
    late = dm.get("late_report_s")
    return (f"{dm['total']} deadline misses ({100 * dm['miss_rate']:.2f} % of messages and reports: "
            f"{dm['messages']} messages, {dm['reports']} reports"
            + (f", late reports a median {late['median']:.2f} s late" if late and dm["reports"] else "") + ")")


def run_summary(rec: WorldRecord, faults: FaultConfig) -> dict:
    """The run's faults, every agent's counters (its last report's; a
    restarted agent's count from its restart), the ticks it did not report,
    and ``completeness``."""
    out = {"faults": faults.to_dict(), "counters": {}, "missing_ticks": {}, **completeness(rec)}
    for j, i in enumerate(rec.ids):
        c = Counters.from_dict(rec.agent_counters.get(i, {}))
        out["counters"][str(rec.label(i))] = c.to_json()
        if c.imbalance():
            out["counters"][str(rec.label(i))]["imbalance"] = c.imbalance()
        missing = (1 + np.flatnonzero(~rec.reported[:, j])).tolist()
        if missing:
            out["missing_ticks"][str(rec.label(i))] = missing
    return out


def deadline_summary(rec: WorldRecord, clock: realtime.Clock) -> dict:
    """A real-time run's ``deadline_misses`` (per agent and in total: its
    neighbours' messages not fused in time, its reports not in by the tick's
    end, of which ``late_reports`` came later; ``miss_rate`` = misses over
    messages and reports due) and ``tick_period`` (``clock.period_stats``)."""
    dl = rec.deadlines
    per = {}
    for i in rec.ids:
        m, r = dl.message_misses[i], dl.report_misses[i]
        per[str(rec.label(i))] = {"total": m + r, "messages": m, "reports": r, "late_reports": dl.late_reports[i],
                       "messages_due": dl.messages_due[i], "reports_due": dl.reports_due[i]}
    tot = {key: sum(a[key] for a in per.values()) for key in next(iter(per.values()))}
    due = tot["messages_due"] + tot["reports_due"]
    tot["miss_rate"] = tot["total"] / due if due else 0.0
    tot["message_miss_rate"] = tot["messages"] / tot["messages_due"] if tot["messages_due"] else 0.0
    tot["report_miss_rate"] = tot["reports"] / tot["reports_due"] if tot["reports_due"] else 0.0
    if dl.late_by:
        tot["late_report_s"] = {"median": float(np.median(dl.late_by)), "max": float(np.max(dl.late_by))}
    return {"rate_hz": clock.rate_hz, "deadline_s": clock.deadline_s, "deadline_misses": {**tot, "per_agent": per},
            "tick_period": realtime.period_stats(dl.opened_at, clock)}


def checked_status(rec: WorldRecord, trace: Trace, scn: Scenario, spec, seed: int, faults: FaultConfig,
                   clock: realtime.Clock | None, collect_s: float = math.inf, online=None) -> RunStatus:
    """The run checked by the engine (``mesh.protocol.run_status``): ``exact``, ``as
    planned``, ``degraded``, ``diverged`` or ``incomplete``, with its reason
    and evidence. The plan: a copy the link faults delay past the agents'
    deadline (real time's, else their ``collect_s``) is not planned to be
    fused. ``online``: the world's check as the run went, whose replay of
    each tick is taken where it is the end's own (``run_status``)."""
    return run_status(rec, trace, spec.algorithm, scn.params, run_id=spec.run_id, seed=seed, faults=faults,
                      deadline_s=realtime.agents_deadline(clock, collect_s), labels=scn.labels, online=online)


def status_fields(status: RunStatus) -> dict:
    """The status in the result JSON and the estimates document: ``status``,
    ``reason`` (one line) and ``evidence``."""
    return {"status": status.status, "reason": status.reason, "evidence": json_safe(status.evidence)}


def exit_status(status: RunStatus, summary: dict, args, clock: realtime.Clock | None) -> tuple:
    """(exit status, level, line) of the run (``mesh.protocol.run_status.accept``
    under ``--allow-missing``, ``--allow-degraded`` and, in real time,
    ``--max-miss-rate``); an incomplete run's line names what is missing
    per agent and why."""
    if status.status == exits.INCOMPLETE_STATUS:
        status = replace(status, reason=missing_line(summary))
    miss = summary["deadline_misses"]["miss_rate"] if clock is not None else None
    max_rate = realtime.max_miss_rate(args) if clock is not None else None
    code, level, line = accept(status, allow_missing=args.allow_missing,
                               allow_degraded=getattr(args, "allow_degraded", False),
                               accept_unverifiable=getattr(args, "accept_unverifiable", False), miss_rate=miss,
                               max_miss_rate=max_rate)
    if code == exits.TOO_MANY_MISSES:
        line = miss_problem(summary, max_rate)
    return code, level, line


def fused_lists(rec: WorldRecord) -> list:
    """K x N: the ids whose messages agent i fused at tick k (empty where it
    did not report)."""
    ids = rec.ids
    return [[[ids[s] for s in np.flatnonzero(row).tolist()] for row in tick] for tick in rec.fused]


def fused_digest_lists(rec: WorldRecord) -> list:
    """K x N, aligned with ``fused_lists``: the hex digest of each message
    agent i fused at tick k, as it reported them."""
    K, N = rec.reported.shape
    out = [[[] for _ in range(N)] for _ in range(K)]
    for (k, i), (senders, digests) in rec.claimed_digests().items():
        order = np.argsort(senders, kind="stable")
        out[k - 1][i] = [int(g).to_bytes(8, "little").hex() for g in digests[order].tolist()]
    return out


def estimates_doc(rec: WorldRecord, algorithm: str, scn: Scenario, seed: int, run_id: str, row: dict) -> dict:
    doc = estimates_to_json(rec.estimates(), algorithm, metrics=row)
    doc.update(format=MESH_ESTIMATES_FORMAT, scenario=scn.name, seed=seed, run_id=run_id, ids=list(scn.labels),
               reported=rec.reported.tolist(), **({} if rec.live is None else {"live": rec.live.tolist()}),
               agent_counters={str(rec.label(k)): v for k, v in rec.agent_counters.items()},
               world_counters=dict(rec.counters), startup_s=rec.startup_s, ticks_s=rec.ticks_s,
               fused=fused_lists(rec), fused_digests=fused_digest_lists(rec), estimator=asdict(scn.params))
    return doc


def open_recorder(path, trace, scn, spec, seed, faults, prov=None):
    from diskf_mesh.core.errors import InputError
    from diskf_mesh.recording.writer import Recorder

    try:
        return Recorder(path, trace, scn, scenario=spec.scenario, algorithm=spec.algorithm, seed=seed,
                        run_id=spec.run_id, faults=faults, provenance=prov)
    except OSError as e:
        raise InputError("record", f"cannot write {path}: {e.strerror or e}") from None


@dataclass(frozen=True)
class RunSetup:
    """A run as it starts: its spec, scenario, trace, link faults, clock
    (None: lockstep), provenance and recorder."""

    spec: object
    scn: Scenario
    trace: Trace
    faults: FaultConfig
    clock: realtime.Clock | None
    prov: dict
    recorder: NoRecorder = NO_RECORDER


def setup_run(args, spec, scn: Scenario, started: str) -> RunSetup:
    """The run of ``spec`` on ``scn`` with ``args``' seed, link faults, clock
    and ``--record``."""
    clock = realtime.from_args(args)
    faults = faults_from_args(args, scn.faults)  # the agents apply them; the world records them
    trace = simulate(scn, [args.seed])
    prov = provenance.record(scenario=scn, seeds=[args.seed], ticks=trace.has.shape[1], estimator=spec.algorithm,
                             settings=scn.params, faults=faults, started=started, argv=getattr(args, "argv", None))
    recorder = open_recorder(args.record, trace, scn, spec, args.seed, faults, prov) if args.record else NO_RECORDER
    return RunSetup(spec, scn, trace, faults, clock, prov, recorder)


def run_failed(error: MeshError, run: RunSetup, log: Log) -> int:
    """A run that could not go on: one line, the recording says why; its
    exit status."""
    log.error(str(error))
    run.recorder.finish(f"failed: {error}")
    return error.status


def finish_run(args, run: RunSetup, rec: WorldRecord, done: bool, json_path=None, extra=None,
               log: Log | None = None, online=None) -> tuple:
    """The end of a run, the world process's and ``up --network simulated``'s:
    the metrics, ``run_summary`` (and ``deadline_summary`` in real time,
    and ``extra``), the run checked (``checked_status`` with the agents'
    ``--collect-timeout``), the recording finished (one not written whole:
    ``recording_failed``), the results written to ``json_path`` and the
    estimates to ``--estimates``. ``log``: says the counters that do not add
    up and the exit status's line (None: the caller says them). Returns
    (exit status, results): ``exit_status``'s, or ``RECORDING_FAILED`` for
    an accepted run whose recording failed."""
    spec, scn, trace, clock = run.spec, run.scn, run.trace, run.clock
    row = result_metrics(trace, rec)
    timing = deadline_summary(rec, clock) if clock is not None else {}
    summary = {**run_summary(rec, run.faults), **timing}
    status = checked_status(rec, trace, scn, spec, args.seed, run.faults, clock, args.collect_timeout, online)
    summary.update(status_fields(status), **(extra or {}))
    # the recording's result: a real-time run's deadline misses with the metrics (its replay accepts them)
    recording = run.recorder.finish("done" if done else "stopped", {**row, **timing}, status.to_json())
    if recording:  # the run is measured, the file is not whole: the results say so, and the exit status
        summary["recording_failed"] = recording
    results = {spec.algorithm: {runspec.setting_label(scn): {**row, **summary}}}
    prov = {**run.prov, "status": status.status}
    if json_path:
        save_json(json_path, provenance.attach(results, prov), "json")
    if args.estimates:
        doc = estimates_doc(rec, spec.algorithm, scn, args.seed, spec.run_id, row)
        doc.update({k: v for k, v in summary.items() if k != "counters"})  # agent_counters has them
        save_json(args.estimates, provenance.attach(doc, prov), "estimates")
    code, level, line = exit_status(status, summary, args, clock)
    if log is not None:
        for i, c in summary["counters"].items():
            if "imbalance" in c:
                log.info(f"agent {i}'s message counters do not add up: {'; '.join(c['imbalance'])}")
        if level:
            (log.error if level == "error" else log.info)(line)
        if recording:
            log.error(failure_line(recording))
    return (code or exits.RECORDING_FAILED) if recording else code, results


# --------------------------------------------------------------------------
# command line
# --------------------------------------------------------------------------
PROGRESS = ("bar", "lines", "none")


def add_allow_missing(p) -> None:
    add_tolerances(p, "; with it, the run also starts without agents not ready after --startup-timeout")


def add_timing_arguments(p) -> None:
    """A run's ``--startup-timeout``, ``--tick-timeout`` and
    ``--collect-timeout`` (``world``, ``up``): their defaults are
    ``WorldTiming``'s and ``AgentTiming``'s."""
    p.add_argument("--startup-timeout", type=seconds, default=WorldTiming.startup_timeout, metavar="S",
                   help="seconds to wait for every agent to be ready (default %(default)s)")
    p.add_argument("--tick-timeout", type=seconds, default=WorldTiming.tick_timeout, metavar="S",
                   help="world: seconds to wait for the reports of one tick (default %(default)s)")
    p.add_argument("--collect-timeout", type=seconds, default=AgentTiming.collect_timeout, metavar="S",
                   help="agents: seconds to wait for the neighbours' messages of a tick (default %(default)s); "
                        "with link latency injected, a message due later is not planned to be fused (the run's "
                        "status)")


def timing_argv(args) -> list:
    """``add_timing_arguments``' flags as given, for a world ``up`` starts."""
    return ["--startup-timeout", repr(args.startup_timeout), "--tick-timeout", repr(args.tick_timeout),
            "--collect-timeout", repr(args.collect_timeout)]


def agent_world_timeout(args) -> float:
    """The agents' ``--world-timeout`` in a run ``up`` starts: the world's
    start-up and two ticks of silence."""
    return args.startup_timeout + 2 * args.tick_timeout


def run_timings(args, clock: realtime.Clock | None) -> tuple:
    """(``WorldTiming``, ``AgentTiming``) of a run from
    ``add_timing_arguments``' flags and its clock."""
    return (WorldTiming(args.startup_timeout, args.tick_timeout, clock=clock),
            AgentTiming(args.collect_timeout, agent_world_timeout(args), clock))


def register(subparsers) -> None:
    p = subparsers.add_parser("world", help="the world process of a mesh run (ground truth, lockstep)",
                              description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    runspec.add_arguments(p)
    add_ticks(p, help="ticks to run (default: the scenario's)")
    p.add_argument("--seed", type=seed_value, default=0, metavar="S", help="simulation seed (default 0)")
    p.add_argument("--json", metavar="OUT", help="write the results {algorithm: {setting: metrics}}")
    p.add_argument("--estimates", metavar="OUT", help="write every agent's fused estimates and counters")
    p.add_argument("--record", metavar="FILE.mcap", help="record the run as MCAP (diskf_mesh.recording)")
    add_timing_arguments(p)
    add_allow_missing(p)
    live_server.add_arguments(p)
    realtime.add_arguments(p)
    p.add_argument("--progress", choices=PROGRESS, default="bar",
                   help="progress bar on stderr, 'tick k K' lines on stdout (ticks 1 and K, and at most "
                        f"one every {LINES_EVERY_S:g} s between), or none")
    p.add_argument("--profile", metavar="DIR",
                   help="measure where each tick's time goes (wait for reports, decode, encode, publish) and "
                        "write DIR/world.json at exit")
    add_fault_arguments(p)
    zenoh_config.add_arguments(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    check_output(args.json, "json", stdout=False)  # before any work: a bad path must not cost the run
    check_output(args.estimates, "estimates", stdout=False)
    check_output(args.record, "record", stdout=False)
    if args.live is not None:
        live_server.check_port(args.live)
    signalled = [""]  # the signal's name, then the World, which ends the run at its next look (POLL_S)

    def interrupt(signum, frame):
        if isinstance(signalled[0], World):
            signalled[0].interrupted = signal.Signals(signum).name
        else:
            signalled[0] = signal.Signals(signum).name

    for sig in (signal.SIGTERM, signal.SIGINT):  # from the start: up may stop the world while it starts
        signal.signal(sig, interrupt)
    started = provenance.now()
    spec = runspec.from_args(args)
    scn = spec.load(args.ticks)
    return _run(args, spec, scn, started, signalled)


def online_check(args, spec, scn: Scenario, trace: Trace, faults: FaultConfig, clock) -> OnlineCheck:
    """The world's check as the run goes (``OnlineCheck``) of a run."""
    return OnlineCheck(trace, estimators.get(spec.algorithm), scn.params, run_id=spec.run_id, seed=args.seed,
                       faults=faults, deadline_s=realtime.agents_deadline(clock, args.collect_timeout))


def _run(args, spec, scn: Scenario, started: str, signalled: list) -> int:
    from tqdm import tqdm

    from diskf_mesh.studies.experiment import format_table

    zenoh = zenoh_config.from_args(args, credentials.WORLD, spec.run_id)
    run = setup_run(args, spec, scn, started)
    if args.live is not None:  # the live server: fed as the recorder is
        run = replace(run, recorder=live_server.feed(run.recorder, args.live, run.trace, scn, scenario=spec.scenario,
                                                     algorithm=spec.algorithm, seed=args.seed, run_id=spec.run_id,
                                                     faults=run.faults, provenance=run.prov))
    K = run.trace.has.shape[1]
    log = Log("world")
    if problem := estimators.get(spec.algorithm).warning(scn.params, run.trace.links):
        log.info(problem)
    bar = tqdm(total=K, desc=f"world {spec.algorithm}", unit="tick", file=sys.stderr,
               disable=args.progress != "bar" or not sys.stderr.isatty())

    last_line = -math.inf

    def progress(k):
        nonlocal last_line
        if args.progress == "lines":  # every tick would wake the reader of the lines (the launcher) each tick
            now = time.monotonic()
            if k in (1, K) or now - last_line >= LINES_EVERY_S:
                print(f"tick {k} {K}", flush=True)
                last_line = now
        bar.update(1)

    prof = Phases(WORLD_PHASES, "world") if args.profile else NO_PHASES
    make = lambda: online_check(args, spec, scn, run.trace, run.faults, run.clock)  # noqa: E731
    # lockstep: the check as the run goes in a thread of its own; real time: on the world's timer
    online = CheckThread(make, prof) if run.clock is None else make()
    try:
        with ZenohTransport(zenoh, hold_ms=HOLD_MS) as transport:
            world = World(scn, run.trace, spec.algorithm, args.seed, Keys(spec.run_id), transport,
                          run_timings(args, run.clock)[0], progress, log, prof, run.recorder, online)
            world.interrupted, signalled[0] = signalled[0], world
            rec = world.run(allow_missing=args.allow_missing > 0)
    except MeshError as e:
        return run_failed(e, run, log)
    finally:
        bar.close()
        if isinstance(online, CheckThread):
            online.close()
        if prof:
            prof.write(args.profile, "world")
    code, results = finish_run(args, run, rec, world.done, args.json, log=log, online=online)
    if args.progress != "lines":
        row = next(iter(next(iter(results.values())).values()))
        print(format_table(results))
        print(f"status: {row['status']}: {row['reason']}")
    return code


if __name__ == "__main__":
    from diskf_mesh.cli import main as cli

    sys.exit(cli.run_one("world", __spec__.name))
