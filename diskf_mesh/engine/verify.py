"""A run checks itself: the engine replays it from what each agent said it
fused, and every reported estimate is compared bit for bit.

``verify`` is pure: a run's claims in (``RunClaims``: every agent's reported
x, P, d per tick, the senders it fused, the digests of the messages it
fused, the re-initialisations), its ``RunStatus`` out. The mesh's world, the
simulated network and ``replay RUN.mcap`` / ``replay --fused`` all call it.

The replay is ``engine.run_batch`` on the run's trace with each tick's links
set to exactly what each agent fused (an agent-tick without a report: the
planned links, a guess that only matters if it goes on without a
re-initialisation), and every re-initialised agent restarted at its tick
from the starting state it was handed (``Restart``). Each tick's messages
are recomputed from the trace; with a ``message_digest`` (the mesh's wire
encoding) each digest an agent reported for a fused sender is compared with
the digest of the engine's message, so a message the engine does not
reproduce (forged, or an insider's extreme one) is named with its sender.

Statuses (exit statuses: ``diskf_mesh.core.exits``), first that applies:

    diverged     a reported estimate, or a fused message's digest, differs
                 from the engine's replay where the run's history is known:
                 the first tick, agent and sender whose message it does not
                 reproduce (the agent itself when every message it fused was
                 the engine's)
    unverifiable some reported agent-tick cannot be verified: it differs
                 from the replay, built on a state the run did not report
                 (``Judge``); how many, the first, and whose missing
                 reports made the states unknown. ``--allow-missing`` never
                 accepts it, only ``accept_unverifiable``
    incomplete   some agent-tick was not reported
    degraded     every agent-tick reported and reproduced, but some fused
                 fewer messages than planned: how many, which, and the
                 agents' reasons (lost, late, rejected:<reason>); or some
                 agent was re-initialised (a rejoin: its estimate restarted
                 from a neighbour's or its prior, not the algorithm's own)
    as planned   every fused set is the fault plan's delivered set (link
                 faults injected, seeded by the run's seed)
    exact        every fused set is the nominal links (live and in range)

A history is unknown after an agent-tick that was not reported (what it
fused is unknown) until that agent is re-initialised or its next report
equals the replay bit for bit; an estimate built on an unknown sender's
message whose digest is missing or differs is not verifiable
(``unverified``), not a divergence (``Judge``). ``Online`` is the same
check one tick at a time, as a run's reports come (the mesh's world).

May import: core, estimators, data (the engine layer).
"""
from __future__ import annotations

import hashlib
from collections import Counter
from dataclasses import dataclass, field, fields, replace

import numpy as np

from diskf_mesh.core import exits
from diskf_mesh.core.exits import (AS_PLANNED_STATUS, DEGRADED_STATUS, DIVERGED_STATUS, EXACT_STATUS,
                                   INCOMPLETE_STATUS, UNVERIFIABLE_STATUS)
from diskf_mesh.data.faults import FaultConfig, delivered_links
from diskf_mesh.data.trace import Trace
from diskf_mesh.engine import batch
from diskf_mesh.engine.batch import Estimates
from diskf_mesh.engine.fused import digest_value, digest_values, first_digests, tick_digests

LISTED = 20  # agent-ticks listed by name in the evidence (the counts cover all)


@dataclass(frozen=True)
class Restart:
    """An agent re-initialised: it worked again from ``tick`` on, starting
    from the fused estimate of tick - 1 of agent ``source`` (or its prior)."""

    tick: int
    agent: int                  # index on the trace's agent axis
    source: int | None          # index of the agent whose estimate it took; None: the prior
    x: np.ndarray | None = None  # the starting state it was handed; None: ``source``'s report of tick - 1
    P: np.ndarray | None = None


@dataclass(frozen=True)
class RunClaims:
    """What a run says it did, ticks 1..K on the trace's agent axis."""

    x: np.ndarray               # (K, N, n) reported fused state (NaN where not reported)
    P: np.ndarray               # (K, N, n, n)
    d: np.ndarray               # (K, N, m)
    d_valid: np.ndarray         # (K, N) bool
    reported: np.ndarray        # (K, N) bool
    fused: np.ndarray           # (K, N, N) bool [tick - 1, receiver, sender]; the diagonal is ignored
    live: np.ndarray | None = None   # (K, N) bool the agents counted live at each tick (None: all)
    restarts: tuple = ()        # Restart, ...
    digests: dict = field(default_factory=dict)   # (tick, receiver) -> (senders, digests): (J,) int, (J,) uint64
    verdicts: dict = field(default_factory=dict)  # (tick, receiver) -> ((sender, why not fused), ...)
    why: np.ndarray | None = None  # (K, N) why an agent-tick is missing, as the run says

    @property
    def ticks(self) -> int:
        return int(self.reported.shape[0])


