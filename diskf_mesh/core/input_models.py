"""Input models: what an estimator assumes of the unknown input between ticks
(``diskf-r``, ``diskf-auto``; our derivations, not the paper's equations).

The paper's DISKF assumes nothing of the input (its unbiased estimate, eqs.
input_estimation .. input_estimation_mk2). A filter that predicts with an
input needs a model of how it moves from one tick to the next. Every model
here is the first-order recursion

    d_{k-1} = rho d_{k-2} + eta,    eta ~ N(0, q I)                  (IM)

with its scale q in the input's units squared per tick:

    walk            rho = 1: the random walk (a persistent input: steps,
                    ramps, slow sines, a fault that stays)
    mean-reverting  0 <= rho < 1: the input returns to zero; rho = 0 is a
                    zero-mean input of variance q, independent from tick to
                    tick (noise-like, switching, fast inputs)
    none            rho = 0, q = 0: no input at all

``input_scales`` gives the scales of a model and its sensors in input
units, from which the defaults follow (never a number fitted to a
scenario).

Every function is pure, with leading batch axes.
"""
from __future__ import annotations

import math
from functools import lru_cache

import numpy as np

from diskf_mesh.core.equations import replace_marginal
from diskf_mesh.core.linalg import T, cholesky, identity, inv_spd, matmul_left, matmul_shared, mv, nbr_sum, row_sum, solve, sym

INPUT_MODELS = ("walk", "mean-reverting", "none")


def model_rho(kind: str, rho: float) -> float:
    """rho of (IM) for a model kind: 1 for the walk, ``rho`` for the
    mean-reverting input, 0 for none."""
    return {"walk": 1.0, "mean-reverting": float(rho), "none": 0.0}[kind]


def input_predict(A, C, d, S, rho, q):
    """The joint prediction of (v_k, d_{k-1}), v_k = x_k - G d_{k-1}, under
    (IM): with the fused (x_bar, d_bar) of tick k-1, joint error covariance
    [[P_bar, C], [C^T, S]], the errors of v = A x_bar and of rho d_bar are
    A e_x - w and rho e_d - eta, so

        d'        = rho d
        cov(v, d) = rho A C
        cov(d)    = rho^2 S + q I

    and cov(v) = A P_bar A^T + Q (the message's P^). With rho = 1 it is
    ``equations.input_walk``. A: (n, n); C: (..., n, m); d: (..., m);
    S: (..., m, m); rho, q: floats or arrays broadcasting against the
    batch. Returns (rho d, rho A C, rho^2 S + q I).
    """
    rho = np.asarray(rho, dtype=float)
    q = np.asarray(q, dtype=float)
    m = S.shape[-1]
    r1, r2 = rho[..., None], rho[..., None, None]
    return d * r1, np.matmul(A, C) * r2, sym(S * (r2 * r2) + q[..., None, None] * np.eye(m))


def input_scales(Q, G, H, R, p=None):
    """(q_process, q_sensor): the process noise and the sensors' noise
    expressed in the input's units squared, per input component.

        q_process = tr(G^+ Q G^+T) / m
        q_sensor  = median over sensors i of tr(F_i^+ R_i F_i^+T) / m,
                    F_i = H_i G (sensors whose F_i = 0 are left out)

    q_process is the variance of the input that would explain the process
    noise; q_sensor that of the input one tick of one sensor resolves.
    Q: (n, n); G: (n, m); H: (N, p, n) and R: (N, p, p) (padded as
    ``model.Sensors``; ``p`` the true row counts). Where no sensor sees the
    input, q_sensor = q_process.
    """
    m = G.shape[-1]
    Gp = np.linalg.pinv(G)
    q_process = float(np.trace(Gp @ Q @ Gp.T)) / m
    vals = []
    for i in range(H.shape[0]):
        rows = H.shape[1] if p is None else int(p[i])
        F = H[i, :rows] @ G
        if np.abs(F).max() > 0:
            Fp = np.linalg.pinv(F)
            vals.append(float(np.trace(Fp @ R[i, :rows, :rows] @ Fp.T)) / m)
    q_sensor = float(np.median(vals)) if vals else q_process
    return max(q_process, 1e-300), max(q_sensor, 1e-300)


def default_scales(q_process: float, q_sensor: float):
    """(walk, prior): the scale-aware defaults of one input model
    (``diskf-r``'s ``input_walk`` and ``input_prior`` when not given): the
    geometric mean sqrt(q_process q_sensor) per tick, between an input as
    small as the process noise and one a single measurement resolves, and a
    prior 10^4 max(q_process, q_sensor) (an input up to a hundred times the
    larger noise scale)."""
    return float(np.sqrt(q_process * q_sensor)), 1e4 * max(q_process, q_sensor)


def information_energy(U, u, rtol: float = 1e-9):
    """(E, k): a measurement's energy y^T R^-1 y and its rank, from its
    information U = H^T R^-1 H, u = H^T R^-1 y alone: E = u^T U^+ u over the
    eigenvalues of U above ``rtol`` times its largest, k their count. Where
    H has full row rank (p <= n) that is y^T R^-1 y exactly; otherwise the
    energy and rank of the measurement's projection on what H sees (the
    same statistic for every model the likelihood compares). U: (..., n,
    n); u: (..., n). Returns (...,), (...,); 0 and 0 where U = 0."""
    lam, V = np.linalg.eigh(U)
    kept = lam > rtol * np.max(lam, axis=-1, keepdims=True)
    proj = np.einsum("...ji,...j->...i", V, u)
    E = np.sum(np.where(kept, proj * proj / np.where(kept, lam, 1.0), 0.0), axis=-1)
    return E, np.sum(kept, axis=-1).astype(float)


