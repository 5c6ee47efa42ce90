"""``diskf-mesh world``: the world process of a mesh run.

It owns the ground truth (``scenario.simulate`` with ``--seed``) and the
agents' motion. It waits until every agent of the scenario is ready (their
liveliness tokens; it fails after ``--startup-timeout`` naming the missing
ones), then runs the ticks in lockstep: for tick k it sends each live agent
its own measurement (or none) on that agent's key, broadcasts every agent's
position and the live set, and waits for every live agent's fused estimate
of tick k, or ``--tick-timeout`` seconds. A report of a past tick is counted
("stale") and dropped. At the end it says stop, computes the metrics and
writes the same result JSON as ``experiment``:
``{algorithm: {setting: {mae_state, ...}}}``, plus, per setting, the link
faults of the run, every agent's message counters (``diskf_mesh.counters``)
and the ticks each agent did not report (``missing_ticks``: killed, or
rejoining); ``--estimates`` writes every agent's fused estimates, what was
missing, and every agent's counters.

An agent whose liveliness token goes (a crash, ``kill -9``) drops out of the
live set from the next tick on; the world goes on with the others. An agent
that comes back (same id) is live again from the tick after it is ready.

The report that completes tick k opens tick k+1 in zenoh's callback itself
(``World``); ``--profile DIR`` writes where each tick's time went
(``mesh.profile``).
"""
from __future__ import annotations

import argparse
import math
import sys
import threading
import time
from collections import Counter
from dataclasses import dataclass, field

import numpy as np

from diskf_mesh import metrics, wire
from diskf_mesh.algorithms.consensus_baselines import consensus_step_problem
from diskf_mesh.commands.options import positive_int, save_json, seed_value
from diskf_mesh.counters import Counters
from diskf_mesh.faults import FaultConfig
from diskf_mesh.faults import add_arguments as add_fault_arguments
from diskf_mesh.faults import from_args as faults_from_args
from diskf_mesh.engine import Estimates
from diskf_mesh.mesh import runspec, zenoh_config
from diskf_mesh.mesh.keys import Keys
from diskf_mesh.mesh.log import Log
from diskf_mesh.mesh.profile import NO_PHASES, WORLD_PHASES, Phases
from diskf_mesh.mesh.transport import MeshError, Transport, ZenohTransport
from diskf_mesh.recording.writer import NO_RECORDER, NoRecorder
from diskf_mesh.scenario import Scenario, simulate
from diskf_mesh.trace import Trace, estimates_to_json

ESTIMATES_FORMAT = "diskf-mesh-estimates/1"


@dataclass(frozen=True)
class WorldTiming:
    startup_timeout: float = 30.0  # for every agent to be ready
    tick_timeout: float = 10.0     # for the reports of one tick
    leave_timeout: float = 2.0     # after stop, for the agents to leave


@dataclass
class WorldRecord:
    """What the world heard. Arrays (K, N, ...), NaN where no report came."""

    ids: tuple
    x: np.ndarray
    P: np.ndarray
    d: np.ndarray
    d_valid: np.ndarray
    reported: np.ndarray                       # (K, N) bool
    agent_counters: dict = field(default_factory=dict)   # id -> counters of its last report
    counters: Counter = field(default_factory=Counter)   # the world's own
    startup_s: float = 0.0                     # start to tick 1
    ticks_s: float = 0.0                       # tick 1 to the last report

    def estimates(self, fill: bool = False) -> Estimates:
        """Batch of one; with ``fill`` missing entries are x = 0, P = I (for
        metrics, which mask them out)."""
        x, P, d = self.x, self.P, self.d
        if fill:
            miss = ~self.reported
            x, d = np.where(miss[..., None], 0.0, x), np.where(miss[..., None], 0.0, d)
            P = np.where(miss[..., None, None], np.eye(P.shape[-1]), P)
        return Estimates(x[None], P[None], d[None], self.d_valid[None])


