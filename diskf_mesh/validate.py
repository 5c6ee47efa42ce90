"""Checks that turn user-supplied numbers into arrays or raise ``InputError``
naming the field."""
from __future__ import annotations

import numpy as np

from .errors import InputError
from .linalg import is_spd


def _array(value, field: str, ndim: int) -> np.ndarray:
    if value is None:
        raise InputError(field, "is missing")
    try:
        a = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise InputError(field, "must be numbers (a ragged or non-numeric array was given)") from None
    if a.ndim != ndim:
        raise InputError(field, f"must be a {ndim}-dimensional array, got shape {a.shape}")
    if not np.isfinite(a).all():
        raise InputError(field, "contains NaN or infinity")
    return a


def matrix(value, field: str, shape: tuple | None = None) -> np.ndarray:
    """A finite 2-D array; ``shape`` entries of None are free."""
    a = _array(value, field, 2)
    if shape is not None and any(s is not None and s != t for s, t in zip(shape, a.shape)):
        want = "x".join("*" if s is None else str(s) for s in shape)
        raise InputError(field, f"must be {want}, got {a.shape[0]}x{a.shape[1]}")
    return a


def vector(value, field: str, length: int | None = None) -> np.ndarray:
    a = _array(value, field, 1)
    if length is not None and a.shape[0] != length:
        raise InputError(field, f"must have length {length}, got {a.shape[0]}")
    return a


def spd(a: np.ndarray, field: str) -> np.ndarray:
    """A symmetric positive-definite matrix (a covariance)."""
    if a.shape[0] != a.shape[1]:
        raise InputError(field, f"must be square, got {a.shape[0]}x{a.shape[1]}")
    if not np.allclose(a, a.T, rtol=1e-9, atol=1e-12):
        raise InputError(field, "must be symmetric")
    if not bool(is_spd(a)):
        raise InputError(field, "must be positive definite")
    return a
