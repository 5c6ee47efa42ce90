"""The wire format: round trip, size, every rejection reason, and what is on
the wire in a real run (never a measurement, an H or an R)."""
from __future__ import annotations

import queue
import re
import time

import msgpack
import numpy as np
import pytest

from diskf_mesh.mesh.wire import codec as wire
from diskf_mesh.mesh.wire.keys import Keys
from diskf_mesh.mesh.process.runspec import RunSpec
from diskf_mesh.mesh.process.transport import ZenohTransport
from diskf_mesh.core.messages import Message
from diskf_mesh.data.scenario import scenario_path, simulate

from mesh_helpers import start_mesh

pytestmark = pytest.mark.mesh

RUN = "wire-test"


def _message(n=2, m=1, valid=True, seed=0) -> Message:
    rng = np.random.default_rng(seed)
    A = rng.standard_normal((n, n))
    P = A @ A.T + n * np.eye(n)
    return Message(rng.standard_normal((1, 1, n)), P[None, None], rng.standard_normal((1, 1, n)),
                   (0.5 * P)[None, None], rng.standard_normal((1, 1, m)), (np.eye(m) * 0.3)[None, None],
                   np.array([[valid]]))


def _doc(msg=None) -> dict:
    return msgpack.unpackb(wire.encode(RUN, 3, 12, msg or _message()))


def _rejects(doc_or_bytes, reason: str, **kw) -> None:
    data = doc_or_bytes if isinstance(doc_or_bytes, bytes) else msgpack.packb(doc_or_bytes)
    with pytest.raises(wire.Rejected) as e:
        wire.decode(data, **kw)
    assert e.value.reason == reason


def test_round_trip_is_exact_and_small():
    for n, m in [(2, 1), (4, 2), (6, 3)]:
        msg = _message(n, m, valid=(n != 4))
        data = wire.encode(RUN, 3, 12, msg)
        w = wire.decode(data, run_id=RUN, sender=3, n=n, m=m)
        assert (w.run_id, w.sender, w.tick) == (RUN, 3, 12)
        for f in Message.ARRAY_FIELDS:
            np.testing.assert_array_equal(getattr(w.message, f), getattr(msg, f)[0, 0])  # bit for bit
        assert bool(w.message.d_valid) == (n != 4)
    assert len(wire.encode("a1b2c3d4", 9, 200, _message(2, 1))) < 200


def test_an_estimators_declaration_makes_the_layout_and_the_guards_checks():
    """``Estimator.exchanged``: the default is the seven fields' bytes; a
    declaration of fewer arrays sends only those, the rest arrive as zeros,
    and the guard checks what is declared (here: no P_pred, so no
    information check, and a bad P_pred cannot be refused)."""
    from diskf_mesh.estimators import EXCHANGED, Exchanged
    from diskf_mesh.mesh.protocol.guard import Guard, GuardConfig

    msg = _message(2, 1)
    assert wire.encode(RUN, 3, 12, msg) == wire.encode(RUN, 3, 12, msg, EXCHANGED)
    few = (Exchanged("x_upd", "n"), Exchanged("P_upd", "n n"), Exchanged("d", "m"), Exchanged("S", "m m"))
    data = wire.encode(RUN, 3, 12, msg, few)
    assert len(wire.encode(RUN, 3, 12, msg)) - len(data) == 8 * (2 + 4)
    w = wire.decode(data, run_id=RUN, sender=3, n=2, m=1, exchanged=few)
    for f in ("x_upd", "P_upd", "d", "S"):
        np.testing.assert_array_equal(getattr(w.message, f), getattr(msg, f)[0, 0])
    assert not w.message.x_pred.any() and w.message.P_pred.shape == (2, 2) and not w.message.P_pred.any()
    with pytest.raises(wire.Rejected):  # the other layout's bytes do not fit
        wire.decode(data, run_id=RUN, sender=3, n=2, m=1)
    guard = Guard(GuardConfig(RUN, 1, frozenset({1, 3}), 2, 1, exchanged=few))
    assert isinstance(guard.screen(3, data, 12), wire.WireMessage)
    bad = Message(msg.x_pred, -msg.P_pred, msg.x_upd, msg.P_upd, msg.d, msg.S, msg.d_valid)
    assert isinstance(guard.screen(3, wire.encode(RUN, 3, 12, bad, few), 12), wire.WireMessage)
    assert guard.screen(3, wire.encode(RUN, 3, 12, bad), 12).reason == "size"  # not its layout: refused
    assert Guard(GuardConfig(RUN, 1, frozenset({1, 3}), 2, 1)).screen(3, wire.encode(RUN, 3, 12, bad), 12).reason \
        == "not-spd"


