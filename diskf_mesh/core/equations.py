"""The equations of the paper, one function each: Z. Wu and A. Mehta,
"Decentralized Input and State Estimation for Multi-agent System with Dynamic
Topology and Heterogeneous Sensor Network", arXiv:2410.00272 (CITATION.cff).

Every function is pure, works on numpy arrays with any leading batch axes
(seeds x agents, or a single agent as a batch of one) and names the equation
label it implements. Nothing here knows about transport, timing or faults.

Notation (per agent i, tick k):
    x_pred, P_pred   x^_{k|k-1}, P^_{k|k-1}     prediction without input
    x_upd,  P_upd    x~_{k|k},  P~_{k|k}        local Kalman update
    d, S             d^_{k-1},  S^_k            local input estimate
    d_bar, S_bar     fused input (covariance intersection)
    x_bar, P_bar     fused state
    U, u             H^T R^-1 H and H^T R^-1 y  (measurement information)
"""
from __future__ import annotations

import numpy as np

from diskf_mesh.core.small import not_pd
from diskf_mesh.core.linalg import (
    T,
    congruence,
    congruence_const,
    congruence_each,
    eigvalsh,
    factorable,
    identity,
    inv_spd,
    matmul_left,
    matmul_right,
    mv,
    nbr_sum,
    nbr_sum_pair,
    pair_sum,
    psd_part,
    row_sum,
    solve,
    sum_order,
    sym,
    sym_of_inverses,
)


# --------------------------------------------------------------------------
# Step 1: individual estimation
# --------------------------------------------------------------------------
def predict(x: np.ndarray, P: np.ndarray, A: np.ndarray, Q: np.ndarray):
    """Eq. (info_kf_prediction0): x^ = A x_bar,  P^ = A P_bar A^T + Q."""
    x_pred = mv(A, x)
    P_pred = sym(congruence_const(A, P) + Q)
    return x_pred, P_pred


def sensor_information(H: np.ndarray, R: np.ndarray):
    """The sensor's constant factors of the measurement information below eq.
    (state_fusion): (H^T R^-1, H^T R^-1 H). Computed once per sensor, not per
    tick; ``measurement_information`` takes them as ``info``."""
    HtRi = T(solve(R, H))  # (R^-1 H)^T = H^T R^-1 (R symmetric)
    return HtRi, sym(np.matmul(HtRi, H))


def measurement_information(info, y: np.ndarray, has: np.ndarray):
    """Information of one measurement: U = H^T R^-1 H, u = H^T R^-1 y.

    These are the per-agent terms of the unpacked sums below eq. (state_fusion).
    ``info`` = ``sensor_information(H, R)``, H: (..., p, n), R: (..., p, p);
    y: (..., p), has: (...) bool. Rows of H that are zero (padding of a
    shorter sensor) contribute nothing, so sensors of different p^i share one
    padded array. An agent that measured nothing (has=False) contributes zero
    information.
    """
    HtRi, HtRiH = info
    has = np.asarray(has)
    U = HtRiH * has[..., None, None]
    u = mv(HtRi, np.where(has[..., None], y, 0.0))  # exactly zero where nothing was measured
    return U, u


def local_update(x_pred: np.ndarray, P_pred: np.ndarray, Y: np.ndarray, Ji: np.ndarray, u: np.ndarray, has=None):
    """Eq. (info_kf_update0), information form of the local Kalman update.

    P~^-1 = P^^-1 + H^T R^-1 H,   x~ = P~ (P^^-1 x^ + H^T R^-1 y)
    (equal to x^ + L (y - H x^) with L = P~ H^T R^-1).
    In the information form it works in: ``Y`` = P^^-1 and ``Ji`` =
    (Y + U)^-1 (``input_estimate`` needs the same two inverses; the caller
    computes them once per tick, ``information_pair``).
    Where ``has`` is False the update is the prediction, bit for bit, so a
    neighbour that measured nothing contributes exactly zero information.
    """
    P_upd = Ji
    x_upd = mv(P_upd, mv(Y, x_pred) + u)
    if has is not None:
        has = np.asarray(has, dtype=bool)
        x_upd = np.where(has[..., None], x_upd, x_pred)
        P_upd = np.where(has[..., None, None], P_upd, P_pred)
    return x_upd, P_upd


