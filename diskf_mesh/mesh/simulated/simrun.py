"""A whole mesh run on the simulated network (``mesh.simulated.simnet``).

``simulate_run`` puts the world (``mesh.protocol.world_machine``) and every agent of a
scenario (``mesh.protocol.agent_machine``) as machines on one ``SimNet``, each under
its own identity of the run's access rules (``credentials.access_control``),
runs it on the virtual clock; ``SimRun.status`` checks the result the way
every run is checked (``mesh.protocol.run_status``: the engine replays what
each agent said it fused). A ``SimPlan`` says what the network does: the links, a fault plan
(pauses, crashes, restarts, interrupts), twins (a second process holding
an agent's id), late starts. The agents' own link faults (``FaultConfig``,
the plan every run can recompute from its seed) come with ``faults``.

Process ids: ``world``, ``agent-<id>``, a twin ``agent-<id>~<n>``; a world
twin ``world~<n>``.

An agent names a linked sender's message that had not come when it closed
the tick "late": it cannot tell a message the network lost from one still on
its way. The simulated network can: the world takes every report's verdicts
through ``NetworkLosses.relabel``, so the run's record, status, deadline
misses and recording name every message it lost "lost".

May import: core, estimators, data, engine (the mesh layer).
"""
from __future__ import annotations

import functools
import io
from dataclasses import dataclass, field

import msgpack

from diskf_mesh import estimators
from diskf_mesh.core.errors import InputError
from diskf_mesh.data.faults import FaultConfig
from diskf_mesh.data.scenario import Scenario
from diskf_mesh.data.trace import Trace
from diskf_mesh.mesh.protocol import clock as realtime
from diskf_mesh.mesh.security import credentials
from diskf_mesh.mesh.protocol.agent_machine import AgentMachine, AgentTiming
from diskf_mesh.mesh.wire.keys import Keys
from diskf_mesh.mesh.protocol.log import Log
from diskf_mesh.mesh.protocol.run_status import OnlineCheck, run_status
from diskf_mesh.mesh.protocol.shared import Shared
from diskf_mesh.mesh.simulated.simnet import Lease, Link, Outcome, SimNet
from diskf_mesh.mesh.protocol.world_machine import WorldMachine, WorldTiming

WORLD = "world"
# Resident memory of a simulated run: a base; per agent (its machine, estimator, views); per link (a sender
# in an agent's largest neighbourhood: its inbox entry, roster of deliveries, the routes' and the access
# rules' answers); per pair of agents (each agent's roster of tokens, two bytes, and the check's (N, N) arrays
# of a tick, a byte each: links, what was fused, digests said and wrong); and per message fused, the world's
# record (two bytes: ``engine.fused.FusedSets``) and what the process's peak gains a tick (about 25 MiB a
# tick at 10,000 agents). Fitted on random-geometric runs (peak RSS of 72, 95, 246 and 399 MiB at 100,
# 200, 1,000 and 2,000 agents x 20 ticks, 80 MiB at 200 x 5, 3,712 MiB at 10,000 x 2 and 4,199 MiB at
# 10,000 x 20; docs/simnet.md), rounded up (tests/test_simnet_up.py holds it within twice a measured
# peak). Every agent is counted with the largest neighbourhood (970 at 10,000 agents, 755 on average):
# 4.1 GiB for 10,000 agents x 20 ticks.
SIM_BYTES_BASE = 64 * 2**20
SIM_BYTES_PER_AGENT = 150 * 2**10
SIM_BYTES_PER_LINK = 64
SIM_BYTES_PER_PAIR = 16
SIM_BYTES_PER_FUSED = 3
# above it a simulated run is refused before it starts: 5 GiB, so that 10,000 random-geometric agents x 20
# ticks run (about 4.1 GiB: 4,199 MiB measured); 12,000 (5.5 GiB) are refused
SIM_MEMORY_BOUND = 5 * 2**30


def simulated_bytes(N: int, degree: int, ticks: int = 0) -> int:
    """About the peak resident memory of a simulated run of ``N`` agents
    whose largest neighbourhood is ``degree`` agents, over ``ticks`` ticks."""
    links = N * min(degree, N)
    return (SIM_BYTES_BASE + N * SIM_BYTES_PER_AGENT + links * SIM_BYTES_PER_LINK + N * N * SIM_BYTES_PER_PAIR
            + links * ticks * SIM_BYTES_PER_FUSED)


