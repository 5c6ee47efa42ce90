"""A restarted agent's re-initialisation (``mesh.protocol.rejoin``), without zenoh."""
from __future__ import annotations

import numpy as np

from diskf_mesh.estimators import get
from diskf_mesh.mesh.protocol.rejoin import in_range, most_certain
from diskf_mesh.mesh.wire import codec as wire
from diskf_mesh.mesh.protocol.estimator import AgentEstimator
from diskf_mesh.data.scenario import load_scenario


def report(sender, scale, x=(1.0, 2.0)):
    return wire.Report("r", sender, 9, np.array(x), scale * np.eye(2), np.zeros(1), False)


def test_takes_the_most_certain_linked_neighbour():
    reports = {1: report(1, 4.0), 2: report(2, 0.5, (7.0, 8.0)), 3: report(3, 2.0, (5.0, 6.0))}
    src = most_certain(reports, linked={1, 3})
    assert src == 3                                  # 2 is more certain but not linked
    est = AgentEstimator(load_scenario("dynamic"), 5, get("diskf"), 50, 0, start=(reports[src].x, reports[src].P))
    assert est.state.x.shape == (1, 1, 2) and est.state.P.shape == (1, 1, 2, 2)
    np.testing.assert_array_equal(est.state.x[0, 0], [5.0, 6.0])
    np.testing.assert_array_equal(est.state.P[0, 0], 2.0 * np.eye(2))
    assert (est.state.since == 0).all()


def test_no_linked_neighbour_means_the_prior():
    assert most_certain({1: report(1, 1.0)}, linked={2}) is None
    assert most_certain({2: report(2, 1.0), 1: report(1, 1.0)}, linked={1, 2}) == 1   # a tie: the smaller id


def test_in_range_follows_the_scenario_geometry():
    """Who a rejoining agent re-initialises from is found from the
    scenario's motion alone: the same links as the simulation's."""
    from diskf_mesh.data.scenario import simulate

    scn = load_scenario("dynamic").with_overrides(steps=120)
    links = simulate(scn, [0]).links[0]
    ids = [a.id for a in scn.agents]
    for k in (1, 17, 60, 119):
        for j, i in enumerate(ids):
            assert in_range(scn, i, k) == {ids[q] for q in np.flatnonzero(links[k - 1, j]) if q != j}
