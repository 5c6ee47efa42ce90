"""Encoding and decoding of the wire's payloads (what they hold, and their bounds: ``payloads``).

``decode_*`` either returns a dataclass or raises ``Rejected`` with one of
``REASONS``, never anything else, whatever the bytes.

Limits (``limits``): before anything is decoded, a payload larger than its
kind's schema allows for the receiver's dimensions is refused ("size"): a
"msg" of n = 2, m = 1 is at most ``HEADER_BYTES`` + 8 x 14 bytes. Then one
msgpack unpack with every container and string bounded by the schema
(``max_map_len`` = the kind's field count + 2, ``max_bin_len`` = its float
bytes, ``max_array_len`` = its longest array or float count, ``max_str_len``
= ``MAX_STR``), so a map of 130,000 keys is refused at its header, before
one key is read. Report counters are non-negative ints of at most
``count_bound(ticks)``, at most ``MAX_COUNTERS`` of them, with known names.
"""
from __future__ import annotations

import functools
import hashlib
import math
import re
import struct
from dataclasses import dataclass, fields

import msgpack
import numpy as np

from diskf_mesh.core.small import cholesky_ok, eigen_range
from diskf_mesh.core.messages import Message
from diskf_mesh.estimators.base import EXCHANGED
from diskf_mesh.mesh.wire.counters import SCALARS
from diskf_mesh.mesh.wire.payloads import (
    DIGEST_BYTES, DTYPE, HEADER_BYTES, HOLDER_BYTES, Join, MAX_ABS, MAX_BYTES, MAX_COND, MAX_COUNTERS, MAX_DIM,
    MAX_LINKS, MAX_STR, MAX_VERDICT, MAX_WHY, Measurement, PER_TICK, REASONS, Rejected, Report, SCHEMA, Start,
    Stop, Tick, WireMessage)


@dataclass(frozen=True)
class Slot:
    """Where one exchanged array lies in a message's floats."""

    name: str
    index: int        # its position among ``Message``'s fields
    start: int
    stop: int
    shape: tuple
    covariance: bool
    update_of: str | None
    weights: bool = False  # probabilities (``Exchanged.weights``)


@dataclass(frozen=True)
class Layout:
    """The floats of a "msg" for one estimator's ``exchanged`` and (n, m)."""

    slots: tuple
    count: int        # floats in all
    spans: tuple      # (start, k) of every k x k covariance, in declared order
    covariances: tuple  # the covariances' slots, in declared order
    updates: tuple    # (slot, slot of the covariance it updates), for ``Exchanged.update_of``
    weights: tuple    # the slots of probabilities (``Exchanged.weights``)
    absent: tuple     # ``Message``'s fields with the zeros (read-only) of every array not exchanged, else None
    views: tuple      # (index, start, stop, shape or None for a vector) of every slot

    def message(self, a: np.ndarray, d_valid: bool) -> Message:
        """The ``Message`` of the float64 array ``a`` (views into it); an
        array not exchanged is zeros of its usual shape (finite, never
        read by its estimator's ``fuse``)."""
        parts = list(self.absent)
        for i, start, stop, shape in self.views:
            v = a[start:stop]
            parts[i] = v if shape is None else v.reshape(shape)
        parts[_D_VALID] = np.array(d_valid)
        return Message(*parts)


_MESSAGE_FIELDS = tuple(f.name for f in fields(Message))  # in ``Message``'s order
_D_VALID = _MESSAGE_FIELDS.index("d_valid")


@functools.lru_cache(maxsize=64)
def layout(exchanged: tuple, n: int, m: int) -> Layout:
    """The layout of a message of the arrays ``exchanged`` (``Exchanged``)
    for state dimension ``n`` and input dimension ``m``."""
    slots, i = [], 0
    for f in exchanged:
        if f.name not in Message.ARRAY_FIELDS:
            raise ValueError(f"exchanged field {f.name!r} is not an array of Message")
        shape = f.dims(n, m)
        size = math.prod(shape)
        slots.append(Slot(f.name, _MESSAGE_FIELDS.index(f.name), i, i + size, shape, f.covariance, f.update_of,
                          f.weights))
        i += size
    by_name = {s.name: s for s in slots}
    covs = tuple(s for s in slots if s.covariance)
    absent = [None] * len(_MESSAGE_FIELDS)
    for f in EXCHANGED:
        if f.name not in by_name:
            zeros = np.zeros(f.dims(n, m))
            zeros.flags.writeable = False
            absent[_MESSAGE_FIELDS.index(f.name)] = zeros
    return Layout(tuple(slots), i, tuple((s.start, s.shape[-1]) for s in covs), covs,
                  tuple((s, by_name[s.update_of]) for s in slots if s.update_of is not None),
                  tuple(s for s in slots if s.weights), tuple(absent),
                  tuple((s.index, s.start, s.stop, None if len(s.shape) == 1 else s.shape) for s in slots))


