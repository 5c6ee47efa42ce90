"""The fusion guard: every kind of bad input is rejected with its reason,
counted, logged once per sender and reason, and never changes an estimate."""
from __future__ import annotations

import logging

import msgpack
import numpy as np
import pytest

from diskf_mesh.mesh.wire import codec as wire
from diskf_mesh.mesh.wire.counters import Counters
from diskf_mesh.data.faults import FaultConfig, FaultModel
from diskf_mesh.mesh.protocol.guard import REASONS, Guard
from diskf_mesh.core.messages import Message
from diskf_mesh.mesh.protocol.receive import Receiver
from diskf_mesh.mesh.protocol.events import at_once
from message_factory import tick_view


def admit(g, sender, payload, tick):
    """The guard's message, or None (rejected, or the agent's own)."""
    out = g.screen(sender, payload, tick)
    return out if isinstance(out, wire.WireMessage) else None


def wait_accounted(rx, tick, expected, deadline):
    """Poll until every sender in ``expected`` is accounted for at ``tick`` or the deadline."""
    import time
    while not set(expected) <= rx.accounted(tick) and time.monotonic() < deadline:
        time.sleep(0.01)
    return rx.accounted(tick)


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
        ("ill-conditioned", j, with_arrays(view, j, P_pred=np.diag([1.0, 1e-15]), P_upd=np.diag([0.5, 1e-15]))),
        ("information", j, with_arrays(view, j, P_upd=10.0 * P)),
    ]
    return cases


def test_every_bad_input_is_rejected_with_its_reason(view):
    g = Guard(view.guard_config())
    for reason, sender, payload in bad_payloads(view):
        before = dict(g.counters.rejected)
        assert admit(g, sender, payload, view.tick) is None, reason
        assert g.counters.rejected.get(reason, 0) == before.get(reason, 0) + 1, (reason, g.counters.rejected)
    assert set(g.counters.rejected) <= set(REASONS) and "error" not in g.counters.rejected


def test_a_key_without_an_integer_id_is_rejected_without_a_decode(view):
    g = Guard(view.guard_config())
    j = view.linked[0]
    for payload in (view.payload(j), b"junk"):   # the verdict does not depend on the bytes: never decoded
        assert admit(g, None, payload, view.tick) is None
    assert g.counters.rejected == {"key": 2}


def test_a_good_message_passes_bit_for_bit(view):
    g = Guard(view.guard_config())
    for j in view.linked:
        wm = admit(g, j, view.payload(j), view.tick)
        assert (wm.sender, wm.tick, wm.run_id) == (j, view.tick, view.run_id)
        for f in Message.ARRAY_FIELDS:
            assert np.array_equal(getattr(wm.message, f), getattr(view.messages[j], f))
            assert getattr(wm.message, f).tobytes() == np.ascontiguousarray(getattr(view.messages[j], f)).tobytes()
    assert g.counters.rejected == {}


def test_own_messages_are_ignored_silently(view):
    g = Guard(view.guard_config())
    assert admit(g, view.me, view.payload(view.me), view.tick) is None
    assert g.counters == Counters()


def test_ticks_inside_the_window_pass(view):
    g = Guard(view.guard_config(max_lag=3, max_lead=2))
    j = view.linked[0]
    ok = [view.tick - 3, view.tick, view.tick + 2]
    assert all(admit(g, j, view.payload(j, tick=t), view.tick) for t in ok)
    bad = [view.tick - 4, view.tick + 3]
    assert not any(admit(g, j, view.payload(j, tick=t), view.tick) for t in bad)


def test_logged_once_per_sender_and_reason(view, caplog):
    g = Guard(view.guard_config())
    j, k = view.linked[:2]
    with caplog.at_level(logging.WARNING, logger="diskf_mesh.mesh.protocol.guard"):
        for _ in range(5):
            admit(g, j, b"junk", view.tick)
            admit(g, k, b"junk", view.tick)
            admit(g, j, view.payload(j, tick=0), view.tick)
    assert len(caplog.records) == 3
    assert g.by_sender[(j, "not-msgpack")] == 5 and g.by_sender[(k, "not-msgpack")] == 5
    assert g.by_sender[(j, "tick-past")] == 5
    assert g.counters.rejected == {"not-msgpack": 10, "tick-past": 5}
    assert all(f"agent {view.me}" in r.getMessage() for r in caplog.records)


def test_guard_never_raises_even_on_non_bytes(view):
    g = Guard(view.guard_config())
    for payload in (None, 12, "text", [b"x"], object()):
        assert admit(g, view.linked[0], payload, view.tick) is None
    assert "error" not in g.counters.rejected


