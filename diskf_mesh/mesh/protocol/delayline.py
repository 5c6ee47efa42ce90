"""Holds message copies until the fault model says they arrive.

A pure queue on its owner's clock (no thread, no clock read): the receive
path (``mesh.protocol.receive``) pushes each delayed copy with the time it is due,
and its agent's machine sets a timer at ``next_at`` and takes ``due(now)``
when it fires, so a shell with the wall clock and the simulated network
with a virtual one deliver the same copies in the same order.

    ``push(item, at)``  hold ``item`` until ``at``
    ``due(now)``        the items due by ``now``, in due order (ties in the
                        order they were pushed), no longer held
    ``next_at``         when the next item is due (inf: none held)
    ``drain()``         every item still held, in due order (the run is
                        over: a copy that had not arrived missed its tick)
"""
from __future__ import annotations

import heapq
import itertools
import math


class DelayLine:
    def __init__(self):
        self._heap: list = []
        self._seq = itertools.count()

    def push(self, item, at: float) -> None:
        heapq.heappush(self._heap, (at, next(self._seq), item))

    def due(self, now: float) -> list:
        out = []
        while self._heap and self._heap[0][0] <= now:
            out.append(heapq.heappop(self._heap)[2])
        return out

    @property
    def next_at(self) -> float:
        return self._heap[0][0] if self._heap else math.inf

    @property
    def in_flight(self) -> int:
        return len(self._heap)

    def drain(self) -> list:
        left = [item for _, _, item in sorted(self._heap)]
        self._heap.clear()
        return left
