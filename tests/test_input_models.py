"""The input models of ``core.input_models`` against hand-worked numbers."""
from __future__ import annotations

import numpy as np
import pytest

from diskf_mesh.core import input_models as im
from diskf_mesh.core import equations as eq


def test_input_predict_hand_worked():
    # A = [[0, -1], [1, 0]], C = [1, 2]^T, d = 4, S = 3.
    # walk (rho 1, q 0.5): d 4, A C = [-2, 1]^T, S 3.5 (as equations.input_walk)
    # mean-reverting rho 0.5, q 0.5: d 2, 0.5 A C = [-1, 0.5]^T, S 0.25 * 3 + 0.5 = 1.25
    # none (0, 0): d 0, cross 0, S 0
    A = np.array([[0.0, -1.0], [1.0, 0.0]])
    C, d, S = np.array([[1.0], [2.0]]), np.array([4.0]), np.array([[3.0]])
    for rho, q, want in ((1.0, 0.5, ([4.0], [[-2.0], [1.0]], [[3.5]])),
                         (0.5, 0.5, ([2.0], [[-1.0], [0.5]], [[1.25]])),
                         (0.0, 0.0, ([0.0], [[0.0], [0.0]], [[0.0]]))):
        got = im.input_predict(A, C, d, S, rho, q)
        for g, w in zip(got, want):
            np.testing.assert_allclose(g, w)
    # the walk is equations.input_walk bit for bit
    B, S1 = eq.input_walk(A, C, S, 0.5 * np.eye(1))
    _, B2, S2 = im.input_predict(A, C, d, S, 1.0, 0.5)
    assert np.array_equal(B, B2) and np.array_equal(S1, S2)
    # per model along a batch axis: rho (M,), q (M,)
    dd, BB, SS = im.input_predict(A, C[None].repeat(3, 0), d[None].repeat(3, 0), S[None].repeat(3, 0),
                                  np.array([1.0, 0.5, 0.0]), np.array([0.5, 0.5, 0.0]))
    np.testing.assert_allclose(SS[:, 0, 0], [3.5, 1.25, 0.0])


def test_input_scales_hand_worked():
    # G = [1, 1]^T, Q = 0.2 I: G^+ = [0.5, 0.5], G^+ Q G^+T = 0.2 * 0.5 = 0.1.
    # sensors x (R 2), y (R 2), both (R 4 I): F = 1, 1, [1, 1]^T:
    # 2, 2, F^+ = [0.5, 0.5]: 0.25 * 4 * 2 = 2 -> median 2. A sensor with F = 0 is left out.
    G, Q = np.array([[1.0], [1.0]]), 0.2 * np.eye(2)
    H = np.zeros((4, 2, 2))
    H[0, 0, 0] = H[1, 0, 1] = 1.0
    H[2] = np.eye(2)
    H[3, 0] = [1.0, -1.0]  # (1, -1) G = 0: does not see the input
    R = np.broadcast_to(np.eye(2), (4, 2, 2)).copy()
    R[0, 0, 0] = R[1, 0, 0] = 2.0
    R[2] *= 4.0
    qp, qs = im.input_scales(Q, G, H, R, np.array([1, 1, 2, 1]))
    assert qp == pytest.approx(0.1) and qs == pytest.approx(2.0)
    walk, prior = im.default_scales(qp, qs)
    assert walk == pytest.approx(np.sqrt(0.2)) and prior == pytest.approx(2e4)


def test_information_loglik_is_the_gaussian_likelihood_up_to_a_constant():
    # the same measurement y under two priors: the difference of the log
    # densities N(y; H x, H P H^T + R) equals the difference of information_loglik
    rng = np.random.default_rng(0)
    H = np.array([[1.0, 0.0], [0.5, 2.0], [0.0, 1.0]])
    R = np.diag([2.0, 1.0, 0.5])
    y = np.array([1.0, -2.0, 0.5])
    U, u = H.T @ np.linalg.solve(R, H), H.T @ np.linalg.solve(R, y)

    def logpdf(x, P):
        Sg = H @ P @ H.T + R
        r = y - H @ x
        return -0.5 * (r @ np.linalg.solve(Sg, r) + np.linalg.slogdet(Sg)[1] + 3 * np.log(2 * np.pi))

    def ll(x, P):
        Y = np.linalg.inv(P)
        return im.information_loglik(x, P, Y, np.linalg.inv(Y + U), U, u)

    x1, x2 = rng.standard_normal(2), rng.standard_normal(2)
    P1, P2 = np.array([[2.0, 0.3], [0.3, 1.0]]), np.array([[0.5, 0.0], [0.0, 4.0]])
    assert ll(x1, P1) - ll(x2, P2) == pytest.approx(logpdf(x1, P1) - logpdf(x2, P2), rel=1e-12)
    # nothing measured: 0 for every prior
    Z = np.zeros((2, 2))
    assert im.information_loglik(x1, P1, np.linalg.inv(P1), P1, Z, np.zeros(2)) == pytest.approx(0.0, abs=1e-15)