def check_size(scn: Scenario) -> None:
    """``InputError`` when a simulated run of ``scn`` would need more than
    ``SIM_MEMORY_BOUND`` bytes (``simulated_bytes``); the engine's own bound
    (``Scenario.check_size``) is checked where the trace is drawn."""
    N, K = len(scn.agents), scn.steps
    if simulated_bytes(N, N, K) <= SIM_MEMORY_BOUND:
        return
    degree = scn.largest_neighbourhood(scn.steps)
    need = simulated_bytes(N, degree, K)
    if need > SIM_MEMORY_BOUND:
        raise InputError("size", f"a simulated run of {N} agents (up to {degree} in one neighbourhood) needs about "
                                 f"{need / 2**30:.1f} GiB, over the simulated network's bound of "
                                 f"{SIM_MEMORY_BOUND / 2**30:g} GiB; use fewer agents, or the engine (experiment)")


def agent_pid(agent_id, twin: int = 0) -> str:
    return credentials.agent_identity(agent_id) + (f"~{twin}" if twin else "")


@dataclass(frozen=True)
class SimPlan:
    """What the simulated network does to a run."""

    link: Link = Link()
    links: object = None             # (sender pid, receiver pid) -> Link or None (``link``)
    faults: tuple = ()               # simnet.Fault, ...
    twins: tuple = ()                # (agent id or "world", start time), ...: a second process of that id
    late: dict = field(default_factory=dict)  # agent id -> start time (default 0)
    lease: Lease = Lease()
    secure: bool = True              # the credentials' access rules (False: anyone may do anything)
    router: bool = False             # the rules have a router identity (that may put anything of the run)
    wrap: dict = field(default_factory=dict)  # pid -> f(machine) -> machine (a compromised process)
    extra: tuple = ()                # (pid, identity, factory(Boot), start time), ...: other processes
    world_timing: WorldTiming = WorldTiming()
    agent_timing: AgentTiming = AgentTiming()
    allow_missing: bool = False      # the world starts without the agents not ready after its startup timeout
    max_time: float = 3600.0
    online: bool = True              # the world checks each tick as its reports come (and cuts off a liar)
    views: bool = True               # the agents share views of the tokens (``SimNet(views=)``; False: one each)
    arrivals: bool = True            # an agent's samples of one instant come as one event (``SimNet(arrivals=)``)


class NetworkLosses:
    """The agents' messages the network lost (``SimNet.lost_samples``), as
    (receiver id, sender id, tick), and the verdicts that say so."""

    def __init__(self, net: SimNet, ids):
        self._net, self._seen, self._lost = net, 0, set()
        self._ids = {agent_pid(i): i for i in ids}

    def lost(self) -> set:
        samples = self._net.lost_samples
        for pid, payload in samples[self._seen:]:
            receiver = self._ids.get(pid)
            if receiver is None:
                continue
            try:
                doc = msgpack.unpackb(payload, raw=False)
            except (ValueError, msgpack.UnpackException):
                continue
            if isinstance(doc, dict) and doc.get("k") == "msg":
                self._lost.add((receiver, doc.get("s"), doc.get("t")))
        self._seen = len(samples)
        return self._lost

    def relabel(self, receiver, tick: int, not_fused) -> tuple:
        """``not_fused`` ((sender, verdict), ...) of ``receiver``'s report of
        ``tick`` with "late" made "lost" where the network lost the message."""
        lost = self.lost()
        return tuple((s, "lost" if v == "late" and (receiver, s, tick) in lost else v) for s, v in not_fused)


@dataclass
class SimRun:
    """A simulated run as it ended; ``status`` judges it (once, when asked)."""

    outcome: Outcome
    world: WorldMachine              # the world that ran the run (its last incarnation)
    finished: bool                   # ... and it finished
    log: str                         # every process's lines
    scn: Scenario
    trace: Trace
    algorithm: str
    seed: int
    faults: FaultConfig | None
    run_id: str
    deadline_s: float                # the agents' deadline (real time; inf: lockstep)

    @property
    def record(self):
        return self.world.record

    @functools.cached_property
    def status(self):
        """``engine.verify.RunStatus`` of the run (``mesh.protocol.run_status``:
        incomplete with the world's reason if it ended before any report),
        or None if the world never finished."""
        if not self.finished:
            return None
        return run_status(self.record, self.trace, self.algorithm, self.scn.params, run_id=self.run_id,
                          seed=self.seed, faults=self.faults, deadline_s=self.deadline_s, labels=self.scn.labels,
                          online=getattr(self.world, "online", None))