_CODECS: dict = {}  # (id(exchanged), n, m) -> (exchanged, limits, layout): a lookup without hashing the fields


def _codec(exchanged: tuple, n: int | None, m: int | None) -> tuple:
    """(limits, layout) of a "msg" of ``exchanged`` for the receiver's (n, m)
    (layout None where n or m is not given), remembered per declaration."""
    key = (id(exchanged), n, m)
    hit = _CODECS.get(key)
    if hit is None or hit[0] is not exchanged:
        if len(_CODECS) >= 256:
            _CODECS.clear()
        hit = _CODECS[key] = (exchanged, limits("msg", n, m, exchanged=exchanged),
                              None if n is None or m is None else layout(exchanged, n, m), _dim_fields(exchanged))
    return hit[1:]


@functools.lru_cache(maxsize=64)
def _dim_fields(exchanged: tuple) -> tuple:
    """The first declared array with an n axis and the first with an m axis,
    and that axis (the header's "n" and "m" are read from them)."""
    out = []
    for d in ("n", "m"):
        hit = next(((f.name, f.shape.split().index(d) - len(f.shape.split())) for f in exchanged
                    if d in f.shape.split()), None)
        if hit is None:
            raise ValueError(f"an estimator's exchanged arrays must include one with an {d} axis")
        out.append(hit)
    return tuple(out)


# --------------------------------------------------------------------------
# encoding
# --------------------------------------------------------------------------
def _f8(*arrays) -> bytes:
    return b"".join(np.ascontiguousarray(a, dtype=DTYPE).tobytes() for a in arrays)


def _pack(doc: dict) -> bytes:
    return msgpack.packb(doc, use_bin_type=True)


def _dims(x: np.ndarray, d: np.ndarray) -> tuple:
    return int(np.shape(x)[-1]), int(np.shape(d)[-1])


def encode(run_id: str, sender: int, tick: int, msg: Message, exchanged: tuple = EXCHANGED) -> bytes:
    """One agent's message: the arrays ``exchanged`` (its estimator's
    declaration); ``msg`` arrays may keep leading batch axes of size 1."""
    _, _, ((fn, an), (fm, am)) = _codec(exchanged, None, None)
    n, m = int(np.shape(getattr(msg, fn))[an]), int(np.shape(getattr(msg, fm))[am])
    blob = _f8(*(getattr(msg, f.name) for f in exchanged))
    if len(blob) != 8 * _codec(exchanged, n, m)[1].count:
        raise ValueError("encode: a message must hold one agent's arrays")
    return _message(run_id, sender, tick, n, m, bool(np.asarray(msg.d_valid).reshape(-1)[0]), blob)


def _message(run_id: str, sender: int, tick: int, n: int, m: int, d_valid: bool, blob: bytes) -> bytes:
    """A "msg" payload from its fields (``encode``, ``engine_digests``)."""
    return _pack({"v": SCHEMA, "k": "msg", "run": run_id, "s": int(sender), "t": int(tick), "n": n, "m": m,
                  "dt": DTYPE, "dv": bool(d_valid), "a": blob})


def digest(payload: bytes) -> bytes:
    """A message's short digest (``DIGEST_BYTES`` of blake2b): what a report
    says of each message it fused."""
    return hashlib.blake2b(payload, digest_size=DIGEST_BYTES).digest()


def message_digest(run_id: str, sender: int, tick: int, msg: Message, exchanged: tuple = EXCHANGED) -> bytes:
    """The digest of ``sender``'s message of ``tick``: of its encoding
    (``encode`` is deterministic, so an honest message's is the digest of
    the payload its sender published, which a receiver reports of the copy
    it fused: ``WireMessage.digest``)."""
    return digest(encode(run_id, sender, tick, msg, exchanged))


