"""The receive path of one agent: guard, range gate, the link's faults, the inbox.

    a neighbour's message as the agent's edge read it (``MessageArrived``:
    its key's id, its decode and the checks of its own values, each once)
      -> ``Guard.judge``      rejected (counted by reason; one that named a
                              tick in the window accounts for its sender at
                              that tick), or the decoded message, its tick
                              in the window around the agent's
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

The agent's machine (``mesh.protocol.agent_machine``) calls ``on_message``
for every message on a neighbour's key and, per tick, closes the tick once every
linked sender is ``accounted`` for (or at its deadline) with ``take(tick,
linked)``. A copy the fault layer delays waits in the ``DelayLine`` until
the time it is due: the machine sets a timer at ``next_due`` and calls
``arrive_due(now)`` when it fires. Without a fault model (or with an
inactive one) a copy goes straight to the inbox, so a fault-free run is
exactly the run without this layer.

No thread, no lock, no clock read: every call carries the time ``now`` of
the event that made it (the wall clock under the real transport, virtual
time in the simulated network), so a seeded run replays exactly.

``Inbox``: the one place a neighbour's message waits.

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
tick of the window. A taken tick remembers who came as the linked set it was
taken with (the agent's, shared from tick to tick) and the few linked senders
that did not come or the few others that did: nothing per sender heard.

Counts go to a ``Counters`` (arrived, duplicate, fused, late, unlinked; the
receiver counts what waited for a tick and never went on a link). No lock
and no clock: its agent's machine calls it, one event at a time, with the
time the event came.
"""
from __future__ import annotations

import dataclasses
import itertools
from operator import attrgetter

from diskf_mesh.data.faults import PERFECT, FaultConfig, FaultModel
from diskf_mesh.mesh.protocol.delayline import DelayLine
from diskf_mesh.mesh.protocol.events import MessageArrived
from diskf_mesh.mesh.protocol.guard import Guard
from diskf_mesh.mesh.wire import codec as wire
from diskf_mesh.mesh.wire.counters import Counters

_DIGEST, _MESSAGE = attrgetter("digest"), attrgetter("message")  # of a ``wire.WireMessage``


