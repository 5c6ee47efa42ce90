"""``diskf-mesh replay RUN.mcap``: the engine on exactly what each agent fused.

Each agent's report of tick k named the senders it fused (``recording.
verdicts``); those make a per-tick (N, N) delivered matrix, and the
in-process engine runs the recording's trace on it (``Trace.with_links``,
the path ``faults.delivered_links`` feeds for a fault layer known in
advance). The mesh computes the engine's bits (README, "mesh == engine"),
so the replay reproduces every recorded estimate bit for bit; ``compare``
says whether it did.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from diskf_mesh.data.trace import Trace
from diskf_mesh.engine import batch as engine
from diskf_mesh.engine.batch import Estimates
from diskf_mesh.recording.reader import Recording, take_ticks


def replay_fused(trace: Trace, fused: np.ndarray, reported: np.ndarray, algorithm: str, params) -> Estimates:
    """The engine on the first K ticks of ``trace`` with exactly the ``fused``
    sets (K, N, N). Where an agent did not report a tick (so its fusion is
    unknown) it is taken as fusing what its range links gave it."""
    trace = take_ticks(trace, fused.shape[0])
    links = fused.copy()
    missing = ~reported
    links[missing] = trace.links[0][missing]
    return engine.run(trace.with_links(links[None]), algorithm, params)


def replay(rec: Recording) -> Estimates:
    """Ticks 1..K of the recording, re-run on what was fused."""
    return replay_fused(rec.trace, rec.fused[:rec.ticks], rec.reported, rec.algorithm, rec.params)


@dataclass(frozen=True)
class Comparison:
    agent_ticks: int            # recorded agent-ticks compared
    equal: bool                 # every one bit for bit (x, P, d_valid, d where valid)
    differing: int              # agent-ticks with any difference
    max_abs: float              # largest |difference| of x, P, d


def compare(rec, est: Estimates) -> Comparison:
    """``rec``: what a run computed (a ``Recording`` or a ``FusedRecord``:
    ``reported``, ``x``, ``P``, ``d``, ``d_valid``), against ``est``."""
    r = rec.reported
    x, P, d, dv = est.x[0], est.P[0], est.d[0], est.d_valid[0]
    same_dv = dv == rec.d_valid
    both = rec.d_valid & dv
    diff_x = np.where(r[..., None], x != rec.x, False).any(-1)
    diff_P = np.where(r[..., None, None], P != rec.P, False).any((-1, -2))
    diff_d = np.where(both[..., None], d != rec.d, False).any(-1)
    bad = r & (diff_x | diff_P | diff_d | ~same_dv)
    gaps = [np.abs(x - rec.x)[r], np.abs(P - rec.P)[r], np.abs(d - rec.d)[both]]
    max_abs = max((float(g.max()) for g in gaps if g.size), default=0.0)
    return Comparison(int(r.sum()), not bad.any(), int(bad.sum()), max_abs)
