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
from diskf_mesh.mesh.protocol.estimator import lockstep
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


def test_input_walk_hand_worked():
    # A = [[0, -1], [1, 0]], C = [1, 2]^T: A C = [-2, 1]^T; S = 3, Qd = 0.5: 3.5
    A = np.array([[0.0, -1.0], [1.0, 0.0]])
    B, S = eq.input_walk(A, np.array([[1.0], [2.0]]), np.array([[3.0]]), 0.5 * np.eye(1))
    np.testing.assert_allclose(B, [[-2.0], [1.0]])
    np.testing.assert_allclose(S, [[3.5]])


def test_replace_marginal_hand_worked():
    # (a, b) scalars: Paa = 4, Pab = 2, Pbb = 3, a = 1, b = 5. K = 2 / 4 = 0.5.
    # a -> a' = 3 with Paa' = 1: b' = 5 + 0.5 * 2 = 6, Pab' = 1 * 0.5 = 0.5,
    # Pbb' = 3 - 0.5 * 2 + 0.5 * 1 * 0.5 = 2.25
    b, Pab, Pbb = eq.replace_marginal(np.array([1.0]), np.array([[4.0]]), np.array([5.0]), np.array([[2.0]]),
                                      np.array([[3.0]]), np.array([3.0]), np.array([[1.0]]))
    np.testing.assert_allclose(b, [6.0])
    np.testing.assert_allclose(Pab, [[0.5]])
    np.testing.assert_allclose(Pbb, [[2.25]])
    # it is the joint Kalman update of (x, d) when x is measured: x prior N(0, 2),
    # d prior N(0, 1), cov(x, d) = 1; y = x + v, R = 2, y = 4. Joint gain:
    # L = [2, 1] / (2 + 2) = [0.5, 0.25]: x = 2, d = 1, P = 1, S = 1 - 0.25 = 0.75, C = 0.5
    x_post, P_post = np.array([2.0]), np.array([[1.0]])
    d, C, S = eq.replace_marginal(np.array([0.0]), np.array([[2.0]]), np.array([0.0]), np.array([[1.0]]),
                                  np.array([[1.0]]), x_post, P_post)
    np.testing.assert_allclose([d[0], C[0, 0], S[0, 0]], [1.0, 0.5, 0.75])


def test_input_to_state_hand_worked():
    # v = [1, 2], Pv = I, B = [0.5, 0]^T, d = 2, S = 1, G = [1, 1]^T:
    # x = [3, 4]; G B^T = [[0.5, 0], [0.5, 0]], + its transpose = [[1, 0.5], [0.5, 0]],
    # G S G^T = ones: P = [[3, 1.5], [1.5, 2]]; C = B + G S = [1.5, 1]^T
    x, P, C = eq.input_to_state(np.array([1.0, 2.0]), np.eye(2), np.array([[0.5], [0.0]]), np.array([2.0]),
                                np.array([[1.0]]), G)
    np.testing.assert_allclose(x, [3.0, 4.0])
    np.testing.assert_allclose(P, [[3.0, 1.5], [1.5, 2.0]])
    np.testing.assert_allclose(C, [[1.5], [1.0]])
    # with B = 0 it is input_injection
    xi, Pi = eq.input_injection(np.array([1.0, 2.0]), np.eye(2), G, np.array([2.0]), np.array([[1.0]]), np.array(True))
    x0, P0, _ = eq.input_to_state(np.array([1.0, 2.0]), np.eye(2), np.zeros((2, 1)), np.array([2.0]),
                                  np.array([[1.0]]), G)
    np.testing.assert_allclose(x0, xi)
    np.testing.assert_allclose(P0, Pi)


def test_free_input_gain_hand_worked():
    # Y = diag(1, 3), G = [1, 1]^T: G^T Y G = 4, G^T Y = [1, 3]: L = [0.25, 0.75]
    L = eq.free_input_gain(np.diag([1.0, 3.0]), G)
    np.testing.assert_allclose(L, [[0.25, 0.75]])


def test_free_input_gain_reads_the_unbiased_input():
    """The Gillijns-De Moor input estimate is L (x - x^) of its own state
    update: the flat-prior joint update (``free_input_gain``'s docstring)."""
    from diskf_mesh.core.rkf import rkf_update
    rng = np.random.default_rng(3)
    x_pred = rng.normal(size=2)
    M = rng.normal(size=(2, 2))
    P_pred = M @ M.T + np.eye(2)
    U, u = info(0, 1), rng.normal(size=2)
    Y, Ji = eq.information_pair(P_pred, U)
    d, _, valid = eq.input_estimate(x_pred, Y, Ji, U, u, G)
    x, _ = rkf_update(x_pred, Y, U, u, G, valid)
    L = eq.free_input_gain(Y, G)
    np.testing.assert_allclose(L @ (x - x_pred), d, rtol=1e-12, atol=1e-12)


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


