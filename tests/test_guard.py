"""The fusion guard: every kind of bad input is rejected with its reason,
counted, logged once per sender and reason, and never changes an estimate."""
from __future__ import annotations

import logging

import msgpack
import numpy as np
import pytest

from diskf_mesh import wire
from diskf_mesh.counters import Counters
from diskf_mesh.faults import FaultConfig, FaultModel
from diskf_mesh.guard import REASONS, Guard, fuse_checked
from diskf_mesh.messages import Message, Neighbourhood
from diskf_mesh.receive import Receiver
from message_factory import tick_view


@pytest.fixture(scope="module")
def view():
    return tick_view("diskf", tick=30)


def doc_of(view, sender, tick=None) -> dict:
    return msgpack.unpackb(view.payload(sender, tick), raw=False)


def pack(doc) -> bytes:
    return msgpack.packb(doc, use_bin_type=True)


def with_arrays(view, sender, **arrays) -> bytes:
    msg = view.messages[sender]
    fields = {f: getattr(msg, f) for f in ("x_pred", "P_pred", "x_upd", "P_upd", "d", "S", "d_valid")}
    fields.update(arrays)
    return wire.encode(view.run_id, sender, view.tick, Message(**fields))


def bad_payloads(view):
    """(reason, key sender, payload) for every way a message can be bad."""
    j = view.linked[0]
    other = [i for i in view.ids if i not in (j, view.me)][0]
    d = doc_of(view, j)
    n = view.n
    blob = np.frombuffer(d["a"], dtype="<f8").copy()
    nan = blob.copy()
    nan[3] = np.nan
    inf = blob.copy()
    inf[0] = -np.inf
    P = view.messages[j].P_pred
    cases = [
        ("not-msgpack", j, b"\xc1\xc1\xc1"),
        ("not-msgpack", j, b""),
        ("schema", j, pack([1, 2, 3])),
        ("schema", j, pack({**d, "v": 2})),
        ("schema", j, pack({**d, "k": "report"})),
        ("schema", j, pack({k: v for k, v in d.items() if k != "t"})),
        ("schema", j, pack({**d, "dv": 1})),
        ("run", j, pack({**d, "run": "another-run"})),
        ("shape", j, pack({**d, "n": n + 1})),
        ("shape", j, pack({**d, "a": d["a"][:-8]})),
        ("dtype", j, pack({**d, "dt": "<f4"})),
        ("dtype", j, pack({**d, "a": blob.tolist()})),
        ("non-finite", j, pack({**d, "a": nan.tobytes()})),
        ("non-finite", j, pack({**d, "a": inf.tobytes()})),
        ("not-spd", j, with_arrays(view, j, P_pred=P + np.array([[0, 1], [0, 0]]))),
        ("not-spd", j, with_arrays(view, j, P_upd=-P)),
        ("not-spd", j, with_arrays(view, j, S=np.zeros((1, 1)))),
        ("sender", other, view.payload(j)),                       # key names another agent than the body
        ("unknown-sender", 99, pack({**d, "s": 99})),
        ("tick-past", j, view.payload(j, tick=view.tick - 20)),
        ("tick-past", j, view.payload(j, tick=0)),
        ("tick-future", j, view.payload(j, tick=view.tick + 5)),
        ("tick-future", j, view.payload(j, tick=10 ** 12)),
        ("magnitude", j, with_arrays(view, j, x_upd=np.array([1e200, 0.0]))),
        ("ill-conditioned", j, with_arrays(view, j, P_pred=np.diag([1.0, 1e-12]), P_upd=np.diag([0.5, 1e-12]))),
        ("information", j, with_arrays(view, j, P_upd=10.0 * P)),
    ]
    return cases


def test_every_bad_input_is_rejected_with_its_reason(view):
    g = Guard(view.guard_config())
    for reason, sender, payload in bad_payloads(view):
        before = dict(g.counters.rejected)
        assert g.admit(sender, payload, view.tick) is None, reason
        assert g.counters.rejected.get(reason, 0) == before.get(reason, 0) + 1, (reason, g.counters.rejected)
    assert set(g.counters.rejected) <= set(REASONS) and "error" not in g.counters.rejected


def test_a_key_without_an_integer_id_is_rejected_without_a_decode(view):
    g = Guard(view.guard_config())
    j = view.linked[0]
    for payload in (view.payload(j), b"junk"):   # the verdict does not depend on the bytes: never decoded
        assert g.admit(None, payload, view.tick) is None
    assert g.counters.rejected == {"key": 2}


def test_a_good_message_passes_bit_for_bit(view):
    g = Guard(view.guard_config())
    for j in view.linked:
        wm = g.admit(j, view.payload(j), view.tick)
        assert (wm.sender, wm.tick, wm.run_id) == (j, view.tick, view.run_id)
        for f in Message.ARRAY_FIELDS:
            assert np.array_equal(getattr(wm.message, f), getattr(view.messages[j], f))
            assert getattr(wm.message, f).tobytes() == np.ascontiguousarray(getattr(view.messages[j], f)).tobytes()
    assert g.counters.rejected == {}


