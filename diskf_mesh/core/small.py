"""Small-matrix kernels: a few 1x1 and 2x2 matrices in closed form, on Python floats.

On stacks of a handful of tiny matrices (an agent's own covariances, its
few neighbours' messages, one message in the guard) numpy's per-call
overhead is most of the time; these kernels do the same IEEE operations on
Python floats, so every result equals the numpy path of ``linalg`` bit for
bit (``tests/test_linalg_fast.py``). ``linalg`` chooses between them;
the checks of single messages, reports and starting estimates
(``mesh.protocol.guard``, ``mesh.wire.codec``) use ``eigen_range``, ``information_gain``
and ``cholesky_ok``, which take nested lists (size 1 or 2) or arrays.
"""
from __future__ import annotations

import math

import numpy as np

# Stacks of at most this many matrices (or vectors) take the Python-float
# paths: below it they are faster than numpy's; above it numpy's loops win.
FEW = 8


def few(a: np.ndarray, core: int) -> bool:
    """Whether ``a`` is a non-empty float64 stack of at most ``FEW`` cores of
    ``core`` entries (a 2 x 2 matrix: core 4), for a Python-float path."""
    return 0 < a.size <= FEW * core and a.dtype.char == "d"


def array(values: list, shape: tuple) -> np.ndarray:
    """A float64 array of ``shape`` from a flat list of Python floats (the
    output of a Python-float path; faster than np.array of nested lists)."""
    return np.fromiter(values, float, len(values)).reshape(shape)


def sym_2_few(a: np.ndarray) -> np.ndarray:
    """``sym`` of a few 2 x 2 matrices in Python floats: (a + a^T) * 0.5 entry
    by entry, as numpy computes it."""
    out = []
    for p, q, s, r in a.reshape(-1, 4).tolist():  # [[p, q], [s, r]]
        off = (q + s) * 0.5
        out += ((p + p) * 0.5, off, off, (r + r) * 0.5)  # s + q is q + s: IEEE addition commutes
    return array(out, a.shape)


def mv_one(a: np.ndarray, v: np.ndarray) -> np.ndarray:
    """``mv`` of one matrix with two columns and one or two rows, and one
    vector, in Python floats: a[r, 0] v_0 + a[r, 1] v_1 row by row, as the
    numpy path computes it."""
    v0, v1 = v.ravel().tolist()
    m = a.ravel().tolist()
    out = [m[0] * v0 + m[1] * v1, m[2] * v0 + m[3] * v1] if len(m) == 4 else [m[0] * v0 + m[1] * v1]
    batch = v.shape[:-1] if v.ndim >= a.ndim - 1 else a.shape[:-2]  # the longer: all ones
    return array(out, batch + (len(out),))


def mv_2x2_few(a: np.ndarray, v: np.ndarray) -> np.ndarray:
    """``mv`` of a few 2 x 2 matrices, each with its vector, in Python floats
    (as ``mv_one``)."""
    m, x = a.ravel().tolist(), v.ravel().tolist()
    out = []
    for i in range(0, len(x), 2):  # vector i // 2 and its matrix, from m[2 i]
        x0, x1, k = x[i], x[i + 1], 2 * i
        out += (m[k] * x0 + m[k + 1] * x1, m[k + 2] * x0 + m[k + 3] * x1)
    return array(out, v.shape)


def inv_spd_2_few(a: np.ndarray) -> np.ndarray:
    """``_inv_spd_2`` of a few matrices in Python floats, the same operations:
    r / det, q / (-det), p / det. A comparison with NaN is False, so a NaN
    propagates instead of raising, as with ``fmin`` there."""
    out = []
    for p, _, q, r in a.reshape(-1, 4).tolist():
        det = p * r - q * q
        if p <= 0 or det <= 0:
            raise not_pd()
        off = q / -det
        out += (r / det, off, off, p / det)
    return array(out, a.shape)


def cholesky_2_few(a: np.ndarray) -> np.ndarray:
    """``linalg.cholesky`` of a few 2 x 2 matrices in Python floats, the same
    operations (l00 = sqrt(a00), l10 = a10 (1 / l00), l11 = sqrt(a11 - l10 l10);
    the lower triangle read). A comparison with NaN is False, so a NaN
    propagates instead of raising."""
    out = []
    for p, _, q, r in a.reshape(-1, 4).tolist():
        if p <= 0:  # False for NaN
            raise not_pd()
        l00 = math.sqrt(p)
        l10 = q * (1.0 / l00)
        pivot = r - l10 * l10
        if pivot <= 0:
            raise not_pd()
        out += (l00, 0.0, l10, math.sqrt(pivot))
    return array(out, a.shape)