def information_loglik(x, P, Y, Ji, U, u, heavy=None, logdet_Y=None):
    """The log-likelihood of the neighbourhood's measurement given the prior
    N(x, P), up to a term the same for every prior (for the model weights
    of ``diskf-auto``), from the measurement information alone:

        log N(y; H x, H P H^T + R) = c(y, R) + x^T u - x^T U x / 2
                                     + g^T (P^-1 + U)^-1 g / 2 - log det(I + P U) / 2,
        g = u - U x

    (Woodbury: (H P H^T + R)^-1 = R^-1 - R^-1 H (P^-1 + U)^-1 H^T R^-1, and
    det(H P H^T + R) = det R det(I + P U)); c collects y^T R^-1 y and
    log det R. No H, R or y is needed, only U = H^T R^-1 H and
    u = H^T R^-1 y; 0 where nothing is measured (U = 0, u = 0).
    ``Y`` = P^-1 and ``Ji`` = (P^-1 + U)^-1 (``equations.information_pair``).

    ``heavy`` = (E_y, k, nu): the Student-t of nu degrees of freedom with
    the same scale instead, E_y = y^T R^-1 y and k the measurement's
    energy and rank (``information_energy``, summed over the senders):

        log t(y; H x, H P H^T + R, nu) = c(k, nu) - (nu + k)/2 log(1 + E / nu)
                                         - log det(I + P U) / 2,
        E = E_y - (2 x^T u - x^T U x + g^T (P^-1 + U)^-1 g)

    E the innovation's Mahalanobis energy; c(k, nu) collects log det R
    and the gamma functions, the same for every prior.

    ``logdet_Y``: log det Y where the caller has it (one Y for several
    (U, u)), the same bits as computed here.
    """
    Ux = mv(U, x)
    g = u - Ux
    quad = 2.0 * _dot(x, u) - _dot(x, Ux) + _dot(g, mv(Ji, g))
    # log det(I + P U) = log det(P (Y + U)) = -log det(Y) - log det(Ji)
    if logdet_Y is not None:
        logdet_Ji = np.linalg.slogdet(Ji)[1]
    elif Y.shape == Ji.shape:  # both in one call (each matrix's own, bit for bit)
        logdet_Y, logdet_Ji = np.linalg.slogdet(np.stack([Y, Ji]))[1]
    else:
        logdet_Y, logdet_Ji = np.linalg.slogdet(Y)[1], np.linalg.slogdet(Ji)[1]
    logdet = -(logdet_Y + logdet_Ji)
    if heavy is None:
        return 0.5 * (quad - logdet)
    energy, rank, nu = heavy
    E = np.maximum(energy - quad, 0.0)  # >= 0 but for round-off
    return -0.5 * ((nu + rank) * np.log1p(E / nu) + logdet)


def _dot(a, b):
    """Sum over the last axis, entry by entry in order (the same bits for
    any batch shape)."""
    out = a[..., 0] * b[..., 0]
    for i in range(1, a.shape[-1]):
        out = out + a[..., i] * b[..., i]
    return out


def model_weights(mu, Pi, prune=0.0):
    """IMM mixing (Blom and Bar-Shalom): the predicted model probabilities
    c_j = sum_i Pi_ij mu_i and the mixing weights w_ij = Pi_ij mu_i / c_j.
    mu: (..., M); Pi: (M, M) rows sum to 1. Returns (c, w) with w (..., M, M),
    w[..., i, j] the weight of model i in model j's mixed prior.

    ``prune``: weights below it are set to 0 and each column renormalised
    (c is unchanged). A model that holds almost no probability then enters
    no other model's prior, while its own prior is still drawn from the
    models that hold it (its weights there are large). Without it, a
    minority model whose covariance grew through a silence adds it to the
    dominant model's prior through a weight of 10^-5..10^-4
    (docs/estimators.md, "Which estimator"). A column always keeps its
    largest weight (at least 1/M)."""
    joint = mu[..., :, None] * Pi
    c = _ordered_sum(joint, -2)
    w = np.divide(joint, c[..., None, :], out=joint)  # in place: the same numbers, no second (..., M, M) array
    if prune > 0.0:
        np.putmask(w, w < prune, 0.0)
        np.divide(w, _ordered_sum(w, -2)[..., None, :], out=w)
    return c, w


def output_weights(mu, prune: float):
    """The weights of the bank's output mixture: the model probabilities
    mu (..., M) with those below ``prune`` set to 0, renormalised, as
    ``model_weights`` prunes the mixing weights. The output is then the
    mixture of the models that hold the probability: a model at 10^-5 whose
    covariance is a hundred to a thousand times the others' (a zero-mean
    input at the sensor's scale, in a run without input) would otherwise
    widen the output covariance in the directions the measurements pin
    down least (the acceleration of the constant-acceleration model), and
    the NEES falls under its band (docs/estimators.md). The largest
    probability (1/M or more) is always kept."""
    kept = np.where(mu < prune, 0.0, mu)
    return kept / sum_last(kept)[..., None]


