"""Schedules for the simulated network's property tests, and the invariants
every run must keep.

``build(draw)`` makes one ``Case`` (a small world, a link model, a fault
plan) from a source of choices: hypothesis (``from_hypothesis``: shrinks to
a small failing case) or one integer seed (``from_seed``: a sweep, and a
seed that replays alone). ``run(case)`` runs it; ``check(case, run)``
asserts the invariants:

    (a) a run reported ``exact`` equals the engine on the nominal links, bit for bit
    (b) any other run names the agent-ticks whose fused set differs from
        the plan, and the engine's replay of the fused sets reproduces every
        verifiable estimate (an honest run never ``diverged``)
    (c) nothing is fused from a sender not linked at that tick
    (d) every run ends in bounded virtual time with a status
    (e) a rejoining agent starts from a neighbour's estimate whenever a
        neighbour in range reported the tick before
    (f) the world's check as the run goes cuts no agent off
"""
from __future__ import annotations

import functools
from dataclasses import dataclass, field

import numpy as np

from diskf_mesh.core import exits
from diskf_mesh.data.faults import FaultConfig
from diskf_mesh.data.scenario import load_scenario, simulate
from diskf_mesh.engine import batch
from diskf_mesh.engine.verify import nominal_links, planned_links
from diskf_mesh.mesh.protocol.agent_machine import AgentTiming
from diskf_mesh.mesh.protocol.events import FREEZE_S
from diskf_mesh.mesh.simulated.simnet import Fault, Lease, Link
from diskf_mesh.mesh.simulated.simrun import WORLD, SimPlan, agent_pid, simulate_run
from diskf_mesh.mesh.protocol.world_machine import WorldTiming
from diskf_mesh.recording.replay import compare_reported

ALGORITHMS = ("diskf", "diskf", "diskf", "diskf-r", "diskf-auto", "kcf", "diffkf", "ldrkf")
MSGS = "diskf/sim/agent/*/msg/**"
# random-geometric with 3 to 9 agents (sparse, links come and go), quadrants (4, every pair linked),
# dynamic (9, in range of each other as they move)
SCENARIOS = ("random-geometric", "random-geometric", "quadrants", "dynamic")
SIZES = {"quadrants": 4, "dynamic": 9}
STATUSES = exits.STATUSES


@dataclass(frozen=True)
class Case:
    agents: int
    ticks: int
    algorithm: str
    seed: int
    link: Link = Link()
    faults: tuple = ()          # simnet.Fault
    twins: tuple = ()           # (agent id or "world", start time)
    late: tuple = ()            # (agent id, start time)
    injected: FaultConfig | None = None  # the agents' own seeded link faults (the plan)
    lease: Lease = Lease()
    world_timing: WorldTiming = WorldTiming()
    agent_timing: AgentTiming = AgentTiming()
    scenario: str = "random-geometric"
    links: tuple = ()           # ((sender pid, receiver pid), Link): a pair's link other than ``link``
    notes: tuple = field(default=(), compare=False)

    @property
    def bound(self) -> float:
        """Virtual time a run may take: start-up, every tick at its timeout,
        every pause, the agents' patience with a silent world, the leave."""
        w, a = self.world_timing, self.agent_timing
        paused = sum(f.duration for f in self.faults if f.kind == "pause")
        started = max([0.0] + [t for _, t in self.twins] + [t for _, t in self.late])
        return started + w.startup_timeout * 3 + self.ticks * (w.tick_timeout + a.collect_timeout) + paused \
            + a.world_timeout * 2 + w.leave_timeout + self.lease.lease * (1 + len(self.faults))


def apart(pid: str) -> tuple:
    """Links of 30 s both ways between ``pid`` and its first twin: neither session hears the other."""
    return tuple(((a, b), Link(delay=30.0)) for a, b in ((pid, pid + "~1"), (pid + "~1", pid)))


