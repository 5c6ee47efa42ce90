"""The world's protocol machine with no transport and no clock: events in, effects out."""
from __future__ import annotations

import numpy as np
import pytest

from diskf_mesh.data.scenario import simulate
from diskf_mesh.mesh.wire import codec as wire
from diskf_mesh.mesh.protocol.clock import Clock
from diskf_mesh.mesh.protocol.estimator import neighbours
from diskf_mesh.mesh.protocol.events import (AskTokens, Answer, DeclareQueryable, DeclareToken, Finish, Interrupt, Publish,
                                    Query, Sample, SetTimer, Subscribe, Timer, Token, Tokens, WatchTokens, Woke)
from diskf_mesh.mesh.wire.keys import Keys
from diskf_mesh.mesh.process.runspec import RunSpec
from diskf_mesh.mesh.protocol.world_machine import (CLAIM, DUPLICATE, FAILED, PAUSE_MIN_S, WorldMachine, WorldTiming)

TICKS = 6
RUN = "wm"
NONCE = "0000000000000010aaaaaaaa"


@pytest.fixture(scope="module")
def run():
    spec = RunSpec("quadrants", "kcf", run_id=RUN, topology="ring")
    scn = spec.load(TICKS)
    return scn, simulate(scn, [0])


def machine(run, **timing) -> WorldMachine:
    scn, trace = run
    return WorldMachine(scn, trace, "kcf", 0, Keys(RUN), NONCE, WorldTiming(**{"startup_timeout": 30.0,
                                                                                 "tick_timeout": 10.0, **timing}))


def published(effects, key=None) -> list:
    return [e for e in effects if isinstance(e, Publish) and (key is None or e.key == key)]


def ticks_opened(effects) -> list:
    return [wire.decode_tick(e.payload).tick for e in published(effects, Keys(RUN).tick)]


def ready(w: WorldMachine, ids, now: float, nonce: str = "n1") -> list:
    keys, out = Keys(RUN), []
    for i in ids:
        out += w.handle(Token(keys.alive(i, nonce), True), now)
        out += w.handle(Token(keys.ready(i, nonce), True), now)
    return out


def gone(w: WorldMachine, i, now: float, nonce: str = "n1") -> list:
    keys = Keys(RUN)
    return w.handle(Token(keys.ready(i, nonce), False), now) + w.handle(Token(keys.alive(i, nonce), False), now)


def report(w: WorldMachine, i, k: int, now: float, x=None, P=None, fused=(), restart=None) -> list:
    n, m = w.trace.model.n, w.trace.model.m
    x = np.full(n, float(i)) if x is None else x
    P = np.eye(n) if P is None else P
    payload = wire.encode_report(RUN, i, k, x, P, np.zeros(m), False, fused=fused, restart=restart)
    return w.handle(Sample(Keys(RUN).report(i), payload), now)


def started(run, **timing) -> tuple:
    """A machine whose agents are all ready: (machine, effects of tick 1)."""
    w = machine(run, **timing)
    w.start(0.0)
    w.handle(Tokens(CLAIM, ()), 0.0)
    return w, ready(w, w.ids, 0.1)


def test_start_listens_and_claims(run):
    w = machine(run)
    out = w.start(0.0)
    keys = Keys(RUN)
    assert Subscribe(keys.report("*")) in out and DeclareQueryable(keys.start("*")) in out
    assert any(isinstance(e, WatchTokens) for e in out)
    assert out[-1] == AskTokens(CLAIM, keys.alive_world, 1.0)
    out = w.handle(Tokens(CLAIM, (keys.world(NONCE),)), 0.5)  # its own token only
    assert out == [DeclareToken(keys.world(NONCE)), SetTimer("startup", 30.5)]  # from the claim


def test_another_world_holds_the_run_id(run):
    w = machine(run)
    w.start(0.0)
    out = w.handle(Tokens(CLAIM, (Keys(RUN).world("0000000000000001bbbbbbbb"),)), 0.5)
    assert out[-1].code == DUPLICATE and not published(out)
    assert w.handle(Token(Keys(RUN).ready(1, "x"), True), 0.6) == []  # finished: nothing more