def information_pair(P_pred: np.ndarray, U: np.ndarray, Y: np.ndarray | None = None):
    """(Y, Ji) = (P^^-1, (P^^-1 + H^T R^-1 H)^-1): the information form of a
    prediction and of its update (eq. info_kf_update0), inverted once for
    ``local_update`` and ``input_estimate``; ``Y``: P^^-1 already inverted
    (for several U of one prediction)."""
    Y = inv_spd(P_pred) if Y is None else Y
    return Y, inv_spd(Y + U)


def information_pair_psd(P_pred: np.ndarray, U: np.ndarray, Y: np.ndarray | None = None):
    """``information_pair`` for a neighbourhood's information U summed from
    messages: U = sum_j (P~_j^-1 - P^_j^-1) is positive semidefinite, but
    where a prediction's covariance is 10^9 or more on an axis nobody
    measures, the differences of inverses leave round-off of 10^-5 there,
    and Y + U can lose its Cholesky factor. Only then, and only for those
    matrices (each tried alone, so the choice never depends on the batch),
    U is replaced by its nearest positive-semidefinite matrix
    (``linalg.psd_part``). A prediction without a factor still raises.
    ``Y``: as ``information_pair``'s. Returns (Y, Ji, U), U broadcast to
    Y's shape where it was replaced."""
    try:
        return information_pair(P_pred, U, Y) + (U,)
    except np.linalg.LinAlgError:
        Y = inv_spd(P_pred) if Y is None else Y
        U = np.broadcast_to(U, Y.shape).copy()
        bad = ~factorable(Y + U)
        U[bad] = psd_part(U[bad])
        return Y, inv_spd(Y + U), U


def input_estimate(x_pred, Y, Ji, U, u, G, allowed=None, rank_rtol: float = 1e-9):
    """Eqs. (input_estimation), (input_estimation_mk1), (input_estimation_mk2),
    the covariance S^ below them and the rank condition (eq10).

        R~ = H P^ H^T + R
        M  = [(HG)^T R~^-1 (HG)]^-1 (HG)^T R~^-1
        d^ = M (y - H x^),     S^ = [(HG)^T R~^-1 (HG)]^-1

    Computed from the measurement information (U, u) with the Woodbury
    identity, so the same function serves one sensor (DISKF, L-DRKF, the
    comparison input of KCF/DiffKF/GDKF) and a stacked neighbourhood (C-DRKF)
    without ever forming the p x p matrix R~:

        H^T R~^-1 H          = Y J^-1 U,       J = P^^-1 + U,  Y = P^^-1
        H^T R~^-1 (y - H x^) = Y J^-1 (u - U x^)

    Returns (d, S, valid). ``valid`` is False where the rank condition
    rank(H G) = m fails (this includes "no measurement"), or where ``allowed``
    (the observation time window) forbids input estimation; there d = 0 and
    S = I as inert placeholders.
    ``Y`` = P^^-1 and ``Ji`` = (Y + U)^-1 (``information_pair``).
    """
    J = Y + U
    YJi = np.matmul(Y, Ji)
    C = sym(np.matmul(YJi, U))                     # H^T R~^-1 H
    c = mv(YJi, u - mv(U, x_pred))                 # H^T R~^-1 (y - H x^)
    # F_info = (HG)^T R~^-1 (HG), m x m.
    # rank(HG) = m  <=>  G^T U G = (HG)^T R^-1 (HG) is positive definite.
    # Judged against the total information G^T J G, so that round-off in a
    # neighbour's (P~^-1 - P^^-1) is not mistaken for a measurement.
    F_info, GUG, GJG = congruence_each(G, C, U, J)
    m = G.shape[-1]
    if m == 1:  # the 1 x 1 matrices are their own eigenvalues
        valid = GUG[..., 0, 0] > rank_rtol * GJG[..., 0, 0]
    else:
        valid = eigvalsh(GUG)[..., 0] > rank_rtol * eigvalsh(GJG)[..., -1]
    if allowed is not None:
        valid &= np.asarray(allowed, dtype=bool)
    # the inverse of an identity placeholder is exactly the identity
    S = inv_spd(np.where(valid[..., None, None], F_info, identity(m)))
    d = mv(S, mv(T(G), c))
    d *= valid[..., None]  # exact: d is finite (S = I where not valid)
    return d, S, valid