def test_every_rejection_reason():
    _rejects(b"\xc1\xc1 not msgpack", "not-msgpack")
    _rejects(b"", "not-msgpack")
    _rejects([1, 2, 3], "schema")
    _rejects({**_doc(), "v": 2}, "schema")
    _rejects({**_doc(), "k": "report"}, "schema")
    _rejects({k: v for k, v in _doc().items() if k != "t"}, "schema")
    _rejects({**_doc(), "s": "3"}, "schema")
    _rejects(_doc(), "run", run_id="another-run")
    _rejects(_doc(), "sender", sender=4)
    _rejects(_doc(), "shape", n=3)
    _rejects({**_doc(), "a": _doc()["a"][:-8]}, "shape")
    _rejects({**_doc(), "dt": ">f8"}, "dtype")
    _rejects({**_doc(), "a": [1.0] * 14}, "dtype")
    bad = np.frombuffer(_doc()["a"], "<f8").copy()
    bad[0] = np.nan
    _rejects({**_doc(), "a": bad.tobytes()}, "non-finite")
    bad[0] = np.inf
    _rejects({**_doc(), "a": bad.tobytes()}, "non-finite")
    not_pd = _message()
    not_pd = Message(**{**not_pd.__dict__, "P_upd": np.array([[[[1.0, 2.0], [2.0, 1.0]]]])})
    _rejects(wire.encode(RUN, 3, 12, not_pd), "not-spd")
    asym = Message(**{**_message().__dict__, "P_pred": np.array([[[[2.0, 0.5], [0.4, 2.0]]]])})
    _rejects(wire.encode(RUN, 3, 12, asym), "not-spd")
    assert set(wire.REASONS) >= {"not-msgpack", "schema", "run", "sender", "shape", "dtype", "non-finite",
                                 "not-spd"}


def test_world_payloads_round_trip():
    pos = np.arange(8.0).reshape(4, 2)
    t = wire.decode_tick(wire.encode_tick(wire.Tick(RUN, 5, 30, 7, "diskf", "range", float("inf"), pos,
                                                    (1, 2, 4))), run_id=RUN, agents=4)
    assert (t.tick, t.ticks, t.seed, t.live, t.comm_range) == (5, 30, 7, (1, 2, 4), float("inf"))
    np.testing.assert_array_equal(t.positions, pos)
    mm = wire.decode_measurement(wire.encode_measurement(RUN, 5, 2, True, [1.5]), run_id=RUN, agent=2, p=1)
    assert mm.has and mm.y.tolist() == [1.5]
    with pytest.raises(wire.Rejected):
        wire.decode_measurement(wire.encode_measurement(RUN, 5, 2, True, [1.5]), agent=3)
    r = wire.decode_report(wire.encode_report(RUN, 2, 5, [1.0, 2.0], np.eye(2), [0.5], True, {"fused": 3}),
                           run_id=RUN, sender=2, n=2, m=1)
    assert r.counters == {"fused": 3} and r.d_valid


def test_limits_fit_every_payload_of_a_run_and_nothing_much_larger():
    """The schema's sizes: the largest legitimate payload of each kind (a
    32-character run id, 19-digit ids and ticks) fits; one byte of padding
    over the limit does not, and is refused before it is decoded."""
    run, big = "r" * 32, 2 ** 63 - 1
    cases = [("msg", (2, 1), wire.encode(run, big, big, _message(2, 1)), wire.decode, {"n": 2, "m": 1}),
             ("msg", (6, 3), wire.encode(run, big, big, _message(6, 3)), wire.decode, {"n": 6, "m": 3}),
             ("report", (2, 1), wire.encode_report(run, big, big, [1.0, 2.0], np.eye(2), [0.5], True,
                                                   {f"rejected.{'x' * 32}{i:c}": big for i in range(97, 97 + 26)}
                                                   | {k: big for k in ("published", "sent", "lost", "received",
                                                                       "arrived", "duplicate", "fused", "late",
                                                                       "unlinked", "out_of_range", "in_flight",
                                                                       "pending")}),
              None, None),
             ("tick", (9,), wire.encode_tick(wire.Tick(run, big, big, big, "random-gdkf", "random-geometric",
                                                       1e300, np.ones((9, 2)), tuple(range(big - 9, big)))),
              wire.decode_tick, {"agents": 9}),
             ("meas", (1,), wire.encode_measurement(run, big, big, True, [1.5]), wire.decode_measurement, {"p": 1}),
             ("stop", (), wire.encode_stop(run, big, "x" * wire.MAX_WHY), wire.decode_stop, {})]
    for kind, dims, payload, dec, kw in cases:
        lim = wire.limits(kind, *dims)
        assert len(payload) <= lim.max_bytes, kind
        if dec is not None:
            dec(payload, **kw)
            with pytest.raises(wire.Rejected) as e:
                dec(payload + b"\x00" * (lim.max_bytes + 1 - len(payload)), **kw)
            assert e.value.reason == "size"


