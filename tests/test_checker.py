"""The world's check as the run goes, answered late or in a thread of its
own (``mesh.process.checker.CheckThread``): the same findings, the liar cut
off from the same tick, a failure of the check raised in the world."""
from __future__ import annotations

import copy
import time
from types import SimpleNamespace

import numpy as np
import pytest

from diskf_mesh import estimators
from diskf_mesh.mesh.process.checker import CheckFailed, CheckThread
from diskf_mesh.mesh.process import checker
from diskf_mesh.mesh.protocol import events, run_status, world_machine
from diskf_mesh.mesh.protocol.reports import RunReports
from diskf_mesh.mesh.wire import codec as wire
from diskf_mesh.mesh.simulated import simrun
from test_simnet_liars import FROM, LIAR, OFFSET, RUN, dynamic, run  # noqa: F401 - the fixture

assert dynamic


class LateCheck(run_status.OnlineCheck):
    """An ``OnlineCheck`` whose finding is only there when the world waits
    for it (as a check in a thread of its own still busy)."""

    asked_early = 0

    def result(self, rec, k, wait=True):
        if not wait:
            LateCheck.asked_early += 1
            return None
        return super().result(rec, k, wait)


def test_a_check_answered_only_when_waited_for_cuts_the_liar_off_from_the_same_tick(dynamic, monkeypatch):
    at_once = run(dynamic, start=FROM, offset=OFFSET)
    monkeypatch.setattr(simrun, "OnlineCheck", LateCheck)
    late = run(dynamic, start=FROM, offset=OFFSET)
    assert LateCheck.asked_early > 0  # the ticks went on without its finding
    assert late.record.quarantined == at_once.record.quarantined and len(late.record.quarantined) == 1
    assert late.record.quarantined[0]["tick"] == FROM
    for a, b in ((late.record.live, at_once.record.live), (late.record.x, at_once.record.x),
                 (late.record.fused, at_once.record.fused)):
        np.testing.assert_array_equal(a, b)
    assert late.status.to_json() == at_once.status.to_json()



class HandedOverCheck(LateCheck):
    """A ``LateCheck`` the world hands ticks over to (as ``CheckThread``):
    each final tick comes with ``HandOver``, with no timer."""

    handed_over = True
    submitted = []  # (tick, every live agent's report of it in, tick + 1 opened yet, a report of tick + 1 in yet)

    def submit(self, rec, k):
        after = k < len(rec.live)
        HandedOverCheck.submitted.append((k, bool(rec.reported[k - 1][rec.live[k - 1]].all()),
                                         after and bool(rec.live[k].any()), after and bool(rec.reported[k].any())))


def test_a_check_that_takes_ticks_is_handed_each_final_tick_after_the_next_ticks_puts_and_cuts_the_liar_off_from_the_same_tick(
        dynamic, monkeypatch):
    at_once = run(dynamic, start=FROM, offset=OFFSET)
    monkeypatch.setattr(simrun, "OnlineCheck", HandedOverCheck)
    monkeypatch.setattr(HandedOverCheck, "submitted", [])
    monkeypatch.setattr(LateCheck, "asked_early", 0)
    effects = []  # the kinds of each event's effects that hand a tick over, in order
    handle = world_machine.WorldMachine.handle

    def watched(self, event, now):
        out = handle(self, event, now)
        if any(isinstance(e, events.HandOver) for e in out):
            effects.append([type(e).__name__ for e in out])
        return out

    monkeypatch.setattr(world_machine.WorldMachine, "handle", watched)
    late = run(dynamic, start=FROM, offset=OFFSET)
    first = {}
    for k, whole, next_open, next_reported in HandedOverCheck.submitted:
        first.setdefault(k, (whole, next_open, next_reported))
    K = late.record.reported.shape[0]
    assert list(first) == list(range(1, K + 1))
    assert all(whole for whole, _, _ in first.values())  # handed over once its reports are final ...
    # ... in the event that made them so, after the next tick opened and before any of its reports came
    assert all(next_open and not next_reported for k, (_, next_open, next_reported) in first.items() if k < K)
    assert len(effects) >= K - 1
    for kinds in effects:  # the last effects of their event: the next tick's puts go out first
        assert "Publish" in kinds and kinds.index("HandOver") > max(i for i, e in enumerate(kinds) if e == "Publish")
    assert LateCheck.asked_early == 0  # no timer asks before the world must know
    assert late.record.quarantined == at_once.record.quarantined and len(late.record.quarantined) == 1
    for a, b in ((late.record.live, at_once.record.live), (late.record.x, at_once.record.x),
                 (late.record.fused, at_once.record.fused)):
        np.testing.assert_array_equal(a, b)
    assert late.status.to_json() == at_once.status.to_json()

def test_the_check_in_its_own_thread_finds_what_the_check_on_the_worlds_timer_finds(dynamic):
    scn, trace = dynamic
    rec = run(dynamic, online=False, start=FROM, offset=OFFSET).record  # the liar never cut off: it lies on
    make = lambda: run_status.OnlineCheck(trace, estimators.get("diskf"), scn.params, run_id=RUN, seed=0)  # noqa: E731
    here, there = make(), CheckThread(make)
    try:
        found = []
        for k in range(1, rec.reported.shape[0] + 1):
            there.submit(rec, k)
            found.append(there.result(rec, k))
            assert found[-1] == here.tick(rec, k), k
        assert [q["tick"] for f in found for q in f][0] == FROM and {q["agent"] for f in found for q in f} == {LIAR}
        assert there.kept(trace, "diskf", scn.params, RUN) is None  # its thread still runs: its ticks may change
    finally:
        there.close()
    # the thread ended: the end of the run takes its replay, the status a replay of the whole run gives
    kept = there.kept(trace, "diskf", scn.params, RUN)
    assert kept is not None and kept.step is None and len(kept.kept) == rec.reported.shape[0]
    assert there.kept(trace, "diskf", scn.params, "another run") is None
    st, again = (run_status.run_status(rec, trace, "diskf", scn.params, run_id=RUN, seed=0, online=o)
                 for o in (there, None))
    assert st.evidence.pop("replayed_online") and not again.evidence.pop("replayed_online")
    assert st.to_json() == again.to_json() and st.status == "diverged"