@dataclass(frozen=True)
class RunStatus:
    """A run's verdict: one of ``exits.STATUSES``, its one-line ``reason``
    and JSON-able ``evidence``."""

    status: str
    reason: str
    evidence: dict = field(default_factory=dict)

    @property
    def exit_code(self) -> int:
        return exits.STATUS_EXIT[self.status]

    def accepted(self, *, allow_missing: float = 0.0, allow_degraded: bool = False,
                 accept_unverifiable: bool = False) -> bool:
        """Whether the user accepted this status: exact and as planned always;
        incomplete within ``allow_missing`` (a share of the agent-ticks),
        never a run with no agent-tick reported;
        degraded with ``allow_degraded``; unverifiable only with
        ``accept_unverifiable`` (and its missing agent-ticks as incomplete);
        diverged never."""
        if self.status in (EXACT_STATUS, AS_PLANNED_STATUS):
            return True
        if self.status == UNVERIFIABLE_STATUS:
            return accept_unverifiable and (
                self._missing_within(allow_missing) or not self.evidence.get("missing_agent_ticks")
            ) and (allow_degraded or not self.degraded_beyond_missing)
        if self.status == INCOMPLETE_STATUS:
            return self._missing_within(allow_missing) and (allow_degraded or not self.degraded_beyond_missing)
        return self.status == DEGRADED_STATUS and allow_degraded

    @property
    def nothing_reported(self) -> bool:
        """No agent-tick of the run was reported: there is no estimate to
        accept, whatever share ``--allow-missing`` names."""
        return self.evidence.get("reported") == 0

    def _missing_within(self, allow_missing: float) -> bool:
        return not self.nothing_reported and self.evidence.get("missing_fraction", 1.0) <= allow_missing

    @property
    def degraded_beyond_missing(self) -> int:
        """Agent-ticks of an incomplete run that fused less than planned
        though every sender they lack did report that tick, or fused a
        sender not planned: degradation the missing agent-ticks do not
        explain, which ``--allow-missing`` alone does not accept."""
        ev = self.evidence
        return int(ev.get("degraded", {}).get("beyond_missing", 0)) + int(ev.get("unplanned", {}).get("agent_ticks", 0))

    def to_json(self) -> dict:
        return {"status": self.status, "reason": self.reason, **self.evidence}


# --------------------------------------------------------------------------
# the links a run should have fused
# --------------------------------------------------------------------------
def first_ticks(trace: Trace, K: int) -> Trace:
    """The first K ticks of a trace (everything is causal: ticks 1..K of a
    run do not depend on later ones)."""
    cut = lambda a: None if a is None else a[:, :K]  # noqa: E731
    return replace(trace, model=replace(trace.model, A=trace.model.A[:K]), y=trace.y[:, :K], has=trace.has[:, :K],
                   links=trace.links[:, :K], truth_x=cut(trace.truth_x), truth_d=cut(trace.truth_d),
                   positions=None if trace.positions is None else trace.positions[:K])


def first_claims(claims: RunClaims, K: int) -> RunClaims:
    """``claims`` of ticks 1..K only."""
    cut = lambda a: None if a is None else a[:K]  # noqa: E731
    return RunClaims(claims.x[:K], claims.P[:K], claims.d[:K], claims.d_valid[:K], claims.reported[:K],
                     claims.fused[:K], cut(claims.live), tuple(r for r in claims.restarts if r.tick <= K),
                     first_digests(claims.digests, K),
                     {key: v for key, v in claims.verdicts.items() if key[0] <= K}, cut(claims.why))


def nominal_links(trace: Trace, K: int, live: np.ndarray | None = None, first_tick: int = 1) -> np.ndarray:
    """(K, N, N): the range links of ticks first_tick..K between agents
    live at the tick (``live`` (ticks, N); None: all), the diagonal True."""
    links = np.array(trace.links[0, first_tick - 1:K], dtype=bool)
    if live is not None:
        links &= live[:, :, None] & live[:, None, :]
    N = links.shape[-1]
    links[:, np.arange(N), np.arange(N)] = True
    return links


def announced(trace: Trace, live: np.ndarray) -> Trace:
    """``trace`` with each tick's links only between the agents that tick
    counted live (``live`` (K, N), as a run's ticks announce it): the engine
    applies a run's quarantine (and its joins and departures) from the same
    ticks, so its estimates are the run's on what was delivered."""
    K = live.shape[0]
    return first_ticks(trace, K).with_links(nominal_links(trace, K, live)[None])


