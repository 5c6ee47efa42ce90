"""Screening a neighbour's message before it is fused: what an agent can
check itself, against an insider whose messages pass every check of the
wire and the guard.

Every function is pure and works on numpy arrays with leading batch axes,
receivers R and senders S as ``Neighbourhood`` lays them out: a value per
sender (..., S, ...) and one per receiver (..., R, ...), a pair value
(..., R, S). Everything a pair computes is element-wise over the pairs (or
an order statistic over the senders), so a receiver's result does not depend
on how many other senders sit in the batch: the engine's dense layout, its
gathered one and an agent process give the same bits.

The tests, per tick, receiver i and linked sender j (not i itself):

* the floor (``below_floor``): no prediction is more certain than the
  model's own process noise. A consistent filter's P^ = A P A^T + Q is at
  least Q, so a message claiming less (a shrunk covariance) is not one the
  algorithm made. It bounds how much weight one message can take.
* the prediction gate (``gate_statistic``): the chi-square statistic of the
  difference between j's prediction x^_j and a reference, with both
  covariances, (x^_j - r)^T (P^_j + P^_i)^-1 (x^_j - r): the innovation gate
  of a Kalman filter (Bar-Shalom, Li and Kirubarajan, "Estimation with
  Applications to Tracking and Navigation", 2001, sec. 5.4.2) applied to a
  neighbour's estimate. Predictions do not hold the unknown input of the
  tick, so honest ones differ only by their errors. The same for the
  input estimates (d_j, S_j) where both sides have one.
* the reference (``reference``): the receiver's own prediction, or, where
  three or more linked senders (the receiver included) report, the
  coordinate-wise median of their predictions: a lone liar among three
  cannot move it outside the honest values (the trimmed and median
  combinations of Su and Shahrampour, "Finite-time guarantees for Byzantine-
  resilient distributed state estimation with noisy measurements", IEEE TAC
  2020, and the local filtering of W-MSR, LeBlanc, Zhang, Koutsoukos and
  Sundaram, IEEE JSAC 2013).
* the evidence (``accumulate``): per neighbour, the cumulative sum of
  (statistic - allowance), floored at 0 (Page's CUSUM, Biometrika 1954):
  a lie too small for one tick's gate adds up over ticks; a failed gate or
  floor sets it at once to ``SUSPECT``. A neighbour is fused while its
  evidence is below ``LIMIT`` and, once above, only after its honest
  messages have worked it back down (the allowance minus their statistic
  per tick): trust that drops on a failed test and recovers slowly. A
  message fused is fused whole (weight 1), so a run in which no test fails
  is the undefended run, bit for bit.

Where the information is large, an insider that stays below the gate every
tick can still move its receivers by up to about the gate's width in its
own and the receiver's standard deviations (docs/security.md).
"""
from __future__ import annotations


import numpy as np

from diskf_mesh.core.linalg import eigvalsh, inv_spd, mv, not_pd

GATE = 20.0       # the gate: a difference of more than 20 standard deviations (statistic 400)
ALLOWANCE = 3.0   # the evidence grows by what a statistic exceeds 3 standard deviations (9)
LIMIT = 10.0      # a neighbour is cut while the evidence against it is at least 10^2
RECOVERY = 100    # ticks of honest messages (statistic 0) that win back a neighbour cut by a failed test
RTOL = 1e-9       # the floor's tolerance, relative to the covariance's scale


def thresholds() -> tuple:
    """(gate, allowance, limit, suspect) of the statistics, in their units
    (squared standard deviations): a failed test sets the evidence to
    ``suspect``, ``RECOVERY`` allowances above the limit. The chi-square
    tail would put a 1e-6 gate at 27.6 for a 2-vector; the estimators'
    covariances are not that consistent after an unmodelled change (an
    input step: honest statistics up to 224 on Scenario 2, diskf-auto), so
    the one-tick gate is wide and a smaller lie is left to the evidence;
    the same in every dimension."""
    gate, allowance, limit = GATE * GATE, ALLOWANCE * ALLOWANCE, LIMIT * LIMIT
    return gate, allowance, limit, limit + RECOVERY * allowance


