"""Each equation of the paper against numbers worked by hand."""
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from diskf_mesh.core import equations as eq
from diskf_mesh.core.linalg import inv_spd, is_spd, nbr_sum

G = np.array([[1.0], [1.0]])


def local_update(x, P, U, u, has=None):
    """eq. info_kf_update0 from (P^, U): the information pair inverted here."""
    return eq.local_update(x, P, *eq.information_pair(P, U), u, has)


def input_estimate(x, P, U, u, Gm, allowed=None):
    return eq.input_estimate(x, *eq.information_pair(P, U), U, u, Gm, allowed)


def test_prediction_eq_info_kf_prediction0():
    A = np.array([[0.0, -1.0], [1.0, 0.0]])  # rotation by 90 degrees
    x, P = eq.predict(np.array([1.0, 2.0]), np.diag([1.0, 2.0]), A, 0.2 * np.eye(2))
    np.testing.assert_allclose(x, [-2.0, 1.0])
    np.testing.assert_allclose(P, np.diag([2.2, 1.2]))


def test_measurement_information_padding_and_absence():
    # sensor sees x with R = 2, padded to two rows (zero row in H, 1 in R)
    H = np.array([[1.0, 0.0], [0.0, 0.0]])
    R = np.diag([2.0, 1.0])
    U, u = eq.measurement_information(eq.sensor_information(H, R), np.array([3.0, 0.0]), np.array(True))
    np.testing.assert_allclose(U, np.diag([0.5, 0.0]))
    np.testing.assert_allclose(u, [1.5, 0.0])
    U, u = eq.measurement_information(eq.sensor_information(H, R), np.array([3.0, 0.0]), np.array(False))
    assert not U.any() and not u.any()


def test_local_update_eq_info_kf_update0():
    # P^ = 2I, x^ = (1, 1), sees x = 3 with R = 2:
    # K = P H^T / (H P H^T + R) = (0.5, 0);  x~ = (1 + 0.5 * 2, 1) = (2, 1);  P~ = diag(1, 2)
    x, P = local_update(np.array([1.0, 1.0]), 2 * np.eye(2), np.diag([0.5, 0.0]), np.array([1.5, 0.0]))
    np.testing.assert_allclose(x, [2.0, 1.0])
    np.testing.assert_allclose(P, np.diag([1.0, 2.0]))


def test_local_update_without_measurement_is_prediction_bit_for_bit():
    P = np.array([[2.0, 0.3], [0.3, 1.7]])
    x = np.array([0.1, -4.0])
    xu, Pu = local_update(x, P, np.zeros((2, 2)), np.zeros(2), np.array(False))
    assert np.array_equal(xu, x) and np.array_equal(Pu, P)


def test_input_estimation_scalar_by_hand():
    # H = (1, 0), G = (1, 1): HG = 1.  R~ = H P^ H^T + R = 2 + 2 = 4
    # M = (1/4)^-1 * 1/4 = 1,  d^ = y - H x^ = 3 - 1 = 2,  S^ = 4
    d, S, valid = input_estimate(np.array([1.0, 1.0]), 2 * np.eye(2), np.diag([0.5, 0.0]),
                                    np.array([1.5, 0.0]), G)
    assert valid
    np.testing.assert_allclose(d, [2.0])
    np.testing.assert_allclose(S, [[4.0]])


def test_input_estimation_two_rows_by_hand():
    # H = I, R = I, P^ = I, x^ = 0, y = (1, 3): R~ = 2I, F = G
    # F^T R~^-1 F = 1 -> S^ = 1;  M = (1/2, 1/2);  d^ = 2
    d, S, valid = input_estimate(np.zeros(2), np.eye(2), np.eye(2), np.array([1.0, 3.0]), G)
    assert valid
    np.testing.assert_allclose(d, [2.0])
    np.testing.assert_allclose(S, [[1.0]])