def test_model_weights_and_mix_hand_worked():
    # two models, mu = (0.8, 0.2), switch 0.1: c = (0.8 * 0.9 + 0.2 * 0.1, 0.8 * 0.1 + 0.2 * 0.9) = (0.74, 0.26)
    Pi = im.transition_matrix(2, 0.1)
    np.testing.assert_allclose(Pi, [[0.9, 0.1], [0.1, 0.9]])
    c, w = im.model_weights(np.array([0.8, 0.2]), Pi)
    np.testing.assert_allclose(c, [0.74, 0.26])
    np.testing.assert_allclose(w[:, 0], [0.72 / 0.74, 0.02 / 0.74])
    # mixture of N(0, 1) and N(2, 1) with weights 0.5, 0.5: mean 1, variance 1 + 1 = 2
    z, Z = np.array([[0.0], [2.0]]), np.array([[[1.0]], [[1.0]]])
    mean, cov = im.mix(np.array([[0.5], [0.5]]), z, Z)
    np.testing.assert_allclose(mean, [[1.0]])
    np.testing.assert_allclose(cov, [[[2.0]]])
    # bounded: the spread (1) is at most the models' own variance (1): unchanged
    np.testing.assert_allclose(im.mix(np.array([[0.5], [0.5]]), z, Z, bounded=True)[1], [[[2.0]]])
    # N(0, 1) and N(6, 1): spread 9 > own 1, so it is scaled to 1: variance 1 + 1 = 2 (10 unbounded)
    z6 = np.array([[0.0], [6.0]])
    np.testing.assert_allclose(im.mix(np.array([[0.5], [0.5]]), z6, Z)[1], [[[10.0]]])
    np.testing.assert_allclose(im.mix(np.array([[0.5], [0.5]]), z6, Z, bounded=True)[1], [[[2.0]]])
    # in 2-D by traces: own covariances I (trace 2), means (0, 0) and (4, 0): spread diag(4, 0) (trace 4),
    # halved to diag(2, 0)
    z2, Z2 = np.array([[0.0, 0.0], [4.0, 0.0]]), np.array([np.eye(2), np.eye(2)])
    np.testing.assert_allclose(im.mix(np.array([[0.5], [0.5]]), z2, Z2, bounded=True)[1], [np.diag([3.0, 1.0])])


