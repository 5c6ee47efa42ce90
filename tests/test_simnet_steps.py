"""The agents' steps of one tick run together (``mesh.protocol.estimator.Steps``,
as the simulated network runs them) give the bits each agent's step gives
alone (a process's), for every estimator, with the defence on and off, on
agents with few and many neighbours, from the prior and from a rejoin."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from diskf_mesh import estimators
from diskf_mesh.estimators.base import DEFENCE
from diskf_mesh.data.scenario import load_scenario, simulate
from diskf_mesh.mesh.protocol.estimator import AgentEstimator, Steps
from diskf_mesh.mesh.protocol.events import Work
from diskf_mesh.mesh.simulated.simnet import Fault, Link
from diskf_mesh.mesh.simulated.simrun import SimPlan, simulate_run

K, SEED = 6, 5


@pytest.fixture(scope="module")
def run():
    scn = load_scenario("random-geometric", agents=60).with_overrides(steps=K)
    return scn, simulate(scn, [SEED])


def _fields(x):
    return [np.asarray(v).tobytes() for v in dataclasses.astuple(x)]


def lockstep_both(scn, trace, name, steps, start=None, liars=(), agents=None):
    """Every agent twice, alone and together, tick by tick over ``trace``:
    yields (alone's outputs, together's outputs) per tick, with each
    receiver fusing the message objects it received (one object per
    sender, shared by its receivers, as the simulated network decodes it;
    every third receiver's also holding its own, which it fuses as its
    own, not as received)."""
    ids = list(scn.ids)
    est = estimators.get(name)
    alone = {i: AgentEstimator(scn, i, est, K, SEED, start=start) for i in ids}
    together = {i: AgentEstimator(scn, i, est, K, SEED, start=start) for i in ids}
    if agents is not None:
        agents.update(alone=alone, together=together)
    for k in range(1, K + 1):
        args = {i: (k, bool(trace.has[0, k - 1, j]), trace.y[0, k - 1, j, :alone[i].p]) for j, i in enumerate(ids)}
        own_a = {i: alone[i].local(*args[i]) for i in ids}
        got = steps.carry_out([Work(together[i], "local", args[i]) for i in ids])
        own_t = dict(zip(ids, got))
        for i in ids:
            assert _fields(own_a[i]) == _fields(own_t[i]), (name, k, i)
        sent = {i: own_t[i].take((0, 0)) for i in ids}
        for i in liars:
            sent[i] = dataclasses.replace(sent[i], x_pred=sent[i].x_pred + 40.0)
        heard = {i: {o: sent[o] for jj, o in enumerate(ids) if trace.links[0, k - 1, j, jj] and (o != i or j % 3 == 0)}
                 for j, i in enumerate(ids)}
        outs_a = [alone[i].fuse(k, own_a[i], heard[i]) for i in ids]
        outs_t = steps.carry_out([Work(together[i], "fuse", (k, own_t[i], heard[i])) for i in ids])
        yield k, outs_a, outs_t


CASES = [(n, False) for n in estimators.NAMES] + [(n, True) for n in estimators.NAMES
                                                   if DEFENCE in estimators.get(n).settings]


@pytest.mark.parametrize("name,defence", CASES, ids=[f"{n}{'-defence' if d else ''}" for n, d in CASES])
def test_steps_together_equal_each_alone_bit_for_bit(run, name, defence):
    scn, trace = run
    if defence:
        scn = dataclasses.replace(scn, params=dataclasses.replace(scn.params, defence=True))
    degrees = trace.links[0].sum(axis=-1)
    assert degrees.min() <= 2 and degrees.max() >= 8  # lone agents and crowded ones
    for k, outs_a, outs_t in lockstep_both(scn, trace, name, Steps()):
        for a, t in zip(outs_a, outs_t):
            assert _fields(a) == _fields(t), (name, k)


def test_steps_together_with_liars_equal_each_alone(run):
    """With the defence on and two liars, the evidence each receiver keeps
    against each sender, at that sender's place, and what it then fuses, are
    the same together as alone (the liars are cut by some receivers)."""
    scn, trace = run
    scn = dataclasses.replace(scn, params=dataclasses.replace(scn.params, defence=True))
    ids = list(scn.ids)
    agents, grew = {}, 0.0
    for k, outs_a, outs_t in lockstep_both(scn, trace, estimators.DEFAULT, Steps(), liars=(ids[4], ids[31]),
                                           agents=agents):
        for a, t in zip(outs_a, outs_t):
            assert _fields(a) == _fields(t), k
        for i in ids:
            alone, together = agents["alone"][i].state.evidence, agents["together"][i].state.evidence
            assert alone.tobytes() == together.tobytes(), (k, i)
            grew = max(grew, float(alone.max()))
    assert grew > 0.0


@pytest.mark.parametrize("name", ["diskf-auto", "diskf-r"])
def test_steps_in_parts_equal_each_alone(run, name, monkeypatch):
    """Receivers fused in parts of a few (a working set past
    ``BLOCK_BYTES_MAX``), each part as wide as its busiest receiver: the
    same bits as each alone."""
    from diskf_mesh.mesh.protocol import estimator as agent_estimator

    scn, trace = run
    monkeypatch.setattr(agent_estimator, "BLOCK_BYTES_MAX", 5 * 10 * 3000)
    parts = []
    fuse = type(estimators.get(name)).__dict__.get("screened_fuse", estimators.get(name).screened_fuse)
    monkeypatch.setattr(estimators.get(name), "screened_fuse",
                        lambda self, state, own, senders, nb: parts.append(senders.x_pred.shape[1:3])
                        or fuse(self, state, own, senders, nb))
    for k, outs_a, outs_t in lockstep_both(scn, trace, name, Steps()):
        for a, t in zip(outs_a, outs_t):
            assert _fields(a) == _fields(t), (name, k)
    together = [p for p in parts if p[0] > 1]
    assert len(together) > 2 * K and len({p[1] for p in together}) > 2  # many parts, of several widths


def test_steps_together_from_a_rejoin_equal_each_alone(run):
    scn, trace = run
    start = (np.array([3.0, -2.0, 1.0, 0.5])[:scn.model(K).n], 4.0 * np.eye(scn.model(K).n))
    for k, outs_a, outs_t in lockstep_both(scn, trace, estimators.DEFAULT, Steps(), start=start):
        for a, t in zip(outs_a, outs_t):
            assert _fields(a) == _fields(t)


RUN_CASES = [
    # a pause past the lease (a rejoin from a neighbour's estimate), a crash and restart, lost messages;
    # duplicated and reordered messages, a pause past the collect timeout
    ("diskf-auto", dict(link=Link(delay=0.002, loss=0.02, faulty="diskf/sim/agent/*/msg/**"),
                        faults=(Fault("pause", "agent-7", at=0.6, duration=12.0),
                                Fault("crash", "agent-3", at=0.3), Fault("restart", "agent-3", at=4.0)))),
    ("diskf-r", dict(link=Link(delay=0.002, duplicate=0.05, reorder=0.1, faulty="diskf/sim/agent/*/msg/**"),
                     faults=(Fault("pause", "agent-12", at=0.3, duration=3.0),))),
    ("diskf", dict(link=Link(delay=0.0002))),
]


@pytest.mark.parametrize("name,plan", RUN_CASES, ids=[n for n, _ in RUN_CASES])
def test_a_simulated_run_with_steps_together_is_the_run_with_each_alone(name, plan):
    """``simulate_run(batch=True)`` (the steps of an instant together) and
    ``batch=False`` (each alone) are one run: the same events, counters,
    reports, estimates and status, with lost messages, a rejoin and a restart."""
    scn = load_scenario("random-geometric", agents=40).with_overrides(steps=12)
    trace = simulate(scn, [2])
    a, b = (simulate_run(scn, trace, name, 2, plan=SimPlan(**plan), batch=batch) for batch in (True, False))
    assert (a.outcome.digest, a.outcome.events, a.outcome.lost) == (b.outcome.digest, b.outcome.events, b.outcome.lost)
    for pid, m in a.outcome.machines.items():
        assert getattr(m, "counters", None) == getattr(b.outcome.machines[pid], "counters", None), pid
    ra, rb = a.record, b.record
    assert ra.reported.tolist() == rb.reported.tolist() and ra.reported.sum() > 0
    for f in ("x", "P", "d"):
        assert getattr(ra, f).tobytes() == getattr(rb, f).tobytes(), f
    assert a.status.status == b.status.status and a.status.evidence == b.status.evidence
    if name == "diskf-auto":  # agent 3 restarted from the prior, agent 7 rejoined from a neighbour's estimate
        assert {p: m.rejoins for p, m in a.outcome.machines.items() if getattr(m, "rejoins", None)} == \
            {"agent-3": [(3, None)], "agent-7": [(6, 6)]}