class TickLinks:
    """(K, N, N) bool links of ticks 1..K read a tick at a time: ``at(t)``
    is tick t + 1's (N, N), from ``array`` or, without one, the range links
    between the agents ``live`` at the tick (``nominal_links`` of ``trace``)
    made when asked: never all K ticks at once (10,000 agents over 20 ticks
    would take 2 GB for each such array)."""

    def __init__(self, K: int, trace: Trace | None = None, live: np.ndarray | None = None,
                 array: np.ndarray | None = None):
        self.K, self.trace, self.live, self.array = K, trace, live, array

    def at(self, t: int) -> np.ndarray:
        if self.array is not None:
            return self.array[t]
        return nominal_links(self.trace, t + 1, None if self.live is None else self.live[t:t + 1], first_tick=t + 1)[0]

    def cut(self, K: int) -> "TickLinks":
        """Ticks 1..K only."""
        return TickLinks(K, self.trace, None if self.live is None else self.live[:K],
                         None if self.array is None else self.array[:K])

    def off_diagonal(self) -> int:
        """How many links the K ticks hold between two agents."""
        return sum(int(a.sum()) - int(a.diagonal().sum()) for a in map(self.at, range(self.K)))


def tick_links(links, K: int, trace: Trace, live: np.ndarray | None) -> TickLinks:
    """``links`` (a (K, N, N) array, a ``TickLinks``, or None: the nominal
    links of ``trace`` between the agents ``live``) as a ``TickLinks``."""
    if isinstance(links, TickLinks):
        return links
    return TickLinks(K, trace, live) if links is None else TickLinks(K, array=np.asarray(links, dtype=bool))


def planned_links(nominal: np.ndarray, ids, faults: FaultConfig | None, seed: int,
                  deadline_s: float = np.inf, first_tick: int = 1) -> np.ndarray:
    """The nominal links (of ticks ``first_tick``...) after the injected
    faults (``faults.delivered_links`` of the run's seed; ``ids``: the run's
    agent ids in the trace's order): what the agents fuse when every copy
    due before ``deadline_s`` is in."""
    if faults is None or not faults.active:
        return nominal
    return delivered_links(nominal, list(ids), faults, seed, deadline_s, first_tick)


# --------------------------------------------------------------------------
# the replay
# --------------------------------------------------------------------------
def restarted(est, state, agent: int, x=None, P=None):
    """``state`` with ``agent``'s slot as a fresh agent's (``est.init``),
    its fused estimate set to (x, P) and its observation window reset when
    given: what a re-initialised agent process starts from."""
    fresh = est.init(state.x.shape[:-1])
    out = {}
    for f in fields(state):
        a = getattr(state, f.name)
        if isinstance(a, np.ndarray):
            a = a.copy()
            start = getattr(fresh, f.name)
            a[:, agent] = 0 if start is None else start[:, agent]  # None: made at the first fusion, zeros
            out[f.name] = a
    new = replace(state, **out)
    if x is not None:
        new.x[:, agent], new.P[:, agent] = x, P
        new.since[:, agent] = 0
    return new


def restart_at(k: int, restarts, claims: RunClaims, est, state):
    """``state`` with tick k's ``restarts`` applied: each agent starts from
    the state it was handed, or its source's report of tick k - 1 (the
    replay's own state where that is not in the claims)."""
    for r in restarts:
        x, P = r.x, r.P
        if x is None and r.source is not None:
            x, P = claims.x[k - 2, r.source], claims.P[k - 2, r.source]
            if not claims.reported[k - 2, r.source]:  # not in the claims: the replay's own
                x, P = state.x[0, r.source].copy(), state.P[0, r.source].copy()
        state = restarted(est, state, r.agent, x, P)
    return state


def replay(trace: Trace, algorithm: str, params, claims: RunClaims, planned: np.ndarray | TickLinks | None = None,
           message_digest=None, wanted=None) -> tuple:
    """The engine on ticks 1..K of ``trace`` with exactly the fused sets of
    ``claims`` (an agent-tick without a report: ``planned``'s row; a
    (K, N, N) array, a ``TickLinks`` or None: the nominal links), their
    links made a tick at a time, each ``Restart`` applied at its tick.
    Returns (Estimates, digests): with
    ``message_digest(k, sender indices, the tick's Message batch) -> [bytes]``,
    the digest of every engine message (k, sender) in ``wanted`` (a set;
    None: none), as ``digest_value``s."""
    K, N = claims.reported.shape
    tr = first_ticks(trace, K)
    planned = tick_links(planned, K, tr, claims.live)
    diagonal = np.arange(N), np.arange(N)

    def links_at(k):  # tick k's (1, N, N): what each agent fused, the planned row where it did not report
        return replay_links(claims, k, planned.at, diagonal)[None]

    by_tick = {}
    for r in claims.restarts:
        by_tick.setdefault(int(r.tick), []).append(r)

    def restart(k, est, state):
        return restart_at(k, by_tick.get(k, ()), claims, est, state)

    digests = {}
    need = {}
    for k, s in wanted or ():
        need.setdefault(k, set()).add(s)

    def listen(k, msg):
        if message_digest is not None and need.get(k):
            senders = sorted(need[k])
            for s, g in zip(senders, message_digest(k, senders, msg)):
                digests[(k, s)] = digest_value(g)

    est = batch.run_batch(tr, algorithm, params, restart=restart if by_tick else None,
                          listen=listen if need else None, links_at=links_at)
    return est, digests


