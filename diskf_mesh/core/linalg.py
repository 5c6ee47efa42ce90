"""Stacked linear algebra used by every filter.

All functions take arrays with any number of leading batch axes
(seeds x agents x ...) and operate on the trailing one or two axes.
Inverses of covariances go through Cholesky (or, for 1x1 and 2x2, its
closed form with the same positive-definiteness check), so a covariance that
is not positive definite raises instead of silently producing garbage.

A few matrices (an agent process works on a batch of one) take Python-float
paths (``small.few``): there numpy's per-call overhead (about 1 us per ufunc or
slice) is most of the time, not the arithmetic. They are used only for
element-wise arithmetic (+, -, *, /), never for a sum over an axis, a BLAS
product or an ``einsum``, whose kernels may round differently (pairwise sums,
fused multiply-adds). Every entry is then the same IEEE double operation on
the same operands in the same order as numpy's, so the bits are the same
(``tests/test_linalg_fast.py``).
"""
from __future__ import annotations

import math
from functools import lru_cache

import numpy as np

from diskf_mesh.core.small import (
    FEW, array, cholesky_2_few, few, inv_2_few, inv_spd_2_few, mv_2x2_few, mv_one, not_pd, sym_2_few)


def T(a: np.ndarray) -> np.ndarray:
    """Transpose of the trailing two axes. A single matrix (a model constant
    such as A or G) is copied contiguous: stacked products with a transposed
    view take numpy's slow strided path."""
    return np.ascontiguousarray(a.T) if a.ndim == 2 else a.swapaxes(-1, -2)


@lru_cache(maxsize=None)
def identity(n: int) -> np.ndarray:
    """A read-only n x n identity, made once (e.g. a placeholder in ``np.where``)."""
    eye = np.eye(n)
    eye.flags.writeable = False
    return eye


def sym(a: np.ndarray) -> np.ndarray:
    """Symmetric part, used after every covariance product to keep it symmetric."""
    if a.ndim > 2 and a.shape[-2:] == (2, 2) and few(a, 4):
        return sym_2_few(a)
    out = a + transposed(a)
    if out.dtype.kind != "f":
        return 0.5 * out
    out *= 0.5  # in place: the same numbers as 0.5 * (a + a^T)
    return out


def transposed(a: np.ndarray) -> np.ndarray:
    """A C-contiguous copy of a stack of matrices, each transposed. 2x2
    matrices are copied as rows of four entries with the two off-diagonal
    ones swapped: one gather, twice as fast as copying the transposed view."""
    if a.ndim > 2 and a.shape[-2:] == (2, 2) and a.flags.c_contiguous:
        return a.reshape(-1, 4).take(_TRANSPOSE_2, axis=1).reshape(a.shape)
    return np.ascontiguousarray(a.swapaxes(-1, -2))


_TRANSPOSE_2 = np.array([0, 2, 1, 3])


