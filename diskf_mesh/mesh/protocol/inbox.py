"""An agent's inbox: the one place a neighbour's message waits.

A message waits here in one of two stages: before its link, for its tick to
open at this agent (the world's tick gives the links), and after its link
delivered it, until its tick is fused.

    ``wait_for_tick(sender, tick, m)``  a message whose tick the world has
                                      not opened here yet: held (first copy
                                      per (sender, tick); False for a repeat)
    ``opened(tick)``                  the world's tick is in: what waited for
                                      it, {sender: message}, goes on a link
    ``skipped(tick)``                 the agent works on ``tick`` now: how
                                      many waited for an earlier one (their
                                      tick was skipped; never on a link)

The estimator fuses only what arrived in time for its tick:

    ``offer(sender, tick, message, now)``  a copy that arrived at ``now``:
                                      the first copy of
                                      (sender, tick) is held; a later one is a
                                      duplicate (fused at most once); one for
                                      a tick already fused is late
    ``take(tick, linked)``            the messages of ``tick`` from the senders
                                      in ``linked``, sorted by sender id (so
                                      fusion sums in a fixed order); every
                                      other one held for ``tick`` is unlinked,
                                      and ``tick`` is closed: anything for it
                                      or an earlier tick that comes later is
                                      late
    ``close()``                       the run is over: whatever is still held
                                      never made it into fusion, late
    ``due(tick, at)``                 real time (``mesh.protocol.clock``): a copy of
                                      ``tick`` arriving after ``at`` (the
                                      agent's clock) is late, even before
                                      ``take``: it missed its deadline

Bounded: a (sender, tick) is remembered (to tell a duplicate) only for
``keep`` ticks behind the last tick taken; the receiver's guard refuses
anything older before it gets here, and anything further ahead than its
window, so what waits for its tick is one message per scenario agent and
tick of the window.

Counts go to a ``Counters`` (arrived, duplicate, fused, late, unlinked; the
receiver counts what waited for a tick and never went on a link). No lock
and no clock: its agent's machine calls it, one event at a time, with the
time the event came.
"""
from __future__ import annotations

from diskf_mesh.mesh.wire.counters import Counters


_NONE: dict = {}


class Inbox:
    def __init__(self, counters: Counters | None = None, keep: int | None = None):
        self.counters = counters if counters is not None else Counters()
        self.keep = keep             # ticks behind the last taken whose arrivals are remembered (None: all)
        self._seen: dict = {}        # tick -> senders arrived so far
        self._held: dict = {}        # tick -> {sender: message}
        self._closed_through = 0     # ticks <= this were fused
        self._closed = False         # the run is over: everything is late
        self._due: dict = {}         # tick -> deadline (real time): a copy after it is late
        self._early: dict = {}       # tick -> {sender: message} before the world's tick of that tick

    def wait_for_tick(self, sender: int, tick: int, message) -> bool:
        """Hold ``message`` of ``tick`` until the tick opens here; False (not
        held) if ``sender`` already has one waiting for it."""
        early = self._early.setdefault(tick, {})
        if sender in early:
            return False
        early[sender] = message
        return True

    def opened(self, tick: int) -> dict:
        """{sender: message} that waited for ``tick``, no longer held."""
        return self._early.pop(tick, {})

    def skipped(self, tick: int) -> int:
        """Drop what waited for a tick before ``tick``; how many."""
        old = [t for t in self._early if t < tick]
        return sum(len(self._early.pop(t)) for t in old)

    def due(self, tick: int, at: float) -> None:
        self._due[tick] = at

    def offer(self, sender: int, tick: int, message, now: float = 0.0) -> str:
        """A copy that arrived at ``now``; returns what happened: "held",
        "duplicate" or "late"."""
        c = self.counters
        c.arrived += 1
        seen = self._seen.setdefault(tick, set())
        if sender in seen:
            c.duplicate += 1
            return "duplicate"
        seen.add(sender)
        if self._closed or tick <= self._closed_through or (
                self._due and tick in self._due and now > self._due[tick]):
            c.late += 1
            return "late"
        self._held.setdefault(tick, {})[sender] = message
        return "held"

    def take(self, tick: int, linked) -> list:
        """[(sender, message)] of ``tick`` from ``linked`` senders, by sender id."""
        c = self.counters
        for t in [t for t in self._held if t < tick]:  # skipped ticks: never fused
            c.late += len(self._held.pop(t))
        held = self._held.pop(tick, {})
        linked = set(linked)
        out = sorted((s, msg) for s, msg in held.items() if s in linked) if held else []
        c.fused += len(out)
        c.unlinked += len(held) - len(out)
        self._closed_through = max(self._closed_through, tick)
        for t in [t for t in self._due if t <= tick]:
            del self._due[t]
        if self.keep is not None:
            for t in [t for t in self._seen if t < tick - self.keep]:
                del self._seen[t]
        return out

    def senders(self, tick: int) -> set:
        """Who has been heard for ``tick`` so far (to stop waiting early)."""
        return set(self._held.get(tick, ()))

    def held(self, tick: int):
        """The same, read-only and not copied: {sender: message} held for ``tick``."""
        return self._held.get(tick, _NONE)

    @property
    def pending(self) -> int:
        return sum(len(h) for h in self._held.values())

    def close(self) -> None:
        self.counters.late += sum(len(h) for h in self._held.values())
        self._held.clear()
        self._closed = True