def inv_2_few(a: np.ndarray) -> np.ndarray:
    """The closed-form inverse of ``solve`` for a few 2 x 2 matrices, in
    Python floats with the same operations: [[d, -b], [-c, a]] entry by
    entry over det and -det."""
    out = []
    for p, q, s, r in a.reshape(-1, 4).tolist():  # [[p, q], [s, r]]
        det = p * r - q * s
        if det == 0:  # False for NaN, as ``det.all()`` there
            raise np.linalg.LinAlgError("Singular matrix")
        minus_det = -det
        out += (r / det, q / minus_det, s / minus_det, p / det)
    return array(out, a.shape)




def not_pd() -> np.linalg.LinAlgError:
    return np.linalg.LinAlgError("Matrix is not positive definite")


def inverse(a: list) -> list:
    """Inverse of a 1x1 or 2x2 matrix given as nested lists (adjugate over
    determinant, the operations of ``inv_2_few``); raises
    ``numpy.linalg.LinAlgError`` where it is singular, like ``numpy.linalg.inv``."""
    if len(a) == 1:
        if a[0][0] == 0.0:
            raise np.linalg.LinAlgError("Singular matrix")
        return [[1.0 / a[0][0]]]
    (p, q), (s, r) = a
    det = p * r - q * s
    if det == 0.0:
        raise np.linalg.LinAlgError("Singular matrix")
    minus_det = -det
    return [[r / det, q / minus_det], [s / minus_det, p / det]]


def extreme_eigenvalues(M: list) -> tuple:
    """(smallest, largest) eigenvalue of a symmetric 1x1 or 2x2 matrix given
    as nested lists (lower triangle, as ``eigvalsh``). The smallest is the
    determinant over the largest: accurate even where the largest minus the
    radius would cancel (an ill-conditioned matrix)."""
    if len(M) == 1:
        v = float(M[0][0])
        return v, v
    (p, _), (q, r) = M
    hi = 0.5 * (p + r) + math.hypot(0.5 * (p - r), q)
    return ((p * r - q * q) / hi if hi > 0 else hi), hi


def eigen_range(M) -> tuple:
    """(smallest, largest) eigenvalue of a symmetric matrix (lower triangle,
    as ``eigvalsh``): nested lists of size 1 or 2, or an array."""
    if isinstance(M, list):
        return extreme_eigenvalues(M)
    if M.shape[-1] <= 2:
        return extreme_eigenvalues(M.tolist())
    ev = np.linalg.eigvalsh(M)
    return float(ev[0]), float(ev[-1])


def information_gain(P_pred, P_upd) -> tuple:
    """(smallest eigenvalue of sym(inv(P_upd) - inv(P_pred)), max |inv(P_upd)|):
    what an update added to the information matrix (never negative for a
    Kalman update); nested lists of size 1 or 2, or arrays."""
    if not isinstance(P_upd, list) and P_upd.shape[-1] <= 2:
        P_pred, P_upd = P_pred.tolist(), P_upd.tolist()
    if isinstance(P_upd, list):
        k = len(P_upd)
        Yu, Yp = inverse(P_upd), inverse(P_pred)
        scale = max(abs(v) for row in Yu for v in row)
        if k == 1:
            return Yu[0][0] - Yp[0][0], scale
        a, c = Yu[0][0] - Yp[0][0], Yu[1][1] - Yp[1][1]
        b = 0.5 * ((Yu[0][1] - Yp[0][1]) + (Yu[1][0] - Yp[1][0]))
        return 0.5 * (a + c) - math.hypot(0.5 * (a - c), b), scale
    Yu = np.linalg.inv(P_upd)
    dY = Yu - np.linalg.inv(P_pred)
    return float(np.linalg.eigvalsh(0.5 * (dY + dY.T))[0]), float(np.abs(Yu).max())


def cholesky_ok(a: list) -> bool:
    """Whether the Cholesky factorisation of a small symmetric matrix (nested
    lists, lower triangle read) has a positive pivot at every step."""
    k = len(a)
    L = [[0.0] * k for _ in range(k)]
    for j in range(k):
        pivot = a[j][j] - sum(L[j][i] * L[j][i] for i in range(j))
        if not pivot > 0.0:
            return False
        L[j][j] = pivot ** 0.5
        for r in range(j + 1, k):
            L[r][j] = (a[r][j] - sum(L[r][i] * L[j][i] for i in range(j))) / L[j][j]
    return True
