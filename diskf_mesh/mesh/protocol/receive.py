"""The receive path of one agent: guard, range gate, the link's faults, the inbox.

    payload on a neighbour's key (its id parsed once, by the agent)
      -> ``Guard.screen``     rejected (counted by reason; one that named a
                              tick in the window accounts for its sender at
                              that tick), or a decoded message (decoded
                              once, every value and the tick window checked
                              once)
      -> range gate           the sender not in range at the message's tick:
                              out_of_range += 1, never on a link. A message
                              whose tick the world has not opened here yet
                              waits for it in the inbox
                              (``Inbox.wait_for_tick``, ``release``), first
                              copy per (sender, tick), before the link: a
                              link's latency runs from when its receiver
                              knows the tick, as in the engine's fault
                              model (``faults.delivered_links``)
      -> sent += 1
      -> ``FaultModel.plan``  lost (lost += 1), or one or two copies with delays
      -> ``DelayLine``        holds each copy until it is due
      -> received += 1 at the message's first copy
      -> ``Inbox.offer``      every copy: held (later fused or unlinked),
                              duplicate or late

Every map here is bounded by the guard's window (``max_lag`` + ``max_lead``
+ 1 ticks) times the scenario's agents: what a flood of other ids, ticks or
copies sends costs counts, never memory.

The agent's machine (``mesh.protocol.agent_machine``) calls ``on_payload`` for every
payload on a neighbour's key and, per tick, closes the tick once every
linked sender is ``accounted`` for (or at its deadline) with ``take(tick,
linked)``. A copy the fault layer delays waits in the ``DelayLine`` until
the time it is due: the machine sets a timer at ``next_due`` and calls
``arrive_due(now)`` when it fires. Without a fault model (or with an
inactive one) a copy goes straight to the inbox, so a fault-free run is
exactly the run without this layer.

No thread, no lock, no clock read: every call carries the time ``now`` of
the event that made it (the wall clock under the real transport, virtual
time in the simulated network), so a seeded run replays exactly.
"""
from __future__ import annotations

import itertools

from diskf_mesh.mesh.wire import codec as wire
from diskf_mesh.mesh.wire.counters import Counters
from diskf_mesh.mesh.protocol.delayline import DelayLine
from diskf_mesh.data.faults import PERFECT, FaultModel
from diskf_mesh.mesh.protocol.guard import Guard
from diskf_mesh.mesh.protocol.inbox import Inbox


