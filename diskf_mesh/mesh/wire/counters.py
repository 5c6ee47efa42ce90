"""What one agent did with the messages of a run, counted.

Counted on the receiving side, per agent, over the whole run:

    published   own messages this agent put on the wire (one per tick)
    sent        neighbours' well-formed messages that entered this agent's
                links (after the guard, before the fault layer)
    lost        of those, dropped by the link (no copy arrived)
    received    of those, arrived (counted at the first copy)
    arrived     copies that arrived: one per received message, plus the
                link's extra copies (duplication)
    duplicate   arrived copies of a (sender, tick) that had already arrived:
                the link's duplicates, or a sender repeating itself. A
                duplicate is fused at most once.
    fused       arrived in time for their tick and fused
    late        arrived after this agent fused their tick (or when the run
                ended), dropped
    unlinked    arrived in time, but the sender was not within range (or not
                alive) at that tick, so not fused
    out_of_range  messages from agents not within range (or not alive) at
                their tick, dropped by the radio-range gate before a link:
                never sent on one
    rejected    payloads the decoder or guard refused, by reason
                (``wire.REASONS`` and ``guard.REASONS``); never fused

and two gauges, the state when the counters were read (a report mid-run):

    in_flight   messages on a link of which no copy has arrived yet
    pending     arrived copies held for a tick not fused yet

The books balance at any report (``Counters.imbalance`` is empty):

    sent    = received + lost + in_flight
    arrived = fused + late + unlinked + duplicate + pending
"""
from __future__ import annotations

from dataclasses import dataclass, field, fields
from operator import attrgetter

SCALARS = ("published", "sent", "lost", "received", "arrived", "duplicate", "fused", "late", "unlinked",
           "out_of_range", "in_flight", "pending")
REJECTED_PREFIX = "rejected."


@dataclass
class Counters:
    published: int = 0
    sent: int = 0
    lost: int = 0
    received: int = 0
    arrived: int = 0
    duplicate: int = 0
    fused: int = 0
    late: int = 0
    unlinked: int = 0
    out_of_range: int = 0
    in_flight: int = 0
    pending: int = 0
    rejected: dict = field(default_factory=dict)

    def reject(self, reason: str, count: int = 1) -> None:
        self.rejected[reason] = self.rejected.get(reason, 0) + count

    @property
    def rejected_total(self) -> int:
        return sum(self.rejected.values())

    def imbalance(self) -> list:
        """The identities that do not hold, as text (empty: the books balance)."""
        in_flight, pending = self.in_flight, self.pending
        out = []
        if self.sent != self.received + self.lost + in_flight:
            out.append(f"sent {self.sent} != received {self.received} + lost {self.lost}"
                       + (f" + in flight {in_flight}" if in_flight else ""))
        if self.arrived != self.fused + self.late + self.unlinked + self.duplicate + pending:
            out.append(f"arrived {self.arrived} != fused {self.fused} + late {self.late} + unlinked {self.unlinked}"
                       f" + duplicate {self.duplicate}" + (f" + pending {pending}" if pending else ""))
        if self.arrived < self.received:
            out.append(f"arrived {self.arrived} < received {self.received}")
        return out

    def to_dict(self, cap: int | None = None) -> dict:
        """Flat {name: int}, rejections as ``rejected.<reason>`` (the report's
        "c" map); with ``cap``, no count above it (``wire.count_bound``: a
        receiver refuses a report with a larger one)."""
        out = dict(zip(SCALARS, map(int, _scalars(self))))
        if self.rejected:
            out.update({REJECTED_PREFIX + r: int(n) for r, n in sorted(self.rejected.items())})
        if cap is not None and max(out.values()) > cap:
            out = {k: min(v, cap) for k, v in out.items()}
        return out

    @classmethod
    def from_dict(cls, flat: dict) -> "Counters":
        c = cls(**{k: int(v) for k, v in flat.items() if k in SCALARS})
        c.rejected = {k[len(REJECTED_PREFIX):]: int(v) for k, v in flat.items() if k.startswith(REJECTED_PREFIX)}
        return c

    def to_json(self) -> dict:
        """Nested form for result files: the scalars and ``rejected: {reason: n}``."""
        out = dict(zip(SCALARS, map(int, _scalars(self))))
        out["rejected"] = dict(sorted(self.rejected.items()))
        return out


_scalars = attrgetter(*SCALARS)  # a ``Counters``'s scalars, in ``SCALARS`` order


def total(counters) -> Counters:
    """Sum over agents."""
    out = Counters()
    for c in counters:
        for f in fields(Counters):
            if f.name == "rejected":
                for r, n in c.rejected.items():
                    out.reject(r, n)
            else:
                setattr(out, f.name, getattr(out, f.name) + getattr(c, f.name))
    return out
