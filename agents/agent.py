"""``diskf-mesh agent``: one agent of a mesh run, in its own process.

It knows the shared motion model and parameters and only its own sensor
(H, R from the scenario file). Every tick k:

1. wait for the world's tick k (every agent's position, the live set) and for
   its own measurement of tick k (or none);
2. local step (``AgentEstimator.local``), publish ONE message;
3. collect the messages of tick k of its neighbours: the live agents within
   range at tick k (positions from the world). It stops collecting when all
   have arrived, after ``--collect-timeout`` seconds, or as soon as the world
   has opened a later tick;
4. fuse what it has, report the fused estimate to the world.

With ``--rate`` (real time, ``diskf_mesh.mesh.clock``) step 3 ends at the
deadline instead: ``--deadline-ms`` after tick k reached this agent (default
half the period), or at once for an agent that fell behind; what came later
is a deadline miss, never fused.

Each step is taken by whichever message makes it possible, in the
transport's callback (zenoh's network thread): the world's tick (its
measurement came just before) runs steps 1-2, the last neighbour's message
steps 3-4. The main thread only starts the agent, joins the run, and watches
the timeouts and the stop; it is not woken per message (a thread hop per
message was most of a message's cost on a busy machine).

The process is a ``diskf_mesh.mesh.process.Process`` (one lock, the
callback, the failure, the main thread's wait); that module's docstring
follows one tick world -> agent -> neighbour -> world through this code.
Neighbours' messages pass the receive path (``diskf_mesh.mesh.receive``: the
guard decodes each once and rejects what is malformed, the inbox, the one
place a message waits, fuses it at most once and discards, counted as late,
one for a tick already fused). The world's
messages are taken only when they fit the run (``_tick_problem``,
``_meas_problem``): a tick for k or k+1 (k the tick being worked on) with the
run's constants, a measurement for k or k+1 of this agent's length within
``GuardConfig.max_abs``; every per-tick map is kept to a few ticks. The counters
(``diskf_mesh.mesh.counters``) go to the world with every report.

Exit status: 0 only when the world says stop with "done" at the run's last
tick; 2 (one line) when another process already holds this agent's id in the
run (``mesh.keys``: every token carries its process's nonce); 1 with one line
on stderr otherwise: the world stopped the run early, or it has been gone
(its liveliness token) or silent for ``--world-timeout`` seconds. While the
world is gone the agent waits for it (a frozen world comes back).

Link faults (``--loss``, ``--latency-ms``, ... or the scenario's
``[faults]``) act in the receive path on every link into this agent, seeded
by the run's seed (from the world's first tick). An agent started while the
run is in progress (a restart after a crash) joins at the world's next tick
and re-initialises from a neighbour's fused estimate (``agents.rejoin``).
So does an agent that was frozen (SIGSTOP) past zenoh's lease and finds,
when it wakes, that the world dropped it: it withdraws its ready token,
declares a new one and rejoins like a restart.

``--profile DIR`` writes where each tick's time went (``mesh.profile``).
"""
from __future__ import annotations

import argparse
import dataclasses
import math
import os
import sys
import time
from dataclasses import dataclass

import numpy as np

from agents import rejoin
from diskf_mesh import estimators
from diskf_mesh.mesh import wire
from diskf_mesh.mesh.guard import Guard, GuardConfig
from diskf_mesh.mesh import clock as realtime
from diskf_mesh.mesh import credentials
from diskf_mesh.mesh import runspec
from diskf_mesh.mesh import zenoh_config
from diskf_mesh.mesh.estimator import AgentEstimator, neighbours
from diskf_mesh.mesh.keys import Keys, nonce
from diskf_mesh.mesh.log import Log
from diskf_mesh.mesh.process import FREEZE_S, Process
from diskf_mesh.mesh.stopping import exit_on_sigterm
from diskf_mesh.mesh.profile import AGENT_PHASES, NO_PHASES, Phases
from diskf_mesh.mesh.transport import DuplicateProcess, MeshError, Transport, ZenohTransport
from diskf_mesh.data.faults import FaultConfig, FaultModel
from diskf_mesh.data.faults import add_arguments as add_fault_arguments
from diskf_mesh.data.faults import from_args as faults_from_args
from diskf_mesh.mesh.receive import Receiver
from diskf_mesh.recording.verdicts import TickVerdicts
from diskf_mesh.data.scenario import Scenario

LINKS_KEPT = 16  # link sets of past ticks kept, to gate late messages too
AHEAD_KEPT = 4   # ticks (and measurements) kept ahead of joining: a restart sees the world's latest
WOKE_S = 3.0     # a world token that goes within this long of waking from a freeze: we were dropped
PEERS_WAIT_S = 5.0  # a (re)joining agent waits at most this long to see the live agents
DUPLICATE_SAY_S = 0.2  # a duplicate's word to the world is on the wire before it leaves
REPORTS_WAIT_S = 1.0   # a rejoining agent waits at most this long for its neighbours' reports


