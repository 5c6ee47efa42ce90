"""The samples that reach an agent at one instant as one ``Arrivals`` event
(``SimNet(arrivals=True)``, the receivers of a fan in one pass, a run of
neighbours' messages taken by ``Receiver.on_messages`` in one call) give the
run each sample delivered as its own event gives (``arrivals=False``): the
same reports, estimates, counters, rejoins, losses and status, for every
estimator, with the agents' own link faults, a pause past the lease, a
crash and a restart (a rejoin)."""
from __future__ import annotations

import collections

import numpy as np
import pytest

import simnet_cases as cases

from diskf_mesh import estimators
from diskf_mesh.core.messages import Message
from diskf_mesh.data.faults import FaultConfig
from diskf_mesh.mesh.protocol.events import MessageArrived, TickArrived
from diskf_mesh.mesh.protocol.guard import Guard, GuardConfig
from diskf_mesh.mesh.protocol.receive import Receiver
from diskf_mesh.mesh.simulated.simnet import Fault, Link
from diskf_mesh.mesh.simulated.simrun import SimPlan, agent_pid, simulate_run
from diskf_mesh.mesh.wire import codec as wire

PLANS = {
    "nominal": ({}, None),
    "own link faults": ({}, FaultConfig(loss=0.1, latency_ms=1.0, duplicate=0.1, reorder=0.1)),
    "paused past the lease, crash and restart": (
        {"faults": (Fault("pause", agent_pid(7), at=0.08, duration=12.0), Fault("crash", agent_pid(3), at=0.05),
                    Fault("restart", agent_pid(3), at=0.1))}, None),
}


def _run(algorithm, plan, arrivals):
    scn, trace = cases.world("random-geometric", 40, 30, 2)
    how, faults = PLANS[plan]
    return simulate_run(scn, trace, algorithm, 2, faults=faults,
                        plan=SimPlan(Link(delay=0.002), max_time=600, arrivals=arrivals, **how))


CASES = [(n, "nominal") for n in estimators.NAMES] + [(estimators.DEFAULT, p) for p in PLANS if p != "nominal"] + [
    ("diskf", p) for p in PLANS if p != "nominal"]


@pytest.mark.parametrize("algorithm,plan", CASES, ids=[f"{a}-{p}" for a, p in CASES])
def test_a_run_with_arrivals_is_the_run_with_each_sample_alone(algorithm, plan):
    a, b = _run(algorithm, plan, True), _run(algorithm, plan, False)
    assert a.outcome.events < b.outcome.events  # the samples of an instant came together
    assert a.record.reported.tolist() == b.record.reported.tolist() and a.record.reported.sum() > 0
    for f in ("x", "P", "d"):
        assert getattr(a.record, f).tobytes() == getattr(b.record, f).tobytes(), f
    assert set(a.outcome.machines) == set(b.outcome.machines)
    for pid, m in a.outcome.machines.items():
        other = b.outcome.machines[pid]
        assert getattr(m, "counters", None) == getattr(other, "counters", None), pid
        assert getattr(m, "rejoins", None) == getattr(other, "rejoins", None), pid
    assert a.outcome.lost == b.outcome.lost
    assert a.status.status == b.status.status and a.status.evidence == b.status.evidence
    if plan.startswith("paused"):
        assert a.outcome.machines[agent_pid(3)].rejoins == [(14, None)]  # restarted, rejoined from the prior


def test_messages_taken_together_are_counted_and_held_as_each_alone():
    """``Receiver.on_messages`` takes the front of a queue of arrivals that
    each would be held for the current tick, stops at the first that would
    not (a repeat, an unlinked sender, another tick), and leaves the
    receiver as ``on_message`` of each would."""
    n, m, me, tick = 2, 1, 0, 3
    ids = frozenset(range(8))
    config = GuardConfig("r", me, ids, n, m, ticks=10)

    def arrival(sender, k):
        payload = wire.encode("r", sender, k, _message(n, m, sender), estimators.get("diskf").exchanged)
        return Guard(GuardConfig("r", 7, ids, n, m)).read(sender, payload)

    queue = [arrival(s, tick) for s in (1, 2, 3)] + [arrival(2, tick), arrival(4, tick), arrival(5, tick + 1)]
    links = {tick: {1, 2, 3, 4, 5}, tick + 1: {5}}
    together, alone = Receiver(Guard(config)), Receiver(Guard(config))
    for r in (together, alone):
        r.advance(tick)
    waiting = collections.deque(queue)
    assert together.on_messages(waiting, links, 1.0) == 3 and list(waiting) == queue[3:]
    while waiting:
        together.on_message(waiting.popleft(), links, 1.0)
    for a in queue:
        alone.on_message(a, links, 1.0)
    assert together.counters == alone.counters and together.counters.duplicate == 1
    assert [(s, x.x_pred.tobytes()) for s, x in together.take(tick, links[tick])] == \
        [(s, x.x_pred.tobytes()) for s, x in alone.take(tick, links[tick])]
    assert together.digests(tick) == alone.digests(tick)
    other = Receiver(Guard(config))
    other.advance(tick)
    waiting = collections.deque([queue[0], TickArrived(None), queue[1]])  # a world's sample ends the run taken
    assert other.on_messages(waiting, links, 1.0) == 1 and len(waiting) == 2


def _message(n, m, sender):
    rng = np.random.default_rng(sender)
    return Message(x_pred=rng.normal(size=n), P_pred=2.0 * np.eye(n), x_upd=rng.normal(size=n), P_upd=np.eye(n),
                   d=rng.normal(size=m), S=np.eye(m), d_valid=np.ones(m, dtype=bool))


def test_on_messages_takes_nothing_under_a_fault_model():
    config = GuardConfig("r", 0, frozenset(range(4)), 2, 1, ticks=10)
    r = Receiver(Guard(config), FaultConfig(loss=0.5))
    r.learn_run(10, 1)
    r.advance(1)
    waiting = collections.deque([MessageArrived(1, None, None)])
    assert r.on_messages(waiting, {1: {1}}, 0.0) == 0 and len(waiting) == 1
