"""What one agent did with the messages of a run, counted.

Counted on the receiving side, per agent, over the whole run:

    published   own messages this agent put on the wire (one per tick)
    sent        neighbours' well-formed messages that entered this agent's
                links (after the guard, before the fault layer)
    lost        of those, dropped by the link (no copy arrived)
    received    of those, arrived (the first copy; counted once)
    duplicate   extra copies that arrived (a duplicate is fused once)
    fused       received in time for their tick and fused
    late        received after this agent fused their tick (or when the run
                ended), dropped
    unlinked    received in time, but the sender was not within range (or not
                alive) at that tick, so not fused
    rejected    payloads the decoder or guard refused, by reason
                (``wire.REASONS`` and ``guard.REASONS``); never fused

The books balance at the end of a run (``Counters.imbalance`` is empty):

    sent     = received + lost
    received = fused + late + unlinked
"""
from __future__ import annotations

from dataclasses import dataclass, field, fields

SCALARS = ("published", "sent", "lost", "received", "duplicate", "fused", "late", "unlinked")
REJECTED_PREFIX = "rejected."


@dataclass
class Counters:
    published: int = 0
    sent: int = 0
    lost: int = 0
    received: int = 0
    duplicate: int = 0
    fused: int = 0
    late: int = 0
    unlinked: int = 0
    rejected: dict = field(default_factory=dict)

    def reject(self, reason: str, count: int = 1) -> None:
        self.rejected[reason] = self.rejected.get(reason, 0) + count

    @property
    def rejected_total(self) -> int:
        return sum(self.rejected.values())

    def imbalance(self, in_flight: int = 0, pending: int = 0) -> list:
        """The identities that do not hold, as text (empty: the books balance).
        ``in_flight``: copies still on a link; ``pending``: received messages
        waiting for their tick."""
        out = []
        if self.sent != self.received + self.lost + in_flight:
            out.append(f"sent {self.sent} != received {self.received} + lost {self.lost}"
                       + (f" + in flight {in_flight}" if in_flight else ""))
        if self.received != self.fused + self.late + self.unlinked + pending:
            out.append(f"received {self.received} != fused {self.fused} + late {self.late}"
                       f" + unlinked {self.unlinked}" + (f" + pending {pending}" if pending else ""))
        return out

    def to_dict(self) -> dict:
        """Flat {name: int}, rejections as ``rejected.<reason>`` (the report's "c" map)."""
        out = {name: int(getattr(self, name)) for name in SCALARS}
        out.update({REJECTED_PREFIX + r: int(n) for r, n in sorted(self.rejected.items())})
        return out

    @classmethod
    def from_dict(cls, flat: dict) -> "Counters":
        c = cls(**{k: int(v) for k, v in flat.items() if k in SCALARS})
        c.rejected = {k[len(REJECTED_PREFIX):]: int(v) for k, v in flat.items() if k.startswith(REJECTED_PREFIX)}
        return c

    def to_json(self) -> dict:
        """Nested form for result files: the scalars and ``rejected: {reason: n}``."""
        out = {name: int(getattr(self, name)) for name in SCALARS}
        out["rejected"] = dict(sorted(self.rejected.items()))
        return out


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
