"""The attacks and faults that once ended in a wrong estimate reported as
complete, driven on the simulated network with the real machines: each run
now ends with a status that says what happened, and the estimates it
reports are the engine's replay of what was fused.

    a paused agent           longer than the collect timeout, shorter than the lease
    a compromised process    holding only its own identity, it forges another agent's messages
    an extreme message       an insider's own, well-formed, far out
    skewed probabilities     an insider's diskf-auto message whose model probabilities are not its own
    a forged report          an agent's report with an absurd estimate
    a rejoin                 a crashed agent restarts and starts from a neighbour's estimate
    a diverging estimator    the agent stops and tells the world why: its missing ticks say "diverged"
"""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from diskf_mesh import estimators
from diskf_mesh.data.scenario import load_scenario, simulate
from diskf_mesh.engine import batch
from diskf_mesh.mesh.protocol import events as ev
from diskf_mesh.mesh.wire import codec as wire
from diskf_mesh.mesh.protocol.agent_machine import AgentTiming
from diskf_mesh.mesh.wire.keys import Keys
from diskf_mesh.mesh.simulated.simnet import Fault, Link
from diskf_mesh.mesh.simulated.simrun import SimPlan, agent_pid, simulate_run

K = 40
RUN = "sim"
KEYS = Keys(RUN)
EXCHANGED = estimators.get("diskf").exchanged


@pytest.fixture(scope="module")
def quadrants():
    scn = load_scenario("quadrants").with_overrides(steps=K)  # four agents, every one linked to every other
    return scn, simulate(scn, [0])


def run(quadrants, **plan):
    scn, trace = quadrants
    return simulate_run(scn, trace, "diskf", 0, run_id=RUN, plan=SimPlan(Link(delay=0.002), **plan))


class Tamper:
    """A machine whose effects pass through ``edit(effect) -> effect``."""

    def __init__(self, inner, edit):
        self.inner, self.edit = inner, edit

    def __getattr__(self, name):
        return getattr(self.inner, name)

    def start(self, now):
        return [self.edit(e) for e in self.inner.start(now)]

    def handle(self, event, now):
        return [self.edit(e) for e in self.inner.handle(event, now)]


def extreme(payload: bytes, sender: int) -> bytes:
    m = wire.decode(payload, run_id=RUN, sender=sender, exchanged=EXCHANGED)
    n = m.message.x_pred.shape[-1]
    far = dataclasses.replace(m.message, x_pred=np.full(n, 9e11), x_upd=np.full(n, 9e11), P_pred=1e-6 * np.eye(n),
                              P_upd=1e-6 * np.eye(n))
    return wire.encode(RUN, sender, m.tick, far, EXCHANGED)


def engine(quadrants):
    scn, trace = quadrants
    return batch.run(trace, "diskf", scn.params)


def test_nominal_run_is_exact_and_the_engine(quadrants):
    r = run(quadrants)
    assert r.status.status == "exact"
    assert np.array_equal(r.record.x, engine(quadrants).x[0])


def test_a_paused_agent_is_degraded_not_complete(quadrants):
    # agent 2 stops for 5 s at tick ~10: longer than the 2 s collect timeout, shorter than the 10 s lease
    r = run(quadrants, agent_timing=AgentTiming(collect_timeout=2.0),
            faults=(Fault("pause", agent_pid(2), at=10 * 3 * 0.002, duration=5.0),))
    st = r.status
    assert st.status == "degraded", st.reason
    assert st.evidence["degraded"]["agent_ticks"] >= 1 and st.evidence["differing"] == 0
    assert not np.array_equal(r.record.x, engine(quadrants).x[0])  # what it fused differs from the nominal links


class Forger:
    """Forges agent 4's message of every tick, far out, as soon as the world's
    tick opens it (from agent 4's message of the tick before, as agent 1 hears it)."""

    read = ev.Sample  # takes its samples as they are

    def __init__(self, boot):
        self.last = None

    def start(self, now):
        return [ev.Subscribe(KEYS.msg_to(1)), ev.Subscribe(KEYS.tick)]

    def handle(self, e, now):
        kind, who = KEYS.parse(e.key)
        if kind == "msg" and who == 4:
            self.last = wire.decode(e.payload, run_id=RUN, sender=4, exchanged=EXCHANGED)
        elif kind == "tick" and self.last is not None:
            k = wire.decode_tick(e.payload, run_id=RUN).tick
            forged = extreme(wire.encode(RUN, 4, k, self.last.message, EXCHANGED), 4)
            return [ev.Publish(KEYS.msg(4, to=[1, 2, 3]), forged)]
        return []


def fast_intruder(sender, receiver):
    """The intruder's links are faster than the agents': its forgery comes first."""
    return Link(delay=0.0005) if sender == "intruder" else None


def test_a_compromised_process_cannot_speak_for_another_agent(quadrants):
    # it listens as agent 1 would (it holds agent 1's identity, the only one it finds) and forges agent 4
    r = run(quadrants, links=fast_intruder, extra=(("intruder", "agent-1", Forger, 0.0),))
    assert r.outcome.refused.get("put", 0) > 0  # the access rules refuse every forged put
    assert r.status.status == "exact"
    assert np.array_equal(r.record.x, engine(quadrants).x[0])