def test_every_ready_token_opens_tick_1(run):
    w, out = started(run)
    scn, trace = run
    keys = Keys(RUN)
    meas = [e for e in published(out) if e.key != keys.tick]
    assert [e.key for e in meas] == [keys.meas(i) for i in w.ids] and not any(e.express for e in meas)
    assert ticks_opened(out) == [1] and published(out)[-1].express
    t = wire.decode_tick(published(out)[-1].payload)
    assert t.live == w.ids and np.array_equal(t.positions, trace.positions[0])
    assert DeclareToken(keys.ticking) in out and SetTimer("tick", 10.1) in out
    for j, i in enumerate(w.ids):
        m = wire.decode_measurement(meas[j].payload)
        assert m.agent == i and m.has == bool(trace.has[0, 0, j])


def test_all_reports_of_tick_k_open_tick_k_plus_1(run):
    w, _ = started(run)
    for i in w.ids[:-1]:
        assert ticks_opened(report(w, i, 1, 0.2)) == []
    assert ticks_opened(report(w, w.ids[-1], 1, 0.3)) == [2]
    assert w.record.reported[0].all() and w.record.x[0, 0, 0] == w.ids[0]


def test_tick_timer_opens_next_tick_and_records_the_missing_one(run):
    w, _ = started(run)
    for i in w.ids[1:]:
        report(w, i, 1, 0.2)
    out = w.handle(Timer("tick"), 10.1)
    assert ticks_opened(out) == [2]
    assert not w.record.reported[0, 0] and w.record.why[0, 0] == "no report"
    assert w.record.counters["missing-report"] == 1
    assert report(w, w.ids[0], 1, 10.2) == [] and w.record.counters["stale"] == 1


def test_whole_run_stops_and_finishes_when_the_agents_leave(run):
    w, _ = started(run)
    for k in range(1, TICKS + 1):
        for i in w.ids:
            out = report(w, i, k, float(k))
    assert published(out, Keys(RUN).stop) and w.done and w.phase == "leaving"
    for i in w.ids[:-1]:
        assert not any(isinstance(e, Finish) for e in gone(w, i, 7.0))
    out = gone(w, w.ids[-1], 7.1)
    assert out[-1] == Finish("done", 0, "") and w.record.reported.all() and w.record.live.all()


def test_startup_timeout_names_the_missing_agents(run):
    w = machine(run)
    w.start(0.0)
    w.handle(Tokens(CLAIM, ()), 0.0)
    ready(w, w.ids[1:], 0.1)
    out = w.handle(Timer("startup"), 30.0)
    assert out[-1].code == FAILED and f"no agent process for id {w.ids[0]}" in out[-1].reason


def test_frozen_world_pauses_and_sends_the_open_tick_again(run):
    w, first = started(run)
    report(w, w.ids[0], 1, 0.2)
    out = w.handle(Woke(5.0), 5.3)
    assert w._paused and not published(out)
    assert w.handle(Timer("tick"), 5.4) == []  # a paused tick does not close
    out = w.handle(Timer("pause"), 5.3 + PAUSE_MIN_S)  # every agent still there: resume
    assert [e.key for e in published(out)] == [e.key for e in published(first)]
    assert w.record.pauses == [{"tick": 1, "why": "the world was frozen", "seconds": PAUSE_MIN_S}]
    assert ticks_opened(sum((report(w, i, 1, 6.5) for i in w.ids[1:]), [])) == [2]


def test_a_gone_agent_is_dropped_and_comes_back_two_ticks_later(run):
    w, _ = started(run)
    a = w.ids[0]
    gone(w, a, 0.15)
    out = sum((report(w, i, 1, 0.2) for i in w.ids[1:]), [])
    assert ticks_opened(out) == [2] and a not in wire.decode_tick(published(out, Keys(RUN).tick)[0].payload).live
    ready(w, [a], 0.25, nonce="n2")
    out = sum((report(w, i, 2, 0.3) for i in w.ids[1:]), [])
    assert a not in wire.decode_tick(published(out, Keys(RUN).tick)[0].payload).live  # tick 3: rejoining
    out = sum((report(w, i, 3, 0.4) for i in w.ids[1:]), [])
    assert a in wire.decode_tick(published(out, Keys(RUN).tick)[0].payload).live     # tick 4: live
    j = w.ids.index(a)
    assert list(w.record.why[:3, j]) == ["left", "left", "rejoining"] and not w.record.live[1:3, j].any()


