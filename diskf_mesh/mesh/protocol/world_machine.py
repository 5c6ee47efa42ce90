"""The world's protocol as a state machine: events in, effects out (``mesh.protocol.events``).

``WorldMachine`` holds everything the world of a mesh run decides, and does
nothing else: no transport, no thread, no clock read. Its shell
(``mesh.process.shell.Shell`` over zenoh and the wall clock, or the simulated
network) hands it one event at a time with the time ``now`` and carries out
the effects it returns, in order::

    world = WorldMachine(scn, trace, algorithm, seed, keys, nonce, timing)
    effects = world.start(now)          # subscribe, watch, claim the run id
    effects = world.handle(event, now)  # Sample, Token, Timer, Query, Woke, ...
    ...                                 # until a Finish effect
    world.record                        # what the run reported (WorldRecord)

A run, in the order of this module:

 1. start-up   subscribe to the agents' reports and duplicates,
               watch every agent's tokens and every world's, answer the
               rejoin query; claim the run id (``AskTokens``: another world
               holding it ends this one, code 2); declare the world's token;
               wait for every agent's ready token (timer ``startup``; with
               ``allow_missing`` start with those ready ``LATE_READY_S``
               later).
 2. a tick     ``_open_tick(k)``: each live agent's measurement (not
               express) and the tick (every position, the live set); timer
               ``tick`` (``tick_timeout``). Each report is decoded and taken
               (``_on_report`` -> ``_take``); the last one of tick k closes
               it (``_advance`` -> ``_close_tick``: what did not come is
               missing, and why) and opens tick k + 1 in the same step. The
               ``tick`` timer closes a tick whose reports did not all come.
 3. real time  with ``timing.clock`` the timer ``clock`` opens tick k at
               t0 + (k - 1) / HZ and ends tick k - 1 whatever came in
               (``mesh.protocol.clock``); a report owed is taken whenever it comes.
 4. tokens     an agent whose token goes drops out from the next tick on;
               one that comes back (a new ready token) is live from the tick
               after next (``_on_token``); a second world in the run id: the
               later one leaves.
 5. pauses     woken late (``Woke``: the world was frozen) or every agent
               gone: keep the open tick, wait for the agents that were live
               (at least ``PAUSE_MIN_S``, at most ``startup_timeout``), send
               the tick again (``_resume``).
 6. rejoin     an agent (re)joining at tick J asks ``Keys.start(agent)``;
               once tick J - 1 is over the world answers with the most
               certain fused estimate that an agent in range reported for
               J - 1, or the prior (``start_state``); each answer is kept
               (``WorldRecord.starts``); each report says the tick and
               source of its agent's latest (re)initialisation ("rj"): a
               rejoin (``WorldRecord.rejoins``), so the run can be replayed
               whichever of that agent's reports came.
 7. the end    after tick K (or an interrupt, or no agent left): publish
               stop, wait up to ``leave_timeout`` for the agents to leave,
               then ``Finish``.
 8. the check  once tick k's reports are final (``_check_later``: on a
               timer after the effects of the event that made them so,
               before tick k + 2 opens at the latest) ``online``
               (``mesh.protocol.run_status.OnlineCheck``) replays it on the
               engine; an agent it proves lied is cut off: no later tick
               counts it live (``WorldRecord.quarantined``). A check in a
               thread of its own (``mesh.process.checker``) is handed tick k
               (``HandOver``, the last effect of the event that made it
               final: after tick k + 1's puts), with no timer, and may
               answer later: in lockstep the world waits for it only
               before tick k + 2 opens, which cuts a liar off from the
               same tick.

Observers (the recorder, the progress callback, the profile, the log) are
called as the run goes; they never feed back into the machine.

May import: core, estimators, data, engine (the mesh layer).
"""
from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass, field, replace

import numpy as np

from diskf_mesh.data.scenario import Scenario
from diskf_mesh.data.trace import Trace
from diskf_mesh.mesh.protocol import clock as realtime
from diskf_mesh.mesh.protocol import rejoin
from diskf_mesh.mesh.wire import codec as wire
from diskf_mesh.mesh.protocol.estimator import neighbours
from diskf_mesh.mesh.protocol.events import (FREEZE_S, AskTokens, Answer, CancelTimer, DeclareQueryable, DeclareToken, Finish,
                                    HandOver, Interrupt, Publish, Query, Sample, SetTimer, Subscribe, Timer, Token, Tokens,
                                    WatchTokens, Woke)
from diskf_mesh.mesh.wire.keys import Keys, nonce as nonce_of
from diskf_mesh.mesh.protocol.log import Log
from diskf_mesh.mesh.protocol.profile import NO_PHASES, Phases
from diskf_mesh.mesh.protocol.reports import RunReports

PAUSE_MIN_S = 1.0    # a pause lasts at least this long (the links that closed while frozen close on waking)
LATE_READY_S = 5.0   # allow_missing: after the startup timeout, how long the agents up have to be ready
CLAIM_S = 1.0        # the liveliness query for another world holding the run id
CLAIM = 1            # qid of that query

# Finish codes (the world command's exit status for a run that could not go on)
FAILED = 1           # the agents did not come (startup timeout)
DUPLICATE = 2        # another world runs this run id


