"""Fuzz: at least 10,000 generated payloads at the decoder, the guard and the
DISKF fusion of one agent (a batch of one).

Each example is one tick of one receiver: its good neighbours' real messages,
mixed in random order with generated bad payloads (random bytes, msgpack of
random structures, real messages with one field broken: schema version,
kind, run, shapes, dtype, NaN or infinity, a covariance that is not SPD, a
wrong tick, an unknown sender, a key naming another agent than the body),
duplicates of the good ones, and well-formed messages that must not be fused
at this tick (another tick, an unlinked sender). Nothing may raise, every bad
payload must be rejected with a known reason (never ``error``), and the
fused estimate must equal, bit for bit, the fusion of the good messages alone.
"""
from __future__ import annotations

import msgpack
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from diskf_mesh.mesh.wire import codec as wire
from diskf_mesh.mesh.protocol.guard import REASONS, Guard
from diskf_mesh.core.messages import Message
from diskf_mesh.mesh.protocol.receive import Receiver
from message_factory import tick_view

EXAMPLES = 250
BAD_PER_EXAMPLE = (35, 60)


@pytest.fixture(scope="module")
def views():
    # two receivers, two ticks of Scenario 2: input being estimated and not
    return [tick_view("diskf", tick=t) for t in (20, 47)]


# --------------------------------------------------------------------------
# payload strategies: (key sender, payload bytes)
# --------------------------------------------------------------------------
json_like = st.recursive(
    st.none() | st.booleans() | st.integers(-2**63, 2**64 - 1) | st.floats() | st.text(max_size=8)
    | st.binary(max_size=40),
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=4), inner, max_size=5),
    max_leaves=12,
)
FIELDS = ("v", "k", "run", "s", "t", "n", "m", "dv", "a")  # every required field ("dt" has a default)


def bad_payload(view):
    j0 = view.linked[0]
    known = list(view.ids)
    others = [i for i in known if i != view.me]  # a payload on the receiver's own key is ignored, not rejected
    unknown = st.integers(-5, 10**6).filter(lambda i: i not in known)
    template = st.sampled_from(others).map(lambda j: (j, msgpack.unpackb(view.payload(j), raw=False)))
    n, m = view.n, view.m
    count = 2 * n + 2 * n * n + m + m * m

    def broken(draw_doc, mutate):
        return st.tuples(template, mutate).map(lambda t: (t[0][0], pack(draw_doc(t[0][1], t[1]))))

    def arrays(doc):
        return np.frombuffer(doc["a"], dtype="<f8").copy()

    def set_block(doc, which, value):
        a = arrays(doc)
        offs = {"P_pred": n, "P_upd": 2 * n + n * n, "S": 2 * n + 2 * n * n + m}
        size = m * m if which == "S" else n * n
        a[offs[which]:offs[which] + size] = np.asarray(value, dtype=float).ravel()
        return {**doc, "a": a.tobytes()}

    def not_spd(doc, choice):
        which, kind = choice
        k = m if which == "S" else n
        if kind == "neg":
            M = -np.eye(k)
        elif kind == "zero":
            M = np.zeros((k, k))
        else:  # asymmetric (only possible for k > 1) or indefinite
            M = np.eye(k)
            if k > 1:
                M[0, 1] = 0.5
            else:
                M = -M
        return set_block(doc, which, M)

    def non_finite(doc, choice):
        pos, val = choice
        a = arrays(doc)
        a[pos % count] = val
        return {**doc, "a": a.tobytes()}

    mutations = [
        st.binary(max_size=300).map(lambda b: (j0, b)),
        st.tuples(st.sampled_from(others), json_like).map(lambda t: (t[0], pack(t[1]))),
        broken(lambda d, v: {**d, "v": v}, st.one_of(st.integers(-2**63, 2**64 - 1).filter(lambda v: v != wire.SCHEMA),
                                                     st.text(max_size=3), st.none(), st.booleans())),
        broken(lambda d, k: {**d, "k": k}, st.sampled_from(["report", "tick", "meas", "stop", "", "MSG"])),
        broken(lambda d, f: {k: v for k, v in d.items() if k != f}, st.sampled_from(FIELDS)),
        broken(lambda d, fv: {**d, fv[0]: fv[1]}, st.tuples(st.sampled_from(("s", "t", "n", "m", "dv", "a", "run")),
                                                            st.sampled_from([None, "x", 1.5, [], {}]))),
        broken(lambda d, r: {**d, "run": r}, st.text(max_size=10).filter(lambda r: r != view.run_id)),
        broken(lambda d, nm: {**d, "n": nm[0], "m": nm[1]},
               st.tuples(st.integers(-3, 70), st.integers(-3, 70)).filter(lambda t: t != (n, m))),
        broken(lambda d, cut: {**d, "a": d["a"][:cut]}, st.integers(0, 8 * count - 1)),
        broken(lambda d, extra: {**d, "a": d["a"] + extra}, st.binary(min_size=1, max_size=24)),
        broken(lambda d, dt: {**d, "dt": dt}, st.sampled_from(["<f4", ">f8", "float64", "", "<i8"])),
        broken(lambda d, _: {**d, "a": list(arrays(d))}, st.none()),
        broken(non_finite, st.tuples(st.integers(0, 10**6), st.sampled_from([np.nan, np.inf, -np.inf]))),
        broken(not_spd, st.tuples(st.sampled_from(["P_pred", "P_upd", "S"]), st.sampled_from(["neg", "zero", "asym"]))),
        broken(lambda d, t: {**d, "t": t}, st.one_of(st.integers(-10**9, 0),
                                                     st.integers(view.ticks + 1, 2**63),
                                                     st.integers(1, max(1, view.tick - 17)),
                                                     st.integers(view.tick + 3, view.ticks + 1))),
        broken(lambda d, scale: {**d, "a": (arrays(d) * scale).tobytes()}, st.sampled_from([1e14, 1e100, 1e300])),
        # body claims an unknown sender, key names it too
        st.tuples(template, unknown).map(lambda t: (t[1], pack({**t[0][1], "s": t[1]}))),
        # key names another (known) agent than the body
        st.tuples(template, st.sampled_from(others)).filter(lambda t: t[0][0] != t[1])
          .map(lambda t: (t[1], pack(t[0][1]))),
        # negative information: the "update" is less certain than the prediction
        broken(lambda d, f: set_block(d, "P_upd", f * arrays(d)[n:n + n * n]), st.floats(1.5, 1e3)),
    ]
    return st.one_of(*mutations)