def test_rejoin_query_is_answered_with_a_neighbours_reported_estimate(run):
    w, _ = started(run)
    scn, trace = run
    a = w.ids[0]
    near = set(neighbours(scn, a, trace.positions[0])) - {a}
    best = min(near)
    n = trace.model.n
    for i in w.ids:  # the lowest-id neighbour is the most certain
        report(w, i, 1, 0.2, P=np.eye(n) * (0.5 if i == best else 2.0))
    keys = Keys(RUN)
    assert w.handle(Query(7, keys.start(a), wire.encode_join(RUN, a, 3)), 0.3) == []  # tick 2 not over yet
    out = sum((report(w, i, 2, 0.4) for i in w.ids), [])
    answers = [e for e in out if isinstance(e, Answer)]
    assert len(answers) == 1 and answers[0].qid == 7
    s = wire.decode_start(answers[0].payload, run_id=RUN, agent=a, tick=3)
    assert s.source in near
    out = w.handle(Query(8, keys.start(a), wire.encode_join(RUN, a, 2)), 0.5)  # tick 1 is over: at once
    s = wire.decode_start(out[0].payload, run_id=RUN, agent=a, tick=2)
    assert s.source == best and np.array_equal(s.x, np.full(n, float(best)))
    assert np.array_equal(s.P, np.eye(n) * 0.5)
    assert w.record.starts[-1].source == best and a not in w.record.rejoins  # answered, not started yet
    report(w, a, 3, 0.6, restart=(2, best))   # a report says how its agent's estimate started
    assert w.record.rejoins[a] == [{"tick": 2, "source": best}]


def tick_of(effects) -> wire.Tick:
    tick, = [wire.decode_tick(e.payload) for e in published(effects, Keys(RUN).tick)]
    return tick


def test_every_tick_names_the_process_it_counts_as_each_agent(run):
    """Tick 1 counts the earliest started of two processes of one id (the
    agents' own rule); later the one it counted keeps the id while its token
    lasts, even against a process with a smaller nonce that appears late;
    once its token goes, the one left is counted."""
    w = machine(run)
    w.start(0.0)
    w.handle(Tokens(CLAIM, ()), 0.0)
    keys, a = Keys(RUN), w.ids[0]
    w.handle(Token(keys.alive(a, "n5"), True), 0.05)               # a second process of a, started later
    t = tick_of(ready(w, w.ids, 0.1))
    assert t.holder(a) == wire.holder_tag("n1") and t.holder(w.ids[1]) == wire.holder_tag("n1")
    assert len(t.holders) == wire.HOLDER_BYTES * len(t.live)
    w.handle(Token(keys.alive(a, "n0"), True), 0.2)                # a late one, with the smallest nonce
    t = tick_of(sum((report(w, i, 1, 0.3) for i in w.ids), []))
    assert t.tick == 2 and t.holder(a) == wire.holder_tag("n1")
    w.handle(Token(keys.alive(a, "n1"), False), 0.4)               # the counted one's token goes
    t = tick_of(sum((report(w, i, 2, 0.5) for i in w.ids), []))
    assert t.tick == 3 and t.holder(a) == wire.holder_tag("n0")


def test_rejoin_with_no_neighbour_reported_starts_from_the_prior(run):
    w, _ = started(run)
    a = w.ids[0]
    report(w, a, 1, 0.2)  # only itself reported tick 1
    w.handle(Timer("tick"), 10.1)
    out = w.handle(Query(1, Keys(RUN).start(a), wire.encode_join(RUN, a, 2)), 10.2)
    s = wire.decode_start(out[0].payload, run_id=RUN, agent=a, tick=2)
    model = w.trace.model
    assert s.source is None and np.array_equal(s.x, np.ravel(model.x0)) and np.array_equal(s.P, model.P0)


