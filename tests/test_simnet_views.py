"""The agents' shared views of the liveliness tokens (``SimNet(views=True)``:
one count per key for every agent that watches the same tokens, a token's
coming or going cast to all of them as one ``TokenBatch``) give the run
each agent would see with its own view (``views=False``: one ``Token``
event per watcher): the same reports, estimates, counters and status,
under pauses past the lease, crashes, restarts, rejoins and twins, for
every estimator."""
from __future__ import annotations

import numpy as np
import pytest

import simnet_cases as cases

from diskf_mesh.mesh.simulated.simnet import Fault, Lease, Link
from diskf_mesh.mesh.simulated.simrun import SimPlan, agent_pid, simulate_run
from diskf_mesh.mesh.protocol.roster import Roster

PLANS = {
    "nominal": {},
    "paused past the lease": {"faults": (Fault("pause", agent_pid(2), at=0.5, duration=14.0),)},
    "crash and restart": {"faults": (Fault("crash", agent_pid(3), at=0.3, lease=True),
                                     Fault("restart", agent_pid(3), at=12.0))},
    "crash at once, restart": {"faults": (Fault("crash", agent_pid(1), at=0.2),
                                          Fault("restart", agent_pid(1), at=3.0))},
    "twin": {"twins": ((2, 0.0),)},
    "late": {"late": {4: 2.0}},
}


def _run(algorithm, plan, views, scenario="random-geometric", agents=6):
    scn, trace = cases.world(scenario, agents, 30, 7)
    return simulate_run(scn, trace, algorithm, 7, plan=SimPlan(Link(delay=0.002), lease=Lease(), views=views,
                                                                max_time=600, **PLANS[plan]))


def _same(a, b):
    assert a.record.reported.tolist() == b.record.reported.tolist()
    assert np.array_equal(a.record.x, b.record.x, equal_nan=True)
    assert (a.status is None) == (b.status is None)
    if a.status is not None:
        assert (a.status.status, a.status.reason) == (b.status.status, b.status.reason)
    for pid, m in a.outcome.machines.items():
        assert getattr(m, "counters", None) == getattr(b.outcome.machines[pid], "counters", None), pid
        assert getattr(m, "rejoins", None) == getattr(b.outcome.machines[pid], "rejoins", None), pid


@pytest.mark.parametrize("plan", list(PLANS))
def test_shared_views_give_the_run_of_one_view_each(plan):
    a, b = _run("diskf", plan, True), _run("diskf", plan, False)
    _same(a, b)
    assert a.outcome.events < b.outcome.events  # the casts: one event per agent, not one per token and agent


@pytest.mark.parametrize("algorithm", sorted(set(cases.ALGORITHMS)))
def test_every_estimator_the_same_with_shared_views(algorithm):
    _same(_run(algorithm, "crash and restart", True), _run(algorithm, "crash and restart", False))


def test_a_roster_counts_tokens_one_at_a_time_and_in_batches():
    ids = (5, 7, 9, 11)
    places = {j: i for i, j in enumerate(ids)}
    one, many = Roster(ids, places, 7), Roster(ids, places, 7)
    for who, nonce in ((5, "a"), (9, "b"), (9, "c"), (11, "d")):
        one.token(who, nonce, True)
    many.tokens(np.array([0, 2, 2, 3]), True)
    for r in (one, many):
        assert (r.size, r.complete, 9 in r, 7 in r) == (3, False, True, False)
    one.token(7, "me", True)
    one.token(7, "me", True)   # its own token heard twice (its session, and the network's batch): once
    assert one.complete and one.mine == ("me",)
    many.tokens(np.array([2, 2, 0, 1]), False)  # a token of 7's never heard to come: no count below none
    assert (many.size, 9 in many, 5 in many, 7 in many, 11 in many) == (1, False, False, False, True)
