"""engine.verify on engine-made runs: each status, named where it starts.

A run's claims are made here from the engine itself (what a faithful mesh
reports), then changed the way a fault, a paused agent, a tampered report
or a forged message changes them; ``verify`` must give the status and name
the agent, tick and sender."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from diskf_mesh.core import exits
from diskf_mesh.data.faults import FaultConfig
from diskf_mesh.data.scenario import load_scenario, simulate
from diskf_mesh.engine import verify as V
from diskf_mesh.estimators import get as get_estimator
from diskf_mesh.mesh.wire import codec as wire
from diskf_mesh.mesh.protocol.estimator import AgentEstimator

TICKS, SEED, ALG, RUN = 40, 3, "diskf", "verify"


@pytest.fixture(scope="module")
def run():
    scn = load_scenario("dynamic").with_overrides(steps=TICKS)
    trace = simulate(scn, [SEED])
    return scn, trace


def digester(trace):
    return wire.engine_digests(RUN, trace.sensors.ids, get_estimator(ALG).exchanged)


def claims_of(scn, trace, links=None, restarts=(), live=None):
    """What a faithful mesh reports on ``links`` (default: nominal): every
    agent an ``AgentEstimator`` (a batch of one, as in an agent process)
    fusing exactly its row of ``links``, a restarted agent a fresh one
    re-initialised from its source's fused estimate of the tick before (as
    ``agents.rejoin``), and a digest of every message fused."""
    K, N = trace.has.shape[1:]
    ids = list(trace.sensors.ids)
    links = V.nominal_links(trace, K, live) if links is None else links
    estimator = get_estimator(ALG)
    agents = {i: AgentEstimator(scn, i, estimator, K, SEED) for i in ids}
    x, P, d = np.full((K, N, 2), np.nan), np.full((K, N, 2, 2), np.nan), np.full((K, N, 1), np.nan)
    dv, fd = np.zeros((K, N), bool), {}
    exchanged = estimator.exchanged
    for k in range(1, K + 1):
        for r in restarts:
            if r.tick == k:
                start = None if r.source is None else (x[k - 2, r.source], P[k - 2, r.source])  # None: the prior
                agents[ids[r.agent]] = AgentEstimator(scn, ids[r.agent], estimator, K, SEED, start=start)
        msgs = {i: agents[i].local(k, bool(trace.has[0, k - 1, j]), trace.y[0, k - 1, j, :agents[i].p])
                for j, i in enumerate(ids)}
        for j, i in enumerate(ids):
            heard = {}
            for s in np.flatnonzero(links[k - 1, j]).tolist():
                if s != j:
                    heard[ids[s]] = msgs[ids[s]].take((0, 0))
                    fd[(k, j, s)] = wire.message_digest(RUN, ids[s], k, heard[ids[s]], exchanged)
            out = agents[i].fuse(k, msgs[i], heard)
            x[k - 1, j], P[k - 1, j], d[k - 1, j], dv[k - 1, j] = out.x[0, 0], out.P[0, 0], out.d[0, 0], out.d_valid[0, 0]
    per = {}
    for (k, j, s), g in sorted(fd.items()):
        per.setdefault((k, j), []).append((s, g))
    digests = {kj: (np.array([s for s, _ in v]), V.digest_values([g for _, g in v])) for kj, v in per.items()}
    return V.RunClaims(x, P, d, dv, np.ones((K, N), bool), links, live, tuple(restarts), digests)


def check(trace, scn, claims, **kw):
    return V.verify(trace, ALG, scn.params, claims, message_digest=digester(trace), **kw)


def with_(claims, **changes):
    return replace(claims, **changes)


def test_exact(run):
    scn, trace = run
    st = check(trace, scn, claims_of(scn, trace))
    assert st.status == "exact", st.reason
    assert st.exit_code == exits.OK
    assert st.evidence["differing"] == 0 and st.evidence["digests_checked"] > 0


def test_dropped_link_is_degraded_naming_the_agent_tick(run):
    scn, trace = run
    links = V.nominal_links(trace, TICKS)
    k, r, s = next((k, r, s) for k, r, s in zip(*np.nonzero(links)) if r != s and k >= 10)
    links[k, r, s] = False
    claims = claims_of(scn, trace, links)
    claims = with_(claims, verdicts={(k + 1, r): ((s, "late"),)})
    st = check(trace, scn, claims)
    assert st.status == "degraded", st.reason
    assert st.exit_code == exits.DEGRADED
    dg = st.evidence["degraded"]
    assert dg["agent_ticks"] == 1 and dg["why"] == {"late": 1}
    names = trace.agent_labels
    assert dg["listed"] == [{"tick": int(k) + 1, "agent": names[r], "not_fused": {str(names[s]): "late"}}]
    assert st.accepted(allow_degraded=True) and not st.accepted()


def test_injected_faults_alone_are_as_planned(run):
    scn, trace = run
    nominal = V.nominal_links(trace, TICKS)
    planned = V.planned_links(nominal, trace.sensors.ids, FaultConfig(loss=0.3), SEED)
    assert (planned != nominal).any()
    st = check(trace, scn, claims_of(scn, trace, planned), planned=planned)
    assert st.status == "as planned", st.reason
    assert st.exit_code == exits.OK


def test_tampered_estimate_is_diverged_naming_agent_and_tick(run):
    scn, trace = run
    claims = claims_of(scn, trace)
    claims.x[24, 5, 0] += 1e-9
    st = check(trace, scn, claims)
    assert st.status == "diverged", st.reason
    assert st.exit_code == exits.DIVERGED
    dv = st.evidence["diverged"]
    assert (dv["tick"], dv["agent"], dv["senders"]) == (25, trace.agent_labels[5], [])
    assert not st.accepted(allow_missing=1.0, allow_degraded=True)


def test_tampered_message_digest_is_diverged_naming_the_sender(run):
    scn, trace = run
    claims = claims_of(scn, trace)
    k, r = sorted(kr for kr in claims.digests if kr[0] == 30)[0]
    senders, digests = claims.digests[(k, r)]
    digests[0] ^= np.uint64(1)
    s = int(senders[0])
    st = check(trace, scn, claims)
    assert st.status == "diverged", st.reason
    dv = st.evidence["diverged"]
    assert (dv["tick"], dv["agent"], dv["senders"]) == (k, trace.agent_labels[r], [trace.agent_labels[s]])


def test_a_rejoin_replays_exactly(run):
    """Agent 2 crashed after tick 14 and restarted at tick 17 from agent 0's
    fused estimate of tick 16, as a mesh's rejoin does: the replay restarts
    it there and every estimate is reproduced."""
    scn, trace = run
    K, N = TICKS, trace.has.shape[2]
    live = np.ones((K, N), bool)
    live[14:16, 2] = False
    restart = V.Restart(17, 2, 0)
    claims = claims_of(scn, trace, live=live, restarts=[restart])
    reported = live.copy()
    claims = with_(claims, reported=reported)
    st = check(trace, scn, claims, planned=None)
    assert st.status == "incomplete", st.reason
    assert st.evidence["differing"] == 0 and st.evidence["unverified"] == 0
    assert st.evidence["missing_agent_ticks"] == 2
    assert st.accepted(allow_missing=2 / (K * N))
    # without the restart the replay does not reproduce agent 2 (its prior is not agent 0's estimate)
    st = check(trace, scn, with_(claims, restarts=()))
    assert st.evidence["differing"] > 0 and st.status != "exact"


def test_a_complete_run_with_a_restart_is_degraded_never_exact(run):
    """Every agent-tick reported and every fused set nominal, but agent 2
    (index 2) re-initialised from agent 0's estimate at tick 17 (frozen past the lease
    while the world was frozen too: no tick missed): its estimates are the
    replay's, not the algorithm's own, so the run is degraded, not exact."""
    scn, trace = run
    claims = claims_of(scn, trace, restarts=[V.Restart(17, 2, 0)])
    st = check(trace, scn, claims)
    assert st.status == "degraded" and "agent 3 at tick 17 from agent 1" in st.reason, st.reason  # ids from 1
    assert st.evidence["differing"] == 0 and st.evidence["restarts"] == 1
    assert not st.accepted() and st.accepted(allow_degraded=True)


def test_a_restart_from_the_prior_and_a_handed_state(run):
    """A restart from the prior (no neighbour in range) replays as a fresh
    agent; one handed a state replays from exactly that state, and a handed
    state the agent did not start from is caught."""
    scn, trace = run
    K, N = TICKS, trace.has.shape[2]
    live = np.ones((K, N), bool)
    live[20:22, 6] = False
    claims = claims_of(scn, trace, live=live, restarts=[V.Restart(23, 6, None)])
    claims = with_(claims, reported=live.copy())
    st = check(trace, scn, claims)
    assert st.status == "incomplete" and st.evidence["differing"] == 0 and st.evidence["unverified"] == 0
    handed = V.Restart(23, 6, 0, claims.x[21, 0].copy(), claims.P[21, 0].copy())
    claims = with_(claims_of(scn, trace, live=live, restarts=[V.Restart(23, 6, 0)]), reported=live.copy())
    assert check(trace, scn, with_(claims, restarts=(handed,))).evidence["differing"] == 0
    wrong = V.Restart(23, 6, 0, claims.x[21, 0] + 1.0, claims.P[21, 0].copy())
    st = check(trace, scn, with_(claims, restarts=(wrong,)))
    dv, six = st.evidence["diverged"], trace.agent_labels[6]
    assert st.status == "diverged" and dv["tick"] == 23
    # named as the agent whose estimate differs, or as the sender of a message its neighbours fused
    assert dv["agent"] == six or six in dv["senders"], dv


def test_a_missing_report_then_agreement_is_known_again(run):
    """A report that did not come (the agent went on) makes its tick
    unknown; once its next report equals the replay the agent is known
    again, and a later tampering is still caught."""
    scn, trace = run
    claims = claims_of(scn, trace)
    claims.reported[9, 4] = False
    st = check(trace, scn, claims)
    assert st.status == "incomplete" and st.evidence["differing"] == 0
    claims.x[30, 4, 1] *= 1.5
    st = check(trace, scn, claims)
    assert st.status == "diverged" and st.evidence["diverged"]["tick"] == 31


def test_allow_missing_accepts_only_what_the_missing_reports_explain(run):
    """Agent 4 sent nothing and reported nothing at tick 10: its neighbours
    fused less that tick, which the missing agent-tick explains, so
    ``--allow-missing`` alone accepts the run. A link dropped elsewhere
    between two agents that both reported is degradation the missing
    agent-tick does not explain: the run stays incomplete, and only
    ``--allow-missing`` with ``--allow-degraded`` accepts it."""
    from diskf_mesh.mesh.protocol.run_status import accept

    scn, trace = run
    K, N = trace.has.shape[1:]
    links = V.nominal_links(trace, TICKS)
    j = 4
    assert links[9, :, j].sum() > 1  # agent 4 had neighbours at tick 10
    links[9, np.arange(N) != j, j] = False
    claims = claims_of(scn, trace, links)
    claims.reported[9, j] = False
    st = check(trace, scn, claims)
    assert st.status == "incomplete" and st.evidence["differing"] == 0, st.reason
    assert st.evidence["degraded"]["agent_ticks"] > 0 and st.degraded_beyond_missing == 0
    assert st.accepted(allow_missing=1 / (K * N))
    assert accept(st, allow_missing=1 / (K * N))[:2] == (exits.OK, "warning")

    k, r, s = next((k, r, s) for k, r, s in zip(*np.nonzero(links)) if r != s and k >= 20)
    links[k, r, s] = False
    claims = claims_of(scn, trace, links)
    claims.reported[9, j] = False
    st = check(trace, scn, claims)
    assert st.status == "incomplete" and st.degraded_beyond_missing == 1, st.reason
    assert not st.accepted(allow_missing=1.0)
    code, level, line = accept(st, allow_missing=1.0)
    assert (code, level) == (exits.INCOMPLETE, "error") and "--allow-degraded" in line
    assert st.accepted(allow_missing=1 / (K * N), allow_degraded=True)
    assert accept(st, allow_missing=1.0, allow_degraded=True)[:2] == (exits.OK, "warning")


def test_accept_is_the_one_place_a_status_meets_the_users_tolerances():
    from diskf_mesh.mesh.protocol.run_status import accept

    degraded = V.RunStatus("degraded", "3 agent-ticks fused fewer messages than planned", {})
    incomplete = V.RunStatus("incomplete", "2 of 100 agent-ticks not reported", {"missing_fraction": 0.02})
    diverged = V.RunStatus("diverged", "agent 3 ...", {})
    assert accept(V.RunStatus("exact", "", {}))[:2] == (exits.OK, "")
    assert accept(V.RunStatus("as planned", "", {}))[:2] == (exits.OK, "")
    assert accept(degraded)[:2] == (exits.DEGRADED, "error")
    assert accept(degraded, allow_degraded=True)[:2] == (exits.OK, "warning")
    # real time: misses within --max-miss-rate are accepted degradation, beyond it exit TOO_MANY_MISSES
    assert accept(degraded, miss_rate=0.01, max_miss_rate=0.05)[:2] == (exits.OK, "warning")
    assert accept(degraded, miss_rate=0.10, max_miss_rate=0.05)[0] == exits.TOO_MANY_MISSES
    assert accept(incomplete)[:2] == (exits.INCOMPLETE, "error")
    assert accept(incomplete, allow_missing=0.02)[:2] == (exits.OK, "warning")
    assert accept(incomplete, allow_missing=0.01)[0] == exits.INCOMPLETE
    for kw in ({}, {"allow_degraded": True, "allow_missing": 1.0}, {"miss_rate": 0.0, "max_miss_rate": 1.0}):
        assert accept(diverged, **kw)[:2] == (exits.DIVERGED, "error")
    assert len({exits.OK, exits.FAILED, exits.BAD_INPUT, exits.INCOMPLETE, exits.TOO_MANY_MISSES, exits.DEGRADED,
                exits.DIVERGED}) == 7


def test_a_run_stopped_early_is_replayed_to_its_last_report_only(run):
    """A world stopped at tick 25 of 40: the replay ends at tick 25 (a run
    planned for 100,000 ticks and stopped at 100 does not replay the rest)."""
    scn, trace = run
    claims = claims_of(scn, trace)
    claims.reported[25:] = False
    st = check(trace, scn, claims)
    assert st.status == "incomplete" and st.evidence["ticks_replayed"] == 25 and st.evidence["differing"] == 0
    assert st.evidence["missing_agent_ticks"] == 15 * trace.has.shape[2]
    claims.reported[:] = False
    assert check(trace, scn, claims).evidence["ticks_replayed"] == 0


def test_allow_missing_never_accepts_a_run_with_no_agent_tick_reported():
    """A world that gave up at its start reported nothing: no share of
    missing agent-ticks accepts it (exit 3, not 0), and the line says why."""
    from diskf_mesh.mesh.protocol.run_status import accept

    st = V.RunStatus("incomplete", "after 30 s waiting for the agents: no agent process for id 4",
                   {"agent_ticks": 90, "reported": 0, "missing_agent_ticks": 90, "missing_fraction": 1.0})
    assert not st.accepted(allow_missing=1.0, allow_degraded=True)
    code, level, line = accept(st, allow_missing=1.0)
    assert (code, level) == (3, "error") and "nothing to accept" in line
    some = V.RunStatus("incomplete", "agent 4 missing", {"agent_ticks": 90, "reported": 89, "missing_agent_ticks": 1,
                                                       "missing_fraction": 1 / 90})
    assert some.accepted(allow_missing=1.0) and accept(some, allow_missing=1.0)[0] == 0


@pytest.mark.parametrize("algorithm", ["diskf", "diskf-auto"])
def test_the_engines_digests_are_the_digests_of_the_messages_the_agents_encode(run, algorithm):
    """``wire.engine_digests`` (every sender of a tick at once, the fields
    that do not change packed once) hashes the bytes ``encode`` puts on the
    wire, at ticks of every msgpack integer width and either ``d_valid``."""
    from diskf_mesh.engine import batch

    scn, trace = run
    exchanged = get_estimator(algorithm).exchanged
    ids = list(trace.sensors.ids)
    step = batch.Stepper(trace.model, trace.sensors, algorithm, scn.params, trace.seeds[:1], TICKS)
    msgs = []
    step.step(trace.y[:1, 0], trace.has[:1, 0], trace.links[:1, 0], lambda k, msg: msgs.append(msg))
    msg = msgs[0]
    flipped = replace(msg, d_valid=~np.asarray(msg.d_valid))
    digests = wire.engine_digests(RUN, ids, exchanged)
    for k in (1, 127, 128, 255, 256, 65535, 65536, 2 ** 32 + 1):
        for m, senders in ((msg, list(range(len(ids)))), (flipped, [4, 0, 7])):
            assert digests(k, senders, m) == [wire.message_digest(RUN, ids[s], k, m.take((slice(0, 1), slice(s, s + 1))),
                                                                  exchanged) for s in senders], (k, senders)


def _checked_as_it_went(trace, scn, claims, planned=None):
    """An ``Online`` fed ``claims`` tick by tick, as the world feeds it."""
    N = trace.has.shape[2]
    online = V.Online(trace, ALG, scn.params, digester(trace))
    nominal = V.TickLinks(TICKS, trace, claims.live)
    planned = nominal if planned is None else V.tick_links(planned, TICKS, trace, claims.live)
    for k in range(1, TICKS + 1):
        said = V.tick_digests(claims.digests, k)
        online.tick(k, claims, lambda: planned.at(k - 1), said)
    online.release()
    assert len(online.kept) == TICKS and N
    return online


def test_the_end_of_run_check_takes_the_replay_the_check_as_it_went_made(run):
    """A run with a restart from a neighbour's estimate and a missing
    report: ``verify`` with the check that went with it takes its replay
    (``replayed_online``), whose estimates and digests are the full
    replay's bit for bit, and gives the same status and evidence."""
    scn, trace = run
    K, N = TICKS, trace.has.shape[2]
    live = np.ones((K, N), bool)
    live[14:16, 2] = False
    claims = with_(claims_of(scn, trace, live=live, restarts=[V.Restart(17, 2, 0)]), reported=live.copy())
    claims.reported[30, 5] = False
    online = _checked_as_it_went(trace, scn, claims)
    planned = V.TickLinks(K, trace, claims.live)
    wanted = {(k, int(s)) for k in range(1, K + 1) for s in np.unique(V.tick_digests(claims.digests, k)[1])}
    kept = online.replayed(trace, ALG, scn.params, claims, planned, online.message_digest, wanted)
    full = V.replay(trace, ALG, scn.params, claims, planned, online.message_digest, wanted)
    assert kept is not None and kept[1] == full[1] and len(full[1]) > 0
    for a, b in zip(kept[0].__dict__.values(), full[0].__dict__.values()):
        assert a.tobytes() == b.tobytes()
    st, again = (V.verify(trace, ALG, scn.params, claims, message_digest=online.message_digest, online=o)
                 for o in (online, None))
    assert st.evidence.pop("replayed_online") and not again.evidence.pop("replayed_online")
    assert (st.status, st.reason, st.evidence) == (again.status, again.reason, again.evidence)
    assert st.status == "incomplete" and st.evidence["differing"] == 0


def test_the_end_of_run_check_replays_again_what_changed_since_it_was_checked(run):
    """Claims that differ from those the check saw as the run went (a link
    dropped at tick 12 after it was checked; a restart it did not see):
    ``verify`` replays the run itself, and finds what the claims say."""
    scn, trace = run
    claims = claims_of(scn, trace)
    online = _checked_as_it_went(trace, scn, claims)
    links = np.array(claims.fused)
    r, s = next((r, s) for r, s in zip(*np.nonzero(links[11])) if r != s)
    links[11, r, s] = False
    dropped = claims_of(scn, trace, links=links)
    st = V.verify(trace, ALG, scn.params, dropped, message_digest=online.message_digest, online=online)
    assert not st.evidence["replayed_online"] and st.status == "degraded", st.reason
    restarted = claims_of(scn, trace, restarts=[V.Restart(17, 2, 0)])
    st = V.verify(trace, ALG, scn.params, restarted, message_digest=online.message_digest, online=online)
    assert not st.evidence["replayed_online"] and st.status == "degraded" and st.evidence["differing"] == 0
    same = V.verify(trace, ALG, scn.params, claims, message_digest=online.message_digest, online=online)
    assert same.evidence["replayed_online"] and same.status == "exact"
