"""One agent's protocol as a state machine: events in, effects out (``mesh.protocol.events``).

``AgentMachine`` holds everything an agent process knows about its run and
nothing else: no transport, no thread, no clock read. A shell
(``mesh.process.shell`` over zenoh and the wall clock, or the simulated network
``mesh.simulated.simnet``) hands it one event at a time with the time ``now`` and
carries out the effects it returns, in order::

    m = AgentMachine(scn, agent_id, estimators.get(name), keys, nonce)
    effects = m.start(now)            # Subscribe, WatchTokens, SetTimer
    event = m.read(key, payload)      # a sample, decoded once at the edge (``mesh.protocol.intake``)
    effects = m.handle(event, now)    # Publish, DeclareToken, Ask, ..., Finish

The machine never sees bytes of the world's or a neighbour's: ``read``
turns each sample into a typed event (``TickArrived``,
``MeasurementArrived``, ``StopArrived``, ``MessageArrived``,
``Unreadable``: ``mesh.protocol.events``) before ``handle``.

One tick k, in the order the code below runs it (lockstep; real time
differs only in when a tick is closed, ``mesh.protocol.clock``):

 1. ``_on_meas``, ``_on_tick``  the world's measurement of tick k and its
    tick (every position, the live set) come in, decoded at the edge, and
    are taken if they fit the run (``_meas_problem``,
    ``_tick_problem``). The tick gives the agents linked at k (``linked``)
    and lets the neighbours' messages of k that came before it onto their
    links (``Receiver.release``).
 2. ``_open(k)``  once both are in: the local step
    (``AgentEstimator.local``, handed to the shell as ``Work``: its result
    comes back as ``Worked`` to ``_opened``), ONE message (``wire.encode``),
    published on a key addressed to the linked agents; the collection of
    tick k starts (``SetTimer("collect")`` at its deadline).
 3. ``_on_msg``  each neighbour's message (decoded and its values checked
    at the edge: ``Guard.read``) goes through the receive path
    (``mesh.protocol.receive``: the guard's window, range gate, the link's faults, inbox); a copy
    the fault layer delays comes back at ``Timer("delay")``.
 4. ``_close(k)``  once every linked sender is accounted for (arrived,
    lost, refused), at the collect timer, when a later tick is already in,
    or at the stop: fuse what came (``AgentEstimator.fuse``, as ``Work``;
    ``_closed`` takes its result), report to the
    world (``wire.encode_report``: the fused estimate, the counters, who was
    fused and why the others were not, the digests of the messages fused and
    of its own as published; never a message itself).

``_step`` takes every step the state allows after every event, so a
sample that completes a tick closes it (and may open the next) at once.
A step handed out as ``Work`` is the last effect of its list: the machine
takes no step until its ``Worked`` comes back, which a shell hands it
before any other event (a process's shell at once, the simulated network
once the steps of that instant have run together).

Before its first tick (``_start_up``): wait for the world's token; claim the
agent id (a liveliness query, ``AskTokens``: another process holding it
means this one leaves); declare the alive token; once the world and
every agent are seen (or the world is already ticking: a restart), declare
a ready token; join at the first tick the world counts this agent live
(``_join``). A (re)joining agent asks the world for its starting estimate
(``Ask`` on ``Keys.start``, ``mesh.protocol.rejoin``) and starts from the answer;
one that found the run in progress first asks once more whether another
process holds its id (``_on_confirm``). Whichever way a process finds its
id held (the claim, another token, the confirm, a tick naming another
holder), it tells the world (``Keys.duplicate``) and leaves with exit 2
(``_duplicate``).
An agent that finds itself out of the run (the world counts it out, a tick
never came, or it was frozen past zenoh's lease: ``Woke`` then the world's
token going) drops its estimator and rejoins the same way (``_resync``).

An estimator that diverges (its covariance no longer positive definite,
or a fused estimate the world would refuse: ``wire.report_problem``) ends
the agent at that tick with one line naming the tick and why: nothing it
could send would be taken, and its token going lets the world close the
tick at once instead of waiting out ``--tick-timeout`` every tick.

Exit (``Finish``): 0 only when the world says stop with "done" at the run's
last tick; 2 when another process holds this agent's id; 3 when its
estimator diverged (it told the world, whose run goes on without it and
ends ``incomplete``, its missing ticks saying "diverged"); 1 otherwise (the
world stopped the run early, it has been gone or silent for
``world_timeout`` seconds, a mismatch of the run's settings, an interrupt).

May import: core, estimators, data, engine (the mesh layer).
"""
from __future__ import annotations

import collections
import functools
import itertools
import math
from dataclasses import dataclass

import numpy as np

from diskf_mesh.core import exits
from diskf_mesh.data.faults import FaultConfig, FaultModel
from diskf_mesh.data.lies import Liars
from diskf_mesh.data.scenario import Scenario
from diskf_mesh.estimators.base import Estimator
from diskf_mesh.mesh.protocol import clock as realtime
from diskf_mesh.mesh.wire import codec as wire
from diskf_mesh.mesh.protocol.estimator import AgentEstimator, neighbours
from diskf_mesh.mesh.protocol.events import (FREEZE_S, Arrivals, Ask, AskTokens, DeclareToken, DropToken, Finish, Interrupt,
                                             MeasurementArrived, MessageArrived, Publish, Reply, Sample, SetTimer,
                                             StopArrived, Subscribe, TickArrived, Timer, Token, TokenBatch, Tokens,
                                             Unreadable, WatchTokens, Woke, Work, Worked)