def engine_digests(run_id: str, ids, exchanged: tuple = EXCHANGED):
    """``engine.verify``'s ``message_digests`` for a run: (tick, senders'
    indices in ``ids``, the engine's Message of the tick, batch (1, N, ...))
    -> the ``message_digest`` of each sender's message, every sender's
    floats laid out at once as ``encode`` lays out one's. The bytes hashed
    are ``_message``'s: its map's fields packed one by one, those that do
    not change within a run (the sender's, the sizes) packed once."""
    ids = list(ids)
    _, _, ((fn, an), (fm, am)) = _codec(exchanged, None, None)
    pack = msgpack.Packer(use_bin_type=True).pack
    heads = [b"".join((msgpack.Packer().pack_map_header(10), pack("v"), pack(SCHEMA), pack("k"), pack("msg"),
                       pack("run"), pack(run_id), pack("s"), pack(int(i)), pack("t"))) for i in ids]
    flags = (pack("dv") + pack(False), pack("dv") + pack(True))
    middles = {}  # (n, m, float bytes) -> the fields between the tick and the floats

    def digests(k: int, senders, msg: Message) -> list:
        senders = np.asarray(senders, dtype=np.intp)
        n, m = int(np.shape(getattr(msg, fn))[an]), int(np.shape(getattr(msg, fm))[am])
        arrays = [np.asarray(getattr(msg, f.name), dtype=DTYPE)[0] for f in exchanged]
        N = arrays[0].shape[0]
        rows = np.concatenate([a.reshape(N, -1) for a in arrays], axis=1)[senders]
        size = (n, m, rows.shape[1] * 8)
        middle = middles.get(size)
        if middle is None:
            middle = middles[size] = (b"".join((pack("n"), pack(n), pack("m"), pack(m), pack("dt"), pack(DTYPE))),
                                      pack("a") + _bin_header(pack, size[2]))
        tick, (sizes, floats) = pack(int(k)), middle
        dv = np.asarray(msg.d_valid)[0, senders].tolist()
        return [digest(b"".join((heads[s], tick, sizes, flags[v], floats, row.tobytes())))
                for s, v, row in zip(senders.tolist(), dv, rows)]
    return digests


def _bin_header(pack, size: int) -> bytes:
    """The header ``pack`` writes before ``size`` bytes."""
    whole = pack(bytes(size))
    return whole[:len(whole) - size]


def encode_report(run_id: str, sender: int, tick: int, x, P, d, d_valid, counters=None, fused=(),
                  not_fused=(), sent_digest: bytes = b"", digests=(), restart=None) -> bytes:
    n, m = _dims(x, d)
    blob = _f8(x, P, d)
    if len(blob) != 8 * (n + n * n + m):
        raise ValueError("encode_report: a report must hold one agent's arrays")
    return _pack({"v": SCHEMA, "k": "report", "run": run_id, "s": int(sender), "t": int(tick), "n": n, "m": m,
                  "dt": DTYPE, "dv": bool(np.asarray(d_valid).reshape(-1)[0]), "a": blob,
                  "c": {str(k): int(v) for k, v in (counters or {}).items()},
                  "f": [int(s) for s in fused], "nf": [[int(s), str(v)] for s, v in not_fused], "od": bytes(sent_digest),
                  "fd": [bytes(g) for g in digests],
                  **({} if restart is None else {"rj": [int(restart[0]), -1 if restart[1] is None else int(restart[1])]})})


def encode_tick(t: Tick) -> bytes:
    return _pack({"v": SCHEMA, "k": "tick", "run": t.run_id, "t": int(t.tick), "K": int(t.ticks),
                  "seed": int(t.seed), "alg": t.algorithm, "topo": t.topology, "range": float(t.comm_range),
                  "dt": DTYPE, "pos": _f8(t.positions), "live": [int(i) for i in t.live],
                  **({"ho": bytes(t.holders)} if t.holders else {})})


@functools.lru_cache(maxsize=4096)
def holder_tag(nonce: str) -> bytes:
    """The 4-byte tag of a process (its liveliness nonce) in a tick's "ho"."""
    return hashlib.blake2b(nonce.encode(), digest_size=HOLDER_BYTES).digest()


def encode_measurement(run_id: str, tick: int, agent: int, has: bool, y) -> bytes:
    return _pack({"v": SCHEMA, "k": "meas", "run": run_id, "t": int(tick), "to": int(agent), "has": bool(has),
                  "dt": DTYPE, "y": _f8(y) if has else b""})


STOPPED = ("diverged", "interrupted")  # why an agent may say it stops before the run's end (``encode_stopped``)


def encode_stopped(run_id: str, tick: int, category: str, reason: str) -> bytes:
    """An agent's notice that it stops at ``tick`` (``keys.stopped``): a
    "stop" payload whose why is "<category>: <reason>", ``category`` one of
    ``STOPPED`` (``stopped_category`` reads it back)."""
    if category not in STOPPED:
        raise ValueError(f"encode_stopped: {category!r} is not one of {STOPPED}")
    return encode_stop(run_id, tick, f"{category}: {reason}"[:MAX_WHY])


def stopped_category(st: Stop) -> str | None:
    """The category of an agent's stop notice (``encode_stopped``), or None
    where its why does not start with one of ``STOPPED``."""
    category = st.why.split(":", 1)[0]
    return category if category in STOPPED else None


def encode_stop(run_id: str, tick: int, why: str) -> bytes:
    return _pack({"v": SCHEMA, "k": "stop", "run": run_id, "t": int(tick), "why": str(why)})


