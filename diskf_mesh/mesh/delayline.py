"""Holds message copies until the fault model says they arrive.

``DelayLine(deliver)`` calls ``deliver(item)`` once per submitted copy, after
its delay: a copy with no delay is delivered at once in the caller's thread,
delayed ones by one daemon thread in due order (ties in submission order).
``close()`` stops the thread within its timeout and returns the copies that
were still in flight, so the caller can count them (a copy that had not
arrived when the run ended missed its tick: late).
"""
from __future__ import annotations

import heapq
import itertools
import threading
import time


class DelayLine:
    def __init__(self, deliver, clock=time.monotonic):
        self._deliver = deliver
        self._clock = clock
        self._heap: list = []
        self._seq = itertools.count()
        self._cv = threading.Condition()
        self._thread: threading.Thread | None = None
        self._closed = False

    def submit(self, item, delay_s: float) -> None:
        if delay_s <= 0.0:
            self._deliver(item)
            return
        with self._cv:
            if self._closed:
                return
            heapq.heappush(self._heap, (self._clock() + delay_s, next(self._seq), item))
            if self._thread is None:
                self._thread = threading.Thread(target=self._run, name="delayline", daemon=True)
                self._thread.start()
            self._cv.notify()

    @property
    def in_flight(self) -> int:
        with self._cv:
            return len(self._heap)

    def _run(self) -> None:
        while True:
            with self._cv:
                while not self._closed and (not self._heap or self._heap[0][0] > self._clock()):
                    wait = None if not self._heap else self._heap[0][0] - self._clock()
                    self._cv.wait(timeout=wait if wait is None else max(wait, 0.0))
                if self._closed:
                    return
                _, _, item = heapq.heappop(self._heap)
            self._deliver(item)  # outside the lock: the callback may submit again

    def close(self, timeout: float = 1.0) -> list:
        """Stop; return the items not yet delivered, in due order."""
        with self._cv:
            self._closed = True
            left = [item for _, _, item in sorted(self._heap)]
            self._heap.clear()
            self._cv.notify_all()
        if self._thread is not None:
            self._thread.join(timeout)
        return left