from diskf_mesh.mesh.protocol.guard import Guard, GuardConfig
from diskf_mesh.mesh.protocol.intake import Intake
from diskf_mesh.mesh.wire.keys import Keys, nonce as nonce_of
from diskf_mesh.mesh.protocol.log import Log
from diskf_mesh.mesh.protocol.profile import NO_PHASES, Phases
from diskf_mesh.mesh.protocol.receive import Receiver
from diskf_mesh.mesh.protocol.roster import Roster, parse_batch
from diskf_mesh.mesh.protocol.shared import Shared
from diskf_mesh.mesh.protocol.verdicts import TickVerdicts

LINKS_KEPT = 16  # link sets of past ticks kept, to gate late messages too
AHEAD_KEPT = 4   # ticks (and measurements) kept ahead of joining: a restart sees the world's latest
WOKE_S = 3.0     # a world token that goes within this long of waking from a freeze: we were dropped
PEERS_WAIT_S = 5.0  # a (re)joining agent waits at most this long to see the live agents
DUPLICATE_SAY_S = 0.2  # a duplicate's word to the world is on the wire before it leaves
CLAIM_S = 1.0    # the liveliness query for another process holding this agent's id
ASK_S = 5.0      # a (re)joining agent waits this long for the world's answer, then asks again

OK, FAILED, DUPLICATE = 0, 1, 2  # exit statuses (``Finish.code``)
ARRIVALS = frozenset({TickArrived, MeasurementArrived, StopArrived, MessageArrived, Unreadable, Sample})


@dataclass(frozen=True)
class AgentTiming:
    collect_timeout: float = 5.0   # wait for neighbours' messages after publishing
    world_timeout: float = 60.0    # longest silence from the world before giving up
    clock: realtime.Clock | None = None  # real time (``mesh.protocol.clock``): fuse at its deadline; None: lockstep