def test_model_weights_prune_hand_worked():
    # mu = (0.9995, 0.0005), switch 0.1: c = (0.9 * 0.9995 + 0.1 * 0.0005, 0.1 * 0.9995 + 0.9 * 0.0005)
    # = (0.8996, 0.1004); w_10 = 0.1 * 0.0005 / 0.8996 = 5.6e-5 < 1e-3 is dropped, so model 0's prior is
    # model 0's posterior alone; column 1 (w = (0.09995 / 0.1004, 0.00045 / 0.1004)) is kept
    Pi = im.transition_matrix(2, 0.1)
    mu = np.array([0.9995, 0.0005])
    c, w = im.model_weights(mu, Pi)
    np.testing.assert_allclose(w[1, 0], 0.1 * 0.0005 / 0.89960)
    c_p, w_p = im.model_weights(mu, Pi, prune=1e-3)
    np.testing.assert_array_equal(c_p, c)
    np.testing.assert_array_equal(w_p[:, 0], [1.0, 0.0])
    np.testing.assert_allclose(w_p[:, 1], [0.09995 / 0.1004, 0.00045 / 0.1004])
    # the dropped model's covariance (1e8) no longer enters model 0's prior
    z, Z = np.array([[0.0], [0.0]]), np.array([[[1.0]], [[1e8]]])
    assert im.mix(w, z, Z)[1][0, 0, 0] == pytest.approx(1.0 + 5.558e-5 * 1e8, rel=1e-3)
    assert im.mix(w_p, z, Z)[1][0, 0, 0] == 1.0
    # three models, column 2's small weights (0.0003 / 0.3998 = 0.00075 each) dropped: all of its weight on model 2
    Pi3 = np.array([[0.998, 0.001, 0.001], [0.001, 0.998, 0.001], [0.001, 0.001, 0.998]])
    _, w3 = im.model_weights(np.array([0.3, 0.3, 0.4]), Pi3, prune=1e-3)
    np.testing.assert_array_equal(w3[:, 2], [0.0, 0.0, 1.0])
    # a batch gives the same bits as one by one
    mus = np.random.default_rng(0).dirichlet(np.full(3, 0.05), size=(4, 5))
    batch = im.model_weights(mus, Pi3, prune=1e-3)[1]
    one = np.array([[im.model_weights(mus[a, b], Pi3, prune=1e-3)[1] for b in range(5)] for a in range(4)])
    np.testing.assert_array_equal(batch, one)
    np.testing.assert_allclose(batch.sum(axis=-2), 1.0)


def test_update_probabilities_hand_worked():
    # c = (0.5, 0.5), log-likelihoods (0, log 3): mu = (0.25, 0.75); a floor of 0.3 lifts the first
    mu = im.update_probabilities(np.array([0.5, 0.5]), np.array([0.0, np.log(3.0)]), 1e-6)
    np.testing.assert_allclose(mu, [0.25, 0.75])
    mu = im.update_probabilities(np.array([0.5, 0.5]), np.array([0.0, 1000.0]), 0.3)  # no overflow
    np.testing.assert_allclose(mu, [0.3 / 1.3, 1.0 / 1.3])


def test_affine_prior_hand_worked():
    # from N(0, 4) to N(1, 1): x -> 1 + (1 / 2) x. A model at v = 2, Pv = 8, B = 2:
    # v' = 2, Pv' = 8 / 4 = 2, B' = 1. Where from == to it is the identity.
    v, Pv, B = np.array([[2.0]]), np.array([[[8.0]]]), np.array([[[2.0]]])
    vn, Pn, Bn = im.affine_prior(np.array([0.0]), np.array([[4.0]]), np.array([1.0]), np.array([[1.0]]), v, Pv, B)
    np.testing.assert_allclose(vn, [[2.0]])
    np.testing.assert_allclose(Pn, [[[2.0]]])
    np.testing.assert_allclose(Bn, [[[1.0]]])
    P = np.array([[2.0, 0.5], [0.5, 1.0]])
    vn, Pn, _ = im.affine_prior(np.zeros(2), P, np.zeros(2), P, np.ones((1, 2)), P[None], np.ones((1, 2, 1)))
    np.testing.assert_allclose(vn, np.ones((1, 2)))
    np.testing.assert_allclose(Pn, P[None])


def test_default_bank_follows_the_scales():
    names, a1, a2, q = im.default_bank(0.1, 2.0)
    lo, hi = 0.1, 200.0
    assert names[0] == "none" and a1[0] == 0.0 and q[0] == 0.0
    np.testing.assert_allclose(q[1:4], [lo, np.sqrt(lo * hi), hi])
    assert set(a1[1:4]) == {1.0} and not a2[:8].any()
    # the oscillating models: every period of PERIODS, their names in the wire's order, each expecting
    # the stationary variance of the mean-reverting model at sqrt(lo hi): sqrt(lo hi) / (1 - rho^2)
    assert names[8:] == im.OSCILLATING and names == im.BANK
    np.testing.assert_allclose(a2[8:], -0.95 ** 2)
    size = np.sqrt(lo * hi) / (1 - np.exp(-0.2))
    np.testing.assert_allclose([q[j] * im.stationary_gain(a1[j], a2[j]) for j in range(8, 21)], size)
    assert q[8] > 20 * q[20]  # the slowest model's noise is far smaller than the fastest's
    names, _, _, _ = im.default_bank(0.1, 2.0, none=False, zero_mean=False, oscillating_inputs=False)
    assert names == ("walk lo", "walk mid", "walk hi")