def test_interrupt_ends_the_run_early(run):
    w, _ = started(run)
    out = w.handle(Interrupt("SIGTERM"), 1.0)
    assert published(out, Keys(RUN).stop) and w.record.ended_early == "interrupted (SIGTERM)"
    out = w.handle(Timer("leave"), 3.0)
    assert out[-1] == Finish("stopped", 0, "interrupted (SIGTERM)") and not w.done


def test_real_time_opens_ticks_on_the_clock(run):
    w, out = started(run, clock=Clock(10.0, 0.05))
    assert ticks_opened(out) == [1] and SetTimer("clock", 0.1 + 0.1) in out
    out = w.handle(Timer("clock"), 0.2)
    assert ticks_opened(out) == [2]  # whatever came in
    assert w.record.deadlines.report_misses == {i: 1 for i in w.ids}
    report(w, w.ids[0], 1, 0.25)  # late, still taken
    assert w.record.reported[0, 0] and w.record.deadlines.late_reports[w.ids[0]] == 1


def test_real_time_an_agent_that_leaves_mid_tick_is_missing_as_left(run):
    """In real time, as in lockstep, an agent live at tick k whose token
    goes before its report is missing because it left (not "not run")."""
    w, _ = started(run, clock=Clock(10.0, 0.05))
    gone(w, w.ids[2], 0.15)
    w.handle(Timer("clock"), 0.2)  # tick 1 ends
    assert w.record.why[0, 2] == "left" and w.record.why[0, 0] == "no report"
    assert w.record.deadlines.report_misses[w.ids[2]] == 0


def test_real_time_start_waits_for_a_late_report_in_range(run):
    """Real time: tick 1 has ended but a neighbour in range still owes its
    report of it; the rejoin answer waits for that report (not the prior)."""
    scn, trace = run
    w, _ = started(run, clock=Clock(10.0, 0.05))
    a = w.ids[0]
    near = sorted(set(neighbours(scn, a, trace.positions[0])) - {a})
    for i in w.ids:
        if i not in near:
            report(w, i, 1, 0.15)
    w.handle(Timer("clock"), 0.2)  # tick 1 ends, tick 2 opens
    assert w.handle(Query(3, Keys(RUN).start(a), wire.encode_join(RUN, a, 2)), 0.21) == []
    assert len(near) == 2 and not any(isinstance(e, Answer) for e in report(w, near[1], 1, 0.22))
    out = report(w, near[0], 1, 0.23)  # the last late one in range: the answer comes with it
    s = wire.decode_start(next(e for e in out if isinstance(e, Answer)).payload, run_id=RUN, agent=a, tick=2)
    assert s.source == near[0]  # equally certain: the lower id


def test_every_agent_gone_pauses_and_ends_the_run_early(run):
    w, _ = started(run)
    for i in w.ids:
        gone(w, i, 0.2)
    out = w.handle(Timer("tick"), 10.1)  # tick 1 closes with no one: pause before tick 2
    assert w._paused == "every agent is gone" and not published(out)
    w.handle(Timer("pause"), 10.1 + PAUSE_MIN_S)
    out = w.handle(Timer("pause"), 40.1)  # startup_timeout later, still no one
    assert published(out, Keys(RUN).stop) and w.record.ended_early.startswith("no agent came back")
    assert out[-1] == Finish("stopped", 0, w.record.ended_early)  # no agent left to wait for


def test_allow_missing_starts_with_the_agents_that_are_ready(run):
    scn, trace = run
    w = WorldMachine(scn, trace, "kcf", 0, Keys(RUN), NONCE, WorldTiming(30.0, 10.0), allow_missing=True)
    w.start(0.0)
    w.handle(Tokens(CLAIM, ()), 0.0)
    keys = Keys(RUN)
    ready(w, w.ids[1:-1], 0.1)
    w.handle(Token(keys.alive(w.ids[-1], "n1"), True), 0.1)  # up, not ready yet
    out = w.handle(Timer("startup"), 30.0)
    assert DeclareToken(keys.ticking) in out and not ticks_opened(out)
    out = w.handle(Token(keys.ready(w.ids[-1], "n1"), True), 31.0)  # every agent up is ready: tick 1
    t = wire.decode_tick(published(out, keys.tick)[0].payload)
    assert t.tick == 1 and t.live == w.ids[1:] and w.record.why[0, 0] == "never joined"