@dataclass(frozen=True)
class AgentTiming:
    collect_timeout: float = 5.0   # wait for neighbours' messages after publishing
    world_timeout: float = 60.0    # longest silence from the world before giving up
    clock: realtime.Clock | None = None  # real time (``mesh.clock``): fuse at its deadline; None: lockstep


class Agent(Process):
    """The protocol of one agent over a ``Transport`` (a ``mesh.process``:
    its steps 2 to 5 of a tick). ``run`` returns the number of ticks fused,
    or raises ``MeshError``.

    Everything the transport delivers (the world's messages, neighbours'
    messages, liveliness changes) is handled in the transport's callback,
    under one lock (``_cv``, ``_take_in``), and ``_advance`` then takes every step the
    new state allows (open tick k: local step and own message; close it:
    fusion and report). Neighbours' messages that pass the range gate go on
    to the receive path (``diskf_mesh.mesh.receive``: guard, the link's
    ``faults``, inbox); a copy the fault layer delays comes back through
    ``wake``. The main thread (``run``) waits on ``_cv`` for what only it
    does: joining the run (the estimator, a rejoining agent's
    re-initialisation and its subscription to the reports), the collect
    deadline, the world's silence or departure, and the stop. Callbacks
    notify it only then."""

    def __init__(self, scn: Scenario, agent_id: int, algorithm: str, keys: Keys, transport: Transport,
                 timing: AgentTiming = AgentTiming(), log: Log | None = None, faults: FaultModel | None = None,
                 fault_config: FaultConfig | None = None, profile: Phases = NO_PHASES):
        """``faults``: the link faults; or ``fault_config``, seeded with the
        run's seed when the world's first tick tells it. ``profile``: where
        the time of each tick goes (``mesh.profile``), if measured."""
        super().__init__(keys, transport, log or Log(f"agent {agent_id}"), profile)
        self.scn = scn
        self.ids = tuple(a.id for a in scn.agents)
        if agent_id not in self.ids:
            raise MeshError(f"agent {agent_id} is not in scenario {scn.name!r} (ids {', '.join(map(str, self.ids))})")
        self.id = agent_id
        self.algorithm = algorithm
        self.timing = timing
        n, m = scn.G.shape
        self.p = int(scn.sensors().p[self.ids.index(agent_id)])
        # how far ahead of tick k the world's ticks and neighbours' messages are taken: lockstep one
        # tick (the guard's window two); real time further, for an agent that fell behind
        self.lead = 1 if timing.clock is None else realtime.LEAD_TICKS
        self.kept = AHEAD_KEPT if timing.clock is None else realtime.LEAD_TICKS + 2
        declared = estimators.get(algorithm)
        self.exchanged = declared.exchanged  # what its messages carry (``Estimator.exchanged``)
        self.receiver = Receiver(Guard(GuardConfig(
            keys.run_id, agent_id, frozenset(self.ids), n, m,
            information_check=declared.information_check, exchanged=declared.exchanged,
            **({} if timing.clock is None else {"max_lead": realtime.LEAD_TICKS})),
            profile=profile), faults, on_arrival=self.wake)
        self.counters = self.receiver.counters
        self.verdicts = TickVerdicts()  # per tick: who was fused, why the others were not
        self.fault_config = fault_config
        self.rejoining = False
        self.reports = {}    # k -> {sender: wire.Report}, listened to only while rejoining
        self.est: AgentEstimator | None = None
        self.ticks = {}      # k -> wire.Tick (k and k + 1; before joining, a few; real time: up to k + lead)
        self.tick_at = {}    # k -> when tick k reached this agent (monotonic; real time: its deadline's start)
        self.meas = {}       # k -> wire.Measurement (likewise)
        self.constants = None  # (K, seed, algorithm, topology, range) of the first tick taken
        self.alive = set()   # agent ids of the scenario with a liveliness token
        self.alive_tokens = {}  # agent id -> nonces of its processes' tokens
        self.claimed = False      # own alive token declared
        self._ready_token = None
        self._joins = 0           # ready tokens declared so far
        self.join_after = 0       # join at the first tick after this that counts this agent live
        self._join_wanted = True  # the main thread declares a (new) ready token
        self.rejoins = []         # (tick, source) of every re-initialisation
        self._worked = False      # has made an estimator once
        self._started_late = False  # ... first at a tick after 1, re-initialised (a restart, a late twin)
        self._reports_by = None   # joining: until when to wait for the neighbours' reports
        self.last_report = None   # (k, payload) of the last report sent
        self.K = None             # ticks in the run (the world's tick says)
        self.newest = 0           # newest tick heard of
        self.world_tokens = set()
        self.world_gone_at = math.inf
        self._woke_at = -math.inf  # when the main thread found it had been frozen
        self.linked = {}     # k -> ids of live agents in range at tick k (not this one), recent ticks
        self.world_seen = False
        self.world_ticking = False  # the world's "ticking" token: the run is past its start
        self.world_gone = False
        self.stopped = None
        self.k = 1           # the tick being worked on
        self.last_heard = time.monotonic()
        self.collecting = False    # tick k is open: own message out, neighbours' being collected
        self.own = None            # this agent's message of tick k while collecting
        self.own_payload = b""     # ... as published (it goes with the report: a recording's "as sent")
        self.deadline = math.inf   # end of the collection of tick k (monotonic)
        self._main_looks_at = 0.0  # when the main thread looks at the timeouts next (monotonic)
        self._advancing = False    # in _advance (a put may deliver to this process on the same thread)
        self._reports_subscribed = False

    # -- transport callbacks ---------------------------------------------------
    def _take_in(self, key: str | None, payload) -> None:
        """Lock held: every sample (world's messages, neighbours' messages,
        reports) and every liveliness change (``payload`` True or False);
        ``key`` None: a delayed copy came (``wake``)."""
        if key is None or self._handle(key, payload):
            self._advance()
            self._notify_main()

    def wake(self) -> None:
        """A delayed copy reached the inbox (the fault layer's thread): it may
        complete the tick being collected."""
        self._on_sample(None, None)

    def _notify_main(self) -> None:
        """Wake the main thread if there is something for it (lock held)."""
        if (self.est is None or self.stopped is not None or self.world_gone or self._join_wanted
                or self.failure is not None or self.deadline < self._main_looks_at):
            self._cv.notify_all()

    # -- the world's messages and liveliness ---------------------------------
    def _handle(self, key: str, payload) -> bool:
        """Take in one sample; False if it was dropped without changing
        anything a step waits for (a neighbour out of range, a rejection)."""
        kind, who = self.keys.parse(key)
        try:
            if kind == "msg":
                return self._gate(who, payload)
            elif kind == "tick":
                self.prof.begin()
                try:
                    t = wire.decode_tick(payload, run_id=self.keys.run_id, agents=len(self.ids))
                finally:
                    self.prof.end("decode")
                consts = (t.ticks, t.seed, t.algorithm, t.topology, t.comm_range)
                if t.tick < self.k or t.tick in self.ticks:
                    self.last_heard = time.monotonic()
                    if self.constants in (None, consts):
                        self._repeat_report(t.tick)  # a world that lost the reports of that tick sends it again
                    return True
                if self.est is not None and self.k + 1 < t.tick <= t.ticks and self.id not in t.live \
                        and consts == self.constants:  # the world went on without it (its router was gone)
                    self.newest = max(self.newest, t.tick)
                    self._resync(f"the world is at tick {t.tick} without this agent")
                problem = self._tick_problem(t)
                if problem is not None:
                    return self._refuse(kind, *problem)
                self.last_heard = time.monotonic()
                if self.constants is None:
                    self.constants = consts
                    guard = self.receiver.guard
                    guard.config = dataclasses.replace(guard.config, ticks=t.ticks)
                self.K, self.newest = t.ticks, max(self.newest, t.tick)
                if self.fault_config is not None and self.receiver.faults is None:
                    self.receiver.use_faults(FaultModel(self.fault_config, t.seed))
                self.ticks[t.tick] = t
                if self.timing.clock is not None:  # a copy after the deadline is late, even before the close
                    self.tick_at[t.tick] = now = time.monotonic()
                    self.receiver.inbox.due(t.tick, now + self.timing.clock.deadline_s)
                    for old in [j for j in self.tick_at if j not in self.ticks]:
                        del self.tick_at[old]
                # not live at a tick (joining later): linked to no one, nothing to fuse
                self.linked[t.tick] = ((set(neighbours(self.scn, self.id, t.positions)) & set(t.live)) - {self.id}
                                       if self.id in t.live else set())
                if self.id not in t.live and self.est is None:
                    self._joining(t.tick)
                self.receiver.release(t.tick, self.linked[t.tick])
                self._bound(self.ticks)
                if len(self.linked) > LINKS_KEPT + 2:
                    for old in [j for j in self.linked if j < self.k - LINKS_KEPT]:
                        del self.linked[old]
            elif kind == "meas":
                self.prof.begin()
                try:
                    mm = wire.decode_measurement(payload, run_id=self.keys.run_id, agent=self.id, p=self.p)
                finally:
                    self.prof.end("decode")
                if mm.tick < self.k:
                    return True
                problem = self._meas_problem(mm)
                if problem is not None:
                    return self._refuse(kind, *problem)
                self.last_heard = time.monotonic()
                self.meas.setdefault(mm.tick, mm)
                self._bound(self.meas)
            elif kind == "report" and self.rejoining and self.est is None and who in self.ids:
                n, m = self.scn.G.shape
                r = wire.decode_report(payload, run_id=self.keys.run_id, sender=who, n=n, m=m,
                                       ticks=self.constants and self.constants[0], agents=len(self.ids))
                if self.k - 1 <= r.tick <= self.k + 1:  # the re-initialisation reads tick k - 1
                    self.reports.setdefault(r.tick, {})[who] = r
                for old in [j for j in self.reports if j < self.k - 1]:
                    del self.reports[old]
            elif kind == "stop":
                self.stopped = wire.decode_stop(payload, run_id=self.keys.run_id)
            elif kind == "alive-world":
                self._on_world_token(nonce(key), bool(payload))
            elif kind == "ticking":
                self.world_ticking = bool(payload)
            elif kind == "alive" and who in self.ids:
                self._on_agent_token(who, nonce(key), bool(payload))
        except wire.Rejected as e:
            return self._refuse(kind, e.reason, e.detail)
        return True

    def _refuse(self, kind: str, reason: str, detail: str) -> bool:
        """Count a rejected message of the world (or a report), say it once
        per kind and reason."""
        self.counters.reject(reason)
        self.log.once((kind, reason), f"rejected a {kind} message: {reason}" + (f" ({detail[:200]})" if detail else ""))
        return False

    def _tick_problem(self, t: wire.Tick):
        """None if the world's tick ``t`` (not before k, not seen yet) may be
        taken, else (reason, detail): it must carry the run's constants as
        the first tick taken did, lie within the run, and be for k or k + 1
        (before this agent has joined, any later tick: a restart joins the
        world where it is)."""
        consts = (t.ticks, t.seed, t.algorithm, t.topology, t.comm_range)
        if self.constants is not None and consts != self.constants:
            return "constants", f"tick {t.tick} says (K, seed, algorithm, topology, range) = {consts}, " \
                                f"the run {self.constants}"
        if t.tick > t.ticks or (t.tick > self.k + self.lead and self.est is not None):
            return "tick-future", f"tick {t.tick} at tick {self.k} of {t.ticks}"
        return None

    def _meas_problem(self, mm: wire.Measurement):
        """None if this agent's measurement ``mm`` (not before k) may be
        taken: for k or k + 1 (before joining, any later tick of the run),
        every value within ``GuardConfig.max_abs``; else (reason, detail)."""
        K = self.constants[0] if self.constants is not None else math.inf
        if mm.tick > K or (mm.tick > self.k + self.lead and self.est is not None):
            return "tick-future", f"measurement of tick {mm.tick} at tick {self.k}"
        limit = self.receiver.guard.config.max_abs
        if mm.has and not all(abs(v) <= limit for v in mm.y.tolist()):
            return "magnitude", f"measurement of tick {mm.tick}: a value beyond {limit:.3g}"
        return None

    def _bound(self, by_tick: dict) -> None:
        """Keep a per-tick map of the world's messages to ticks from k - 1
        (a restart re-initialises from tick k - 1) and at most
        ``AHEAD_KEPT`` of them (only a joining agent takes more than two;
        real time: the lead window)."""
        for old in [j for j in by_tick if j < self.k - 1]:
            del by_tick[old]
        while len(by_tick) > self.kept:
            del by_tick[max(by_tick)]

    def _gate(self, sender, payload) -> bool:
        """A neighbour's message (``sender``: its key's id, parsed once) into
        the receive path (``diskf_mesh.mesh.receive``): the guard decodes it once
        and rejects (counts) what is malformed or off the window around tick
        k, the range gate drops (counts "out_of_range") one from an agent not
        linked to this one at the message's tick (one whose tick the world
        has not opened here yet waits for it), and the inbox holds the rest
        until the tick is fused. False if it was dropped."""
        self.receiver.advance(self.k)
        return self.receiver.on_payload(sender, payload, self.linked)

    def _check_world(self, deadline: float, what: str) -> None:
        """Main thread: a failure of a callback, or the world gone or silent
        past ``deadline`` (its last word + ``--world-timeout``)."""
        self._raise_failure()
        now = time.monotonic()
        if now > deadline:
            if self.world_gone:
                raise MeshError(f"the world is gone (its liveliness token went {now - self.world_gone_at:.0f} s ago "
                                f"and did not come back) while {what}")
            raise MeshError(f"no word from the world for {self.timing.world_timeout:g} s while {what}")

    def _woke(self, late: float) -> None:
        """Main thread: waking much later than planned means this process
        was frozen (SIGSTOP): noted, for ``_on_world_token``."""
        if late > FREEZE_S:
            self._woke_at = time.monotonic()

    def _was_frozen(self) -> bool:
        """In a callback: this process has just been frozen (its main thread
        is long overdue, or found it had overslept a moment ago)."""
        now = time.monotonic()
        return now - self._main_looks_at > FREEZE_S or now - self._woke_at < WOKE_S

    # -- liveliness ----------------------------------------------------------
    def _on_world_token(self, nonce_: str, up: bool) -> None:
        """The world's token came or went. Gone while this process was frozen
        past zenoh's lease: the world has dropped this agent from the run, so
        it rejoins (``_resync``). Gone otherwise: wait for it (a frozen world
        comes back), at most ``--world-timeout``."""
        was_gone = self.world_gone
        (self.world_tokens.add if up else self.world_tokens.discard)(nonce_)
        self.world_seen |= bool(self.world_tokens)
        self.world_gone = self.world_seen and not self.world_tokens
        if self.world_gone and not was_gone:
            self.world_gone_at = time.monotonic()
            if self.est is not None and self._was_frozen():
                self._resync("this process was frozen past zenoh's lease")
        elif was_gone and not self.world_gone:
            self.world_gone_at = math.inf
            self.log.info(f"the world is back (at tick {self.newest})")

    def _on_agent_token(self, who: int, nonce_: str, up: bool) -> None:
        """An agent's token came or went. One of this agent's id that appears
        after this one declared its own: two processes started at once. This
        one leaves if it joined the run late (``_late``), or if the other's
        nonce is smaller (an earlier start) and this one has not worked on a
        tick yet; one that works since tick 1 keeps the id (its estimate is
        the engine's, a late twin's is not)."""
        if who not in self.ids:
            return
        held = self.alive_tokens.setdefault(who, set())
        (held.add if up else held.discard)(nonce_)
        (self.alive.add if held else self.alive.discard)(who)
        if not (up and who == self.id and self.claimed and nonce_ != self.nonce and self.failure is None):
            return
        if self._late():
            self.failure = self._duplicate(nonce_, "it holds this id in the run this one joined late")
        elif nonce_ < self.nonce and not self._worked:
            self.failure = self._duplicate(nonce_, "started earlier")

    def _late(self) -> bool:
        """Lock held: this process found the run in progress before it ever
        worked, or first worked from a re-initialisation (a neighbour's
        estimate): another process of its id that is alive keeps the id,
        however their nonces compare (that one may be working since tick 1,
        and its estimate is the engine's; this one's never is)."""
        return self._started_late or (self.rejoining and not self._worked)

    def _duplicate(self, other: str, how: str) -> DuplicateProcess:
        return DuplicateProcess(f"agent id {self.id} is already held by another process in run "
                                f"{self.keys.run_id!r} (token nonce {other}, {how}): this one leaves")

    def claim_id(self) -> None:
        """Main thread: declare this process's alive token, unless another
        process already holds this id (a liveliness query, then what the
        token watch has seen): then this one is the second, and leaves."""
        others = self._other_nonces(self.keys.alive(self.id))
        with self._cv:
            others |= self.alive_tokens.get(self.id, set())
            others.discard(self.nonce)
            if others:  # tell the world (it counts duplicates), then leave
                self.transport.put(self.keys.duplicate(self.id), self.nonce.encode())
                time.sleep(DUPLICATE_SAY_S)
                raise self._duplicate(min(others), "found before this one declared its own")
            self.claimed = True
        self.transport.declare_token(self.keys.alive(self.id, self.nonce))

    def wait_world(self) -> None:
        """Main thread: until the world's token is seen (this process is on
        the network), at most ``--world-timeout``."""
        with self._cv:
            self.last_heard = time.monotonic()
            deadline = self.last_heard + self.timing.world_timeout
            self._wait_until(lambda: self.world_seen or self.stopped is not None, deadline,
                             lambda: self._check_world(deadline, "waiting for the world"))

    def _resync(self, why: str) -> None:
        """Lock held: this agent is out of the run (the world dropped it, or
        it missed a tick): drop the estimator and rejoin as a restarted
        agent does (the main thread declares a new ready token)."""
        if self.est is None:
            return
        self.log.info(f"tick {self.k}: out of the run ({why}): rejoining")
        self.est, self.rejoining, self.join_after, self._join_wanted = None, True, None, True
        self.collecting, self.own, self.deadline = False, None, math.inf
        self.k = max(self.k, self.newest + 1)
        self.receiver.advance(self.k)
        for by_tick in (self.ticks, self.meas):
            for old in [j for j in by_tick if j < self.k]:
                del by_tick[old]
        self.reports.clear()
        self._cv.notify_all()

    def _repeat_report(self, tick: int) -> None:
        """The world sent tick ``tick`` again (it lost the reports of that
        tick: it was frozen): send it this agent's report of it again."""
        if self.last_report is not None and self.last_report[0] == tick == self.k - 1:
            self.transport.put(self.keys.report(self.id), self.last_report[1])

    # -- the steps -----------------------------------------------------------
    def _advance(self) -> None:
        """Take every step the state allows (lock held): open tick k once the
        world's tick and this agent's measurement are in, close it once the
        neighbours' messages are (or the collection ends otherwise)."""
        if self._advancing:  # a sample our own put delivered on this thread: the loop below goes on
            return
        self._advancing = True
        try:
            self._steps()
        finally:
            self._advancing = False

    def _steps(self) -> None:
        while self.failure is None and self.est is not None:
            k = self.k
            if not self.collecting:
                if self.stopped is not None:
                    return
                if k in self.ticks and self.id not in self.ticks[k].live:
                    return self._resync(f"the world counts this agent out at tick {k}")
                if k not in self.ticks and any(j > k for j in self.ticks):
                    return self._resync(f"tick {k} never came")
                if k not in self.ticks or k not in self.meas:
                    return
                self._open(k)
            if not (self.linked[k] <= self.receiver.accounted(k) or self.stopped is not None
                    or any(j > k for j in self.ticks) or time.monotonic() >= self.deadline):
                return
            self._close(k)

    def _open(self, k: int) -> None:
        """Local step of tick k, own message out."""
        prof = self.prof
        mm = self.meas.pop(k)
        self.receiver.advance(k)
        prof.begin()
        self.own = self.est.local(k, mm.has, mm.y)
        prof.end("local")
        prof.begin()
        payload = self.own_payload = wire.encode(self.keys.run_id, self.id, k, self.own, self.exchanged)
        prof.end("encode")
        prof.begin()
        # addressed to the agents it fuses at tick k: links are symmetric (range, ring, all), so
        # these are the agents that fuse it
        self.transport.put(self.keys.msg(self.id, to=self.linked[k]), payload)
        prof.end("publish")
        self.counters.published += 1
        self.collecting = True
        clock = self.timing.clock
        if clock is None:
            self.deadline = time.monotonic() + self.timing.collect_timeout
        else:  # from when tick k came: an agent that fell behind closes it at once
            self.deadline = self.tick_at.pop(k, time.monotonic()) + clock.deadline_s
        prof.waiting = "wait-neighbours"

    def _close(self, k: int) -> None:
        """Fuse what came for tick k, report to the world."""
        prof = self.prof
        heard, rejected = self.receiver.accounted(k), self.receiver.refusals(k)
        fused = dict(self.receiver.take(k, self.linked[k]))
        failed = False
        prof.begin()
        try:
            out = self.est.fuse(k, self.own, fused)
        except np.linalg.LinAlgError:  # well-formed messages that still break fusion: keep our own estimate
            self.counters.reject("fusion", len(fused))
            self.log.once("fusion", f"tick {k}: fusion failed; fused this agent's own message alone")
            out = self.est.fuse(k, self.own, {})
            failed = True
        finally:
            prof.end("fuse")
        counters = self.receiver.snapshot(cap=wire.count_bound(self.constants[0]))
        fused_ids, not_fused = self.verdicts.of_tick(k, self.linked[k], heard, rejected, fused, failed)
        prof.begin()
        report = wire.encode_report(self.keys.run_id, self.id, k, out.x[0, 0], out.P[0, 0], out.d[0, 0],
                                    out.d_valid[0, 0], counters, fused_ids, not_fused, self.own_payload)
        prof.end("encode")
        prof.begin()
        self.transport.put(self.keys.report(self.id), report)
        prof.end("publish")
        self.last_report = (k, report)
        prof.tick()
        prof.waiting = "wait-world"
        self.ticks.pop(k, None)
        self.linked.pop(k - LINKS_KEPT, None)
        self.collecting, self.own, self.deadline = False, None, math.inf
        self.k = k + 1

    # -- protocol ----------------------------------------------------------
    def start(self) -> None:
        """Subscribe and watch the tokens; the own tokens come later
        (``claim_id``, ``_join_setup``)."""
        k = self.keys
        for key in (k.tick, k.meas(self.id), k.stop):
            self.transport.subscribe(key, self._on_sample)
        self.transport.subscribe(k.msg_to(self.id), self._on_sample)  # what its neighbours send it
        self.transport.watch_tokens(f"{k.root}/alive/**", self._on_sample)
        self.transport.watch_tokens(k.ticking, self._on_sample)

    def _join_setup(self) -> None:
        """Main thread, without the lock (no transport call is made from a
        callback): declare a ready token when one is wanted. At the start,
        once the world and every agent are seen; joining a run in progress
        (a restart, or a resync after a freeze) once the agents the world
        counts live are seen (at most ``PEERS_WAIT_S``), after withdrawing
        the old token and subscribing to the reports, to re-initialise from
        a neighbour's. The world counts a token that appears mid-run live
        from its tick after next, so the reports of the tick before this
        agent's first one reach it; this agent joins at the first tick after
        the newest it knew of when it declared."""
        with self._cv:
            if not self._join_wanted:
                return
            self._join_wanted = False
            old, self._ready_token = self._ready_token, None
            deadline = self.last_heard + self.timing.world_timeout
            self._wait_until(lambda: (self.world_seen and (self.alive >= set(self.ids) or self.world_ticking))
                             or self.stopped is not None or self.failure is not None, deadline,
                             lambda: self._check_world(deadline, "waiting for the world and every agent"))
            if self.world_ticking and self.est is None:
                self._joining(self.newest)
            subscribe = self.rejoining and not self._reports_subscribed
        if old is not None:
            old.undeclare()
        if subscribe:
            self._reports_subscribed = True
            self.transport.subscribe(self.keys.report("*"), self._on_sample)
        with self._cv:
            if self.rejoining:
                self._wait_until(lambda: not self.ticks or set(self.ticks[max(self.ticks)].live) - {self.id}
                                 <= self.alive or self.stopped is not None or self.failure is not None,
                                 time.monotonic() + PEERS_WAIT_S)
            self.join_after = self.newest
            self._joins += 1
        self._ready_token = self.transport.declare_token(self.keys.ready(self.id, f"{self.nonce}.{self._joins}"))

    def _joining(self, tick: int) -> None:
        """The world is at ``tick`` without this agent: a restart joining a run
        in progress. It cannot join before the next tick; meanwhile it listens
        to the others' fused estimates, to re-initialise from one (the main
        thread subscribes: ``_join_setup``)."""
        self.k = max(self.k, tick + 1)
        self.receiver.advance(self.k)  # the guard's window: the tick it may join at
        if not self.rejoining:
            self.rejoining = True
            self.log.info("the run is in progress: rejoining" + (f" (at tick {tick})" if tick else ""))

    def _join(self) -> bool:
        """Main thread, lock held: the first tick this agent works on. Once
        the world counts it live at a tick k after ``join_after`` (1, or the
        tick after next once it saw a rejoining agent's ready token) and tick
        k's messages are in, make the estimator (a rejoining agent
        re-initialises it) and start working."""
        if self.join_after is None:
            return False
        twins = self.alive_tokens.get(self.id, set()) - {self.nonce}
        if self._late() and twins and self.failure is None:  # seen before this one found the run in progress
            self.failure = self._duplicate(min(twins), "it holds this id in the run this one joined late")
            return False
        mine = [t for t, tk in self.ticks.items() if t > self.join_after and self.id in tk.live]
        if not mine:
            return False
        self.k = min(mine)
        for by_tick in (self.ticks, self.meas):
            for t in [t for t in by_tick if t < self.k]:
                del by_tick[t]
        if self.k not in self.meas or not self._reports_in(self.k):
            return False
        est = self._make_estimator(self.ticks[self.k])
        if not self._worked:
            self._worked = True
            self._started_late = self.rejoining and self.k > 1
            self.prof.start()  # measured from the first tick this agent works on
        self.est = est
        if self.rejoining and self.k > 1:  # at tick 1 (a run started without some agents) all start alike
            self._reinitialise(self.k)
        return True

    def _reports_in(self, k: int) -> bool:
        """A rejoining agent joining at tick k: whether the reports of tick
        k - 1 of the agents in range then (and live at k) are in, to
        re-initialise from the best of them; a report may come after the
        world's tick k (another path), so it waits at most
        ``REPORTS_WAIT_S``."""
        if not self.rejoining or k == 1:
            return True
        now = time.monotonic()
        if self._reports_by is None:
            self._reports_by = now + REPORTS_WAIT_S
        want = rejoin.in_range(self.scn, self.id, k - 1) & set(self.ticks[k].live)
        if want <= set(self.reports.get(k - 1, ())) or now >= self._reports_by:
            self._reports_by = None
            return True
        return False

    def _reinitialise(self, k: int) -> None:
        """A rejoining agent's estimate of tick k - 1 (``agents.rejoin``): the
        agents in range then follow from the scenario's motion, the ones
        live then from who reported; the world is told the source."""
        near = rejoin.in_range(self.scn, self.id, k - 1) if k > 1 else set()
        src = rejoin.reinitialise(self.est, self.reports.get(k - 1, {}), near)
        self.rejoins.append((k, src))
        self.transport.put(self.keys.rejoin(self.id), wire.encode_rejoin(self.keys.run_id, self.id, k, src))
        self.log.info(f"joined at tick {k}, re-initialised from "
                      + (f"agent {src}'s fused estimate of tick {k - 1}" if src is not None else "the prior"))
        self.reports.clear()

    def _make_estimator(self, t: wire.Tick) -> AgentEstimator:
        mine = (self.algorithm, self.scn.topology, self.scn.comm_range)
        theirs = (t.algorithm, t.topology, t.comm_range)
        if mine != theirs:
            raise MeshError(f"the world runs algorithm {t.algorithm}, topology {t.topology}, range {t.comm_range:g}; "
                            f"this agent {mine[0]}, {mine[1]}, {mine[2]:g}: start both with the same flags")
        return AgentEstimator(self.scn, self.id, self.algorithm, t.ticks, t.seed)

    def run(self) -> int:
        """The run, to the world's stop; returns the ticks worked on. Raises
        ``MeshError`` (``DuplicateProcess``) unless the stop is the world's
        "done" at the run's last tick."""
        self.start()
        self.wait_world()
        self.claim_id()
        while True:
            self._join_setup()
            with self._cv:
                if self.est is None and self.stopped is None:
                    self._join()
                self._advance()
                self._raise_failure()
                if self.stopped is not None and not self.collecting:
                    break
                what = ("waiting to join" if self.est is None else
                        f"collecting tick {self.k}" if self.collecting else f"waiting for tick {self.k}")
                until = self.last_heard + self.timing.world_timeout
                self._check_world(until, what)
                self._wait(min(until, self.deadline))
        self.prof.stop()
        self.receiver.close()
        st = self.stopped
        if st.why != "done" or st.tick != self.K:
            raise MeshError(f"the world stopped the run at tick {st.tick}"
                            + (f" of {self.K}" if self.K else "") + f": {st.why}")
        return self.k - 1