@dataclass(frozen=True)
class WorldTiming:
    startup_timeout: float = 30.0  # for every agent to be ready
    tick_timeout: float = 10.0     # for the reports of one tick (real time: of every tick, after the last)
    leave_timeout: float = 2.0     # after stop, for the agents to leave
    clock: realtime.Clock | None = None  # real time (``mesh.protocol.clock``); None: lockstep


@dataclass
class Deadlines:
    """A real-time run's clock and deadline misses, per agent id."""

    opened_at: list = field(default_factory=list)       # the time (``now``) each tick opened
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
    live: np.ndarray | None = None             # (K, N) bool: the live set tick k carried (``engine.verify.nominal_links``)
    rejoins: dict = field(default_factory=dict)        # id -> [{"tick", "source"}]
    starts: list = field(default_factory=list)         # [wire.Start] every starting state the world answered
    duplicates: Counter = field(default_factory=Counter)  # id (or "world") -> extra processes seen
    pauses: list = field(default_factory=list)         # [{"tick", "why", "seconds"}]
    ended_early: str = ""                      # why the run ended before tick K, if it did
    deadlines: Deadlines | None = None         # real time only
    labels: tuple = ()                         # the ids as the scenario gave them (results show these)
    quarantined: list = field(default_factory=list)  # [{"agent", "tick", "why", "fused_by", "from"}]

    def label(self, i):
        """Agent ``i``'s id as the scenario gave it (``i`` itself if unknown)."""
        return self.labels[self.ids.index(i)] if self.labels and i in self.ids else i


