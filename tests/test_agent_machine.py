"""The agent's protocol machine (``mesh.protocol.agent_machine``) without any transport:
events in, effects out, a virtual clock."""
from __future__ import annotations

import numpy as np
import pytest

from diskf_mesh import estimators
from diskf_mesh.data.faults import FaultConfig
from diskf_mesh.data.scenario import load_scenario, simulate
from diskf_mesh.engine import batch as engine
from diskf_mesh.mesh.wire import codec as wire
from diskf_mesh.mesh.protocol.agent_machine import ASK_S, DUPLICATE_SAY_S, AgentMachine, AgentTiming
from diskf_mesh.mesh.protocol.estimator import AgentEstimator, lockstep, neighbours
from diskf_mesh.mesh.protocol.events import (at_once, Ask, AskTokens, DeclareToken, DropToken, Finish, MeasurementArrived,
                                             MessageArrived, Publish, Reply, Sample, SetTimer, StopArrived, Subscribe,
                                             TickArrived, Timer, Token, Tokens, Unreadable, WatchTokens, Woke)
from diskf_mesh.mesh.wire.keys import Keys
from diskf_mesh.mesh.wire.keys import key_matches

RUN = "m"
DISKF = estimators.get("diskf")
K = 12
SEED = 3


@pytest.fixture(scope="module")
def run():
    scn = load_scenario("dynamic").with_overrides(steps=K)
    trace = simulate(scn, [SEED])
    return scn, trace, engine.run(trace, "diskf", scn.params)


def of(effects, kind):
    return [e for e in effects if isinstance(e, kind)]


def hand(m, event, now):
    """``event`` into ``m`` as a shell hands it: a sample read first (``AgentMachine.read``)."""
    return at_once(m, m.read(event.key, event.payload) if isinstance(event, Sample) else event, now)


class World:
    """The world's side of a run, by hand: the samples it sends and the
    tokens every process holds."""

    def __init__(self, scn, trace):
        self.scn, self.trace, self.keys = scn, trace, Keys(RUN)
        self.ids = [a.id for a in scn.agents]

    def tick(self, k, live=None, holders=None):
        """Tick k; ``holders``: {id: nonce} of the processes it counts (others: "n<id>")."""
        live = tuple(self.ids if live is None else live)
        tags = b"" if holders is None else b"".join(wire.holder_tag(holders.get(i, f"n{i}")) for i in live)
        return Sample(self.keys.tick, wire.encode_tick(wire.Tick(
            RUN, k, K, SEED, "diskf", self.scn.topology, self.scn.comm_range, self.trace.positions[k - 1],
            live, tags)))

    def meas(self, k, i):
        j = self.ids.index(i)
        p = int(self.scn.sensors().p[j])
        has = bool(self.trace.has[0, k - 1, j])
        return Sample(self.keys.meas(i), wire.encode_measurement(RUN, k, i, has, self.trace.y[0, k - 1, j, :p]))

    def stop(self, k=K, why="done"):
        return Sample(self.keys.stop, wire.encode_stop(RUN, k, why))

    def tokens(self, ticking=False):
        out = [Token(self.keys.world("w0"), True)] + [Token(self.keys.alive(i, f"n{i}"), True) for i in self.ids]
        return out + ([Token(self.keys.ticking, True)] if ticking else [])


def started(scn, i, now=0.0, ticking=False, timing=AgentTiming(), faults=None):
    """Agent ``i``'s machine through its start-up: subscribed, id claimed,
    alive and ready tokens declared; returns (machine, effects so far)."""
    w = World(scn, None)
    m = AgentMachine(scn, i, DISKF, Keys(RUN), f"n{i}", timing, faults)
    out = m.start(now)
    assert {e.key for e in of(out, Subscribe)} == {m.keys.tick, m.keys.meas(i), m.keys.stop, m.keys.msg_to(i)}
    assert of(out, WatchTokens)
    for tok in w.tokens(ticking):
        if tok.key != m.keys.alive(i, f"n{i}"):
            out += hand(m, tok, now)
    ask, = of(out, AskTokens)
    assert ask.key == m.keys.alive(i)
    out += hand(m, Tokens(ask.qid, ()), now)
    assert DeclareToken(m.keys.alive(i, f"n{i}")) in out
    out += hand(m, Token(m.keys.alive(i, f"n{i}"), True), now)
    return m, out


