"""Checks that turn user-supplied values into typed values or arrays, or
raise ``InputError`` naming the field.

``setting`` reads one scalar of a table (a TOML table, a JSON object) by
type and range; ``check_keys`` refuses keys a table does not know, with a
"did you mean" suggestion; ``matrix``/``vector``/``spd`` read arrays.
"""
from __future__ import annotations

import difflib
import math

import numpy as np

from diskf_mesh.core.errors import InputError
from diskf_mesh.core.linalg import is_spd


MAX_ID = 2**63 - 1  # agent ids travel as msgpack int64 and name mesh keys
MAX_MAGNITUDE = 1e12  # array entries: products of a few stay far from float overflow
MIN_VARIANCE = 1e-12  # covariance eigenvalues: their inverses stay below 1 / MIN_VARIANCE
_REQUIRED = object()


def _show(v) -> str:
    """A value for an error line: one line, at most about 60 characters."""
    text = repr(v)
    return text if len(text) <= 60 else text[:57] + "..."


def _join(where: str, key: str) -> str:
    return f"{where}.{key}" if where else key


def check_keys(table, known, where: str) -> dict:
    """``table`` itself, if it is a table whose keys are all in ``known``."""
    if not isinstance(table, dict):
        raise InputError(where, f"must be a table, got {_show(table)}")
    known = sorted(known)
    for key in table:
        if key not in known:
            close = difflib.get_close_matches(str(key), known, n=1, cutoff=0.6)
            hint = f"did you mean {close[0]!r}?" if close else f"known keys: {', '.join(known)}"
            raise InputError(_join(where, str(key)), f"unknown key; {hint}")
    return table


def scalar(v, field: str, kind: type, *, low=None, above=None, high=None, choices=None, allow_inf=False):
    """``v`` as a ``kind`` (bool, int, float or str), range-checked: ``low``
    <= v, ``above`` < v, v <= ``high``, v in ``choices``. Ints must be
    integers (not 2.0, not true); floats finite unless ``allow_inf``."""
    if kind is bool:
        if not isinstance(v, bool):
            raise InputError(field, f"must be true or false, got {_show(v)}")
        return v
    if kind is str:
        if not isinstance(v, str):
            raise InputError(field, f"must be a string, got {_show(v)}")
        if choices is not None and v not in choices:
            raise InputError(field, f"must be one of {', '.join(map(str, choices))}, got {_show(v)}")
        return v
    if isinstance(v, bool) or not isinstance(v, (int, float)) or (kind is int and not isinstance(v, int)):
        what = "an integer" if kind is int else "a number"
        raise InputError(field, f"must be {what}, got {_show(v)}")
    if kind is float:
        try:
            v = float(v)
        except OverflowError:
            raise InputError(field, f"is too large, got {_show(v)}") from None
        if math.isnan(v) or (math.isinf(v) and not allow_inf):
            raise InputError(field, f"must be a finite number, got {_show(v)}")
    if low is not None and not v >= low:
        raise InputError(field, f"must be >= {low}, got {_show(v)}")
    if above is not None and not v > above:
        raise InputError(field, f"must be > {above}, got {_show(v)}")
    if high is not None and not v <= high:
        raise InputError(field, f"must be <= {high}, got {_show(v)}")
    return v


def setting(table: dict, key: str, where: str, kind: type, default=_REQUIRED, **checks):
    """Field ``key`` of ``table`` through ``scalar``; ``default`` if absent
    (no default: the field is required). The error names ``where.key``."""
    if key not in table:
        if default is _REQUIRED:
            raise InputError(_join(where, key), "is missing")
        return default
    return scalar(table[key], _join(where, key), kind, **checks)


MAX_NAME = 64  # characters of a string agent id


def agent_id(v, field: str):
    """An agent id as the user gave it: an integer in 0..2^63-1, or a string
    of 1 to ``MAX_NAME`` printable characters without leading or trailing
    spaces ("drone-1"). Inside a run every agent has an integer id
    (``internal_ids``); the user's id is its label."""
    if isinstance(v, str):
        if not v or len(v) > MAX_NAME or not v.isprintable() or v.strip() != v:
            raise InputError(field, f"a string id must be 1 to {MAX_NAME} printable characters without leading "
                                    f"or trailing spaces, got {_show(v)}")
        return v
    if isinstance(v, bool) or not isinstance(v, int):
        raise InputError(field, f"must be an integer or a string, got {_show(v)}")
    return scalar(v, field, int, low=0, high=MAX_ID)


def unique_ids(labels, field: str) -> tuple:
    """``labels`` if no two ids are equal as text (1 and "1" would name one
    key, one column of the results)."""
    seen = {}
    for j, i in enumerate(labels):
        if str(i) in seen:
            raise InputError(field, f"agent ids must be unique: {_show(i)} is given twice "
                                    f"(agents {seen[str(i)]} and {j})")
        seen[str(i)] = j
    return tuple(labels)


def internal_ids(labels) -> tuple:
    """The integer ids a run uses for agents labelled ``labels`` (the mesh's
    keys and messages, the certificates ``agent-<id>``, the seeded per-agent
    streams): the ids themselves when every one is an integer, else 1..N in
    the order given (the ids a scenario without ids gets), so a scenario
    whose ids are names runs exactly as the same scenario without ids."""
    if all(isinstance(i, int) for i in labels):
        return tuple(labels)
    return tuple(range(1, len(labels) + 1))


def index_list(v, field: str, n: int, max_len: int | None = None) -> tuple:
    """A non-empty list of distinct indices into a length-``n`` vector."""
    if (not isinstance(v, list) or not v or (max_len is not None and len(v) > max_len)
            or not all(isinstance(i, int) and not isinstance(i, bool) and 0 <= i < n for i in v)
            or len(set(v)) != len(v)):
        most = "" if max_len is None else f"at most {max_len} "
        raise InputError(field, f"must be a non-empty list of {most}distinct indices in 0..{n - 1}, got {_show(v)}")
    return tuple(v)


def _numbers_only(value, depth: int = 0) -> bool:
    """Nested lists of ints and floats only (no bool, no text, no null)."""
    if isinstance(value, (list, tuple)):
        return depth < 4 and all(_numbers_only(v, depth + 1) for v in value)
    return isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, (bool, np.bool_))


def _array(value, field: str, ndim: int) -> np.ndarray:
    if value is None:
        raise InputError(field, "is missing")
    if not isinstance(value, np.ndarray) and not _numbers_only(value):
        raise InputError(field, "must be numbers (a non-numeric array was given)")
    try:
        a = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise InputError(field, "must be numbers (a ragged or non-numeric array was given)") from None
    except OverflowError:
        raise InputError(field, "contains a number too large for a float") from None
    if a.ndim != ndim:
        raise InputError(field, f"must be a {ndim}-dimensional array, got shape {a.shape}")
    if not np.isfinite(a).all():
        raise InputError(field, "contains NaN or infinity")
    if a.size and np.abs(a).max() > MAX_MAGNITUDE:
        raise InputError(field, f"entries must be within +-{MAX_MAGNITUDE:g}, got {np.abs(a).max():g}")
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
    if np.linalg.eigvalsh(a)[0] < MIN_VARIANCE:
        raise InputError(field, f"eigenvalues must be at least {MIN_VARIANCE:g}")
    return a