def replay_links(claims: RunClaims, k: int, planned_at, diagonal) -> np.ndarray:
    """Tick k's (N, N) links of the replay: what each agent fused, the
    planned row (``planned_at(k - 1)``, asked only then) where it did not
    report, the diagonal (``diagonal``: its indices) True."""
    links = np.array(claims.fused[k - 1], dtype=bool)
    missing = ~claims.reported[k - 1]
    if missing.any():
        links[missing] = planned_at(k - 1)[missing]
    links[diagonal] = True
    return links


def replay_inputs(k: int, links: np.ndarray, restarts, claims: RunClaims) -> bytes:
    """A digest of what the replay of tick k starts from besides the
    trace and the state before it: its links, its ``restarts`` in order and
    the reports of tick k - 1 a restart starts from (``restart_at``)."""
    h = hashlib.blake2b(np.packbits(links).tobytes(), digest_size=16)
    for r in restarts:
        h.update(repr((int(r.tick), int(r.agent), None if r.source is None else int(r.source))).encode())
        if r.x is not None:
            h.update(np.asarray(r.x, dtype=float).tobytes() + np.asarray(r.P, dtype=float).tobytes())
        elif r.source is not None:
            known = bool(claims.reported[k - 2, r.source])
            h.update(bytes([known]))
            if known:
                h.update(claims.x[k - 2, r.source].tobytes() + claims.P[k - 2, r.source].tobytes())
    return h.digest()


def differing(claims: RunClaims, est: Estimates) -> tuple:
    """((K, N) bool: reported agent-ticks whose x, P, d_valid or (where
    valid) d differ from ``est`` bit for bit; (K, N) largest |difference|)."""
    return compare(claims.reported, claims.x, claims.P, claims.d, claims.d_valid,
                   est.x[0], est.P[0], est.d[0], est.d_valid[0])


def compare(r, cx, cP, cd, cdv, x, P, d, dv, largest: bool = True) -> tuple:
    """``differing`` on arrays of any leading shape: the claims (``r``
    reported, ``cx``, ``cP``, ``cd``, ``cdv``) against the engine's; without
    ``largest`` the largest differences are not computed (None)."""
    both = cdv & dv
    bad = r & ((x != cx).any(-1) | (P != cP).any((-1, -2)) | (dv != cdv) | (both & (d != cd).any(-1)))
    if not largest:
        return bad, None
    with np.errstate(invalid="ignore"):
        dx = np.abs(x - cx).max(-1)
        dP = np.abs(P - cP).max((-1, -2))
        dd = np.where(both, np.abs(d - cd).max(-1), 0.0)
    gap = np.where(r, np.fmax(np.fmax(dx, dP), dd), 0.0)
    return bad, np.nan_to_num(gap, nan=np.inf)


# --------------------------------------------------------------------------
# one tick's judgement
# --------------------------------------------------------------------------
@dataclass(frozen=True)
class Judged:
    """One tick's judgement (``Judge.tick``), (N,) over receivers or (N, N)
    [receiver, sender]."""

    diverged: np.ndarray     # (N,) a reported estimate that provably differs from the algorithm's
    forged: np.ndarray       # (N, N) a fused message of a known sender the engine does not reproduce
    unverified: np.ndarray   # (N,) a reported estimate that differs, built on an unknown state
    doubtful: np.ndarray     # (N, N) a fused message of a sender whose state is unknown, not reproduced

    def liars(self) -> list:
        """The agents this tick proves lied: senders of forged messages, and
        agents whose own estimate differs though every message they fused
        was the engine's."""
        if not (self.diverged.any() or self.forged.any()):
            return []
        own = self.diverged & ~self.forged.any(-1)
        return sorted(set(np.flatnonzero(self.forged.any(0)).tolist()) | set(np.flatnonzero(own).tolist()))


