"""What a run's reports said: one container for the world's record
(``mesh.protocol.world_machine.WorldRecord``) and a recording's reader
(``diskf_mesh.recording.reader.Recording``), which both extend it.

Arrays (K, N, ...) over ticks 1..K and the agents in the scenario's order,
NaN where no report came.

May import: core, estimators, data, engine (the mesh layer).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from diskf_mesh.engine.batch import Estimates
from diskf_mesh.engine.fused import FusedDigests, FusedSets, digest_values, tick_digests


@dataclass
class RunReports:
    x: np.ndarray               # (K, N, n) each agent's fused state
    P: np.ndarray               # (K, N, n, n) its covariance
    d: np.ndarray               # (K, N, m) its fused input (NaN where it has none)
    d_valid: np.ndarray         # (K, N) bool
    reported: np.ndarray        # (K, N) bool: the report of tick k came
    fused: np.ndarray | FusedSets  # (K, N, N) bool [tick - 1, receiver, sender]: what the receiver fused
    digests: dict = field(default_factory=dict)   # (tick, receiver) -> (senders, their 8-byte digests), as reported
    # (tuples of indices and bytes, or ``fused``'s ``FusedDigests``; ``claimed_digests`` gives the arrays verify holds)
    verdicts: dict = field(default_factory=dict)  # (tick, receiver) -> ((sender, why not fused), ...)

    @staticmethod
    def empty(K: int, N: int, n: int, m: int, sparse: bool = False) -> dict:
        """The fields of a run with no report yet, for a subclass's constructor;
        ``sparse``: who fused whom and the digests as a ``FusedSets`` (memory
        with the messages fused, not K N^2), else a dense bool and a dict."""
        fused = FusedSets(K, N) if sparse else np.zeros((K, N, N), dtype=bool)
        return dict(x=np.full((K, N, n), np.nan), P=np.full((K, N, n, n), np.nan), d=np.full((K, N, m), np.nan),
                    d_valid=np.zeros((K, N), dtype=bool), reported=np.zeros((K, N), dtype=bool),
                    fused=fused, digests=fused.digests if sparse else {})

    def note_fused(self, tick: int, i: int, fused, not_fused, digests, index) -> None:
        """Receiver ``i``'s report of ``tick``: the senders it fused (ids;
        ``index`` maps an id to its place on the agent axis, unknown ids are
        skipped), why the others were not, and the digests of what it fused
        (one per sender of ``fused``, or none)."""
        senders = list(map(index.get, fused))
        if None in senders:  # unknown ids skipped, with their digests
            kept = [n for n, j in enumerate(senders) if j is not None]
            senders = [senders[n] for n in kept]
            digests = [digests[n] for n in kept] if digests else digests
        self.fused[tick - 1, i, senders] = True
        if digests and senders:
            self.digests[(tick, i)] = (tuple(senders), tuple(digests))
        said = tuple((index[s], str(v)) for s, v in not_fused if s in index)
        if said:
            self.verdicts[(tick, i)] = said

    def claimed_digests(self):
        """``digests`` as the engine's claims hold them (``verify.RunClaims``):
        (tick, receiver) -> (sender indices (J,) intp, digests (J,) uint64)."""
        if isinstance(self.digests, FusedDigests):
            return self.digests
        return {key: (np.array(senders, dtype=np.intp), digest_values(gs))
                for key, (senders, gs) in self.digests.items()}

    def tick_digests(self, k: int) -> tuple:
        """Tick k's ``digests`` as three (J,) arrays, receivers in order:
        receivers, senders (intp) and digests (uint64, as
        ``claimed_digests``): ``engine.verify.Online``'s ``said``."""
        return tick_digests(self.digests, k)

    def estimates(self, fill: bool = False) -> Estimates:
        """The reports as an engine ``Estimates`` batch of one; with ``fill``
        the agent-ticks without a report hold x = 0, P = I, d = 0 (for
        metrics, which mask them out)."""
        x, P, d = self.x, self.P, self.d
        if fill:
            miss = ~self.reported
            x, d = np.where(miss[..., None], 0.0, x), np.where(miss[..., None], 0.0, d)
            P = np.where(miss[..., None, None], np.eye(P.shape[-1]), P)
        return Estimates(x[None], P[None], d[None], self.d_valid[None])