def collecting_tick_1(run, now=0.0, **kw):
    """Agent 5 (Scenario 2's fifth) started and collecting tick 1, opened at
    ``now``: (machine, world, its id, its ready token's key)."""
    scn, trace, _ = run
    w = World(scn, trace)
    me = w.ids[4]
    m, out = started(scn, me, **kw)
    hand(m, w.meas(1, me), now)
    hand(m, w.tick(1), now)
    return m, w, me, of(out, DeclareToken)[-1].key


def test_one_tick_publishes_one_message_then_one_report_equal_to_the_engine(run):
    scn, trace, ref = run
    w = World(scn, trace)
    ids = w.ids
    me = ids[4]
    m, out = started(scn, me)
    assert of(out, DeclareToken)[-1].key.startswith(m.keys.ready(me, ""))
    msgs = {k: mm for k, mm, _ in lockstep(scn, "diskf", trace, SEED)}
    out = hand(m, w.meas(1, me), 0.1)
    assert of(out, Publish) == []                        # the tick is not in yet
    out = hand(m, w.tick(1), 0.2)
    pub, = of(out, Publish)                              # exactly one message, to the agents in range
    linked = set(neighbours(scn, me, trace.positions[0])) - {me}
    assert pub.key == m.keys.msg(me, to=linked)
    assert pub.payload == wire.encode(RUN, me, 1, msgs[1][me])
    assert SetTimer("collect", 0.2 + m.timing.collect_timeout) in out
    reports = []
    for j in sorted(linked):
        out = hand(m, Sample(m.keys.msg(j, to=[me]), wire.encode(RUN, j, 1, msgs[1][j])), 0.3)
        reports += [e for e in of(out, Publish) if e.key == m.keys.report(me)]
    r = wire.decode_report(reports[0].payload, run_id=RUN, sender=me)
    assert len(reports) == 1 and r.tick == 1 and r.fused == tuple(sorted(linked)) and r.not_fused == ()
    i = ids.index(me)
    assert r.x.tobytes() == ref.x[0, 0, i].tobytes() and r.P.tobytes() == ref.P[0, 0, i].tobytes()


def test_a_sample_is_read_at_the_edge_into_the_typed_event_the_machine_handles(run):
    """``read`` decodes each sample once (the world's tick, measurement and
    stop; a neighbour's message with the checks of its own values); a
    world's payload that does not decode is ``Unreadable`` and counted as
    refused once handled; ``handle`` takes typed events made by hand, with
    no bytes: the measurement and tick open tick 1."""
    scn, trace, _ = run
    w = World(scn, trace)
    me, j = w.ids[4], w.ids[0]
    m, _ = started(scn, me)
    msgs = {k: mm for k, mm, _ in lockstep(scn, "diskf", trace, SEED)}
    read = lambda sample: m.read(sample.key, sample.payload)  # noqa: E731
    tick, meas, stop = read(w.tick(1)), read(w.meas(1, me)), read(w.stop())
    assert type(tick) is TickArrived and tick.tick.tick == 1 and tick.tick.live == tuple(w.ids)
    assert type(meas) is MeasurementArrived and meas.measurement.tick == 1
    assert type(stop) is StopArrived and stop.stop.why == "done"
    msg = m.read(m.keys.msg(j, to=[me]), wire.encode(RUN, j, 1, msgs[1][j]))
    assert type(msg) is MessageArrived and msg.sender == j and msg.message.tick == 1 and msg.problem is None
    bad = m.read(m.keys.tick, b"\xc1")
    assert type(bad) is Unreadable and bad.kind == "tick" and m.counters.rejected == {}
    assert at_once(m, bad, 0.0) == [] and m.counters.rejected == {bad.reason: 1}
    assert at_once(m, MeasurementArrived(meas.measurement), 0.1) == []
    pub, = of(at_once(m, TickArrived(tick.tick), 0.2), Publish)
    assert pub.payload == wire.encode(RUN, me, 1, msgs[1][me])