def test_input_estimation_matches_direct_formula_random():
    rng = np.random.default_rng(3)
    n, m, p = 4, 2, 3
    for _ in range(20):
        a = rng.normal(size=(n, n))
        P = a @ a.T + np.eye(n)
        b = rng.normal(size=(p, p))
        R = b @ b.T + np.eye(p)
        H = rng.normal(size=(p, n))
        Gm = rng.normal(size=(n, m))
        x = rng.normal(size=n)
        y = rng.normal(size=p)
        Rt = H @ P @ H.T + R
        F = H @ Gm
        Fi = F.T @ np.linalg.inv(Rt)
        S_ref = np.linalg.inv(Fi @ F)
        d_ref = S_ref @ Fi @ (y - H @ x)
        U = H.T @ np.linalg.solve(R, H)
        u = H.T @ np.linalg.solve(R, y)
        d, S, valid = input_estimate(x, P, U, u, Gm)
        assert valid
        np.testing.assert_allclose(d, d_ref, rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(S, S_ref, rtol=1e-9, atol=1e-9)


@pytest.mark.parametrize("case", ["rank", "absent", "window"])
def test_input_estimation_skipped(case):
    H = np.array([[1.0, -1.0]]) if case == "rank" else np.array([[1.0, 0.0]])  # H G = 0 for "rank"
    U, u = eq.measurement_information(eq.sensor_information(H, np.array([[2.0]])), np.array([3.0]), np.array(case != "absent"))
    d, S, valid = input_estimate(np.zeros(2), np.eye(2), U, u, G, allowed=np.array(case != "window"))
    assert not valid
    assert np.array_equal(d, [0.0]) and np.array_equal(S, [[1.0]])


def test_input_fusion_by_hand():
    # d = (1, 3), S = (1, 3): w = (1, 1/3) / (4/3) = (3/4, 1/4)
    # S_bar^-1 = 3/4 * 1 + 1/4 * 1/3 = 5/6 -> S_bar = 1.2
    # d_bar = 1.2 * (3/4 * 1 + 1/4 * 3/3) = 1.2
    adj = np.ones((1, 3))
    d = np.array([[1.0], [3.0], [100.0]])
    S = np.array([[[1.0]], [[3.0]], [[0.001]]])
    valid = np.array([True, True, False])  # the third is not an estimate
    d_bar, S_bar, has = eq.input_fusion(adj, d, S, valid)
    assert has[0]
    np.testing.assert_allclose(d_bar, [[1.2]])
    np.testing.assert_allclose(S_bar, [[[1.2]]])


def test_input_fusion_with_nothing_valid():
    d_bar, S_bar, has = eq.input_fusion(np.ones((1, 2)), np.ones((2, 1)), np.ones((2, 1, 1)), np.array([False, False]))
    assert not has[0] and d_bar[0, 0] == 0.0


@pytest.mark.parametrize("seed", range(4))
def test_scalar_input_fusion_is_input_fusions_bits(seed):
    """input_fusion_scalar (m = 1, sender after sender) gives input_fusion's
    bytes, signs of zero included: any leading axes, receivers broadcast
    against the senders' models, zero weights, invalid and -0.0 inputs,
    receivers with nothing to fuse; and its error where an S is not positive."""
    rng = np.random.default_rng(seed)
    for _ in range(200):
        lead, R, senders = tuple(rng.integers(1, 4, rng.integers(0, 3))), rng.integers(1, 5), rng.integers(1, 10)
        adj = (rng.random(lead[:1] + (1, R, senders)) < 0.6).astype(float)   # broadcast over the models' axis
        d = rng.standard_normal(lead[:1] + (3, senders, 1)) * 10.0 ** rng.uniform(-5, 5, (senders, 1))
        d[rng.random(d.shape) < 0.1] = -0.0
        S = 10.0 ** rng.uniform(-6, 6, lead[:1] + (3, senders, 1, 1))
        valid = rng.random(lead[:1] + (1, senders)) < 0.7
        for want, got in zip(eq.input_fusion(adj, d, S, valid), eq.input_fusion_scalar(adj, d, S, valid)):
            assert want.shape == got.shape and want.tobytes() == got.tobytes()
    with pytest.raises(np.linalg.LinAlgError):
        eq.input_fusion_scalar(np.ones((1, 2)), np.ones((2, 1)), np.array([[[1.0]], [[0.0]]]), np.ones(2, bool))


spd_strategy = hnp.arrays(np.float64, (3, 3), elements=st.floats(-3, 3))


@settings(max_examples=200, deadline=None)
@given(a=spd_strategy, d=hnp.arrays(np.float64, 3, elements=st.floats(-1e3, 1e3)), copies=st.integers(1, 6))
def test_ci_of_identical_estimates_returns_that_estimate(a, d, copies):
    S = a @ a.T + 0.1 * np.eye(3)
    d_bar, S_bar, has = eq.input_fusion(
        np.ones((1, copies)), np.tile(d, (copies, 1)), np.tile(S, (copies, 1, 1)), np.ones(copies, bool))
    assert has[0]
    np.testing.assert_allclose(S_bar[0], S, rtol=1e-8, atol=1e-10)
    np.testing.assert_allclose(d_bar[0], d, rtol=1e-8, atol=1e-8 * (1 + np.abs(d).max()))


def test_information_contribution_recovers_measurement_information():
    x, P = np.array([1.0, 1.0]), 2 * np.eye(2)
    U, u = np.diag([0.5, 0.0]), np.array([1.5, 0.0])
    xu, Pu = local_update(x, P, U, u)
    dy, dY = eq.information_contribution(x, inv_spd(P), xu, inv_spd(Pu))
    np.testing.assert_allclose(dY, U, atol=1e-12)
    np.testing.assert_allclose(dy, u, atol=1e-12)


def test_round_off_in_a_neighbourhoods_information_is_cut_where_it_breaks_the_update():
    """A prediction of variance 10^9 on axes nobody measures, and a summed
    information U whose differences of inverses left -2e-5 there (as
    measured on isolated constant-acceleration agents): P^-1 + U has no
    Cholesky factor. ``information_pair_psd`` replaces that matrix's U by
    its nearest positive-semidefinite one, and only that matrix's: its
    neighbour in the batch gets ``information_pair``'s bits."""
    rng = np.random.default_rng(3)
    Q, _ = np.linalg.qr(rng.normal(size=(4, 4)))
    P = np.stack([np.diag([0.5, 0.04, 3e9, 2e5]), Q @ np.diag([1.0, 2.0, 3.0, 4.0]) @ Q.T])
    U = np.zeros((2, 4, 4))
    U[:, 0, 0] = 1.0
    U[0, 2, 2], U[0, 3, 3] = -6e-10, -2e-5  # round-off of P~^-1 - P^^-1
    U[1, 3, 3] = -1e-12  # round-off the update survives: left as it is
    with pytest.raises(np.linalg.LinAlgError):
        eq.information_pair(P, U)
    Y, Ji, Uc = eq.information_pair_psd(P, U)
    np.testing.assert_array_equal(Uc[0], np.diag([1.0, 0.0, 0.0, 0.0]))
    np.testing.assert_array_equal(Uc[1], U[1])
    Y1, Ji1 = eq.information_pair(P[1:], U[1:])
    np.testing.assert_array_equal(Ji[1], Ji1[0])
    np.linalg.cholesky(Ji)  # raises where not positive definite
    P[0, 2, 2] = -1.0  # a prediction without a factor: the filter diverged, and that still raises
    with pytest.raises(np.linalg.LinAlgError):
        eq.information_pair_psd(P, U)


def test_state_fusion_by_hand():
    # own prior P^ = 2I, x^* = (0, 0); neighbours add diag(0.5, 0) with u = (1.5, 0)
    # and diag(0, 0.5) with u = (0, 1):  P_bar^-1 = 0.5 I + diag(.5, .5) = I
    # x_bar = (1.5, 1)
    adj = np.ones((1, 2))
    dY = np.array([np.diag([0.5, 0.0]), np.diag([0.0, 0.5])])
    dy = np.array([[1.5, 0.0], [0.0, 1.0]])
    x, P = eq.state_fusion(adj, np.zeros((1, 2)), inv_spd(2 * np.eye(2)[None]), dy, dY)
    np.testing.assert_allclose(P[0], np.eye(2))
    np.testing.assert_allclose(x[0], [1.5, 1.0])


def test_input_prediction_eq_info_kf_prediction():
    x = eq.input_prediction(np.array([[1.0, 2.0], [1.0, 2.0]]), G, np.array([[3.0], [3.0]]), np.array([True, False]))
    np.testing.assert_allclose(x, [[4.0, 5.0], [1.0, 2.0]])


def test_compensation_by_hand():
    # two agents, P_bar = I, eps = 0.05, one neighbour each
    # bounded gain M = I / 1.05;  x_1 += 0.05/1.05 * (x^_2 - x^_1)
    adj = np.ones((2, 2))
    x_pred = np.array([[0.0, 0.0], [2.1, -4.2]])
    P = np.broadcast_to(np.eye(2), (2, 2, 2))
    gain = eq.compensation_gain(P, "bounded", 0.05, np.array([1, 1]))
    np.testing.assert_allclose(gain, np.broadcast_to(np.eye(2) / 1.05, (2, 2, 2)))
    x = eq.compensation_state(adj, np.zeros((2, 2)), gain, x_pred, x_pred, 0.05)
    np.testing.assert_allclose(x, [[0.1, -0.2], [-0.1, 0.2]])
    np.testing.assert_allclose(eq.compensation_gain(P, "paper"), P)
    np.testing.assert_allclose(eq.compensation_gain(P, "normalized"), P / (1 + np.sqrt(2)))


def test_bounded_gain_never_overshoots():
    rng = np.random.default_rng(0)
    for scale in (1e-3, 1.0, 1e3, 1e8):
        a = rng.normal(size=(2, 2))
        P = scale * (a @ a.T + 0.01 * np.eye(2))
        M = eq.compensation_gain(P, "bounded", 0.05, np.array(8))
        ev = np.linalg.eigvals(0.05 * 8 * M).real
        assert ev.max() < 1.0


def test_compensation_exactly_zero_for_identical_predictions():
    x_pred = np.tile(np.array([[123.456789, -0.000123]]), (5, 1))
    x = np.arange(10.0).reshape(5, 2)
    out = eq.compensation_state(np.ones((5, 5)), x, np.broadcast_to(np.eye(2), (5, 2, 2)), x_pred, x_pred, 0.05)
    assert np.array_equal(out, x)
    # a large batch of small all-to-all neighbourhoods (the sum runs batch-innermost)
    rng = np.random.default_rng(0)
    x_pred = np.broadcast_to(rng.standard_normal((60, 1, 2)) * 100, (60, 4, 2))
    x = rng.standard_normal((60, 4, 2))
    out = eq.compensation_state(np.ones((60, 4, 4)), x, np.broadcast_to(np.eye(2), (60, 4, 2, 2)), x_pred, x_pred, 0.05)
    assert np.array_equal(out, x)


def test_window():
    since = np.array([0, 1, 5, 6])
    assert list(eq.window_allows(since, 5)) == [True, True, True, False]
    assert eq.window_allows(since, None).all()


def test_nbr_sum_rows_are_bit_identical():
    rng = np.random.default_rng(1)
    x = rng.normal(size=(7, 2, 2)) * 1e3
    out = nbr_sum(np.ones((7, 7)), x, 2)
    assert all(np.array_equal(out[0], out[i]) for i in range(7))


def test_inv_spd_and_is_spd():
    a = np.array([[4.0, 1.0], [1.0, 3.0]])
    np.testing.assert_allclose(inv_spd(a) @ a, np.eye(2), atol=1e-12)
    assert is_spd(a)
    assert not is_spd(np.array([[1.0, 2.0], [2.0, 1.0]]))   # indefinite
    assert not is_spd(np.array([[1.0, 0.5], [0.0, 1.0]]))   # not symmetric
    assert not is_spd(np.array([[np.nan, 0.0], [0.0, 1.0]]))