def mix(w, z, Z, bounded=False):
    """Gaussian mixture moments: for every column j of the weights w
    (..., M, J), the mean sum_i w_ij z_i and covariance
    sum_i w_ij Z_i + sum_i w_ij (z_i - mean)(z_i - mean)^T (the models' own
    covariances, then the spread between their means). z: (..., M, k);
    Z: (..., M, k, k). Returns (..., J, k), (..., J, k, k). Each sum runs
    over the models i of nonzero weight, in order (the same bits for any
    batch shape): a weight pruned to 0 (``model_weights``) costs nothing.

    ``bounded``: the spread counts at most as much as the models' own
    covariances (it is scaled down until its trace is at most theirs). The
    IMM mixing of ``diskf-auto`` uses it: where nothing measures a direction
    the models' estimates drift apart unchecked, and a spread that enters
    every model's prior in full makes the next update's gain in that
    direction, and so the next spread, larger each tick (doubling about every
    tick in ``tests/test_auto.py``'s velocity-only agent, until the
    covariance is no longer positive definite). Where the models disagree by
    less than their own uncertainty the mixture is the exact one."""
    k = z.shape[-1]
    if w.size * k * k <= (ALL_TERMS_AT_ONCE if w.all() else ZEROS_AT_ONCE):
        # every term at once (model axis i before the column axis j), then summed over i in order
        # (``add.accumulate`` adds one term after the other, as the slots below do); the terms of weight 0
        # set to -0.0, which leaves every sum as the nonzero terms alone make it (``_left_out``)
        pad = None if w.all() else w == 0                                      # (..., M, J)
        mean = _ordered_sum(_left_out(w[..., :, :, None] * z[..., :, None, :], pad, 1), -3)  # (..., J, k)
        dz = z[..., :, None, :] - mean[..., None, :, :]                        # (..., M, J, k)
        wij = w[..., :, :, None, None]
        within = _ordered_sum(_left_out(Z[..., :, None, :, :] * wij, pad, 2), -4)  # (..., J, k, k)
        spread = _ordered_sum(_left_out(_outer(dz) * wij, pad, 2), -4)
    elif (padded := _padded(w, PADDED_TERMS)) is not None:  # a few columns: as many terms each
        batch, J = w.shape[:-2], w.shape[-1]
        rows, wk, pad = padded                                                     # (T, columns)
        zk = np.take(_over(z, batch, 2).reshape(-1, k), rows, axis=0)                             # (T, columns, k)
        Zk = np.take(_over(Z, batch, 3).reshape(-1, k, k), rows, axis=0)                          # (T, columns, k, k)
        mean = _sum_first(_left_out(wk[..., None] * zk, pad, 1))
        dz = zk - mean
        both = np.empty(Zk.shape[:2] + (2, k, k))                                  # within's terms, spread's
        wt = wk[..., None, None]
        np.multiply(Zk, wt, out=both[:, :, 0])
        np.multiply(_outer(dz), wt, out=both[:, :, 1])
        sums = _sum_first(_left_out(both, pad, 3))
        mean = mean.reshape(batch + (J, k))
        within, spread = (sums[:, i].reshape(batch + (J, k, k)) for i in (0, 1))
    else:  # the terms of nonzero weight only, slot after slot (``_terms``)
        batch, J = w.shape[:-2], w.shape[-1]
        rows, wk, ends, back = _terms(w)
        zk = np.take(_over(z, batch, 2).reshape(-1, k), rows, axis=0)                             # (terms, k)
        Zk = np.take(_over(Z, batch, 3).reshape(-1, k, k), rows, axis=0)                          # (terms, k, k)
        slots = list(zip([0] + ends[:-1], ends))                                   # slot t: terms start:end
        mean = wk[:ends[0], None] * zk[:ends[0]]
        for start, end in slots[1:]:  # slot t adds to the end - start columns that have a t-th term
            mean[:end - start] += wk[start:end, None] * zk[start:end]
        within = spread = None
        for start, end in slots:
            wt = wk[start:end, None, None]
            dz = zk[start:end] - mean[:end - start]
            a, b = Zk[start:end] * wt, _outer(dz) * wt
            if within is None:
                within, spread = a, b
            else:
                within[:end - start] += a
                spread[:end - start] += b
        if len(back) > ends[0]:  # columns of no nonzero weight (``model_weights`` leaves none): zeros
            pad = len(back) - ends[0]
            mean, within, spread = (np.concatenate([a, np.zeros((pad,) + a.shape[1:])]) for a in (mean, within, spread))
        mean = np.take(mean, back, axis=0).reshape(batch + (J, k))
        within, spread = (np.take(s, back, axis=0).reshape(batch + (J, k, k)) for s in (within, spread))
    if bounded:
        tw, ts = _trace(within), _trace(spread)
        over = ts > tw
        spread *= np.where(over, tw / np.where(over, ts, 1.0), 1.0)[..., None, None]
    return mean, sym(np.add(within, spread, out=within))  # in place: both are this call's own arrays


def mixture_mean(c, x):
    """sum_j c_j x_j over the models' axis, in order (the same bits for any
    batch shape). c: (..., M); x: (..., M, k). Returns (..., k)."""
    return _ordered_sum(c[..., :, None] * x, -2)


def _over(a, batch: tuple, core: int):
    """``a`` broadcast to ``batch`` + its ``core`` trailing axes (itself
    where it has that shape: ``np.broadcast_to`` costs a few us a call)."""
    shape = batch + a.shape[a.ndim - core:]
    return a if a.shape == shape else np.broadcast_to(a, shape)


