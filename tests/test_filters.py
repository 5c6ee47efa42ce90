"""DISKF against the filters it must reduce to, and the RKF against its textbook form."""
import numpy as np
import pytest

from diskf_mesh.engine import batch as engine
from diskf_mesh.estimators import Params
from diskf_mesh.core.rkf import rkf_update
from diskf_mesh.data.scenario import load_scenario, simulate


@pytest.fixture(scope="module")
def quadrants():
    return load_scenario("quadrants")


def _agent_data(tr, b, k, i):
    s = tr.sensors
    p = s.p[i]
    return s.H[i, :p], s.R[i, :p, :p], tr.y[b, k, i, :p], tr.has[b, k, i]


def test_all_to_all_equals_neighbourhood_centralised_filter(quadrants):
    """Given DISKF's own fused input, the centralised information filter on
    everyone's stacked H, R, y gives DISKF's state and covariance (1e-9)."""
    scn = quadrants.with_overrides(topology="all", steps=120)
    tr = simulate(scn, [0, 1, 2])
    est = engine.run(tr, "diskf", scn.params)
    m = tr.model
    B, K, N = tr.has.shape
    for b in range(B):
        x, P = m.x0.copy(), m.P0.copy()
        for k in range(K):
            A = m.A_at(k + 1)
            x_pred, P_pred = A @ x, A @ P @ A.T + m.Q
            if est.d_valid[b, k, 0]:
                x_pred = x_pred + m.G @ est.d[b, k, 0]
            rows = [_agent_data(tr, b, k, i) for i in range(N) if tr.has[b, k, i]]
            if rows:
                H = np.vstack([r[0] for r in rows])
                R = np.zeros((len(H), len(H)))
                o = 0
                for r in rows:
                    q = len(r[0])
                    R[o:o + q, o:o + q] = r[1]
                    o += q
                y = np.concatenate([r[2] for r in rows])
                S = H @ P_pred @ H.T + R
                K_gain = P_pred @ H.T @ np.linalg.inv(S)
                x = x_pred + K_gain @ (y - H @ x_pred)
                P = (np.eye(2) - K_gain @ H) @ P_pred
            else:
                x, P = x_pred, P_pred
            for i in range(N):
                np.testing.assert_allclose(est.x[b, k, i], x, rtol=1e-9, atol=1e-9)
                np.testing.assert_allclose(est.P[b, k, i], P, rtol=1e-9, atol=1e-9)


def test_all_to_all_compensation_is_exactly_zero(quadrants):
    scn = quadrants.with_overrides(topology="all", steps=80)
    tr = simulate(scn, [0, 1])
    with_c = engine.run(tr, "diskf", Params(eps=0.05, compensation="paper"))
    without = engine.run(tr, "diskf", Params(eps=0.0))
    assert np.array_equal(with_c.x, without.x)


def test_no_neighbours_is_the_local_filter(quadrants):
    """With no links each agent runs: windowed RKF input estimate from its
    own measurement, input-driven prediction, standard Kalman update."""
    scn = quadrants.with_overrides(topology="none", steps=120)
    tr = simulate(scn, [4])
    params = scn.params
    est = engine.run(tr, "diskf", params)
    m = tr.model
    _, K, N = tr.has.shape
    for i in range(N):
        x, P, since = m.x0.copy(), m.P0.copy(), 0
        for k in range(K):
            A = m.A_at(k + 1)
            x_pred, P_pred = A @ x, A @ P @ A.T + m.Q
            H, R, y, has = _agent_data(tr, 0, k, i)
            since += 1
            x_star = x_pred
            if has and since <= params.window:
                F = H @ m.G
                Rt = H @ P_pred @ H.T + R
                M = np.linalg.inv(F.T @ np.linalg.inv(Rt) @ F) @ F.T @ np.linalg.inv(Rt)
                d = M @ (y - H @ x_pred)
                x_star = x_pred + m.G @ d
                assert est.d_valid[0, k, i]
                np.testing.assert_allclose(est.d[0, k, i], d, rtol=1e-9, atol=1e-9)
            else:
                assert not est.d_valid[0, k, i]
            if has:
                Kg = P_pred @ H.T @ np.linalg.inv(H @ P_pred @ H.T + R)
                x = x_star + Kg @ (y - H @ x_star)
                P = (np.eye(2) - Kg @ H) @ P_pred
                since = 0
            else:
                x, P = x_star, P_pred
            np.testing.assert_allclose(est.x[0, k, i], x, rtol=1e-9, atol=1e-8)
            np.testing.assert_allclose(est.P[0, k, i], P, rtol=1e-9, atol=1e-9)


