"""Who fused whom in a run, and the digests of what was fused, held sparse.

A run's record says, for every tick and receiver, which senders' messages
the receiver fused ([tick - 1, receiver, sender]: a (K, N, N) bool) and the
digest of each of those messages as the receiver reported it. Held dense,
that is K N^2 bytes and a Python object per fused message: 2 GB and 151
million digests for 10,000 random-geometric agents over 20 ticks.
``FusedSets`` holds each receiver's fused senders of a tick as an index
array (``uint16`` below 65,536 agents), and the digests once per (tick,
sender): a sender publishes one message a tick, so every receiver of it
reports the same digest; a receiver that reports another (a forged copy)
keeps its own. Memory grows with the messages fused, not with N^2.

``FusedSets`` reads as the dense array it stands for where a caller wants
one: ``sets[t]`` is tick t + 1's (N, N) bool, ``sets[:K]`` the first K
ticks (sparse), ``numpy.asarray(sets)`` the whole (K, N, N); ``sets[t] =
rows`` and ``sets[t, i, senders] = True`` write. ``FusedSets.digests`` is
the mapping (tick, receiver) -> (sender indices, digests) a run's claims
hold (``engine.verify.RunClaims.digests``); ``tick_digests(digests, k)``
gives one tick's as three arrays, from it or from a plain dict.

May import: core, estimators, data (the engine layer).
"""
from __future__ import annotations

from collections.abc import MutableMapping

import numpy as np

_NO_SENDERS = np.zeros(0, dtype=np.intp)


def digest_value(digest: bytes) -> int:
    """An 8-byte message digest as the unsigned integer claims hold."""
    return int.from_bytes(bytes(digest)[:8], "little")


def digest_values(digests) -> np.ndarray:
    """Several 8-byte digests as a (J,) uint64 array."""
    if not isinstance(digests, (list, tuple)):
        digests = list(digests)
    if set(map(len, digests)) <= _EIGHT:  # each 8 bytes already (a report's): joined as they are
        return np.frombuffer(b"".join(digests), dtype="<u8").astype(np.uint64)
    return np.frombuffer(b"".join(bytes(g)[:8] for g in digests), dtype="<u8").astype(np.uint64)


_EIGHT = frozenset((8,))


class FusedSets:
    """The (K, N, N) bool of who fused whom over ticks 1..K of N agents,
    each receiver's senders of a tick an index array (module docstring)."""

    dtype = np.dtype(bool)

    def __init__(self, K: int, N: int):
        self.shape = (int(K), int(N), int(N))
        self._index = np.uint16 if N <= 1 << 16 else np.uint32
        self._rows = [{} for _ in range(K)]   # [tick - 1] -> {receiver: its senders, sorted, unique}
        self.digests = FusedDigests(self)

    # -- reading ---------------------------------------------------------------
    def __len__(self) -> int:
        return self.shape[0]

    def senders(self, t: int, i: int) -> np.ndarray:
        """Receiver ``i``'s fused senders of tick t + 1 (indices, ascending)."""
        row = self._rows[t].get(i)
        return _NO_SENDERS if row is None else row.astype(np.intp)

    def receivers(self, t: int, j: int) -> list:
        """The receivers that fused sender ``j`` at tick t + 1, ascending."""
        return sorted(i for i, row in self._rows[t].items() if _holds(row, j))

    def tick(self, t: int) -> np.ndarray:
        """Tick t + 1 as a new (N, N) bool [receiver, sender]."""
        N = self.shape[1]
        out = np.zeros((N, N), dtype=bool)
        for i, row in self._rows[t].items():
            out[i, row] = True
        return out

    def __getitem__(self, key):
        if isinstance(key, (int, np.integer)):
            return self.tick(range(self.shape[0])[key])
        ticks = range(self.shape[0])[key] if isinstance(key, slice) else None
        if ticks is not None and ticks.start == 0 and ticks.step == 1:  # the first ticks, sparse
            out = FusedSets(len(ticks), self.shape[1])
            out._rows = [self._rows[t] for t in ticks]  # the same rows (read as a cut, never written)
            out.digests = self.digests.cut(ticks)
            return out
        return np.asarray(self)[key]

    def __iter__(self):
        return (self.tick(t) for t in range(self.shape[0]))

    def __array__(self, dtype=None, copy=None):
        out = np.zeros(self.shape, dtype=bool)
        for t in range(self.shape[0]):
            for i, row in self._rows[t].items():
                out[t, i, row] = True
        return out if dtype is None else out.astype(dtype)

    # -- writing ---------------------------------------------------------------
    def __setitem__(self, key, value) -> None:
        if isinstance(key, tuple) and len(key) == 3 and value is True:  # sets[t, i, senders] = True
            self.mark(int(key[0]), int(key[1]), key[2])
            return
        ticks = range(self.shape[0])[key]
        if isinstance(ticks, int):
            ticks, value = [ticks], np.asarray(value, dtype=bool)[None]
        else:
            value = np.broadcast_to(np.asarray(value, dtype=bool), (len(ticks),) + self.shape[1:])
        for n, t in enumerate(ticks):
            self.digests.forget(t)
            self._rows[t] = {i: np.flatnonzero(r).astype(self._index) for i, r in enumerate(value[n]) if r.any()}

    def mark(self, t: int, i: int, senders) -> None:
        """Receiver ``i`` fused ``senders`` (indices) at tick t + 1, besides
        what it is marked with already."""
        new = np.unique(np.asarray(senders, dtype=np.int64)).astype(self._index)
        old = self._rows[t].get(i)
        if old is not None:
            self.digests.pin(t + 1, i)  # digests said of the row as it was stay as they were said
            new = np.union1d(old, new).astype(self._index)
        if len(new):
            self._rows[t][i] = new


