"""A mesh run's status at its end: what the world heard, checked by the engine.

``run_status`` turns a run's reports (a ``mesh.protocol.reports.RunReports``: the
world's record, a recording) into ``engine.verify.RunClaims`` and asks
``engine.verify`` for the status: the world's end of run (``sim.world``),
the simulated network and ``replay RUN.mcap`` call it, so every run is
checked the same way. Message digests are the wire's
(``wire.engine_digests``); the planned links are the live range links after
the run's seeded link faults (``verify.planned_links``).

``OnlineCheck`` is the same check one tick at a time, as the world's reports
come: it names the agents to cut off (``mesh.protocol.world_machine``).

``accept`` is the one place a status meets the user's tolerances
(``--allow-missing``, ``--allow-degraded``, ``--accept-unverifiable``, real
time's ``--max-miss-rate``) and becomes an exit status (``core.exits``).

May import: core, estimators, data, engine (the mesh layer).
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np

from diskf_mesh import estimators
from diskf_mesh.core import exits
from diskf_mesh.data.argtypes import fraction
from diskf_mesh.data.faults import FaultConfig
from diskf_mesh.data.trace import Trace
from diskf_mesh.engine import verify
from diskf_mesh.engine.verify import Restart, RunClaims, RunStatus
from diskf_mesh.estimators.base import Estimator
from diskf_mesh.mesh.wire import codec as wire


def restarts_of(rejoins: dict, starts, index: dict) -> tuple:
    """``verify.Restart``s of a run: ``rejoins`` {agent id: [{"tick",
    "source"}]} (what the world answered and the agents said they used),
    with the starting state the world handed where ``starts`` (``wire.Start``
    answers) holds it for that agent, tick and source."""
    handed = {(s.agent, s.tick, s.source): s for s in starts or ()}
    out = []
    for agent, runs in sorted(rejoins.items(), key=lambda kv: index.get(kv[0], -1)):
        if agent not in index:
            continue
        for r in runs:
            tick, src = int(r["tick"]), r["source"]
            if tick < 2 or (src is not None and src not in index):
                continue
            s = handed.get((agent, tick, src))
            out.append(Restart(tick, index[agent], None if src is None else index[src],
                               None if s is None or src is None else np.asarray(s.x, dtype=float),
                               None if s is None or src is None else np.asarray(s.P, dtype=float)))
    return tuple(out)


def restarts_to_json(restarts, names) -> list:
    """``Restart``s as JSON, agents by ``names`` (in the trace's order)."""
    return [{"tick": r.tick, "agent": names[r.agent], "source": None if r.source is None else names[r.source],
             "x": None if r.x is None else np.asarray(r.x).tolist(),
             "P": None if r.P is None else np.asarray(r.P).tolist()} for r in restarts]


def restarts_from_json(docs, names) -> tuple:
    """``restarts_to_json`` read back (agents unknown to ``names`` skipped)."""
    index = {str(n): j for j, n in enumerate(names)}  # JSON may have turned an id into a string
    arr = lambda v: None if v is None else np.asarray(v, dtype=float)  # noqa: E731
    return tuple(Restart(int(d["tick"]), index[str(d["agent"])],
                         None if d["source"] is None else index[str(d["source"])], arr(d.get("x")), arr(d.get("P")))
                 for d in docs or () if str(d["agent"]) in index and (d["source"] is None or str(d["source"]) in index))


def claims_of(rec, ids, restarts=None) -> RunClaims:
    """``rec`` (a ``RunReports``, ticks 1..K, ``fused`` with or without the
    diagonal; ``live``, ``why``, ``rejoins`` and ``starts`` when it has
    them) as the engine's claims; ``ids`` the run's agent ids in the trace's
    order; ``restarts`` (``Restart``s) instead of the record's rejoins."""
    index = {i: j for j, i in enumerate(ids)}
    if restarts is None:
        restarts = restarts_of(getattr(rec, "rejoins", {}), getattr(rec, "starts", ()), index)
    return RunClaims(rec.x, rec.P, rec.d, rec.d_valid, rec.reported, rec.fused, getattr(rec, "live", None),
                     tuple(restarts), rec.claimed_digests(), dict(rec.verdicts), getattr(rec, "why", None))


def run_status(rec, trace: Trace, algorithm: str, params, *, run_id: str, seed: int,
               faults: FaultConfig | None = None, deadline_s: float = math.inf, labels=None,
               restarts=None, online: "OnlineCheck | None" = None) -> RunStatus:
    """The status of a run whose reports are ``rec`` (``claims_of``), on
    ``trace`` (the run's simulation; its agent axis the run's ids), with the
    run's estimator, run id (its messages' digests), seed and link faults;
    ``deadline_s``: real time's deadline (a copy planned later is not
    planned to be fused). The evidence lists the ``restarts`` replayed
    (``restarts_to_json``), so a recording replays them. A run that ended
    before any report (``rec.ended_early``: a world that gave up at its
    start) is incomplete, its reason first. ``online``: the run's check as
    it went (``OnlineCheck``), whose replay of each tick ``verify`` takes
    where it is its own bit for bit, instead of replaying the run again."""
    ids = list(trace.sensors.ids)
    claims = claims_of(rec, ids, restarts)
    names = list(labels if labels is not None else trace.agent_labels)
    K = claims.ticks
    planned = None
    if faults is not None and faults.active:
        planned = verify.planned_links(verify.nominal_links(trace, K, claims.live), ids, faults, seed, deadline_s)
    kept = None if online is None else online.kept(trace, algorithm, params, run_id)
    digest = kept.message_digest if kept is not None else \
        wire.engine_digests(run_id, ids, estimators.get(algorithm).exchanged)
    st = verify.verify(trace, algorithm, params, claims, planned=planned, message_digest=digest, labels=names,
                       online=kept)
    ended = getattr(rec, "ended_early", "")
    if ended and not claims.reported.any():  # the world gave up before any report (a start-up failure): why
        st = RunStatus(st.status, f"{ended}; {st.reason}", st.evidence)
    st.evidence["restarts"] = restarts_to_json(claims.restarts, names)
    if getattr(rec, "quarantined", None):
        st.evidence["quarantined"], line = quarantine_evidence(rec, names)
        st = dataclasses.replace(st, reason=f"{st.reason}; {line}")
    if faults is not None and faults.active and math.isfinite(deadline_s):
        st.evidence["plan_deadline_s"] = deadline_s  # a replay plans with the same deadline
    return st


class OnlineCheck:
    """The world's check as the run goes (``engine.verify.Online``): after
    each tick whose reports are final, ``tick(rec, k)`` replays it on the
    engine from the world's record ``rec`` (its reports, live sets,
    rejoins) with the same digests and planned links as ``run_status``,
    and returns the agents it proves lied, to cut off: a fused message or
    a report of theirs that the engine does not reproduce on a known
    state: [{"agent", "tick", "why": "lied", "fused_by"}], ids as the
    record holds them. An agent whose state is unknown (a report of its
    did not come) is never cut off: an honest one whose report was lost
    looks the same; what it changes is ``unverifiable`` at the end.
    ``estimator``: the run's, the class ``estimators.get`` resolved.
    ``handed_over``: False, the world checks each tick on its timer, in
    its own thread (a check in a thread of its own,
    ``mesh.process.checker``, says True: the world hands it each tick)."""

    handed_over = False

    def __init__(self, trace: Trace, estimator: type[Estimator], params, *, run_id: str, seed: int,
                 faults: FaultConfig | None = None, deadline_s: float = math.inf):
        self.ids = list(trace.sensors.ids)
        self.trace, self.seed, self.deadline_s, self.run_id = trace, seed, deadline_s, run_id
        self.faults = faults if faults is not None and faults.active else None
        self.online = verify.Online(trace, estimator.name, params,
                                    wire.engine_digests(run_id, self.ids, estimator.exchanged))
        self.index = {i: j for j, i in enumerate(self.ids)}

    def submit(self, rec, k: int) -> None:
        """Tick k's reports in ``rec`` are final (the world's machine says
        so before it asks ``result``): nothing to do here, where ``result``
        checks at once; a check in a thread of its own starts on them
        (``mesh.process.checker``)."""

    def result(self, rec, k: int, wait: bool = True) -> list:
        """``tick(rec, k)``: always done here (a check in a thread of its
        own says None while it is not done, unless ``wait``)."""
        return self.tick(rec, k)

    def tick(self, rec, k: int, said: tuple | None = None) -> list:
        """Tick k checked (the class's docstring); ``said``: its digests as
        ``rec.tick_digests(k)`` gives them (None: taken from ``rec``)."""
        rejoins = getattr(rec, "rejoins", None)
        restarts = tuple(r for r in restarts_of(rejoins, getattr(rec, "starts", ()), self.index)
                         if r.tick == k) if rejoins else ()
        claims = RunClaims(rec.x, rec.P, rec.d, rec.d_valid, rec.reported, rec.fused, None, restarts)
        judged = self.online.tick(k, claims, lambda: self.planned(rec, k),
                                  rec.tick_digests(k) if said is None else said)
        if judged is None:
            return []
        return [{"agent": self.ids[s], "tick": k, "why": "lied",
                 "fused_by": [self.ids[r] for r in np.flatnonzero(judged.forged[:, s])]} for s in judged.liars()]

    def close(self) -> None:
        """The run is over: the replay's state (its agents, its links, 100 MB
        each at 10,000 agents) is let go; no tick is checked after. The
        ticks it replayed stay for ``kept``."""
        if self.online is not None:
            self.online.release()

    def kept(self, trace: Trace, algorithm: str, params, run_id: str) -> verify.Online | None:
        """The check's ``verify.Online`` (its ticks kept) if it checked this
        run: the same trace, estimator, settings and run id (None else)."""
        on = self.online
        if on is None or trace is not self.trace or run_id != self.run_id or algorithm != on.algorithm \
                or params != on.params:
            return None
        return on

    def planned(self, rec, k: int) -> np.ndarray:
        """(N, N) tick k's planned links: the range links between the agents
        ``rec`` says it counted live, after the run's link faults."""
        live = rec.live[k - 1] if getattr(rec, "live", None) is not None else np.ones(len(self.ids), dtype=bool)
        planned = verify.nominal_links(self.trace, k, live[None], first_tick=k)
        if self.faults is not None:
            planned = verify.planned_links(planned, self.ids, self.faults, self.seed, self.deadline_s, first_tick=k)
        return planned[0]


def quarantine_evidence(rec, names) -> tuple:
    """(evidence, line) of the agents the world cut off (``rec.quarantined``:
    ``OnlineCheck.tick``'s, each with the tick it was cut off ``from``): who,
    why, from which tick, and the honest agent-ticks that fused it from the
    tick it was named to the one before it was cut off."""
    index = {i: j for j, i in enumerate(rec.ids)}
    out = []
    for q in rec.quarantined:
        j = index[q["agent"]]
        fused_by = [{"tick": t + 1, "agent": names[r]} for t in range(q["tick"] - 1, min(q["from"] - 1, len(rec.fused)))
                    for r in np.flatnonzero(rec.fused[t][:, j]).tolist() if r != j]
        out.append({"agent": names[j], "why": q["why"], "named_at": q["tick"], "from": q["from"],
                    "fused_by": fused_by})
    line = "; ".join(
        f"agent {q['agent']} cut off from tick {q['from']} (it lied, named at tick {q['named_at']}; "
        f"{len(q['fused_by'])} agent-ticks fused it"
        + (f", first agent {q['fused_by'][0]['agent']} at tick {q['fused_by'][0]['tick']}" if q["fused_by"] else "")
        + ")" for q in out)
    return out, line


def add_tolerances(p, missing_also: str = "") -> None:
    """``--allow-missing`` and ``--allow-degraded``: the statuses a user
    accepts (``accept``)."""
    p.add_argument("--allow-missing", type=fraction, default=0.0, metavar="FRACTION",
                   help="accept a run that misses at most this share of its agent-ticks (exit 0; the results "
                        f"still say incomplete){missing_also} (default 0: every agent reports every tick, or exit "
                        f"{exits.INCOMPLETE})")
    p.add_argument("--allow-degraded", action="store_true",
                   help="accept a run whose agent-ticks fused fewer messages than planned, e.g. a paused or slow "
                        f"agent's (exit 0, the results say degraded; without it exit {exits.DEGRADED}); a run "
                        f"whose estimates the engine does not reproduce (diverged) always exits {exits.DIVERGED}")
    p.add_argument("--accept-unverifiable", action="store_true",
                   help="accept a run with reported agent-ticks the engine cannot verify (built on a report that "
                        f"did not come; without it exit {exits.UNVERIFIABLE}, whatever --allow-missing says): exit 0, "
                        "the results say unverifiable and the final line gives the count")


def accept(status: RunStatus, *, allow_missing: float = 0.0, allow_degraded: bool = False,
           accept_unverifiable: bool = False, miss_rate: float | None = None,
           max_miss_rate: float | None = None) -> tuple:
    """(exit status, level, line) of a run with ``status`` under the user's
    tolerances; level "" (exact, as planned: nothing to say), "warning" (a
    status the user accepted) or "error". Real time (``miss_rate`` given):
    deadline misses within ``max_miss_rate`` are accepted degradation, more
    exit ``TOO_MANY_MISSES`` (the caller's line names the misses).
    ``diverged`` is never accepted; ``unverifiable`` only with
    ``accept_unverifiable`` (its line gives the count either way)."""
    s = status.status
    if s == exits.DIVERGED_STATUS:
        return exits.DIVERGED, "error", f"diverged: {status.reason}"
    if miss_rate is not None and max_miss_rate is not None and miss_rate > max_miss_rate:
        return exits.TOO_MANY_MISSES, "error", ""
    if s in (exits.EXACT_STATUS, exits.AS_PLANNED_STATUS):
        return exits.OK, "", ""
    if s == exits.UNVERIFIABLE_STATUS:
        if status.accepted(allow_missing=allow_missing, allow_degraded=allow_degraded or miss_rate is not None,
                           accept_unverifiable=accept_unverifiable):
            return exits.OK, "warning", f"unverifiable run accepted (--accept-unverifiable): {status.reason}"
        hint = ("--accept-unverifiable accepts it" if not accept_unverifiable else
                "--accept-unverifiable with --allow-missing (and --allow-degraded) for the rest")
        return exits.UNVERIFIABLE, "error", f"unverifiable run: {status.reason} ({hint})"
    realtime_ok = s in (exits.DEGRADED_STATUS, exits.INCOMPLETE_STATUS) and miss_rate is not None
    if status.accepted(allow_missing=allow_missing, allow_degraded=allow_degraded or realtime_ok):
        how = (f"--allow-missing {allow_missing:g}" + (" --allow-degraded" if status.degraded_beyond_missing else "")
               if s == exits.INCOMPLETE_STATUS else
               "--allow-degraded" if allow_degraded or miss_rate is None else f"--max-miss-rate {max_miss_rate:g}")
        return exits.OK, "warning", f"{s} run accepted ({how}): {status.reason}"
    if s != exits.INCOMPLETE_STATUS:
        hint = "--allow-degraded accepts it"
    elif status.nothing_reported:
        hint = "no agent-tick was reported: nothing to accept"
    elif status.degraded_beyond_missing:
        hint = (f"and {status.degraded_beyond_missing} agent-ticks degraded beyond the missing ones; "
                "--allow-missing with --allow-degraded accepts it")
    else:
        hint = "--allow-missing accepts it"
    return status.exit_code, "error", f"{s} run: {status.reason} ({hint})"
