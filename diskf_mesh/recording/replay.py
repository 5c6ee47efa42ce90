"""``diskf-mesh replay RUN.mcap``: the run checked again, from its recording.

Each agent's report of tick k named the senders it fused (``recording.
verdicts``) and the digests of their messages; the world's result names the
re-initialisations (tick, agent, source, the starting state it handed). The
engine replays the recording's trace on exactly those fused sets with those
restarts (``engine.verify``, the check every run makes at its end) and
compares every recorded estimate bit for bit: ``recording_status`` is the
run's status (exact, as planned, degraded, diverged, incomplete), ``compare``
the plain comparison.

A recording is checked whole first (``Recording.not_whole``): a whole MCAP file
(``reader.scan``: every CRC, the summary, the footer), the run's result and
every planned tick. One that is not is ``incomplete`` whatever its whole
ticks replay to (``diverged`` or ``unverifiable`` if they are), and says
why and its last whole tick.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from diskf_mesh.core import exits
from diskf_mesh.core.errors import InputError
from diskf_mesh.data import schemas
from diskf_mesh.data.faults import FaultConfig
from diskf_mesh.data.trace import MESH_ESTIMATES_FORMAT, Trace, estimator_from_json
from diskf_mesh.estimators import Params
from diskf_mesh.engine import verify
from diskf_mesh.engine.batch import Estimates
from diskf_mesh.engine.verify import RunClaims, RunStatus
from diskf_mesh.mesh.protocol.reports import RunReports
from diskf_mesh.mesh.protocol.run_status import restarts_from_json, run_status
from diskf_mesh.recording.reader import Recording


def recorded_restarts(rec: Recording) -> tuple:
    """The re-initialisations the world's result lists (``verify.Restart``s)."""
    docs = ((rec.result or {}).get("verification") or {}).get("restarts")
    return restarts_from_json(docs, list(rec.ids))


def recorded_miss_rate(rec: Recording) -> float | None:
    """A real-time run's share of deadline misses, as its result says (None:
    lockstep, or a run that did not end)."""
    return (((rec.result or {}).get("metrics") or {}).get("deadline_misses") or {}).get("miss_rate")


def recording_status(rec: Recording) -> RunStatus:
    """The recorded run checked by the engine: its status, reason, evidence
    (planned with the deadline the run's own check used, if it said one);
    a recording that is not whole (``Recording.not_whole``) is ``incomplete``, or
    ``diverged`` (``unverifiable``) if its whole ticks are, its evidence's
    ``recording`` saying why and the last whole tick."""
    run = rec.run
    faults = FaultConfig.from_mapping(run.get("faults") or {})
    deadline = ((rec.result or {}).get("verification") or {}).get("plan_deadline_s")
    st = run_status(rec, verify.first_ticks(rec.trace, rec.ticks), rec.algorithm, rec.params,
                    run_id=run["run_id"], seed=int(run["seed"]), faults=faults,
                    deadline_s=math.inf if deadline is None else float(deadline), labels=list(rec.ids),
                    restarts=recorded_restarts(rec))
    why = rec.not_whole()
    st.evidence["recording"] = {"whole": not why, "damage": why or None, "last_whole_tick": rec.ticks,
                                "planned_ticks": rec.planned_ticks, "replayed_status": st.status}
    if not why:
        return st
    line = f"the recording is not whole: {why}; its last whole tick is {rec.ticks} of {rec.planned_ticks}"
    if st.status in (exits.DIVERGED_STATUS, exits.UNVERIFIABLE_STATUS):  # the worse verdict stays
        return RunStatus(st.status, f"{st.reason}; and {line}", st.evidence)
    return RunStatus(exits.INCOMPLETE_STATUS, f"{line} (ticks 1 to {rec.ticks} replay {st.status})", st.evidence)


def replay(rec: Recording) -> Estimates:
    """Ticks 1..K of the recording, re-run on what was fused, each restart at its tick."""
    claims = RunClaims(rec.x, rec.P, rec.d, rec.d_valid, rec.reported, rec.fused, rec.live,
                       recorded_restarts(rec))
    return verify.replay(rec.trace, rec.algorithm, rec.params, claims)[0]