def fake(seconds: float):
    """A check of 3 ticks of 2 agents that takes ``seconds`` a tick and finds
    the tick."""
    trace = SimpleNamespace(has=np.zeros((1, 3, 2), dtype=bool), model=SimpleNamespace(n=2, m=1))
    return SimpleNamespace(trace=trace, tick=lambda rec, k, said: time.sleep(seconds) or [k], close=lambda: None)


def record(K=3, N=2):
    rec = world_machine.WorldRecord(**RunReports.empty(K, N, 2, 1), live=np.ones((K, N), dtype=bool))
    rec.reported[:] = True
    return rec


def test_a_finding_not_in_yet_is_none_unless_waited_for_and_the_thread_ends_with_close():
    check = CheckThread(lambda: fake(0.5))
    rec = record()
    try:
        check.submit(rec, 1)
        assert check.result(rec, 1, wait=False) is None
        assert check.result(rec, 1) == [1]
        assert check.result(rec, 2) == [2]  # submitted when asked
    finally:
        check.close()
    assert not check._thread.is_alive()


def test_a_check_that_fails_in_its_thread_fails_in_the_world():
    def broken():
        raise ZeroDivisionError("the replay")

    for made in (False, True):  # the check cannot be made, or its replay fails
        check = CheckThread(broken if not made else lambda: SimpleNamespace(
            trace=fake(0).trace, tick=lambda rec, k, said: 1 / 0, close=lambda: None))
        try:
            with pytest.raises(CheckFailed, match="ZeroDivisionError"):
                check.result(record(), 1)
        finally:
            check.close()


@pytest.mark.parametrize("live", [True, False])
def test_a_tick_handed_over_arrives_as_the_worlds_rows_and_digests(live):
    """``tick_copy`` taken by ``take_tick`` (the world's side and the check's
    thread): tick k's rows of every array, bit for bit (NaN where no
    report), its digests as ``tick_digests`` gives them, the rejoins and
    starting states; the other ticks untouched; what the world writes after
    the copy is not in it."""
    K, N, n, m, k = 4, 5, 3, 2, 3
    rng = np.random.default_rng(7)
    rec = world_machine.WorldRecord(**RunReports.empty(K, N, n, m), live=rng.random((K, N)) < 0.7 if live else None)
    rec.x[:] = rng.standard_normal(rec.x.shape)
    rec.P[:] = rng.standard_normal(rec.P.shape)
    rec.d[:] = rng.standard_normal(rec.d.shape)
    rec.x[k - 1, 2] = np.nan
    for a in (rec.d_valid, rec.reported, rec.fused):
        a[:] = rng.random(a.shape) < 0.5
    for i, senders in ((0, (1, 4)), (3, (0,)), (4, (2, 1, 3))):
        rec.digests[(k, i)] = (senders, tuple(wire.digest(bytes([i, s])) for s in senders))
    rec.digests[(k - 1, 1)] = ((0,), (wire.digest(b"another tick"),))
    rec.rejoins = {2: [{"tick": k, "source": 1}]}
    rec.starts = [wire.Start("r", 2, k, 1, np.ones(n), np.eye(n), np.zeros(m), True)]
    there = world_machine.WorldRecord(**RunReports.empty(K, N, n, m), live=np.zeros((K, N), dtype=bool))
    names = ("x", "P", "d", "d_valid", "reported", "fused") + (("live",) if live else ())
    want = {name: getattr(rec, name)[k - 1].copy() for name in names}
    want_rejoins = copy.deepcopy(rec.rejoins)
    handed = checker.tick_copy(rec, k)
    for name in names:  # the world's record moves on after the hand-over; the copy does not
        getattr(rec, name)[k - 1] = 1
    rec.rejoins[2].append({"tick": k + 1, "source": 0})
    got, said = checker.take_tick(handed, there)
    assert got == k
    for name in names:
        np.testing.assert_array_equal(getattr(there, name)[k - 1], want[name])
        assert getattr(there, name)[k - 1].dtype == getattr(rec, name).dtype
        others = np.arange(K) != k - 1
        assert np.isnan(getattr(there, name)[others]).all() if name in ("x", "P", "d") else not getattr(there, name)[others].any()
    assert (there.live is None) == (not live)
    for a, b in zip(said, rec.tick_digests(k)):
        np.testing.assert_array_equal(a, b)
        assert a.dtype == b.dtype
    assert [a.tolist() for a in said[:2]] == [[0, 0, 3, 4, 4, 4], [1, 4, 0, 2, 1, 3]]
    assert there.rejoins == want_rejoins and len(there.starts) == 1 and there.starts[0].agent == 2
    np.testing.assert_array_equal(there.starts[0].P, np.eye(n))
    rec.rejoins, rec.starts = {}, []
    checker.take_tick(checker.tick_copy(rec, k), there)
    assert there.rejoins == {} and there.starts == []