class Receiver:
    def __init__(self, guard: Guard, faults: FaultModel | None = None):
        self.guard = guard
        self.me = guard.config.me
        self.counters: Counters = guard.counters
        self.faults = faults if faults is not None and faults.config.active else None
        self.inbox = Inbox(self.counters, keep=guard.config.max_lag)
        self._delay = DelayLine()
        self._copies_left: dict = {}   # send event -> copies not yet arrived
        self._heard: set = set()       # send events of which a copy arrived
        self._events = itertools.count()
        self._lost: dict = {}          # tick -> senders whose message of that tick the link dropped
        self._refused: dict = {}       # tick -> {sender: reason} whose message of that tick was rejected
        self._digests: dict = {}       # tick -> {sender: digest of the copy held for fusion}
        self.tick = 0                  # the agent's current tick, for the guard's window (``advance``)

    def advance(self, tick: int) -> None:
        """The agent works on ``tick`` now: the guard's window follows it;
        messages waiting for an earlier tick's links never enter a link (the
        agent skipped that tick: out_of_range)."""
        if tick > self.tick:
            self.tick = tick
            self.counters.out_of_range += self.inbox.skipped(tick)

    def on_payload(self, sender, payload, links=None, now: float = 0.0) -> bool:
        """A payload on agent ``sender``'s message key (None: the key's id is
        not an integer) at ``now``. ``links``: {tick: ids in range at that
        tick} for the ticks the world has opened (None: no range gate).
        Returns whether a wait may be over (a message or a refusal accounted
        for a sender)."""
        wm = self.guard.screen(sender, payload, self.tick)
        if not isinstance(wm, wire.WireMessage):
            if wm is not None and wm.tick is not None:
                self._refused.setdefault(wm.tick, {}).setdefault(sender, wm.reason)
                return True
            return False
        if links is not None:
            linked = links.get(wm.tick)
            if linked is None:  # its tick is not open here yet: it waits in the inbox
                if not self.inbox.wait_for_tick(wm.sender, wm.tick, wm):
                    self._repeated()
                return False
            if wm.sender not in linked:
                self.counters.out_of_range += 1
                return False
        self._link(wm, now)
        return True

    def release(self, tick: int, linked, now: float = 0.0) -> None:
        """The world's tick ``tick`` is in (at ``now``): what waited for it
        goes on a link (a sender in ``linked``) or is out of range."""
        for s, wm in self.inbox.opened(tick).items():
            if s in linked:
                self._link(wm, now)
            else:
                self.counters.out_of_range += 1

    def _repeated(self) -> None:
        """A sender repeated a message still waiting for its tick: counted as
        the link counts a repeat (sent, received, arrived, a duplicate),
        without holding it."""
        c = self.counters
        c.sent += 1
        c.received += 1
        c.arrived += 1
        c.duplicate += 1

    def _link(self, wm, now: float) -> None:
        """Put ``wm`` on its link at ``now``: lost, or each copy into the inbox
        now or into the delay line until it is due."""
        self.counters.sent += 1
        plan = PERFECT if self.faults is None else self.faults.plan(wm.sender, self.me, wm.tick)
        if not plan:
            self.counters.lost += 1
            self._lost.setdefault(wm.tick, set()).add(wm.sender)
            return
        event = next(self._events)
        self._copies_left[event] = len(plan)
        for d in plan:
            if d.delay_s > 0:
                self._delay.push((event, wm), now + d.delay_s)
            else:
                self._arrive((event, wm), now)

    @property
    def next_due(self) -> float:
        """When the next delayed copy is due (inf: none in flight)."""
        return self._delay.next_at

    def arrive_due(self, now: float) -> bool:
        """The delayed copies due by ``now`` arrive; whether any did."""
        items = self._delay.due(now)
        for item in items:
            self._arrive(item, now)
        return bool(items)

    def _arrive(self, item, now: float) -> None:
        event, wm = item
        if event not in self._heard:
            self._heard.add(event)
            self.counters.received += 1
        self._copies_left[event] -= 1
        if not self._copies_left[event]:
            del self._copies_left[event]
            self._heard.discard(event)
        if self.inbox.offer(wm.sender, wm.tick, wm.message, now) == "held":
            self._digests.setdefault(wm.tick, {})[wm.sender] = wm.digest

    @property
    def in_flight(self) -> int:
        """Messages sent on a link of which no copy has arrived yet."""
        return sum(1 for e in self._copies_left if e not in self._heard)

    def accounted(self, tick: int) -> set:
        """Senders of ``tick`` that need no more waiting for: their message
        arrived, the (simulated) link dropped it, or it came and was rejected.
        Waiting for a message the fault layer has dropped could only end at
        the deadline with the same messages fused, so a loop may stop as soon
        as every expected sender is accounted for: a lossy run is then as
        fast as a clean one, and a poisoned neighbour costs no timeout."""
        heard = self.inbox.senders(tick)
        lost, refused = self._lost.get(tick), self._refused.get(tick)
        if lost:
            heard |= lost
        if refused:
            heard |= refused.keys()
        return heard

    def all_accounted(self, tick: int, senders) -> bool:
        """Whether every one of ``senders`` is ``accounted`` for at ``tick``
        (stops at the first that is not: one look per arrival)."""
        held = self.inbox.held(tick)
        lost, refused = self._lost.get(tick, ()), self._refused.get(tick, ())
        return all(s in held or s in lost or s in refused for s in senders)

    def refusals(self, tick: int) -> dict:
        """{sender: the guard's reason} of the messages of ``tick`` it refused
        (the first refusal per sender), until ``take`` of that tick."""
        return dict(self._refused.get(tick, {}))

    def take(self, tick: int, linked) -> list:
        """[(sender, message)] to fuse at ``tick``, sorted by sender id."""
        for book in (self._lost, self._refused):
            for t in [t for t in book if t <= tick]:
                del book[t]
        return self.inbox.take(tick, linked)

    def digests(self, tick: int) -> dict:
        """{sender: ``wire.WireMessage.digest``} of the copies of ``tick`` held
        for fusion (after ``take``: what was fused); forgets ``tick`` and
        every earlier one."""
        out = self._digests.pop(tick, {})
        for t in [t for t in self._digests if t < tick]:
            del self._digests[t]
        return out

    def use_faults(self, faults: FaultModel | None) -> None:
        """Set the link faults once the run's seed is known (before any
        neighbour's message was let through)."""
        self.faults = faults if faults is not None and faults.config.active else None

    def snapshot(self, cap: int | None = None) -> dict:
        """The counters with the gauges (in flight, pending) filled in, flat
        (none above ``cap``)."""
        self.counters.in_flight = self.in_flight
        self.counters.pending = self.inbox.pending
        return self.counters.to_dict(cap)

    def close(self) -> Counters:
        """End of run: copies still in flight or held arrive too late to count as fused."""
        self.inbox.close()
        for item in self._delay.drain():
            self._arrive(item, 0.0)
        self.counters.in_flight = self.counters.pending = 0
        return self.counters