def _holds(row: np.ndarray, j: int) -> bool:
    at = int(np.searchsorted(row, j))
    return at < len(row) and int(row[at]) == j


class FusedDigests(MutableMapping):
    """(tick, receiver) -> (sender indices (J,) intp, digests (J,) uint64)
    of the messages the receiver said it fused, held once per (tick,
    sender) where its senders are its row of ``sets`` (sorted by sender;
    otherwise, and where its digest differs from the one held, its own).
    A value may be set as (senders, digests) in any order, the digests
    8-byte ``bytes`` or their ``digest_values``."""

    def __init__(self, sets: FusedSets):
        self._sets = sets
        self._one = {}      # tick -> ((N,) uint64 the first digest said of each sender's message, (N,) bool said)
        self._rows = {}     # tick -> receivers whose digests are their row's, as held in ``_one``
        self._odd = {}      # (tick, receiver) -> (positions in its row, digests) that differ from ``_one``
        self._own = {}      # (tick, receiver) -> (senders, digests) not its row's: held whole

    def __setitem__(self, key, value) -> None:
        tick, i = key
        senders, gs = value
        senders = np.asarray(senders, dtype=np.intp).reshape(-1)
        gs = np.asarray(gs, dtype=np.uint64) if isinstance(gs, np.ndarray) else digest_values(gs)
        order = np.argsort(senders, kind="stable")
        senders, gs = senders[order], gs[order]
        self._drop(tick, i)
        row = self._sets._rows[tick - 1].get(i) if 1 <= tick <= len(self._sets) else None
        if row is None or len(row) != len(senders) or not np.array_equal(row, senders):
            self._own[key] = (senders, gs)
            return
        N = self._sets.shape[1]
        first, said = self._one.setdefault(tick, (np.zeros(N, dtype=np.uint64), np.zeros(N, dtype=bool)))
        new = ~said[senders]
        first[senders[new]], said[senders[new]] = gs[new], True
        differ = np.flatnonzero(first[senders] != gs)
        if len(differ):
            self._odd[key] = (differ, gs[differ])
        self._rows.setdefault(tick, set()).add(i)

    def __getitem__(self, key) -> tuple:
        own = self._own.get(key)
        if own is not None:
            return own[0].copy(), own[1].copy()
        tick, i = key
        if i not in self._rows.get(tick, ()):
            raise KeyError(key)
        senders = self._sets.senders(tick - 1, i)
        gs = self._one[tick][0][senders]
        odd = self._odd.get(key)
        if odd is not None:
            gs[odd[0]] = odd[1]
        return senders, gs

    def __delitem__(self, key) -> None:
        if key not in self:
            raise KeyError(key)
        self._drop(*key)

    def __contains__(self, key) -> bool:
        return key in self._own or (isinstance(key, tuple) and len(key) == 2 and key[1] in self._rows.get(key[0], ()))

    def __iter__(self):
        for key in sorted(set(self._own) | {(t, i) for t, rows in self._rows.items() for i in rows}):
            yield key

    def __len__(self) -> int:
        return len(self._own) + sum(len(rows) for rows in self._rows.values())

    def tick(self, k: int) -> tuple:
        """Tick k's digests as three (J,) arrays, receivers in order:
        receivers, senders (intp) and digests (uint64)."""
        keys = sorted({i for t, i in self._own if t == k} | self._rows.get(k, set()))
        parts = [self[(k, i)] for i in keys]
        rows = np.repeat(np.array(keys, dtype=np.intp), [len(s) for s, _ in parts]) if parts else _NO_SENDERS
        return (rows, np.concatenate([s for s, _ in parts]) if parts else _NO_SENDERS.copy(),
                np.concatenate([g for _, g in parts]) if parts else np.zeros(0, dtype=np.uint64))

    def _drop(self, tick: int, i: int) -> None:
        self._own.pop((tick, i), None)
        self._odd.pop((tick, i), None)
        rows = self._rows.get(tick)
        if rows is not None:
            rows.discard(i)

    def pin(self, tick: int, i: int) -> None:
        """Receiver ``i``'s row of ``tick`` is about to change: its digests,
        if held as its row's, are held whole from now on."""
        if i in self._rows.get(tick, ()):
            self._own[(tick, i)] = self[(tick, i)]
            self._rows[tick].discard(i)
            self._odd.pop((tick, i), None)

    def forget(self, t: int) -> None:
        """Tick t + 1's rows are written anew: what was said of them is held whole."""
        for i in sorted(self._rows.get(t + 1, ())):
            self.pin(t + 1, i)

    def cut(self, ticks: range) -> "FusedDigests":
        """The digests of ``ticks`` (0-based, the first ones: 0, 1, ...),
        sharing what they hold."""
        out = FusedDigests(self._sets)
        last = ticks.stop
        out._one = {k: v for k, v in self._one.items() if k <= last}
        out._rows = {k: v for k, v in self._rows.items() if k <= last}
        out._odd = {key: v for key, v in self._odd.items() if key[0] <= last}
        out._own = {key: v for key, v in self._own.items() if key[0] <= last}
        return out


def tick_digests(digests, k: int) -> tuple:
    """Tick k of ``digests`` ((tick, receiver) -> (senders, digests as
    uint64), a ``FusedDigests`` or a plain dict) as three (J,) arrays,
    receivers in order: receivers, senders (intp), digests (uint64)."""
    if isinstance(digests, FusedDigests):
        return digests.tick(k)
    keys = sorted(i for t, i in digests if t == k)
    parts = [digests[(k, i)] for i in keys]
    rows = [i for i, (s, _) in zip(keys, parts) for _ in range(len(s))]
    values = [gs if isinstance(gs, np.ndarray) else digest_values(gs) for _, gs in parts]
    return (np.array(rows, dtype=np.intp), np.array([j for s, _ in parts for j in s], dtype=np.intp),
            np.concatenate(values).astype(np.uint64) if values else np.zeros(0, dtype=np.uint64))


def first_digests(digests, K: int):
    """``digests`` ((tick, receiver) -> ..., a ``FusedDigests`` or a plain
    dict) of ticks 1..K only."""
    if isinstance(digests, FusedDigests):
        return digests.cut(range(K))
    return {key: v for key, v in digests.items() if key[0] <= K}
