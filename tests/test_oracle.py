"""The batched engine against the plain per-agent DISKF oracle."""
from __future__ import annotations

import tomllib
from dataclasses import replace
from importlib import resources

import numpy as np
import pytest

from diskf_mesh.engine import batch as engine
from diskf_mesh.engine import oracle
from diskf_mesh.estimators import Params
from diskf_mesh.data.scenario import load_scenario, parse_scenario, simulate

TOL = 1e-9


def assert_matches_oracle(trace, params: Params, neighbours: str = "auto"):
    x, P, d, d_valid = oracle.run_diskf(trace, params)
    est = engine.run(trace, "diskf", params, neighbours=neighbours)
    np.testing.assert_array_equal(est.d_valid, d_valid)
    np.testing.assert_allclose(est.x, x, rtol=TOL, atol=TOL)
    np.testing.assert_allclose(est.P, P, rtol=TOL, atol=TOL)
    np.testing.assert_allclose(est.d, d, rtol=TOL, atol=TOL)


@pytest.mark.parametrize("topology", ["all", "ring", "none"])
def test_quadrants_matches_oracle(topology):
    scn = load_scenario("quadrants").with_overrides(topology=topology)
    assert_matches_oracle(simulate(scn, [0, 1]), scn.params)


@pytest.mark.parametrize("params", [
    Params(compensation="paper"),
    Params(compensation="normalized"),
    Params(compensation="none"),
    Params(window=None),
    Params(window=0, reset=False),
    Params(hold_input=True),
], ids=["paper-gain", "normalized-gain", "no-compensation", "no-window", "window0-noreset", "hold-input"])
def test_estimator_variants_match_oracle(params):
    scn = load_scenario("quadrants").with_overrides(topology="ring", steps=80)
    assert_matches_oracle(simulate(scn, [3]), params)


@pytest.mark.parametrize("neighbours", ["dense", "gather"])
@pytest.mark.parametrize("hold", [False, True])
def test_random_geometric_matches_oracle(neighbours, hold):
    scn = load_scenario("random-geometric", agents=15).with_overrides(steps=60, comm_range=220.0)
    trace = simulate(scn, [0])
    assert trace.has.any() and not trace.links.all()
    assert_matches_oracle(trace, replace(scn.params, hold_input=hold), neighbours)


def test_mobile_agents_match_oracle():
    """Dynamic links: the quadrant agents drive around the square, range-gated."""
    raw = tomllib.loads((resources.files("diskf_mesh") / "scenarios" / "quadrants.toml").read_text())
    raw["topology"] = {"kind": "range", "range": 260.0}
    for i, a in enumerate(raw["agents"]):
        a.pop("position")
        a.update(path=[[150, 150], [-150, 150], [-150, -150], [150, -150]], period=60.0,
                 phase=0.3 * i, sense="range", sense_range=220.0)
    scn = parse_scenario(raw).with_overrides(steps=100)
    trace = simulate(scn, [0])
    links = trace.links[0]
    assert (links != links[:1]).any(), "links should change over time"
    assert_matches_oracle(trace, scn.params)


def test_all_to_all_agents_agree_bit_for_bit():
    """Receivers that hear the same senders get identical results, so the
    state compensation is exactly zero under all-to-all communication."""
    trace = simulate(load_scenario("quadrants"), [0, 1])
    for name in ("diskf", "cdrkf"):
        est = engine.run(trace, name)
        assert (est.x == est.x[:, :, :1]).all() and (est.P == est.P[:, :, :1]).all(), name


def test_three_states_two_inputs_match_oracle():
    """n = 3, m = 2 and sensors of 1 to 3 rows: the engine's general (not
    closed-form) linear algebra, and an agent whose rank(H G) < m."""
    agents = [[[1, 0, 0], [0, 1, 0]], [[0, 1, 0], [0, 0, 1]], [[1, 0, 0], [0, 0, 1], [0, 1, 0]], [[1, 0, 0]],
              [[0, 0, 1], [1, 1, 0]]]
    raw = {
        "steps": 40,
        "model": {"dynamics": "matrix", "A": [[1, 0.1, 0], [0, 1, 0.1], [0, 0, 0.95]], "G": [[1, 0], [0, 1], [1, 1]],
                  "Q": np.diag([0.1, 0.1, 0.1]).tolist(), "x0": [0, 0, 0], "P0": np.eye(3).tolist()},
        "input": {"kind": "step", "at": 5, "before": [0, 0], "after": [1, -1]},
        "topology": {"kind": "ring"},
        "agents": [{"id": i + 1, "H": H, "R": np.eye(len(H)).tolist(), "sense": "always", "position": [0, 0]}
                   for i, H in enumerate(agents)],
    }
    scn = parse_scenario(raw)
    assert_matches_oracle(simulate(scn, [0, 1]), scn.params)