class Receiver:
    """The receive path of agent ``guard.config.me``; ``faults``: the link
    faults into it, a seeded ``FaultModel``, or a ``FaultConfig`` seeded
    with the run's seed once the world's first tick tells it
    (``learn_run``)."""

    def __init__(self, guard: Guard, faults: FaultConfig | FaultModel | None = None):
        self.guard = guard
        self.me = guard.config.me
        self.counters: Counters = guard.counters
        self._fault_config = faults if isinstance(faults, FaultConfig) and faults.active else None
        self.faults = faults if isinstance(faults, FaultModel) and faults.config.active else None
        self.inbox = Inbox(self.counters, keep=guard.config.max_lag)
        self._delay = DelayLine()
        self._copies_left: dict = {}   # send event -> copies not yet arrived
        self._heard: set = set()       # send events of which a copy arrived
        self._events = itertools.count()
        self._lost: dict = {}          # tick -> senders whose message of that tick the link dropped
        self._refused: dict = {}       # tick -> {sender: reason} whose message of that tick was rejected
        self._taken = (0, (), ())      # (tick, senders, their messages' digests) of the last ``take``
        self.tick = 0                  # the agent's current tick, for the guard's window (``advance``)

    def advance(self, tick: int) -> None:
        """The agent works on ``tick`` now: the guard's window follows it;
        messages waiting for an earlier tick's links never enter a link (the
        agent skipped that tick: out_of_range)."""
        if tick > self.tick:
            self.tick = tick
            self.counters.out_of_range += self.inbox.skipped(tick)

    def learn_run(self, ticks: int, seed: int) -> None:
        """The run's constants, from the world's first tick taken (before
        any neighbour's message went on a link): the guard's window ends at
        its last tick, and a ``FaultConfig`` is seeded with its seed."""
        self.guard.config = dataclasses.replace(self.guard.config, ticks=ticks)
        if self._fault_config is not None and self.faults is None:
            self.faults = FaultModel(self._fault_config, seed)

    def on_payload(self, sender, payload, links=None, now: float = 0.0) -> bool:
        """A payload on agent ``sender``'s message key (None: the key's id is
        not an integer) at ``now``: ``on_message`` of the guard's read."""
        return self.on_message(self.guard.read(sender, payload), links, now)

    def on_message(self, arrival: MessageArrived, links=None, now: float = 0.0) -> bool:
        """A neighbour's message as the agent's edge read it (``Guard.read``)
        at ``now``. ``links``: {tick: ids in range at that tick} for the
        ticks the world has opened (None: no range gate). Returns whether a
        wait may be over (a message or a refusal accounted for a sender)."""
        wm = self.guard.judge(arrival, self.tick)
        if not isinstance(wm, wire.WireMessage):
            if wm is not None and wm.tick is not None:
                self._refused.setdefault(wm.tick, {}).setdefault(arrival.sender, wm.reason)
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

    def on_messages(self, arrivals, links, now: float = 0.0) -> int:
        """Take from the front of the deque ``arrivals`` the messages that
        ``on_message`` would each put straight into the inbox, held for
        fusion at the current tick, in one call: decoded and passing their
        checks, of the current tick, from distinct linked senders not heard
        at that tick yet, with no fault model on the link; how many (0: the
        first one is not such a message, or the inbox would not hold a
        message of that tick now). Counted and held as ``on_message``
        counts and holds each one."""
        tick = self.tick
        linked = links.get(tick)
        if self.faults is not None or linked is None or not self.guard.in_window(tick, tick) \
                or not self.inbox.open(tick, now):
            return 0
        held, also = self.inbox.held(tick), self.inbox.also(tick)
        me, taken = self.me, {}
        for a in arrivals:
            if type(a) is not MessageArrived:
                break
            wm, s = a.message, a.sender
            if type(wm) is not wire.WireMessage or a.problem is not None or wm.tick != tick or s == me \
                    or s not in linked or s in held or s in also or s in taken:
                break
            taken[s] = wm
        n = len(taken)
        for _ in range(n):
            arrivals.popleft()
        if n:
            c = self.counters
            c.sent += n
            c.received += n
            self.inbox.hold(tick, taken)
        return n

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
        self.inbox.offer(wm.sender, wm.tick, wm, now)

    @property
    def in_flight(self) -> int:
        """Messages sent on a link of which no copy has arrived yet."""
        return sum(1 for e in self._copies_left if e not in self._heard)

    def dropped(self, tick: int) -> set:
        """Senders of ``tick`` accounted for without a message held: the
        (simulated) link dropped it, or it came and was rejected. Of the
        senders linked at ``tick`` and not fused, those ``accounted`` for
        are these (every linked sender held is fused), so a closed tick's
        verdicts need only them, never a copy of every sender heard."""
        lost, refused = self._lost.get(tick), self._refused.get(tick)
        return set(lost or ()) | set(refused or ())

    def accounted(self, tick: int) -> set:
        """Senders of ``tick`` that need no more waiting for: their message
        arrived, the (simulated) link dropped it, or it came and was rejected.
        Waiting for a message the fault layer has dropped could only end at
        the deadline with the same messages fused, so a loop may stop as soon
        as every expected sender is accounted for: a lossy run is then as
        fast as a clean one, and a poisoned neighbour costs no timeout."""
        return self.inbox.senders(tick) | self.dropped(tick)

    def all_accounted(self, tick: int, senders) -> bool:
        """Whether every one of ``senders`` is ``accounted`` for at ``tick``
        (fewer accounted for than senders: not all, without a look at each)."""
        held = self.inbox.held(tick)
        lost, refused = self._lost.get(tick, ()), self._refused.get(tick, ())
        if len(held) + len(lost) + len(refused) < len(senders):
            return False
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
        taken = self.inbox.take(tick, linked)
        senders, wms = tuple(zip(*taken)) or ((), ())
        self._taken = (tick, senders, tuple(map(_DIGEST, wms)))
        return list(zip(senders, map(_MESSAGE, wms)))

    def digests(self, tick: int) -> dict:
        """{sender: ``wire.WireMessage.digest``} of the copies fused at
        ``tick`` (the last ``take``; empty for another tick); forgets them."""
        t, senders, digests = self._taken
        self._taken = (0, (), ())
        return dict(zip(senders, digests)) if t == tick else {}

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