def replay_fused(trace: Trace, fused: np.ndarray, reported: np.ndarray, algorithm: str, params, restarts=(),
                 run: Estimates | None = None) -> Estimates:
    """The engine on the first K ticks of ``trace`` with exactly the ``fused``
    sets (K, N, N), each ``verify.Restart`` at its tick (a restart without
    its starting state takes its source's estimate in ``run``). Where an
    agent did not report a tick (so its fusion is unknown) it is taken as
    fusing what its range links gave it."""
    K, N = reported.shape
    if run is None:
        nan = np.full((1, K, N), np.nan)
        run = Estimates(nan, nan, nan, np.zeros((1, K, N), bool))
    claims = RunClaims(run.x[0], run.P[0], run.d[0], run.d_valid[0], reported, fused, None, tuple(restarts))
    return verify.replay(trace, algorithm, params, claims)[0]


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
    agent-ticks against ``est``, bit for bit (``verify.differing``)."""
    K, N = reported.shape
    claims = RunClaims(run.x[0], run.P[0], run.d[0], run.d_valid[0], reported, np.zeros((K, N, N), bool))
    bad, gap = verify.differing(claims, est)
    return Comparison(int(reported.sum()), not bad.any(), int(bad.sum()), float(gap.max()) if gap.size else 0.0)


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
    restarts: tuple = ()        # verify.Restart: the re-initialisations the run's evidence lists
    run_id: str = ""
    seed: int = 0
    faults: FaultConfig = FaultConfig()
    miss_rate: float | None = None  # a real-time run's share of deadline misses (None: lockstep)
    digests: dict = field(default_factory=dict)  # the fused messages' digests (``RunReports.digests``)
    live: np.ndarray | None = None  # (K, N) the live set of each tick (None: the document predates it)
    plan_deadline_s: float = math.inf  # the deadline the run's own check planned with


def fused_status(run: FusedRecord, trace: Trace, params) -> RunStatus:
    """A run's estimates document checked by the engine on ``trace``."""
    K, N = run.reported.shape
    e = run.estimates
    reports = RunReports(e.x[0], e.P[0], e.d[0], e.d_valid[0], run.reported, run.fused, dict(run.digests))
    reports.live = run.live
    return run_status(reports, verify.first_ticks(trace, K), run.algorithm, params, run_id=run.run_id,
                      seed=run.seed, faults=run.faults, deadline_s=run.plan_deadline_s,
                      labels=list(trace.agent_labels), restarts=run.restarts)


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
    reports = RunReports(**RunReports.empty(K, N, 1, 1))
    said = doc.get("fused_digests")
    for k, tick in enumerate(doc["fused"]):
        if len(tick) != N:
            raise InputError(f"fused[{k}]", f"must list {N} agents' senders, got {len(tick)}")
        for r, senders in enumerate(tick):
            for s in senders:
                if str(s) not in index:
                    raise InputError(f"fused[{k}][{r}]", f"names {s!r}, not an agent of the run")
                fused[k, r, index[str(s)]] = True
            hexes = said[k][r] if said is not None else []
            if hexes:
                try:
                    reports.note_fused(k + 1, r, [str(s) for s in senders], (), [bytes.fromhex(h) for h in hexes], index)
                except (ValueError, TypeError, IndexError):
                    raise InputError(f"fused_digests[{k}][{r}]", "must hold one 16-digit hex digest per fused "
                                                                 "sender") from None
    d = doc["d"]
    d_valid = np.array([[row is not None for row in tick] for tick in d], dtype=bool).reshape(K, N)
    m = next((len(row) for tick in d for row in tick if row is not None), 1)
    d_arr = np.array([[row if row is not None else [np.nan] * m for row in tick] for tick in d], dtype=float)
    params = estimator_from_json(doc) if "estimator" in doc else None
    x, P = np.array(doc["x"], dtype=float).reshape(K, N, -1), np.array(doc["P"], dtype=float)
    restarts = restarts_from_json((doc.get("evidence") or {}).get("restarts"), labels)
    return FusedRecord(doc["algorithm"], params, Estimates(x[None], P[None], d_arr.reshape(1, K, N, m), d_valid[None]),
                       reported, fused, restarts, str(doc.get("run_id", "")), int(doc.get("seed", 0)),
                       FaultConfig.from_mapping(doc.get("faults") or {}),
                       (doc.get("deadline_misses") or {}).get("miss_rate"), reports.digests,
                       np.asarray(doc["live"], dtype=bool).reshape(K, N) if "live" in doc else None,
                       float((doc.get("evidence") or {}).get("plan_deadline_s") or math.inf))