def test_rkf_information_form_equals_gillijns_de_moor_textbook():
    """The RKF measurement update (Gillijns & De Moor 2007, with the
    pseudo-inverse of R~*) equals our information form."""
    rng = np.random.default_rng(1)
    n, m, p = 4, 2, 3

    def spd(k):
        a = rng.normal(size=(k, k))
        return a @ a.T + k * np.eye(k)

    for _ in range(10):
        G = rng.normal(size=(n, m))
        C = rng.normal(size=(p, n))
        R = spd(p)
        Pp = spd(n)
        xp = rng.normal(size=n)
        y = rng.normal(size=p)
        Rt = C @ Pp @ C.T + R
        F = C @ G
        Ri = np.linalg.inv(Rt)
        M = np.linalg.inv(F.T @ Ri @ F) @ F.T @ Ri
        d = M @ (y - C @ xp)
        xs = xp + G @ d
        I_GMC = np.eye(n) - G @ M @ C
        Ps = I_GMC @ Pp @ I_GMC.T + G @ M @ R @ M.T @ G.T
        Rs = C @ Ps @ C.T + R - C @ G @ M @ R - R @ M.T @ G.T @ C.T
        Kg = (Ps @ C.T - G @ M @ R) @ np.linalg.pinv(Rs, rcond=1e-10)
        x_ref = xs + Kg @ (y - C @ xs)
        P_ref = Ps - Kg @ (Ps @ C.T - G @ M @ R).T
        U = C.T @ np.linalg.solve(R, C)
        u = C.T @ np.linalg.solve(R, y)
        x, P = rkf_update(xp, np.linalg.inv(Pp), U, u, G, np.array(True))
        np.testing.assert_allclose(x, x_ref, rtol=1e-8, atol=1e-8)
        np.testing.assert_allclose(P, P_ref, rtol=1e-8, atol=1e-8)


def test_diskf_equals_cdrkf_all_to_all_on_quadrants(quadrants):
    """With one observer at a time (p = m = 1) the two filters have the same
    mean recursion; the paper reports them equal in all-to-all."""
    scn = quadrants.with_overrides(topology="all", steps=100)
    tr = simulate(scn, [0, 1, 2])
    a = engine.run(tr, "diskf", scn.params)
    c = engine.run(tr, "cdrkf", scn.params)
    np.testing.assert_allclose(a.x, c.x, rtol=1e-9, atol=1e-7)


def test_kcf_warns_when_its_consensus_step_may_diverge(quadrants):
    """Olfati-Saber's step needs eps x max degree < 1: quadrants all-to-all has
    degree 3, so eps = 0.4 is warned about (with the bound), 0.1 is not."""
    from dataclasses import replace

    from diskf_mesh.estimators.consensus_baselines import consensus_step_problem

    trace = simulate(quadrants, [0], steps=5)
    with pytest.warns(RuntimeWarning, match=r"consensus_eps = 0.4 with up to 3 neighbours.*below 0.333"):
        engine.run(trace, "kcf", replace(quadrants.params, consensus_eps=0.4))
    assert consensus_step_problem(0.1, trace.links) is None
    assert consensus_step_problem(1.0, np.eye(4, dtype=bool)) is None  # no neighbours, no consensus step


def test_a_diverging_estimator_is_a_row_that_says_so_not_a_traceback():
    """Long runs of the shipped scenarios where the unbiased input estimate
    is unstable (one scalar sensor of a rotation: not strongly detectable):
    C-DRKF's and L-DRKF's covariance stops being positive definite (quadrants,
    isolated, 700 ticks), DISKF's input estimate grows past what a message
    may carry, and its state with it (random geometric, 25 agents, 900
    ticks). The engine names the
    estimator and the tick; ``experiment`` marks the row diverged and keeps
    the others."""
    from diskf_mesh.mesh.wire import codec as wire
    from diskf_mesh.mesh.process.runspec import RunSpec
    from diskf_mesh.studies import experiment

    scn = load_scenario("quadrants").with_overrides(topology="none", steps=700)
    with pytest.raises(np.linalg.LinAlgError, match=r"^cdrkf, tick \d+: .*diverged"):
        engine.run(simulate(scn, [0]), "cdrkf", scn.params)
    rows = experiment.run_experiment(scn, experiment.settings_for(["none"]), ["cdrkf", "ldrkf", "kcf"], [0])
    assert rows["cdrkf"]["none"]["diverged"] and rows["ldrkf"]["none"]["diverged"]
    assert not rows["kcf"]["none"].get("diverged") and np.isfinite(rows["kcf"]["none"]["mae_state"])
    assert "diverged" in experiment.format_table(rows).splitlines()[2]

    rg = RunSpec("random-geometric", "diskf", agents=25).load(900)
    est = engine.run(simulate(rg, [0]), "diskf", rg.params)
    assert np.isfinite(est.x).all() and np.abs(est.x).max() > wire.MAX_ABS  # finite, but no message carries it
    assert experiment.diverged(est) and experiment.run_or_none(simulate(rg, [0]), "diskf", rg.params) is None
    assert not experiment.diverged(engine.run(simulate(rg, [0]), "kcf", rg.params))