def build(draw) -> Case:
    """One case from ``draw``: ``draw.int(lo, hi)`` and ``draw.pick(seq)``."""
    scenario = draw.pick(SCENARIOS)
    N, K = (draw.int(3, 9) if scenario == "random-geometric" else SIZES[scenario]), draw.int(20, 60)
    algorithm = draw.pick(ALGORITHMS)
    seed = draw.int(0, 2 ** 16)
    wt, at, lease = WorldTiming(), AgentTiming(), Lease()
    delay = draw.pick((0.0002, 0.002, 0.02))
    jitter = draw.pick((0.0, delay, 10 * delay))
    # durations around every timeout of the protocol
    timeouts = (FREEZE_S, at.collect_timeout, wt.tick_timeout, lease.lease, wt.startup_timeout, at.world_timeout)
    around = lambda: max(0.001, draw.pick(timeouts) + draw.pick((-0.3, -0.01, 0.01, 0.3)))  # noqa: E731
    hold = draw.pick((2 * delay, at.collect_timeout * 0.9, at.collect_timeout * 1.1))
    link = Link(delay, jitter)
    if draw.int(0, 3) == 0:  # the network loses, duplicates and reorders agents' messages
        link = Link(delay, jitter, loss=draw.pick((0.0, 0.05, 0.3)), duplicate=draw.pick((0.0, 0.1, 0.5)),
                    reorder=draw.pick((0.0, 0.1, 0.5)), hold=hold, faulty=MSGS)
    elif draw.int(0, 5) == 0:  # every sample may come twice
        link = Link(delay, jitter, duplicate=draw.pick((0.1, 0.5)), hold=hold)
    injected = None
    if draw.int(0, 4) == 0:
        injected = FaultConfig(loss=draw.pick((0.0, 0.1, 0.3)), duplicate=draw.pick((0.0, 0.1)),
                               latency_ms=draw.pick((0.0, 1.0)), jitter_ms=draw.pick((0.0, 1.0)),
                               reorder=draw.pick((0.0, 0.1)))
    pids = [WORLD] + [agent_pid(i) for i in range(1, N + 1)]
    events = K * N * 8
    faults = []
    for _ in range(draw.pick((0, 0, 1, 1, 2, 3))):
        kind = draw.pick(("pause", "pause", "crash", "crash-restart", "world-pause", "interrupt"))
        pid = WORLD if kind == "world-pause" else draw.pick(pids[1:] if kind != "interrupt" else pids)
        e = draw.int(1, events)
        if kind in ("pause", "world-pause"):
            faults.append(Fault("pause", pid, after_event=e, duration=around()))
        elif kind == "interrupt":
            faults.append(Fault("interrupt", pid, after_event=e, why=draw.pick(("SIGTERM", "SIGINT"))))
        else:
            faults.append(Fault("crash", pid, after_event=e, lease=bool(draw.int(0, 1))))
            if kind == "crash-restart":
                faults.append(Fault("restart", pid, after_event=e + draw.int(1, events)))
    twins = ()
    if draw.int(0, 7) == 0:
        who = WORLD if draw.int(0, 3) == 0 else draw.int(1, N)
        twins = ((who, draw.pick((0.0, 0.0001, delay * K))),)
    late = ()
    if draw.int(0, 7) == 0:
        late = ((draw.int(1, N), draw.pick((0.001, delay * K / 2, around()))),)
    links = ()
    if twins and twins[0][0] != WORLD and draw.int(0, 1):  # the two processes' sessions do not hear each other
        links = apart(agent_pid(twins[0][0]))
    return Case(N, K, algorithm, seed, link, tuple(faults), twins, late, injected, lease, wt, at, scenario, links)


class _Hypothesis:
    def __init__(self, data):
        self.data = data

    def int(self, lo, hi):
        from hypothesis import strategies as st
        return self.data.draw(st.integers(lo, hi))

    def pick(self, seq):
        from hypothesis import strategies as st
        return self.data.draw(st.sampled_from(seq))


class _Seeded:
    def __init__(self, seed):
        self.rng = np.random.default_rng([0x5EED, seed])

    def int(self, lo, hi):
        return int(self.rng.integers(lo, hi + 1))

    def pick(self, seq):
        return seq[int(self.rng.integers(len(seq)))]


def from_hypothesis(data) -> Case:
    return build(_Hypothesis(data))


def from_seed(seed: int) -> Case:
    return build(_Seeded(seed))


@functools.lru_cache(maxsize=64)
def world(scenario: str, N: int, K: int, seed: int):
    scn = load_scenario(scenario, agents=N if scenario == "random-geometric" else None).with_overrides(steps=K)
    return scn, simulate(scn, [seed])


def run(case: Case, keep_lines: bool = False, batch: bool = True, views: bool = True, arrivals: bool = True):
    scn, trace = world(case.scenario, case.agents, case.ticks, case.seed)
    pairs = dict(case.links)
    plan = SimPlan(case.link, links=(lambda a, b: pairs.get((a, b))) if pairs else None,
                   faults=case.faults, twins=case.twins, late=dict(case.late), lease=case.lease,
                   world_timing=case.world_timing, agent_timing=case.agent_timing, max_time=case.bound,
                   views=views, arrivals=arrivals)
    return simulate_run(scn, trace, case.algorithm, case.seed, plan=plan, faults=case.injected,
                        keep_lines=keep_lines, batch=batch)