# --------------------------------------------------------------------------
# Step 3: input fusion by fast covariance intersection
# --------------------------------------------------------------------------
def input_fusion(adj, d, S, valid):
    """Eqs. (input_fusion) and (input_fusion_p), trace-weighted fast CI.

        w_j   = (1/tr S_j) / sum_n (1/tr S_n)        over valid j in N_i
        S_bar = (sum_j w_j S_j^-1)^-1
        d_bar = S_bar sum_j w_j S_j^-1 d_j

    adj: (..., R, S) 0/1 neighbourhood (self included); d, S, valid per sender.
    Returns (d_bar, S_bar, has) per receiver; has=False where no neighbour
    (self included) had a valid input estimate.
    """
    m = d.shape[-1]
    Si = inv_spd(S)
    inv_tr = Si[..., 0, 0] if m == 1 else 1.0 / np.einsum("...ii->...", S)  # 1 x 1: 1/tr S is S^-1
    W = adj * (inv_tr * valid)[..., None, :]  # 1/tr S_j of valid senders, else 0 (exact: tr S_j > 0)
    tot = row_sum(W)
    has = tot > 0
    Wn = W / np.where(has, tot, 1.0)[..., None]
    if m == 1:  # both one-entry sums in one: the second entry takes the place of the zero padding
        both = nbr_sum(Wn, np.concatenate([Si[..., 0], mv(Si, d)], axis=-1), 1)
        info, vec = both[..., :1, None], both[..., 1:]
    else:
        info, vec = nbr_sum_pair(Wn, Si, mv(Si, d))
    # Where no sender is valid, every weight is 0, so vec = 0, and the
    # identity placeholder's inverse is exactly I: d_bar = 0 and S_bar = I.
    S_bar = inv_spd(np.where(has[..., None, None], info, identity(m)))
    d_bar = mv(S_bar, vec)
    return d_bar, S_bar, has


def input_fusion_scalar(adj, d, S, valid):
    """``input_fusion`` of a scalar input (m = 1), sender after sender: the
    same operations on the same numbers as its sums (``linalg.nbr_sum``, each
    receiver's total built from zero adding the senders in order), so the
    same bits, in a few element-wise operations per sender instead of its
    stacked sums (faster on two senders: ``diskf-auto``'s fast CI of a
    model's own input and its neighbours' relayed one).
    adj: (..., R, S); d: (..., S, 1); S: (..., S, 1, 1); valid: (..., S).
    Raises numpy.linalg.LinAlgError where an S is not positive, as
    ``linalg.inv_spd``."""
    s = S[..., 0, 0]
    if s.size and np.fmin.reduce(s, axis=None) <= 0:  # fmin skips NaN (it propagates)
        raise not_pd()
    Si = 1.0 / s                                            # (..., S): 1 / tr S_j is S_j^-1
    W = adj * (Si * valid)[..., None, :]                    # (..., R, S)
    Wi, Wd = Si[..., None, :], (Si * d[..., 0])[..., None, :]
    tot = 0.0 + W[..., 0]
    for j in range(1, W.shape[-1]):
        tot = tot + W[..., j]
    has = tot > 0
    Wn = W / np.where(has, tot, 1.0)[..., None]
    info, vec = 0.0 + Wn[..., 0] * Wi[..., 0], 0.0 + Wn[..., 0] * Wd[..., 0]
    for j in range(1, W.shape[-1]):
        info, vec = info + Wn[..., j] * Wi[..., j], vec + Wn[..., j] * Wd[..., j]
    S_bar = 1.0 / np.where(has, info, 1.0)
    return (S_bar * vec)[..., None], S_bar[..., None, None], has