def test_the_factory_fuses_as_the_engine_does(view):
    """The batch-of-one fusion of the factory equals the in-process engine's."""
    from diskf_mesh.engine import batch as engine
    from diskf_mesh.data.scenario import load_scenario, simulate
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


# --------------------------------------------------------------------------
# resources under hostile input: bytes in, verdict and counts out
# --------------------------------------------------------------------------
def test_unknown_sender_ids_share_one_row_and_are_never_decoded(view, caplog):
    g = Guard(view.guard_config())
    ids = [int(i) for i in np.random.default_rng(1).integers(100, 2 ** 62, 10_000)]
    with caplog.at_level(logging.WARNING, logger="diskf_mesh.mesh.protocol.guard"):
        for i in ids:  # garbage: were it decoded, the reason would be "not-msgpack"
            assert admit(g, i, b"\xc1" * 300, view.tick) is None
    assert g.counters.rejected == {"unknown-sender": 10_000}
    assert dict(g.by_sender) == {(None, "unknown-sender"): 10_000}
    assert len(caplog.records) == 1


def test_oversized_payloads_are_refused_before_decoding(view):
    g = Guard(view.guard_config())
    j = view.linked[0]
    doc = doc_of(view, j)
    big_map = msgpack.packb({str(i): 0 for i in range(130_000)})   # ~0.9 MB, under wire.MAX_BYTES
    cases = [big_map, b"\x00" * (1 << 20), pack({**doc, "pad": b"x" * 400}),   # bytes over the schema's
             pack({**doc, **{f"x{i}": 0 for i in range(3)}}),                    # more fields than the schema's
             pack({**doc, "run": "r" * 65}),                                      # a string over MAX_STR
             pack({**doc, "a": doc["a"] + b"\x00" * 8})]                          # a bin over the schema's
    assert len(big_map) < wire.MAX_BYTES
    for payload in cases:
        assert admit(g, j, payload, view.tick) is None
    assert g.counters.rejected == {"size": len(cases)}


def test_a_poisoned_neighbour_is_accounted_for_and_never_fused(view):
    import time
    j, *rest = view.linked
    d = doc_of(view, j)
    blob = np.frombuffer(d["a"], dtype="<f8").copy()
    blob[0] = np.nan
    poisoned = pack({**d, "a": blob.tobytes()})
    rx = Receiver(Guard(view.guard_config()))
    rx.advance(view.tick)
    rx.on_payload(j, poisoned)
    rx.on_payload(j, pack({**d, "a": blob.tobytes(), "t": view.tick + 7}))   # outside the window: accounts nothing
    for i in rest:
        rx.on_payload(i, view.payload(i))
    t0 = time.monotonic()
    assert wait_accounted(rx, view.tick, view.linked, t0 + 30.0) >= set(view.linked)
    assert time.monotonic() - t0 < 1.0                      # no collect timeout for the poisoned one
    assert rx.accounted(view.tick + 7) == set()
    assert rx.refusals(view.tick) == {j: "non-finite"}      # what the report's verdicts say of it
    rx.on_payload(j, pack({**d, "s": rest[0]}))              # another agent's body on j's key: accounts nothing
    assert rx.refusals(view.tick) == {j: "non-finite"}
    got = rx.take(view.tick, view.linked)
    assert [s for s, _ in got] == sorted(rest)
    _, out = view.fuse(got)
    _, ref = view.fuse([(i, view.messages[i]) for i in rest])
    assert out.x.tobytes() == ref.x.tobytes() and out.P.tobytes() == ref.P.tobytes()
    c = rx.close()
    assert c.rejected == {"non-finite": 2, "sender": 1} and c.fused == len(rest) and c.imbalance() == []


def test_what_waits_is_bounded_by_the_window_and_the_scenario(view):
    """Copies of every agent's message for ticks 1..20, 50 times over, before
    tick 1: the inbox holds one per sender and tick of the window."""
    cfg = view.guard_config()
    rx = Receiver(Guard(cfg))
    rx.advance(1)
    payloads = {(j, t): view.payload(j, tick=t) for j in view.ids for t in range(1, 21)}
    for _ in range(50):
        for (j, t), payload in payloads.items():
            rx.on_payload(j, payload)
    others = len(view.ids) - 1
    assert rx.inbox.pending == others * (1 + cfg.max_lead)
    c = rx.counters
    assert c.rejected == {"tick-future": 50 * others * (20 - 1 - cfg.max_lead)}
    assert c.duplicate == 49 * others * (1 + cfg.max_lead)
    for t in range(1, 200):  # a long run: what the inbox remembers stays within the window
        rx.advance(t)
        rx.take(t, view.linked)
    for book in (rx.inbox._also, rx.inbox._taken, rx.inbox._held):
        assert len(book) <= cfg.max_lag + cfg.max_lead + 1


