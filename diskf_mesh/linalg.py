"""Stacked linear algebra used by every filter.

All functions take arrays with any number of leading batch axes
(seeds x agents x ...) and operate on the trailing one or two axes.
Inverses of covariances go through Cholesky, so a covariance that is not
positive definite raises instead of silently producing garbage.
"""
from __future__ import annotations

import numpy as np


def T(a: np.ndarray) -> np.ndarray:
    """Transpose of the trailing two axes."""
    return np.swapaxes(a, -1, -2)


def sym(a: np.ndarray) -> np.ndarray:
    """Symmetric part, used after every covariance product to keep it symmetric."""
    return 0.5 * (a + T(a))


def mv(a: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Stacked matrix-vector product a @ v."""
    return np.matmul(a, v[..., None])[..., 0]


def inv_spd(a: np.ndarray) -> np.ndarray:
    """Inverse of a stack of symmetric positive-definite matrices via Cholesky.

    A = L L^T  =>  A^-1 = L^-T L^-1, symmetric by construction.
    Raises numpy.linalg.LinAlgError if any matrix is not positive definite.
    """
    L = np.linalg.cholesky(a)
    eye = np.broadcast_to(np.eye(a.shape[-1]), a.shape)
    Li = np.linalg.solve(L, eye)
    return np.matmul(T(Li), Li)


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

    Written as broadcast-multiply-then-sum (not BLAS) on purpose: every
    receiver row is reduced in the same order, so receivers that hear the same
    senders get bit-identical results. This is what makes the state
    compensation exactly zero under all-to-all communication.
    """
    a = adj.reshape(adj.shape + (1,) * core_ndim)
    return (a * np.expand_dims(x, -core_ndim - 2)).sum(axis=-core_ndim - 1)