def test_a_second_world_leaves_and_the_first_counts_it(run):
    keys = Keys(RUN)
    w, _ = started(run)
    assert w.handle(Token(keys.world("ffffffffffffffff00000000"), True), 1.0) == []
    assert w.record.duplicates["world"] == 1
    out = w.handle(Token(keys.world("0000000000000001cccccccc"), True), 1.1)  # an earlier one: this one leaves
    assert out[-1].code == DUPLICATE and not published(out)


def test_the_machine_reads_no_clock_and_touches_no_network():
    """Pure by construction: the module imports no clock, thread, socket,
    randomness or transport (the shell and the simulated network bring
    them)."""
    import ast
    from pathlib import Path

    import diskf_mesh.mesh.protocol.world_machine as wm

    tree = ast.parse(Path(wm.__file__).read_text())
    imported = {a.name.split(".")[0] for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names}
    imported |= {n.module for n in ast.walk(tree) if isinstance(n, ast.ImportFrom)}
    forbidden = {"time", "threading", "socket", "random", "secrets", "os", "zenoh", "asyncio",
                 "diskf_mesh.mesh.process.transport", "diskf_mesh.mesh.process.shell"}
    assert not imported & forbidden
    names = {n.attr for n in ast.walk(tree) if isinstance(n, ast.Attribute)}
    assert not names & {"new_nonce", "monotonic", "perf_counter", "time_ns"}


def test_same_events_same_effects(run):
    """Two machines fed the same events at the same times say the same."""
    def script(w):
        out = w.start(0.0) + w.handle(Tokens(CLAIM, ()), 0.0) + ready(w, w.ids, 0.1)
        for k in (1, 2):
            for i in w.ids[k - 1:]:
                out += report(w, i, k, 0.1 * k + 0.01 * i)
            out += w.handle(Timer("tick"), 10.0 * k + 0.2)
        return out + w.handle(Woke(3.0), 25.0) + w.handle(Timer("pause"), 26.0)

    assert script(machine(run)) == script(machine(run))


def test_a_flood_of_start_queries_keeps_one_owed_and_one_start_per_answer(run):
    w, _ = started(run)
    a, keys = w.ids[0], Keys(RUN)
    for qid in range(1, 1001):  # all for tick 3: tick 2 is not over yet
        assert w.handle(Query(qid, keys.start(a), wire.encode_join(RUN, a, 3)), 0.2) == []
    for k in (1, 2):
        out = sum((report(w, i, k, 0.3 + k) for i in w.ids), [])
    assert [e.qid for e in out if isinstance(e, Answer)] == [1000]  # the latest only
    for qid in range(1001, 1101):  # answered at once, kept once
        w.handle(Query(qid, keys.start(a), wire.encode_join(RUN, a, 3)), 3.0)
    assert len(w.record.starts) == 1 and w.record.starts[0].tick == 3


@pytest.mark.parametrize("sparse", [True, False])
def test_a_report_naming_an_agent_not_in_the_run_is_recorded_without_it(sparse):
    """A report's fused list with an id the run does not have: the record
    holds the known senders, each with its own digest, and nothing of the
    unknown one."""
    from diskf_mesh.mesh.protocol.reports import RunReports

    rec = RunReports(**RunReports.empty(2, 3, 4, 2, sparse=sparse))
    index = {10: 0, 11: 1, 12: 2}
    rec.note_fused(1, 0, (11, 99, 12), ((98, "late"), (12, "stale")), (b"a" * 8, b"b" * 8, b"c" * 8), index)
    assert np.asarray(rec.fused[0])[0].tolist() == [False, True, True]
    senders, digests = rec.claimed_digests()[(1, 0)]
    assert senders.tolist() == [1, 2]
    assert digests.tolist() == wire_values([b"a" * 8, b"c" * 8])
    assert rec.verdicts[(1, 0)] == ((2, "stale"),)


def wire_values(gs):
    return [int.from_bytes(g, "little") for g in gs]