class Judge:
    """The check of a run's ticks in order (``verify`` at the end of a run,
    ``Online`` as it goes): which reported estimates diverged, which cannot
    be verified, and whose state is known.

    An agent's state is unknown after an agent-tick it did not report (what
    it fused is unknown; ``withheld`` holds that tick) until it is
    re-initialised or its next report equals the replay bit for bit; an
    estimate built on an unknown state (its own, or an unknown sender's
    message that the engine does not reproduce) that differs from the
    replay is not a divergence but ``unverified``, and its own state is
    unknown from then on."""

    def __init__(self, N: int):
        self.unknown = np.zeros(N, dtype=bool)
        self.withheld = np.zeros(N, dtype=int)  # the tick of the missing report that made the state unknown (0: none)

    def tick(self, k: int, reported, bad, fused, has, wrong, restarted=()) -> Judged:
        """Tick k: ``reported``, ``bad`` (its estimate differs from the
        replay) (N,); ``fused``, ``has`` (a digest was reported), ``wrong``
        (it differs from the engine's message's) (N, N) [receiver, sender];
        ``restarted``: the agents re-initialised at k."""
        unknown = self.unknown
        if len(restarted):
            unknown[list(restarted)] = False
            self.withheld[list(restarted)] = 0
        if not unknown.any() and not wrong.any() and reported.all() and not bad.any():  # all known and reproduced
            none = np.zeros_like(reported)
            self.withheld[:] = 0
            self.unknown = none.copy()
            return Judged(none, np.zeros_like(wrong), none.copy(), np.zeros_like(wrong))
        if unknown.any() or wrong.any():
            fused = _off_diagonal(fused)
            forged = fused & wrong & ~unknown[None, :]   # a known sender's message the engine does not reproduce
            doubtful = fused & unknown[None, :] & (~has | wrong)
            tainted = unknown | doubtful.any(-1)
            div = reported & (forged.any(-1) | (bad & ~tainted))
        else:  # every state and message known: any difference is a divergence
            forged, div, doubtful = _off_diagonal(wrong), reported & bad, np.zeros_like(wrong)
        unver = reported & ~div & bad
        self.withheld = np.where(~reported, np.where(self.withheld > 0, self.withheld, k),
                                 np.where(unver & unknown, self.withheld, 0))
        self.unknown = ~reported | (div & bad) | unver
        return Judged(div, forged, unver, doubtful)


def _off_diagonal(a: np.ndarray) -> np.ndarray:
    """A copy of the (N, N) ``a`` without its diagonal (no (N, N) mask kept
    for it: 100 MB at 10,000 agents)."""
    out = np.array(a, dtype=bool)
    np.fill_diagonal(out, False)
    return out


class Online:
    """The check as a run goes: ``replay`` and ``Judge`` one tick at a time,
    each tick once its reports are final (the mesh's world), so an agent
    that lies is named at the tick an honest agent fused its lie, not at the
    run's end. ``tick(k, claims, planned, said)``: ``claims`` the run's
    claims so far (at least tick k's), ``planned`` tick k's planned links
    (an agent-tick without a report: its row), ``said`` the digests its
    reports gave. The same
    numbers as ``verify``'s replay, bit for bit: the same engine step
    (``batch.Stepper``) on the same links, restarts and digests. Once the
    engine's own replay diverges (``ended``: that tick) nothing more is
    checked.

    Each tick replayed is kept (its estimates, the digests of the engine's
    messages it computed, and ``replay_inputs``' digest of its links and
    restarts), so that ``verify`` at the run's end takes the replay from
    here where the whole run's claims give every tick the same inputs
    (``replayed``), instead of computing it a second time. ``release``
    lets the engine's state go and keeps these."""

    def __init__(self, trace: Trace, algorithm: str, params, message_digest=None):
        B, K, N = trace.has.shape
        self.trace, self.message_digest = trace, message_digest
        self.algorithm, self.params = algorithm, params
        self.step = batch.Stepper(trace.model, trace.sensors, algorithm, params, trace.seeds[:1], K)
        self.judge = Judge(N)
        self.links = None
        self.ended = 0
        self.diagonal = (np.arange(N), np.arange(N))
        self.kept = []  # [tick - 1] -> (inputs digest, x, P, d, d_valid, {sender: engine digest})

    def tick(self, k: int, claims: RunClaims, planned, said: tuple) -> Judged | None:
        """Tick k's ``Judged``, or None after the engine's replay diverged.
        ``planned``: a function that makes tick k's planned links (N, N),
        called only if some report of tick k did not come; ``said``: the
        digests reported of tick k's fused messages, three (J,) arrays:
        receivers, senders, digests (``digest_values``)."""
        if self.ended or self.step is None or k != self.step.k + 1:
            return None
        reported = claims.reported[k - 1]
        N = reported.shape[0]
        links = replay_links(claims, k, lambda _: planned(), self.diagonal)
        rows, cols, values = said
        checked = self.message_digest is not None and len(cols) > 0
        senders = np.unique(cols) if checked else None
        engine = np.zeros(N, dtype=np.uint64)

        def listen(_, msg):
            engine[senders] = digest_values(self.message_digest(k, senders, msg))

        restarts = [r for r in claims.restarts if r.tick == k]
        inputs = replay_inputs(k, links, restarts, claims)
        if restarts:
            self.step.state = restart_at(k, restarts, claims, self.step.est, self.step.state)
        changed = self.links is None or bool((links != self.links).any())
        self.links = links
        tr = self.trace
        try:
            out = self.step.step(tr.y[:1, k - 1], tr.has[:1, k - 1], links[None] if changed else None,
                                 listen if checked else None)
        except batch.Diverged:
            self.ended = k
            return None
        if len(self.kept) == k - 1:
            computed = dict(zip(senders.tolist(), engine[senders].tolist())) if checked else {}
            self.kept.append((inputs, *(np.array(a[0]) for a in (out.x, out.P, out.d, out.d_valid)), computed))
        bad, _ = compare(reported, claims.x[k - 1], claims.P[k - 1], claims.d[k - 1], claims.d_valid[k - 1],
                         out.x[0], out.P[0], out.d[0], out.d_valid[0], largest=False)
        has, wrong = np.zeros((N, N), dtype=bool), np.zeros((N, N), dtype=bool)
        if checked:
            has[rows, cols] = True
            wrong[rows, cols] = engine[cols] != values
        return self.judge.tick(k, reported, bad, claims.fused[k - 1], has, wrong, [r.agent for r in restarts])

    def release(self) -> None:
        """The run is over: the engine's state and links go (no tick is
        checked after); the ticks kept stay for ``replayed``."""
        self.step = self.links = None

    def replayed(self, trace: Trace, algorithm: str, params, claims: RunClaims, planned: "TickLinks",
                 message_digest, wanted) -> tuple | None:
        """``replay``'s (Estimates, digests) of ticks 1..K of ``claims``
        from the ticks kept, or None where it would not be that replay bit
        for bit: another run (trace, estimator, settings or digest), a tick
        not kept (never checked, or after the replay diverged), a tick whose
        links or restarts the whole run's claims give otherwise than they
        were when it was checked, or a digest ``wanted`` it did not compute."""
        K = claims.reported.shape[0]
        if trace is not self.trace or algorithm != self.algorithm or params != self.params \
                or message_digest is not self.message_digest or len(self.kept) < K:
            return None
        by_tick = {}
        for r in claims.restarts:
            by_tick.setdefault(int(r.tick), []).append(r)
        need = {}
        for k, s in wanted or ():
            need.setdefault(k, set()).add(s)
        digests = {}
        for k in range(1, K + 1):
            inputs, *_, computed = self.kept[k - 1]
            links = replay_links(claims, k, planned.at, self.diagonal)
            if replay_inputs(k, links, by_tick.get(k, ()), claims) != inputs:
                return None
            for s in need.get(k, ()):
                if s not in computed:
                    return None
                digests[(k, s)] = computed[s]
        x, P, d, dv = (np.stack([kept[i] for kept in self.kept[:K]])[None] for i in range(1, 5))
        return Estimates(x, P, d, dv), digests