def test_what_waits_for_the_worlds_tick_is_bounded_and_gated_on_release(view):
    """The same flood before the world's tick 1 is in (no links known): one
    copy per sender and tick of the window waits, before any link; the
    world's tick lets the linked ones on, the others are out of range."""
    cfg = view.guard_config()
    rx = Receiver(Guard(cfg))
    rx.advance(1)
    links = {}
    for _ in range(50):
        for j in view.ids:
            for t in range(1, 21):
                rx.on_payload(j, view.payload(j, tick=t), links)
    others = len(view.ids) - 1
    assert sum(map(len, rx.inbox._early.values())) == others * (1 + cfg.max_lead)
    c = rx.counters
    assert c.sent == c.duplicate == 49 * others * (1 + cfg.max_lead) and c.fused == c.pending == 0
    rx.release(1, view.linked)
    assert c.out_of_range == others - len(view.linked)
    assert [s for s, _ in rx.take(1, view.linked)] == sorted(view.linked)
    rx.advance(10)                          # ticks the agent skipped: never on a link
    assert rx.inbox._early == {} and c.out_of_range == others - len(view.linked) + 2 * others
    assert rx.close().imbalance() == []


# --------------------------------------------------------------------------
# the world's messages at an agent (agents.agent), fed bytes on a LocalBus
# --------------------------------------------------------------------------
class FedAgent:
    """An agent's machine (``mesh.protocol.agent_machine``) of Scenario 2 working on
    tick ``k`` (ticks before it fed as the world and its neighbours send
    them), for tests of what it takes from the world."""

    K = 30

    def __init__(self, k: int = 5):
        from diskf_mesh.estimators import get
        from diskf_mesh.mesh.protocol.agent_machine import AgentMachine
        from diskf_mesh.mesh.protocol.estimator import lockstep
        from diskf_mesh.mesh.protocol.events import AskTokens, Token, Tokens
        from diskf_mesh.mesh.wire.keys import Keys
        from diskf_mesh.data.scenario import load_scenario, simulate
        self.scn = scn = load_scenario("dynamic")
        self.trace = simulate(scn, [0], steps=self.K)
        self.ids = [a.id for a in scn.agents]
        self.me = self.ids[4]
        self.keys = Keys("fed")
        self.agent = AgentMachine(scn, self.me, get("diskf"), self.keys, "n0")
        self.agent.start(0.0)
        ask, = [e for e in self.agent.handle(Token(self.keys.world("w"), True), 0.0) if isinstance(e, AskTokens)]
        self.agent.handle(Tokens(ask.qid, ()), 0.0)
        for i in self.ids:
            self.token(self.keys.alive(i, "n0" if i == self.me else f"n{i}"))
        self.msgs = {t: m for t, m, _ in lockstep(scn, "diskf", self.trace)}
        for t in range(1, k):
            self.world(t)
            self.neighbours(t)
        assert self.agent.k == k and not self.agent.collecting

    def sample(self, key: str, payload: bytes) -> None:
        at_once(self.agent, self.agent.read(key, payload), 0.0)

    def token(self, key: str, up: bool = True) -> None:
        from diskf_mesh.mesh.protocol.events import Token
        at_once(self.agent, Token(key, up), 0.0)

    def tick(self, t: int, **change) -> bytes:
        tick = wire.Tick("fed", t, self.K, 0, "diskf", self.scn.topology, self.scn.comm_range,
                         self.trace.positions[min(t, self.K) - 1], tuple(self.ids))
        return wire.encode_tick(wire.Tick(**{**tick.__dict__, **change}))

    def meas(self, t: int, y=None) -> bytes:
        j = self.ids.index(self.me)
        y = self.trace.y[0, min(t, self.K) - 1, j, :1] if y is None else y
        return wire.encode_measurement("fed", t, self.me, True, y)

    def world(self, t: int) -> None:
        self.sample(self.keys.meas(self.me), self.meas(t))
        self.sample(self.keys.tick, self.tick(t))

    def neighbours(self, t: int) -> None:
        from diskf_mesh.mesh.protocol.estimator import neighbours
        for o in neighbours(self.scn, self.me, self.trace.positions[t - 1]):
            if o != self.me:
                self.sample(self.keys.msg(o, to=[self.me]), wire.encode("fed", o, t, self.msgs[t][o]))