# --------------------------------------------------------------------------
# Step 4: state fusion by information-filter decomposition
# --------------------------------------------------------------------------
def information_contribution(x_pred, Yp, x_upd, Yu):
    """What a neighbour's local update added, in information form.

    dY_j = P~_j^-1 - P^_j^-1           (= H_j^T R_j^-1 H_j)
    dy_j = P~_j^-1 x~_j - P^_j^-1 x^_j (= H_j^T R_j^-1 y_j)
    The terms inside the sums of eqs. (state_fusion) and (state_fusion_p);
    ``Yp`` = P^_j^-1 and ``Yu`` = P~_j^-1, the information form of the
    message's two covariances.
    """
    return mv(Yu, x_upd) - mv(Yp, x_pred), sym_of_inverses(Yu - Yp)


def input_prediction(x_pred, G, d_bar, has=None):
    """Eq. (info_kf_prediction): x^* = A x_bar + G d_bar = x^ + G d_bar.

    The covariance is unchanged (P^* = P^), as the paper states. Where no fused
    input exists (``has`` False) the prediction is left without input;
    ``has=None`` when d_bar is already exactly zero there (as ``input_fusion``
    returns it): x^ + 0 is x^.
    """
    if has is None:
        return x_pred + mv(G, d_bar)
    return x_pred + np.where(has[..., None], mv(G, d_bar), 0.0)


def state_fusion(adj, x_star, Ystar, dy, dY):
    """Eqs. (state_fusion) and (state_fusion_p).

        P_bar^-1 = P^*^-1 + sum_j (P~_j^-1 - P^_j^-1)
        x_bar    = P_bar [ sum_j (P~_j^-1 x~_j - P^_j^-1 x^_j) + P^*^-1 x^* ]

    adj: (..., R, S); x_star and ``Ystar`` = P^*^-1 per receiver; dy, dY per
    sender (``information_contribution``).
    """
    sum_dY, sum_dy = nbr_sum_pair(adj, dY, dy)
    Y_bar = sym_of_inverses(Ystar + sum_dY)  # dY as information_contribution gives it
    P_bar = inv_spd(Y_bar)
    x_bar = mv(P_bar, sum_dy + mv(Ystar, x_star))
    return x_bar, P_bar


def compensation_gain(P_bar, form: str = "bounded", eps: float = 0.05, n_neighbours=None):
    """The gain M_i of eq. (compensation_state).

    ``paper``:      M_i = P_bar, as printed. Not scale-free: after a long
                    unobserved stretch P_bar grows without bound, the step
                    eps * P_bar * sum_j (x^_j - x^_i) overshoots the neighbours'
                    predictions it is meant to pull towards, and can diverge.
    ``bounded``:    M_i = P_bar (I + eps |N_i| P_bar)^-1  (our default), where
                    |N_i| counts the neighbours other than i. For small P_bar it
                    is the paper's gain; for any P_bar the step matrix
                    eps |N_i| M_i has eigenvalues lambda/(1+lambda) < 1 (lambda
                    those of eps |N_i| P_bar), so the correction moves x_bar at
                    most to the neighbours' mean prediction and never past it.
    ``normalized``: M_i = P_bar / (1 + ||P_bar||_F), the normalisation of
                    Olfati-Saber's Kalman-consensus filter (used by our KCF).
                    Stable, but it shrinks the gain even where P_bar is small.
    ``none``:       no compensation (ablation).
    """
    if form == "paper":
        return P_bar
    if form == "bounded":
        a = P_bar * (eps * np.asarray(n_neighbours, dtype=float))[..., None, None]
        for i in range(a.shape[-1]):  # I + k P_bar, the diagonal in place
            a[..., i, i] += 1.0
        return sym(solve(a, P_bar))
    if form == "normalized":
        nrm = np.linalg.norm(P_bar, axis=(-2, -1))
        return P_bar / (1.0 + nrm)[..., None, None]
    if form == "none":
        return np.zeros_like(P_bar)
    raise ValueError(f"unknown compensation form {form!r}")