def test_own_messages_are_ignored_silently(view):
    g = Guard(view.guard_config())
    assert g.admit(view.me, view.payload(view.me), view.tick) is None
    assert g.counters == Counters()


def test_ticks_inside_the_window_pass(view):
    g = Guard(view.guard_config(max_lag=3, max_lead=2))
    j = view.linked[0]
    ok = [view.tick - 3, view.tick, view.tick + 2]
    assert all(g.admit(j, view.payload(j, tick=t), view.tick) for t in ok)
    bad = [view.tick - 4, view.tick + 3]
    assert not any(g.admit(j, view.payload(j, tick=t), view.tick) for t in bad)


def test_logged_once_per_sender_and_reason(view, caplog):
    g = Guard(view.guard_config())
    j, k = view.linked[:2]
    with caplog.at_level(logging.WARNING, logger="diskf_mesh.guard"):
        for _ in range(5):
            g.admit(j, b"junk", view.tick)
            g.admit(k, b"junk", view.tick)
            g.admit(j, view.payload(j, tick=0), view.tick)
    assert len(caplog.records) == 3
    assert g.by_sender[(j, "not-msgpack")] == 5 and g.by_sender[(k, "not-msgpack")] == 5
    assert g.by_sender[(j, "tick-past")] == 5
    assert g.counters.rejected == {"not-msgpack": 10, "tick-past": 5}
    assert all(f"agent {view.me}" in r.getMessage() for r in caplog.records)


def test_guard_never_raises_even_on_non_bytes(view):
    g = Guard(view.guard_config())
    for payload in (None, 12, "text", [b"x"], object()):
        assert g.admit(view.linked[0], payload, view.tick) is None
    assert "error" not in g.counters.rejected


def test_the_factory_fuses_as_the_engine_does(view):
    """The batch-of-one fusion of the factory equals the in-process engine's."""
    from diskf_mesh import engine
    from diskf_mesh.scenario import load_scenario, simulate
    scn = load_scenario("dynamic")
    est = engine.run(simulate(scn, [0], steps=view.tick), "diskf", scn.params)
    _, out = view.fuse([(j, view.messages[j]) for j in view.linked])
    i = view.ids.index(view.me)
    np.testing.assert_allclose(out.x[0], est.x[0, -1, i], rtol=0, atol=1e-9)


def test_rejected_messages_leave_the_estimate_bit_for_bit(view):
    rx = Receiver(Guard(view.guard_config()))
    rx.tick = view.tick
    for reason, sender, payload in bad_payloads(view):
        rx.on_payload(sender, payload)
    for j in view.linked:
        rx.on_payload(j, view.payload(j))
        rx.on_payload(j, view.payload(j))      # a duplicate is fused once
    got = rx.take(view.tick, view.linked)
    _, out = view.fuse(got)
    _, ref = view.fuse([(j, view.messages[j]) for j in view.linked])
    assert out.x.tobytes() == ref.x.tobytes() and out.P.tobytes() == ref.P.tobytes()
    c = rx.close()
    assert c.fused == len(view.linked) and c.duplicate == len(view.linked)
    assert c.sent == c.received == c.arrived == 2 * len(view.linked)   # the sender repeated itself
    assert c.rejected_total == len(bad_payloads(view))
    assert c.imbalance() == []


def test_fusion_that_still_fails_keeps_the_own_estimate(view):
    """A set of individually plausible messages that makes fusion fail: the
    agent fuses its own message alone and goes on."""
    j = view.linked[0]
    P = view.messages[j].P_pred
    liar = Message(**{**{f: getattr(view.messages[j], f) for f in ("x_pred", "x_upd", "d", "S", "d_valid")},
                      "P_pred": P, "P_upd": np.full((2, 2), np.nan)})
    rows = sorted([(view.me, view.own.take(0)), (j, liar)], key=lambda r: r[0])
    senders = Message.stack([m for _, m in rows])
    own_index = [s for s, _ in rows].index(view.me)
    mask = np.zeros((1, 2), dtype=bool)
    mask[0, own_index] = True
    with np.errstate(all="ignore"):
        _, out, ok = fuse_checked(view.alg, view.state, view.own, senders, Neighbourhood(np.ones((1, 2)), mask),
                                  own_index)
    _, alone = view.fuse([])
    assert not ok and out.x.tobytes() == alone.x.tobytes()


def test_receiver_with_faults_balances_its_books(view):
    """Many ticks of every linked neighbour through a lossy, duplicating link."""
    cfg = FaultConfig(loss=0.3, duplicate=0.2)
    rx = Receiver(Guard(view.guard_config(max_lag=1000, max_lead=1000)), FaultModel(cfg, seed=5))
    for t in range(1, view.ticks + 1):
        rx.tick = t
        for j in view.ids:
            rx.on_payload(j, view.payload(j, tick=t))
        rx.take(t, view.linked)
    c = rx.close()
    others = len(view.ids) - 1
    assert c.sent == others * view.ticks
    assert c.imbalance() == []
    assert abs(c.lost / c.sent - 0.3) < 0.05
    assert c.fused + c.unlinked + c.duplicate == c.arrived and c.late == 0
    assert c.arrived > c.received and c.duplicate == c.arrived - c.received