class AgentMachine:
    """The protocol of agent ``agent_id`` of scenario ``scn`` in the run of
    ``keys`` (module docstring) with ``estimator``, the class
    ``estimators.get`` resolved.

    ``nonce``: this process's token suffix (``keys.new_nonce()`` in a real
    process; any distinct, sortable string in a simulation). ``faults``: the
    link faults into this agent, a ``FaultConfig`` (seeded with the run's
    seed when the world's first tick tells it) or a seeded ``FaultModel``.
    ``log``: its one-line messages; ``profile``: where the time of each tick
    goes (``mesh.protocol.profile``), if measured; ``shared``: the decodes
    other machines in this process made of the same payloads
    (``mesh.protocol.shared``: the simulated network). ``ticks`` is the number of ticks
    worked on so far."""

    batches_tokens = True  # takes ``TokenBatch`` (the simulated network's casts of many tokens)
    batches_arrivals = True  # takes ``Arrivals`` (the simulated network's samples of one instant)

    def __init__(self, scn: Scenario, agent_id: int, estimator: type[Estimator], keys: Keys, nonce: str,
                 timing: AgentTiming = AgentTiming(), faults: FaultConfig | FaultModel | None = None,
                 log: Log | None = None, profile: Phases = NO_PHASES, shared: Shared | None = None):
        self.scn, self.keys, self.nonce, self.timing = scn, keys, nonce, timing
        self.ids = scn.ids  # shared by every machine of the run, as ``scn.id_set``
        if agent_id not in self.ids:
            raise ValueError(f"agent {agent_id} is not in scenario {scn.name!r} "
                             f"(ids {', '.join(map(str, self.ids))})")
        self.id = agent_id
        self.estimator = estimator  # the class ``estimators.get`` resolved, once for the run
        self.algorithm = estimator.name
        self.log = log or Log(f"agent {agent_id}")
        self.prof = profile
        n, m = scn.G.shape
        self.n, self.m = n, m
        self.p = int(scn.sensors().p[self.ids.index(agent_id)])
        # how far ahead of tick k the world's ticks and neighbours' messages are taken: lockstep one
        # tick (the guard's window two); real time further, for an agent that fell behind
        self.lead = 1 if timing.clock is None else realtime.LEAD_TICKS
        self.kept = AHEAD_KEPT if timing.clock is None else realtime.LEAD_TICKS + 2
        self.exchanged = estimator.exchanged  # what its messages carry (``Estimator.exchanged``)
        self.liars = Liars(scn.lies, (agent_id,), n, scn.position_dims)  # this agent's lies, if it is a liar
        guard = Guard(GuardConfig(keys.run_id, agent_id, scn.id_set, n, m,
                                  information_check=estimator.information_check, exchanged=estimator.exchanged,
                                  **({} if timing.clock is None else {"max_lead": realtime.LEAD_TICKS})),
                      profile=profile, shared=shared)
        self.intake = Intake(keys, agent_id, self.p, len(self.ids), guard, profile)  # ``read``: the edge
        self.receiver = Receiver(guard, faults)
        self.counters = self.receiver.counters
        self.verdicts = TickVerdicts()  # per tick: who was fused, why the others were not
        self._qids = itertools.count(1)
        self._out: list = []      # the effects of the event being handled

        # -- the run, as the world's messages tell it
        self.constants = None     # (K, seed, algorithm, topology, range) of the first tick taken
        self.K = None             # ticks in the run
        self.newest = 0           # newest tick heard of
        self.ticks = {}           # k -> wire.Tick (k and k + 1; joining: a few; real time: up to k + lead)
        self.tick_at = {}         # real time: k -> when tick k came (its deadline's start)
        self.meas = {}            # k -> wire.Measurement (likewise)
        self.linked = {}          # k -> ids of live agents in range at tick k (not this one), recent ticks
        self.stopped = None       # the world's stop (wire.Stop)
        self.last_heard = 0.0     # when the world was last heard
        # -- liveliness
        self.world_tokens = set()
        self.world_seen = False
        self.world_gone = False
        self.world_gone_at = math.inf
        self.world_ticking = False  # the world's "ticking" token: the run is past its start
        self.alive = Roster(self.ids, scn.places, agent_id)  # the agents with an alive token
        self._woke_at = -math.inf   # when this process found it had been frozen
        # -- start-up and joining
        self.phase = "world"      # world, claim, gather, peers, joining, leaving, finished
        self._claim_qid = None
        self._leaving = ""        # why this process leaves (another holds its id), after its word to the world
        self.claimed = False      # own alive token declared
        self._ready_key = None    # own ready token's key
        self._joins = 0           # ready tokens declared so far
        self._peers_until = math.inf
        self.join_after = None    # join at the first tick after this that counts this agent live
        self.rejoining = False    # joining a run in progress: starts from the world's answer
        self._asked = None        # (qid, tick, until when) of the query for the starting estimate
        self._start = None        # (tick, wire.Start or None) the world's answer (None: the prior)
        self._confirm_qid = None  # a late joiner's second liveliness query for its id, just before it joins
        self._confirmed = False   # ... answered: no other process holds the id
        self.rejoins = []         # (tick, source) of every re-initialisation
        self._worked = False      # has made an estimator once
        self._started_late = False  # ... first at a tick after 1, re-initialised (a restart, a late twin)
        # -- the tick being worked on
        self.est: AgentEstimator | None = None
        self.k = 1                # the tick being worked on
        self.collecting = False   # tick k is open: own message out, neighbours' being collected
        self.own = None           # this agent's message of tick k while collecting
        self._work = None         # the Work handed out, until its Worked comes back
        self._waiting = collections.deque()  # arrivals of an ``Arrivals`` not taken yet (a Work came first)
        self._closing = None      # (heard, rejected, fused, failed) of the tick being fused
        self.own_digest = b""     # ... the digest of its payload as published (in the report)
        self.deadline = math.inf  # end of the collection of tick k
        self.last_report = None   # (k, payload) of the last report sent
        self._delay_at = math.inf  # when the delay timer is set for (inf: not set)
        self._near_key, self._near_ids = None, frozenset()  # ``_near``: the last positions and their answer
        self._linked_key, self._linked_ids = (None, None), frozenset()  # ``_live_near``: likewise
        self.finish: Finish | None = None

    @property
    def ticks_worked(self) -> int:
        return self.k - 1 if self._worked else 0

    # ======================================================================
    # the interface (mesh.protocol.events)
    # ======================================================================
    def start(self, now: float) -> list:
        """What this agent listens to, and the world's silence timer."""
        k = self.keys
        self.last_heard = now
        self._out = out = [Subscribe(key) for key in (k.tick, k.meas(self.id), k.stop, k.msg_to(self.id))]
        out += [WatchTokens(f"{k.root}/alive/**"), WatchTokens(k.ticking)]
        self._world_timer()
        self._step(now)
        return out

    def read(self, key: str, payload: bytes):
        """A sample on one of this agent's keys as the event ``handle``
        takes (``mesh.protocol.intake``: decoded once, at the edge)."""
        return self.intake.read(key, payload)

    def read_all(self, samples) -> tuple:
        """``read`` of each of ``samples`` (``Sample`` events), in order:
        what ``Arrivals`` carries."""
        return self.intake.read_all(samples)

    def handle(self, event, now: float) -> list:
        """Take in one event at ``now`` (a sample as ``read`` made it);
        returns the effects, in order."""
        self._out = out = []
        if self.finish is not None:
            return out
        kind = type(event)
        if kind in ARRIVALS:
            if self._on_arrival(event, now):
                self._step(now)
            return out
        if kind is Arrivals:
            self._waiting.extend(event.events)
            self._take_arrivals(now)
            return out
        if kind is Token:
            self._on_token(event.key, event.up, now)
        elif kind is TokenBatch:
            self._on_tokens(event.keys, event.up, now)
        elif kind is Timer:
            self._on_timer(event.name, now)
        elif kind is Reply:
            self._on_reply(event.qid, event.payload)
        elif kind is Tokens:
            if event.qid == self._confirm_qid:
                self._on_confirm(event.keys, now)
            else:
                self._on_claim(event.qid, event.keys, now)
        elif kind is Worked:
            if event.work is not self._work:
                return out
            self._work = None
            if event.work.step == "local":
                self._opened(self.k, event.result, now)
            else:
                self._closed(self.k, event.result, now)
        elif kind is Woke:
            if event.late > FREEZE_S:
                self._woke_at = now
        elif kind is Interrupt:
            self._say_stopped("interrupted", f"stopped by {event.why}")
            self._finish("interrupted", FAILED, f"stopped by {event.why}")
            return out
        self._step(now)
        if self._waiting:
            self._take_arrivals(now)
        return out

    @property
    def waiting(self) -> int:
        """Arrivals of an ``Arrivals`` event not taken yet: a step handed
        out as ``Work`` on an earlier one holds them until its ``Worked``
        (or the process finished: they never will be)."""
        return len(self._waiting)

    def _take_arrivals(self, now: float) -> None:
        """Take the waiting arrivals in order, each as ``handle`` takes one
        alone, until a step is handed out as ``Work`` or the agent finishes."""
        waiting = self._waiting
        while waiting and self._work is None and self.finish is None:
            if self._collecting(now) and self.receiver.on_messages(waiting, self.linked, now):
                self._step(now)  # it closes the tick if the last message taken was the last one missing
            elif self._on_arrival(waiting.popleft(), now):
                self._step(now)

    def _collecting(self, now: float) -> bool:
        """Whether tick k is open and nothing but its neighbours' messages
        would close it now: a step after each of them changes nothing until
        the last one missing is in, so a run of them may be taken in one
        call (``Receiver.on_messages``) and stepped after."""
        return (self.collecting and self.est is not None and self.stopped is None and now < self.deadline
                and self.receiver.tick == self.k and self.phase != "leaving" and not any(j > self.k for j in self.ticks))

    # ======================================================================
    # one tick, in order: the world's tick and measurement, open, collect, close
    # ======================================================================
    def _step(self, now: float) -> None:
        """Take every step the state allows: start-up and joining, then open
        tick k once the world's tick and this agent's measurement are in,
        close it once the neighbours' messages are (or the collection ends
        otherwise); the end once the world said stop."""
        if self.finish is not None or self.phase == "leaving" or self._work is not None:
            return
        if self.est is None:
            self._start_up(now)
        while self.finish is None and self.est is not None and self._work is None:
            k = self.k
            if not self.collecting:
                if self.stopped is not None:
                    break
                why = self._out_of_run(k)
                if why:
                    self._resync(why, now)
                    self._start_up(now)
                    break
                if k not in self.ticks or k not in self.meas:
                    break
                self._open(k)
                break  # ``_opened`` steps on
            if not (self.receiver.all_accounted(k, self.linked[k]) or self.stopped is not None
                    or now >= self.deadline or any(j > k for j in self.ticks)):
                break
            self._close(k)
        if self.stopped is not None and not self.collecting and self.finish is None:
            self._end()

    def _out_of_run(self, k: int) -> str:
        """Why this agent is out of the run at tick ``k`` ("": it is not):
        the world's tick k counts it out, or a later tick came and k never
        did."""
        if k in self.ticks and self.id not in self.ticks[k].live:
            return f"the world counts this agent out at tick {k}"
        if k not in self.ticks and any(j > k for j in self.ticks):
            return f"tick {k} never came"
        return ""

    def _on_arrival(self, event, now: float) -> bool:
        """A sample, as ``read`` made it: the world's tick, measurement or
        stop, a neighbour's message. False if it changed nothing a step
        waits for."""
        kind = type(event)
        if kind is MessageArrived:
            return self._on_msg(event, now)
        if kind is TickArrived:
            return self._on_tick(event.tick, now)
        if kind is MeasurementArrived:
            return self._on_meas(event.measurement, now)
        if kind is StopArrived:
            self.stopped = event.stop
            return True
        if kind is Unreadable:
            return self._refuse(event.kind, event.reason, event.detail)
        return False  # a sample on a key no step reads

    # -- 1. the world's tick and this agent's measurement ---------------------
    def _on_meas(self, mm: wire.Measurement, now: float) -> bool:
        if mm.tick < self.k:
            return True
        problem = self._meas_problem(mm)
        if problem is not None:
            return self._refuse("meas", *problem)
        self.last_heard = now
        self.meas.setdefault(mm.tick, mm)
        self._bound(self.meas)
        return True

    def _on_tick(self, t: wire.Tick, now: float) -> bool:
        consts = (t.ticks, t.seed, t.algorithm, t.topology, t.comm_range)
        if t.tick < self.k or t.tick in self.ticks:
            self.last_heard = now
            if self.constants in (None, consts):
                self._repeat_report(t.tick)  # a world that lost the reports of that tick sends it again
            return True
        if self.est is not None and self.k + 1 < t.tick <= t.ticks and self.id not in t.live \
                and consts == self.constants:  # the world went on without it (its router was gone)
            self.newest = max(self.newest, t.tick)
            self._resync(f"the world is at tick {t.tick} without this agent", now)
        problem = self._tick_problem(t)
        if problem is not None:
            return self._refuse("tick", *problem)
        holder = t.holder(self.id)
        if holder is not None and holder != self._tag:  # the world counts another process as this id
            self._duplicate(f"tag {holder.hex()}", f"the world's tick {t.tick} counts that one as agent {self.id}",
                            now)
            return True
        self.last_heard = now
        if self.constants is None:
            self.constants = consts
            self.receiver.learn_run(t.ticks, t.seed)
        self.K, self.newest = t.ticks, max(self.newest, t.tick)
        self.ticks[t.tick] = t
        clock = self.timing.clock
        if clock is not None:  # a copy after the deadline is late, even before the close
            self.tick_at[t.tick] = now
            self.receiver.inbox.due(t.tick, now + clock.deadline_s)
            for old in [j for j in self.tick_at if j not in self.ticks]:
                del self.tick_at[old]
        # not live at a tick (joining later): linked to no one, nothing to fuse
        self.linked[t.tick] = self._live_near(t) if self.id in t.live else frozenset()
        if self.id not in t.live and self.est is None:
            self._joining(t.tick)
        self.receiver.release(t.tick, self.linked[t.tick], now)
        self._arm_delay()
        self._bound(self.ticks)
        if len(self.linked) > LINKS_KEPT + 2:
            for old in [j for j in self.linked if j < self.k - LINKS_KEPT]:
                del self.linked[old]
        return True

    def _live_near(self, t: wire.Tick) -> frozenset:
        """The live agents of tick ``t`` in range of this agent (not itself);
        the last answer again (the same set, shared by the ticks) while the
        positions and the live set are those of the tick before."""
        near = self._near(t.positions)
        if near is not self._linked_key[0] or t.live != self._linked_key[1]:
            live = near & set(t.live)
            self._linked_key, self._linked_ids = (near, t.live), near if len(live) == len(near) else live
        return self._linked_ids

    def _near(self, positions) -> frozenset:
        """The ids in range of this agent (not itself) at ``positions``
        (``mesh.protocol.estimator.neighbours``); the last answer again while the
        positions are those of the tick before (static agents). The positions
        are kept as the array the tick came with (the same one for every
        agent that read the tick), not as a copy per agent."""
        last = self._near_key
        if last is None or (positions is not last and not np.array_equal(positions, last)):
            self._near_key = positions
            self._near_ids = frozenset(neighbours(self.scn, self.id, positions)) - {self.id}
        return self._near_ids

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
        and at most ``kept`` of them (only a joining agent takes more than
        two; real time: the lead window)."""
        for old in [j for j in by_tick if j < self.k - 1]:
            del by_tick[old]
        while len(by_tick) > self.kept:
            del by_tick[max(by_tick)]

    def _refuse(self, kind: str, reason: str, detail: str) -> bool:
        """Count a rejected message of the world (or an answer), say it once
        per kind and reason."""
        self.counters.reject(reason)
        self.log.once((kind, reason), f"rejected a {kind} message: {reason}" + (f" ({detail[:200]})" if detail else ""))
        return False

    def _hand(self, step: str, *args) -> None:
        """A step of the estimator for the shell to carry out (``Work``)."""
        self._work = Work(self.est, step, args)
        self._out.append(self._work)

    # -- 2. open: the local step, ONE message out ------------------------------
    def _open(self, k: int) -> None:
        mm = self.meas.pop(k)
        self.receiver.advance(k)
        self.prof.begin()
        self._hand("local", k, mm.has, mm.y)

    def _opened(self, k: int, own, now: float) -> None:
        prof = self.prof
        prof.end("local")
        if isinstance(own, np.linalg.LinAlgError):
            return self._diverged(k, f"its local step failed ({own})")
        self.own = own
        prof.begin()
        payload = wire.encode(self.keys.run_id, self.id, k, self.liars.message(k, self.own), self.exchanged)
        self.own_digest = wire.digest(payload)  # the report says what was sent, not the message itself
        prof.end("encode")
        # addressed to the agents it fuses at tick k: links are symmetric (range, ring, all), so
        # these are the agents that fuse it
        self._out.append(Publish(self.keys.msg(self.id, to=self.linked[k]), payload))
        self.counters.published += 1
        self.collecting = True
        clock = self.timing.clock
        if clock is None:
            self.deadline = now + self.timing.collect_timeout
        else:  # from when tick k came: an agent that fell behind closes it at once
            self.deadline = self.tick_at.pop(k, now) + clock.deadline_s
        if self.deadline > now:
            self._out.append(SetTimer("collect", self.deadline))
        prof.waiting = "wait-neighbours"

    # -- 3. collect: the neighbours' messages through the receive path ---------
    def _on_msg(self, arrival: MessageArrived, now: float) -> bool:
        """A neighbour's message (read at the edge: its key's id, its decode,
        the checks of its own values) into the receive path
        (``mesh.protocol.receive``): the guard rejects (counts) what is
        malformed or off the window around tick k,
        the range gate drops (counts "out_of_range") one from an agent not
        linked to this one at the message's tick (one whose tick the world
        has not opened here yet waits for it), and the inbox holds the rest
        until the tick is fused. False if it was dropped."""
        self.receiver.advance(self.k)
        taken = self.receiver.on_message(arrival, self.linked, now)
        self._arm_delay()
        return taken

    def _arm_delay(self) -> None:
        """A timer at the next delayed copy's arrival, if it is earlier than
        the one set."""
        at = self.receiver.next_due
        if at < self._delay_at:
            self._delay_at = at
            self._out.append(SetTimer("delay", at))

    # -- 4. close: fuse, report ------------------------------------------------
    def _close(self, k: int) -> None:
        heard, rejected = self.receiver.dropped(k), self.receiver.refusals(k)
        fused = dict(self.receiver.take(k, self.linked[k]))
        self._closing = (heard, rejected, fused, False)
        self.prof.begin()
        self._hand("fuse", k, self.own, fused)

    def _closed(self, k: int, out, now: float) -> None:
        prof = self.prof
        prof.end("fuse")
        heard, rejected, fused, failed = self._closing
        if isinstance(out, np.linalg.LinAlgError):
            if failed:
                return self._diverged(k, f"its fusion failed even alone ({out})")
            # well-formed messages that still break fusion: keep our own estimate
            self.counters.reject("fusion", len(fused))
            self.log.once("fusion", f"tick {k}: fusion failed; fused this agent's own message alone")
            self._closing = (heard, rejected, fused, True)
            prof.begin()
            return self._hand("fuse", k, self.own, {})
        self._closing = None
        problem = wire.report_problem(out.x[0, 0], out.P[0, 0], out.d[0, 0])
        if problem is not None:
            return self._diverged(k, f"its fused estimate would be refused ({problem[0]}: {problem[1]})")
        out = self.liars.report(k, out)
        counters = self.receiver.snapshot(cap=wire.count_bound(self.constants[0]))
        fused_ids, not_fused = self.verdicts.of_tick(k, self.linked[k], heard, rejected, fused, failed)
        prof.begin()
        received = self.receiver.digests(k)
        digests = list(map(received.get, fused_ids))
        if not all(digests):  # a message this agent did not receive as a copy (fused again alone): its digest
            digests = [g or wire.message_digest(self.keys.run_id, s, k, fused[s], self.exchanged)
                       for s, g in zip(fused_ids, digests)]
        report = wire.encode_report(self.keys.run_id, self.id, k, out.x[0, 0], out.P[0, 0], out.d[0, 0],
                                    out.d_valid[0, 0], counters, fused_ids, not_fused, self.own_digest, digests,
                                    self.rejoins[-1] if self.rejoins else None)
        prof.end("encode")
        if not self.liars.withholds(k):
            self._out.append(Publish(self.keys.report(self.id), report))
            self.last_report = (k, report)
        prof.tick()
        prof.waiting = "wait-world"
        self.ticks.pop(k, None)
        self.linked.pop(k - LINKS_KEPT, None)
        self.collecting, self.own, self.deadline = False, None, math.inf
        self.k = k + 1

    def _repeat_report(self, tick: int) -> None:
        """The world sent tick ``tick`` again (it lost the reports of that
        tick: it was frozen): send it this agent's report of it again."""
        if self.last_report is not None and self.last_report[0] == tick == self.k - 1:
            self._out.append(Publish(self.keys.report(self.id), self.last_report[1]))

    def _end(self) -> None:
        """The world said stop and no tick is open: the run is over for this
        agent."""
        st = self.stopped
        if st.why == "done" and st.tick == self.K:
            self._finish("done", OK)
        else:
            self._finish("stopped", FAILED, f"the world stopped the run at tick {st.tick}"
                         + (f" of {self.K}" if self.K else "") + f": {st.why}")

    def _diverged(self, k: int, why: str) -> None:
        """The estimator diverged at tick ``k``: the end, no report; the
        world is told why (``_say_stopped``)."""
        reason = f"the estimator ({self.algorithm}) diverged at tick {k}: {why}"
        self._say_stopped("diverged", reason)
        self._finish("diverged", exits.STOPPED, reason)

    def _say_stopped(self, category: str, reason: str) -> None:
        """Tell the world this agent stops before the run's end, and why
        (``keys.stopped``): the run then says "diverged" or "interrupted"
        for its missing ticks, not only that it left. Only once it works on
        ticks (the world knows it) and while the run goes on."""
        if self.est is None or self.stopped is not None:
            return
        self._out.append(Publish(self.keys.stopped(self.id),
                                 wire.encode_stopped(self.keys.run_id, self.k, category, reason)))

    def _finish(self, status: str, code: int, reason: str = "") -> None:
        self.finish = Finish(status, code, reason)
        self.phase = "finished"
        self.prof.stop()
        self.receiver.close()
        self._out.append(self.finish)

    # ======================================================================
    # timers, liveliness, the world's silence
    # ======================================================================
    def _on_timer(self, name: str, now: float) -> None:
        if name == "delay":
            self._delay_at = math.inf
            self.receiver.arrive_due(now)
            self._arm_delay()
        elif name == "world":
            self._check_world(now)
        elif name == "leave":
            self._finish("duplicate", DUPLICATE, self._leaving)
        elif name == "ask" and self._asked is not None and self._start is None and now >= self._asked[2]:
            self._asked = None  # no answer in time: ``_join`` asks again (the world decides the start)
        # "collect", "peers": ``_step`` looks at the time (a timer is a wake-up, never a deadline by itself)

    def _world_timer(self) -> None:
        self._out.append(SetTimer("world", self.last_heard + self.timing.world_timeout))

    def _check_world(self, now: float) -> None:
        """The world gone or silent for ``world_timeout`` seconds: the end;
        else the timer again, from the world's last word."""
        if now < self.last_heard + self.timing.world_timeout:
            return self._world_timer()
        what = {"world": "waiting for the world", "claim": "waiting for the world",
                "gather": "waiting for the world and every agent"}.get(self.phase, "waiting to join")
        if self.est is not None:
            what = f"collecting tick {self.k}" if self.collecting else f"waiting for tick {self.k}"
        if self.world_gone:
            self._finish("world gone", FAILED, f"the world is gone (its liveliness token went "
                                               f"{now - self.world_gone_at:.0f} s ago and did not come back) "
                                               f"while {what}")
        else:
            self._finish("world silent", FAILED, f"no word from the world for {self.timing.world_timeout:g} s "
                                                 f"while {what}")

    def _on_token(self, key: str, up: bool, now: float) -> None:
        kind, who = self.keys.parse(key)
        if kind == "alive-world":
            self._on_world_token(nonce_of(key), up, now)
        elif kind == "ticking":
            self.world_ticking = up
        elif kind == "alive" and who in self.ids:
            self._on_agent_token(who, nonce_of(key), up, now)

    def _on_tokens(self, batch: tuple, up: bool, now: float) -> None:
        """Many tokens at once (``TokenBatch``): the others' alive tokens
        counted in one call, the world's and this id's one by one."""
        shared = self.receiver.guard.shared
        parse = lambda: parse_batch(self.keys, self.scn.places, batch)  # noqa: E731
        places, nonces, others = parse() if shared is None else shared.once(batch, ("tokens", self.keys.root), parse)
        for key in others:
            self._on_token(key, up, now)
        own = self.scn.index(self.id)
        mine = places == own
        if mine.any():
            for j in np.flatnonzero(mine).tolist():
                self._on_agent_token(self.id, nonces[j], up, now)
            places = places[~mine]
        self.alive.tokens(places, up)

    def _on_world_token(self, nonce_: str, up: bool, now: float) -> None:
        """The world's token came or went. Gone while this process was frozen
        past zenoh's lease: the world has dropped this agent from the run, so
        it rejoins (``_resync``). Gone otherwise: wait for it (a frozen world
        comes back), at most ``world_timeout``."""
        was_gone = self.world_gone
        (self.world_tokens.add if up else self.world_tokens.discard)(nonce_)
        self.world_seen |= bool(self.world_tokens)
        self.world_gone = self.world_seen and not self.world_tokens
        if self.world_gone and not was_gone:
            self.world_gone_at = now
            if self.est is not None and now - self._woke_at < WOKE_S:
                self._resync("this process was frozen past zenoh's lease", now)
        elif was_gone and not self.world_gone:
            self.world_gone_at = math.inf
            self.log.info(f"the world is back (at tick {self.newest})")

    def _on_agent_token(self, who: int, nonce_: str, up: bool, now: float) -> None:
        """An agent's token came or went. One of this agent's id that appears
        after this one declared its own: two processes started at once. This
        one leaves if it joined the run late (``_late``), or if the other's
        nonce is smaller (an earlier start) and this one has not worked on a
        tick yet; one that works since tick 1 keeps the id (its estimate is
        the engine's, a late twin's is not)."""
        self.alive.token(who, nonce_, up)
        if not (up and who == self.id and self.claimed and nonce_ != self.nonce):
            return
        if self._late():
            self._duplicate(nonce_, "it holds this id in the run this one joined late", now)
        elif nonce_ < self.nonce and not self._worked:
            self._duplicate(nonce_, "started earlier", now)

    def _late(self) -> bool:
        """This process found the run in progress before it ever worked, or
        first worked from a re-initialisation (a neighbour's estimate):
        another process of its id that is alive keeps the id, however their
        nonces compare (that one may be working since tick 1, and its
        estimate is the engine's; this one's never is)."""
        return self._started_late or (self.rejoining and not self._worked)

    def _duplicate(self, other: str, how: str, now: float) -> None:
        """Another process holds this agent's id: this one stops working,
        tells the world (which counts it: ``duplicate_ids``) and leaves once
        its word is on the wire (exit 2)."""
        if self.phase == "leaving":
            return
        self.phase = "leaving"
        self._leaving = (f"agent id {self.id} is already held by another process in run {self.keys.run_id!r} "
                         f"(process {other}, {how}): this one leaves")
        self._out += [Publish(self.keys.duplicate(self.id), self.nonce.encode()),
                      SetTimer("leave", now + DUPLICATE_SAY_S)]

    # ======================================================================
    # start-up, joining, rejoining
    # ======================================================================
    def _start_up(self, now: float) -> None:
        """The steps before the first tick, each once its condition holds:
        the world seen -> claim the id -> the world and every agent seen (or
        the run in progress) -> ready -> join."""
        if self.phase == "world" and (self.world_seen or self.stopped is not None):
            self.phase = "claim"
            self._claim_qid = next(self._qids)
            self._out.append(AskTokens(self._claim_qid, self.keys.alive(self.id), CLAIM_S))
        if self.phase == "gather" and ((self.world_seen and (self.alive.complete or self.world_ticking))
                                       or self.stopped is not None):
            if self.world_ticking and self.est is None:
                self._joining(self.newest)
            if self._ready_key is not None:
                self._out.append(DropToken(self._ready_key))
                self._ready_key = None
            if self.rejoining and not (self._peers_seen() or self.stopped is not None):
                self.phase, self._peers_until = "peers", now + PEERS_WAIT_S
                self._out.append(SetTimer("peers", self._peers_until))
            else:
                self._ready()
        if self.phase == "peers" and (self._peers_seen() or self.stopped is not None or now >= self._peers_until):
            self._ready()
        if self.phase == "joining" and self.stopped is None:
            self._join(now)

    def _on_claim(self, qid: int, keys, now: float) -> None:
        """The liveliness query's answer: another process holds this id (it
        is the first: this one tells the world and leaves), or this one
        declares its alive token."""
        if qid != self._claim_qid or self.phase != "claim":
            return
        others = self._others({nonce_of(k) for k in keys})
        if others:
            return self._duplicate(min(others), "found before this one declared its own", now)
        self.claimed = True
        self.phase = "gather"
        self._out.append(DeclareToken(self.keys.alive(self.id, self.nonce)))

    def _on_confirm(self, keys, now: float) -> None:
        """A process that found the run in progress asks once more, just
        before its first tick, whether another process holds its id: the
        world counts an id live whichever process holds it, and a session
        that started a moment ago may not have heard every token at its
        claim. Another one: this one leaves (exit 2)."""
        others = self._others({nonce_of(k) for k in keys})
        if others:
            return self._duplicate(min(others), "it holds this id in the run this one joined late", now)
        self._confirmed = True

    @functools.cached_property
    def _tag(self) -> bytes:
        return wire.holder_tag(self.nonce)

    def _others(self, nonces=()) -> set:
        """The nonces of other processes holding this agent's id: ``nonces``
        (an answer's) and the alive tokens of its id this one has seen."""
        return (set(nonces) | set(self.alive.mine)) - {self.nonce}

    def _peers_seen(self) -> bool:
        """The agents the world counts live at its newest tick are seen (so
        this agent's first message reaches them)."""
        return not self.ticks or self.alive.has(set(self.ticks[max(self.ticks)].live) - {self.id})

    def _ready(self) -> None:
        """Declare a ready token: this agent joins at the first tick after
        the newest it knew of that counts it live."""
        self.join_after = self.newest
        self._joins += 1
        self._ready_key = self.keys.ready(self.id, f"{self.nonce}.{self._joins}")
        self._out.append(DeclareToken(self._ready_key))
        self.phase = "joining"

    def _joining(self, tick: int) -> None:
        """The world is at ``tick`` without this agent: a restart joining a run
        in progress. It cannot join before the next tick."""
        self.k = max(self.k, tick + 1)
        self.receiver.advance(self.k)  # the guard's window: the tick it may join at
        if not self.rejoining:
            self.rejoining = True
            self.log.info("the run is in progress: rejoining" + (f" (at tick {tick})" if tick else ""))

    def _join(self, now: float) -> None:
        """The first tick this agent works on: once the world counts it live
        at a tick J after ``join_after`` and J's measurement is in, make the
        estimator; a rejoining agent first asks the world for its starting
        estimate of tick J - 1 and starts from the answer."""
        twins = self._others()
        if self._late() and twins:  # seen before this one found the run in progress
            return self._duplicate(min(twins), "it holds this id in the run this one joined late", now)
        mine = [t for t, tk in self.ticks.items() if t > self.join_after and self.id in tk.live]
        if not mine:
            return
        self.k = min(mine)
        for by_tick in (self.ticks, self.meas):
            for t in [t for t in by_tick if t < self.k]:
                del by_tick[t]
        if self.k not in self.meas:
            return
        k, restart = self.k, self.rejoining and self.k > 1  # at tick 1 all start alike
        confirm = restart and self._late() and not self._confirmed
        if restart and (self._start is None or self._start[0] != k or confirm):
            if self.world_gone:  # cut off (woken past the lease): ask once the world's token is back
                return
            if self._asked is None or self._asked[1] != k:
                qid = next(self._qids)
                self._asked, self._start = (qid, k, now + ASK_S), None
                self._out += [Ask(qid, self.keys.start(self.id), wire.encode_join(self.keys.run_id, self.id, k),
                                  ASK_S), SetTimer("ask", self._asked[2])]
            if confirm and self._confirm_qid is None:
                self._confirm_qid = next(self._qids)
                self._out.append(AskTokens(self._confirm_qid, self.keys.alive(self.id), CLAIM_S))
            return
        t = self.ticks[k]
        mine_ = (self.algorithm, self.scn.topology, self.scn.comm_range)
        if mine_ != (t.algorithm, t.topology, t.comm_range):
            return self._finish("mismatch", FAILED,
                                f"the world runs algorithm {t.algorithm}, topology {t.topology}, range "
                                f"{t.comm_range:g}; this agent {mine_[0]}, {mine_[1]}, {mine_[2]:g}: start both "
                                "with the same flags")
        start = self._start[1] if restart else None  # the world's answer (None: the prior)
        est = AgentEstimator(self.scn, self.id, self.estimator, t.ticks, t.seed,
                             start=None if start is None else (start.x, start.P))
        if not self._worked:
            self._worked = True
            self._started_late = restart
            self.prof.start()  # measured from the first tick this agent works on
        self.est = est
        self.phase = "working"
        if restart:
            self._restarted(k, start)

    def _on_reply(self, qid: int, payload) -> None:
        """The world's answer to the query for the starting estimate; one
        that fails the guard's checks: the prior. None (the query ended
        without an answer: the world frozen, slow, or out of reach) is no
        answer: the agent asks again when the ask timer runs out, or, asked
        while the world's token is gone (a session cut off), once the token
        is back. The prior is the world's answer, never the agent's choice
        for want of one: an agent that never gets an answer never joins, and
        its ticks are missing."""
        if self._asked is None or qid != self._asked[0] or self._start is not None:
            return
        if payload is None:
            if self.world_gone:  # asked while cut off: ask again once the world is back
                self._asked = None
            return
        k, start = self._asked[1], None
        g = self.receiver.guard.config
        try:
            start = wire.decode_start(payload, run_id=self.keys.run_id, agent=self.id, tick=k, n=self.n,
                                      m=self.m, max_abs=g.max_abs, max_cond=g.max_cond)
        except wire.Rejected as e:
            self._refuse("start", e.reason, e.detail)
        self._start = (k, start)

    def _restarted(self, k: int, start) -> None:
        """A (re)joining agent started at tick ``k`` from the world's answer
        ``start`` (``mesh.protocol.rejoin``; None: the prior): every report from
        now on tells the world the tick and the source (``wire.encode_report``'s
        "rj")."""
        src = None if start is None else start.source
        self.rejoins.append((k, src))
        self.log.info(f"joined at tick {k}, re-initialised from "
                      + (f"agent {src}'s fused estimate of tick {k - 1}" if src is not None else "the prior"))

    def _resync(self, why: str, now: float) -> None:
        """This agent is out of the run (the world dropped it, or it missed a
        tick): drop the estimator and rejoin as a restarted agent does (a new
        ready token)."""
        if self.est is None:
            return
        self.log.info(f"tick {self.k}: out of the run ({why}): rejoining")
        self.est, self.rejoining, self.join_after = None, True, None
        self._work = self._closing = None
        self.phase, self._asked, self._start = "gather", None, None
        self.collecting, self.own, self.deadline = False, None, math.inf
        self.k = max(self.k, self.newest + 1)
        self.receiver.advance(self.k)
        for by_tick in (self.ticks, self.meas):
            for old in [j for j in by_tick if j < self.k]:
                del by_tick[old]