def test_with_a_router_identity_handed_out_the_forgery_is_caught_as_diverged(quadrants):
    # the run's credentials as they once were: the compromised process finds the router's identity too
    r = run(quadrants, router=True, links=fast_intruder, extra=(("intruder", "router", Forger, 0.0),))
    assert r.status.status == "diverged", r.status.reason
    assert r.status.evidence["diverged"]["senders"] == [4]


def test_an_extreme_insider_message_is_never_reported_exact(quadrants):
    def edit(e):
        if isinstance(e, ev.Publish) and KEYS.parse(e.key) == ("msg", 3):
            m = wire.decode(e.payload, run_id=RUN, sender=3, exchanged=EXCHANGED)
            if m.tick == 20:
                return dataclasses.replace(e, payload=extreme(e.payload, 3))
        return e

    r = run(quadrants, wrap={agent_pid(3): lambda m: Tamper(m, edit)})
    st = r.status
    assert st.status in ("diverged", "degraded"), st.reason
    if st.status == "diverged":  # fused: the engine does not reproduce agent 3's message
        assert st.evidence["diverged"]["tick"] == 20 and st.evidence["diverged"]["senders"] == [3]
    else:  # refused by the guard: fewer messages fused, every estimate the engine's replay
        assert st.evidence["differing"] == 0 and np.abs(r.record.x[r.record.reported]).max() < 1e6


def test_a_forged_report_is_never_taken(quadrants):
    def edit(e):
        if isinstance(e, ev.Publish) and KEYS.parse(e.key) == ("report", 3):
            rp = wire.decode_report(e.payload, run_id=RUN, sender=3)
            if rp.tick == 20:
                return dataclasses.replace(e, payload=wire.encode_report(
                    RUN, 3, rp.tick, np.full_like(rp.x, 1e300), rp.P, rp.d, rp.d_valid, rp.counters, rp.fused,
                    rp.not_fused, rp.sent_digest, rp.digests))
        return e

    r = run(quadrants, wrap={agent_pid(3): lambda m: Tamper(m, edit)})
    st = r.status
    assert st.status in ("incomplete", "diverged"), st.reason
    assert np.isfinite(r.record.x[r.record.reported]).all()
    assert not r.record.reported[19, 2] or st.status == "diverged"


def test_a_restarted_agent_starts_from_a_neighbours_estimate(quadrants):
    tick = 3 * 0.002  # a tick takes three link delays: tick, message, report
    r = run(quadrants, faults=(Fault("crash", agent_pid(2), at=10 * tick), Fault("restart", agent_pid(2), at=15 * tick)))
    rejoins = r.record.rejoins.get(2, [])
    assert rejoins and all(rj["source"] is not None for rj in rejoins), rejoins
    st = r.status
    assert st.status == "incomplete" and st.evidence["differing"] == 0, st.reason
    assert r.record.reported[-1].all()  # back to the end of the run


def test_an_insiders_model_probabilities_are_caught_as_diverged(quadrants):
    """diskf-auto: agent 3 sends, from tick 20 on, a well-formed message
    whose model probabilities put all but the floor on "no input" (its
    estimates its own). Its neighbours pool them, so their estimates move;
    the engine recomputes agent 3's honest message, so the run says
    diverged and names agent 3 at tick 20, never exact."""
    scn, trace = quadrants
    auto = estimators.get("diskf-auto").exchanged

    def edit(e):
        if isinstance(e, ev.Publish) and KEYS.parse(e.key) == ("msg", 3):
            m = wire.decode(e.payload, run_id=RUN, sender=3, exchanged=auto)
            if m.tick >= 20:
                w = np.full(m.message.w.shape, 1e-6)
                w[0] = 1.0 - 1e-6 * (w.size - 1)
                return dataclasses.replace(e, payload=wire.encode(RUN, 3, m.tick, dataclasses.replace(
                    m.message, w=w), auto))
        return e

    honest = simulate_run(scn, trace, "diskf-auto", 0, run_id=RUN, plan=SimPlan(Link(delay=0.002)))
    assert honest.status.status == "exact", honest.status.reason
    r = simulate_run(scn, trace, "diskf-auto", 0, run_id=RUN,
                     plan=SimPlan(Link(delay=0.002), wrap={agent_pid(3): lambda m: Tamper(m, edit)}))
    st = r.status
    assert st.status == "diverged", st.reason
    assert st.evidence["diverged"]["tick"] == 20 and st.evidence["diverged"]["senders"] == [3]
    moved = np.abs(r.record.x[20:, [0, 1, 3]] - honest.record.x[20:, [0, 1, 3]]).max()
    assert moved > 0  # the pooled probabilities did change the neighbours' estimates
    # the world named it as the run went and cut it off within two ticks
    assert [(q["agent"], q["tick"]) for q in r.record.quarantined] == [(3, 20)]
    assert 20 < r.record.quarantined[0]["from"] <= 22