def encode_join(run_id: str, sender: int, tick: int) -> bytes:
    return _pack({"v": SCHEMA, "k": "join", "run": run_id, "t": int(tick), "s": int(sender)})


def encode_start(run_id: str, agent: int, tick: int, source: int | None, x, P, d, d_valid) -> bytes:
    n, m = _dims(x, d)
    blob = _f8(x, P, d)
    if len(blob) != 8 * (n + n * n + m):
        raise ValueError("encode_start: a starting estimate must hold one agent's arrays")
    return _pack({"v": SCHEMA, "k": "start", "run": run_id, "t": int(tick), "s": int(agent),
                  "src": -1 if source is None else int(source), "n": n, "m": m, "dt": DTYPE,
                  "dv": bool(np.asarray(d_valid).reshape(-1)[0]), "a": blob})


# --------------------------------------------------------------------------
# decoding
# --------------------------------------------------------------------------
def _is_int(v) -> bool:
    """An int and not a bool (msgpack gives plain ints and bools only)."""
    return type(v) is int


def _ints(xs) -> bool:
    """Whether every item of ``xs`` is an int and not a bool (``_is_int``),
    in one C loop over the items."""
    return set(map(type, xs)) <= _INT


_INT = frozenset((int,))
_BYTES = frozenset((bytes,))
_DIGEST_LEN = frozenset((DIGEST_BYTES,))


def _field(doc: dict, key: str, kind):
    v = doc.get(key)
    if type(v) is kind:  # what msgpack gives (never a subclass but bool, which is not int's type)
        return v
    ok = _is_int(v) if kind is int else isinstance(v, kind)
    if not ok:
        raise Rejected("schema", f"field {key!r} missing or not {getattr(kind, '__name__', kind)}")
    return v


@dataclass(frozen=True)
class Limits:
    """The most one kind of payload may hold, for the receiver's dimensions."""

    max_bytes: int       # the whole payload
    max_str_len: int     # any string (map keys too)
    max_bin_len: int     # any bin (the float arrays)
    max_array_len: int   # any array
    max_map_len: int     # any map

    def unpack(self, data):
        return msgpack.unpackb(data, raw=False, strict_map_key=True, use_list=True, max_str_len=self.max_str_len,
                               max_bin_len=self.max_bin_len, max_array_len=self.max_array_len,
                               max_map_len=self.max_map_len, max_ext_len=0)


# fields of each kind (the map's length), and room for a few more (a signature, a binding) that a
# decoder ignores: each is still bounded by the string, bin and byte limits
_FIELDS = {"msg": 10, "report": 13, "tick": 13, "meas": 8, "stop": 5, "join": 5, "start": 11}
EXTRA_FIELDS = 2


@functools.lru_cache(maxsize=64)
def limits(kind: str, a: int | None = None, b: int | None = None, agents: int | None = None,
           exchanged: tuple = EXCHANGED) -> Limits:
    """``kind``'s limits: "msg" and "report" for dimensions (a, b) = (n, m)
    ("msg" of the arrays ``exchanged``; a report also for the run's
    ``agents``: its "f" and "nf" name senders),
    "tick" for a = N agents, "meas" for a = p values, "stop". A dimension
    not given is the largest any run may have (``MAX_DIM``; for N, what fits
    in ``MAX_BYTES``)."""
    n, m = a or MAX_DIM, b or MAX_DIM
    fields = _FIELDS[kind] + EXTRA_FIELDS
    if kind in ("msg", "report"):
        floats = layout(exchanged, n, m).count if kind == "msg" else n + n * n + m
        size = HEADER_BYTES + 8 * floats
        arrays, bins = floats, 8 * floats
        if kind == "report":  # the counters: MAX_COUNTERS names and ints; "f" and "nf": a few bytes per sender;
            # "od": the digest of the agent's own message
            links = agents if agents is not None else MAX_LINKS
            own = 2 + DIGEST_BYTES
            size += MAX_COUNTERS * (2 + MAX_STR + 9) + links * (9 + 12 + MAX_VERDICT + 2 + DIGEST_BYTES) + own
            fields, arrays, bins = MAX_COUNTERS, max(floats, links), max(bins, own)
        return Limits(size, MAX_STR, bins, arrays, fields)
    if kind == "tick":  # alg, topo; N positions (2 float64), N live ids (<= 9 bytes each), N holder tags
        N = a or (MAX_BYTES - HEADER_BYTES - 2 * MAX_STR) // (25 + HOLDER_BYTES)
        return Limits(HEADER_BYTES + 2 * MAX_STR + (25 + HOLDER_BYTES) * N, MAX_STR, 16 * N, N, fields)
    if kind == "meas":
        p = a or MAX_DIM
        return Limits(HEADER_BYTES + 8 * p, MAX_STR, 8 * p, p, fields)
    if kind == "start":
        floats = n + n * n + m
        return Limits(HEADER_BYTES + 8 * floats, MAX_STR, 8 * floats, floats, fields)
    if kind == "join":  # ints only
        return Limits(HEADER_BYTES, MAX_STR, 0, 0, fields)
    return Limits(HEADER_BYTES + MAX_WHY, MAX_WHY, 0, 0, fields)