POLL_S = 0.5  # the main thread looks at the tick's deadline at least this often
LINES_EVERY_S = 0.1  # --progress lines: at most one line this often (and ticks 1 and K)
HOLD_MS = 5   # a measurement waits at most this long in zenoh's batch for its tick (it comes at once)


class World:
    """The lockstep over a ``Transport``. ``run`` returns the ``WorldRecord``.

    Reports and liveliness changes are handled in the transport's callback
    (zenoh's network thread) under one lock (``_cv``): the report that
    completes tick k closes it and opens tick k+1 right there (measurements
    and tick out), with no hop to another thread. The main thread waits for
    the agents at the start, for a tick's deadline (``--tick-timeout``: the
    reports that did not come are counted missing), for the end and for the
    agents to leave after the stop."""

    def __init__(self, scn: Scenario, trace: Trace, algorithm: str, seed: int, keys: Keys, transport: Transport,
                 timing: WorldTiming = WorldTiming(), progress=None, log: Log | None = None,
                 profile: Phases = NO_PHASES, recorder: NoRecorder = NO_RECORDER):
        self.recorder = recorder  # diskf_mesh.recording: called at open, report, close
        self.scn, self.trace, self.algorithm, self.seed = scn, trace, algorithm, seed
        self.prof = profile
        self.keys, self.transport, self.timing = keys, transport, timing
        self.progress = progress
        self.log = log or Log("world")
        self.ids = tuple(a.id for a in scn.agents)
        self.p = scn.sensors().p
        self.alive, self.ready = set(), set()
        K, N = trace.has.shape[1:]
        self.K = K
        n, m = trace.model.n, trace.model.m
        self.record = WorldRecord(self.ids, np.full((K, N, n), np.nan), np.full((K, N, n, n), np.nan),
                                  np.full((K, N, m), np.nan), np.zeros((K, N), dtype=bool),
                                  np.zeros((K, N), dtype=bool))
        self.k = 0
        self.stopping = False
        self.done = False              # tick K is closed
        self.failure: BaseException | None = None  # raised in a callback, re-raised by the main thread
        self._cv = threading.Condition(threading.RLock())  # everything above, shared with the callbacks
        self._open = 0                 # k while the reports of tick k are being collected
        self._waiting = set()          # live (ready) agents whose report of tick k has not come yet
        self._deadline = math.inf      # end of tick k's collection (monotonic)
        self._main_looks_at = 0.0      # when the main thread looks at the deadline next

    # -- transport callbacks ---------------------------------------------------
    def _on_sample(self, key: str, payload) -> None:
        """A report, or a liveliness change (``payload`` True or False)."""
        self.prof.begin()
        try:
            with self._cv:
                kind, who = self.keys.parse(key)
                if kind == "report":
                    try:
                        self._on_report(who, payload)
                    except wire.Rejected as e:
                        self.record.counters[f"rejected:{e.reason}"] += 1
                        self.log.once(("report", who, e.reason), f"rejected a report from {key}: {e}")
                elif kind in ("alive", "ready") and who is not None:
                    self._on_token(kind, who, payload)
                self._advance()
        except BaseException as e:  # noqa: BLE001 - a callback must not swallow a failure
            with self._cv:
                self.failure = self.failure or e
                self._cv.notify_all()
        finally:
            self.prof.end("other")

    def _on_token(self, kind: str, who: int, alive: bool) -> None:
        if kind == "alive" and self.k and not self.stopping and (who in self.alive) != alive:
            self.log.info(f"tick {self.k}: agent {who} " + ("is back" if alive else "is gone (its liveliness "
                                                                                     "token went)"))
        group = self.alive if kind == "alive" else self.ready
        (group.add if alive else group.discard)(who)
        if kind == "alive" and not alive:
            self.ready.discard(who)
        if who not in self.ready:
            self._waiting.discard(who)  # gone: the tick does not wait for it
        self._cv.notify_all()

    def _on_report(self, sender, payload) -> None:
        if sender not in self.ids:
            raise wire.Rejected("sender", f"unknown agent {sender}")
        self.prof.begin()
        try:
            r = wire.decode_report(payload, run_id=self.keys.run_id, sender=sender,
                                   n=self.trace.model.n, m=self.trace.model.m)
        finally:
            self.prof.end("decode")
        i = self.ids.index(sender)
        if r.tick < self.k or (r.tick == self.k and not self._open):
            self.record.counters["stale"] += 1
        elif r.tick > self.k or self.record.reported[r.tick - 1, i]:
            self.record.counters["unexpected"] += 1
        else:
            rec = self.record
            rec.x[r.tick - 1, i], rec.P[r.tick - 1, i], rec.d[r.tick - 1, i] = r.x, r.P, r.d
            rec.d_valid[r.tick - 1, i] = r.d_valid
            rec.reported[r.tick - 1, i] = True
            rec.agent_counters[sender] = r.counters
            self._waiting.discard(sender)
            self.recorder.on_report(r)

    # -- the ticks (lock held) ---------------------------------------------------
    def _advance(self) -> None:
        """Close every tick whose reports are all in, opening the next."""
        while self._open and not self._waiting and self.failure is None:
            self._close_tick()

    def _open_tick(self, k: int) -> None:
        """Send each live agent its measurement of tick k, then the tick. The
        measurements are not express: each waits in its agent's link for the
        (express) tick, so an agent gets both in one write and wakes once."""
        tr, run, prof = self.trace, self.keys.run_id, self.prof
        live = [i for i in self.ids if i in self.ready]
        self.k = self._open = k
        self._waiting = set(live)
        self.recorder.on_open(k, live)
        prof.begin()
        out = [(self.keys.meas(i), wire.encode_measurement(run, k, i, bool(tr.has[0, k - 1, j]),
                                                           tr.y[0, k - 1, j, : self.p[j]]))
               for i, j in ((i, self.ids.index(i)) for i in live)]
        out.append((self.keys.tick, wire.encode_tick(wire.Tick(
            run, k, tr.has.shape[1], self.seed, self.algorithm, self.scn.topology, self.scn.comm_range,
            tr.positions[k - 1], tuple(live)))))
        prof.end("encode")
        prof.begin()
        for key, payload in out[:-1]:
            self.transport.put(key, payload, express=False)
        self.transport.put(*out[-1])
        prof.end("publish")
        prof.waiting = "wait-reports"
        self._deadline = time.monotonic() + self.timing.tick_timeout
        if self._deadline < self._main_looks_at:
            self._cv.notify_all()

    def _close_tick(self) -> None:
        """Tick k is over (every live agent reported, or its deadline passed):
        what did not come is missing; open tick k+1, or end."""
        k = self.k
        for i in sorted(self._waiting):
            self.record.counters["missing-report"] += 1
            self.log.once(("late", i), f"tick {k}: no report from agent {i} within {self.timing.tick_timeout:g} s")
        self.recorder.on_close(k, self._waiting)
        self._open, self._waiting, self._deadline = 0, set(), math.inf
        self.prof.tick()
        if self.progress is not None:
            self.progress(k)
        if k < self.K:
            self._open_tick(k + 1)
        else:
            self.done = True
            self._cv.notify_all()

    def _wait(self, until: float) -> None:
        """Main thread, lock held: sleep until notified or ``until``, at most ``POLL_S``."""
        now = time.monotonic()
        timeout = max(min(until, now + POLL_S), now) - now
        self._main_looks_at = now + timeout
        self._cv.wait(timeout)
        if self.failure is not None:
            raise self.failure

    # -- protocol ----------------------------------------------------------
    def start(self) -> None:
        self.transport.subscribe(f"{self.keys.root}/agent/*/report", self._on_sample)
        self.transport.watch_tokens(f"{self.keys.root}/*/agent/*", self._on_sample)
        self.transport.declare_token(self.keys.alive_world)

    def wait_agents(self) -> None:
        t0 = time.monotonic()
        deadline = t0 + self.timing.startup_timeout
        with self._cv:
            while not self.ready >= set(self.ids):
                if time.monotonic() >= deadline:
                    absent = [i for i in self.ids if i not in self.alive]
                    stuck = [i for i in self.ids if i in self.alive and i not in self.ready]
                    parts = []
                    if absent:
                        parts.append(f"no agent process for id {', '.join(map(str, absent))} (no liveliness token)")
                    if stuck:
                        parts.append(f"agent {', '.join(map(str, stuck))} up but not connected to every peer")
                    raise MeshError(f"after {self.timing.startup_timeout:g} s waiting for the agents: "
                                    + "; ".join(parts))
                self._wait(deadline)

    def run_ticks(self) -> None:
        """Tick 1 to K, in lockstep (the callbacks drive it; the main thread
        closes a tick at its deadline)."""
        with self._cv:
            self._open_tick(1)
            self._advance()
            while not self.done:
                if time.monotonic() >= self._deadline:
                    self._close_tick()
                    self._advance()
                    continue
                self._wait(self._deadline)

    def stop(self, why: str) -> None:
        with self._cv:
            self.stopping = True
            self._open = 0
        self.transport.put(self.keys.stop, wire.encode_stop(self.keys.run_id, self.k, why))
        deadline = time.monotonic() + self.timing.leave_timeout
        with self._cv:
            while self.alive and time.monotonic() < deadline:
                self._cv.wait(max(0.0, min(deadline - time.monotonic(), POLL_S)))

    def run(self) -> WorldRecord:
        t0 = time.monotonic()
        self.start()
        self.wait_agents()
        t1 = time.monotonic()
        self.record.startup_s = t1 - t0
        self.transport.declare_token(self.keys.ticking)  # an agent starting from now on is rejoining
        self.prof.start()
        try:
            self.run_ticks()
        finally:
            self.prof.stop()
            self.record.ticks_s = time.monotonic() - t1
            self.stop("done" if self.done else "world stopped")
        return self.record


