"""Stacked linear algebra used by every filter.

All functions take arrays with any number of leading batch axes
(seeds x agents x ...) and operate on the trailing one or two axes.
Inverses of covariances go through Cholesky (or, for 1x1 and 2x2, its
closed form with the same positive-definiteness check), so a covariance that
is not positive definite raises instead of silently producing garbage.
"""
from __future__ import annotations

import numpy as np


def T(a: np.ndarray) -> np.ndarray:
    """Transpose of the trailing two axes. A single matrix (a model constant
    such as A or G) is copied contiguous: stacked products with a transposed
    view take numpy's slow strided path."""
    return np.ascontiguousarray(a.T) if a.ndim == 2 else a.swapaxes(-1, -2)


def sym(a: np.ndarray) -> np.ndarray:
    """Symmetric part, used after every covariance product to keep it symmetric."""
    return 0.5 * (a + a.swapaxes(-1, -2))


def mv(a: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Stacked matrix-vector product a @ v.

    With one or two columns it is written out (a[:, 0] v_0 + a[:, 1] v_1):
    on large stacks of tiny matrices that is several times faster than
    ``matmul``, and equal to it to round-off."""
    cols = a.shape[-1]
    if cols == 1:
        return a[..., 0] * v[..., 0, None]
    if cols == 2:
        return a[..., 0] * v[..., 0, None] + a[..., 1] * v[..., 1, None]
    return np.matmul(a, v[..., None])[..., 0]


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


def inv_spd_cholesky(a: np.ndarray) -> np.ndarray:
    """The general path of ``inv_spd``, for any size: Cholesky, then L^-T L^-1."""
    L = np.linalg.cholesky(a)
    eye = np.broadcast_to(np.eye(a.shape[-1]), a.shape)
    Li = np.linalg.solve(L, eye)
    return np.matmul(T(Li), Li)


def _not_pd() -> np.linalg.LinAlgError:
    return np.linalg.LinAlgError("Matrix is not positive definite")


def _inv_spd_1(a: np.ndarray) -> np.ndarray:
    if (a <= 0).any():  # NaN propagates, as through numpy's Cholesky
        raise _not_pd()
    return 1.0 / a


def _inv_spd_2(a: np.ndarray) -> np.ndarray:
    """[[p, q], [q, r]]^-1 = [[r, -q], [-q, p]] / (p r - q^2), q from the lower
    triangle; positive definite iff p > 0 and p r - q^2 > 0 (Sylvester)."""
    flat = a.reshape(-1, 4)
    p, q, r = flat[:, 0], flat[:, 2], flat[:, 3]
    det = p * r - q * q
    if (np.minimum(p, det) <= 0).any():  # NaN propagates, as through numpy's Cholesky
        raise _not_pd()
    out = np.empty(flat.shape)
    np.divide(r, det, out=out[:, 0])
    np.divide(p, det, out=out[:, 3])
    np.divide(q, det, out=out[:, 1])
    np.negative(out[:, 1], out=out[:, 1])
    out[:, 2] = out[:, 1]
    return out.reshape(a.shape)


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
    flat = a.reshape(-1, 4)
    det = flat[:, 0] * flat[:, 3] - flat[:, 1] * flat[:, 2]
    if (det == 0).any():
        raise np.linalg.LinAlgError("Singular matrix")
    inv = np.take(flat, _ADJUGATE, axis=1)  # [[d, -b], [-c, a]] / det
    inv *= _ADJUGATE_SIGN
    inv /= det[:, None]
    return np.matmul(inv.reshape(a.shape), b)


_ADJUGATE = np.array([3, 1, 2, 0])  # flat 2x2 [a, b, c, d] -> [d, b, c, a]
_ADJUGATE_SIGN = np.array([1.0, -1.0, -1.0, 1.0])


def congruence(G: np.ndarray, X: np.ndarray) -> np.ndarray:
    """sym(G^T X G) for one (n, m) matrix G and a stack X (..., n, n).

    With m = 1 it is the single number sum_ij X_ij g_i g_j, one ``einsum``
    instead of two broadcast matrix products."""
    if G.shape[-1] == 1:
        g = G[:, 0]
        return np.einsum("...ij,ij->...", X, np.outer(g, g))[..., None, None]
    return sym(np.matmul(np.matmul(T(G), X), G))


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
    core = "ijkl"[:core_ndim]
    return np.einsum(f"...rs,...s{core}->...r{core}", adj, x, optimize=False)


def nbr_sum_pair(adj: np.ndarray, M: np.ndarray, v: np.ndarray):
    """(nbr_sum(adj, M, 2), nbr_sum(adj, v, 1)) for M (..., S, n, n) and
    v (..., S, n), in one pass over the senders (bit for bit the same sums:
    each entry is reduced over the senders in the same order). Pays for
    n >= 2; with 1x1 matrices two ``nbr_sum`` calls are faster."""
    both = nbr_sum(adj, np.concatenate([M, v[..., None]], axis=-1), 2)
    return both[..., :-1], both[..., -1]
