"""Scenario 2: range links, the shipped geometry, and the compensation term
vanishing in all-to-all communication."""
from __future__ import annotations

import numpy as np
import pytest

from diskf_mesh.engine import batch as engine
from diskf_mesh.core.model import COMPENSATION_FORMS
from diskf_mesh.estimators import Params
from diskf_mesh.data.scenario import load_scenario, simulate
from diskf_mesh.studies.suite import StudyConfig, compensation_ablation, input_zero

# Three agents on a line: A and B static 100 apart, C shuttles along y = 50
# between x = 0 and x = 200, one loop in 4 ticks (400 units of path), so at
# ticks 1, 2, 3, 4 it is at x = 100, 200, 100, 0: 50 from B, then far from
# both, then 50 from B, then 50 from A. Range 50 is exactly those distances
# (the rule is inclusive).
TINY = """
name = "tiny"
steps = 8
[model]
dynamics = "rotation"
omega = 0.1
G = [[1.0], [1.0]]
Q = [[0.2, 0.0], [0.0, 0.2]]
x0 = [10.0, 10.0]
P0 = [[1.0, 0.0], [0.0, 1.0]]
[topology]
kind = "range"
range = 50.0
[[agents]]
id = 1
H = [[1.0, 0.0]]
R = [[2.0]]
position = [0.0, 0.0]
[[agents]]
id = 2
H = [[0.0, 1.0]]
R = [[2.0]]
position = [100.0, 0.0]
[[agents]]
id = 3
H = [[1.0, 0.0]]
R = [[2.0]]
path = [[0.0, 50.0], [200.0, 50.0]]
period = 4
"""

A, B, C = 0, 1, 2
EXPECTED_PAIRS = {1: {(B, C)}, 2: set(), 3: {(B, C)}, 4: {(A, C)}}


@pytest.fixture
def tiny(tmp_path):
    path = tmp_path / "tiny.toml"
    path.write_text(TINY)
    return load_scenario(str(path))


def pairs(L: np.ndarray) -> set:
    return {(int(i), int(j)) for i, j in zip(*np.nonzero(np.triu(L, 1)))}


def test_hand_placed_positions(tiny):
    pos = tiny.positions(4)
    np.testing.assert_allclose(pos[:, C], [[100, 50], [200, 50], [100, 50], [0, 50]])
    np.testing.assert_allclose(pos[:, A], [[0, 0]] * 4)


def test_links_follow_range_exactly(tiny):
    L = simulate(tiny, [0]).links[0]
    assert L.shape == (8, 3, 3)
    for k in range(1, 9):  # the loop repeats every 4 ticks
        assert pairs(L[k - 1]) == EXPECTED_PAIRS[(k - 1) % 4 + 1], k
        assert np.array_equal(L[k - 1], L[k - 1].T)
        assert L[k - 1].diagonal().all()


def test_range_just_below_the_distance_drops_the_links(tiny):
    L = simulate(tiny.with_overrides(comm_range=49.999), [0]).links[0]
    assert not any(pairs(l) for l in L)
    L = simulate(tiny.with_overrides(comm_range=1000.0), [0]).links[0]
    assert L.all()


@pytest.fixture(scope="module")
def dynamic():
    return load_scenario("dynamic")


def test_dynamic_scenario_shape(dynamic):
    assert dynamic.N == 9 and dynamic.topology == "range" and dynamic.comm_range == 120.0
    assert sum(not a.mobile for a in dynamic.agents) == 4
    assert sum(a.mobile for a in dynamic.agents) == 5
    assert all(a.sense == "quadrant" and a.H.shape == (1, 2) for a in dynamic.agents)
    static = np.array([a.position for a in dynamic.agents if not a.mobile])
    assert {tuple(np.sign(p)) for p in static} == {(1, 1), (-1, 1), (-1, -1), (1, -1)}


def test_dynamic_topology_changes_and_mobiles_bridge(dynamic):
    L = simulate(dynamic, [0]).links[0]
    assert np.array_equal(L, np.swapaxes(L, -1, -2))
    assert len({l.tobytes() for l in L}) > 50  # the graph keeps changing
    static = [i for i, a in enumerate(dynamic.agents) if not a.mobile]
    # static agents never hear each other directly at range 120 ...
    assert not L[:, static][:, :, static][:, ~np.eye(4, dtype=bool)].any()
    # ... but each one is linked to some mobile agent at some ticks, not always
    deg = L.sum(-1) - 1
    for i in static:
        assert 0 < (deg[:, i] > 0).mean() < 1
    # the mobile agents sweep through all four quadrants
    pos = dynamic.positions(dynamic.steps)
    for i, a in enumerate(dynamic.agents):
        if a.mobile:
            assert len({tuple(q) for q in np.sign(pos[:, i]) if 0 not in q}) == 4, a.id


def _run(scn, params, seeds=(0, 1)):
    return engine.run(simulate(scn, seeds), "diskf", params)


@pytest.mark.parametrize("name", ["quadrants", "dynamic"])
@pytest.mark.parametrize("form", [f for f in COMPENSATION_FORMS if f != "none"])
def test_compensation_is_exactly_zero_all_to_all(name, form):
    scn = load_scenario(name).with_overrides(topology="all", steps=60)
    on = _run(scn, Params(eps=0.05, compensation=form))
    off = _run(scn, Params(eps=0.0, compensation=form))
    for f in ("x", "P", "d", "d_valid"):
        assert np.array_equal(getattr(on, f), getattr(off, f)), f


@pytest.mark.parametrize("name,overrides", [("quadrants", {"topology": "ring"}), ("dynamic", {"comm_range": 120.0})])
def test_compensation_acts_without_all_to_all(name, overrides):
    """The control: where neighbourhoods differ the term is not zero."""
    scn = load_scenario(name).with_overrides(steps=60, **overrides)
    assert not np.array_equal(_run(scn, Params(eps=0.05)).x, _run(scn, Params(eps=0.0)).x)


def test_compensation_ablation_flags_all_to_all_identical():
    out = compensation_ablation(StudyConfig(seeds=2, steps=40, quiet=True))
    for env in ("stationary", "dynamic"):
        cell = out[env]["all-to-all"]
        assert cell["bit_identical"] is True
        rows = list(cell["rows"].values())
        assert all(r == rows[0] for r in rows)  # to the last digit
        assert out[env]["1-hop"]["bit_identical"] is False


def test_input_zero_of_single_coordinate_sensors(dynamic):
    w = 2 * np.pi / 40
    A = np.array([[np.cos(w), -np.sin(w)], [np.sin(w), np.cos(w)]])
    G = np.array([[1.0], [1.0]])
    assert input_zero(A, G, np.array([[1.0, 0.0]])) == pytest.approx(np.cos(w) + np.sin(w))
    assert input_zero(A, G, np.array([[0.0, 1.0]])) == pytest.approx(np.cos(w) - np.sin(w))