def mv(a: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Stacked matrix-vector product a @ v.

    With one or two columns it is written out (a[:, 0] v_0 + a[:, 1] v_1):
    on large stacks of tiny matrices that is several times faster than
    ``matmul``, and equal to it to round-off."""
    cols = a.shape[-1]
    if cols == 2 and v.size <= 2 * FEW and a.dtype.char == v.dtype.char == "d":  # a few: in Python floats
        if v.size == 2 and a.size == 2 * a.shape[-2] <= 4:
            return mv_one(a, v)  # one matrix, one vector (an agent's own), twice as fast
        if a.shape[:-1] == v.shape and v.shape[-1] == 2:
            return mv_2x2_few(a, v)  # one 2 x 2 matrix per vector (an agent's senders)
    if cols == 1:
        return a[..., 0] * v[..., 0, None]
    if cols == 2:
        out = a[..., 0] * v[..., 0, None]
        out += a[..., 1] * v[..., 1, None]
        return out
    return np.matmul(a, v[..., None])[..., 0]


def matmul_right(X: np.ndarray, B: np.ndarray) -> np.ndarray:
    """X @ B for a stack X (..., r, k) and one matrix B (k, c), as ONE BLAS
    product of the stacked rows (np.matmul calls BLAS once per matrix of the
    stack: on hundreds of 2x2 matrices that call is most of the time). Every
    entry is the same k-term dot product in the same kernel, so the result
    equals np.matmul(X, B) bit for bit (``tests/test_linalg_fast.py``)."""
    X = np.ascontiguousarray(X)
    return (X.reshape(-1, X.shape[-1]) @ B).reshape(X.shape[:-1] + B.shape[-1:])


def matmul_left(A: np.ndarray, X: np.ndarray) -> np.ndarray:
    """A @ X for one matrix A (r, k) and a stack X (..., k, c), as ONE BLAS
    product: (X^T A^T)^T, every entry the same k-term dot product as
    np.matmul(A, X)'s, bit for bit (``tests/test_linalg_fast.py``). A few
    matrices take np.matmul itself (faster there), and so do products with
    a single row or column (np.matmul runs those as matrix-vector products,
    whose BLAS kernel rounds differently)."""
    if A.ndim != 2 or 1 in A.shape or X.shape[-1] == 1 or X.size <= FEW * X.shape[-1] * X.shape[-2]:
        return np.matmul(A, X)
    return T(matmul_right(transposed(X), T(A)))


def matmul_shared(L: np.ndarray, X: np.ndarray, R: np.ndarray | None = None) -> np.ndarray:
    """L @ X (and then @ R) for a stack X (..., M, k, c) whose M matrices
    share their factors L (..., 1, r, k) (and R (..., 1, c, s)): one BLAS
    product per L for all M of them ([X_1 ... X_M] side by side, then
    stacked), bit for bit np.matmul's (``tests/test_linalg_fast.py``;
    products with a single row or column are np.matmul's, as in
    ``matmul_left``, and one agent's, faster in one call)."""
    batch, (M, k, c) = X.shape[:-3], X.shape[-3:]
    r = L.shape[-2]
    if 1 in (r, k, c) or (R is not None and R.shape[-1] == 1) or math.prod(batch) == 1:  # one agent: one call
        LX = np.matmul(L, X)
        return LX if R is None else np.matmul(LX, R)
    side = np.ascontiguousarray(np.swapaxes(X, -3, -2)).reshape(batch + (k, M * c))  # (..., k, M c)
    LX = np.matmul(L[..., 0, :, :], side).reshape(batch + (r, M, c))
    if R is None:
        return np.swapaxes(LX, -3, -2)
    stacked = np.ascontiguousarray(np.swapaxes(LX, -3, -2)).reshape(batch + (M * r, c))  # (..., M r, c)
    return np.matmul(stacked, R[..., 0, :, :]).reshape(batch + (M, r, R.shape[-1]))


def congruence_const(A: np.ndarray, P: np.ndarray) -> np.ndarray:
    """A @ P @ A^T for one (n, n) matrix A and a stack P, equal to
    np.matmul(np.matmul(A, P), A.T) bit for bit, in two BLAS products:
    (A P)^T = P^T A^T, then A P A^T = (A P) A^T. A few matrices take that
    reference form itself: two stacked products, three times faster there."""
    AT = T(A)
    if P.size <= FEW * P.shape[-1] ** 2:
        return np.matmul(np.matmul(A, P), AT)
    APt = matmul_right(transposed(P), AT)
    return matmul_right(transposed(APt), AT)


def inv_spd(a: np.ndarray) -> np.ndarray:
    """Inverse of a stack of symmetric positive-definite matrices via Cholesky.

    A = L L^T  =>  A^-1 = L^-T L^-1, symmetric by construction.
    Raises numpy.linalg.LinAlgError if any matrix is not positive definite.
    Like the Cholesky factorisation, only the lower triangle is read.
    1x1 and 2x2 stacks take a closed form (same result to round-off; on 240
    2x2 matrices about 9 us instead of 90 us).
    """
    n = a.shape[-1]
    if n == 1:
        return _inv_spd_1(a)
    if n == 2:
        return _inv_spd_2(a)
    return inv_spd_cholesky(a)


def factorable(a: np.ndarray) -> np.ndarray:
    """(...,) True where a stack's matrix has a Cholesky factor, each matrix
    tried alone as ``inv_spd`` tries it (on a stack it raises if any one
    fails), so the answer for a matrix never depends on its batch."""
    n = a.shape[-1]
    flat = a.reshape(-1, n, n)
    ok = np.ones(len(flat), dtype=bool)
    for i in range(len(flat)):
        try:
            inv_spd(flat[i:i + 1])
        except np.linalg.LinAlgError:
            ok[i] = False
    return ok.reshape(a.shape[:-2])


def psd_part(a: np.ndarray) -> np.ndarray:
    """The nearest positive-semidefinite matrix to each symmetric matrix of
    a stack in the Frobenius norm (Higham 1988): V max(L, 0) V^T from its
    eigendecomposition V L V^T."""
    lam, V = np.linalg.eigh(a)
    return sym(np.matmul(V * np.maximum(lam, 0.0)[..., None, :], T(V)))


def inv_spd_cholesky(a: np.ndarray) -> np.ndarray:
    """The general path of ``inv_spd``, for any size: Cholesky, then L^-T L^-1."""
    L = np.linalg.cholesky(a)
    eye = np.broadcast_to(np.eye(a.shape[-1]), a.shape)
    Li = np.linalg.solve(L, eye)
    return np.matmul(T(Li), Li)


def _inv_spd_1(a: np.ndarray) -> np.ndarray:
    if few(a, 1):
        values = a.ravel().tolist()
        for v in values:
            if v <= 0:  # False for NaN: it propagates, as below
                raise not_pd()
        return array([1.0 / v for v in values], a.shape)
    # fmin skips NaN: a NaN propagates, as through numpy's Cholesky
    if a.size and np.fmin.reduce(a, axis=None) <= 0:
        raise not_pd()
    return 1.0 / a


def _inv_spd_2(a: np.ndarray) -> np.ndarray:
    """[[p, q], [q, r]]^-1 = [[r, -q], [-q, p]] / (p r - q^2), q from the lower
    triangle; positive definite iff p > 0 and p r - q^2 > 0 (Sylvester).
    The output is exactly symmetric."""
    if few(a, 4):
        return inv_spd_2_few(a)
    flat = a.reshape(-1, 4)
    p, q, r = flat[:, 0], flat[:, 2], flat[:, 3]
    det = p * r - q * q
    if flat.size and np.fmin.reduce(np.fmin(p, det), axis=None) <= 0:  # fmin skips NaN (it propagates)
        raise not_pd()
    out = np.empty(flat.shape)  # column by column: long loops, faster than broadcasting over rows of 4
    np.divide(r, det, out=out[:, 0])
    np.divide(q, np.negative(det), out=out[:, 1])
    out[:, 2] = out[:, 1]
    np.divide(p, det, out=out[:, 3])
    return out.reshape(a.shape)


def cholesky(a: np.ndarray) -> np.ndarray:
    """Stacked ``np.linalg.cholesky(a)`` (the lower factor L, A = L L^T, only
    the lower triangle read), 1x1 and 2x2 in closed form with LAPACK's own
    operations (its unblocked ``potf2``: l00 = sqrt(a00), l10 = a10 (1 / l00),
    l11 = sqrt(a11 - l10 l10)), so the same bits (``tests/test_linalg_fast.py``)
    without its per-matrix call. Raises numpy.linalg.LinAlgError where a
    pivot is not positive (a NaN propagates, as there)."""
    n = a.shape[-1]
    if n == 1:
        if a.size and np.fmin.reduce(a, axis=None) <= 0:  # fmin skips NaN (it propagates)
            raise not_pd()
        return np.sqrt(a)
    if n != 2:
        return np.linalg.cholesky(a)
    if few(a, 4):
        return cholesky_2_few(a)
    flat = a.reshape(-1, 4)
    if flat.size and np.fmin.reduce(flat[:, 0], axis=None) <= 0:  # fmin skips NaN (it propagates)
        raise not_pd()
    out = np.zeros(flat.shape)  # column by column, as ``_inv_spd_2``
    l00 = np.sqrt(flat[:, 0], out=out[:, 0])
    l10 = np.multiply(flat[:, 2], 1.0 / l00, out=out[:, 2])
    pivot = flat[:, 3] - l10 * l10
    if flat.size and np.fmin.reduce(pivot, axis=None) <= 0:
        raise not_pd()
    np.sqrt(pivot, out=out[:, 3])
    return out.reshape(a.shape)


def inv_spd_each(*stacks: np.ndarray) -> tuple:
    """``inv_spd`` of several stacks of n x n matrices (any leading shapes)
    in one call: the fixed cost of a stacked inverse is paid once. Each
    matrix's inverse is the one ``inv_spd`` gives it alone, bit for bit."""
    n = stacks[0].shape[-1]
    if len(stacks) == 1 or (n <= 2 and few(stacks[0], n * n)):  # the Python-float path pays per matrix
        return tuple(inv_spd(s) for s in stacks)
    inv = inv_spd(np.concatenate([s.reshape(-1, n, n) for s in stacks]))
    out, start = [], 0
    for s in stacks:
        count = s.size // (n * n)
        out.append(inv[start:start + count].reshape(s.shape))
        start += count
    return tuple(out)


def solve(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Stacked ``np.linalg.solve(a, b)`` for a (..., n, n), b (..., n, k).

    1x1 and 2x2 systems go through the closed-form inverse (adjugate over
    determinant; LAPACK's per-matrix overhead dominates such stacks). Like
    LAPACK, an exactly singular matrix raises numpy.linalg.LinAlgError."""
    n = a.shape[-1]
    if n > 2 or b.ndim < 2 or a.shape[-2] != n or b.shape[-2] != n:
        return np.linalg.solve(a, b)
    if n == 1:
        if (a == 0).any():
            raise np.linalg.LinAlgError("Singular matrix")
        return b / a
    if few(a, 4):
        return np.matmul(inv_2_few(a), b)
    flat = a.reshape(-1, 4)
    det = flat[:, 0] * flat[:, 3] - flat[:, 1] * flat[:, 2]
    if not det.all():
        raise np.linalg.LinAlgError("Singular matrix")
    inv = np.empty(flat.shape)  # [[d, -b], [-c, a]] / det, column by column
    minus_det = np.negative(det)
    np.divide(flat[:, 3], det, out=inv[:, 0])
    np.divide(flat[:, 1], minus_det, out=inv[:, 1])
    np.divide(flat[:, 2], minus_det, out=inv[:, 2])
    np.divide(flat[:, 0], det, out=inv[:, 3])
    return np.matmul(inv.reshape(a.shape), b)


def congruence(G: np.ndarray, X: np.ndarray) -> np.ndarray:
    """sym(G^T X G) for one (n, m) matrix G and a stack X (..., n, n).

    With m = 1 it is the single number sum_ij X_ij g_i g_j, one ``einsum``
    instead of two broadcast matrix products."""
    if G.shape[-1] == 1:
        g = G[:, 0]
        return np.einsum("...ij,ij->...", X, g[:, None] * g)[..., None, None]  # g g^T, as np.outer
    return sym(np.matmul(np.matmul(T(G), X), G))


def congruence_each(G: np.ndarray, *Xs: np.ndarray) -> tuple:
    """``congruence(G, X)`` for each X (stacks of one shape), bit for bit;
    with m = 1 in one ``einsum`` over the stacked Xs."""
    if G.shape[-1] != 1 or len(Xs) == 1:
        return tuple(congruence(G, X) for X in Xs)
    g = G[:, 0]
    stacked = np.array(Xs)  # as np.stack (the same array), faster on small stacks
    both = np.einsum("...ij,ij->...", stacked, g[:, None] * g)[..., None, None]
    return tuple(both)


def sym_of_inverses(a: np.ndarray) -> np.ndarray:
    """``sym(a)`` for a sum or difference of ``inv_spd`` outputs (and of
    such sums). For n <= 2 the closed-form inverses are exactly symmetric, so
    ``a`` already is and is returned as it is (the same bits ``sym`` gives)."""
    return a if a.shape[-1] <= 2 else sym(a)


def eigvalsh(a: np.ndarray) -> np.ndarray:
    """Stacked ``np.linalg.eigvalsh(a)`` (ascending, lower triangle), closed
    form for 1x1 and 2x2."""
    n = a.shape[-1]
    if n == 1:
        return a[..., 0].copy()
    if n == 2:
        p, q, r = a[..., 0, 0], a[..., 1, 0], a[..., 1, 1]
        mid, half = 0.5 * (p + r), 0.5 * (p - r)
        rad = np.hypot(half, q)
        return np.stack([mid - rad, mid + rad], axis=-1)
    return np.linalg.eigvalsh(a)


def is_spd(a: np.ndarray, rtol: float = 1e-9) -> np.ndarray:
    """Boolean mask over the batch: finite, symmetric and positive definite."""
    a = np.asarray(a, dtype=float)
    finite = np.isfinite(a).all(axis=(-1, -2))
    safe = np.where(finite[..., None, None], a, 0.0)
    scale = np.maximum(np.abs(safe).max(axis=(-1, -2)), 1e-300)
    symmetric = np.abs(safe - T(safe)).max(axis=(-1, -2)) <= rtol * scale
    eig_min = np.linalg.eigvalsh(sym(safe))[..., 0]
    return finite & symmetric & (eig_min > rtol * scale)


def nbr_sum(adj: np.ndarray, x: np.ndarray, core_ndim: int) -> np.ndarray:
    """Sum over senders weighted by an adjacency (or weight) matrix.

    adj: (..., R, S) weights of sender s at receiver r.
    x:   (..., S, *core) one value per sender, ``core_ndim`` trailing axes.
    returns (..., R, *core) = sum_s adj[r, s] * x[s].

    Deliberately not BLAS: ``einsum`` without ``optimize`` runs numpy's own
    sum-of-products loop, which reduces every receiver row with the same
    kernel over the same strides, in sender order, so receivers that hear the
    same senders get bit-identical results (a BLAS product may block rows
    differently). This is what makes the state compensation exactly zero
    under all-to-all communication. It equals broadcast-multiply-then-sum
    ``(adj[..., None] * x[..., None, :, :]).sum(-2)`` bit for bit
    (``tests/test_linalg_fast.py``), at a fraction of its temporaries.
    """
    if math.prod(x.shape[x.ndim - core_ndim:]) == 1:
        return nbr_sum(adj, _second_entry(x), core_ndim)[..., :1]
    x = np.ascontiguousarray(x)  # einsum's loop order, and so the bits, follow the layout
    core = "ijkl"[:core_ndim]
    return np.einsum(f"...rs,...s{core}->...r{core}", adj, x, optimize=False, order=sum_order(x, core_ndim))


def pair_sum(adj: np.ndarray, diff: np.ndarray, order: str = "C") -> np.ndarray:
    """(..., R, n): sum_s adj[r, s] diff[r, s] for a value per (receiver,
    sender) pair, diff (..., R, S, n), sender by sender as ``nbr_sum``
    (``order``: of the output, as ``sum_order`` picks it)."""
    if diff.shape[-1] == 1:
        return pair_sum(adj, _second_entry(diff), order)[..., :1]
    return np.einsum("...rs,...rsn->...rn", adj, diff, optimize=False, order=order)


def _second_entry(x: np.ndarray) -> np.ndarray:
    """``x`` with a zero second entry on its last axis. With a one-entry core
    the sender sum is einsum's inner loop, which numpy unrolls into partial
    sums: its rounding would depend on how many senders there are, zero
    weights included (the engine sums over all N agents, an agent over its J
    neighbours). With two entries the inner loop runs over the core, and each
    entry is summed sender by sender, as with larger cores."""
    return np.concatenate([x, np.zeros_like(x)], axis=-1)


def row_sum(w: np.ndarray) -> np.ndarray:
    """(..., R) the sum of each row of weights (..., R, S), sender by sender
    (as ``nbr_sum``), whatever the number of zero weights in it: the
    weights times the rows (1, 0), made once per sender count (a one-entry
    core as ``_second_entry`` pads it)."""
    return nbr_sum(w, _one_zero(w.shape[-1]), 1)[..., 0]


@lru_cache(maxsize=None)
def _one_zero(senders: int) -> np.ndarray:
    """(senders, 2) rows (1, 0), read-only (``row_sum``)."""
    rows = np.zeros((senders, 2))
    rows[:, 0] = 1.0
    rows.flags.writeable = False
    return rows


def sum_order(x: np.ndarray, core_ndim: int) -> str:
    """Memory order of a neighbour sum's output that makes ``einsum`` fast.

    ``einsum`` loops innermost over the output's fastest axis. In C order that
    is a tiny core axis (2 for a 2-vector), and with many small stacks most of
    the time goes into the loop overhead. For a big batch of small
    neighbourhoods (the paper's four agents over many seeds) Fortran order
    puts the batch innermost: 2-3x faster. Either way every output entry is
    accumulated over the senders one by one in sender order (the inner loop
    runs over independent entries), so both orders give the same bits
    (``tests/test_linalg_fast.py``). A one-entry core never reaches
    ``einsum`` (``_second_entry``); it keeps C order here."""
    core = math.prod(x.shape[x.ndim - core_ndim:])
    senders = x.shape[x.ndim - core_ndim - 1]
    return "F" if core > 1 and senders <= 16 and x.size >= 8 * senders * core else "C"


def nbr_sum_pair(adj: np.ndarray, M: np.ndarray, v: np.ndarray):
    """(nbr_sum(adj, M, 2), nbr_sum(adj, v, 1)) for M (..., S, n, n) and
    v (..., S, n), in one pass over the senders (bit for bit the same sums:
    each entry is reduced over the senders in the same order). Pays for
    n >= 2; with 1x1 matrices two ``nbr_sum`` calls are faster."""
    both = nbr_sum(adj, np.concatenate([M, v[..., None]], axis=-1), 2)
    return both[..., :-1], both[..., -1]