_NONE: dict = {}


class Inbox:
    def __init__(self, counters: Counters | None = None, keep: int | None = None):
        self.counters = counters if counters is not None else Counters()
        self.keep = keep             # ticks behind the last taken whose arrivals are remembered (None: all)
        self._held: dict = {}        # tick -> {sender: message}
        self._also: dict = {}        # tick -> senders arrived and not held (late; or held, then never fused)
        self._taken: dict = {}       # tick -> (linked, those linked not held) at its ``take``
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
        if self.arrived(tick, sender):
            c.duplicate += 1
            return "duplicate"
        if not self.open(tick, now):
            c.late += 1
            self._also.setdefault(tick, set()).add(sender)
            return "late"
        self._held.setdefault(tick, {})[sender] = message
        return "held"

    def arrived(self, tick: int, sender) -> bool:
        """Whether a copy of ``sender``'s message of ``tick`` arrived before
        (remembered ``keep`` ticks behind the last taken). A taken tick
        remembers its linked senders as the set it was taken with and those
        of them not held, not as a set of every sender that came."""
        if sender in self._held.get(tick, _NONE) or sender in self._also.get(tick, _NONE):
            return True
        taken = self._taken.get(tick)
        return taken is not None and sender in taken[0] and sender not in taken[1]

    def open(self, tick: int, now: float) -> bool:
        """Whether a copy of ``tick`` arriving at ``now`` from a sender not
        seen at ``tick`` is held (``offer``), not late."""
        return not (self._closed or tick <= self._closed_through or (
            self._due and tick in self._due and now > self._due[tick]))

    def also(self, tick: int):
        """The senders of ``tick`` that arrived and are not held (read-only,
        not copied): with ``held``, every sender of an open tick arrived so
        far."""
        return self._also.get(tick, _NONE)

    def hold(self, tick: int, messages: dict) -> None:
        """``offer`` of every {sender: message} of ``tick``, each the first
        copy of its sender, while ``tick`` is ``open``: all held."""
        self.counters.arrived += len(messages)
        self._held.setdefault(tick, {}).update(messages)

    def _unheld(self, tick: int, senders) -> None:
        """``senders`` of ``tick`` are no longer held: remembered as arrived."""
        if senders:
            self._also.setdefault(tick, set()).update(senders)

    def take(self, tick: int, linked) -> list:
        """[(sender, message)] of ``tick`` from ``linked`` senders, by sender id."""
        c = self.counters
        for t in [t for t in self._held if t < tick]:  # skipped ticks: never fused
            held = self._held.pop(t)
            c.late += len(held)
            self._unheld(t, held)
        held = self._held.pop(tick, {})
        linked = frozenset(linked)
        fused = sorted(held.keys() & linked) if held else []
        out = list(zip(fused, map(held.__getitem__, fused)))
        c.fused += len(out)
        c.unlinked += len(held) - len(out)
        if len(out) < len(held):
            self._unheld(tick, [s for s in held if s not in linked])
        if tick not in self._taken:  # taken again (nothing held then): what came the first time stays
            self._taken[tick] = (linked, {s for s in linked if s not in held} if len(out) < len(linked) else _NONE)
        self._closed_through = max(self._closed_through, tick)
        for t in [t for t in self._due if t <= tick]:
            del self._due[t]
        if self.keep is not None:
            for book in (self._also, self._taken):
                for t in [t for t in book if t < tick - self.keep]:
                    del book[t]
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
        for t, held in self._held.items():
            self._unheld(t, held)
        self._held.clear()
        self._closed = True