def test_the_collect_timer_closes_the_tick_with_what_came(run):
    scn, trace, _ = run
    w = World(scn, trace)
    me = w.ids[4]
    m, _ = started(scn, me)
    msgs = {k: mm for k, mm, _ in lockstep(scn, "diskf", trace, SEED)}
    hand(m, w.meas(1, me), 1.0)
    hand(m, w.tick(1), 1.0)
    linked = sorted(set(neighbours(scn, me, trace.positions[0])) - {me})
    assert len(linked) >= 2
    out = hand(m, Sample(m.keys.msg(linked[0], to=[me]), wire.encode(RUN, linked[0], 1, msgs[1][linked[0]])), 1.5)
    assert of(out, Publish) == []
    out = hand(m, Timer("collect"), 1.0 + m.timing.collect_timeout)
    rep, = of(out, Publish)
    r = wire.decode_report(rep.payload, run_id=RUN, sender=me)
    assert r.fused == (linked[0],) and r.not_fused == tuple((j, "late") for j in linked[1:])
    assert m.k == 2 and not m.collecting


def test_a_whole_run_of_machines_equals_the_engine_bit_for_bit(run, monkeypatch):
    """Every agent a machine, messages routed by key, the world by hand:
    every report is the engine's, and the world's stop ends each with 0.
    No machine reads a clock: its time is the ``now`` it is handed."""
    import threading
    import time

    def no_clock(*a):
        raise AssertionError("a protocol machine read the clock")

    for name in ("monotonic", "time", "time_ns", "perf_counter", "sleep"):
        monkeypatch.setattr(time, name, no_clock)
    monkeypatch.setattr(threading, "Thread", no_clock)
    scn, trace, ref = run
    w = World(scn, trace)
    machines = {i: started(scn, i)[0] for i in w.ids}
    now = 0.0
    got = {}
    for k in range(1, K + 1):
        queue = []
        for i, m in machines.items():
            queue += hand(m, w.meas(k, i), now)
        for i, m in machines.items():
            queue += hand(m, w.tick(k), now)
        while queue:
            e = queue.pop(0)
            assert isinstance(e, (Publish, SetTimer)), e
            if not isinstance(e, Publish):
                continue
            kind, sender = m.keys.parse(e.key)
            if kind == "report":
                got[(k, sender)] = wire.decode_report(e.payload, run_id=RUN, sender=sender)
                continue
            for i, m2 in machines.items():
                if key_matches(m2.keys.msg_to(i), e.key):
                    queue += hand(m2, Sample(e.key, e.payload), now)
        now += 0.01
    for j, i in enumerate(w.ids):
        for k in range(1, K + 1):
            r = got[(k, i)]
            assert r.x.tobytes() == ref.x[0, k - 1, j].tobytes() and r.P.tobytes() == ref.P[0, k - 1, j].tobytes()
    for m in machines.values():
        fin, = hand(m, w.stop(), now)
        assert fin == Finish("done", 0, "")


