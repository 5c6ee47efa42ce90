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
faults of the run, every agent's message counters (``diskf_mesh.mesh.counters``)
and the ticks each agent did not report (``missing_ticks``: killed, or
rejoining); ``--estimates`` writes every agent's fused estimates, what was
missing, and every agent's counters.

An agent whose liveliness token goes (a crash, ``kill -9``, a freeze past
zenoh's lease) drops out of the live set from the next tick on; the world
goes on with the others. An agent that comes back (same id: a restart, or a
frozen process that woke) is live again from the tick after next once it is
ready with a new token; an old ready token that reappears (a frozen
process's, re-announced by zenoh when it reconnects) does not count.

The world does not run on alone. If it was frozen itself (its main thread
wakes long after it should), or every agent is gone, it pauses: it keeps the
open tick open and waits up to ``--startup-timeout`` for the agents that were
live to come back (an agent that comes back while it pauses is live again at
once), then sends that tick again (agents that had reported it send their
report again). If none comes back the run ends early.

Exit status: 0 only if every agent reported every tick (``complete``), or
the share of missing agent-ticks is within ``--allow-missing``; else 3 with
one line: how many agent-ticks are missing, of which agents, and why (never
joined, left, rejoining, no report, rejected, not run). The result JSON
holds what was measured either way, with ``complete``, the missing counts,
the rejoins (tick and re-initialisation source), duplicate processes and
pauses. 2: another world already runs this run id (``mesh.keys`` nonces).

The report that completes tick k opens tick k+1 in zenoh's callback itself
(``World``, a ``diskf_mesh.mesh.process.Process``: that module's docstring
follows one tick world -> agent -> neighbour -> world through this code);
``--profile DIR`` writes where each tick's time went (``mesh.profile``).
"""
from __future__ import annotations

import argparse
import math
import signal
import sys
import time
from collections import Counter
from dataclasses import asdict, dataclass, field

import numpy as np

from diskf_mesh.data import metrics
from diskf_mesh.mesh import wire
from diskf_mesh import estimators
from diskf_mesh.data.argtypes import fraction, positive_int, seed_value
from diskf_mesh.data import provenance
from diskf_mesh.data.outputs import check_output, save_json
from diskf_mesh.mesh.counters import Counters
from diskf_mesh.data.faults import FaultConfig
from diskf_mesh.data.faults import add_arguments as add_fault_arguments
from diskf_mesh.data.faults import from_args as faults_from_args
from diskf_mesh.mesh.reports import RunReports
from diskf_mesh.mesh import clock as realtime
from diskf_mesh.mesh import credentials
from diskf_mesh.mesh import runspec
from diskf_mesh.mesh import zenoh_config
from diskf_mesh.mesh.keys import Keys, nonce
from diskf_mesh.mesh.log import Log
from diskf_mesh.mesh.process import FREEZE_S, POLL_S, Process
from diskf_mesh.mesh.profile import NO_PHASES, WORLD_PHASES, Phases
from diskf_mesh.mesh.transport import DuplicateProcess, MeshError, Transport, ZenohTransport
from diskf_mesh.recording.writer import NO_RECORDER, NoRecorder
from diskf_mesh.data.scenario import Scenario, simulate
from diskf_mesh.data.trace import MESH_ESTIMATES_FORMAT, Trace, estimates_to_json



@dataclass(frozen=True)
class WorldTiming:
    startup_timeout: float = 30.0  # for every agent to be ready
    tick_timeout: float = 10.0     # for the reports of one tick (real time: of every tick, after the last)
    leave_timeout: float = 2.0     # after stop, for the agents to leave
    clock: realtime.Clock | None = None  # real time (``mesh.clock``); None: lockstep


@dataclass
class Deadlines:
    """A real-time run's clock and deadline misses, per agent id."""

    opened_at: list = field(default_factory=list)       # monotonic time each tick opened
    report_misses: Counter = field(default_factory=Counter)  # live, no report by the tick's end
    late_reports: Counter = field(default_factory=Counter)   # of those, came later (taken, counted)
    message_misses: Counter = field(default_factory=Counter)  # neighbours' messages not in by the deadline
    messages_due: Counter = field(default_factory=Counter)    # neighbours' messages linked (fused or not)
    reports_due: Counter = field(default_factory=Counter)     # live agent-ticks
    late_by: list = field(default_factory=list)               # seconds after its tick's end each late report came


@dataclass
class WorldRecord(RunReports):
    """What the world heard: the reports (``RunReports``; its ``fused``
    without the diagonal), and what else it saw of the run."""

    ids: tuple = ()
    agent_counters: dict = field(default_factory=dict)   # id -> counters of its last report
    counters: Counter = field(default_factory=Counter)   # the world's own
    startup_s: float = 0.0                     # start to tick 1
    ticks_s: float = 0.0                       # tick 1 to the last report
    why: np.ndarray | None = None              # (K, N) why an agent-tick is missing ("" if reported or not run)
    rejoins: dict = field(default_factory=dict)        # id -> [{"tick", "source"}]
    duplicates: Counter = field(default_factory=Counter)  # id (or "world") -> extra processes seen
    pauses: list = field(default_factory=list)         # [{"tick", "why", "seconds"}]
    ended_early: str = ""                      # why the run ended before tick K, if it did
    deadlines: Deadlines | None = None         # real time only
    labels: tuple = ()                         # the ids as the scenario gave them (results show these)

    def label(self, i):
        """Agent ``i``'s id as the scenario gave it (``i`` itself if unknown)."""
        return self.labels[self.ids.index(i)] if self.labels and i in self.ids else i


PAUSE_MIN_S = 1.0  # a pause lasts at least this long (the links that closed while frozen close on waking)
LATE_READY_S = 5.0  # --allow-missing: after the startup timeout, how long the agents up have to be ready
LINES_EVERY_S = 0.1  # --progress lines: at most one line this often (and ticks 1 and K)
HOLD_MS = 5   # a measurement waits at most this long in zenoh's batch for its tick (it comes at once)


class World(Process):
    """The lockstep over a ``Transport`` (a ``mesh.process``: steps 1 and 6
    of a tick). ``run`` returns the ``WorldRecord``.

    Reports and liveliness changes are handled in the transport's callback
    (zenoh's network thread) under one lock (``_cv``, ``_take_in``): the report that
    completes tick k closes it and opens tick k+1 right there (measurements
    and tick out), with no hop to another thread. The main thread waits for
    the agents at the start, for a tick's deadline (``--tick-timeout``: the
    reports that did not come are counted missing), for the end and for the
    agents to leave after the stop."""

    def __init__(self, scn: Scenario, trace: Trace, algorithm: str, seed: int, keys: Keys, transport: Transport,
                 timing: WorldTiming = WorldTiming(), progress=None, log: Log | None = None,
                 profile: Phases = NO_PHASES, recorder: NoRecorder = NO_RECORDER):
        super().__init__(keys, transport, log or Log("world"), profile)
        self.recorder = recorder  # diskf_mesh.recording: called at open, report, close
        self.scn, self.trace, self.algorithm, self.seed = scn, trace, algorithm, seed
        self.timing = timing
        self.progress = progress
        self.ids = tuple(a.id for a in scn.agents)
        self.p = scn.sensors().p
        self.alive, self.ready = set(), set()
        self._tokens = {"alive": {}, "ready": {}}  # kind -> id -> nonces held
        self._gone_ready = {}          # id -> ready nonces that went (they do not count again)
        self._joins_at = {}            # id -> first tick a (re)joining agent is live at
        self._why = dict.fromkeys(self.ids, "never joined")  # id -> why it is not live (None: live)
        self._rejected = set()         # ids whose report of the open tick was rejected
        K, N = trace.has.shape[1:]
        self.K = K
        n, m = trace.model.n, trace.model.m
        self.record = WorldRecord(**RunReports.empty(K, N, n, m), ids=self.ids, why=np.full((K, N), "", dtype=object),
                                  labels=scn.labels, deadlines=None if timing.clock is None else Deadlines())
        self._index = {i: j for j, i in enumerate(self.ids)}
        self.clock = timing.clock
        self._owed = {}                # real time: tick -> live agents whose report has not come yet
        self._ended = 0                # real time: the last tick whose end has passed
        self._unrecorded = 1           # real time: the first tick not handed to the recorder yet
        self.k = 0
        self.stopping = False
        self.done = False              # tick K is closed
        self._open = 0                 # k while the reports of tick k are being collected
        self._waiting = set()          # live (ready) agents whose report of tick k has not come yet
        self._deadline = math.inf      # end of tick k's collection (monotonic)
        self._live_at_open = ()        # the live set of the open tick
        self._sent = []                # [(key, payload)] that opened it (sent again after a pause)
        self._paused = ""              # why the ticks are paused ("" if not)
        self._paused_at = 0.0
        self._expect = set()           # the agents a pause waits for
        self._pending = 0              # the tick to open after a pause (0: the open tick goes on)
        self.interrupted = ""          # a signal's name: end the run early (the main thread looks)
        self._ticking = False          # the "ticking" token is declared

    # -- transport callbacks ---------------------------------------------------
    def _take_in(self, key: str, payload) -> None:
        """Lock held: a report, or a liveliness change (``payload`` True or False)."""
        if (self._open and not self._paused and self.clock is None
                and time.monotonic() - self._main_looks_at > FREEZE_S):
            self._pause("the world was frozen", self._live_at_open)
        kind, who = self.keys.parse(key)
        if kind == "report":
            try:
                self._on_report(who, payload)
            except wire.Rejected as e:
                self.record.counters[f"rejected:{e.reason}"] += 1
                if who in self.ids:
                    self._rejected.add(who)
                self.log.once(("report", who if who in self.ids else None, e.reason),
                              f"rejected a report from {key[:200]}: {e}")
        elif kind == "rejoin" and who in self.ids:
            try:
                r = wire.decode_rejoin(payload, run_id=self.keys.run_id, sender=who)
                self.record.rejoins.setdefault(who, []).append({"tick": r.tick, "source": r.source})
            except wire.Rejected as e:
                self.record.counters[f"rejected:{e.reason}"] += 1
        elif kind == "duplicate" and who in self.ids:
            self.record.duplicates[who] += 1
            self.log.info(f"agent id {who}: a second process (nonce {bytes(payload[:32]).decode(errors='replace')})"
                          " found this id held and leaves: duplicate id")
        elif kind in ("alive", "ready") and who is not None:
            self._on_token(kind, who, nonce(key), payload)
        elif kind == "alive-world":
            self._on_world_token(nonce(key), payload)
        self._advance()

    def _on_token(self, kind: str, who: int, nonce_: str, up: bool) -> None:
        """An agent's alive or ready token (one per process: ``nonce_``) came
        or went. A second process's alive token for one id is a duplicate
        (logged, counted; the later one leaves by itself). A ready token that
        went does not count if it comes back, except while the world pauses
        (zenoh re-announces the tokens of a process that reconnects: a
        frozen agent rejoins with a new one)."""
        if who not in self.ids:
            return
        held = self._tokens[kind].setdefault(who, set())
        gone = self._gone_ready.setdefault(who, set())
        if up:
            if kind == "ready" and nonce_ in gone and not self._paused:
                return
            if kind == "alive" and held and nonce_ not in held:
                self.record.duplicates[who] += 1
                self.log.info(f"agent id {who}: a second process (token {nonce_}) besides {min(held)}: duplicate id")
            held.add(nonce_)
        else:
            held.discard(nonce_)
            if kind == "ready":
                gone.add(nonce_)
        was_alive, was_ready = who in self.alive, who in self.ready
        alive = bool(self._tokens["alive"].get(who))
        ready = alive and bool(self._tokens["ready"].get(who))
        (self.alive.add if alive else self.alive.discard)(who)
        (self.ready.add if ready else self.ready.discard)(who)
        if self.k and not self.stopping and was_alive != alive:
            self.log.info(f"tick {self.k}: agent {who} " + ("is back" if alive else "is gone (its liveliness "
                                                                                     "token went)"))
        if ready and not was_ready and self.k and not (self._paused and who in self._expect):
            self._joins_at[who] = self.k + 2  # its first tick: the reports of the one before reach it
            self._why[who] = "rejoining"
        if not ready and was_ready:
            self._why[who] = "left"
            if not self._paused:
                self._waiting.discard(who)  # gone: the tick does not wait for it
            for owed in self._owed.values():
                owed.discard(who)
        self._cv.notify_all()

    def _on_world_token(self, nonce_: str, up: bool) -> None:
        """Another world's token in this run id: the later started of two
        leaves (the other counts it)."""
        if nonce_ == self.nonce or not up:
            return
        if nonce_ < self.nonce:
            self.failure = self.failure or DuplicateProcess(
                f"another world runs run id {self.keys.run_id!r} (token nonce {nonce_}, started earlier): "
                "this one leaves; give each run its own --run-id")
        else:
            self.record.duplicates["world"] += 1
            self.log.info(f"a second world (token {nonce_}) in run id {self.keys.run_id!r}: it leaves")

    def _on_report(self, sender, payload) -> None:
        if sender not in self.ids:
            raise wire.Rejected("sender", f"unknown agent {sender}")
        self.prof.begin()
        try:
            r = wire.decode_report(payload, run_id=self.keys.run_id, sender=sender,
                                   n=self.trace.model.n, m=self.trace.model.m, ticks=self.K, agents=len(self.ids))
        finally:
            self.prof.end("decode")
        i = self._index[sender]
        if self.clock is not None:
            self._on_clocked_report(r, i)
        elif r.tick < self.k or (r.tick == self.k and not self._open):
            self.record.counters["stale"] += 1
        elif r.tick > self.k or self.record.reported[r.tick - 1, i]:
            self.record.counters["unexpected"] += 1
        else:
            self._waiting.discard(sender)
            self._take(r, i)

    def _take(self, r: wire.Report, i: int) -> None:
        """Record agent ``r.sender``'s (index ``i``) report of its tick."""
        rec, t = self.record, r.tick - 1
        rec.x[t, i], rec.P[t, i], rec.d[t, i] = r.x, r.P, r.d
        rec.d_valid[t, i] = r.d_valid
        rec.reported[t, i] = True
        rec.agent_counters[r.sender] = r.counters
        row = rec.fused[t, i]
        for s in r.fused:
            j = self._index.get(s)
            if j is not None:
                row[j] = True
        self.recorder.on_report(r)

    def _on_clocked_report(self, r: wire.Report, i: int) -> None:
        """Real time: a report owed for its tick is taken whenever it comes;
        after the tick's end it counts late. Its messages not fused in time
        (verdict "late") are message deadline misses."""
        owed = self._owed.get(r.tick)
        if owed is None or r.sender not in owed:
            self.record.counters["stale" if r.tick <= self.k else "unexpected"] += 1
            return
        owed.discard(r.sender)
        dl = self.record.deadlines
        if r.tick != self._open:  # its tick has ended
            dl.late_reports[r.sender] += 1
            dl.late_by.append(time.monotonic() - dl.opened_at[r.tick - 1] - self.clock.period_s)
            self.record.why[r.tick - 1, i] = ""
        dl.message_misses[r.sender] += sum(1 for _, v in r.not_fused if v == "late")
        dl.messages_due[r.sender] += len(r.fused) + len(r.not_fused)
        self._take(r, i)
        self._to_recorder()
        if self._ended >= self.K and not any(self._owed.values()):
            self._cv.notify_all()  # the last report owed: the run is over

    # -- the ticks (lock held) ---------------------------------------------------
    def _advance(self) -> None:
        """Close every tick whose reports are all in, opening the next (real
        time: the clock does)."""
        while self.clock is None and self._open and not self._waiting and self.failure is None and not self._paused:
            self._close_tick()

    def _live(self, k: int) -> list:
        return [i for i in self.ids if i in self.ready and self._joins_at.get(i, 0) <= k]

    def _open_tick(self, k: int) -> None:
        """Send each live agent its measurement of tick k, then the tick. The
        measurements are not express: each waits in its agent's link for the
        (express) tick, so an agent gets both in one write and wakes once."""
        tr, run, prof = self.trace, self.keys.run_id, self.prof
        live = self._live(k)
        self.k = self._open = k
        self._waiting = set(live)
        self._live_at_open = tuple(live)
        self._rejected = set()
        if self.clock is not None:
            self._owed[k] = set(live)
            self.record.deadlines.reports_due.update(live)
        for j, i in enumerate(self.ids):
            if i in live:
                self._why[i] = None
            else:
                self.record.why[k - 1, j] = self._why[i] or "left"
        self.recorder.on_open(k, live)
        prof.begin()
        out = [(self.keys.meas(i), wire.encode_measurement(run, k, i, bool(tr.has[0, k - 1, j]),
                                                           tr.y[0, k - 1, j, : self.p[j]]))
               for i, j in ((i, self.ids.index(i)) for i in live)]
        out.append((self.keys.tick, wire.encode_tick(wire.Tick(
            run, k, tr.has.shape[1], self.seed, self.algorithm, self.scn.topology, self.scn.comm_range,
            tr.positions[k - 1], tuple(live)))))
        prof.end("encode")
        self._sent = out
        prof.begin()
        self._publish(out)
        prof.end("publish")
        prof.waiting = "wait-reports"
        self._deadline = time.monotonic() + self.timing.tick_timeout
        if self._deadline < self._main_looks_at:
            self._cv.notify_all()

    def _publish(self, out: list) -> None:
        for key, payload in out[:-1]:
            self.transport.put(key, payload, express=False)
        self.transport.put(*out[-1])

    def _close_tick(self) -> None:
        """Tick k is over (every live agent reported, or its deadline passed):
        what did not come is missing; open tick k+1 (or pause, if every agent
        is gone), or end."""
        k = self.k
        for j, i in enumerate(self.ids):
            if i in self._live_at_open and not self.record.reported[k - 1, j]:
                self.record.why[k - 1, j] = ("rejected" if i in self._rejected else
                                             "left" if i not in self.ready else "no report")
        for i in sorted(self._waiting):
            self.record.counters["missing-report"] += 1
            self.log.once(("late", i), f"tick {k}: no report from agent {i} within {self.timing.tick_timeout:g} s")
        self.recorder.on_close(k, self._waiting)
        self._open, self._waiting, self._deadline = 0, set(), math.inf
        self.prof.tick()
        if self.progress is not None:
            self.progress(k)
        if k >= self.K:
            self.done = True
            self._cv.notify_all()
        elif not self._live(k + 1) and not self.ready:
            self._pending = k + 1
            self._pause("every agent is gone", self._live_at_open)
        else:
            self._open_tick(k + 1)

    # -- pauses (lock held) ----------------------------------------------------
    def _pause(self, why: str, expect) -> None:
        """Stop ticking until the agents ``expect`` are back (``_resume``)."""
        self._paused, self._paused_at, self._expect = why, time.monotonic(), set(expect)
        self.log.info(f"tick {self.k}: {why}: waiting up to {self.timing.startup_timeout:g} s for agents "
                      f"{', '.join(map(str, sorted(self._expect))) or '(none)'} to come back")
        self._cv.notify_all()

    def _resume(self) -> None:
        """Main thread: end the pause. The open tick is sent again (to the
        agents that missed it; one that had reported it sends its report
        again) with a new deadline; or the tick after a run without agents
        opens; or, if no agent came back, the run ends early."""
        now = time.monotonic()
        self.record.pauses.append({"tick": self.k, "why": self._paused, "seconds": round(now - self._paused_at, 3)})
        self.log.info(f"tick {self.k}: resuming after {now - self._paused_at:.1f} s with agents "
                      f"{', '.join(map(str, sorted(self.ready))) or '(none)'}")
        self._paused, self._expect = "", set()
        if not self.ready:
            self.record.ended_early = f"no agent came back within {self.timing.startup_timeout:g} s"
            self._open, self._waiting = 0, set()
            self.done = True
            return
        if self._pending:
            k, self._pending = self._pending, 0
            self._open_tick(k)
            return
        k = self.k
        self._waiting = {i for i in self._live_at_open
                         if i in self.ready and not self.record.reported[k - 1, self.ids.index(i)]}
        self._publish(self._sent)
        self._deadline = now + self.timing.tick_timeout
        self._advance()

    def _pause_over(self) -> bool:
        now = time.monotonic()
        if now - self._paused_at < PAUSE_MIN_S:
            return False
        return self._expect <= self.ready or now - self._paused_at >= self.timing.startup_timeout

    def _woke(self, late: float) -> None:
        """Main thread, after a wait: a callback's failure is raised; waking
        much later than planned (frozen) pauses the ticks."""
        self._raise_failure()
        if late > FREEZE_S and self._open and not self._paused and self.clock is None:
            self._pause("the world was frozen", self._live_at_open)

    # -- protocol ----------------------------------------------------------
    def start(self) -> None:
        """Subscribe, watch the tokens, and declare this world's token unless
        another world of this run id holds one (exit 2)."""
        root = self.keys.root
        self.transport.subscribe(f"{root}/agent/*/report", self._on_sample)
        self.transport.subscribe(f"{root}/agent/*/rejoin", self._on_sample)
        self.transport.subscribe(f"{root}/agent/*/duplicate", self._on_sample)
        self.transport.watch_tokens(f"{root}/*/agent/*/*", self._on_sample)
        self.transport.watch_tokens(self.keys.alive_world, self._on_sample)
        others = self._other_nonces(self.keys.alive_world)
        if others:
            raise DuplicateProcess(f"another world runs run id {self.keys.run_id!r} (token nonce {min(others)}): "
                                   "give each run its own --run-id")
        self.transport.declare_token(self.keys.world(self.nonce))

    def wait_agents(self, allow_missing: bool = False) -> None:
        """Until every agent is ready; after ``--startup-timeout`` fail naming
        the missing ones, or (``allow_missing``) start with the agents up:
        the world declares its ``ticking`` token (they stop waiting for the
        missing peers and declare ready, as a restart does) and starts with
        those ready ``LATE_READY_S`` later."""
        t0 = time.monotonic()
        deadline = t0 + self.timing.startup_timeout
        with self._cv:
            while not self.ready >= set(self.ids):
                if self.interrupted:
                    self.record.ended_early = f"interrupted ({self.interrupted}) before tick 1"
                    return
                if time.monotonic() >= deadline and allow_missing and self.alive:
                    break
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
            else:
                return
        self._declare_ticking()
        late = time.monotonic() + LATE_READY_S
        with self._cv:
            self._wait_until(lambda: self.ready >= self.alive, late)
            if not self.ready:
                raise MeshError(f"no agent ready {self.timing.startup_timeout + LATE_READY_S:g} s after the start")
            self.log.info(f"starting without agent {', '.join(str(i) for i in self.ids if i not in self.ready)}"
                          f" (not ready after {self.timing.startup_timeout:g} s; --allow-missing)")

    def _declare_ticking(self) -> None:
        if not self._ticking:
            self._ticking = True
            self.transport.declare_token(self.keys.ticking)  # an agent starting from now on is rejoining

    def run_ticks(self) -> None:
        """Tick 1 to K, in lockstep (the callbacks drive it; the main thread
        closes a tick at its deadline), or on the clock."""
        if self.clock is not None:
            return self._run_clocked()
        with self._cv:
            self._open_tick(1)
            self._advance()
            while not self.done:
                if self.interrupted:
                    self.record.ended_early = f"interrupted ({self.interrupted})"
                    break
                if self._paused:
                    if self._pause_over():
                        self._resume()
                        continue
                    self._wait(self._paused_at + PAUSE_MIN_S if time.monotonic() - self._paused_at < PAUSE_MIN_S
                               else self._paused_at + self.timing.startup_timeout)
                    continue
                if time.monotonic() >= self._deadline:
                    self._close_tick()
                    self._advance()
                    continue
                self._wait(self._deadline)

    # -- real time (lock held; ``mesh.clock``) ------------------------------------
    def _run_clocked(self) -> None:
        """Main thread: tick k opens at t0 + (k - 1) / HZ and ends when tick
        k + 1 opens, whatever came in; after the last tick's end, the reports
        still owed have ``--tick-timeout`` to come."""
        period = self.clock.period_s
        with self._cv:
            t0 = time.monotonic()
            for k in range(1, self.K + 2):
                due = t0 + (k - 1) * period
                self._wait_until(lambda: self.interrupted, due)
                if self.interrupted:
                    self.record.ended_early = f"interrupted ({self.interrupted})"
                    break
                if k > 1:
                    self._end_tick(k - 1)
                if k <= self.K:
                    self.record.deadlines.opened_at.append(time.monotonic())
                    self._open_tick(k)
            grace = time.monotonic() + self.timing.tick_timeout
            self._wait_until(lambda: not any(self._owed.values()) or self.interrupted, grace)
            self._to_recorder(final=True)
            self.done = not self.record.ended_early

    def _end_tick(self, k: int) -> None:
        """Real time: tick k's end. A live agent whose report is not in
        misses its deadline (its report may still come: ``late_reports``)."""
        dl = self.record.deadlines
        for i in sorted(self._owed.get(k, ())):
            j = self._index[i]
            self.record.why[k - 1, j] = "rejected" if i in self._rejected else "no report"
            dl.report_misses[i] += 1
        self._open, self._ended = 0, k
        self.prof.tick()
        if self.progress is not None:
            self.progress(k)
        self._to_recorder()

    def _to_recorder(self, final: bool = False) -> None:
        """Real time: hand the recorder every ended tick, in order, once its
        reports are all in (or ``LEAD_TICKS`` later, or at the end: the
        rest are missing). An agent further behind than that is out of the
        run anyway (``mesh.clock``)."""
        while self._unrecorded <= self._ended:
            k = self._unrecorded
            if self._owed.get(k) and not final and k >= self._ended - realtime.LEAD_TICKS:
                return
            self.recorder.on_close(k, self._owed.pop(k, set()))
            self._unrecorded += 1

    def stop(self, why: str) -> None:
        with self._cv:
            self.stopping = True
            self._open = 0
        self.transport.put(self.keys.stop, wire.encode_stop(self.keys.run_id, self.k, why))
        deadline = time.monotonic() + self.timing.leave_timeout
        with self._cv:
            while self.alive and time.monotonic() < deadline:
                self._cv.wait(max(0.0, min(deadline - time.monotonic(), POLL_S)))

    def run(self, allow_missing: bool = False) -> WorldRecord:
        """The whole run; ``allow_missing``: start without the agents not
        ready after ``--startup-timeout`` (they never joined)."""
        t0 = time.monotonic()
        self.start()
        self.wait_agents(allow_missing)
        t1 = time.monotonic()
        self.record.startup_s = t1 - t0
        if self.record.ended_early:
            self.stop(self.record.ended_early)
            return self.record
        self._declare_ticking()
        self.prof.start()
        try:
            self.run_ticks()
        finally:
            self.prof.stop()
            self.record.ticks_s = time.monotonic() - t1
            self.stop("done" if self.done and not self.record.ended_early else
                      self.record.ended_early or "world stopped")
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
    """One line of what ``completeness`` found missing."""
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


def fused_lists(rec: WorldRecord) -> list:
    """K x N: the ids whose messages agent i fused at tick k (empty where it
    did not report)."""
    ids = rec.ids
    return [[[ids[s] for s in np.flatnonzero(row).tolist()] for row in tick] for tick in rec.fused]


def estimates_doc(rec: WorldRecord, algorithm: str, scn: Scenario, seed: int, run_id: str, row: dict) -> dict:
    doc = estimates_to_json(rec.estimates(), algorithm, metrics=row)
    doc.update(format=MESH_ESTIMATES_FORMAT, scenario=scn.name, seed=seed, run_id=run_id, ids=list(scn.labels),
               reported=rec.reported.tolist(),
               agent_counters={str(rec.label(k)): v for k, v in rec.agent_counters.items()},
               world_counters=dict(rec.counters), startup_s=rec.startup_s, ticks_s=rec.ticks_s,
               fused=fused_lists(rec), estimator=asdict(scn.params))
    return doc


def open_recorder(path, trace, scn, spec, seed, faults, prov=None):
    from diskf_mesh.core.errors import InputError
    from diskf_mesh.recording.writer import Recorder

    try:
        return Recorder(path, trace, scn, scenario=spec.scenario, algorithm=spec.algorithm, seed=seed,
                        run_id=spec.run_id, faults=faults, provenance=prov)
    except OSError as e:
        raise InputError("record", f"cannot write {path}: {e.strerror or e}") from None


# --------------------------------------------------------------------------
# command line
# --------------------------------------------------------------------------
PROGRESS = ("bar", "lines", "none")
INCOMPLETE = 3  # exit status of a run with missing agent-ticks beyond --allow-missing


def add_allow_missing(p) -> None:
    p.add_argument("--allow-missing", type=fraction, default=0.0, metavar="FRACTION",
                   help="accept a run that misses at most this share of its agent-ticks (exit 0; the results "
                        "still say complete: false); with it, the run also starts without agents not ready "
                        "after --startup-timeout (default 0: every agent reports every tick, or exit 3)")


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
    add_allow_missing(p)
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
    from tqdm import tqdm

    from diskf_mesh.studies.experiment import format_table

    check_output(args.json, "json", stdout=False)  # before any work: a bad path must not cost the run
    check_output(args.estimates, "estimates", stdout=False)
    check_output(args.record, "record", stdout=False)
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
    clock = realtime.from_args(args)
    zenoh = zenoh_config.from_args(args, credentials.WORLD, spec.run_id)
    faults = faults_from_args(args, scn.faults)  # the agents apply them; the world records them
    trace = simulate(scn, [args.seed])
    K = trace.has.shape[1]
    log = Log("world")
    if problem := estimators.get(spec.algorithm).warning(scn.params, trace.links):
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
    prov = provenance.record(scenario=scn, seeds=[args.seed], ticks=K, estimator=spec.algorithm, settings=scn.params,
                             faults=faults, started=started, argv=getattr(args, "argv", None))
    recorder = open_recorder(args.record, trace, scn, spec, args.seed, faults, prov) if args.record else NO_RECORDER
    try:
        with ZenohTransport(zenoh, hold_ms=HOLD_MS) as transport:
            world = World(scn, trace, spec.algorithm, args.seed, Keys(spec.run_id), transport,
                          WorldTiming(args.startup_timeout, args.tick_timeout, clock=clock), progress, log, prof, recorder)
            world.interrupted, signalled[0] = signalled[0], world
            rec = world.run(allow_missing=args.allow_missing > 0)
    except MeshError as e:
        log.error(str(e))
        recorder.finish(f"failed: {e}")
        return e.status
    finally:
        bar.close()
        if prof:
            prof.write(args.profile, "world")
    row = result_metrics(trace, rec)
    recorder.finish("done" if world.done else "stopped", row)
    summary = run_summary(rec, faults)
    if clock is not None:
        summary.update(deadline_summary(rec, clock))
    results = {spec.algorithm: {runspec.setting_label(scn): {**row, **summary}}}
    prov["status"] = summary.get("status") or ("complete" if summary["complete"] else "incomplete")
    if args.json:
        save_json(args.json, provenance.attach(results, prov), "json")
    if args.estimates:
        doc = estimates_doc(rec, spec.algorithm, scn, args.seed, spec.run_id, row)
        doc.update(faults=summary["faults"], missing_ticks=summary["missing_ticks"], **completeness(rec))
        if clock is not None:
            doc.update(deadline_summary(rec, clock))
        save_json(args.estimates, provenance.attach(doc, prov), "estimates")
    for i, c in summary["counters"].items():
        if "imbalance" in c:
            log.info(f"agent {i}'s message counters do not add up: {'; '.join(c['imbalance'])}")
    if args.progress != "lines":
        print(format_table(results))
    if not summary["complete"]:
        line = missing_line(summary)
        if summary["missing_fraction"] > args.allow_missing:
            log.error(f"incomplete run: {line}; metrics cover the rest")
            return INCOMPLETE
        log.info(f"incomplete run accepted (--allow-missing {args.allow_missing:g}): {line}")
    if clock is not None and (bad := miss_problem(summary, realtime.max_miss_rate(args))):
        log.error(bad)
        return realtime.TOO_MANY_MISSES
    return 0


if __name__ == "__main__":
    from diskf_mesh.cli import main as cli

    sys.exit(cli.run_one("world", __spec__.name))
