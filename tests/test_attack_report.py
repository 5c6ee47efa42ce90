"""A forged report (docs/security.md): an agent's own key, a well-formed
report whose estimate no honest agent could hold. ``wire.decode_report``
checks it as the guard checks a message (magnitude ``wire.MAX_ABS``,
conditioning ``wire.MAX_COND``) before anything uses it, so it never
becomes anyone's state or a metric.
"""
from __future__ import annotations

import numpy as np
import pytest

from diskf_mesh.mesh import wire
from diskf_mesh.mesh.guard import GuardConfig

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
    ([0.0, 0.0], np.eye(2), (-2e12,), "magnitude"),          # the input estimate too
    ([0.0, 0.0], np.diag([1e13, 1.0]), (0.0,), "magnitude"),  # a covariance entry beyond the limit
    ([0.0, 0.0], np.diag([1.0, 1e-11]), (0.0,), "ill-conditioned"),
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
    big = np.diag([1.0, 1.0, 1.0, 1e11])  # n > 2: numpy's eigenvalues
    assert wire.estimate_problem(np.zeros(1), big)[0] == "ill-conditioned"