def test_delayed_copies_are_timers_of_the_machine(run):
    """A link latency: each neighbour's copy waits for the machine's delay
    timer; nothing arrives before it fires."""
    scn, trace, _ = run
    w = World(scn, trace)
    me = w.ids[4]
    m, _ = started(scn, me, faults=FaultConfig(latency_ms=100))
    msgs = {k: mm for k, mm, _ in lockstep(scn, "diskf", trace, SEED)}
    hand(m, w.meas(1, me), 0.0)
    hand(m, w.tick(1), 0.0)
    linked = sorted(set(neighbours(scn, me, trace.positions[0])) - {me})
    timers = []
    for j in linked:
        out = hand(m, Sample(m.keys.msg(j, to=[me]), wire.encode(RUN, j, 1, msgs[1][j])), 0.0)
        assert of(out, Publish) == []
        timers += [e for e in of(out, SetTimer) if e.name == "delay"]
    assert timers == [SetTimer("delay", 0.1)]
    out = hand(m, Timer("delay"), 0.1)
    rep, = of(out, Publish)
    assert wire.decode_report(rep.payload, run_id=RUN, sender=me).fused == tuple(linked)


def test_a_rejoining_agent_asks_the_world_and_starts_from_its_answer(run):
    scn, trace, _ = run
    w = World(scn, trace)
    me = w.ids[4]
    J = 6
    m, out = started(scn, me, ticking=True)             # a restart: the world ticks already
    assert m.rejoining and of(out, DeclareToken)[-1].key.startswith(m.keys.ready(me, ""))
    others = [i for i in w.ids if i != me]
    assert of(hand(m, w.tick(J - 1, live=others), 0.0), Ask) == []   # the world is at J - 1 without it
    hand(m, w.meas(J, me), 10.0)
    out = hand(m, w.tick(J), 10.0)
    ask, = of(out, Ask)
    assert ask.key == m.keys.start(me) and wire.decode_join(ask.payload, sender=me).tick == J
    confirm, = of(out, AskTokens)                       # and once more: does another process hold the id?
    assert confirm.key == m.keys.alive(me)
    assert of(out, Publish) == []                       # no message before both are in
    assert of(hand(m, Tokens(confirm.qid, (m.keys.alive(me, "n5"),)), 10.05), Publish) == []
    x, P = np.array([3.0, -1.0]), np.diag([0.5, 0.25])
    out = hand(m, Reply(ask.qid, wire.encode_start(RUN, me, J, 7, x, P, np.zeros(1), False)), 10.1)
    assert m.rejoins == [(J, 7)]
    msg, = of(out, Publish)                             # then its one message of tick J, nothing else
    est = AgentEstimator(scn, me, DISKF, K, SEED, start=(x, P))  # ... from the answered estimate, bit for bit
    j = w.ids.index(me)
    own = est.local(J, bool(trace.has[0, J - 1, j]), trace.y[0, J - 1, j, :est.p])
    assert msg.payload == wire.encode(RUN, me, J, own)
    assert m.est is not None and m.k == J and m.collecting
    for k in (J, J + 1):  # every report from now on tells the world how this estimate started
        now = 10.0 + 10 * (k - J + 1)
        rep, = [e for e in of(hand(m, Timer("collect"), now), Publish) if m.keys.parse(e.key)[0] == "report"]
        assert wire.decode_report(rep.payload, run_id=RUN, sender=me).restart == (J, 7)
        hand(m, w.meas(k + 1, me), now)
        hand(m, w.tick(k + 1), now)


def asking(run, J=4, now=10.0):
    """A restarted agent at tick J of the world, its id confirmed, waiting
    for the world's answer: (machine, the start query, the effects of
    tick J)."""
    scn, trace, _ = run
    w = World(scn, trace)
    me = w.ids[4]
    m, _ = started(scn, me, ticking=True)
    hand(m, w.tick(J - 1, live=[i for i in w.ids if i != me]), 0.0)
    hand(m, w.meas(J, me), now)
    out = hand(m, w.tick(J), now)
    hand(m, Tokens(of(out, AskTokens)[0].qid, ()), now)
    return m, of(out, Ask)[0], out


def test_an_answer_that_fails_the_guard_leaves_the_prior(run):
    m, ask, _ = asking(run)
    bad = wire.encode_start(RUN, m.id, 4, 2, np.array([1.0, 0.0]), np.diag([1e-8, 1e8]), np.zeros(1), False)
    hand(m, Reply(ask.qid, bad), 10.1)
    assert m.rejoins == [(4, None)] and m.counters.rejected == {"ill-conditioned": 1}