# --------------------------------------------------------------------------
# the verdict
# --------------------------------------------------------------------------
def verify(trace: Trace, algorithm: str, params, claims: RunClaims, *, planned: np.ndarray | None = None,
           message_digest=None, labels=None, online: Online | None = None) -> RunStatus:
    """The run's status (module docstring). ``planned``: the fault plan's
    delivered sets (``planned_links``; None: no faults injected, the
    nominal links); ``message_digest(k, sender indices, the tick's Message
    batch) -> [bytes]``: the digests an agent reports of the messages it
    fused (``mesh.wire.codec.engine_digests``; None: digests are not checked); ``labels``: the agents' names in the evidence (default: the
    trace's); ``online``: the run's check as it went, whose replay of each
    tick is taken where it is this replay bit for bit (``Online.replayed``;
    the evidence's ``replayed_online`` says whether it was)."""
    whole = claims
    K_all, N = claims.reported.shape
    names = list(labels if labels is not None else trace.agent_labels)
    name = lambda j: names[j]  # noqa: E731
    # the replay ends at the last tick anyone reported: a run stopped early is not replayed to its planned end
    K = int(np.flatnonzero(claims.reported.any(-1))[-1]) + 1 if claims.reported.any() else 0
    if K < K_all:
        claims = first_claims(claims, K)
        planned = None if planned is None else planned[:K]
    missing = ~whole.reported
    if K == 0:
        return _nothing_replayed(whole, f"no report came: {K_all * N} agent-ticks missing")
    nominal = TickLinks(K, trace, claims.live)
    planned = nominal if planned is None else tick_links(planned, K, trace, claims.live)
    wanted = None
    if message_digest is not None:
        wanted = {(k, int(s)) for k in range(1, K + 1) for s in np.unique(tick_digests(claims.digests, k)[1])}
    kept = None if online is None else online.replayed(trace, algorithm, params, claims, planned, message_digest,
                                                        wanted)
    try:
        est, engine_digests = kept if kept is not None else \
            replay(trace, algorithm, params, claims, planned, message_digest, wanted)
        ended = None
    except batch.Diverged as e:  # the algorithm itself diverges on what was delivered: replay the ticks before
        ended = {"tick": e.tick, "reason": str(e),
                 "reported_after": int(claims.reported[e.tick - 1:].sum())}
        K = e.tick - 1
        if K == 0:
            return _nothing_replayed(whole, f"the engine's replay diverged at tick 1 ({e}): nothing verified",
                                     replay_ended=ended)
        claims, planned, nominal = first_claims(claims, K), planned.cut(K), nominal.cut(K)
        wanted = None if wanted is None else {(k, s) for k, s in wanted if k <= K}
        est, engine_digests = replay(trace, algorithm, params, claims, planned, message_digest, wanted)
    bad, gap = differing(claims, est)
    restarts = {}
    for r in claims.restarts:
        restarts.setdefault(int(r.tick), []).append(int(r.agent))
    judge = Judge(N)
    diverged, unverifiable = [], []
    for k in range(1, K + 1):
        has, wrong = np.zeros((N, N), dtype=bool), np.zeros((N, N), dtype=bool)  # [receiver, sender]
        if engine_digests:
            engine = np.array([engine_digests.get((k, s), 0) for s in range(N)], dtype=np.uint64)
            rows, cols, said = tick_digests(claims.digests, k)
            has[rows, cols] = True
            wrong[rows, cols] = engine[cols] != said
        withheld = judge.withheld.copy()
        j = judge.tick(k, claims.reported[k - 1], bad[k - 1], claims.fused[k - 1], has, wrong, restarts.get(k, ()))
        for r in np.flatnonzero(j.diverged).tolist():
            diverged.append((k, r, np.flatnonzero(j.forged[r]).tolist()))
        for r in np.flatnonzero(j.unverified).tolist():
            unverifiable.append((k, r, np.flatnonzero(j.doubtful[r]).tolist(), withheld))
    first = diverged[0] if diverged else None
    unverified = len(unverifiable)

    complete = bool(whole.reported.all())
    ev = {"agent_ticks": K_all * N, "reported": int(claims.reported.sum()), "ticks": K_all, "ticks_replayed": K,
          "differing": int(bad.sum()), "max_abs_difference": float(gap.max()) if gap.size else 0.0,
          "unverified": unverified,
          "digests_checked": sum(len(v[0]) for v in claims.digests.values()) if message_digest else 0,
          "restarts": len(claims.restarts), "replayed_online": kept is not None}
    ev["missing_agent_ticks"] = int(missing.sum())
    ev["missing_fraction"] = float(missing.sum()) / (K_all * N) if K_all * N else 0.0
    if ended is not None:
        ev["replay_ended"] = ended
        ev["unverified"] += ended["reported_after"]

    if first is not None:
        k, j, forged = first
        senders = [name(s) for s in forged]
        ev["diverged"] = {"tick": k, "agent": name(j), "senders": senders,
                          "max_abs_difference": float(gap[k - 1, j]), "agent_ticks": len(diverged),
                          "first": [{"tick": kk, "agent": name(jj), "senders": [name(s) for s in ff]}
                                    for kk, jj, ff in diverged[:LISTED]]}
        ev["diverged"]["estimate_differs"] = bool(bad[k - 1, j])
        if senders:
            what = (f"agent {name(j)} fused at tick {k} a message of agent {', '.join(map(str, senders))} that the "
                    "engine does not reproduce" + (" and its estimate differs from the engine's replay"
                                                   if bad[k - 1, j] else ""))
        else:
            what = (f"agent {name(j)}'s estimate of tick {k} differs from the engine's replay, though every "
                    "message it fused was the engine's")
        return RunStatus(DIVERGED_STATUS, f"{what} ({len(diverged)} agent-ticks diverged)", ev)

    shortfall = _shortfall(claims, planned, nominal, name)
    ev.update(shortfall)
    missing_line = ""
    if not complete:
        why = Counter()
        if whole.why is not None:
            why.update(str(w) or "not run" for w in whole.why[missing])
        ev["missing_why"] = dict(sorted(why.items()))
        missing_line = (f"{ev['missing_agent_ticks']} of {K_all * N} agent-ticks not reported "
                        f"({100 * ev['missing_fraction']:.1f} %)"
                        + (f": {', '.join(f'{w} {n}' for w, n in ev['missing_why'].items())}" if why else ""))
    after = (f"the engine's replay itself diverged at tick {ended['tick']} ({ended['reason']}), so "
             f"{ended['reported_after']} agent-ticks reported from it on are not verified" if ended else "")
    if unverifiable:
        ev["unverifiable"], line = _unverifiable(unverifiable, name)
        return RunStatus(UNVERIFIABLE_STATUS, "; ".join(p for p in (line, missing_line, after) if p), ev)
    if not complete or (ended and ended["reported_after"]):
        return RunStatus(INCOMPLETE_STATUS, "; ".join(p for p in (missing_line, after) if p), ev)
    if shortfall["degraded"]["agent_ticks"]:
        dg = shortfall["degraded"]
        reasons = ", ".join(f"{w} {n}" for w, n in dg["why"].items())
        first_one = dg["listed"][0]
        return RunStatus(DEGRADED_STATUS, f"{dg['agent_ticks']} of {K * N} agent-ticks fused fewer messages than "
                         f"planned ({dg['messages']} messages: {reasons}); first: agent {first_one['agent']} at "
                         f"tick {first_one['tick']}; every estimate equals the engine's replay", ev)
    if shortfall["unplanned"]["agent_ticks"]:
        first_one = shortfall["unplanned"]["listed"][0]
        return RunStatus(DEGRADED_STATUS, f"{shortfall['unplanned']['agent_ticks']} agent-ticks fused a sender not "
                         f"planned (not live, in range and delivered); first: agent {first_one['agent']} at tick "
                         f"{first_one['tick']}; every estimate equals the engine's replay", ev)
    if claims.restarts:
        r = claims.restarts[0]
        return RunStatus(DEGRADED_STATUS, f"{len(claims.restarts)} re-initialisation(s), first: agent {name(r.agent)} "
                         f"at tick {r.tick} from " + (f"agent {name(r.source)}'s estimate" if r.source is not None
                                                        else "its prior")
                         + "; every estimate equals the engine's replay", ev)
    if shortfall["planned_out"]:
        return RunStatus(AS_PLANNED_STATUS, f"every agent-tick fused what the fault plan delivered "
                         f"({shortfall['planned_out']} of {shortfall['nominal_links']} links dropped by the injected "
                         "faults); every estimate equals the engine's replay", ev)
    return RunStatus(EXACT_STATUS, f"all {K * N} agent-ticks reported, fused every nominal link, and equal the "
                     "engine's replay bit for bit", ev)