def reference(linked: np.ndarray, values: np.ndarray, own: np.ndarray, robust_from: int = 3) -> np.ndarray:
    """(..., R, m) what each receiver checks its senders against: the
    coordinate-wise median of the ``linked`` (..., R, S) senders' ``values``
    (..., S, m) where at least ``robust_from`` of them count (the receiver's
    own message among them), else the receiver's ``own`` (..., R, m). An
    order statistic: the same bits for any layout of the senders."""
    count = linked.sum(axis=-1)
    robust = count >= robust_from
    if not robust.any():
        return own
    ordered = np.where(linked[..., None], np.expand_dims(values, -3), np.inf)
    ordered.sort(axis=-2)
    lo = np.take_along_axis(ordered, ((count - 1) // 2)[..., None, None], axis=-2)[..., 0, :]
    hi = np.take_along_axis(ordered, (count // 2)[..., None, None], axis=-2)[..., 0, :]
    return np.where(robust[..., None], 0.5 * (lo + hi), own)


def gate_statistics(x_send, P_send, x_refs, P_ref) -> list:
    """[(P,) (x_s - r)^T (P_s + P_r)^-1 (x_s - r) for each r of ``x_refs``]
    for P pairs: x_send (P, m), P_send (P, m, m), each of x_refs (P, m),
    P_ref (P, m, m). For m of 1 and 2 the quadratic form is written out
    (d^T adj(M) d / det M), else one inverse per pair; a sum that is not
    positive definite raises LinAlgError, as ``inv_spd``."""
    M = P_send + P_ref
    m = M.shape[-1]
    if m <= 2:
        if not positive_definite(M).all():
            raise not_pd()
        a = M[..., 0, 0]
        if m == 1:
            return [(x_send - x_ref)[..., 0] ** 2 / a for x_ref in x_refs]
        b, c = M[..., 1, 0], M[..., 1, 1]
        det = a * c - b * b
        out = []
        for x_ref in x_refs:
            diff = x_send - x_ref
            d0, d1 = diff[..., 0], diff[..., 1]
            out.append((c * d0 * d0 - 2.0 * b * d0 * d1 + a * d1 * d1) / det)
        return out
    W = inv_spd(M)
    out = []
    for x_ref in x_refs:
        diff = x_send - x_ref
        Wd = mv(W, diff)
        q = diff[..., 0] * Wd[..., 0]
        for i in range(1, diff.shape[-1]):
            q = q + diff[..., i] * Wd[..., i]
        out.append(q)
    return out


def input_gate_statistics(d_send, S_send, d_refs, S_ref, valid) -> list:
    """``gate_statistics`` of the input estimates of P pairs, 0 where a pair
    is not ``valid`` (P,) (either side has no input estimate; its
    covariances may hold anything there). Where both sides are certain of
    their input in some direction (S_send + S_ref not positive definite: a
    bank whose output mixture holds only its zero-input model reports d = 0
    with S = 0), the statistic is the limit of the quadratic form as the
    covariance vanishes there: infinite if the two estimates differ in a
    direction of no variance, else the form over the other directions
    (``certain_statistic``)."""
    eye = np.eye(S_send.shape[-1])
    M = S_send + S_ref
    certain = valid & ~positive_definite(M)
    use = (valid & ~certain)[:, None, None]
    qs = gate_statistics(d_send, np.where(use, S_send, eye), d_refs, np.where(use, S_ref, 0.0))
    out = []
    for q, d_ref in zip(qs, d_refs):
        if certain.any():
            q = q.copy()
            q[certain] = certain_statistic(d_send[certain] - d_ref[certain], M[certain])
        out.append(np.where(valid, q, 0.0))
    return out


def certain_statistic(diff: np.ndarray, M: np.ndarray) -> np.ndarray:
    """diff^T M^+ diff (P,) for positive semidefinite M (P, m, m) that are
    singular, infinite where diff (P, m) has a component along a direction
    of M's null space (an eigenvalue at or below 1e-12 of its largest)
    beyond 1e-9 of its length."""
    w, V = np.linalg.eigh(M)
    c = np.einsum("...ji,...j->...i", V, diff)
    null = w <= 1e-12 * np.maximum(w[..., -1:], 0.0)
    scale = np.sqrt((diff * diff).sum(axis=-1, keepdims=True))
    outside = (null & (np.abs(c) > 1e-9 * scale)).any(axis=-1)
    q = np.where(null, 0.0, c * c / np.where(null, 1.0, w)).sum(axis=-1)
    return np.where(outside, np.inf, q)


def positive_definite(M: np.ndarray) -> np.ndarray:
    """(...,) whether each symmetric M (..., m, m) is positive definite, by
    the test ``gate_statistics`` raises on: Sylvester's leading minors for m
    of 1 and 2, else whether the Cholesky factor ``inv_spd`` takes exists
    (the lower triangle read)."""
    m = M.shape[-1]
    a = M[..., 0, 0]
    if m == 1:
        return a > 0
    if m == 2:
        return (a > 0) & (a * M[..., 1, 1] - M[..., 1, 0] * M[..., 1, 0] > 0)
    finite = np.isfinite(M).all(axis=(-2, -1))  # LAPACK lets a NaN through
    if _factors(M):  # every one at once; else which ones, one at a time
        return finite
    return finite & np.array([_factors(one) for one in M.reshape((-1, m, m))]).reshape(M.shape[:-2])


def _factors(M: np.ndarray) -> bool:
    """Whether ``np.linalg.cholesky`` factors M (every matrix of a stack)."""
    try:
        np.linalg.cholesky(M)
        return True
    except np.linalg.LinAlgError:
        return False


def linked_pairs(linked: np.ndarray) -> tuple:
    """(flat index of each linked pair into ``linked`` (..., R, S), of its
    sender into the (..., S) senders, of its receiver into the (..., R)
    receivers): flat indices, for ``take``."""
    R, S = linked.shape[-2:]
    flat = np.flatnonzero(linked)
    return flat, flat // (R * S) * S + flat % S, flat // S


def take(a: np.ndarray, index: np.ndarray, core_ndim: int) -> np.ndarray:
    """(P, *core) the entries ``index`` (flat, ``linked_pairs``) of ``a``
    (..., *core)."""
    core = a.shape[a.ndim - core_ndim:]
    return a.reshape((-1,) + core).take(index, axis=0)


def below_floor(P: np.ndarray, floor: np.ndarray) -> np.ndarray:
    """(...,) whether a covariance P (..., n, n) claims more certainty than
    ``floor`` (n, n) allows: P - floor has an eigenvalue below zero (beyond
    round-off)."""
    scale = np.abs(P).max(axis=(-2, -1))
    D = P - floor
    if D.shape[-1] == 2:  # the smaller eigenvalue alone, as ``eigvalsh`` computes it
        p, q, r = D[..., 0, 0], D[..., 1, 0], D[..., 1, 1]
        return 0.5 * (p + r) - np.hypot(0.5 * (p - r), q) < -RTOL * scale
    return eigvalsh(D)[..., 0] < -RTOL * scale


def nothing_grows(evidence, floor, q_own, qd_own, allowance: float) -> bool:
    """Whether a tick's screen changes nothing, decided from the statistics
    against the receivers' own predictions alone: no evidence yet, no
    prediction below the floor, and every statistic against the receiver's
    own prediction (state, and input where given) within the allowance. The
    statistic that counts is the smaller of that and the one against the
    median, so it too is within the allowance: no evidence grows, no gate
    fails, no sender is cut (``accumulate`` leaves zeros at zero)."""
    return (not floor.any() and not (q_own > allowance).any()
            and (qd_own is None or not (qd_own > allowance).any()) and not evidence.any())


def accumulate(evidence, statistic, failed, allowance: float, suspect: float):
    """Page's CUSUM per pair: max(0, evidence + statistic - allowance), or
    ``suspect`` where a test ``failed`` outright (if that is more)."""
    grown = np.maximum(evidence + statistic - allowance, 0.0)
    return np.where(failed, np.maximum(grown, suspect), grown)


def columns_of(evidence: np.ndarray, columns) -> np.ndarray:
    """(..., R, S) the evidence (..., R, N) of each sender slot, ``columns``
    (..., R, S) its place in the run (None: slot s is agent s)."""
    if columns is None:
        return evidence
    return np.take_along_axis(evidence, np.broadcast_to(columns, evidence.shape[:-1] + columns.shape[-1:]), axis=-1)


def put_columns(evidence: np.ndarray, columns, values: np.ndarray, linked: np.ndarray) -> np.ndarray:
    """``evidence`` (..., R, N) with each linked slot's value written to its
    sender's place (``columns`` as ``columns_of``)."""
    if columns is None:
        return np.where(linked, values, evidence)
    out = evidence.copy()
    idx = np.broadcast_to(columns, values.shape)
    old = np.take_along_axis(evidence, idx, axis=-1)
    np.put_along_axis(out, idx, np.where(linked, values, old), axis=-1)
    return out
