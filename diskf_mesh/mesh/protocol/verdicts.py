"""What an agent tells the world about the messages of each tick it fused.

Every report of tick k carries (``wire.Report``) the senders whose messages
went into the fused estimate and, for every other sender linked at tick k,
why not:

    lost                 the link dropped it (``faults.FaultModel``); on the
                         simulated network also what the network lost
                         (``WorldMachine``'s ``verdicts``: ``simrun.NetworkLosses``)
    late                 no copy had arrived when the agent closed tick k
                         (a copy that comes later is counted late and dropped;
                         over zenoh a message lost on the way is late too)
    rejected:<reason>    the guard refused it (``guard.REASONS``), or fusion
                         failed on the tick's messages ("rejected:fusion")

A recording (``diskf_mesh.recording``) keeps both; ``replay`` re-runs the
engine on exactly the fused senders. ``TickVerdicts`` is the agent's side:
it turns a closed tick (what the receive path accounted, refused and handed
to fusion) into the report's two fields.
"""
from __future__ import annotations



class TickVerdicts:
    """The report's two fields of each closed tick."""

    def of_tick(self, k: int, linked, heard, rejected, fused, fusion_failed: bool = False) -> tuple:
        """(fused ids, ((sender, verdict), ...)) of tick k. ``linked``: the
        senders linked at k; ``heard``: the senders accounted for at k but
        not fused, or a superset (``Receiver.dropped(k)``: dropped by the
        link or refused; ``Receiver.accounted(k)``: arrived too), taken just
        before the inbox was emptied; ``rejected``: ``Receiver.refusals(k)``, {sender: the guard's
        reason}; ``fused``: the senders whose messages were handed to fusion."""
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
