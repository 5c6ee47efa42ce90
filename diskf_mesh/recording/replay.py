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

from diskf_mesh.core.errors import InputError
from diskf_mesh.data import schemas
from diskf_mesh.data.trace import MESH_ESTIMATES_FORMAT, Trace, estimator_from_json
from diskf_mesh.estimators import Params
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


def compare(rec: Recording, est: Estimates) -> Comparison:
    """The recording's reported estimates against ``est``."""
    return compare_reported(Estimates(rec.x[None], rec.P[None], rec.d[None], rec.d_valid[None]), rec.reported, est)


def compare_reported(run: Estimates, reported: np.ndarray, est: Estimates) -> Comparison:
    """What a run computed (``run``, one seed) at its ``reported`` (K, N)
    agent-ticks against ``est``, bit for bit."""
    r = reported
    x, P, d, dv = est.x[0], est.P[0], est.d[0], est.d_valid[0]
    rx, rP, rd, rdv = run.x[0], run.P[0], run.d[0], run.d_valid[0]
    same_dv = dv == rdv
    both = rdv & dv
    diff_x = np.where(r[..., None], x != rx, False).any(-1)
    diff_P = np.where(r[..., None, None], P != rP, False).any((-1, -2))
    diff_d = np.where(both[..., None], d != rd, False).any(-1)
    bad = r & (diff_x | diff_P | diff_d | ~same_dv)
    gaps = [np.abs(x - rx)[r], np.abs(P - rP)[r], np.abs(d - rd)[both]]
    max_abs = max((float(g.max()) for g in gaps if g.size), default=0.0)
    return Comparison(int(r.sum()), not bad.any(), int(bad.sum()), max_abs)


@dataclass(frozen=True)
class FusedRecord:
    """A mesh run's diskf-mesh-estimates/1 document (``up``/``world
    --estimates``) on the trace's agent axis: what it computed (one seed,
    NaN where an agent did not report) and what each agent fused."""

    algorithm: str
    params: Params | None       # the run's estimator settings (None: the document predates them)
    estimates: Estimates        # (1, K, N, ...)
    reported: np.ndarray        # (K, N) bool
    fused: np.ndarray           # (K, N, N) bool [tick - 1, receiver, sender], the diagonal set


def fused_record_from_json(doc: dict, labels) -> FusedRecord:
    """A run's estimates document with its ``fused`` sets, checked against
    the agents ``labels`` of the trace it is to be replayed on."""
    schemas.check(doc, MESH_ESTIMATES_FORMAT)
    if "fused" not in doc:
        raise InputError("fused", "is missing: not the estimates of a mesh run (up or world --estimates)")
    ids = [str(i) for i in doc["ids"]]
    labels = [str(i) for i in labels]
    if ids != labels:
        raise InputError("ids", f"the run's agents {ids[:6]}{'...' if len(ids) > 6 else ''} are not the trace's "
                         f"{labels[:6]}{'...' if len(labels) > 6 else ''}")
    N, K = len(ids), len(doc["fused"])
    reported = np.asarray(doc["reported"], dtype=bool)
    if reported.shape != (K, N) or len(doc["x"]) != K:
        raise InputError("reported", f"must be {K} x {N} like fused, got {'x'.join(map(str, reported.shape))}")
    index = {i: j for j, i in enumerate(ids)}
    fused = np.zeros((K, N, N), dtype=bool)
    fused[:, np.arange(N), np.arange(N)] = True
    for k, tick in enumerate(doc["fused"]):
        if len(tick) != N:
            raise InputError(f"fused[{k}]", f"must list {N} agents' senders, got {len(tick)}")
        for r, senders in enumerate(tick):
            for s in senders:
                if str(s) not in index:
                    raise InputError(f"fused[{k}][{r}]", f"names {s!r}, not an agent of the run")
                fused[k, r, index[str(s)]] = True
    d = doc["d"]
    d_valid = np.array([[row is not None for row in tick] for tick in d], dtype=bool).reshape(K, N)
    m = next((len(row) for tick in d for row in tick if row is not None), 1)
    d_arr = np.array([[row if row is not None else [np.nan] * m for row in tick] for tick in d], dtype=float)
    params = estimator_from_json(doc) if "estimator" in doc else None
    x, P = np.array(doc["x"], dtype=float).reshape(K, N, -1), np.array(doc["P"], dtype=float)
    return FusedRecord(doc["algorithm"], params, Estimates(x[None], P[None], d_arr.reshape(1, K, N, m), d_valid[None]),
                       reported, fused)