def test_no_answer_is_asked_again_and_the_worlds_answer_decides_the_start(run):
    """No answer (the query ended empty, then its time ran out: the world
    frozen or out of reach) is not the prior: the agent asks again every
    ASK_S and works on nothing meanwhile; the answer that comes starts it
    (simulated-network sweep seed 15913: the world paused 10.3 s while agent
    6 asked, and agent 6 started from the prior though four agents in range
    had reported the tick before)."""
    m, ask, out = asking(run)
    assert SetTimer("ask", 10.0 + ASK_S) in out
    assert hand(m, Reply(ask.qid, None), 10.2) == []   # ended without an answer: wait for the timer
    out = hand(m, Timer("ask"), 10.0 + ASK_S)
    again, = of(out, Ask)
    assert again.qid != ask.qid and again.payload == ask.payload and SetTimer("ask", 10.0 + 2 * ASK_S) in out
    assert of(out, Publish) == [] and m.rejoins == [] and m.est is None
    x, P = np.array([3.0, -1.0]), np.diag([0.5, 0.25])
    late = wire.encode_start(RUN, m.id, 4, 2, x, P, np.zeros(1), False)
    assert of(hand(m, Reply(ask.qid, late), 15.1), Publish) == []  # an answer to the first query: too late
    out = hand(m, Reply(again.qid, late), 15.2)
    assert m.rejoins == [(4, 2)] and len([e for e in of(out, Publish) if "/msg/" in e.key]) == 1


def test_a_late_joiner_that_finds_its_id_held_just_before_joining_leaves(run):
    """A second process of an id, started while the run goes, whose claim
    did not see the first (its session had not heard every token yet): the
    world counts the id live (the first process), so this one would join;
    its second query before the first tick finds the first: it tells the
    world (the duplicate notice, nothing else) and leaves with exit 2."""
    scn, trace, _ = run
    w = World(scn, trace)
    me = w.ids[4]
    m, out = started(scn, me, ticking=True)
    hand(m, w.meas(6, me), 1.0)
    out = hand(m, w.tick(6), 1.0)
    confirm, = of(out, AskTokens)
    ask, = of(out, Ask)
    out = hand(m, Reply(ask.qid, wire.encode_start(RUN, me, 6, None, np.zeros(2), np.eye(2), np.zeros(1), False)),
                   1.1)
    assert of(out, Publish) == []
    out = hand(m, Tokens(confirm.qid, (m.keys.alive(me, "n0"), m.keys.alive(me, "n5"))), 2.0)
    assert out == [Publish(m.keys.duplicate(me), b"n5"), SetTimer("leave", 2.0 + DUPLICATE_SAY_S)]
    assert hand(m, w.tick(7), 2.1) == []  # leaving: it works on nothing
    fin, = hand(m, Timer("leave"), 2.0 + DUPLICATE_SAY_S)
    assert fin.code == 2 and "n0" in fin.reason and m.est is None


def test_a_process_the_world_does_not_count_as_its_id_leaves_before_working(run):
    """Every tick names the process the world counts as each live id. A
    second process of an id whose own session never heard the first (its
    id-confirming queries found none) leaves (exit 2) at the first tick that
    names the other, before its message, its start query or any estimate;
    the process the tick names works."""
    scn, trace, _ = run
    w = World(scn, trace)
    me = w.ids[4]
    for ticking in (False, True):  # at tick 1 (both started at once) and joining a run in progress
        m, out = started(scn, me, ticking=ticking)
        k = 6 if ticking else 1
        hand(m, w.meas(k, me), 1.0)
        out = hand(m, w.tick(k, holders={me: "n0"}), 1.0)
        assert out == [Publish(m.keys.duplicate(me), b"n5"), SetTimer("leave", 1.0 + DUPLICATE_SAY_S)]
        fin, = hand(m, Timer("leave"), 1.0 + DUPLICATE_SAY_S)
        assert isinstance(fin, Finish) and fin.code == 2 and wire.holder_tag("n0").hex() in fin.reason
        assert m.est is None and m.rejoins == []
    m, _ = started(scn, me)
    hand(m, w.meas(1, me), 1.0)
    out = hand(m, w.tick(1, holders={}), 1.0)  # it is the one counted
    assert [e for e in of(out, Publish) if "/msg/" in e.key] and m.est is not None


