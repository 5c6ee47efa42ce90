"""diskf-r (the robust DISKF variant) and the centralized bound: each new
equation against hand-worked numbers, the strong-detectability test against
hand-computed zeros, diskf-r == the centralized filter where that is exact,
and the batched engine == a plain per-agent loop (``robust_oracle``)."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from diskf_mesh.engine import centralized
from diskf_mesh.engine import batch as engine
from diskf_mesh.core import equations as eq
from diskf_mesh.mesh.estimator import lockstep
from diskf_mesh.core.model import RobustOptions
from diskf_mesh.estimators import Params
from diskf_mesh.data.scenario import load_scenario, simulate

import robust_oracle

TOL = 1e-9
G = np.array([[1.0], [1.0]])


def rot(w):
    return np.array([[np.cos(w), -np.sin(w)], [np.sin(w), np.cos(w)]])


def info(*rows, r=2.0):
    """Stacked H^T R^-1 H of sensors measuring the given state components."""
    U = np.zeros((2, 2))
    for c in rows:
        U[c, c] += 1.0 / r
    return U


# --------------------------------------------------------------------------
# equations
# --------------------------------------------------------------------------
def test_innovation_scale_hand_worked():
    # one x-sensor, R = 2: U = [[0.5, 0], [0, 0]], prior x = 0, P = I, y = 4:
    # u = H^T R^-1 y = [2, 0], r = u, r^T U^+ r = 2 * 2 / 0.5 = 8 (= y^2 / R),
    # rank 1, tr(P U) = 0.5: alpha = (8 - 1) / 0.5 = 14. With y = 1: (0.5 - 1) < 0 -> 1.
    U = info(0)
    x, P = np.zeros(2), np.eye(2)
    a = eq.innovation_scale(np.stack([P, P, P]), np.stack([U, U, np.zeros((2, 2))]),
                            np.array([[2.0, 0.0], [0.5, 0.0], [0.0, 0.0]]), np.stack([x, x, x]))
    np.testing.assert_allclose(a, [14.0, 1.0, 1.0])


def test_input_injection_hand_worked():
    # x = [1, 2], P = diag(1, 2), G = [1, 1]^T, d = 3, S = 0.5:
    # x* = [4, 5], P* = P + 0.5 [[1, 1], [1, 1]] = [[1.5, 0.5], [0.5, 2.5]]
    x, P = np.array([1.0, 2.0]), np.diag([1.0, 2.0])
    xs, Ps = eq.input_injection(x, P, G, np.array([3.0]), np.array([[0.5]]), np.array(True))
    np.testing.assert_allclose(xs, [4.0, 5.0])
    np.testing.assert_allclose(Ps, [[1.5, 0.5], [0.5, 2.5]])
    # no input known: unchanged, exactly
    xs, Ps = eq.input_injection(x, P, G, np.array([3.0]), np.array([[0.5]]), np.array(False))
    assert np.array_equal(xs, x) and np.array_equal(Ps, P)


def test_zero_dynamics_x_sensor_hand_worked():
    # H = [1, 0], G = [1, 1]^T: (G^T U G)^-1 G^T U = [1, 0], so
    # Pi = I - G [1, 0] = [[0, 0], [-1, 1]] and Phi = Pi A = [[0, 0], [s - c, s + c]]
    w = 0.3
    c, s = np.cos(w), np.sin(w)
    Phi = eq.zero_dynamics(rot(w), G, info(0), np.array(True))
    np.testing.assert_allclose(Phi, [[0.0, 0.0], [s - c, s + c]], atol=1e-15)
    np.testing.assert_allclose(sorted(abs(np.linalg.eigvals(Phi))), [0.0, c + s], atol=1e-15)


@pytest.mark.parametrize("w", [0.3, np.pi / 20, -0.3, -np.pi / 20])
def test_strong_detectability_hand_computed(w):
    """x-sensor: zero cos w + sin w; y-sensor: cos w - sin w (README); both
    together: H of full rank, no zeros. Anticlockwise (w > 0) the x-sensor
    alone is not strongly detectable, clockwise the y-sensor alone."""
    c, s = np.cos(w), np.sin(w)
    A = rot(w)
    U = np.stack([info(0), info(1), info(0, 1), info(0, 0), np.zeros((2, 2))])
    valid = np.array([True, True, True, True, False])
    got = eq.strongly_detectable(A, G, U, valid)
    want = [abs(c + s) < 1, abs(c - s) < 1, True, abs(c + s) < 1, False]
    assert got.tolist() == want
    assert got[0] == (w < 0) and got[1] == (w > 0)
    # the oracle's pencil zeros are the hand-computed ones
    np.testing.assert_allclose(robust_oracle.invariant_zeros(A, G, np.array([[1.0, 0.0]])), [c + s])
    np.testing.assert_allclose(robust_oracle.invariant_zeros(A, G, np.array([[0.0, 1.0]])), [c - s])


# --------------------------------------------------------------------------
# the centralized bound
# --------------------------------------------------------------------------
@pytest.mark.parametrize("name", ["quadrants", "dynamic"])
def test_centralized_is_cdrkf_all_to_all(name):
    """In an all-to-all network every neighbourhood is every agent: C-DRKF
    is the centralized Gillijns-De Moor filter."""
    scn = load_scenario(name).with_overrides(topology="all", steps=80)
    tr = simulate(scn, [0, 1])
    c, ref = centralized.run_centralized(tr), engine.run(tr, "cdrkf", scn.params)
    for f in ("x", "P", "d"):
        np.testing.assert_allclose(getattr(c, f), getattr(ref, f), rtol=TOL, atol=TOL)


def _xy_sensors(scn):
    """Every agent measures x and y (R = 2 I): the stacked sensors of any
    tick with a measurement are strongly detectable (H has full rank)."""
    agents = tuple(replace(a, H=np.eye(2), R=2.0 * np.eye(2)) for a in scn.agents)
    return replace(scn, agents=agents)


def test_robust_equals_centralized_where_exact():
    """The exact case: all-to-all, and at every tick the stacked sensors are
    strongly detectable. Then every agent's CI prior is the common prediction,
    the gate always holds, and diskf-r is the centralized filter."""
    scn = _xy_sensors(load_scenario("quadrants").with_overrides(topology="all", steps=120))
    tr = simulate(scn, [0, 1, 2])
    assert tr.has.any(axis=2).all()  # some agent measures at every tick
    r, c = engine.run(tr, "diskf-r", scn.params), centralized.run_centralized(tr)
    for f in ("x", "P", "d"):
        np.testing.assert_allclose(getattr(r, f), getattr(c, f), rtol=TOL, atol=TOL)
    assert r.d_valid.all()


# --------------------------------------------------------------------------
# engine == plain loop
# --------------------------------------------------------------------------
def assert_matches_oracle(tr, params):
    want = robust_oracle.run_robust(tr)
    est = engine.run(tr, "diskf-r", params)
    np.testing.assert_array_equal(est.d_valid, want["v"])
    np.testing.assert_allclose(est.x, want["x"], rtol=TOL, atol=TOL)
    np.testing.assert_allclose(est.P, want["P"], rtol=TOL, atol=TOL)
    np.testing.assert_allclose(est.d, want["d"], rtol=TOL, atol=TOL)


@pytest.mark.parametrize("topology", ["all", "ring", "none"])
def test_robust_matches_oracle_quadrants(topology):
    scn = load_scenario("quadrants").with_overrides(topology=topology, steps=100)
    assert_matches_oracle(simulate(scn, [0, 1]), scn.params)


def test_robust_matches_oracle_dynamic():
    scn = load_scenario("dynamic").with_overrides(steps=80)
    assert_matches_oracle(simulate(scn, [4]), scn.params)


def test_robust_agents_alone_equal_engine():
    """Every agent a batch of one (as in an agent process): the engine's bits."""
    scn = load_scenario("dynamic").with_overrides(steps=60)
    tr = simulate(scn, [0])
    ref = engine.run(tr, "diskf-r", scn.params)
    for k, _, outs in lockstep(scn, "diskf-r", tr):
        for j, a in enumerate(scn.agents):
            assert np.array_equal(outs[a.id].x[0, 0], ref.x[0, k - 1, j])
            assert np.array_equal(outs[a.id].P[0, 0], ref.P[0, k - 1, j])


def test_switches_change_the_estimate():
    """Every switch of RobustOptions is read (the ablation rows differ)."""
    scn = load_scenario("quadrants").with_overrides(topology="ring", steps=60)
    tr = simulate(scn, [0])
    base = engine.run(tr, "diskf-r", scn.params).x
    for sw, val in (("prior_ci", False), ("joint_input", False), ("gate", False), ("latch", False),
                    ("relay", False), ("inject", False), ("inflate", False), ("window", True), ("compensate", True)):
        p = replace(scn.params, robust=replace(RobustOptions(), **{sw: val}))
        assert not np.array_equal(engine.run(tr, "diskf-r", p).x, base), sw
