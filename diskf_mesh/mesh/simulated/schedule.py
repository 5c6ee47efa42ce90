"""A virtual clock and a deterministic event queue.

``Schedule`` holds what happens next in a simulated run as a priority queue
ordered by (time, sequence): two entries due at one time come out in the
order they went in, so a run depends on its seed and on nothing else (no
wall clock, no thread, no hash order). ``Trace`` folds every event a run
dispatches into one digest (and, if asked, keeps the lines): two runs of
one seed and one fault plan give the same digest, event for event.

May import: core, estimators, data, engine (the mesh layer).
"""
from __future__ import annotations

import hashlib
import heapq
import math
import struct
from typing import Any


class Schedule:
    """Entries (time, sequence, item); ``now`` is the time of the last one popped."""

    def __init__(self):
        self._heap = []
        self._seq = 0
        self.now = 0.0

    def at(self, t: float, item: Any) -> None:
        """``item`` at time ``t`` (never before now)."""
        if not math.isfinite(t):
            raise ValueError(f"an event at time {t!r}")
        self._seq += 1
        heapq.heappush(self._heap, (max(t, self.now), self._seq, item))

    def pop(self):
        """The next (time, item), advancing ``now``; None when nothing is left."""
        if not self._heap:
            return None
        t, _, item = heapq.heappop(self._heap)
        self.now = t
        return t, item

    def peek(self):
        """The next (time, item) without taking it; None when nothing is left."""
        return self._heap[0][::2] if self._heap else None

    def next_time(self) -> float:
        return self._heap[0][0] if self._heap else math.inf

    def __len__(self) -> int:
        return len(self._heap)


class Trace:
    """The digest of a run's events; ``keep`` also keeps them as lines (small runs, a failing seed)."""

    def __init__(self, keep: bool = False):
        self._h = hashlib.blake2b(digest_size=16)
        self.lines = [] if keep else None
        self.events = 0
        self.last = 0.0  # time of the last event

    def add(self, t: float, who: str, what: str, key: str = "", payload: bytes | None = None,
            digest: bytes | None = None) -> None:
        """One event; a payload is folded in as its length and its digest
        (``digest``: ``payload_digest(payload)``, made once for a payload many receive)."""
        self.events += 1
        self.last = t
        line = struct.pack("<d", t) + f"|{who}|{what}|{key}|".encode()
        if payload is not None:
            if digest is None:
                digest = payload_digest(payload)
            line += struct.pack("<q", len(payload)) + digest
        self._h.update(line)
        if self.lines is not None:
            tail = "" if payload is None else f" {len(payload)}B {digest[:4].hex()}"
            self.lines.append(f"{t:.6f} {who} {what} {key}{tail}")

    @property
    def digest(self) -> str:
        return self._h.hexdigest()


def payload_digest(payload: bytes) -> bytes:
    """What a trace folds in for a payload (16 bytes)."""
    return hashlib.blake2b(payload, digest_size=16).digest()