def test_oscillating_model_is_a_sinusoid():
    """r = 1 and no noise: (IM2) reproduces any sinusoid of the period exactly;
    period 4: a1 = 2 r cos(pi / 2) = 0, a2 = -r^2."""
    a1, a2 = im.oscillating(10.0, 1.0)
    d = 3.0 * np.sin(2 * np.pi * np.arange(30) / 10.0 + 0.7)
    np.testing.assert_allclose(a1 * d[1:-1] + a2 * d[:-2], d[2:], atol=1e-12)
    a1, a2 = im.oscillating(4.0, 0.5)
    assert abs(a1) < 1e-15 and a2 == -0.25


def test_stationary_gain_hand_worked():
    """(IM2) with a1 = 0 is two interleaved AR(1) of coefficient a2:
    variance 1 / (1 - a2^2); with a2 = 0 it is AR(1): 1 / (1 - a1^2)."""
    assert im.stationary_gain(0.0, -0.5) == 1.0 / (1.0 - 0.25)
    assert abs(im.stationary_gain(0.5, 0.0) - 1.0 / (1.0 - 0.25)) < 1e-15


def test_companion_and_pair_predict_hand_worked():
    F = im.companion(0.5, -0.25, 2)
    np.testing.assert_array_equal(F, [[0.5, 0, -0.25, 0], [0, 0.5, 0, -0.25], [1, 0, 0, 0], [0, 1, 0, 0]])
    # n = 2, m = 1: e = (d_{k-1}, d_{k-2}) = (2, 1); F e = (0.5 * 2 - 0.25 * 1, 2)
    A = np.array([[1.0, 1.0], [0.0, 1.0]])
    C = np.array([[1.0, 0.0], [0.0, 2.0]])
    S = np.array([[1.0, 0.5], [0.5, 2.0]])
    e, B, S1 = im.pair_predict(A, C, np.array([2.0, 1.0]), S, im.companion(0.5, -0.25, 1), 0.5)
    np.testing.assert_allclose(e, [0.75, 2.0])
    np.testing.assert_allclose(B, [[0.0, 1.0], [-0.5, 0.0]])         # (A C) F^T
    np.testing.assert_allclose(S1, [[0.75, 0.375], [0.375, 1.0]])    # F S F^T + q on d_{k-1}
    # a2 = 0: the first block is input_predict's
    d, B1, S2 = im.input_predict(A, C[:, :1], np.array([2.0]), S[:1, :1], 0.5, 0.5)
    e, B, S1 = im.pair_predict(A, C, np.array([2.0, 1.0]), S, im.companion(0.5, 0.0, 1), 0.5)
    np.testing.assert_allclose(e[:1], d)
    np.testing.assert_allclose(B[:, :1], B1)
    np.testing.assert_allclose(S1[:1, :1], S2)


def test_replace_input_hand_worked():
    """d_{k-1}'s marginal replaced by (1, 1) in the joint (v, d_{k-1}, d_{k-2}) ~
    N(0, [[2, 1, 0], [1, 2, 0], [0, 0, 1]]): K = (1/2, 0), v becomes 0.5 with
    variance 2 - 0.5 + 0.25 and covariance 0.5 with d_{k-1}; d_{k-2} is untouched."""
    v, Pv, e, S, B = im.replace_input(np.zeros(1), np.array([[2.0]]), np.zeros(2), np.array([[2.0, 0.0], [0.0, 1.0]]),
                                      np.array([[1.0, 0.0]]), np.array([1.0]), np.array([[1.0]]))
    np.testing.assert_allclose(v, [0.5])
    np.testing.assert_allclose(Pv, [[1.75]])
    np.testing.assert_allclose(e, [1.0, 0.0])
    np.testing.assert_allclose(S, [[1.0, 0.0], [0.0, 1.0]])
    np.testing.assert_allclose(B, [[0.5, 0.0]])