def test_msgpack_limits_are_sized_to_the_schema():
    _rejects(msgpack.packb({str(i): 0 for i in range(130_000)}), "size")            # ~0.9 MB, 130k keys
    _rejects({**_doc(), "x": 1, "y": 2, "z": 3}, "size", n=2, m=1)                  # a 13th field
    wire.decode(msgpack.packb({**_doc(), "x": 1, "y": 2}), n=2, m=1)                # room for two more
    _rejects({**_doc(), "run": "r" * (wire.MAX_STR + 1)}, "size")
    _rejects({**_doc(), "a": _doc()["a"] + b"\x00" * 8}, "size", n=2, m=1)          # a bin over 8 x 14
    _rejects({**_doc(), "a": [1.0] * 15}, "size", n=2, m=1)                        # an array over 14
    tick = msgpack.unpackb(wire.encode_tick(wire.Tick(RUN, 5, 30, 7, "diskf", "range", 1.0, np.ones((4, 2)),
                                                      (1, 2, 3, 4))))
    with pytest.raises(wire.Rejected) as e:
        wire.decode_tick(msgpack.packb({**tick, "live": list(range(5))}), agents=4)    # more ids than agents
    assert e.value.reason == "size"
    with pytest.raises(wire.Rejected) as e:
        wire.decode_measurement(wire.encode_measurement(RUN, 5, 2, True, [1.5, 2.5]), p=1)
    assert e.value.reason == "size"


def test_a_rejection_after_the_tick_was_read_carries_it():
    bad = np.frombuffer(_doc()["a"], "<f8").copy()
    bad[0] = np.nan
    with pytest.raises(wire.Rejected) as e:
        wire.decode(msgpack.packb({**_doc(), "a": bad.tobytes()}), n=2, m=1)
    assert (e.value.reason, e.value.tick) == ("non-finite", 12)
    with pytest.raises(wire.Rejected) as e:
        wire.decode(b"\xc1")
    assert e.value.tick is None


def test_report_counters_are_validated_against_the_run():
    def report(counters):
        return wire.encode_report(RUN, 2, 5, [1.0, 2.0], np.eye(2), [0.5], True, counters)

    bound = wire.count_bound(200)
    assert bound == 201 * wire.PER_TICK and wire.count_bound(None) == 2 ** 53
    ok = wire.decode_report(report({"sent": bound, "rejected.size": 3}), n=2, m=1, ticks=200)
    assert ok.counters == {"sent": bound, "rejected.size": 3}
    letters = [a + b for a in "abcdefghij" for b in "abcdefghij"]
    for counters, reason in [({"sent": 2 ** 63 - 1}, "size"),            # forged, with or without the run's K
                             ({"sent": bound + 1}, "size"), ({"fused": -1}, "size"),
                             ({"made-up": 1}, "schema"), ({"rejected.X1": 1}, "schema"),
                             ({f"rejected.{x}": 1 for x in letters[:wire.MAX_COUNTERS + 1]}, "size")]:
        for ticks in (200, None):
            if counters == {"sent": bound + 1} and ticks is None:
                continue
            with pytest.raises(wire.Rejected) as e:
                wire.decode_report(report(counters), n=2, m=1, ticks=ticks)
            assert e.value.reason == reason, counters
    from diskf_mesh.mesh.wire.counters import Counters
    assert Counters(sent=2 ** 70, fused=3).to_dict(cap=bound)["sent"] == bound


def test_id_lists_hold_ints_only():
    """A tick's live ids and a report's fused ids and re-initialisation are
    ints: a bool, a float or a string among them is refused ("schema")."""
    pos = np.arange(8.0).reshape(4, 2)
    for bad in (True, 2.0, "2"):
        doc = msgpack.unpackb(wire.encode_tick(wire.Tick(RUN, 5, 30, 7, "diskf", "range", 100.0, pos, (1, 2, 4))))
        doc["live"] = [1, bad, 4]
        with pytest.raises(wire.Rejected) as e:
            wire.decode_tick(msgpack.packb(doc), run_id=RUN, agents=4)
        assert e.value.reason == "schema", bad
        rep = msgpack.unpackb(wire.encode_report(RUN, 2, 5, [1.0, 2.0], np.eye(2), [0.5], True, {}, [1, 3], [],
                                                 restart=(4, 1)))
        for field, value in (("f", [1, bad]), ("rj", [4, bad])):
            doc = dict(rep, **{field: value})
            with pytest.raises(wire.Rejected) as e:
                wire.decode_report(msgpack.packb(doc), run_id=RUN, sender=2, n=2, m=1)
            assert e.value.reason == "schema", (field, bad)