def _nothing_replayed(claims: RunClaims, reason: str, **evidence) -> RunStatus:
    """``incomplete``, with not one tick replayed."""
    K, N = claims.reported.shape
    missing = int((~claims.reported).sum())
    return RunStatus(INCOMPLETE_STATUS, reason, {"agent_ticks": K * N, "reported": K * N - missing, "ticks": K,
                                                 "ticks_replayed": 0, "missing_agent_ticks": missing,
                                                 "missing_fraction": missing / (K * N) if K * N else 0.0,
                                                 **evidence})


def _unverifiable(found: list, name) -> tuple:
    """(evidence, line) of an ``unverifiable`` run: ``found`` [(tick, agent,
    unknown senders whose messages it fused, the ticks of the missing
    reports that made states unknown (N,))]."""
    sources = {}
    for k, j, senders, withheld in found:
        for a in [j, *senders]:
            if withheld[a] > 0:
                sources.setdefault(a, int(withheld[a]))
    ev = {"agent_ticks": len(found),
          "listed": [{"tick": k, "agent": name(j), "senders": [name(s) for s in ss]} for k, j, ss, _ in found[:LISTED]],
          "withheld": [{"agent": name(a), "tick": t} for a, t in sorted(sources.items(), key=lambda at: at[1])]}
    k, j, senders, _ = found[0]
    roots = ", ".join(f"agent {w['agent']}'s report of tick {w['tick']}" for w in ev["withheld"][:3])
    return ev, (f"{len(found)} reported agent-ticks cannot be verified: they differ from the engine's replay on a "
                "state the run did not report" + (f" ({roots} did not come)" if roots else "")
                + f"; first: agent {name(j)} at tick {k}"
                + (f", fusing agent {', '.join(str(name(s)) for s in senders)}'s message" if senders else ""))