def _open(data, kind: str, run_id: str | None, lim: Limits) -> dict:
    """Size check, one bounded unpack; check version, kind, run and tick."""
    if not isinstance(data, (bytes, bytearray, memoryview)):
        raise Rejected("not-msgpack", "payload is not bytes")
    if len(data) > min(lim.max_bytes, MAX_BYTES):
        raise Rejected("size", f"payload of {len(data)} bytes, at most {min(lim.max_bytes, MAX_BYTES)}")
    try:
        doc = lim.unpack(data)
    except ValueError as e:  # msgpack's limits and most garbage
        if "exceeds max_" in str(e):
            raise Rejected("size", str(e)) from None
        raise Rejected("not-msgpack", type(e).__name__) from None
    except Exception as e:  # msgpack raises several unrelated types on garbage
        raise Rejected("not-msgpack", type(e).__name__) from None
    if not isinstance(doc, dict):
        raise Rejected("schema", "not a map")
    v, k = doc.get("v"), doc.get("k")
    if v != SCHEMA or isinstance(v, bool):
        raise Rejected("schema", f"version {v!r}, expected {SCHEMA}")
    if k != kind:
        raise Rejected("schema", f"kind {k!r}, expected {kind!r}")
    run = _field(doc, "run", str)
    if run_id is not None and run != run_id:
        raise Rejected("run", f"run {run!r}, expected {run_id!r}")
    if _field(doc, "t", int) < 0:
        raise Rejected("schema", "negative tick")
    return doc


def _floats(doc: dict, key: str, count: int) -> np.ndarray:
    """The float64 array of ``doc[key]`` (``count`` floats), checked finite."""
    values = _values(doc, key, count)
    return np.array(values, dtype=float) if type(values) is tuple else values


def _values(doc: dict, key: str, count: int):
    """The ``count`` floats of ``doc[key]``, checked finite, read once: a
    tuple of Python floats for a few (``_SMALL``), else a float64 array."""
    if doc.get("dt", DTYPE) != DTYPE:
        raise Rejected("dtype", f"dtype {doc.get('dt')!r}, expected {DTYPE!r}")
    blob = doc.get(key)
    if not isinstance(blob, bytes):
        raise Rejected("dtype", f"field {key!r} is not a float64 byte string")
    if len(blob) != 8 * count:
        raise Rejected("shape", f"field {key!r} holds {len(blob)} bytes, expected {8 * count}")
    if count <= _SMALL:  # the usual message: Python floats are faster than numpy calls on a few numbers
        values = _struct(count).unpack(blob)
        if not _finite(values):
            raise Rejected("non-finite", f"field {key!r}")
        return values
    a = np.frombuffer(blob, dtype=DTYPE).astype(float)
    # as ``_finite``: NaN and infinity make a . a non-finite (so may huge finite values: then look at each)
    if not math.isfinite(a.dot(a)) and not np.isfinite(a).all():
        raise Rejected("non-finite", f"field {key!r}")
    return a


_SMALL = 64


def _finite(values: tuple) -> bool:
    """Every Python float of ``values`` is finite: NaN and infinity make the
    sum non-finite (so may huge finite values: then look at each)."""
    return math.isfinite(sum(values)) or all(map(math.isfinite, values))


@functools.lru_cache(maxsize=None)
def _struct(count: int) -> struct.Struct:
    return struct.Struct(f"<{count}d")


def _dims_of(doc: dict, n: int | None, m: int | None) -> tuple:
    dn, dm = _field(doc, "n", int), _field(doc, "m", int)
    if not (1 <= dn <= MAX_DIM and 1 <= dm <= MAX_DIM):
        raise Rejected("shape", f"n={dn}, m={dm} out of range")
    if (n is not None and dn != n) or (m is not None and dm != m):
        raise Rejected("shape", f"n={dn}, m={dm}, expected n={n}, m={m}")
    return dn, dm


def _check_sender(doc: dict, sender: int | None) -> int:
    s = _field(doc, "s", int)
    if sender is not None and s != sender:
        raise Rejected("sender", f"body says sender {s}, key says {sender}")
    return s


