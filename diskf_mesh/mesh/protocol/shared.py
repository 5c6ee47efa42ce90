"""What the receivers of one payload may share: its decode, the checks
that depend on the payload alone, and the event a sample reads as.

Over zenoh each agent process decodes what it receives. On the simulated
network (``mesh.simulated``) one published payload reaches many machines in
one Python process: ``Shared`` keeps what the first receiver computed from a
payload (``wire.decode`` and the guard's checks of its values, the world's
``wire.decode_tick``) for the others. What depends on the receiver (the
tick window, the range gate, the link's faults, the inbox, every counter)
stays with each receiver, so each counts what it counts without sharing.

A payload is the same bytes object for every receiver of a publication,
so its hash is computed once. ``how`` names everything else the result
depends on (the decoder's arguments, the guard's limits); a rejection is
kept as the ``wire.Rejected`` it raised and handed back, not raised. The
newest ``keep`` results are kept: enough for a tick's messages, else a
message evicted before its last receivers read it is decoded again for
each of them, and each holds its own decode until the tick is fused.
"""
from __future__ import annotations

from typing import Callable

from diskf_mesh.mesh.wire import codec as wire

KEEP = 4096   # results kept (at least): a payload's receivers all get it within a tick; one evicted early is
# computed again, and its receivers each hold their own result
PER_AGENT = 2  # ... and two per agent of the run: the messages of a tick (one per agent) all stay until read


class Shared:
    def __init__(self, keep: int | None = None, agents: int = 0):
        """``keep`` results (default ``KEEP``), at least ``PER_AGENT`` per
        agent of a run of ``agents``."""
        self.keep = max(KEEP if keep is None else keep, PER_AGENT * agents)
        self._memo: dict = {}
        self._hows: dict = {}
        self._reads: dict = {}

    def reads(self, how: int) -> dict:
        """The events read from samples under ``how`` (``remember``): {id(sample): (sample, event)}."""
        memo = self._reads.get(how)
        if memo is None:
            memo = self._reads[how] = {}
        return memo

    def remember(self, memo: dict, sample, event) -> None:
        """``event`` is what ``sample`` reads as (the newest ``keep`` kept)."""
        if len(memo) >= self.keep:
            del memo[next(iter(memo))]
        memo[id(sample)] = (sample, event)

    def how(self, what: tuple) -> int:
        """A small int for ``what`` (a tuple of settings, hashed once here)."""
        return self._hows.setdefault(what, len(self._hows))

    def entry(self, payload: bytes, how) -> list:
        """The list kept for (``payload``, ``how``): empty the first time;
        the caller fills it (``once`` puts the result first)."""
        key = (payload, how)
        hit = self._memo.get(key)
        if hit is None:
            hit = self._memo[key] = []
            if len(self._memo) > self.keep:
                del self._memo[next(iter(self._memo))]
        return hit

    def once(self, payload: bytes, how, compute: Callable):
        """``compute()`` once per (``payload``, ``how``): its result, or the
        ``wire.Rejected`` it raised."""
        hit = self.entry(payload, how)
        if not hit:
            try:
                hit.append(compute())
            except wire.Rejected as e:
                hit.append(e)
        return hit[0]