def _shortfall(claims: RunClaims, planned: TickLinks, nominal: TickLinks, name) -> dict:
    """The reported agent-ticks whose fused set is not the planned one:
    fewer (``degraded``, with the agents' reasons; ``beyond_missing``: those
    lacking a sender that reported the tick) or others (``unplanned``).
    One tick at a time (a large run's (K, N, N) temporaries would not fit)."""
    K, N = claims.reported.shape
    diagonal = np.arange(N)
    why = Counter()
    listed, extra = [], []
    short_n = messages = more_n = beyond = 0
    for k0 in range(K):
        plan = planned.at(k0)
        differ = claims.fused[k0] ^ plan
        differ[diagonal, diagonal] = False
        differ &= claims.reported[k0][:, None]
        if not differ.any():
            continue
        less, more = differ & plan, differ & ~plan
        messages += int(less.sum())
        for j in np.flatnonzero(less.any(-1)).tolist():
            short_n += 1
            said = dict(claims.verdicts.get((k0 + 1, j), ()))
            missing = np.flatnonzero(less[j]).tolist()
            beyond += bool(claims.reported[k0, missing].any())  # a sender it lacks did report the tick
            reasons = [said.get(s, "not said") for s in missing]
            why.update(reasons)
            if len(listed) < LISTED:
                listed.append({"tick": k0 + 1, "agent": name(j),
                               "not_fused": {str(name(s)): w for s, w in zip(missing, reasons)}})
        for j in np.flatnonzero(more.any(-1)).tolist():
            more_n += 1
            if len(extra) < LISTED:
                extra.append({"tick": k0 + 1, "agent": name(j), "senders": [name(s) for s in np.flatnonzero(more[j])]})
    links = nominal.off_diagonal()
    planned_out = 0 if planned is nominal else links - planned.off_diagonal()
    return {"degraded": {"agent_ticks": short_n, "messages": messages, "why": dict(sorted(why.items())),
                         "beyond_missing": beyond, "listed": listed},
            "unplanned": {"agent_ticks": more_n, "listed": extra},
            "nominal_links": links, "planned_out": planned_out}