def _spd(values, a: np.ndarray, spans, rtol: float = 1e-9) -> None:
    """Every k x k covariance at ``spans`` ((start, k), ...) of a payload's
    floats: symmetric to ``rtol`` of the largest entry, and a Cholesky
    factor exists. ``values`` are the floats as read (``_values``), ``a``
    the same as a float64 array. Small matrices (the usual n, m <= 4) are
    checked on the Python floats, which is several times faster than numpy
    calls on them; this runs for every message received."""
    small = type(values) is tuple
    for start, k in spans:
        stop = start + k * k
        if k > 4:
            M = a[start:stop].reshape(k, k)
            scale = np.abs(M).max()
            if np.abs(M - M.T).max() > rtol * scale:
                raise Rejected("not-spd", "a covariance is not symmetric")
            try:
                np.linalg.cholesky(M)
            except np.linalg.LinAlgError:
                raise Rejected("not-spd", "a covariance is not positive definite") from None
            continue
        v = values[start:stop] if small else a[start:stop].tolist()
        if k == 1:
            if not v[0] > 0.0:
                raise Rejected("not-spd", "a variance is not positive")
            continue
        if k == 2:  # the same arithmetic as cholesky_ok, unrolled
            p, q, s, r = v
            if abs(q - s) > rtol * max(abs(p), abs(q), abs(s), abs(r)):
                raise Rejected("not-spd", "a covariance is not symmetric")
            if not p > 0.0:
                raise Rejected("not-spd", "a covariance is not positive definite")
            low = s / p ** 0.5
            if not r - low * low > 0.0:
                raise Rejected("not-spd", "a covariance is not positive definite")
            continue
        rows = [list(v[i * k:(i + 1) * k]) for i in range(k)]
        scale = max(abs(x) for x in v)
        if any(abs(rows[i][j] - rows[j][i]) > rtol * scale for i in range(k) for j in range(i)):
            raise Rejected("not-spd", "a covariance is not symmetric")
        if not cholesky_ok(rows):
            raise Rejected("not-spd", "a covariance is not positive definite")


def largest_abs(values) -> float:
    """The largest |v| of the floats as read: a tuple (small arrays, as
    ``_values`` reads them, in C loops over Python floats) or an array."""
    if type(values) is tuple:
        return max(max(values), -min(values)) if values else 0.0
    return float(np.abs(values).max()) if values.size else 0.0


def estimate_problem(a: np.ndarray, P: np.ndarray, max_abs: float = MAX_ABS, max_cond: float = MAX_COND,
                     values=None):
    """The guard's checks of an estimate beyond finiteness and positive
    definiteness (``guard.message_problem`` for messages): None, or
    ("magnitude" | "ill-conditioned", detail) when a value of ``a`` (every
    float of it) is beyond ``max_abs`` or the condition number of ``P``
    exceeds ``max_cond``. ``values``: the same floats as a tuple (as
    ``_values`` reads small ones), checked on Python floats."""
    big = largest_abs(values if type(values) is tuple else a)
    if big > max_abs:
        return "magnitude", f"a value of {big:.3g} (limit {max_abs:.3g})"
    ev = eigen_range(P)
    if not ev[0] > 0 or ev[-1] > max_cond * ev[0]:
        return "ill-conditioned", f"P eigenvalues {ev[0]:.3g} .. {ev[-1]:.3g}"
    return None


def _estimate(doc: dict, n: int, m: int, max_abs: float, max_cond: float) -> tuple:
    """(x (n,), P (n, n), d (m,)) of the floats "a" of a report or a starting
    estimate (views into one array), checked as the guard checks a message:
    finite, P positive definite (``_spd``), then ``estimate_problem``."""
    values = _values(doc, "a", n + n * n + m)
    a = np.array(values, dtype=float) if type(values) is tuple else values
    P = a[n:n + n * n].reshape(n, n)
    _check_estimate(values, a, P, max_abs, max_cond)
    return a[:n], P, a[n + n * n:]


def _check_estimate(values, a, P: np.ndarray, max_abs: float, max_cond: float) -> None:
    """An estimate's checks past finiteness (``Rejected`` if one fails): P
    positive definite (``_spd``), then ``estimate_problem``. ``values``: its
    floats (x, P, d) as read, ``a`` the same as an array (None is enough
    when ``values`` is a tuple and P at most 4 x 4)."""
    _spd(values, a, ((P.shape[-1], P.shape[-1]),))
    problem = estimate_problem(a, P, max_abs, max_cond, values)
    if problem is not None:
        raise Rejected(*problem)