def test_replace_input_is_the_conditional_kept():
    """Against the joint formula on a random (v, d_{k-1}, d_{k-2}) with n = 2,
    m = 2: the new marginal of d_{k-1}, and p(v, d_{k-2} | d_{k-1}) unchanged."""
    rng = np.random.default_rng(3)
    n, m = 2, 2
    L = rng.normal(size=(n + 2 * m, n + 2 * m))
    Z = L @ L.T + np.eye(n + 2 * m)
    z = rng.normal(size=n + 2 * m)
    Ls = rng.normal(size=(m, m))
    d_new, S_new = rng.normal(size=m), Ls @ Ls.T + np.eye(m)
    x, P, e, S, C = im.split(z, Z, n)
    v2, Pv2, e2, S2, B2 = im.replace_input(x, P, e, S, C, d_new, S_new)
    a, rest = np.arange(n, n + m), np.r_[np.arange(n), np.arange(n + m, n + 2 * m)]
    K = Z[np.ix_(rest, a)] @ np.linalg.inv(Z[np.ix_(a, a)])
    want = np.empty(n + 2 * m)
    want[a], want[rest] = d_new, z[rest] + K @ (d_new - z[a])
    W = np.empty_like(Z)
    W[np.ix_(a, a)] = S_new
    W[np.ix_(rest, a)] = K @ S_new
    W[np.ix_(a, rest)] = (K @ S_new).T
    W[np.ix_(rest, rest)] = Z[np.ix_(rest, rest)] - K @ Z[np.ix_(a, rest)] + K @ S_new @ K.T
    got_z, got_Z = im.joint(v2, Pv2, e2, S2, B2)
    np.testing.assert_allclose(got_z, want, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(got_Z, W, rtol=1e-12, atol=1e-12)


def test_initial_probabilities_and_chain_by_shares():
    """Two first-order models and three oscillating ones: the oscillating share
    one model's probability; a switch moves by those shares."""
    mu = im.initial_probabilities([0.0, 0.0, -1.0, -1.0, -1.0])
    np.testing.assert_allclose(mu, [1 / 3, 1 / 3, 1 / 9, 1 / 9, 1 / 9])
    Pi = im.transition_matrix(5, 0.1, mu)
    np.testing.assert_allclose(Pi.sum(axis=1), 1.0)
    np.testing.assert_allclose(Pi[0], [0.9, 0.05, 0.1 / 6, 0.1 / 6, 0.1 / 6])      # 0.1 * (1/3, 1/9) / (2/3)
    np.testing.assert_allclose(Pi[2], [0.1 * 3 / 8, 0.1 * 3 / 8, 0.9, 0.1 / 8, 0.1 / 8])  # 0.1 * (1/3, 1/9) / (8/9)
    np.testing.assert_allclose(im.transition_matrix(3, 0.2), [[0.8, 0.1, 0.1], [0.1, 0.8, 0.1], [0.1, 0.1, 0.8]])


def test_pool_probabilities_hand_worked():
    # receiver 0 fuses senders 0 and 1, receiver 1 only itself. Sender 0 says (0.8, 0.2), sender 1 (0.2, 0.8):
    # the geometric mean is (0.4, 0.4), normalised (0.5, 0.5); alone, receiver 1 keeps (0.2, 0.8)
    adj = np.array([[1.0, 1.0], [0.0, 1.0]])
    w = np.array([[0.8, 0.2], [0.2, 0.8]])
    np.testing.assert_allclose(im.pool_probabilities(adj, w, 1e-6), [[0.5, 0.5], [0.2, 0.8]])
    # (0.9, 0.1) with (0.5, 0.5): sqrt(0.45) : sqrt(0.05) = 3 : 1
    np.testing.assert_allclose(im.pool_probabilities(np.ones((1, 2)), np.array([[0.9, 0.1], [0.5, 0.5]]), 1e-6),
                               [[0.75, 0.25]])
    # the floor bounds what one sender's zero takes from a model: log max(0, 0.01) = log 0.01
    # against the other's log 0.5, mean weights 0.01^(1/2) 0.5^(1/2) : 1^(1/2) 0.5^(1/2) = 0.1 : 1
    pooled = im.pool_probabilities(np.ones((1, 2)), np.array([[0.0, 1.0], [0.5, 0.5]]), 0.01)
    np.testing.assert_allclose(pooled, [[0.1 / 1.1, 1.0 / 1.1]])


@pytest.mark.parametrize("bounded", [False, True])
def test_mix_gives_the_same_bits_for_any_batch_shape(bounded, monkeypatch):
    """An agent (a batch of one, every term at once) and the engine (a large
    batch, one model at a time) mix the same models into the same bits: the
    mesh equals the engine only so."""
    rng = np.random.default_rng(5)
    B, M, k = 40, 21, 4
    w = rng.dirichlet(np.ones(M), size=(B, M)).transpose(0, 2, 1)              # (B, M, J): columns sum to 1
    z = rng.normal(size=(B, M, k)) * rng.choice([1e-3, 1.0, 1e3], size=(B, M, 1))
    L = rng.normal(size=(B, M, k, k))
    Z = L @ np.swapaxes(L, -1, -2) + 1e-3 * np.eye(k)
    assert w.size * k * k > im.ALL_TERMS_AT_ONCE >= w[:1].size * k * k         # the engine's path, the agent's
    engine = im.mix(w, z, Z, bounded=bounded)
    agents = [im.mix(w[b:b + 1], z[b:b + 1], Z[b:b + 1], bounded=bounded) for b in range(B)]
    for got, want in zip(map(np.concatenate, zip(*agents)), engine):
        assert np.array_equal(got, want)
    monkeypatch.setattr(im, "ALL_TERMS_AT_ONCE", 0)                              # every batch one model at a time
    for got, want in zip(im.mix(w[:1], z[:1], Z[:1], bounded=bounded), agents[0]):
        assert np.array_equal(got, want)


@pytest.mark.parametrize("bounded", [False, True])
def test_mix_gives_the_same_bytes_on_every_path(bounded, monkeypatch):
    """A few columns (an agent's: as many terms each, a pruned weight's terms
    -0.0) and many (the engine's: slot after slot) give the same bytes,
    signs of zero included (a model with no input holds exact zeros, of
    either sign)."""
    rng = np.random.default_rng(17)
    B, M, k = 3, 21, 4
    w = rng.dirichlet(np.ones(M), size=(B, M)).transpose(0, 2, 1)
    keep = rng.random((B, M, M)) < rng.choice([0.1, 0.3, 1.0], size=(B, 1, M))
    keep[:, 0, :] |= ~keep.any(axis=1)
    w = np.where(keep, w, 0.0)
    w = w / w.sum(axis=1, keepdims=True)
    z = rng.normal(size=(B, M, k))
    z[:, :, 2:] = rng.choice([0.0, -0.0], size=(B, M, 2))                     # exact zeros, both signs
    L = rng.normal(size=(B, M, k, k))
    Z = L @ np.swapaxes(L, -1, -2) + 1e-3 * np.eye(k)
    Z[:, :, 3, :] = Z[:, :, :, 3] = -0.0
    assert im._padded(w[:1], im.PADDED_TERMS) is not None                       # an agent's columns: padded
    agents = [im.mix(w[b:b + 1], z[b:b + 1], Z[b:b + 1], bounded=bounded) for b in range(B)]
    engine = im.mix(w, z, Z, bounded=bounded)
    monkeypatch.setattr(im, "PADDED_TERMS", 0)                                   # slot after slot
    for b in range(B):
        slots = im.mix(w[b:b + 1], z[b:b + 1], Z[b:b + 1], bounded=bounded)
        for got, by_slots, in_engine in zip(agents[b], slots, engine):
            assert got.tobytes() == by_slots.tobytes() == in_engine[b:b + 1].tobytes()


@pytest.mark.parametrize("bounded", [False, True])
def test_an_output_mixture_with_zero_weights_gives_the_same_bytes_at_once(bounded, monkeypatch):
    """An agent's output mixture (one column, some weights pruned to 0):
    every term at once, the zero weights' terms -0.0, gives the bytes of the
    padded terms and of the slots, signs of zero included."""
    rng = np.random.default_rng(23)
    M, k = 21, 4
    mu = rng.dirichlet(np.full(M, 0.2), size=(5, 1)).transpose(0, 2, 1)         # (5, M, 1)
    w = np.where(mu < 1e-2, 0.0, mu)
    w[:, 0] += (w.sum(axis=1) == 0)
    w = w / w.sum(axis=1, keepdims=True)
    z = rng.normal(size=(5, M, k))
    z[:, :, 2] = rng.choice([0.0, -0.0], size=(5, M))
    z[:, :, 3] = np.where(w[..., 0] == 0, 0.0, -0.0)                            # a weight of 0 adds no +0.0
    L = rng.normal(size=(5, M, k, k))
    Z = L @ np.swapaxes(L, -1, -2) + 1e-3 * np.eye(k)
    Z[:, :, 3, :] = Z[:, :, :, 3] = -0.0
    assert (w == 0).any() and w[:1].size * k * k <= im.ZEROS_AT_ONCE
    at_once = [im.mix(w[b:b + 1], z[b:b + 1], Z[b:b + 1], bounded=bounded) for b in range(5)]
    monkeypatch.setattr(im, "ZEROS_AT_ONCE", 0)                                  # padded terms
    padded = [im.mix(w[b:b + 1], z[b:b + 1], Z[b:b + 1], bounded=bounded) for b in range(5)]
    monkeypatch.setattr(im, "PADDED_TERMS", 0)                                   # slot after slot
    slots = im.mix(w, z, Z, bounded=bounded)
    for b in range(5):
        for one, pad, many in zip(at_once[b], padded[b], slots):
            assert one.tobytes() == pad.tobytes() == many[b:b + 1].tobytes()


@pytest.mark.parametrize("bounded", [False, True])
def test_mix_leaves_out_zero_weights_with_the_same_bits(bounded):
    """Pruned weights (0) add nothing: a batch whose columns hold 1 to M
    nonzero weights mixes, column by column, the bits of the same column
    alone, and of the plain sum over every model in order (its zero terms
    included)."""
    rng = np.random.default_rng(11)
    B, M, k = 30, 21, 4
    w = rng.dirichlet(np.ones(M), size=(B, M)).transpose(0, 2, 1)
    keep = rng.random((B, M, M)) < rng.choice([0.05, 0.2, 1.0], size=(B, 1, M))
    keep[:, 0, :] |= ~keep.any(axis=1)                                           # every column keeps a weight
    w = np.where(keep, w, 0.0)
    w = w / w.sum(axis=1, keepdims=True)
    z = rng.normal(size=(B, M, k)) * rng.choice([1e-3, 1.0, 1e3], size=(B, M, 1))
    L = rng.normal(size=(B, M, k, k))
    Z = L @ np.swapaxes(L, -1, -2) + 1e-3 * np.eye(k)
    mean, cov = im.mix(w, z, Z, bounded=bounded)
    for b in (0, 7, 29):
        for j in (0, 5, 20):
            one = im.mix(w[b:b + 1, :, j:j + 1], z[b:b + 1], Z[b:b + 1], bounded=bounded)
            assert np.array_equal(one[0][0, 0], mean[b, j]) and np.array_equal(one[1][0, 0], cov[b, j])
            wj = w[b, :, j]
            m = wj[0] * z[b, 0]
            for i in range(1, M):
                m = m + wj[i] * z[b, i]
            within, spread = Z[b, 0] * wj[0], np.outer(z[b, 0] - m, z[b, 0] - m) * wj[0]
            for i in range(1, M):
                within = within + Z[b, i] * wj[i]
                spread = spread + np.outer(z[b, i] - m, z[b, i] - m) * wj[i]
            if bounded and np.trace(spread) > np.trace(within):
                spread = spread * (np.trace(within) / np.trace(spread))
            assert np.array_equal(m, mean[b, j])
            assert np.array_equal(0.5 * ((within + spread) + (within + spread).T), cov[b, j])


def test_a_random_walk_hands_down_to_the_walks_of_smaller_scale():
    """``hand_down``: each walk (a1 = 1, a2 = 0) moves to each walk of a
    smaller q with the added rate, never up, and no other model moves more
    than the chain's switch; every row still sums to 1."""
    names, a1, a2, q = im.default_bank(0.01, 1.0)
    walks = {n: names.index(n) for n in ("walk lo", "walk mid", "walk hi")}
    down = im.hand_down(a1, a2, q, 0.001)
    lo, mid, hi = walks["walk lo"], walks["walk mid"], walks["walk hi"]
    assert down[hi, mid] == down[hi, lo] == down[mid, lo] == 0.001
    assert down.sum() == 3 * 0.001  # hi -> mid, hi -> lo, mid -> lo; nothing up, nothing else
    mu0 = im.initial_probabilities(a2)
    plain, handed = im.transition_matrix(len(names), 0.001, mu0), im.transition_matrix(len(names), 0.001, mu0, down)
    np.testing.assert_allclose(handed.sum(axis=1), 1.0, rtol=0, atol=1e-15)
    assert handed[hi, lo] > 5 * plain[hi, lo] and handed[mid, lo] > 5 * plain[mid, lo]
    assert handed[lo, mid] <= plain[lo, mid] and handed[lo, hi] <= plain[lo, hi]
    others = [i for i in range(len(names)) if i not in walks.values()]
    np.testing.assert_allclose(handed[others], plain[others], rtol=1e-12, atol=0)
    assert im.hand_down(a1, a2, q, 0.0) is None
    assert im.hand_down(a1[:2], a2[:2], q[:2], 0.001) is None  # "none" and one walk: no smaller walk


def test_a_bank_per_channel_varies_its_own_channel_and_holds_the_others_at_their_best():
    """``channel_models``: filter j of bank c moves channel c by model j and
    every other channel by that channel's most probable model; where every
    channel's model is the same the filter is ``companion``'s and
    ``pair_predict``'s one model for all channels, bit for bit."""
    names, a1, a2, q = im.default_bank(0.01, 1.0)
    M, m = len(names), 2
    top = np.array([[names.index("walk lo"), names.index("oscillating 8")]])   # one agent's best per channel
    F, noise = im.channel_models(a1, a2, q, top)
    assert F.shape == noise.shape == (1, m * M, 2 * m, 2 * m)
    for c in range(m):
        for j in range(M):
            f = F[0, c * M + j]
            model = [top[0, k] if k != c else j for k in range(m)]
            np.testing.assert_array_equal(np.diag(f[:m, :m]), a1[model])
            np.testing.assert_array_equal(np.diag(f[:m, m:]), a2[model])
            np.testing.assert_array_equal(np.diag(noise[0, c * M + j][:m, :m]), q[model])
            np.testing.assert_array_equal(f[m:, :m], np.eye(m))
    same = im.channel_models(a1, a2, q, np.array([[3, 3]]))
    j = 3  # bank 0's filter of model 3, with channel 1 at model 3 too
    np.testing.assert_array_equal(same[0][0, j], im.companion(a1, a2, m)[j])
    rng = np.random.default_rng(7)
    C, e = rng.normal(size=(4, 2 * m)), rng.normal(size=2 * m)
    L = rng.normal(size=(2 * m, 2 * m))
    S = L @ L.T + np.eye(2 * m)
    A = np.eye(4) + 0.1 * rng.normal(size=(4, 4))
    one = im.pair_predict(A, C, e, S, im.companion(a1, a2, m)[j], q[j])
    per = im.pair_predict(A, C, e, S, same[0][0, j], 0.0, same[1][0, j])
    for a, b in zip(one, per):
        np.testing.assert_array_equal(a, b)


def test_a_measurement_energy_from_its_information_alone():
    """``information_energy``: y^T R^-1 y and the rows from U = H^T R^-1 H and
    u = H^T R^-1 y where H has full row rank (batched, each sender its
    own); where it has more rows than the state, the energy of what H sees
    (the generalised least-squares estimate's); 0 and 0 where nothing was
    measured."""
    rng = np.random.default_rng(3)
    H = rng.normal(size=(5, 2, 4))
    R = np.array([np.diag(rng.uniform(0.5, 3.0, 2)) for _ in range(5)])
    y = 100.0 * rng.normal(size=(5, 2))
    Ri = np.linalg.inv(R)
    U, u = np.swapaxes(H, -1, -2) @ Ri @ H, (np.swapaxes(H, -1, -2) @ Ri @ y[..., None])[..., 0]
    E, k = im.information_energy(U, u)
    np.testing.assert_allclose(E, np.einsum("bi,bij,bj->b", y, Ri, y), rtol=1e-9)
    np.testing.assert_array_equal(k, 2.0)
    tall = rng.normal(size=(3, 2))  # three rows of a two-state model
    y3 = rng.normal(size=3)
    E3, k3 = im.information_energy(tall.T @ tall, tall.T @ y3)
    fit = tall @ np.linalg.lstsq(tall, y3, rcond=None)[0]
    assert k3 == 2.0 and np.isclose(E3, fit @ fit)
    assert im.information_energy(np.zeros((4, 4)), np.zeros(4)) == (0.0, 0.0)
