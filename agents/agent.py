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

Each step is taken by whichever message makes it possible, in the
transport's callback (zenoh's network thread): the world's tick (its
measurement came just before) runs steps 1-2, the last neighbour's message
steps 3-4. The main thread only starts the agent, joins the run, and watches
the timeouts and the stop; it is not woken per message (a thread hop per
message was most of a message's cost on a busy machine).

Neighbours' messages pass the receive path (``diskf_mesh.receive``: the
guard rejects what is malformed, the inbox fuses a message at most once and
discards, counted as late, one for a tick already fused). The counters
(``diskf_mesh.counters``) go to the world with every report. The
agent exits 0 when the world says stop, and 1 with one line on stderr if the
world goes away or stays silent for ``--world-timeout`` seconds.

Link faults (``--loss``, ``--latency-ms``, ... or the scenario's
``[faults]``) act in the receive path on every link into this agent, seeded
by the run's seed (from the world's first tick). An agent started while the
run is in progress (a restart after a crash) joins at the world's next tick
and re-initialises from a neighbour's fused estimate (``agents.rejoin``).

``--profile DIR`` writes where each tick's time went (``mesh.profile``).
"""
from __future__ import annotations

import argparse
import math
import os
import sys
import threading
import time
from dataclasses import dataclass

import numpy as np

from agents import rejoin
from diskf_mesh import wire
from diskf_mesh.guard import Guard, GuardConfig
from diskf_mesh.mesh import runspec, zenoh_config
from diskf_mesh.mesh.estimator import AgentEstimator, neighbours
from diskf_mesh.mesh.keys import Keys
from diskf_mesh.mesh.log import Log
from diskf_mesh.mesh.profile import AGENT_PHASES, NO_PHASES, Phases
from diskf_mesh.mesh.transport import MeshError, Transport, ZenohTransport
from diskf_mesh.faults import FaultConfig, FaultModel
from diskf_mesh.faults import add_arguments as add_fault_arguments
from diskf_mesh.faults import from_args as faults_from_args
from diskf_mesh.receive import Receiver
from diskf_mesh.recording.verdicts import TickVerdicts
from diskf_mesh.scenario import Scenario

POLL_S = 0.5     # the main thread looks at the timeouts at least this often
HOLD_TICKS = 2   # a neighbour's message up to this many ticks ahead waits for its tick
LINKS_KEPT = 16  # link sets of past ticks kept, to gate late messages too


@dataclass(frozen=True)
class AgentTiming:
    collect_timeout: float = 5.0   # wait for neighbours' messages after publishing
    world_timeout: float = 60.0    # longest silence from the world before giving up


class Agent:
    """The protocol of one agent over a ``Transport``. ``run`` returns the
    number of ticks fused, or raises ``MeshError``.

    Everything the transport delivers (the world's messages, neighbours'
    messages, liveliness changes) is handled in the transport's callback,
    under one lock (``_cv``), and ``_advance`` then takes every step the
    new state allows (open tick k: local step and own message; close it:
    fusion and report). Neighbours' messages that pass the range gate go on
    to the receive path (``diskf_mesh.receive``: guard, the link's
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
        self.scn = scn
        self.ids = tuple(a.id for a in scn.agents)
        if agent_id not in self.ids:
            raise MeshError(f"agent {agent_id} is not in scenario {scn.name!r} (ids {', '.join(map(str, self.ids))})")
        self.id = agent_id
        self.algorithm = algorithm
        self.keys = keys
        self.transport = transport
        self.timing = timing
        self.log = log or Log(f"agent {agent_id}")
        n, m = scn.G.shape
        self.p = int(scn.sensors().p[self.ids.index(agent_id)])
        self.prof = profile
        self.receiver = Receiver(Guard(GuardConfig(
            keys.run_id, agent_id, frozenset(self.ids), n, m, information_check=algorithm != "ldrkf"),
            profile=profile), faults, on_arrival=self.wake)
        self.counters = self.receiver.counters
        self.verdicts = TickVerdicts(self.counters)  # per tick: who was fused, why the others were not
        self.fault_config = fault_config
        self.rejoining = False
        self.reports = {}    # k -> {sender: wire.Report}, listened to only while rejoining
        self.est: AgentEstimator | None = None
        self.ticks = {}      # k -> wire.Tick
        self.meas = {}       # k -> wire.Measurement
        self.alive = set()   # agent ids with a liveliness token
        self.linked = {}     # k -> ids of live agents in range at tick k (not this one), recent ticks
        self.held = {}       # k -> [(key, sender, payload)] that came before the world's tick k
        self.out_of_range = 0
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
        self.failure: BaseException | None = None  # raised in a callback, re-raised by the main thread
        self._cv = threading.Condition(threading.RLock())  # the protocol state
        self._main_looks_at = 0.0  # when the main thread looks at the timeouts next (monotonic)
        self._advancing = False    # in _advance (a put may deliver to this process on the same thread)
        self._reports_wanted = False     # rejoining: the main thread subscribes to the reports
        self._reports_subscribed = False

    # -- transport callbacks ---------------------------------------------------
    def _on_sample(self, key: str, payload) -> None:
        """Every sample (world's messages, neighbours' messages, reports) and
        every liveliness change (``payload`` True or False)."""
        self.prof.begin()
        try:
            with self._cv:
                if key is None or self._handle(key, payload):
                    self._advance()
                    self._notify_main()
        except BaseException as e:  # noqa: BLE001 - a callback must not swallow a failure
            self._fail(e)
        finally:
            self.prof.end("other")

    def wake(self) -> None:
        """A delayed copy reached the inbox (the fault layer's thread): it may
        complete the tick being collected."""
        self._on_sample(None, None)

    def _fail(self, e: BaseException) -> None:
        with self._cv:
            if self.failure is None:
                self.failure = e
            self._cv.notify_all()

    def _notify_main(self) -> None:
        """Wake the main thread if there is something for it (lock held)."""
        if (self.est is None or self.stopped is not None or self.world_gone or self._reports_wanted
                or self.deadline < self._main_looks_at):
            self._cv.notify_all()

    # -- the world's messages and liveliness ---------------------------------
    def _handle(self, key: str, payload) -> bool:
        """Take in one sample; False if it was dropped without changing
        anything a step waits for (a neighbour out of range)."""
        kind, who = self.keys.parse(key)
        try:
            if kind == "msg":
                return self._gate(key, who, payload)
            elif kind == "tick":
                self.prof.begin()
                try:
                    t = wire.decode_tick(payload, run_id=self.keys.run_id, agents=len(self.ids))
                finally:
                    self.prof.end("decode")
                self.last_heard = time.monotonic()
                if t.tick >= self.k and t.tick not in self.ticks:
                    if self.fault_config is not None and self.receiver.faults is None:
                        self.receiver.use_faults(FaultModel(self.fault_config, t.seed))
                    self.ticks[t.tick] = t
                    # not live at a tick (joining later): linked to no one, nothing to fuse
                    self.linked[t.tick] = ((set(neighbours(self.scn, self.id, t.positions)) & set(t.live)) - {self.id}
                                           if self.id in t.live else set())
                    if self.id not in t.live and self.est is None:
                        self._joining(t.tick)
                    for held in self.held.pop(t.tick, ()):
                        self._gate(*held)
            elif kind == "meas":
                self.prof.begin()
                try:
                    mm = wire.decode_measurement(payload, run_id=self.keys.run_id, agent=self.id, p=self.p)
                finally:
                    self.prof.end("decode")
                self.last_heard = time.monotonic()
                if mm.tick >= self.k:
                    self.meas.setdefault(mm.tick, mm)
            elif kind == "report" and self.rejoining and self.est is None and who in self.ids:
                n, m = self.scn.G.shape
                r = wire.decode_report(payload, run_id=self.keys.run_id, sender=who, n=n, m=m)
                self.reports.setdefault(r.tick, {})[who] = r
            elif kind == "stop":
                self.stopped = wire.decode_stop(payload, run_id=self.keys.run_id)
            elif kind == "alive-world":
                self.world_seen |= payload
                self.world_gone = self.world_seen and not payload
            elif kind == "ticking":
                self.world_ticking = bool(payload)
            elif kind == "alive" and who is not None:
                (self.alive.add if payload else self.alive.discard)(who)
        except wire.Rejected as e:
            self.counters.reject(e.reason)
            self.log.once((kind, e.reason), f"rejected a {kind} message on {key}: {e}")
        return True

    def _gate(self, key: str, sender, payload) -> bool:
        """The radio range: a message from an agent that is not linked to this
        one at the message's tick never reaches it, so it is dropped here
        (counted "out_of_range") before the receive path spends a decode on
        it. A message whose tick is not known yet waits for the world's tick;
        one that cannot be read, or is for a tick far off, goes on to the
        receive path, which rejects or counts it. False if it was dropped."""
        if sender == self.id:
            return False
        t = wire.peek_tick(payload)
        if t in self.linked:
            if sender not in self.linked[t]:
                self.out_of_range += 1
                return False
            self.verdicts.on_payload(self.receiver.on_payload, key, payload, sender, t)
        elif t is not None and self.k <= t <= self.k + HOLD_TICKS:
            self.held.setdefault(t, []).append((key, sender, payload))
        elif self.est is None and t is not None:  # a tick from before this agent (re)joined the run
            self.out_of_range += 1
            return False
        else:
            self.receiver.on_payload(key, payload)
        return True

    def _check_world(self, deadline: float, what: str) -> None:
        if self.failure is not None:
            raise self.failure
        if self.world_gone and self.stopped is None:
            raise MeshError(f"the world is gone (its liveliness token went) while {what}")
        if time.monotonic() > deadline:
            raise MeshError(f"no word from the world for {self.timing.world_timeout:g} s while {what}")

    def _wait(self, until: float) -> None:
        """Main thread, lock held: sleep until notified or ``until``, at most ``POLL_S``."""
        now = time.monotonic()
        timeout = max(min(until, now + POLL_S), now) - now
        self._main_looks_at = now + timeout
        self._cv.wait(timeout)

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
                if self.stopped is not None or k not in self.ticks or k not in self.meas:
                    return
                self._open(k)
            if not (self.linked[k] <= self.receiver.accounted(k) or self.stopped is not None or self.world_gone
                    or any(j > k for j in self.ticks) or time.monotonic() >= self.deadline):
                return
            self._close(k)

    def _open(self, k: int) -> None:
        """Local step of tick k, own message out."""
        prof = self.prof
        mm = self.meas.pop(k)
        self.receiver.tick = k
        prof.begin()
        self.own = self.est.local(k, mm.has, mm.y)
        prof.end("local")
        prof.begin()
        payload = self.own_payload = wire.encode(self.keys.run_id, self.id, k, self.own)
        prof.end("encode")
        prof.begin()
        # addressed to the agents it fuses at tick k: links are symmetric (range, ring, all), so
        # these are the agents that fuse it
        self.transport.put(self.keys.msg(self.id, to=self.linked[k]), payload)
        prof.end("publish")
        self.counters.published += 1
        self.collecting = True
        self.deadline = time.monotonic() + self.timing.collect_timeout
        prof.waiting = "wait-neighbours"

    def _close(self, k: int) -> None:
        """Fuse what came for tick k, report to the world."""
        prof = self.prof
        heard = self.receiver.accounted(k)
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
        counters = self.receiver.snapshot()
        counters["out_of_range"] = self.out_of_range
        fused_ids, not_fused = self.verdicts.of_tick(k, self.linked[k], heard, fused, failed)
        prof.begin()
        report = wire.encode_report(self.keys.run_id, self.id, k, out.x[0, 0], out.P[0, 0], out.d[0, 0],
                                    out.d_valid[0, 0], counters, fused_ids, not_fused, self.own_payload)
        prof.end("encode")
        prof.begin()
        self.transport.put(self.keys.report(self.id), report)
        prof.end("publish")
        prof.tick()
        prof.waiting = "wait-world"
        self.ticks.pop(k, None)
        self.held.pop(k, None)
        self.linked.pop(k - LINKS_KEPT, None)
        self.collecting, self.own, self.deadline = False, None, math.inf
        self.k = k + 1

    # -- protocol ----------------------------------------------------------
    def start(self) -> None:
        k = self.keys
        for key in (k.tick, k.meas(self.id), k.stop):
            self.transport.subscribe(key, self._on_sample)
        self.transport.subscribe(k.msg_to(self.id), self._on_sample)  # what its neighbours send it
        self.transport.watch_tokens(f"{k.root}/alive/**", self._on_sample)
        self.transport.watch_tokens(k.ticking, self._on_sample)
        self.transport.declare_token(k.alive(self.id))

    def wait_ready(self) -> None:
        """Declare the ready token once the world and every agent are seen."""
        with self._cv:
            self.last_heard = time.monotonic()
            deadline = self.last_heard + self.timing.world_timeout
            while not (self.world_seen and (self.alive >= set(self.ids) or self.world_ticking)) \
                    and self.stopped is None:
                self._check_world(deadline, "waiting for the world and every agent")
                self._wait(deadline)
            if self.world_ticking and self.est is None:
                self._joining(max(self.ticks, default=0))
        self._subscribe_reports()
        self.transport.declare_token(self.keys.ready(self.id))

    def _joining(self, tick: int) -> None:
        """The world is at ``tick`` without this agent: a restart joining a run
        in progress. It cannot join before the next tick; meanwhile it listens
        to the others' fused estimates, to re-initialise from one (the main
        thread subscribes: ``_subscribe_reports``)."""
        self.k = max(self.k, tick + 1)
        if not self.rejoining:
            self.rejoining = True
            self._reports_wanted = True
            self.log.info("the run is in progress: rejoining" + (f" (at tick {tick})" if tick else ""))

    def _subscribe_reports(self) -> None:
        """Main thread, without the lock (a subscription is never made from a
        transport callback)."""
        with self._cv:
            wanted = self._reports_wanted and not self._reports_subscribed
            self._reports_wanted = False
        if wanted:
            self._reports_subscribed = True
            self.transport.subscribe(self.keys.report("*"), self._on_sample)

    def _join(self) -> bool:
        """Main thread, lock held: the first tick this agent works on. Once
        the world counts it live at a tick k (1, or the tick after a
        rejoining agent became ready) and tick k's messages are in, make the
        estimator (a rejoining agent re-initialises it) and start working."""
        mine = [t for t, tk in self.ticks.items() if self.id in tk.live]
        if not mine:
            return False
        self.k = min(mine)
        for t in [t for t in self.ticks if t < self.k - 1]:  # tick k - 1 is kept for the re-initialisation
            del self.ticks[t]
        if self.k not in self.meas:
            return False
        est = self._make_estimator(self.ticks[self.k])
        self.prof.start()  # measured from the first tick this agent works on
        self.est = est
        if self.rejoining:
            self._reinitialise(self.k)
        return True

    def _reinitialise(self, k: int) -> None:
        """A rejoining agent's estimate of tick k - 1 (``agents.rejoin``)."""
        before = self.ticks.pop(k - 1, None)
        near = () if before is None else (set(neighbours(self.scn, self.id, before.positions)) & set(before.live))
        src = rejoin.reinitialise(self.est, self.reports.get(k - 1, {}), set(near) - {self.id})
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
        self.start()
        self.wait_ready()
        while True:
            self._subscribe_reports()
            with self._cv:
                if self.est is None and self.stopped is None:
                    self._join()
                self._advance()
                if self.failure is not None:
                    raise self.failure
                if self.stopped is not None and not self.collecting:
                    break
                what = ("waiting to join" if self.est is None else
                        f"collecting tick {self.k}" if self.collecting else f"waiting for tick {self.k}")
                until = self.last_heard + self.timing.world_timeout
                self._check_world(until, what)
                self._wait(min(until, self.deadline))
        self.prof.stop()
        self.receiver.close()
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
    spec = runspec.from_args(args)
    scn = spec.load()
    log = Log(f"agent {args.agent_id}")
    batch_scheduling()
    prof = Phases(AGENT_PHASES, f"agent {args.agent_id}") if args.profile else NO_PHASES
    try:
        with ZenohTransport(zenoh_config.from_args(args)) as transport:
            agent = Agent(scn, args.agent_id, spec.algorithm, Keys(spec.run_id), transport,
                          AgentTiming(args.collect_timeout, args.world_timeout), log,
                          fault_config=faults_from_args(args, scn.faults), profile=prof)
            agent.run()
    except MeshError as e:
        log.error(str(e))
        return 1
    finally:
        if prof:
            prof.write(args.profile, f"agent-{args.agent_id}")
    return 0


if __name__ == "__main__":
    from diskf_mesh import cli

    sys.exit(cli.run_one("agent", __spec__.name))