def report_problem(x, P, d, max_abs: float = MAX_ABS, max_cond: float = MAX_COND):
    """None if a report (or a starting estimate) of ``x``, ``P``, ``d``
    passes ``_estimate``'s checks (finite, P positive definite,
    ``estimate_problem``), else (reason, detail): what its receiver would
    refuse it for. An agent asks before it reports; on Python floats, as the
    decoder reads a small estimate."""
    P = np.asarray(P)
    values = tuple(np.ravel(x).tolist() + P.ravel().tolist() + np.ravel(d).tolist())
    if not _finite(values):
        return "non-finite", "the estimate holds NaN or infinity"
    try:
        _check_estimate(values, np.array(values) if P.shape[-1] > 4 else None, P, max_abs, max_cond)
    except Rejected as e:
        return e.reason, e.detail
    return None


def _estimate_head(doc: dict, sender, n, m) -> tuple:
    """(sender, n, m, d_valid) of an open "msg" or "report", checked."""
    s = _check_sender(doc, sender)
    n, m = _dims_of(doc, n, m)
    dv = doc.get("dv")
    if not isinstance(dv, bool):
        raise Rejected("schema", "field 'dv' missing or not bool")
    return s, n, m, dv


def decode(data, *, run_id: str | None = None, sender: int | None = None,
           n: int | None = None, m: int | None = None, exchanged: tuple = EXCHANGED) -> WireMessage:
    """A neighbour's "msg" of the arrays ``exchanged`` (its estimator's
    declaration); checks everything a receiver relies on: one unpack, the
    floats read once (finite, every covariance positive definite), the
    arrays made once.

    ``sender`` is the id the key names, ``n``/``m`` the receiver's
    dimensions. A rejection after the tick was read carries it (``tick``)."""
    lim, lay, _ = _codec(exchanged, n, m)
    doc = _open(data, "msg", run_id, lim)
    try:
        s, n, m, dv = _estimate_head(doc, sender, n, m)
        if lay is None:
            lay = layout(exchanged, n, m)
        values = _values(doc, "a", lay.count)
        a = np.array(values, dtype=float) if type(values) is tuple else values
        _spd(values, a, lay.spans)
    except Rejected as e:
        e.tick = doc["t"]
        raise
    return WireMessage(doc["run"], s, doc["t"], lay.message(a, dv), values, lay, digest(bytes(data)))


def count_bound(ticks: int | None) -> int:
    """The largest counter a report of a run of ``ticks`` ticks may carry:
    ``PER_TICK`` payloads per tick (an agent caps its own counters there);
    without the run's length, 2^53 (exact in JSON)."""
    return (int(ticks) + 1) * PER_TICK if ticks else 1 << 53


_COUNTER = re.compile(r"rejected\.[a-z][a-z-]{0,31}")
_SCALAR_SET = frozenset(SCALARS)


def decode_report(data, *, run_id: str | None = None, sender: int | None = None,
                  n: int | None = None, m: int | None = None, ticks: int | None = None,
                  agents: int | None = None, max_abs: float = MAX_ABS, max_cond: float = MAX_COND) -> Report:
    """``ticks``: the run's length, which bounds every counter (``count_bound``);
    ``agents``: the run's agent count, which bounds "f" and "nf". The
    estimate passes the checks of a message (``estimate_problem``)."""
    doc = _open(data, "report", run_id, limits("report", n, m, agents))
    s, n, m, dv = _estimate_head(doc, sender, n, m)
    x, P, d = _estimate(doc, n, m, max_abs, max_cond)
    c = doc.get("c", {})
    if not isinstance(c, dict) or len(c) > MAX_COUNTERS:
        raise Rejected("schema", "field 'c' is not a map of counters")
    bound = count_bound(ticks)
    if not (c.keys() <= _SCALAR_SET and all(type(v) is int and 0 <= v <= bound for v in c.values())):
        for k, v in c.items():  # not the usual report (known scalars in bounds): name what is wrong
            if not (k in SCALARS or _COUNTER.fullmatch(k)):
                raise Rejected("schema", f"field 'c': unknown counter {k[:MAX_STR]!r}")
            if not _is_int(v):
                raise Rejected("schema", f"field 'c': counter {k!r} is not an int")
            if not 0 <= v <= bound:
                raise Rejected("size", f"field 'c': counter {k!r} = {v}, expected 0 .. {bound}")
    links = agents if agents is not None else MAX_LINKS
    f, nf = doc.get("f", []), doc.get("nf", [])
    if not isinstance(f, list) or len(f) > links or not _ints(f):
        raise Rejected("schema", f"field 'f' is not a list of at most {links} ids")
    if not isinstance(nf, list) or len(nf) > links or not all(
            isinstance(e, list) and len(e) == 2 and _is_int(e[0]) and isinstance(e[1], str)
            and len(e[1]) <= MAX_VERDICT for e in nf):
        raise Rejected("schema", f"field 'nf' is not a list of at most {links} [id, verdict] pairs")
    sent = doc.get("od", b"")
    if not isinstance(sent, bytes) or len(sent) not in (0, DIGEST_BYTES):
        raise Rejected("schema", f"field 'od' is not a {DIGEST_BYTES}-byte digest")
    fd = doc.get("fd", [])
    if not isinstance(fd, list) or len(fd) not in (0, len(f)) or not (
            set(map(type, fd)) <= _BYTES and set(map(len, fd)) <= _DIGEST_LEN):
        raise Rejected("schema", f"field 'fd' is not one {DIGEST_BYTES}-byte digest per sender of 'f'")
    rj = doc.get("rj")
    if rj is not None and not (isinstance(rj, list) and len(rj) == 2 and _ints(rj)
                               and 1 <= rj[0] <= doc["t"] and rj[1] >= -1):
        raise Rejected("schema", "field 'rj' is not [tick <= the report's tick, source id or -1]")
    restart = None if rj is None else (rj[0], None if rj[1] < 0 else rj[1])
    return Report(doc["run"], s, doc["t"], x, P, d, dv, c, tuple(f), tuple((i, v) for i, v in nf), sent, tuple(fd),
                  restart)