def compensation_state(adj, x_bar, gain, x_pred_recv, x_pred_send, eps: float):
    """Eq. (compensation_state):

        x_bar_i += eps M_i sum_{j in N_i} (x^*_j - x^*_i)

    With one exchange round the neighbour's fused input d_bar_j is not known
    when i fuses, so every x^*_j is formed with i's own d_bar_i; the G d_bar_i
    terms cancel and the difference is that of the published predictions
    x^_j - x^_i. The pairwise difference is formed before the sum, so that
    identical predictions give an exact zero (all-to-all communication).
    """
    # (..., R, S, n); in the order of nbr_sum's output (the same numbers, faster)
    order = sum_order(x_pred_send, 1)
    diff = np.subtract(x_pred_send[..., None, :, :], x_pred_recv[..., :, None, :], order=order)
    total = pair_sum(adj, diff, order)  # sum_s adj[r, s] diff[r, s]
    return x_bar + eps * mv(gain, total)


# --------------------------------------------------------------------------
# Observation time window
# --------------------------------------------------------------------------
def window_allows(since: np.ndarray, window):
    """Observation time window: input estimation is allowed only when the gap
    since the last refresh (own measurement, or with reset a valid fused input
    from the neighbourhood) is at most ``window`` ticks. ``window=None``
    disables the window."""
    if window is None:
        return np.ones(np.shape(since), dtype=bool)
    return since <= window


def window_advance(since, has_measurement, fused_valid, reset: bool):
    """Counter update after a tick: zero after an own measurement; with
    ``reset``, also zero when input fusion had a valid input to fuse."""
    since = np.where(has_measurement, 0, since)
    if reset:
        since = np.where(fused_valid, 0, since)
    return since


# --------------------------------------------------------------------------
# Robust DISKF (diskf-r): our derivations, not the paper's equations
# --------------------------------------------------------------------------
def input_injection(x, P, G, d, S, has):
    """The prediction with an uncertain input (``diskf-r``, our derivation):

        x^* = x^ + G d,     P^* = P^ + G S G^T

    From x_k = A x_{k-1} + G d_{k-1} + w with an input estimate d of d_{k-1}
    whose error (covariance S) is independent of the state error: the error
    of A x_bar + G d is A e + G (d - d_{k-1}) - w, covariance
    A P_bar A^T + G S G^T + Q. The paper's eq. (info_kf_prediction) sets the
    G S G^T term to zero (P^* = P^), which is why its P understates the error
    wherever the input is uncertain. Where ``has`` is False no input is known
    and the prediction is left without one (x^ and P^ unchanged, exactly).
    x, P: (..., n), (..., n, n); d, S: (..., m), (..., m, m); has: (...).
    """
    has = np.asarray(has, dtype=bool)
    x_star = x + np.where(has[..., None], mv(G, d), 0.0)
    GSG = np.matmul(np.matmul(G, S), T(G))
    P_star = sym(P + np.where(has[..., None, None], GSG, 0.0))
    return x_star, P_star


def zero_dynamics(A, G, U, valid):
    """Phi = (I - G (G^T U G)^-1 G^T U) A: the state motion the unbiased
    input estimate cannot see (``diskf-r``, our derivation).

    With the stacked information U = H^T R^-1 H of the sensors that measured
    and rank(HG) = m (``valid``), the unbiased input estimate reads as input
    every output the input could have produced. The state motions it cannot
    tell from an input are those x_{k+1} = A x_k + G d_k with H x = 0 all
    along: d_k = -(G^T U G)^-1 G^T U A x_k (the least-squares input that
    cancels the output, weighted by R^-1), so x_{k+1} = Phi x_k, restricted
    to the largest Phi-invariant subspace inside ker U (= ker H). Depends
    only on ker H, which U carries: no H or R is needed. Where not ``valid``
    the identity stands in for (G^T U G)^-1 (the result is not used there).
    """
    m = G.shape[-1]
    GUG = congruence(G, U)
    inv = inv_spd(np.where(np.asarray(valid)[..., None, None], GUG, identity(m)))
    Pi = identity(G.shape[0]) - np.matmul(np.matmul(G, inv), np.matmul(T(G), U))
    return np.matmul(Pi, A)


