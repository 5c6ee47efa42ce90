"""The world's check as the run goes, in a thread of its own beside the world's callbacks.

``CheckThread`` has the interface of ``mesh.protocol.run_status.OnlineCheck``
that ``WorldMachine`` calls (``submit``, ``result``): ``submit(rec, k)``
takes a copy of tick k's reports (its rows of the record, its digests, the
rejoins and starting states: ``tick_copy``) and queues it for a thread that holds its own
``OnlineCheck`` (made by ``make()`` there, the same engine replay on the
same trace) and its own record of what it was handed (``take_tick``);
``result(rec, k, wait)`` hands back its finding, None while it is not done
unless ``wait``. The findings, and the tick each counts from, are the same
as a check on the world's timer (``WorldMachine._check_ticks``); what
changes is who waits: the world hands tick k over as the last effect of the
event that made it final, after tick k + 1's puts, and the thread replays it
while the agents work on tick k + 1, so the world's callbacks take the next
tick's reports meanwhile (between the thread's GIL slices) and the world
waits only before tick k + 2 opens. The copy is made under the world's lock,
so the thread reads nothing the callbacks write.

The thread's work counts in the world's "check" phase (``--profile``: its
CPU time, its wall time overlapping the world's), the world's waiting for it in "wait-check". An
exception in it is raised in the world as ``CheckFailed`` with its
traceback when the world next asks.

May import: core, estimators, data, engine (the mesh layer).
"""
from __future__ import annotations

import copy
import queue
import threading
import traceback

import numpy as np

from diskf_mesh.mesh.protocol.profile import NO_PHASES, Phases
from diskf_mesh.mesh.protocol.reports import RunReports
from diskf_mesh.mesh.protocol.world_machine import WorldRecord

JOIN_S = 2.0   # at the end, for the thread to finish the tick it is on


class CheckFailed(RuntimeError):
    """The check's thread failed (its traceback)."""


class CheckThread:
    """``OnlineCheck``'s ``submit`` and ``result`` (module docstring) in a
    thread of the world's process; ``make()`` makes its ``OnlineCheck``
    there; ``profile``: the world's ``Phases`` (the replay counts as
    "check")."""

    handed_over = True  # the world hands each tick over when it is final, and asks for the finding later

    def __init__(self, make, profile: Phases = NO_PHASES):
        self._ticks = queue.SimpleQueue()  # tick_copy of each tick handed over; None: the end
        self._cv = threading.Condition()
        self._found = {}     # tick -> finding, not asked for yet
        self._error = None   # the thread's traceback, if it failed
        self._sent = 0       # the last tick handed over
        self._prof = profile
        self._check = None   # the thread's OnlineCheck, once made
        self._thread = threading.Thread(target=self._serve, args=(make,), daemon=True, name="online-check")
        self._thread.start()

    def submit(self, rec, k: int) -> None:
        """Tick k's reports are final: hand a copy of them over (once)."""
        if k > self._sent:
            self._ticks.put(tick_copy(rec, k))
            self._sent = k

    def result(self, rec, k: int, wait: bool = True) -> list | None:
        """Tick k's finding (``OnlineCheck.tick``), None if it is not in yet
        and not ``wait``."""
        self.submit(rec, k)
        with self._cv:
            while k not in self._found:
                if self._error is not None:
                    raise CheckFailed(f"the online check failed at tick {k}:\n{self._error}")
                if not wait:
                    return None
                self._cv.wait()
            return self._found.pop(k)

    def close(self) -> None:
        """End the thread: it leaves after the tick it is on (at most
        ``JOIN_S``); once it has, its check lets the engine's state go
        (``OnlineCheck.close``) and keeps the ticks it replayed."""
        self._ticks.put(None)
        self._thread.join(JOIN_S)
        if not self._thread.is_alive() and self._check is not None:
            self._check.close()

    def kept(self, trace, algorithm: str, params, run_id: str):
        """``OnlineCheck.kept`` of the thread's check once the thread has
        ended (None before: its ticks may still change)."""
        if self._thread.is_alive() or self._check is None:
            return None
        return self._check.kept(trace, algorithm, params, run_id)

    def _serve(self, make) -> None:
        """The thread: make the check, then check each tick handed over, in order."""
        try:
            check = self._check = make()
            B, K, N = check.trace.has.shape
            rec = WorldRecord(**RunReports.empty(K, N, check.trace.model.n, check.trace.model.m, sparse=True),
                              live=np.zeros((K, N), dtype=bool))
            while (tick := self._ticks.get()) is not None:
                self._prof.begin(beside=True)
                try:
                    k, said = take_tick(tick, rec)
                    found = check.tick(rec, k, said)
                finally:
                    self._prof.end("check")
                with self._cv:
                    self._found[k] = found
                    self._cv.notify_all()
        except Exception:  # noqa: BLE001 - the world raises it when it asks
            with self._cv:
                self._error = traceback.format_exc()
                self._cv.notify_all()


ROWS = ("x", "P", "d", "d_valid", "reported", "fused")  # the record's arrays of a tick that the check reads


def tick_copy(rec, k: int) -> tuple:
    """A copy of tick k of the world's record ``rec`` for the check's thread
    (``take_tick``): (k, its rows of ``ROWS``, its row of live or None where
    ``rec`` holds no live sets, its digests as ``tick_digests`` gives them,
    the rejoins and the starting states). Taken under the world's lock, so
    the thread reads nothing the callbacks write later."""
    t, live = k - 1, getattr(rec, "live", None)
    return (k, {name: getattr(rec, name)[t].copy() for name in ROWS}, None if live is None else live[t].copy(),
            rec.tick_digests(k), copy.deepcopy(getattr(rec, "rejoins", None) or {}),
            list(getattr(rec, "starts", ())))


def take_tick(tick: tuple, rec) -> tuple:
    """``tick_copy``'s tick written into ``rec`` (a record of the run's
    shape): (the tick, its digests as ``tick_digests`` gives them)."""
    k, rows, live, said, rejoins, starts = tick
    for name, row in rows.items():
        getattr(rec, name)[k - 1] = row
    if live is None:
        rec.live = None
    else:
        rec.live[k - 1] = live
    rec.rejoins, rec.starts = rejoins, starts
    return k, said