# --------------------------------------------------------------------------
# results
# --------------------------------------------------------------------------
def result_metrics(trace: Trace, rec: WorldRecord) -> dict:
    """The metrics of ``experiment`` over the agent-ticks that were reported
    (a single seed, so every spread ``<metric>_std`` is 0)."""
    row = metrics.summarize(*metrics.errors(trace, rec.estimates(fill=True)), mask=rec.reported[None])
    row.update({f"{k}_std": 0.0 for k in metrics.METRIC_KEYS})
    return row


def run_summary(rec: WorldRecord, faults: FaultConfig) -> dict:
    """The run's faults, every agent's counters (its last report's; a
    restarted agent's count from its restart) and the ticks it did not report."""
    out = {"faults": faults.to_dict(), "counters": {}, "missing_ticks": {}}
    for j, i in enumerate(rec.ids):
        c = Counters.from_dict(rec.agent_counters.get(i, {}))
        out["counters"][str(i)] = c.to_json()
        if c.imbalance():
            out["counters"][str(i)]["imbalance"] = c.imbalance()
        missing = (1 + np.flatnonzero(~rec.reported[:, j])).tolist()
        if missing:
            out["missing_ticks"][str(i)] = missing
    return out


def estimates_doc(rec: WorldRecord, algorithm: str, scn: Scenario, seed: int, run_id: str, row: dict) -> dict:
    doc = estimates_to_json(rec.estimates(), algorithm, metrics=row)
    doc.update(format=ESTIMATES_FORMAT, scenario=scn.name, seed=seed, run_id=run_id, ids=list(rec.ids),
               reported=rec.reported.tolist(), agent_counters={str(k): v for k, v in rec.agent_counters.items()},
               world_counters=dict(rec.counters), startup_s=rec.startup_s, ticks_s=rec.ticks_s)
    return doc