def test_unbiased_equals_centralized_where_exact():
    """The exact case of the unbiased (Gillijns-De Moor) update alone
    (``persist`` off, ``unbiased`` on, the first diskf-r): all-to-all, and at
    every tick the stacked sensors are strongly detectable. Then every
    agent's CI prior is the common prediction, the gate always holds, and
    diskf-r is the centralized Gillijns-De Moor filter."""
    scn = _xy_sensors(load_scenario("quadrants").with_overrides(topology="all", steps=120))
    tr = simulate(scn, [0, 1, 2])
    assert tr.has.any(axis=2).all()  # some agent measures at every tick
    p = replace(scn.params, robust=RobustOptions(persist=False, unbiased=True, inflate=True))
    r, c = engine.run(tr, "diskf-r", p), centralized.run_centralized(tr)
    for f in ("x", "P", "d"):
        np.testing.assert_allclose(getattr(r, f), getattr(c, f), rtol=TOL, atol=TOL)
    assert r.d_valid.all()


@pytest.mark.parametrize("name", ["quadrants", "dynamic"])
def test_robust_equals_centralized_persist_all_to_all(name):
    """The exact case of the default: all-to-all. Every agent fused the same
    messages, so every CI returns the common prediction and input, and
    diskf-r is the centralized filter with the same persistent-input model."""
    scn = load_scenario(name).with_overrides(topology="all", steps=120)
    tr = simulate(scn, [0, 1])
    r, c = engine.run(tr, "diskf-r", scn.params), centralized.run_centralized_persist(tr, scn.params.robust)
    for f in ("x", "P", "d"):
        np.testing.assert_allclose(getattr(r, f), getattr(c, f), rtol=TOL, atol=TOL)
    np.testing.assert_array_equal(r.d_valid, c.d_valid)


def test_isolated_agent_learns_the_input_from_an_x_sensor():
    """The behaviour the persistent input buys: an isolated x-sensor (whose
    invariant zero is unstable, so no unbiased estimate is stable) estimates
    the step input of 10 to within 1 after its first laps, and its state
    error is far below the input-free filter's (KCF)."""
    scn = load_scenario("quadrants").with_overrides(topology="none", steps=200)
    tr = simulate(scn, [0, 1, 2])
    r, kcf = engine.run(tr, "diskf-r", scn.params), engine.run(tr, "kcf", scn.params)
    late = slice(120, 200)
    d_err = np.abs(r.d[:, late, 0, 0] - tr.truth_d[:, late, 0])  # agent 1 measures x
    assert d_err.mean() < 1.0
    e = lambda est: np.linalg.norm(est.x[:, :, 0] - tr.truth_x, axis=-1).mean()  # noqa: E731
    assert e(r) < 0.5 * e(kcf)


# --------------------------------------------------------------------------
# engine == plain loop
# --------------------------------------------------------------------------
def assert_matches_oracle(tr, params):
    """engine == oracle to 1e-9. With a well-conditioned input prior: the
    default wide one (S0 = 1e4 max(q_process, q_sensor) I = 2e4 I here)
    makes the first updates ill-conditioned (a prior of 2e4 against R = 2),
    where two correct implementations (the information form here, the gain
    form there) agree to about 1e-6 only;
    ``test_robust_matches_oracle_default_prior`` checks that case to 1e-5."""
    params = replace(params, robust=replace(params.robust, input_prior=1.0))
    want = robust_oracle.run_robust(tr, params.robust)
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


@pytest.mark.parametrize("model", [dict(input_model="mean-reverting", input_rho=0.8, input_walk=3.0),
                                   dict(input_model="mean-reverting"), dict(input_model="none")])
def test_robust_input_models_match_oracle(model):
    """The mean-reverting input (rho = 0.8, and rho = 0: zero-mean) and no
    input, each with the scenario's default scales where not given."""
    scn = load_scenario("dynamic").with_overrides(steps=60)
    assert_matches_oracle(simulate(scn, [2]), replace(scn.params, robust=replace(scn.params.robust, **model)))