def _distinctive_scenario(tmp_path):
    """Scenario 1 with H and R values that cannot appear by chance."""
    text = scenario_path("quadrants").read_text()
    text = text.replace("H = [[1.0, 0.0]]", "H = [[1.2345678, 0.0]]").replace("H = [[0.0, 1.0]]",
                                                                            "H = [[0.0, 1.2345678]]")
    text = text.replace("R = [[2.0]]", "R = [[2.718281828]]")
    path = tmp_path / "distinct.toml"
    path.write_text(text)
    return str(path)


def test_no_measurement_h_or_r_on_the_wire(tmp_path):
    """Sniff every agent message of a real run and look for the bytes of H,
    R and every measurement."""
    spec = RunSpec(_distinctive_scenario(tmp_path), "diskf", run_id="sniffed", topology="all")
    ticks, seed = 100, 4
    captured = queue.SimpleQueue()
    # 50 ticks a second: the run lasts 2 s, not the 0.2 s of lockstep, so the sniffer's session, which
    # joins the mesh by gossip, hears most of it
    mesh = start_mesh(spec, ticks, seed, tmp_path, world_extra=["--rate", "50"])
    try:
        sniffer = ZenohTransport(mesh.observer())  # the run's observer identity: it may listen
        sniffer.subscribe(Keys(spec.run_id).msgs, lambda k, p: captured.put((k, p)))
        stop = time.monotonic() + 30
        while not sniffer.tokens(Keys(spec.run_id).alive_world, 1.0) and time.monotonic() < stop:
            pass  # connected to the mesh (it sees the world) before any agent starts
        mesh.start_agents()
        mesh.wait(60)
    finally:
        mesh.stop_all()
    time.sleep(0.2)
    sniffer.close()
    payloads = []
    while not captured.empty():
        payloads.append(captured.get())
    # the sniffer joins the mesh by gossip while the run goes on: it may miss
    # the first ticks, never all of them
    assert len(payloads) >= ticks, "the sniffer heard too little"
    assert {k.split("/")[3] for k, _ in payloads} == {"1", "2", "3", "4"}
    trace = simulate(spec.load(ticks), [seed])
    secrets = {np.float64(v).tobytes() for v in (1.2345678, 2.718281828, 1 / 2.718281828)}
    secrets |= {np.float64(v).tobytes() for v in trace.y[trace.has].ravel()}
    for key, data in payloads:
        assert re.fullmatch(r"diskf/sniffed/agent/\d/msg/_(\d_)*", key)
        assert len(data) < 200
        doc = msgpack.unpackb(data)
        assert set(doc) == {"v", "k", "run", "s", "t", "n", "m", "dt", "dv", "a"}
        for s in secrets:
            assert s not in data


@pytest.mark.parametrize("n", [1, 2, 3, 5])
def test_report_problem_refuses_exactly_what_the_world_refuses(n):
    """``report_problem`` (what an agent asks before reporting) and
    ``decode_report`` (what the world takes) agree on every estimate, with
    the same reason: fine, too large, ill-conditioned, not positive
    definite, not finite."""
    rng = np.random.default_rng(n)
    L = rng.normal(size=(n, n))
    P = L @ L.T + n * np.eye(n)
    x, d = rng.normal(size=n), rng.normal(size=1)
    bad_cond = np.diag([1e14] + [1e-2] * (n - 1)) if n > 1 else np.zeros((1, 1))  # n = 1: not positive
    cases = [(x, P, d), (x * 1e16, P, d), (x, bad_cond, d), (x, -P, d), (x, P, d * np.nan)]
    reasons = []
    for cx, cP, cd in cases:
        problem = wire.report_problem(cx, cP, cd)
        payload = wire.encode_report("r", 1, 3, cx, cP, cd, True)
        try:
            wire.decode_report(payload, run_id="r", sender=1, n=n, m=1)
            said = None
        except wire.Rejected as e:
            said = e.reason
        assert (problem[0] if problem else None) == said
        reasons.append(said)
    assert reasons[0] is None and reasons[1] == "magnitude" and reasons[3] == "not-spd"
    assert reasons[2] == ("ill-conditioned" if n > 1 else "not-spd") and reasons[4] == "non-finite"