def check(case: Case, r) -> None:
    """The invariants (module docstring); an AssertionError names the broken one."""
    scn, trace = world(case.scenario, case.agents, case.ticks, case.seed)
    out, rec = r.outcome, r.record
    # (d) bounded, with a status
    assert out.bounded, f"(d) the run did not end by t={case.bound:g} (last event at {out.end:g})"
    assert any(w == WORLD or w.startswith(WORLD + "~") for w in out.finishes) or _world_crashed(case), \
        "(d) the world never finished"
    if r.status is None:
        assert _world_crashed(case), "(d) a run whose world finished has no status"
        return
    st = r.status
    assert st.status in STATUSES, st
    if not rec.reported.any():  # the world gave up before any report (a start-up failure): incomplete, why
        assert st.status == "incomplete" and st.evidence["missing_fraction"] == 1.0, st
        assert r.world.finish is None or r.world.finish.reason in st.reason or not r.world.finish.reason, st
        return
    ids = list(rec.ids)
    K = rec.reported.shape[0]
    live = rec.live
    nominal = nominal_links(trace, K, live)
    N = nominal.shape[-1]
    off = ~np.eye(N, dtype=bool)
    fused = rec.fused & off
    # (c) nothing fused from a sender not linked (in range, both live) at that tick
    stray = fused & ~nominal
    assert not stray.any(), f"(c) fused a sender not linked: (tick, agent, sender) {np.argwhere(stray)[:5] + [1, 0, 0]}"
    # (a) exact: the engine on the nominal links, bit for bit
    if st.status == "exact":
        assert rec.reported.all(), "(a) exact with agent-ticks missing"
        est = batch.run(trace, case.algorithm, scn.params)
        cmp = compare_reported(rec.estimates(), rec.reported, _first(est, K))
        assert cmp.equal, f"(a) exact but {cmp.differing} agent-ticks differ from the engine (max {cmp.max_abs:g})"
        assert (fused == nominal & off)[rec.reported].all()
    # (b) an honest run never diverges; every agent-tick whose fused set differs from the plan is
    # counted (fewer, or others), the first ones named; a complete run's estimates are the replay's
    assert st.status != "diverged", f"(b) honest run diverged: {st.reason}"
    planned = planned_links(nominal, list(rec.ids), case.injected, case.seed) & off
    short = (rec.reported[..., None] & planned & ~fused).any(-1)
    more = (rec.reported[..., None] & fused & ~planned).any(-1)
    ev = st.evidence
    assert ev["degraded"]["agent_ticks"] == int(short.sum()), \
        f"(b) {int(short.sum())} agent-ticks fused less than planned, the status says {ev['degraded']['agent_ticks']}"
    assert ev["unplanned"]["agent_ticks"] == int(more.sum()), "(b) agent-ticks fusing more than planned"
    for named in ev["degraded"]["listed"]:
        assert short[named["tick"] - 1, ids.index(named["agent"])], f"(b) {named} named but fused as planned"
    if st.status in ("exact", "as planned"):
        assert not short.any() and not more.any(), f"(b) {st.status} with fused sets off the plan"
    if rec.reported.all():
        assert ev["differing"] == 0, f"(b) {ev['differing']} estimates not reproduced"
    # (f) an honest run cuts no agent off (the world's check as the run goes names no liar)
    assert not rec.quarantined, f"(f) honest agents cut off: {rec.quarantined}"
    # (e) a rejoin starts from a neighbour's estimate when a neighbour in range reported the tick before
    for agent, rejoins in rec.rejoins.items():
        j = ids.index(agent)
        for rj in rejoins:
            J = int(rj["tick"])
            if J < 2 or rj["source"] is not None:
                continue
            near = [s for s in range(N) if s != j and trace.links[0, J - 2, j, s] and rec.reported[J - 2, s]]
            assert not near, (f"(e) agent {agent} rejoined at tick {J} from the prior though "
                              f"{[ids[s] for s in near]} in range reported tick {J - 1}")


def _first(est, K):
    return batch.Estimates(est.x[:, :K], est.P[:, :K], est.d[:, :K], est.d_valid[:, :K])


def _world_crashed(case: Case) -> bool:
    return any(f.pid == WORLD and f.kind in ("crash", "interrupt") for f in case.faults)
