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
"""
from __future__ import annotations

import argparse
import sys
import time
from dataclasses import dataclass

import numpy as np

from agents import rejoin
from diskf_mesh import wire
from diskf_mesh.guard import Guard, GuardConfig
from diskf_mesh.mesh import runspec, zenoh_config
from diskf_mesh.mesh.estimator import AgentEstimator, fixed_neighbours, neighbours
from diskf_mesh.mesh.keys import Keys
from diskf_mesh.mesh.log import Log
from diskf_mesh.mesh.transport import Mailbox, MeshError, Transport, ZenohTransport
from diskf_mesh.faults import FaultConfig, FaultModel
from diskf_mesh.faults import add_arguments as add_fault_arguments
from diskf_mesh.faults import from_args as faults_from_args
from diskf_mesh.receive import Receiver
from diskf_mesh.scenario import Scenario

POLL_S = 0.05   # while collecting, look at the world's messages this often
HOLD_TICKS = 2  # a neighbour's message up to this many ticks ahead waits for its tick
LINKS_KEPT = 16  # link sets of past ticks kept, to gate late messages too


@dataclass(frozen=True)
class AgentTiming:
    collect_timeout: float = 5.0   # wait for neighbours' messages after publishing
    world_timeout: float = 60.0    # longest silence from the world before giving up


class Agent:
    """The protocol of one agent over a ``Transport``. ``run`` returns the
    number of ticks fused, or raises ``MeshError``.

    Everything the transport delivers (the world's messages, neighbours'
    messages, liveliness changes) goes into one ``Mailbox`` read by this
    loop, so all decoding and estimation runs on one thread. Neighbours'
    messages that pass the range gate go on to the receive path
    (``diskf_mesh.receive``: guard, the link's ``faults``, inbox); a copy the
    fault layer delays wakes the loop through ``wake``."""

    def __init__(self, scn: Scenario, agent_id: int, algorithm: str, keys: Keys, transport: Transport,
                 timing: AgentTiming = AgentTiming(), log: Log | None = None, faults: FaultModel | None = None,
                 fault_config: FaultConfig | None = None):
        """``faults``: the link faults; or ``fault_config``, seeded with the
        run's seed when the world's first tick tells it."""
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
        self.mailbox = Mailbox()
        self.receiver = Receiver(Guard(GuardConfig(
            keys.run_id, agent_id, frozenset(self.ids), n, m, information_check=algorithm != "ldrkf")),
            faults, on_arrival=self.wake)
        self.counters = self.receiver.counters
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

    # -- the world's messages and liveliness ---------------------------------
    def _handle(self, item) -> None:
        key, payload, _ = item
        kind, who = self.keys.parse(key)
        try:
            if kind == "msg":
                self._gate(key, who, payload)
            elif kind == "tick":
                t = wire.decode_tick(payload, run_id=self.keys.run_id, agents=len(self.ids))
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
                mm = wire.decode_measurement(payload, run_id=self.keys.run_id, agent=self.id, p=self.p)
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

    def _gate(self, key: str, sender, payload) -> None:
        """The radio range: a message from an agent that is not linked to this
        one at the message's tick never reaches it, so it is dropped here
        (counted "out_of_range") before the receive path spends a decode on
        it. A message whose tick is not known yet waits for the world's tick;
        one that cannot be read, or is for a tick far off, goes on to the
        receive path, which rejects or counts it."""
        if sender == self.id:
            return
        t = wire.peek_tick(payload)
        if t in self.linked:
            if sender in self.linked[t]:
                self.receiver.on_payload(key, payload)
            else:
                self.out_of_range += 1
        elif t is not None and self.k <= t <= self.k + HOLD_TICKS:
            self.held.setdefault(t, []).append((key, sender, payload))
        elif self.est is None and t is not None:  # a tick from before this agent (re)joined the run
            self.out_of_range += 1
        else:
            self.receiver.on_payload(key, payload)

    def wake(self) -> None:
        """Make the loop look again (a delayed copy reached the inbox)."""
        self.mailbox.push("", None)

    def _next(self, until: float) -> None:
        """Handle one mailbox item, waiting at most until ``until``."""
        item = self.mailbox.get(until - time.monotonic())
        if item is not None:
            self._handle(item)

    def _drain(self) -> None:
        while (item := self.mailbox.get(0)) is not None:
            self._handle(item)

    def _check_world(self, deadline: float, what: str) -> None:
        if self.world_gone and self.stopped is None:
            raise MeshError(f"the world is gone (its liveliness token went) while {what}")
        if time.monotonic() > deadline:
            raise MeshError(f"no word from the world for {self.timing.world_timeout:g} s while {what}")

    # -- protocol ----------------------------------------------------------
    def start(self) -> None:
        k = self.keys
        for key in (k.tick, k.meas(self.id), k.stop):
            self.transport.subscribe(key, self.mailbox.push)
        fixed = fixed_neighbours(self.scn, self.id)
        for key in [k.msg("*")] if fixed is None else [k.msg(j) for j in fixed]:
            self.transport.subscribe(key, self.mailbox.push)
        self.transport.watch_tokens(f"{k.root}/alive/**", self.mailbox.push)
        self.transport.watch_tokens(k.ticking, self.mailbox.push)
        self.transport.declare_token(k.alive(self.id))

    def wait_ready(self) -> None:
        """Declare the ready token once the world and every agent are seen."""
        self.last_heard = time.monotonic()
        deadline = self.last_heard + self.timing.world_timeout
        while not (self.world_seen and (self.alive >= set(self.ids) or self.world_ticking)) \
                and self.stopped is None:
            self._check_world(deadline, "waiting for the world and every agent")
            self._next(min(deadline, time.monotonic() + 0.5))
        self._drain()  # the rest of the tokens already known
        if self.world_ticking and self.est is None:
            self._joining(max(self.ticks, default=0))
        self.transport.declare_token(self.keys.ready(self.id))

    def _joining(self, tick: int) -> None:
        """The world is at ``tick`` without this agent: a restart joining a run
        in progress. It cannot join before the next tick; meanwhile it listens
        to the others' fused estimates, to re-initialise from one."""
        self.k = max(self.k, tick + 1)
        if not self.rejoining:
            self.rejoining = True
            self.transport.subscribe(self.keys.report("*"), self.mailbox.push)
            self.log.info("the run is in progress: rejoining" + (f" (at tick {tick})" if tick else ""))

    def _await_join(self) -> None:
        """Before the first tick: wait for the first tick the world counts this
        agent live in (1, or the tick after a rejoining agent became ready)."""
        mine = lambda: [t for t, tk in self.ticks.items() if self.id in tk.live]  # noqa: E731
        while not mine() and self.stopped is None:
            self._check_world(self.last_heard + self.timing.world_timeout, "waiting to join")
            self._next(min(self.last_heard + self.timing.world_timeout, time.monotonic() + 0.5))
        if mine():
            self.k = min(mine())
            for t in [t for t in self.ticks if t < self.k - 1]:  # tick k - 1 is kept for the re-initialisation
                del self.ticks[t]

    def _reinitialise(self, k: int) -> None:
        """A rejoining agent's estimate of tick k - 1 (``agents.rejoin``)."""
        self._drain()
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

    def step(self) -> None:
        """Tick ``self.k``: wait for the world, local step, exchange, fuse, report."""
        if self.est is None:
            self._await_join()
        k = self.k
        while (k not in self.ticks or k not in self.meas) and self.stopped is None:
            self._check_world(self.last_heard + self.timing.world_timeout, f"waiting for tick {k}")
            self._next(min(self.last_heard + self.timing.world_timeout, time.monotonic() + 0.5))
        if self.stopped is not None:
            return
        t, mm = self.ticks[k], self.meas.pop(k)
        if self.est is None:
            self.est = self._make_estimator(t)
            if self.rejoining:
                self._reinitialise(k)
        self.receiver.tick = k
        own = self.est.local(k, mm.has, mm.y)
        self.transport.put(self.keys.msg(self.id), wire.encode(self.keys.run_id, self.id, k, own))
        self.counters.published += 1

        linked = self.linked[k]
        deadline = time.monotonic() + self.timing.collect_timeout
        self._drain()
        while not linked <= self.receiver.accounted(k) and self.stopped is None and not self.world_gone \
                and not any(j > k for j in self.ticks) and time.monotonic() < deadline:
            self._next(min(deadline, time.monotonic() + POLL_S))
        fused = dict(self.receiver.take(k, linked))
        try:
            out = self.est.fuse(k, own, fused)
        except np.linalg.LinAlgError:  # well-formed messages that still break fusion: keep our own estimate
            self.counters.reject("fusion", len(fused))
            self.log.once("fusion", f"tick {k}: fusion failed; fused this agent's own message alone")
            out = self.est.fuse(k, own, {})
        self.transport.put(self.keys.report(self.id), wire.encode_report(
            self.keys.run_id, self.id, k, out.x[0, 0], out.P[0, 0], out.d[0, 0], out.d_valid[0, 0],
            self.receiver.snapshot() | {"out_of_range": self.out_of_range}))
        self.ticks.pop(k, None)
        self.held.pop(k, None)
        self.linked.pop(k - LINKS_KEPT, None)
        self.k = k + 1

    def run(self) -> int:
        self.start()
        self.wait_ready()
        while self.stopped is None:
            self.step()
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
    add_fault_arguments(p)
    zenoh_config.add_arguments(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    spec = runspec.from_args(args)
    scn = spec.load()
    log = Log(f"agent {args.agent_id}")
    try:
        with ZenohTransport(zenoh_config.from_args(args)) as transport:
            agent = Agent(scn, args.agent_id, spec.algorithm, Keys(spec.run_id), transport,
                          AgentTiming(args.collect_timeout, args.world_timeout), log,
                          fault_config=faults_from_args(args, scn.faults))
            agent.run()
    except MeshError as e:
        log.error(str(e))
        return 1
    return 0


if __name__ == "__main__":
    from diskf_mesh import cli

    sys.exit(cli.run_one("agent", __spec__.name))