# --------------------------------------------------------------------------
# an agent whose estimator diverges says so
# --------------------------------------------------------------------------
TINY_HG = {  # agent 1 measures x, where H G = -0.056: C-DRKF's unbiased input estimate blows up within ticks
    "name": "tiny-hg", "steps": K,
    "model": {"dynamics": "matrix", "A": [[0.76, -0.32], [-0.19, -0.33]], "G": [[-0.056], [0.75]],
              "Q": [[0.13, 0.0], [0.0, 0.13]], "x0": [-1.5, 0.0], "P0": [[1.0, 0.0], [0.0, 1.0]],
              "position_dims": [0, 1]},
    "topology": {"kind": "none"}, "input": {"kind": "constant", "value": [0.11]},
    "agents": [{"id": 1, "H": [[1.0, 0.0]], "R": [[0.2]], "sense": "always", "position": [0.0, 0.0]},
               {"id": 2, "H": [[0.0, 1.0]], "R": [[0.2]], "sense": "always", "position": [1.0, 0.0]}]}


def _tiny_hg_run(**plan):
    from diskf_mesh.data.scenario import parse_scenario

    scn = parse_scenario(TINY_HG)
    return simulate_run(scn, simulate(scn, [0]), "cdrkf", 0, run_id=RUN,
                        plan=SimPlan(Link(delay=0.002), **plan))


def test_an_agent_whose_estimator_diverges_says_so():
    """Agent 1's C-DRKF diverges (its estimate would be refused as a report):
    it reports nothing more and tells the world why before it goes, so each
    of its missing ticks says "diverged", not "left", and the run is
    incomplete with that reason; agent 2 reports every tick."""
    r = _tiny_hg_run()
    rec, st = r.record, r.status
    assert st.status == "incomplete" and "diverged" in st.reason, st.reason
    assert rec.reported[:, 1].all()
    missing = ~rec.reported[:, 0]
    stop = int(np.argmax(missing))  # the tick index agent 1 stopped at
    assert 5 <= stop < K - 5 and missing[stop:].all() and not missing[:stop].any()
    assert set(rec.why[missing, 0]) == {"diverged"}
    assert st.evidence["missing_why"] == {"diverged": int(missing.sum())}


def test_an_agents_stop_notice_names_only_what_it_may_say():
    """A stop notice whose reason is not one an agent may give ("diverged",
    "interrupted") changes nothing: the ticks say "left"."""
    def lie(e):
        if isinstance(e, ev.Publish) and e.key == KEYS.stopped(1):
            return dataclasses.replace(e, payload=wire.encode_stop(RUN, 1, "forged: the world is wrong"))
        return e

    r = _tiny_hg_run(wrap={agent_pid(1): lambda m: Tamper(m, lie)})
    missing = ~r.record.reported[:, 0]
    assert missing.any() and set(r.record.why[missing, 0]) == {"left"}, set(r.record.why[missing, 0])


def _replayer():
    """An edit: agent 3's message of tick 25 replaced by its message of tick 5 (off the guard's window)."""
    kept = {}

    def edit(e):
        if isinstance(e, ev.Publish) and KEYS.parse(e.key) == ("msg", 3):
            tick = wire.decode(e.payload, run_id=RUN, sender=3, exchanged=EXCHANGED).tick
            kept.setdefault(tick, e.payload)
            if tick == 25:
                return dataclasses.replace(e, payload=kept[5])
        return e
    return edit


@pytest.mark.parametrize("plan", ["replayed", "forger", "paused"])
def test_what_receivers_share_is_counted_by_each(quadrants, plan):
    """A payload decoded and checked once for all its receivers
    (``simulate_run(batch=True)``) is still counted by each receiver as it
    counts it alone: the same run event for event, every agent's counters
    and rejections by sender the same."""
    scn, trace = quadrants
    plans = {"replayed": SimPlan(Link(delay=0.002), wrap={agent_pid(3): lambda m: Tamper(m, _replayer())}),
             "forger": SimPlan(Link(delay=0.002), router=True, links=fast_intruder,
                               extra=(("intruder", "router", Forger, 0.0),)),
             "paused": SimPlan(Link(delay=0.002), agent_timing=AgentTiming(collect_timeout=2.0),
                               faults=(Fault("pause", agent_pid(2), at=10 * 3 * 0.002, duration=5.0),))}
    a, b = (simulate_run(scn, trace, "diskf", 0, run_id=RUN, plan=plans[plan], batch=batch) for batch in (True, False))
    assert a.outcome.digest == b.outcome.digest and a.outcome.events == b.outcome.events
    rejected = 0
    for i in range(1, 5):
        ma, mb = a.outcome.machines[agent_pid(i)], b.outcome.machines[agent_pid(i)]
        assert ma.counters == mb.counters
        assert ma.receiver.guard.by_sender == mb.receiver.guard.by_sender
        rejected += sum(ma.counters.rejected.values())
    assert a.status.status == b.status.status
    assert rejected > 0 or plan != "replayed"