def test_a_process_that_sees_its_id_held_before_its_claim_is_answered_tells_the_world(run):
    """A second process of an id started while the run goes: the world's
    tick, naming the first process, comes before its claim's answer. It
    declares nothing, publishes the duplicate notice (the world counts it:
    it never saw a token of this one) and leaves with exit 2."""
    scn, trace, _ = run
    w = World(scn, trace)
    me = w.ids[2]
    m = AgentMachine(scn, me, DISKF, Keys(RUN), "n9")
    m.start(0.0)
    claim, = of(hand(m, Token(m.keys.world("w0"), True), 0.0), AskTokens)
    out = hand(m, w.tick(6, holders={}), 0.1)  # it names process "n3" as agent 3
    assert out == [Publish(m.keys.duplicate(me), b"n9"), SetTimer("leave", 0.1 + DUPLICATE_SAY_S)]
    assert hand(m, Tokens(claim.qid, ()), 0.2) == []  # leaving: no token declared
    fin, = hand(m, Timer("leave"), 0.1 + DUPLICATE_SAY_S)
    assert fin.code == 2 and m.est is None


def test_another_process_with_this_id_makes_this_one_leave_with_2(run):
    scn, _, _ = run
    me = 1
    m = AgentMachine(scn, me, DISKF, Keys(RUN), "n2")
    m.start(0.0)
    ask, = of(hand(m, Token(m.keys.world("w0"), True), 0.0), AskTokens)
    out = hand(m, Tokens(ask.qid, (m.keys.alive(me, "n1"),)), 0.5)
    assert Publish(m.keys.duplicate(me), b"n2") in out and not of(out, DeclareToken)
    fin, = hand(m, Timer("leave"), 0.7)
    assert fin.code == 2 and hand(m, Timer("world"), 100.0) == []


def test_a_silent_world_ends_the_agent_at_its_timeout(run):
    scn, _, _ = run
    m = AgentMachine(scn, 1, DISKF, Keys(RUN), "n1", AgentTiming(world_timeout=30.0))
    out = m.start(5.0)
    assert SetTimer("world", 35.0) in out
    fin, = hand(m, Timer("world"), 35.0)
    assert fin.code == 1 and "no word from the world for 30 s" in fin.reason


def test_frozen_past_the_lease_it_rejoins(run):
    """Woke (the shell found it had been paused), then the world's token
    goes: this agent was dropped, it withdraws its ready token and rejoins."""
    m, w, me, ready = collecting_tick_1(run)
    hand(m, Timer("collect"), 5.0)
    assert m.est is not None and m.k == 2
    hand(m, Woke(8.0), 20.0)
    out = hand(m, Token(m.keys.world("w0"), False), 20.5)
    assert m.est is None and m.rejoining
    assert out == [DropToken(ready), DeclareToken(m.keys.ready(me, "n5.2"))]


