"""What an agent tells the world about the messages of each tick it fused.

Every report of tick k carries (``wire.Report``) the senders whose messages
went into the fused estimate and, for every other sender linked at tick k,
why not:

    lost                 the link dropped it (``faults.FaultModel``)
    late                 no copy had arrived when the agent closed tick k
                         (a copy that comes later is counted late and dropped)
    rejected:<reason>    the guard refused it (``guard.REASONS``), or fusion
                         failed on the tick's messages ("rejected:fusion")

A recording (``diskf_mesh.recording``) keeps both; ``replay`` re-runs the
engine on exactly the fused senders. ``TickVerdicts`` is the agent's side:
it watches the guard's rejection counters around each neighbour's payload
in range, and turns a closed tick into the report's two fields.
"""
from __future__ import annotations

from ..counters import Counters

KEPT_TICKS = 16  # rejections are remembered this many ticks back (the guard's max_lag)


class TickVerdicts:
    def __init__(self, counters: Counters):
        self.counters = counters
        self._rejected: dict = {}  # tick -> {sender: reason}

    def on_payload(self, receive, key: str, payload, sender: int, tick: int) -> None:
        """``receive(key, payload)`` (the receive path) on a payload from
        ``sender`` for ``tick``; if the guard rejected it, remember why."""
        rejected = self.counters.rejected
        before = dict(rejected)
        receive(key, payload)
        if rejected != before:
            grown = [r for r, n in rejected.items() if n > before.get(r, 0)]
            if grown:
                self._rejected.setdefault(tick, {})[sender] = grown[0]

    def of_tick(self, k: int, linked, heard, fused, fusion_failed: bool = False) -> tuple:
        """(fused ids, ((sender, verdict), ...)) of tick k. ``linked``: the
        senders linked at k; ``heard``: ``Receiver.accounted(k)`` taken just
        before the inbox was emptied (arrived or dropped by the link);
        ``fused``: the senders whose messages were handed to fusion."""
        rejected = self._rejected.pop(k, {})
        for t in [t for t in self._rejected if t <= k - KEPT_TICKS]:
            del self._rejected[t]
        fused = sorted(fused)
        out = []
        for s in sorted(set(linked) - set(fused)):
            if s in rejected:
                out.append((s, f"rejected:{rejected[s]}"))
            else:
                out.append((s, "lost" if s in heard else "late"))
        if fusion_failed:
            out = sorted(out + [(s, "rejected:fusion") for s in fused])
            fused = []
        return tuple(fused), tuple(out)