def decode_tick(data, *, run_id: str | None = None, agents: int | None = None) -> Tick:
    doc = _open(data, "tick", run_id, limits("tick", agents))
    K, seed = _field(doc, "K", int), _field(doc, "seed", int)
    alg, topo = _field(doc, "alg", str), _field(doc, "topo", str)
    rng = doc.get("range")
    if not isinstance(rng, (float, int)) or isinstance(rng, bool) or math.isnan(rng):
        raise Rejected("schema", "field 'range' missing or not a number")
    live = _field(doc, "live", list)
    if not _ints(live):
        raise Rejected("schema", "field 'live' is not a list of ids")
    blob = doc.get("pos")
    if not isinstance(blob, bytes) or len(blob) % 16:
        raise Rejected("shape", "field 'pos' is not N x 2 float64")
    N = len(blob) // 16
    if agents is not None and N != agents:
        raise Rejected("shape", f"{N} positions, expected {agents}")
    pos = _floats(doc, "pos", 2 * N).reshape(N, 2)
    ho = doc.get("ho", b"")
    if not isinstance(ho, bytes) or len(ho) not in (0, HOLDER_BYTES * len(live)):
        raise Rejected("shape", f"field 'ho' is not {HOLDER_BYTES} bytes per live id")
    return Tick(doc["run"], doc["t"], K, seed, alg, topo, float(rng), pos, tuple(live), ho)


def decode_measurement(data, *, run_id: str | None = None, agent: int | None = None,
                       p: int | None = None) -> Measurement:
    doc = _open(data, "meas", run_id, limits("meas", p))
    to = _field(doc, "to", int)
    if agent is not None and to != agent:
        raise Rejected("sender", f"measurement for agent {to}, this is agent {agent}")
    has = doc.get("has")
    if not isinstance(has, bool):
        raise Rejected("schema", "field 'has' missing or not bool")
    blob = doc.get("y")
    size = (len(blob) // 8) if isinstance(blob, bytes) else 0
    want = (p if p is not None else size) if has else 0
    y = _floats(doc, "y", want)
    return Measurement(doc["run"], doc["t"], to, has, y)


def decode_stop(data, *, run_id: str | None = None) -> Stop:
    doc = _open(data, "stop", run_id, limits("stop"))
    return Stop(doc["run"], doc["t"], str(doc.get("why", "")))


def decode_join(data, *, run_id: str | None = None, sender: int | None = None) -> Join:
    doc = _open(data, "join", run_id, limits("join"))
    return Join(doc["run"], _check_sender(doc, sender), doc["t"])


def decode_start(data, *, run_id: str | None = None, agent: int | None = None, tick: int | None = None,
                 n: int | None = None, m: int | None = None, max_abs: float = MAX_ABS,
                 max_cond: float = MAX_COND) -> Start:
    """The estimate a (re)joining agent starts from, for ``agent`` joining at
    ``tick``, checked as the guard checks a message (``guard.GuardConfig``'s
    ``max_abs`` and ``max_cond``)."""
    doc = _open(data, "start", run_id, limits("start", n, m))
    s, n, m, dv = _estimate_head(doc, agent, n, m)
    if tick is not None and doc["t"] != tick:
        raise Rejected("schema", f"tick {doc['t']}, expected {tick}")
    src = _field(doc, "src", int)
    x, P, d = _estimate(doc, n, m, max_abs, max_cond)
    return Start(doc["run"], s, doc["t"], None if src < 0 else src, x, P, d, dv)