def test_a_restart_cut_off_from_the_world_asks_for_its_start_once_the_world_is_back(run):
    """Woken past the lease, its session gone: the world's token went. Its
    start is asked for only once the token is back (an answer the world
    can give: a neighbour's estimate), and "no answer" while cut off is
    asked again, never taken as the prior."""
    J = 4
    scn, trace, _ = run
    w = World(scn, trace)
    me = w.ids[4]
    m, _ = started(scn, me, ticking=True)
    hand(m, w.tick(J - 1, live=[i for i in w.ids if i != me]), 0.0)
    hand(m, Token(m.keys.world("w0"), False), 9.0)         # its session went down
    hand(m, w.meas(J, me), 10.0)
    out = hand(m, w.tick(J), 10.0)
    assert of(out, Ask) == [] and m.est is None               # no question while cut off
    out = hand(m, Token(m.keys.world("w0"), True), 10.2)     # back
    ask, = of(out, Ask)
    hand(m, Tokens(of(out, AskTokens)[0].qid, ()), 10.2)
    hand(m, Token(m.keys.world("w0"), False), 10.3)          # cut off again before the answer
    assert hand(m, Reply(ask.qid, None), 10.4) == [] and m.est is None and m.rejoins == []
    again, = of(hand(m, Token(m.keys.world("w0"), True), 11.0), Ask)
    x, P = np.array([3.0, -1.0]), np.diag([0.5, 0.25])
    hand(m, Reply(again.qid, wire.encode_start(RUN, me, J, 7, x, P, np.zeros(1), False)), 11.1)
    assert m.rejoins == [(J, 7)] and m.est is not None


def test_the_world_going_without_a_freeze_is_waited_for(run):
    m, *_ = collecting_tick_1(run)
    hand(m, Timer("collect"), 5.0)
    assert hand(m, Token(m.keys.world("w0"), False), 20.5) == [] and m.est is not None
    fin, = hand(m, Timer("world"), 5.0 + 60.0)
    assert fin.code == 1 and "the world is gone" in fin.reason


def test_a_timer_fired_before_its_time_changes_nothing(run):
    """A shell (or the simulated network) may fire a timer the machine has
    since set again for later: the machine looks at the time itself."""
    m, *_ = collecting_tick_1(run, 1.0)
    for name in ("collect", "world", "delay", "peers", "ask", "nothing"):
        out = hand(m, Timer(name), 2.0)
        assert all(isinstance(e, SetTimer) and e.at > 2.0 for e in out) and m.collecting   # at most set again
    m2, _, _ = asking(run)
    assert hand(m2, Timer("ask"), 11.0) == [] and m2.est is None


def test_real_time_closes_at_the_deadline_from_when_the_tick_came(run):
    """With a clock (``mesh.protocol.clock``) the collection of tick k ends
    ``deadline_s`` after tick k reached the agent; a copy after that is late,
    never fused. An agent that gets to a tick after its deadline (it fell
    behind) closes it at once."""
    from diskf_mesh.mesh.protocol.clock import Clock
    scn, trace, _ = run
    w = World(scn, trace)
    me = w.ids[4]
    m, _ = started(scn, me, timing=AgentTiming(clock=Clock(10.0, 0.05)))
    msgs = {k: mm for k, mm, _ in lockstep(scn, "diskf", trace, SEED)}
    linked = sorted(set(neighbours(scn, me, trace.positions[0])) - {me})
    hand(m, w.meas(1, me), 1.0)
    out = hand(m, w.tick(1), 1.0)
    assert SetTimer("collect", 1.05) in out
    hand(m, Sample(m.keys.msg(linked[0], to=[me]), wire.encode(RUN, linked[0], 1, msgs[1][linked[0]])), 1.02)
    rep, = of(hand(m, Timer("collect"), 1.05), Publish)
    r = wire.decode_report(rep.payload, run_id=RUN, sender=me)
    assert r.fused == (linked[0],) and dict(r.not_fused) == {j: "late" for j in linked[1:]}
    hand(m, Sample(m.keys.msg(linked[1], to=[me]), wire.encode(RUN, linked[1], 1, msgs[1][linked[1]])), 1.06)
    assert m.counters.late == 1 and m.counters.fused == 1
    hand(m, w.tick(2), 1.1)                            # tick 2 came at 1.1, its measurement only at 1.3:
    out = hand(m, w.meas(2, me), 1.3)                  # past its deadline (1.15), opened and closed at once
    assert [m.keys.parse(e.key)[0] for e in of(out, Publish)] == ["msg", "report"]
    assert not of(out, SetTimer) and m.k == 3