def open_recorder(path, trace, scn, spec, seed, faults):
    from diskf_mesh.errors import InputError
    from diskf_mesh.recording.writer import Recorder

    try:
        return Recorder(path, trace, scn, scenario=spec.scenario, algorithm=spec.algorithm, seed=seed,
                        run_id=spec.run_id, faults=faults)
    except OSError as e:
        raise InputError("record", f"cannot write {path}: {e.strerror or e}") from None


# --------------------------------------------------------------------------
# command line
# --------------------------------------------------------------------------
PROGRESS = ("bar", "lines", "none")


def register(subparsers) -> None:
    p = subparsers.add_parser("world", help="the world process of a mesh run (ground truth, lockstep)",
                              description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    runspec.add_arguments(p)
    p.add_argument("--ticks", type=positive_int, metavar="K", help="ticks to run (default: the scenario's steps)")
    p.add_argument("--seed", type=seed_value, default=0, metavar="S", help="simulation seed (default 0)")
    p.add_argument("--json", metavar="OUT", help="write the results {algorithm: {setting: metrics}}")
    p.add_argument("--estimates", metavar="OUT", help="write every agent's fused estimates and counters")
    p.add_argument("--record", metavar="FILE.mcap", help="record the run as MCAP (diskf_mesh.recording)")
    p.add_argument("--startup-timeout", type=float, default=WorldTiming.startup_timeout, metavar="S",
                   help="seconds to wait for every agent (default %(default)s)")
    p.add_argument("--tick-timeout", type=float, default=WorldTiming.tick_timeout, metavar="S",
                   help="seconds to wait for the reports of one tick (default %(default)s)")
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
    from tqdm import tqdm

    from diskf_mesh.experiment import format_table

    spec = runspec.from_args(args)
    scn = spec.load(args.ticks)
    faults = faults_from_args(args, scn.faults)  # the agents apply them; the world records them
    trace = simulate(scn, [args.seed])
    K = trace.has.shape[1]
    log = Log("world")
    if spec.algorithm == "kcf" and (problem := consensus_step_problem(scn.params.consensus_eps, trace.links)):
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
    recorder = open_recorder(args.record, trace, scn, spec, args.seed, faults) if args.record else NO_RECORDER
    try:
        with ZenohTransport(zenoh_config.from_args(args), hold_ms=HOLD_MS) as transport:
            world = World(scn, trace, spec.algorithm, args.seed, Keys(spec.run_id), transport,
                          WorldTiming(args.startup_timeout, args.tick_timeout), progress, log, prof, recorder)
            rec = world.run()
    except MeshError as e:
        log.error(str(e))
        recorder.finish(f"failed: {e}")
        return 1
    finally:
        bar.close()
        if prof:
            prof.write(args.profile, "world")
    row = result_metrics(trace, rec)
    recorder.finish("done" if world.done else "stopped", row)
    summary = run_summary(rec, faults)
    results = {spec.algorithm: {runspec.setting_label(scn): {**row, **summary}}}
    if args.json:
        save_json(args.json, results, "json")
    if args.estimates:
        doc = estimates_doc(rec, spec.algorithm, scn, args.seed, spec.run_id, row)
        doc.update(faults=summary["faults"], missing_ticks=summary["missing_ticks"])
        save_json(args.estimates, doc, "estimates")
    for i, c in summary["counters"].items():
        if "imbalance" in c:
            log.info(f"agent {i}'s message counters do not add up: {'; '.join(c['imbalance'])}")
    missing = int((~rec.reported).sum())
    if missing:
        log.info(f"{missing} of {rec.reported.size} agent-ticks had no report; metrics cover the rest")
    if args.progress != "lines":
        print(format_table(results))
    return 0


if __name__ == "__main__":
    from diskf_mesh import cli

    sys.exit(cli.run_one("world", __spec__.name))