def strongly_detectable(A, G, U, valid, rtol: float = 1e-8):
    """Whether the sensors with stacked information U make the input and the
    state strongly detectable over the step A (``diskf-r``, our derivation).

    Strong detectability (Hautus 1983): rank(HG) = m and every invariant zero
    of (A, G, H) lies strictly inside the unit circle. The invariant zeros
    are the unobservable modes of (Phi, H) with Phi of ``zero_dynamics``
    (the eigenvalues of Phi on its largest invariant subspace in ker H), so
    by the Hautus test: every eigenvalue lambda of Phi with |lambda| >= 1
    must have rank [Phi - lambda I; U] = n (ker U = ker H). Only then does
    the error of an unbiased input-and-state estimate decay, whatever the
    input; otherwise it grows like |lambda|^k while these sensors are all
    that is heard (docs/reproduction.md §8.1: an x-sensor alone, zero cos w + sin w > 1).
    The rank is judged by the smallest singular value against
    ``rtol`` x (||Phi|| + ||U|| + 1).
    Returns (...) bool; False where not ``valid``.
    """
    n = A.shape[-1]
    Phi = zero_dynamics(A, G, U, valid)
    lam = np.linalg.eigvals(Phi)                                   # (..., n)
    eye = identity(n)
    shifted = Phi[..., None, :, :] - lam[..., :, None, None] * eye  # (..., n, n, n)
    Ub = np.broadcast_to(U[..., None, :, :], shifted.shape).astype(complex)
    smin = np.linalg.svd(np.concatenate([shifted, Ub], axis=-2), compute_uv=False)[..., -1]
    scale = np.linalg.norm(Phi, axis=(-2, -1)) + np.linalg.norm(U, axis=(-2, -1)) + 1.0
    unobservable = smin <= rtol * scale[..., None]
    unstable = np.abs(lam) >= 1.0
    return np.asarray(valid, dtype=bool) & ~np.any(unobservable & unstable, axis=-1)


def innovation_scale(P, U, u, x):
    """Fading factor of the prior (P, x) from the neighbourhood's measurement
    information (U, u) (``diskf-r``, our derivation after Xia et al.'s
    adaptive fading Kalman filter):

        alpha = max(1, (r^T U^+ r - rank U) / tr(P U)),   r = u - U x

    With whitened sensors C = R^-1/2 H and innovation nu = R^-1/2 (y - H x),
    r = C^T nu, so r^T U^+ r = nu^T nu (nu lies in the range of C when the
    stacked rows are independent; otherwise its part outside is not seen),
    and tr(P U) = tr(C P C^T). A prior consistent with the measurement has
    E[nu nu^T] = C P C^T + I; the one-sample estimate nu nu^T - I of
    C P C^T, matched in trace, gives alpha. alpha = 1 (no change) wherever
    the innovation is no larger than the prior and R explain, and where
    nothing is measured (U = 0). Only H^T R^-1 H and H^T R^-1 y are used.
    Computed from the eigendecomposition of U (LAPACK, one matrix at a time)
    with element-wise sums over the n components only (no BLAS product, no
    ``einsum``), so a batch of one gives the bits of a batch of many.
    """
    n = U.shape[-1]
    r = u - mv(U, x)
    lam, V = np.linalg.eigh(U)
    kept = lam > lam[..., -1:] * (n * np.finfo(float).eps)  # the rank rule of numpy.linalg.matrix_rank
    proj = V[..., 0, :] * r[..., 0:1]                        # (V^T r)_i, summed over j one by one
    for j in range(1, n):
        proj = proj + V[..., j, :] * r[..., j:j + 1]
    terms = np.where(kept, proj * proj / np.where(kept, lam, 1.0), 0.0)
    nis, dof, tPU = terms[..., 0], kept[..., 0].astype(float), 0.0
    for i in range(1, n):
        nis, dof = nis + terms[..., i], dof + kept[..., i]
    for i in range(n):
        for j in range(n):
            tPU = tPU + P[..., i, j] * U[..., j, i]
    return np.where(tPU > 0, np.maximum(1.0, (nis - dof) / np.where(tPU > 0, tPU, 1.0)), 1.0)


