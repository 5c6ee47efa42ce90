"""A forged report (docs/security.md): an agent's own key, a well-formed
report whose estimate no honest agent could hold. ``wire.decode_report``
checks it as the guard checks a message (magnitude ``wire.MAX_ABS``,
conditioning ``wire.MAX_COND``) before anything uses it, so it never
becomes anyone's state or a metric.
"""
from __future__ import annotations

import numpy as np
import pytest

from diskf_mesh.mesh.wire import codec as wire
from diskf_mesh.mesh.protocol.guard import GuardConfig

RUN = "report-test"


def _report(x, P, d=(0.5,)):
    return wire.encode_report(RUN, 3, 7, np.asarray(x, float), np.asarray(P, float), np.asarray(d, float), True,
                              {"fused": 2}, fused=(1, 3))


def _decode(payload):
    return wire.decode_report(payload, run_id=RUN, sender=3, n=2, m=1, ticks=50, agents=5)


def test_an_honest_report_passes():
    r = _decode(_report([1.0, -2.0], np.diag([0.5, 2.0])))
    assert r.x.tolist() == [1.0, -2.0] and r.fused == (1, 3)


@pytest.mark.parametrize("x, P, d, reason", [
    ([1e300, 0.0], np.eye(2), (0.0,), "magnitude"),          # finite, but every product of it overflows
    ([0.0, 0.0], np.eye(2), (-2e15,), "magnitude"),          # the input estimate too
    ([0.0, 0.0], np.diag([1e16, 1.0]), (0.0,), "magnitude"),  # a covariance entry beyond the limit
    ([0.0, 0.0], np.diag([1.0, 1e-15]), (0.0,), "ill-conditioned"),
    ([9e11, 0.0], 1e-6 * np.eye(2) + np.diag([0.0, 1e-17]), (0.0,), None),  # large but within the limits
])
def test_a_report_beyond_what_a_message_may_hold_is_refused(x, P, d, reason):
    payload = _report(x, P, d)
    if reason is None:
        assert _decode(payload).x[0] == 9e11
        return
    with pytest.raises(wire.Rejected) as e:
        _decode(payload)
    assert e.value.reason == reason


def test_the_limits_of_reports_are_those_of_messages():
    c = GuardConfig(run_id=RUN, me=1, known=frozenset({1, 2}), n=2, m=1)
    assert (c.max_abs, c.max_cond) == (wire.MAX_ABS, wire.MAX_COND)
    assert wire.estimate_problem(np.array([c.max_abs]), np.eye(2)) is None
    assert wire.estimate_problem(np.array([np.nextafter(c.max_abs, np.inf)]), np.eye(2))[0] == "magnitude"
    assert wire.estimate_problem(np.zeros(1), np.diag([c.max_cond, 1.0])) is None
    assert wire.estimate_problem(np.zeros(1), np.diag([2 * c.max_cond, 1.0]))[0] == "ill-conditioned"
    big = np.diag([1.0, 1.0, 1.0, 1e15])  # n > 2: numpy's eigenvalues
    assert wire.estimate_problem(np.zeros(1), big)[0] == "ill-conditioned"


def test_a_forged_report_never_becomes_a_state_a_start_or_a_metric():
    """The world's machine is fed agent ``best``'s report of tick 1 with
    x = 1e300 and the most certain P of all (it would be every rejoining
    neighbour's starting estimate): it is refused, the tick goes on
    without it, and a rejoining neighbour starts from another's estimate."""
    from diskf_mesh.data.scenario import simulate
    from diskf_mesh.mesh.protocol.estimator import neighbours
    from diskf_mesh.mesh.protocol.events import Answer, Query, Sample, Timer, Token, Tokens
    from diskf_mesh.mesh.wire.keys import Keys
    from diskf_mesh.mesh.process.runspec import RunSpec
    from diskf_mesh.mesh.protocol.world_machine import CLAIM, WorldMachine, WorldTiming

    spec = RunSpec("quadrants", "kcf", run_id=RUN, topology="ring")
    scn = spec.load(6)
    trace = simulate(scn, [0])
    keys = Keys(RUN)
    w = WorldMachine(scn, trace, "kcf", 0, keys, "0000000000000010aaaaaaaa", WorldTiming(30.0, 10.0))
    w.start(0.0)
    w.handle(Tokens(CLAIM, ()), 0.0)
    for i in w.ids:
        w.handle(Token(keys.alive(i, "n1"), True), 0.1)
        w.handle(Token(keys.ready(i, "n1"), True), 0.1)
    a = w.ids[0]
    best = min(set(neighbours(scn, a, trace.positions[0])) - {a})
    n, m = trace.model.n, trace.model.m
    for i in w.ids:
        x = np.full(n, 1e300 if i == best else float(i))
        P = np.eye(n) * (0.1 if i == best else 2.0)
        w.handle(Sample(keys.report(i), wire.encode_report(RUN, i, 1, x, P, np.zeros(m), False)), 0.2)
    w.handle(Timer("tick"), 10.1)  # tick 1 ends without the refused report
    out = w.handle(Query(1, keys.start(a), wire.encode_join(RUN, a, 2)), 10.2)
    start = wire.decode_start(next(e for e in out if isinstance(e, Answer)).payload, run_id=RUN, agent=a, tick=2)
    j = w.ids.index(best)
    assert w.record.counters["rejected:magnitude"] == 1
    assert not w.record.reported[0, j] and w.record.why[0, j] == "rejected"
    assert start.source != best and np.abs(start.x).max() < 1e3
    assert np.nanmax(np.abs(w.record.x)) < 1e3  # what the metrics are computed from