def pack(doc) -> bytes:
    return msgpack.packb(doc, use_bin_type=True)


# --------------------------------------------------------------------------
# the test
# --------------------------------------------------------------------------
def test_fuzz_decoder_guard_and_fusion(views):
    stats = {"payloads": 0, "bad": 0, "examples": 0}
    reasons_seen = set()

    for view in views:
        ref = view.fuse([(j, view.messages[j]) for j in view.linked])[1]
        unlinked = [j for j in view.ids if j not in view.linked and j != view.me]

        @settings(max_examples=EXAMPLES // len(views) + 1, deadline=None, database=None,
                  suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
        @given(data=st.data())
        def one_tick(data):
            bad = data.draw(st.lists(bad_payload(view), min_size=BAD_PER_EXAMPLE[0], max_size=BAD_PER_EXAMPLE[1]))
            good = [(j, view.payload(j)) for j in view.linked]
            dups = data.draw(st.lists(st.sampled_from(good), max_size=4))
            harmless = [(j, view.payload(j)) for j in unlinked] + [(j, view.payload(j, view.tick + 1))
                                                                  for j in view.linked]
            stream = data.draw(st.permutations(bad + good + dups + harmless))
            rx = Receiver(Guard(view.guard_config()))
            rx.tick = view.tick
            for sender, payload in stream:
                rx.on_payload(sender, payload)
            got = rx.take(view.tick, view.linked)
            _, out = view.fuse(got)
            assert out.x.tobytes() == ref.x.tobytes()
            assert out.P.tobytes() == ref.P.tobytes()
            assert out.d.tobytes() == ref.d.tobytes()
            c = rx.close()
            assert c.rejected_total == len(bad), c.rejected
            assert "error" not in c.rejected and set(c.rejected) <= set(REASONS)
            assert c.fused == len(view.linked) and c.duplicate == len(dups)
            assert c.imbalance() == []
            reasons_seen.update(c.rejected)
            stats["payloads"] += len(stream)
            stats["bad"] += len(bad)
            stats["examples"] += 1

        one_tick()

    assert stats["payloads"] >= 10_000, stats
    # every kind of bad input the fuzzer makes was seen and named
    assert {"not-msgpack", "schema", "run", "shape", "dtype", "non-finite", "not-spd", "sender", "unknown-sender",
            "tick-past", "tick-future", "magnitude", "information"} <= reasons_seen, reasons_seen


def test_fuzz_random_bytes_at_every_decoder():
    """Random bytes at every decode function: a result or Rejected, nothing else."""
    decoders = [wire.decode, wire.decode_report, wire.decode_tick, wire.decode_measurement, wire.decode_stop]

    @settings(max_examples=400, deadline=None, database=None)
    @given(st.one_of(st.binary(max_size=200), json_like.map(pack)))
    def check(payload):
        for dec in decoders:
            try:
                dec(payload)
            except wire.Rejected as e:
                assert e.reason in wire.REASONS

    check()


def test_fuzzed_message_is_never_a_message_object():
    """Sanity of the harness: a Message built from a good payload round-trips."""
    view = tick_view("diskf", tick=12)
    j = view.linked[0]
    wm = wire.decode(view.payload(j), run_id=view.run_id, sender=j, n=view.n, m=view.m)
    assert isinstance(wm.message, Message)