def _outer(dz):
    """dz_i dz_j for every (i, j) of the last axis of dz (..., k): (..., k, k),
    each the one product dz[..., :, None] * dz[..., None, :] makes, from two
    contiguous (..., k k) operands (broadcasting k-long rows runs numpy's
    inner loop k entries at a time: 2-3x slower on a stack of a thousand
    4-vectors); a few vectors by broadcasting, in one call."""
    k = dz.shape[-1]
    if dz.size < OUTER_CONTIGUOUS:
        return dz[..., :, None] * dz[..., None, :]
    return dz.repeat(k, axis=-1).reshape(dz.shape + (k,)) * dz[..., None, :].repeat(k, axis=-2)


def _padded(w, most: int):
    """The nonzero weights of w (..., M, J), column by column, as many per
    column as the column with the most holds: (rows, wk, pad), each
    (T, columns), term t of every column (every (batch, j)) in row t, the
    models i in order. ``rows``: each term's model i as a row of the models
    flattened over the batch; ``wk`` its weight; ``pad`` where a column has
    fewer than T terms (its weight 0; None if none has), which ``mix`` sets
    to -0.0 (``_left_out``). None where w holds more than ``most`` weights
    or a column has no nonzero one (``mix`` then adds slot after slot,
    ``_terms``)."""
    batch, (M, J) = w.shape[:-2], w.shape[-2:]
    if w.size > most:
        return None
    wt = np.ascontiguousarray(w.swapaxes(-1, -2)).reshape(-1, M)       # column j of batch b: row b J + j
    f = np.flatnonzero(wt)                                              # column after column, i in order
    col, i = np.divmod(f, M)
    count = np.bincount(col, minlength=len(wt))
    if not count.all():
        return None
    T = int(count.max())
    t = np.arange(f.size) - (np.cumsum(count) - count)[col]             # the term's place in its column
    rows = np.zeros((T, len(wt)), dtype=np.intp)
    wk = np.zeros((T, len(wt)))
    rows[t, col] = (col // J) * M + i
    wk[t, col] = wt.ravel()[f]
    pad = None if f.size == T * len(wt) else np.arange(T)[:, None] >= count
    return rows, wk, pad


def _left_out(terms, pad, core: int):
    """``terms`` (T, columns, *core) with those of ``pad`` (T, columns; None
    for none) set to -0.0, in place: x + (-0.0) is x for every x, so
    ``_sum_first`` then adds the nonzero weights' terms alone, bit for bit
    (0 z would be +0.0 or -0.0, or NaN where z is not finite)."""
    if pad is not None:
        np.copyto(terms, -0.0, where=pad[(...,) + (None,) * core])
    return terms


def _sum_first(terms):
    """The sum over the first axis, term after term in order."""
    if len(terms) == 1:
        return terms[0]
    out = terms[0] + terms[1]
    for term in terms[2:]:
        out += term
    return out


def _terms(w):
    """The nonzero weights of w (..., M, J), column by column, laid out for
    ``mix``: (rows, wk, ends, back). The columns (every (batch, j)) are
    sorted by how many nonzero weights they hold, most first; term t of
    every column that has one forms slot t, the slots one after the other
    (``ends`` where each stops), each slot's columns in that order, so slot
    t's columns are the first ``end - start`` of slot 0's. ``rows``: each
    term's model i as a row of the models flattened over the batch; ``wk``
    its weight; ``back`` puts the sorted columns back in order."""
    batch, (M, J) = w.shape[:-2], w.shape[-2:]
    nonzero = np.ascontiguousarray((w != 0).swapaxes(-1, -2)).reshape(-1, M)  # column j of batch b: row b J + j
    count = nonzero.sum(axis=1)
    by = np.argsort(-count, kind="stable")
    count = count[by]
    f = np.flatnonzero(np.take(nonzero, by, axis=0))                    # column after column, i in order
    col, i = np.divmod(f, M)
    t = np.arange(f.size) - (np.cumsum(count) - count)[col]             # the term's slot
    order = np.argsort(t.astype(np.int16), kind="stable")              # slot after slot, columns in order
    back = np.empty_like(by)
    back[by] = np.arange(by.size)
    rows = ((by // J) * M)[col] + i
    rows = rows[order]
    # each term's weight: w[b, i, j] of its column b J + j (rows[...] // M = b) and model i
    weights = w.reshape(-1)[(rows // M) * (M * J) + (rows % M) * J + (by[col] % J)[order]]
    return rows, weights, np.cumsum(np.bincount(t)).tolist(), back


# the fewest entries of the vectors whose outer products ``_outer`` makes from contiguous operands (four calls
# instead of one: slower on an agent's 21 4-vectors, 1.7x faster on 200, 2.5x on 1,000)
OUTER_CONTIGUOUS = 256
# the most weights (batch x models x columns) for which ``mix`` lays out as many terms per column
# (``_padded``): an agent's 21 x 21; on larger batches the slots are faster
PADDED_TERMS = 1024
# the largest (batch x models x columns x k x k) for which ``mix`` makes every term at once (an
# agent's 21 x 21 models with k = 4 are 7,056) when no weight is 0, and when some are (an agent's output
# mixture of 21 models, k = 4: 336; its 21 x 21 mixing, 7,056 and more, is faster term by term)
ALL_TERMS_AT_ONCE = 1 << 16
ZEROS_AT_ONCE = 1 << 11


def _ordered_sum(terms, axis: int):
    """The sum of ``terms`` over ``axis``, added in order (first + second,
    then + third, ...): the same bits for any batch shape, unlike ``sum``'s
    pairwise summation. Small terms in one ``add.accumulate``, large ones
    added one after the other (the same adds, without the partial sums)."""
    if terms.shape[axis] < 3 or terms.size < 256 * terms.shape[axis]:
        return np.take(np.add.accumulate(terms, axis=axis), -1, axis=axis)
    terms = np.moveaxis(terms, axis, 0)
    out = terms[0] + terms[1]
    for term in terms[2:]:
        out += term
    return out


def _trace(M):
    """The trace of every (k, k) matrix of M (..., k, k), summed in order
    (the same bits for any batch shape)."""
    t = M[..., 0, 0]
    for i in range(1, M.shape[-1]):
        t = t + M[..., i, i]
    return t


def update_probabilities(c, loglik, floor: float):
    """mu_j proportional to c_j exp(loglik_j), normalised, then floored at
    ``floor`` and normalised again (no model is ever ruled out for good,
    and every mixture keeps a positive-definite input covariance).
    c, loglik: (..., M)."""
    top = loglik.max(axis=-1, keepdims=True)
    mu = c * np.exp(loglik - top)
    mu = mu / sum_last(mu)[..., None]
    mu = np.maximum(mu, floor)
    return mu / sum_last(mu)[..., None]


def level_posterior(loglik, c, nu, floor: float):
    """The noise levels' and the models' evidence together
    (``[estimator.auto] noise_span``): ``loglik`` (..., L, M) each model j's
    log-likelihood under each noise level l (``information_loglik`` at
    (U / r_l, u / r_l) with the level's -E / (2 r_l) - k log(r_l) / 2),
    ``c`` (..., M) the models' predicted probabilities, ``nu`` (..., L) the
    levels' predicted ones. With p_lj = nu_l exp(loglik_lj):

        model j's log-likelihood   log sum_l p_lj           (the level summed out)
        nu_l                       proportional to  sum_j c_j p_lj   (floored at ``floor``)
        resp_lj                    p_lj / sum_l p_lj         (model j's level, given the measurement)

    each up to a constant per row. Returns (loglik (..., M), nu (..., L),
    resp (..., L, M)); every sum in order (the same bits for any batch)."""
    top = loglik.max(axis=-1, keepdims=True).max(axis=-2, keepdims=True)
    p = nu[..., :, None] * np.exp(loglik - top)                            # (..., L, M)
    per_model = p[..., 0, :]
    for level in range(1, p.shape[-2]):
        per_model = per_model + p[..., level, :]
    tiny = np.finfo(float).tiny
    resp = p / np.maximum(per_model, tiny)[..., None, :]
    levels = sum_last(c[..., None, :] * p)
    levels = np.maximum(levels / sum_last(levels)[..., None], floor)
    return np.log(np.maximum(per_model, tiny)), levels / sum_last(levels)[..., None], resp


def sum_last(a):
    """The sum over the last axis, entry after entry in order: a few rows
    (an agent's) in one ``add.accumulate``, many one column at a time (the
    same adds)."""
    if a.size <= 32 * a.shape[-1]:
        return np.add.accumulate(a, axis=-1)[..., -1]
    out = a[..., 0]
    for i in range(1, a.shape[-1]):
        out = out + a[..., i]
    return out


def transition_matrix(M: int, switch: float, prior=None, down=None) -> np.ndarray:
    """The models' Markov chain: stay with probability 1 - ``switch``, move
    to another model j with switch prior_j / (1 - prior_i), the models'
    initial probabilities (``initial_probabilities``) renormalised over the
    others; a uniform prior (the default) moves to each with
    switch / (M - 1). ``down`` (M, M): moves added to those (``hand_down``),
    each row then renormalised."""
    if M == 1:
        return np.ones((1, 1))
    prior = np.full(M, 1.0 / M) if prior is None else np.asarray(prior, dtype=float)
    Pi = switch * prior[None, :] / (1.0 - prior[:, None])
    np.fill_diagonal(Pi, 1.0 - switch)
    if down is not None:
        Pi = Pi + down
        Pi /= Pi.sum(axis=1, keepdims=True)
    return Pi


def hand_down(a1, a2, q, rate: float, r=None):
    """(M, M): ``rate`` from each random walk of the bank (a1 = 1, a2 = 0)
    to each walk of a smaller scale q, 0 elsewhere; None where ``rate`` is 0
    or no walk has a smaller one (``transition_matrix``'s ``down``).

    Why: the mixing leaves out the weights under ``PRUNE`` of
    ``diskf-auto``, and the chain's own ``switch`` gives a move between two
    models about 10⁻⁴, so each walk otherwise learns a new level alone. A
    walk of small scale learns it slowly (its input moves little from tick
    to tick), and where measurements are few the bank holds the larger
    scales (noisier estimates), or a zero-mean model, for a hundred ticks
    after a step (docs/estimators.md, rare measurement). With ``rate``
    added, a walk of larger scale that holds the probability reaches the
    smaller ones' priors through the mixing, so they take up the level it
    learned; a walk of small scale that holds it gives the larger ones no
    more than the chain's switch. ``r`` (M,): each model's noise level
    (``at_noise_level``); a walk hands down to the walks of its own level
    only."""
    a1, a2, q = np.asarray(a1), np.asarray(a2), np.asarray(q)
    walk = (a1 == 1.0) & (a2 == 0.0)
    down = walk[:, None] & walk[None, :] & (q[None, :] < q[:, None])
    if r is not None:
        down &= np.asarray(r)[:, None] == np.asarray(r)[None, :]
    if rate <= 0.0 or not down.any():
        return None
    return rate * down


def joint(x, P, d, S, C):
    """(z, Z): the joint (x, d) mean and covariance [[P, C], [C^T, S]]."""
    z = np.concatenate([x, d], axis=-1)
    top = np.concatenate([P, C], axis=-1)
    bottom = np.concatenate([T(C), S], axis=-1)
    return z, np.concatenate([top, bottom], axis=-2)


def split(z, Z, n: int):
    """The inverse of ``joint``: (x, P, d, S, C)."""
    return z[..., :n], Z[..., :n, :n], z[..., n:], Z[..., n:, n:], Z[..., :n, n:]


def replace_input(v, Pv, e, S, B, d_new, S_new):
    """The joint Gaussian of (v, e), e = (d_{k-1}, d_{k-2}) (``split``'s
    parts: v, Pv, e, S and B = cov(v, e)), with the marginal of d_{k-1}
    replaced by (d_new, S_new), the conditional of (v, d_{k-2}) given it
    kept: ``equations.replace_marginal`` with a = d_{k-1} and b = (v, d_{k-2}).
    Returns (v, Pv, e, S, B) as given."""
    n, m = v.shape[-1], d_new.shape[-1]
    Bt = T(B)
    b = np.concatenate([v, e[..., m:]], axis=-1)
    Pab = np.concatenate([Bt[..., :m, :], S[..., :m, m:]], axis=-1)                  # (m, n + m)
    Pbb = np.concatenate([np.concatenate([Pv, B[..., :, m:]], axis=-1),
                          np.concatenate([Bt[..., m:, :], S[..., m:, m:]], axis=-1)], axis=-2)
    b, Pab, Pbb = replace_marginal(e[..., :m], S[..., :m, :m], b, Pab, Pbb, d_new, S_new)
    e = np.concatenate([d_new, b[..., n:]], axis=-1)
    S = np.concatenate([np.concatenate([S_new, Pab[..., n:]], axis=-1),
                        np.concatenate([T(Pab[..., n:]), Pbb[..., n:, n:]], axis=-1)], axis=-2)
    B = np.concatenate([T(Pab[..., :n]), Pbb[..., :n, n:]], axis=-1)
    return b[..., :n], Pbb[..., :n, :n], e, S, B


def affine_prior(x_from, P_from, x_to, P_to, v, Pv, B):
    """The affine map that takes the Gaussian (x_from, P_from) to
    (x_to, P_to), x -> x_to + L_to L_from^-1 (x - x_from) (L the Cholesky
    factors), applied to (v, Pv) with cross-covariance B to the input:
    (v', Pv', B'). ``diskf-auto`` moves each model's own prediction with the
    map that takes its agent's published prediction to the neighbourhood's
    CI prior: exact (the identity) where the two are equal (an isolated
    agent; all-to-all) and positive definite always."""
    if P_to.shape == P_from.shape:  # both factors in one call (each matrix's own, bit for bit)
        L_to, L_from = cholesky(np.stack([P_to, P_from]))
    else:
        L_to, L_from = cholesky(P_to), cholesky(P_from)
    Mt = np.matmul(L_to, solve(L_from, np.broadcast_to(identity(L_from.shape[-1]), L_from.shape)))
    Mt = Mt[..., None, :, :]  # over the models' axis
    v_new = x_to[..., None, :] + mv(Mt, v - x_from[..., None, :])
    return v_new, sym(matmul_shared(Mt, Pv, T(Mt))), matmul_shared(Mt, B)


REVERT = float(np.exp(-0.1))  # rho of the bank's mean-reverting models: a memory of 10 ticks

# (IM2): the oscillating models of ``diskf-auto``'s bank: periods in quarter octaves from 4 ticks (two samples
# a half-period) to 32, and the radius of a memory of 20 ticks (1 / (1 - r))
PERIODS = tuple(4.0 * 2.0 ** (k / 4) for k in range(13))
RADIUS = 0.95


def oscillating(period, radius=RADIUS):
    """(a1, a2) of the second-order input model

        d_{k-1} = a1 d_{k-2} + a2 d_{k-3} + eta,    eta ~ N(0, q I)      (IM2)

    for an input that oscillates with ``period`` ticks: a1 = 2 r cos(2 pi / period),
    a2 = -r^2, the poles r e^{+-2 pi i / period}. With eta = 0 and r = 1 the
    recursion is exactly a sinusoid of that period (any amplitude and phase);
    r < 1 and eta let its amplitude and phase drift, forgotten in about
    1 / (1 - r) ticks. (IM) is (IM2) with a1 = rho, a2 = 0."""
    period = np.asarray(period, dtype=float)
    return 2.0 * radius * np.cos(2.0 * np.pi / period), np.full(period.shape, -radius * radius)


def companion(a1, a2, m: int, per_channel: bool = False) -> np.ndarray:
    """The transition of (IM2) on the input pair e_{k-1} = (d_{k-1}, d_{k-2}):
    F = [[a1 I, a2 I], [I, 0]] (m x m blocks). a1, a2: (...,), one model
    for every channel; with ``per_channel`` (..., m), channel i's own,
    F = [[diag(a1), diag(a2)], [I, 0]]. Returns (..., 2m, 2m)."""
    a1, a2 = np.asarray(a1, dtype=float), np.asarray(a2, dtype=float)
    if not per_channel:
        a1, a2 = (np.broadcast_to(a[..., None], a.shape + (m,)) for a in (a1, a2))
    eye = np.eye(m)
    F = np.zeros(a1.shape[:-1] + (2 * m, 2 * m))
    F[..., :m, :m] = a1[..., :, None] * eye
    F[..., :m, m:] = a2[..., :, None] * eye
    F[..., m:, :m] = eye
    return F


def pair_predict(A, C, e, S, F, q, noise=None):
    """The joint prediction of (v_k, e_{k-1}), e = (d_{k-1}, d_{k-2}), under
    (IM2): with the fused (x_bar, e_bar) of tick k-1, joint error covariance
    [[P_bar, C], [C^T, S]], the errors of v = A x_bar and of F e_bar are
    A e_x - w and F e_e - (eta, 0), so

        e'        = F e
        cov(v, e) = A C F^T
        cov(e)    = F S F^T + [[q I, 0], [0, 0]]

    (``input_predict`` on the pair; with a2 = 0 its first block is
    ``input_predict``'s). A: (n, n); C: (..., n, 2m); e: (..., 2m);
    S: (..., 2m, 2m); F: (..., 2m, 2m) (``companion``); q: broadcasting
    against the batch. Returns (F e, A C F^T, F S F^T + q on the first block);
    with ``noise`` (..., 2m, 2m), F S F^T + noise instead (a model per
    channel, ``channel_models``; q is then not read).
    """
    q = np.asarray(q, dtype=float)
    m = e.shape[-1] // 2
    n = A.shape[-1]
    first = _first_block(m)  # eta drives d_{k-1} only
    # A C and F S stacked, then one product with F^T for both
    AC, FS = matmul_left(A, C), np.matmul(F, S)
    batch = AC.shape[:-2] if AC.shape[:-2] == FS.shape[:-2] else np.broadcast_shapes(AC.shape[:-2], FS.shape[:-2])
    stacked = np.concatenate([_over(AC, batch, 2), _over(FS, batch, 2)], axis=-2)
    both = np.matmul(stacked, np.ascontiguousarray(F.swapaxes(-1, -2)))  # F^T contiguous: numpy's faster layout
    return mv(F, e), both[..., :n, :], sym(both[..., n:, :] + (q[..., None, None] * first if noise is None else noise))


def channel_models(a1, a2, q, top):
    """(F, noise): the transition of the input pair and its noise for the
    filters of one bank per input channel (``diskf-auto``'s
    ``per_channel``): filter j of bank c holds channel c under model j of
    the bank (a1, a2, q: (M,)) and every other channel c' under model
    top_c', its bank's most probable one. top: (..., m) model indices.
    Returns F and noise, each (..., m M, 2m, 2m), filter j of bank c at
    c M + j: (IM2) channel by channel, F = [[diag(a1), diag(a2)], [I, 0]]
    and diag(q) on the first block (``companion`` and ``pair_predict``'s
    one model for every channel are the case of equal models)."""
    m, M = top.shape[-1], len(a1)
    f = np.arange(m * M)
    chan, model = f // M, f % M
    which = np.repeat(top[..., None, :], m * M, axis=-2)                # (..., m M, m) each channel's model
    which[..., f, chan] = model
    F = companion(a1[which], a2[which], m, per_channel=True)
    noise = np.zeros_like(F)
    noise[..., :m, :m] = q[which][..., :, None] * np.eye(m)
    return F, noise


def follow_informed(mu, loglik, blind: float):
    """Banks per input channel (``channel_models``) where this tick told
    some of them which model fits and not others: each bank whose models'
    log-likelihoods differ by less than ``blind`` (the measurements do not
    reach its channel: an agent that measures one axis of a two-axis
    target) takes the mean of the informed banks' probabilities, so a
    channel nobody measures is taken to be of the kind the measured ones
    are; left to its prior it would weigh the larger input models, whose
    covariances on an unmeasured axis grow without bound. mu, loglik:
    (..., B, M). Returns mu (the same array where no bank is blind or
    every bank is)."""
    spread = loglik.max(axis=-1) - loglik.min(axis=-1)                  # (..., B)
    blind_bank = spread < blind
    informed = ~blind_bank
    some = blind_bank.any(axis=-1) & informed.any(axis=-1)              # (...,)
    if not some.any():
        return mu
    count = np.maximum(sum_last(informed.astype(float)), 1.0)                # rows of no informed bank: unused
    shared = _ordered_sum(mu * informed[..., None], -2) / count[..., None]
    return np.where((blind_bank & some[..., None])[..., None], shared[..., None, :], mu)


@lru_cache(maxsize=None)
def _first_block(m: int) -> np.ndarray:
    """[[I, 0], [0, 0]] (m x m blocks), read-only: where (IM2)'s noise enters the pair."""
    block = np.zeros((2 * m, 2 * m))
    block[:m, :m] = np.eye(m)
    block.flags.writeable = False
    return block


def default_bank(q_process: float, q_sensor: float, none: bool = True, walk: bool = True, zero_mean: bool = True,
                 oscillating_inputs: bool = True):
    """The input models ``diskf-auto`` weighs, from the scales of
    ``input_scales``: (names, a1 (M,), a2 (M,), q (M,)) of (IM2).

    The scales run from lo = min(q_process, q_sensor) to
    hi = 100 max(q_process, q_sensor) (an input ten times the sensor's noise
    per tick): no input; random walks at lo, sqrt(lo hi) and hi (an input
    that stays, drifts, or jumps); a zero-mean input at q_sensor and at hi
    (noise-like or switching inputs, small and large); mean-reverting inputs
    (rho = ``REVERT``) at sqrt(lo hi) and hi; oscillating inputs of every
    period of ``PERIODS`` (``oscillating``), each with the noise q that gives
    it the stationary variance the mean-reverting model at sqrt(lo hi)
    has, sqrt(lo hi) / (1 - REVERT^2) (``stationary_gain``): every
    oscillating model expects an input of the same size, where one noise
    for all would let the slow ones (poles near 1) expect one 25 times
    larger than the fast ones."""
    lo, hi = min(q_process, q_sensor), 100.0 * max(q_process, q_sensor)
    mid = float(np.sqrt(lo * hi))
    bank = []
    if none:
        bank.append(("none", 0.0, 0.0, 0.0))
    if walk:
        bank += [("walk lo", 1.0, 0.0, lo), ("walk mid", 1.0, 0.0, mid), ("walk hi", 1.0, 0.0, hi)]
    if zero_mean:
        bank += [("zero-mean lo", 0.0, 0.0, q_sensor), ("zero-mean hi", 0.0, 0.0, hi)]
        bank += [("reverting mid", REVERT, 0.0, mid), ("reverting hi", REVERT, 0.0, hi)]
    if oscillating_inputs:
        size = mid / (1.0 - REVERT ** 2)  # the variance the mean-reverting model at mid expects of the input
        for name, period in zip(OSCILLATING, PERIODS):
            a1, a2 = oscillating(period)
            bank.append((name, float(a1), float(a2), size / stationary_gain(a1, a2)))
    names, a1, a2, q = zip(*bank)
    return names, np.array(a1), np.array(a2), np.array(q)


def stationary_gain(a1, a2) -> float:
    """The stationary variance of (IM2) per unit of its noise variance q:
    (1 - a2) / ((1 + a2) ((1 - a2)^2 - a1^2)) (a stable recursion)."""
    return float((1.0 - a2) / ((1.0 + a2) * ((1.0 - a2) ** 2 - a1 ** 2)))


def initial_probabilities(a2, r=None) -> np.ndarray:
    """The models' probabilities before any evidence: every first-order
    model (a2 = 0) one share, the oscillating models one share together
    (the period of an input that oscillates is one question, not thirteen),
    and the models at a noise level other than the stated one (``r`` != 1,
    ``at_noise_level``) one share together (whether the sensor is noisier
    than stated is one question too)."""
    osc = np.asarray(a2) != 0
    noisy = np.zeros(osc.shape, dtype=bool) if r is None else np.asarray(r) != 1.0
    w = np.where(osc, 1.0 / max(int(osc.sum()), 1), np.where(noisy, 1.0 / max(int(noisy.sum()), 1), 1.0))
    return w / w.sum()


NOISY = ("none", "walk lo", "walk mid")  # the models ``at_noise_level`` repeats


def at_noise_level(names, a1, a2, q, level: float):
    """The bank with its models of ``NOISY`` once more under measurement
    noise ``level`` R (``[estimator.auto] noise_level``): (names, a1, a2, q,
    r), r (M,) each model's noise level (1: as stated). Sensors noisier
    than stated are then a model the bank weighs by its evidence, beside an
    input: no input or a slow one under noisy sensors, against a fast
    zero-mean input under the stated noise, each with a filter of its own,
    so that the one whose predictions fit the measurements over the ticks
    wins (a learner of one scale scores the measurements against the
    prediction of models that took the noise for an input, or an input for
    the noise)."""
    extra = [i for i, name in enumerate(names) if name in NOISY]
    r = np.concatenate([np.ones(len(names)), np.full(len(extra), float(level))])
    return (tuple(names) + tuple(f"{names[i]} x{level:g}" for i in extra), np.r_[a1, a1[extra]],
            np.r_[a2, a2[extra]], np.r_[q, q[extra]], r)


OSCILLATING = tuple(f"oscillating {p:.3g}" for p in PERIODS)
# every model ``default_bank`` may hold, in its order: the slots of diskf-auto's model probabilities on the wire
BANK = ("none", "walk lo", "walk mid", "walk hi", "zero-mean lo", "zero-mean hi", "reverting mid",
        "reverting hi") + OSCILLATING


def pool_probabilities(adj, w, floor: float):
    """The neighbourhood's model probabilities: the normalised geometric
    mean of the fused senders' (the receiver's own included),

        mu_j  proportional to  exp( sum_s a_s log max(w_sj, floor) / sum_s a_s ),

    logarithmic opinion pooling (Genest and Zidek 1986), so a receiver
    whose own neighbourhood has not measured lately still weighs the input
    models by its neighbours' evidence. ``floor`` bounds what one sender's
    near-zero probability can take from a model. adj: (..., R, S) 0/1;
    w: (..., S, M). Returns (..., R, M). The sums over senders are
    ``linalg.nbr_sum``'s (the same bits for any batch shape)."""
    lm = nbr_sum(adj, np.log(np.maximum(w, floor)), 1) / row_sum(adj)[..., None]
    mu = np.exp(lm - lm.max(axis=-1, keepdims=True))
    return mu / sum_last(mu)[..., None]