def test_an_agent_takes_world_ticks_only_for_k_and_k1_with_the_run_constants():
    fed = FedAgent(k=5)
    a = fed.agent
    sample = lambda b: fed.sample(fed.keys.tick, b)  # noqa: E731
    for t in range(7, 1007):                  # far-future ticks (within and beyond the run)
        sample(fed.tick(t))
    sample(fed.tick(6, seed=1))               # k + 1 with another seed, algorithm, topology, range, K
    sample(fed.tick(6, algorithm="kcf"))
    sample(fed.tick(6, topology="all"))
    sample(fed.tick(6, comm_range=1e9))
    sample(fed.tick(6, ticks=10 ** 6))
    assert a.ticks == {} and set(a.linked) <= set(range(1, 5))
    assert a.counters.rejected == {"tick-future": 1000, "constants": 5}
    sample(fed.tick(5))                       # k and k + 1 as the world sends them: taken
    sample(fed.tick(6))
    assert set(a.ticks) == {5, 6}


def test_an_agent_takes_measurements_only_for_k_and_k1_of_its_length_within_max_abs():
    fed = FedAgent(k=5)
    a = fed.agent
    sample = lambda b: fed.sample(fed.keys.meas(fed.me), b)  # noqa: E731
    for t in range(7, 507):
        sample(fed.meas(t))
    sample(fed.meas(5, y=[1e300]))
    sample(fed.meas(5, y=[-2e15]))
    sample(fed.meas(5, y=[1.0, 2.0]))         # two values for a sensor of one
    sample(fed.meas(5, y=[np.nan]))
    assert a.meas == {}
    assert a.counters.rejected == {"tick-future": 500, "magnitude": 2, "size": 1, "non-finite": 1}
    sample(fed.meas(5))
    sample(fed.meas(6))
    assert set(a.meas) == {5, 6}


def test_an_agent_keeps_only_the_scenarios_agents_and_bounded_tables():
    fed = FedAgent(k=3)
    a = fed.agent
    for i in range(1000, 3000):
        fed.token(fed.keys.alive(i))
        fed.sample(fed.keys.msg(i, to=[fed.me]), b"\xc1" * 100)
    assert a.alive.complete and a.alive.size == len(fed.ids)  # the unknown ids are not counted
    assert a.counters.rejected == {"unknown-sender": 2000}
    assert dict(a.receiver.guard.by_sender) == {(None, "unknown-sender"): 2000}
    assert len(a.log._said) == 0              # the guard logs it, once (its own logger)


def test_a_copy_of_another_agents_message_accounts_for_nothing(view):
    """A body naming another agent on j's key (a replay on a credentialed
    agent's own key) is refused and does not stand in for j's message."""
    j, other, *_ = view.linked
    rx = Receiver(Guard(view.guard_config()))
    rx.advance(view.tick)
    rx.on_payload(j, pack({**doc_of(view, j), "s": other}))
    assert j not in rx.accounted(view.tick) and rx.refusals(view.tick) == {}
    assert rx.counters.rejected == {"sender": 1}


def test_model_probabilities_that_are_not_probabilities_are_refused():
    """diskf-auto's w (``Exchanged.weights``): each value in [0, 1], summing
    to 1; what passes is decoded bit for bit."""
    from dataclasses import replace

    from diskf_mesh.core.input_models import BANK
    v = tick_view("diskf-auto", tick=30)
    ex = v.alg.exchanged
    g = Guard(v.guard_config(exchanged=ex))
    j = v.linked[0]
    good = v.messages[j]
    M = len(good.w)
    assert good.w.shape == (len(BANK),) and abs(good.w.sum() - 1.0) < 1e-12
    wm = admit(g, j, wire.encode(v.run_id, j, v.tick, good, ex), v.tick)
    assert wm is not None and wm.message.w.tobytes() == good.w.tobytes()
    one_model = np.eye(M)[0]  # a sender sure of one model is a probability vector
    assert admit(g, j, wire.encode(v.run_id, j, v.tick, replace(good, w=one_model), ex), v.tick) is not None
    for w in (2.0 * good.w, 0.5 * good.w, np.full(M, 0.2), np.r_[1.5, -0.5, np.zeros(M - 2)]):  # the last sums to 1
        assert admit(g, j, wire.encode(v.run_id, j, v.tick, replace(good, w=w), ex), v.tick) is None, w
    assert g.counters.rejected == {"weights": 4}