# --------------------------------------------------------------------------
# command line
# --------------------------------------------------------------------------
def register(subparsers) -> None:
    p = subparsers.add_parser("agent", help="one agent process of a mesh run",
                              description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--id", type=int, required=True, dest="agent_id", help="this agent's id in the scenario")
    runspec.add_arguments(p)
    p.add_argument("--collect-timeout", type=float, default=AgentTiming.collect_timeout, metavar="S",
                   help="seconds to wait for the neighbours' messages of a tick (default %(default)s)")
    p.add_argument("--world-timeout", type=float, default=AgentTiming.world_timeout, metavar="S",
                   help="seconds of silence from the world before giving up (default %(default)s)")
    p.add_argument("--profile", metavar="DIR",
                   help="measure where each tick's time goes (decode, guard, local, fuse, encode, publish, "
                        "wait) and write DIR/agent-<id>.json at exit")
    realtime.add_arguments(p, world=False)
    add_fault_arguments(p)
    zenoh_config.add_arguments(p)
    p.set_defaults(func=run)


def batch_scheduling() -> None:
    """Put this process (its threads to come: call it before zenoh starts
    them) under Linux's SCHED_BATCH: a woken agent thread then does not
    preempt the thread running on its core, e.g. the world's sender halfway
    through opening a tick for every agent. On two cores shared by ten
    processes this measured ~10-20 % more ticks per second and fewer context
    switches; the world keeps the normal policy. Elsewhere, a no-op."""
    try:
        os.sched_setscheduler(0, os.SCHED_BATCH, os.sched_param(0))
    except (AttributeError, OSError):
        pass


def run(args: argparse.Namespace) -> int:
    exit_on_sigterm()  # first thing: stopped at any moment, its session closed (mesh.stopping)
    spec = runspec.from_args(args)
    scn = spec.load()
    clock = realtime.from_args(args)
    log = Log(f"agent {args.agent_id}")
    if clock is None:  # real time wants the deadline's wake-up at once, not after the running thread's slice
        batch_scheduling()
    zenoh = zenoh_config.from_args(args, credentials.agent_identity(args.agent_id), spec.run_id)
    prof = Phases(AGENT_PHASES, f"agent {args.agent_id}") if args.profile else NO_PHASES
    try:
        with ZenohTransport(zenoh) as transport:
            agent = Agent(scn, args.agent_id, spec.algorithm, Keys(spec.run_id), transport,
                          AgentTiming(args.collect_timeout, args.world_timeout, clock), log,
                          fault_config=faults_from_args(args, scn.faults), profile=prof)
            agent.run()
    except MeshError as e:
        log.error(str(e))
        return e.status
    finally:
        if prof:
            prof.write(args.profile, f"agent-{args.agent_id}")
    return 0


if __name__ == "__main__":
    from diskf_mesh.cli import main as cli

    sys.exit(cli.run_one("agent", __spec__.name))