class WorldMachine:
    """The world of one mesh run (module docstring). ``scn``, ``trace``:
    the scenario and its simulation (seed 0 of the trace is the run's
    truth); ``algorithm``, ``seed``: what the ticks announce; ``keys``: the
    run's key space; ``nonce``: this world's token suffix
    (``mesh.wire.keys.new_nonce``; given, so that a replay is the same run);
    ``timing``; ``allow_missing``: start without the agents not ready after
    ``startup_timeout``; ``online``: the check as the run goes
    (``mesh.protocol.run_status.OnlineCheck``; None: only at the end), whose
    named agents are cut off (section 8); ``verdicts(receiver, tick,
    not_fused)``: a report's verdicts with what the network knows of the
    tick's messages (the simulated network: those it lost are "lost", not
    "late"; None: the report's own). Observers: ``log``, ``progress(k)`` after
    each tick, ``profile``, ``recorder`` (``diskf_mesh.recording.writer``'s
    hooks ``on_open``, ``on_report``, ``on_close``; None: not recorded)."""

    def __init__(self, scn: Scenario, trace: Trace, algorithm: str, seed: int, keys: Keys, nonce: str,
                 timing: WorldTiming = WorldTiming(), allow_missing: bool = False, log: Log | None = None,
                 progress=None, profile: Phases = NO_PHASES, recorder=None, online=None, verdicts=None):
        self.scn, self.trace, self.algorithm, self.seed = scn, trace, algorithm, seed
        self.online, self.verdicts = online, verdicts
        self._quarantined = {}         # id -> the online check's finding that cut it off
        self._unchecked = []           # ticks whose reports are final, not checked yet (timer "check")
        self._handed = 0               # the last tick handed to a check that takes ticks (``HandOver``)
        self._now = 0.0                # the time of the event being handled
        self.keys, self.nonce, self.timing = keys, nonce, timing
        self.allow_missing = allow_missing
        self.log, self.progress, self.prof, self.recorder = log or Log("world"), progress, profile, recorder
        self.clock = timing.clock
        self.ids = tuple(a.id for a in scn.agents)
        self._every = frozenset(self.ids)
        self._index = {i: j for j, i in enumerate(self.ids)}
        self.p = scn.sensors().p
        K, N = trace.has.shape[1:]
        self.K = K
        n, m = trace.model.n, trace.model.m
        self.record = WorldRecord(**RunReports.empty(K, N, n, m, sparse=True), ids=self.ids,
                                  why=np.full((K, N), "", dtype=object), live=np.zeros((K, N), dtype=bool),
                                  labels=scn.labels,
                                  deadlines=None if self.clock is None else Deadlines())
        self.phase = "new"             # new, claim, startup, late-ready, ticking, leaving, finished
        self.finish: Finish | None = None
        self._out = []                 # the effects of the event being handled
        self._timers = {}              # name -> at, of the timers set and not fired or cancelled
        # who is there
        self.alive, self.ready = set(), set()
        self._tokens = {"alive": {}, "ready": {}}  # kind -> id -> nonces held
        self._holders = {}             # id -> nonce of the process the ticks count as it (``_holder``)
        self._gone_ready = {}          # id -> ready nonces that went (they do not count again)
        self._twins = {}               # id -> (nonces that said they leave, nonces of tokens that came second)
        self._joins_at = {}            # id -> first tick a (re)joining agent is live at
        self._why = dict.fromkeys(self.ids, "never joined")  # id -> why it is not live (None: live)
        self._stopped = {}             # id -> why the agent said it stops (one of ``wire.STOPPED``)
        # the ticks
        self.k = 0                     # the last tick opened
        self.done = False              # tick K is closed
        self._open = 0                 # k while the reports of tick k are being collected
        self._closed = 0               # the last tick whose reports are final (closed, or ended in real time)
        self._waiting = set()          # live agents whose report of the open tick has not come yet
        self._rejected = set()         # ids whose report of the open tick was rejected
        self._live_at_open = ()        # the live set of the open tick
        self._sent = []                # [Publish] that opened it (sent again after a pause)
        self._t0 = self._t1 = 0.0      # start; tick 1 opened
        self._ticking = False          # the "ticking" token is declared
        # real time
        self._owed = {}                # tick -> live agents whose report has not come yet
        self._ended = 0                # the last tick whose end has passed
        self._unrecorded = 1           # the first tick not handed to the recorder yet
        # pauses
        self._paused = ""              # why the ticks are paused ("" if not)
        self._paused_at = 0.0
        self._expect = set()           # the agents a pause waits for
        self._pending = 0              # the tick to open after a pause (0: the open tick goes on)
        # rejoin queries waiting for their tick: [(qid, agent, tick)]
        self._starts_owed = []
        self._answered = set()         # (agent, tick, source) of the starts in the record

    # ======================================================================
    # the interface
    # ======================================================================
    def start(self, now: float) -> list:
        """Subscribe, watch the tokens, answer the rejoin query, and claim
        the run id (its answer continues in ``_on_claim``)."""
        root = self.keys.root
        self._t0 = now
        self.phase = "claim"
        return [Subscribe(self.keys.report("*")),
                Subscribe(self.keys.duplicate("*")),
                Subscribe(self.keys.stopped("*")),
                WatchTokens(f"{root}/*/agent/*/*"), WatchTokens(self.keys.alive_world),
                DeclareQueryable(self.keys.start("*")),
                AskTokens(CLAIM, self.keys.alive_world, CLAIM_S)]

    read = Sample  # a sample is the event ``handle`` takes, as it is: the world reads reports in ``handle``

    def handle(self, event, now: float) -> list:
        """One event; returns the effects, in order."""
        if self.phase == "finished":
            return []
        self._now = now
        if isinstance(event, Sample):
            self._on_sample(event.key, event.payload, now)
        elif isinstance(event, Token):
            self._on_token_key(event.key, event.up, now)
        elif isinstance(event, Timer):
            if now >= self._timers.get(event.name, math.inf):  # set, not cancelled or moved later
                del self._timers[event.name]
                self._on_timer(event.name, now)
        elif isinstance(event, Query):
            self._on_query(event, now)
        elif isinstance(event, Tokens):
            if event.qid == CLAIM and self.phase == "claim":
                self._on_claim(event.keys, now)
        elif isinstance(event, Woke):
            self._woke(event.late, now)
        elif isinstance(event, Interrupt):
            self._interrupt(event.why, now)
        self._check(now)
        self._hand_over()
        out, self._out = self._out, []
        return out

    def _check(self, now: float) -> None:
        """Every step the new state allows: start the ticks once the agents
        are ready, close the ticks whose reports are in, end a pause whose
        agents are back, answer the rejoin queries whose tick is over, leave
        once the agents have left."""
        if self.phase == "startup" and self.ready >= self._every:
            self._begin_ticks(now)
        elif self.phase == "late-ready" and self.ready >= self.alive:
            self._late_ready_over(now)
        if self.phase == "ticking":
            if self._paused:
                if self._pause_over(now):
                    self._resume(now)
            else:
                self._advance(now)
        if self._starts_owed:
            self._answer_starts()
        if self.phase == "leaving" and not self.alive:
            self._finish("done" if self.done and not self.record.ended_early else "stopped", 0,
                         self.record.ended_early)

    def _emit(self, *effects) -> None:
        self._out.extend(effects)

    def _set_timer(self, name: str, at: float) -> None:
        self._timers[name] = at
        self._emit(SetTimer(name, at))

    def _cancel_timer(self, name: str) -> None:
        if self._timers.pop(name, None) is not None:
            self._emit(CancelTimer(name))

    def _on_timer(self, name: str, now: float) -> None:
        if name == "startup":
            self._startup_over(now)
        elif name == "late-ready":
            self._late_ready_over(now)
        elif name == "tick":
            if self._open and not self._paused and self.clock is None:
                self._close_tick(now)
        elif name == "clock":
            self._clock_tick(now)
        elif name == "grace":
            self._end_clocked(now)
        elif name == "check":
            self._check_ticks(wait=self.clock is not None or not self._open)
        elif name == "pause":
            if self._paused and not self._pause_over(now):
                self._set_timer("pause", self._paused_at + self.timing.startup_timeout)
        elif name == "leave":
            self._finish("done" if self.done and not self.record.ended_early else "stopped", 0,
                         self.record.ended_early)

    # ======================================================================
    # 1. start-up
    # ======================================================================
    def _on_claim(self, keys, now: float) -> None:
        """The worlds' tokens held when this one started: another world's
        ends this one (exit ``DUPLICATE``); else declare this world's token
        and wait for the agents."""
        others = {nonce_of(k) for k in keys} - {self.nonce}
        if others:
            return self._finish("duplicate", DUPLICATE,
                                f"another world runs run id {self.keys.run_id!r} (token nonce {min(others)}): "
                                "give each run its own --run-id")
        self._emit(DeclareToken(self.keys.world(self.nonce)))
        self.phase = "startup"
        self._set_timer("startup", now + self.timing.startup_timeout)

    def _startup_over(self, now: float) -> None:
        """``startup_timeout`` passed with agents not ready: fail naming
        them, or (``allow_missing``) declare the ``ticking`` token (the
        agents up stop waiting for the missing peers and declare ready, as a
        restart does) and start with those ready ``LATE_READY_S`` later."""
        if self.phase != "startup":
            return
        if self.allow_missing and self.alive:
            self.phase = "late-ready"
            self._declare_ticking()
            self._set_timer("late-ready", now + LATE_READY_S)
            return
        absent = [i for i in self.ids if i not in self.alive]
        stuck = [i for i in self.ids if i in self.alive and i not in self.ready]
        parts = []
        if absent:
            parts.append(f"no agent process for id {', '.join(map(str, absent))} (no liveliness token)")
        if stuck:
            parts.append(f"agent {', '.join(map(str, stuck))} up but not connected to every peer")
        self.record.ended_early = (f"after {self.timing.startup_timeout:g} s waiting for the agents: "
                                   + "; ".join(parts))
        self._finish("failed", FAILED, self.record.ended_early)

    def _late_ready_over(self, now: float) -> None:
        if self.phase != "late-ready":
            return
        if not self.ready:
            self.record.ended_early = f"no agent ready {self.timing.startup_timeout + LATE_READY_S:g} s after the start"
            return self._finish("failed", FAILED, self.record.ended_early)
        self._cancel_timer("late-ready")
        self.log.info(f"starting without agent {', '.join(str(i) for i in self.ids if i not in self.ready)}"
                      f" (not ready after {self.timing.startup_timeout:g} s; --allow-missing)")
        self._begin_ticks(now)

    def _declare_ticking(self) -> None:
        if not self._ticking:
            self._ticking = True
            self._emit(DeclareToken(self.keys.ticking))  # an agent starting from now on is rejoining

    def _begin_ticks(self, now: float) -> None:
        """Every agent is ready (or the rest is given up): tick 1 opens."""
        self._cancel_timer("startup")
        self.phase = "ticking"
        self.record.startup_s = now - self._t0
        self._t1 = now
        self._declare_ticking()
        self.prof.start()
        if self.clock is None:
            self._open_tick(1, now)
        else:
            self._clock_tick(now)

    # ======================================================================
    # 2. a tick (lockstep)
    # ======================================================================
    def _live(self, k: int) -> list:
        return [i for i in self.ids if i in self.ready and self._joins_at.get(i, 0) <= k and i not in self._quarantined]

    def _holder(self, agent: int, k: int) -> str:
        """The process (its nonce) counted as ``agent`` at tick k: at tick 1
        the earliest started of those holding the id (as the agents' own
        rule); later the one counted before while its token lasts, else the
        earliest started of those holding it now (a restart). Every tick
        names it (``wire.Tick.holders``): any other process of the id leaves
        before it works."""
        held = self._tokens["alive"].get(agent, set())
        h = self._holders.get(agent)
        if k == 1 or h not in held:
            h = self._holders[agent] = min(held)
        return h

    def _open_tick(self, k: int, now: float) -> None:
        """Send each live agent its measurement of tick k, then the tick. The
        measurements are not express: each waits in its agent's link for the
        (express) tick, so an agent gets both in one write and wakes once."""
        self._check_ticks(k - 2)  # a liar named by then is cut off from this tick on
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
            if i in self._waiting:
                self._why[i] = None
                self.record.live[k - 1, j] = True
            else:
                self.record.why[k - 1, j] = "quarantined" if i in self._quarantined else self._why[i] or "left"
        if self.recorder is not None:
            self.recorder.on_open(k, live)
        prof.begin()
        has, y, index = tr.has[0, k - 1], tr.y[0, k - 1], self._index
        out = [Publish(self.keys.meas(i), wire.encode_measurement(run, k, i, bool(has[j]), y[j, : self.p[j]]),
                       express=False) for i, j in ((i, index[i]) for i in live)]
        holders = b"".join(wire.holder_tag(self._holder(i, k)) for i in live)
        out.append(Publish(self.keys.tick, wire.encode_tick(wire.Tick(
            run, k, self.K, self.seed, self.algorithm, self.scn.topology, self.scn.comm_range,
            tr.positions[k - 1], tuple(live), holders))))
        prof.end("encode")
        self._sent = out
        self._out += out
        prof.waiting = "wait-reports"
        if self.clock is None:
            self._set_timer("tick", now + self.timing.tick_timeout)

    def _on_sample(self, key: str, payload: bytes, now: float) -> None:
        """An agent's report, or a duplicate's notice."""
        kind, who = self.keys.parse(key)
        if kind == "report":
            try:
                self._on_report(who, payload, now)
            except wire.Rejected as e:
                self.record.counters[f"rejected:{e.reason}"] += 1
                if who in self.ids:
                    self._rejected.add(who)
                self.log.once(("report", who if who in self.ids else None, e.reason),
                              f"rejected a report from {key[:200]}: {e}")
        elif kind == "stopped" and who in self.ids:
            self._on_stopped(who, payload)
        elif kind == "duplicate" and who in self.ids:
            nonce_ = bytes(payload[:32]).decode(errors="replace")
            if self._duplicate(who, nonce_, said=True):
                self.log.info(f"agent id {who}: a second process (nonce {nonce_}) found this id held and leaves: "
                              "duplicate id")

    def _on_stopped(self, who: int, payload: bytes) -> None:
        """Agent ``who`` says it stops before the run's end, and why (its
        estimator diverged, it was interrupted): its missing ticks say so
        instead of "left" (``_gone``), those already marked included. Its
        own key (the access rules let only agent ``who`` put there): an
        agent can say this of itself only."""
        try:
            st = wire.decode_stop(payload, run_id=self.keys.run_id)
        except wire.Rejected as e:
            self.record.counters[f"rejected:{e.reason}"] += 1
            return
        category = wire.stopped_category(st)
        if category is None or who in self._stopped:
            return
        self._stopped[who] = category
        self.log.info(f"tick {st.tick}: agent {who} stops: {st.why[:300]}")
        if self._why.get(who) == "left":
            self._why[who] = category
        j = self._index[who]
        why = self.record.why[:, j]
        why[(why == "left") & (np.arange(1, len(why) + 1) >= st.tick)] = category

    def _gone(self, who: int) -> str:
        """Why agent ``who`` is not ready: what it said when it stopped, else "left"."""
        return self._stopped.get(who, "left")

    def _duplicate(self, who, nonce_: str, said: bool) -> bool:
        """A second process of agent ``who``: one that said it leaves
        (``said``, its notice) or an alive token that came while another
        process held the id. ``duplicates`` counts the larger of the two
        kinds of evidence, so a process that shows both ways counts once
        (zenoh's order of two tokens need not be the order the processes
        started in, so the token may name the one that stays). True if new."""
        seen = self._twins.setdefault(who, (set(), set()))[0 if said else 1]
        if nonce_ in seen:
            return False
        seen.add(nonce_)
        self.record.duplicates[who] = max(len(s) for s in self._twins[who])
        return True

    def _on_report(self, sender, payload, now: float) -> None:
        if sender not in self._every:
            raise wire.Rejected("sender", f"unknown agent {sender}")
        self.prof.begin()
        try:
            r = wire.decode_report(payload, run_id=self.keys.run_id, sender=sender,
                                   n=self.trace.model.n, m=self.trace.model.m, ticks=self.K, agents=len(self.ids))
        finally:
            self.prof.end("decode")
        if self.verdicts is not None and r.not_fused:
            r = replace(r, not_fused=self.verdicts(r.sender, r.tick, r.not_fused))
        i = self._index[sender]
        if self.clock is not None:
            self._on_clocked_report(r, i, now)
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
        rec.note_fused(r.tick, i, r.fused, r.not_fused, r.digests, self._index)
        if r.restart is not None:
            self._rejoined(r.sender, *r.restart)
        if self.recorder is not None:
            self.recorder.on_report(r)

    def _advance(self, now: float) -> None:
        """Close every tick whose reports are all in, opening the next (real
        time: the clock does)."""
        while (self.clock is None and self.phase == "ticking" and self._open and not self._waiting
               and not self._paused):
            self._close_tick(now)

    def _close_tick(self, now: float) -> None:
        """Tick k is over (every live agent reported, or its deadline passed):
        what did not come is missing; open tick k+1 (or pause, if every agent
        is gone), or end."""
        k = self.k
        self._mark_missing(k)
        for i in sorted(self._waiting):
            self.record.counters["missing-report"] += 1
            self.log.once(("late", i), f"tick {k}: no report from agent {i} within {self.timing.tick_timeout:g} s")
        if self.recorder is not None:
            self.recorder.on_close(k, self._waiting)
        self._check_later(k)
        self._open, self._waiting, self._closed = 0, set(), k  # its "tick" timer: moved by the next, or cancelled
        self.prof.tick()
        if self.progress is not None:
            self.progress(k)
        if k >= self.K:
            self.done = True
            self._end_run(now, "done")
        elif not self._live(k + 1) and not self.ready:
            self._pending = k + 1
            self._pause("every agent is gone", self._live_at_open, now)
        else:
            self._open_tick(k + 1, now)

    def _mark_missing(self, k: int) -> None:
        """Why each agent live at tick k has no report of it: its report
        failed the decoder, it left (its ready token went), or none came."""
        rec = self.record
        for j, i in enumerate(self.ids):
            if rec.live[k - 1, j] and not rec.reported[k - 1, j]:
                rec.why[k - 1, j] = ("rejected" if i in self._rejected else
                                     self._gone(i) if i not in self.ready else "no report")

    # ======================================================================
    # 3. real time (``mesh.protocol.clock``)
    # ======================================================================
    def _clock_tick(self, now: float) -> None:
        """Timer ``clock``: tick k opens at t0 + (k - 1) / HZ and ends when
        tick k + 1 opens, whatever came in; after the last tick's end, the
        reports still owed have ``tick_timeout`` to come (timer ``grace``)."""
        k = self.k + 1
        if k > 1:
            self._end_tick(k - 1)
        if k <= self.K:
            self.record.deadlines.opened_at.append(now)
            self._open_tick(k, now)
            self._set_timer("clock", self._t1 + k * self.clock.period_s)
        else:
            self._set_timer("grace", now + self.timing.tick_timeout)
            if not any(self._owed.values()):
                self._end_clocked(now)

    def _end_tick(self, k: int) -> None:
        """Tick k's end. A live agent whose report is not in misses its
        deadline (its report may still come: ``late_reports``)."""
        dl = self.record.deadlines
        for i in sorted(self._owed.get(k, ())):
            dl.report_misses[i] += 1
        self._mark_missing(k)
        self._open, self._ended, self._closed = 0, k, k
        self.prof.tick()
        if self.progress is not None:
            self.progress(k)
        self._to_recorder()

    def _on_clocked_report(self, r: wire.Report, i: int, now: float) -> None:
        """A report owed for its tick is taken whenever it comes; after the
        tick's end it counts late. Its messages not fused in time (verdict
        "late") are message deadline misses."""
        owed = self._owed.get(r.tick)
        if owed is None or r.sender not in owed:
            self.record.counters["stale" if r.tick <= self.k else "unexpected"] += 1
            return
        owed.discard(r.sender)
        dl = self.record.deadlines
        if r.tick != self._open:  # its tick has ended
            dl.late_reports[r.sender] += 1
            dl.late_by.append(now - dl.opened_at[r.tick - 1] - self.clock.period_s)
            self.record.why[r.tick - 1, i] = ""
        dl.message_misses[r.sender] += sum(1 for _, v in r.not_fused if v == "late")
        dl.messages_due[r.sender] += len(r.fused) + len(r.not_fused)
        self._take(r, i)
        self._to_recorder()
        if self._ended >= self.K and not any(self._owed.values()) and self.phase == "ticking":
            self._end_clocked(now)  # the last report owed: the run is over

    def _to_recorder(self, final: bool = False) -> None:
        """Hand the recorder every ended tick, in order, once its reports are
        all in (or ``LEAD_TICKS`` later, or at the end: the rest are
        missing). An agent further behind than that is out of the run anyway
        (``mesh.protocol.clock``)."""
        while self._unrecorded <= self._ended:
            k = self._unrecorded
            if self._owed.get(k) and not final and k >= self._ended - realtime.LEAD_TICKS:
                return
            missing = self._owed.pop(k, set())
            if self.recorder is not None:
                self.recorder.on_close(k, missing)
            self._check_later(k)
            self._unrecorded += 1

    def _end_clocked(self, now: float) -> None:
        if self.phase != "ticking":
            return
        self._cancel_timer("grace")
        self._to_recorder(final=True)
        self.done = not self.record.ended_early
        self._end_run(now, "done")

    # ======================================================================
    # 4. tokens
    # ======================================================================
    def _on_token_key(self, key: str, up: bool, now: float) -> None:
        kind, who = self.keys.parse(key)
        if kind in ("alive", "ready") and who is not None:
            self._on_token(kind, who, nonce_of(key), up)
        elif kind == "alive-world":
            self._on_world_token(nonce_of(key), up)

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
            if kind == "alive" and held and nonce_ not in held and self._duplicate(who, nonce_, said=False):
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
        if self.k and self.phase == "ticking" and was_alive != alive:
            came = "is here (it had not joined)" if self._why.get(who) == "never joined" else "is back"
            self.log.info(f"tick {self.k}: agent {who} " + (came if alive else "is gone (its liveliness token went)"))
        if ready and not was_ready and self.k and not (self._paused and who in self._expect):
            self._joins_at[who] = self.k + 2  # its first tick: the reports of the one before are final by then
            self._why[who] = "rejoining"
        if not ready and was_ready:
            self._why[who] = self._gone(who)
            if not self._paused:
                self._waiting.discard(who)  # gone: the tick does not wait for it
            for owed in self._owed.values():
                owed.discard(who)

    def _on_world_token(self, nonce_: str, up: bool) -> None:
        """Another world's token in this run id: the later started of two
        leaves (the other counts it)."""
        if nonce_ == self.nonce or not up:
            return
        if nonce_ < self.nonce:
            self._finish("duplicate", DUPLICATE,
                         f"another world runs run id {self.keys.run_id!r} (token nonce {nonce_}, started earlier): "
                         "this one leaves; give each run its own --run-id")
        else:
            self.record.duplicates["world"] += 1
            self.log.info(f"a second world (token {nonce_}) in run id {self.keys.run_id!r}: it leaves")

    # ======================================================================
    # 5. pauses
    # ======================================================================
    def _woke(self, late: float, now: float) -> None:
        """The shell ran ``late`` seconds after it should have: more than
        ``FREEZE_S`` and the world was frozen; in lockstep it pauses (the
        agents may have dropped out meanwhile)."""
        if late > FREEZE_S and self._open and not self._paused and self.clock is None and self.phase == "ticking":
            self._pause("the world was frozen", self._live_at_open, now)

    def _pause(self, why: str, expect, now: float) -> None:
        """Stop ticking until the agents ``expect`` are back (``_resume``)."""
        self._paused, self._paused_at, self._expect = why, now, set(expect)
        self._cancel_timer("tick")
        self._set_timer("pause", now + PAUSE_MIN_S)
        self.log.info(f"tick {self.k}: {why}: waiting up to {self.timing.startup_timeout:g} s for agents "
                      f"{', '.join(map(str, sorted(self._expect))) or '(none)'} to come back")

    def _pause_over(self, now: float) -> bool:
        if now < self._paused_at + PAUSE_MIN_S:
            return False
        return self._expect <= self.ready or now >= self._paused_at + self.timing.startup_timeout

    def _resume(self, now: float) -> None:
        """End the pause. The open tick is sent again (to the agents that
        missed it; one that had reported it sends its report again) with a
        new deadline; or the tick after a run without agents opens; or, if
        no agent came back, the run ends early."""
        self._cancel_timer("pause")
        self.record.pauses.append({"tick": self.k, "why": self._paused, "seconds": round(now - self._paused_at, 3)})
        self.log.info(f"tick {self.k}: resuming after {now - self._paused_at:.1f} s with agents "
                      f"{', '.join(map(str, sorted(self.ready))) or '(none)'}")
        self._paused, self._expect = "", set()
        if not self.ready:
            self.record.ended_early = f"no agent came back within {self.timing.startup_timeout:g} s"
            self._open, self._waiting = 0, set()
            return self._end_run(now, self.record.ended_early)
        if self._pending:
            k, self._pending = self._pending, 0
            return self._open_tick(k, now)
        k = self.k
        self._waiting = {i for i in self._live_at_open
                         if i in self.ready and not self.record.reported[k - 1, self._index[i]]}
        self._out += self._sent
        self._set_timer("tick", now + self.timing.tick_timeout)

    # ======================================================================
    # 6. rejoin: the starting state of an agent (re)joining at tick J
    # ======================================================================
    def _on_query(self, q: Query, now: float) -> None:
        """Agent ``who`` asks for its starting estimate at tick J
        (``wire.decode_join``); the answer waits until tick J - 1 is over."""
        kind, who = self.keys.parse(q.key)
        if kind != "start" or who not in self.ids:
            return
        try:
            join = wire.decode_join(q.payload, run_id=self.keys.run_id, sender=who)
            if not 1 <= join.tick <= self.K:
                raise wire.Rejected("tick", f"tick {join.tick} outside 1..{self.K}")
        except wire.Rejected as e:
            self.record.counters[f"rejected:{e.reason}"] += 1
            return
        # one query owed per agent (its latest): a flood of queries holds no more
        self._starts_owed = [o for o in self._starts_owed if o[1] != who] + [(q.qid, who, join.tick)]

    def _answer_starts(self, final: bool = False) -> None:
        """Answer every rejoin query whose tick J - 1's reports are final, or
        all of them at the end of the run."""
        keep = []
        for qid, who, tick in self._starts_owed:
            if final or self._reports_final(who, tick - 1):
                s = self.start_state(who, tick)
                self._emit(Answer(qid, wire.encode_start(s.run_id, who, tick, s.source, s.x, s.P, s.d, s.d_valid)))
                if (who, tick, s.source) not in self._answered:  # the same answer again is kept once
                    self._answered.add((who, tick, s.source))
                    self.record.starts.append(s)  # a rejoin once the agent says it started from it
            else:
                keep.append((qid, who, tick))
        self._starts_owed = keep

    def _reports_final(self, agent: int, k: int) -> bool:
        """Whether the reports of tick ``k`` that ``agent``'s start may come
        from are all in: lockstep, tick k is closed; real time, tick k has
        ended and no agent in range of ``agent`` still owes its report (a
        late one is still taken), or tick k + 1 has ended too."""
        if k > self._closed:
            return False
        if self.clock is None or k < 1 or k + 1 <= self._ended:
            return True
        near = set(neighbours(self.scn, agent, self.trace.positions[k - 1]))
        return not (self._owed.get(k, set()) & near)

    def start_state(self, agent: int, tick: int) -> wire.Start:
        """Agent ``agent``'s starting state at ``tick``: of the agents in
        range of it at tick - 1 that reported tick - 1, the most certain
        fused estimate (``rejoin.most_certain``); the prior if none."""
        rec, t, run = self.record, tick - 2, self.keys.run_id
        if t >= 0:
            near = set(neighbours(self.scn, agent, self.trace.positions[t])) - {agent} - set(self._quarantined)
            reported = {i: wire.Start(run, agent, tick, i, rec.x[t, j].copy(), rec.P[t, j].copy(),
                                      rec.d[t, j].copy(), bool(rec.d_valid[t, j]))
                        for i in sorted(near) for j in (self._index[i],) if rec.reported[t, j]}
            source = rejoin.most_certain(reported, near)
            if source is not None:
                return reported[source]
        model = self.trace.model
        return wire.Start(run, agent, tick, None, np.array(model.x0, dtype=float).reshape(model.n),
                          np.array(model.P0, dtype=float).reshape(model.n, model.n), np.zeros(model.m), False)

    def _rejoined(self, agent: int, tick: int, source) -> None:
        """Agent ``agent``'s report says it started at ``tick`` from
        ``source`` (an answer of ``start_state``, or the prior): a rejoin,
        kept once, in tick order (reports may come out of order). An answer
        no agent started from (a duplicate process that left) is none."""
        runs = self.record.rejoins.setdefault(agent, [])
        entry = {"tick": int(tick), "source": source}
        runs[:] = sorted([r for r in runs if r["tick"] != entry["tick"]] + [entry], key=lambda r: r["tick"])

    # ======================================================================
    # 7. the end
    # ======================================================================
    def _interrupt(self, why: str, now: float) -> None:
        """A signal: end the run where it is."""
        if self.phase in ("claim", "new"):  # nothing declared yet: nothing to stop
            self.record.ended_early = f"interrupted ({why}) before tick 1"
            return self._finish("stopped", 0, self.record.ended_early)
        if self.phase in ("startup", "late-ready"):
            self.record.ended_early = f"interrupted ({why}) before tick 1"
        elif self.phase == "ticking":
            self.record.ended_early = f"interrupted ({why})"
        else:
            return
        self._end_run(now, self.record.ended_early)

    def _end_run(self, now: float, why: str) -> None:
        """Say stop and wait up to ``leave_timeout`` for the agents to leave."""
        if self.phase == "ticking":
            self.prof.stop()
            self.record.ticks_s = now - self._t1
            if self.clock is not None:
                self._to_recorder(final=True)  # the ended ticks; the rest are missing
        self._check_ticks()
        for name in list(self._timers):
            self._cancel_timer(name)
        self._open, self._waiting = 0, set()
        self.phase = "leaving"
        self._answer_starts(final=True)
        self._emit(Publish(self.keys.stop, wire.encode_stop(self.keys.run_id, self.k, why)))
        self._set_timer("leave", now + self.timing.leave_timeout)

    def _finish(self, status: str, code: int, reason: str) -> None:
        for name in list(self._timers):
            self._cancel_timer(name)
        self.phase = "finished"
        self.finish = Finish(status, code, reason)
        self._emit(self.finish)

    # ======================================================================
    # 8. the check as the run goes
    # ======================================================================
    def _check_later(self, k: int) -> None:
        """Tick k's reports are final: check it once the effects of this
        event are out (timer ``check`` at once), so the next tick's
        messages go first; at the latest before tick k + 2 opens. A check
        the world hands ticks over to (``online.handed_over``) needs no
        timer: this event's last effect hands it tick k (``_hand_over``),
        and the world's main thread does not wake each tick only to hand it
        over."""
        if self.online is not None:
            self._unchecked.append(k)
            if not getattr(self.online, "handed_over", False):
                self._set_timer("check", self._now)

    def _hand_over(self) -> None:
        """A check the world hands ticks over to gets each final tick not
        handed over yet, as the last effects of the event (``HandOver``):
        the next tick's puts go out before its thread wakes."""
        if self._unchecked and self._unchecked[-1] > self._handed and getattr(self.online, "handed_over", False):
            for k in self._unchecked:
                if k > self._handed:
                    self._emit(HandOver(self.online, self.record, k))
            self._handed = self._unchecked[-1]

    def _check_ticks(self, upto: float = math.inf, wait: bool = True) -> None:
        """Check the final ticks up to ``upto``, in order (each handed to
        the check first, if ``HandOver`` has not yet). An online check
        the world hands ticks over to (``online.result`` None: not done yet) is only
        waited for with ``wait``: the timer ``check`` of a lockstep tick
        waits for none while the next tick is open, since its finding
        counts from the same tick on when it is taken at that tick's end
        (``_open_tick`` waits) as when it is taken at once."""
        for k in self._unchecked:
            if k > upto:
                break
            self.online.submit(self.record, k)
        while self._unchecked and self._unchecked[0] <= upto:
            if not self._check_tick(self._unchecked[0], wait):
                return
            self._unchecked.pop(0)

    def _check_tick(self, k: int, wait: bool = True) -> bool:
        """The online check replays tick k; an agent it names is cut off
        from the next tick opened on (no tick counts it live again, so no
        honest agent links to it or fuses its messages, and no rejoin
        starts from its estimate); its missing ticks say "quarantined".
        False if its finding is not in yet (and not ``wait``)."""
        self.prof.begin()
        try:
            found = self.online.result(self.record, k, wait)
        finally:  # a check in a thread of its own counts its replay there: here the world waits for it
            self.prof.end("wait-check" if getattr(self.online, "handed_over", False) else "check")
        if found is None:
            return False
        for q in found:
            if q["agent"] in self._quarantined:
                continue
            q["from"] = self.k + 1
            self._quarantined[q["agent"]] = q
            self.record.quarantined.append(q)
            self.log.info(f"tick {k}: agent {q['agent']} cut off from tick {q['from']} on: its message or report "
                          "is not what the algorithm computes"
                          + (f" (fused by agent {', '.join(map(str, q['fused_by']))})" if q["fused_by"] else ""))
        return True