def input_walk(A, C, S, Qd):
    """The joint prediction of (v_k, d_{k-1}), v_k = x_k - G d_{k-1}, under
    the persistent-input model (``diskf-r``, our derivation):

        d_{k-1} = d_{k-2} + eta,  eta ~ N(0, Qd)     (a random walk)
        v_k     = A x_{k-1} + w                      (= x^ of eq. info_kf_prediction0)

    With the fused (x_bar, d_bar) of tick k-1, joint error covariance
    [[P_bar, C], [C^T, S]], the errors of v = A x_bar and d = d_bar are
    A e_x - w and e_d - eta, so

        cov(v, d) = A C,      cov(d) = S + Qd

    and cov(v) = A P_bar A^T + Q is the message's P^ (computed there).
    A: (n, n); C: (..., n, m); S: (..., m, m); Qd: (m, m).
    Returns (A C, S + Qd).
    """
    return np.matmul(A, C), sym(S + Qd)


def replace_marginal(a, Paa, b, Pab, Pbb, a_new, Paa_new):
    """A joint Gaussian (a, b) whose marginal of a is replaced by
    (a_new, Paa_new), the conditional p(b | a) kept (``diskf-r``, our
    derivation). With K = Pab^T Paa^-1, b = b0 + K (a - a0) + e, e
    independent of a, cov(e) = Pbb - K Pab; so

        b'   = b + K (a_new - a)
        Pab' = Paa_new K^T
        Pbb' = Pbb - K Pab + K Paa_new K^T

    It serves three steps of ``diskf-r``: the measurement update of the
    input (a = x: the measurement is of x only, so p(d | x) is untouched and
    this *is* the joint Kalman update of (x, d), given the x update), and
    the neighbourhood's CI prior and relayed inputs replacing the agent's own
    marginals. a: (..., na), Paa: (..., na, na), b: (..., nb),
    Pab: (..., na, nb), Pbb: (..., nb, nb). Returns (b', Pab', Pbb').
    """
    K = T(solve(Paa, Pab))               # Pab^T Paa^-1 (Paa symmetric)
    b_new = b + mv(K, a_new - a)
    Pab_new = np.matmul(Paa_new, T(K))
    nb = Pab.shape[-1]
    both = np.matmul(K, np.concatenate([Pab, Pab_new], axis=-1))  # K Pab and K Pab' in one product
    Pbb_new = Pbb - both[..., :nb]
    Pbb_new += both[..., nb:]            # in place: (Pbb - K Pab) + K Pab', one array fewer
    Pbb_new = sym(Pbb_new)
    return b_new, Pab_new, Pbb_new


def input_to_state(v, Pv, B, d, S, G):
    """From (v, d) to (x, d), x = v + G d (``diskf-r``, our derivation):

        x = v + G d
        P = Pv + G B^T + B G^T + G S G^T
        C = cov(x, d) = B + G S

    B = cov(v, d). With B = 0 it is ``input_injection``'s prediction with an
    uncertain input (x^* = x^ + G d, P^* = P^ + G S G^T), the prediction of
    eq. (info_kf_prediction) with the input's covariance kept.
    v: (..., n), Pv: (..., n, n), B: (..., n, m), d: (..., m), S: (..., m, m).
    """
    GS = matmul_left(G, S)
    GB = matmul_left(G, T(B))
    x = v + mv(G, d)
    P = Pv + GB
    P += T(GB)                           # in place, the sum's order kept: ((Pv + G B^T) + B G^T) + G S G^T
    P += matmul_right(GS, T(G))
    P = sym(P)
    return x, P, B + GS


def free_input_gain(Y, G):
    """L = (G^T Y G)^-1 G^T Y, Y = P^^-1: the input that the unbiased
    (Gillijns-De Moor) update reads off its state estimate (``diskf-r``, our
    derivation). That update is the joint Kalman update of (x_k, d_{k-1})
    with no prior information on d_{k-1}: the prior x_k - G d ~ N(x^, P^)
    and the measurement of x only. Its joint information is
    [[Y + U, -Y G], [-G^T Y, G^T Y G]], so given x the input is
    d = L (x - x^), and cov(x error, d error) = P L^T with P the updated
    state covariance (``rkf.rkf_update``'s). Y: (..., n, n), G: (n, m).
    """
    YG = np.matmul(Y, G)
    return solve(congruence(G, Y), T(YG))