def test_robust_matches_oracle_default_prior():
    scn = load_scenario("quadrants").with_overrides(topology="none", steps=100)
    tr = simulate(scn, [0, 1])
    want, est = robust_oracle.run_robust(tr, scn.params.robust), engine.run(tr, "diskf-r", scn.params)
    np.testing.assert_array_equal(est.d_valid, want["v"])
    for f in ("x", "P", "d"):
        np.testing.assert_allclose(getattr(est, f), want[f], rtol=1e-5, atol=1e-5)


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
    """Every switch of RobustOptions is read (the ablation rows differ). The
    gate and window act on the unbiased update, so they are checked
    with it on; the window only without ``persist`` (with it the input is
    held from the first measurement on, and the reset keeps the window open)."""
    scn = load_scenario("quadrants").with_overrides(topology="ring", steps=60)
    tr = simulate(scn, [0])
    base = engine.run(tr, "diskf-r", scn.params).x
    for sw, val in (("persist", False), ("unbiased", True), ("prior_ci", False), ("joint_input", False),
                    ("relay", False), ("inject", False), ("inflate", True), ("compensate", True),
                    ("input_walk", 10.0), ("input_prior", 1.0)):
        p = replace(scn.params, robust=replace(RobustOptions(), **{sw: val}))
        assert not np.array_equal(engine.run(tr, "diskf-r", p).x, base), sw
    for unb in (RobustOptions(unbiased=True), RobustOptions(unbiased=True, persist=False, inflate=True)):
        ref = engine.run(tr, "diskf-r", replace(scn.params, robust=unb)).x
        # the latch is not among them: its guard (a latched tick takes the unbiased update only where it is at
        # least as certain as the model's own) leaves it without effect on this case
        for sw, val in (("gate", False),) + ((("window", True),) if not unb.persist else ()):
            p = replace(scn.params, robust=replace(unb, **{sw: val}))
            assert not np.array_equal(engine.run(tr, "diskf-r", p).x, ref), (sw, unb.persist)


@pytest.mark.parametrize("bad", [0.0, -1.0, float("inf"), float("nan")])
def test_robust_scales_must_be_positive(bad):
    with pytest.raises(ValueError):
        RobustOptions(input_walk=bad)
    with pytest.raises(ValueError):
        RobustOptions(input_prior=bad)


def test_robust_scales_from_a_scenario_and_a_trace():
    """[estimator.robust] takes the two scales as numbers > 0 (and the
    switches as booleans); a trace carries them back."""
    import tomllib
    from diskf_mesh.core.errors import InputError
    from diskf_mesh.data.scenario import parse_scenario, scenario_path
    from diskf_mesh.data.trace import estimator_from_json, trace_to_json
    raw = tomllib.loads(scenario_path("quadrants").read_text())
    raw["estimator"]["robust"] = {"input_walk": 2.5, "input_prior": 100, "persist": True}
    scn = parse_scenario(raw)
    assert scn.params.robust == RobustOptions(input_walk=2.5, input_prior=100.0)
    doc = trace_to_json(simulate(scn.with_overrides(steps=5), [0]), params=scn.params)
    assert estimator_from_json(doc).robust == scn.params.robust
    for bad in ({"input_walk": 0}, {"input_prior": -1.0}, {"input_walk": True}, {"persist": 1}):
        raw["estimator"]["robust"] = bad
        with pytest.raises(InputError):
            parse_scenario(raw)


def test_diskf_none_is_diskf_r_without_input():
    """``diskf-none`` is ``diskf-r`` with ``input_model = "none"``, bit for
    bit, whatever ``[estimator.robust]`` says of the input (a walk, the
    unbiased update: no refusal); it never claims an input estimate."""
    scn = load_scenario("quadrants").with_overrides(topology="ring", steps=60)
    tr = simulate(scn, [0, 1])
    none = replace(scn.params, robust=replace(scn.params.robust, input_model="none"))
    want = engine.run(tr, "diskf-r", none)
    asked = replace(scn.params, robust=replace(scn.params.robust, input_model="walk", input_walk=3.0, unbiased=True))
    for params in (scn.params, asked):
        got = engine.run(tr, "diskf-none", params)
        for f in ("x", "P"):
            np.testing.assert_array_equal(getattr(got, f), getattr(want, f))
        assert not got.d_valid.any()
    assert not np.array_equal(engine.run(tr, "diskf-r", scn.params).x, want.x)