def simulate_run(scn: Scenario, trace: Trace, algorithm: str, seed: int, *, net_seed: int | None = None,
                 plan: SimPlan = SimPlan(), faults: FaultConfig | None = None, run_id: str = "sim",
                 keep_lines: bool = False, quiet: bool = True, progress=None,
                 recorder=None, batch: bool = True) -> SimRun:
    """The run of ``scn`` (simulated as ``trace``, seed ``seed``) with
    ``algorithm`` on the simulated network seeded by ``net_seed`` (default
    ``seed``) under ``plan``. ``quiet``: the processes' lines go to
    ``SimRun.log`` instead of stderr; ``progress(k)``, ``recorder``: the
    world's observers (``WorldMachine``). ``batch``: what the machines
    compute from one payload is computed once for all of them
    (``mesh.protocol.shared``), and the agents' estimator steps of one
    instant run as one call (``SimNet(batch_steps=)``); False: each machine
    alone, as in a process mesh (the same run, event for event, bit for bit)."""
    keys = Keys(run_id)
    ids = tuple(a.id for a in scn.agents)
    stream = io.StringIO() if quiet else None
    policy = credentials.access_control(run_id, ids, observer=False, router=plan.router) if plan.secure else None
    net = SimNet(seed if net_seed is None else net_seed, link=plan.link, links=plan.links, policy=policy,
                 lease=plan.lease, keep_lines=keep_lines, max_time=plan.max_time, views=plan.views,
                 batch_steps=batch, arrivals=plan.arrivals)
    losses = NetworkLosses(net, ids)

    deadline_s = realtime.agents_deadline(plan.agent_timing.clock, plan.agent_timing.collect_timeout)

    shared = Shared(agents=len(ids)) if batch else None  # a payload's decode and checks, once for all its receivers
    estimator = estimators.get(algorithm)  # resolved once: every agent's and the world's online check

    def world(boot):
        first = boot.pid == WORLD and boot.incarnation == 0  # the observers watch the run's own world
        online = OnlineCheck(trace, estimator, scn.params, run_id=run_id, seed=seed, faults=faults,
                             deadline_s=deadline_s) if plan.online else None
        return WorldMachine(scn, trace, algorithm, seed, keys, boot.nonce, plan.world_timing,
                            allow_missing=plan.allow_missing, verdicts=losses.relabel,
                            log=Log(f"world {boot.pid}#{boot.incarnation}" if boot.incarnation else boot.pid, stream),
                            progress=progress if first else None, recorder=recorder if first else None,
                            online=online)

    def agent(i):
        def make(boot):
            who = f"agent {i}" + (f" ({boot.pid}#{boot.incarnation})" if boot.incarnation or "~" in boot.pid else "")
            return AgentMachine(scn, i, estimator, keys, boot.nonce, plan.agent_timing, faults=faults,
                                log=Log(who, stream), shared=shared)
        return make

    def add(pid, factory, identity, at=0.0):
        wrap = plan.wrap.get(pid)
        net.add(pid, factory if wrap is None else (lambda boot: wrap(factory(boot))), identity=identity, at=at)

    add(WORLD, world, credentials.WORLD)
    for i in ids:
        add(agent_pid(i), agent(i), credentials.agent_identity(i), float(plan.late.get(i, 0.0)))
    for n, (who, at) in enumerate(plan.twins, start=1):
        if who == WORLD:
            add(f"{WORLD}~{n}", world, credentials.WORLD, float(at))
        else:
            add(agent_pid(who, n), agent(who), credentials.agent_identity(who), float(at))
    for pid, identity, factory, at in plan.extra:
        add(pid, factory, identity, float(at))
    net.plan(plan.faults)
    out = net.run()
    # the world that ran the run (of two holding the run id, one leaves as a duplicate: it heard no report)
    worlds = [pid for pid in out.machines if pid == WORLD or pid.startswith(WORLD + "~")]
    stayed = lambda p: getattr(out.finishes.get(p), "status", None) != "duplicate"  # noqa: E731
    pid = max(worlds, key=lambda p: (int(out.machines[p].record.reported.sum()), stayed(p), p == WORLD))
    for p in worlds:  # the run is over: the checks let the engine go and keep their ticks (``SimRun.status``)
        if getattr(out.machines[p], "online", None) is not None:
            out.machines[p].online.close()
    return SimRun(out, out.machines[pid], pid in out.finishes, stream.getvalue() if stream is not None else "",
                  scn, trace, algorithm, seed, faults, run_id, deadline_s)

