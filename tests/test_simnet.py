"""The simulated network on small machines: routing, links, leases, pauses,
crashes, restarts, queries, access rules, and one run per seed."""
from __future__ import annotations

import os
import subprocess
import sys

import pytest
from hypothesis import given, settings, strategies as st

from diskf_mesh.mesh.security import credentials
from diskf_mesh.mesh.protocol import events as ev
from diskf_mesh.mesh.wire.keys import key_matches
from diskf_mesh.mesh.simulated.simnet import Fault, Lease, Link, SimNet


class Pong:
    """Answers every ping with a pong of the same number; declares a token; answers queries."""

    read = ev.Sample  # takes its samples as they are

    def __init__(self, boot):
        self.boot = boot
        self.events = []

    def start(self, now):
        return [ev.Subscribe("t/ping"), ev.DeclareQueryable("t/ask/*"),
                ev.DeclareToken(f"t/alive/pong/{self.boot.nonce}")]

    def handle(self, e, now):
        self.events.append((now, e))
        if isinstance(e, ev.Sample):
            return [ev.Publish("t/pong", e.payload)]
        if isinstance(e, ev.Query):
            return [ev.Answer(e.qid, b"answer:" + e.payload)]
        return []


class Ping:
    """Sends pings 1..n once it sees a pong token, one at a time, again after
    ``retry`` s without an answer; finishes at n, or after ``give_up`` s."""

    read = ev.Sample  # takes its samples as they are

    def __init__(self, boot, n=5, retry=1.0, give_up=60.0):
        self.boot, self.n, self.retry, self.give_up = boot, n, retry, give_up
        self.at = 0
        self.tokens = []   # (now, key, up)
        self.pongs = []

    def start(self, now):
        return [ev.Subscribe("t/pong"), ev.WatchTokens("t/alive/**"), ev.SetTimer("give-up", now + self.give_up)]

    def _ping(self, now):
        return [ev.Publish("t/ping", str(self.at).encode()), ev.SetTimer("retry", now + self.retry)]

    def handle(self, e, now):
        if isinstance(e, ev.Token):
            self.tokens.append((now, e.key, e.up))
            if e.up and self.at == 0:
                self.at = 1
                return self._ping(now)
        elif isinstance(e, ev.Sample):
            got = int(e.payload)
            self.pongs.append((now, got))
            if got == self.at:
                if got == self.n:
                    return [ev.Finish("done", 0)]
                self.at += 1
                return self._ping(now)
        elif isinstance(e, ev.Timer):
            if e.name == "give-up":
                return [ev.Finish("gave up", 1)]
            return self._ping(now)
        return []


def ping_pong(seed=1, link=Link(), faults=(), lease=Lease(), pong_at=0.0, **ping):
    net = SimNet(seed, link=link, lease=lease, keep_lines=True, max_time=200.0)
    net.add("pong", Pong, at=pong_at)
    net.add("ping", lambda b: Ping(b, **ping))
    net.plan(faults)
    return net, net.run()


def test_ping_pong_runs_to_its_end_in_virtual_time():
    net, out = ping_pong(link=Link(delay=0.01), n=5)
    assert out.finishes["ping"] == ev.Finish("done", 0)
    ping = out.machines["ping"]
    assert [n for _, n in ping.pongs] == [1, 2, 3, 4, 5]
    # the token came 0.01 s after both started, then 5 round trips of 0.02 s
    assert out.end == pytest.approx(0.01 + 5 * 0.02)
    assert "pong" not in out.finishes  # it never finishes; the run ends with the last process that does not wait
    assert not out.bounded


def test_one_seed_one_run_event_for_event():
    link = Link(delay=0.001, jitter=0.004, loss=0.2, duplicate=0.2, reorder=0.2, hold=0.003)
    runs = [ping_pong(seed, link=link, n=30)[1] for seed in (7, 7, 8)]
    assert runs[0].digest == runs[1].digest and runs[0].lines == runs[1].lines
    assert runs[0].digest != runs[2].digest
    assert runs[0].finishes["ping"].status == "done"  # retries got through the losses
    assert runs[0].lost > 0


def test_a_run_does_not_depend_on_the_hash_seed():
    code = ("import sys; sys.path.insert(0, 'tests'); from test_simnet import ping_pong; from diskf_mesh.mesh.simulated.simnet import Link;"
            "print(ping_pong(3, link=Link(delay=0.001, jitter=0.01, loss=0.3, duplicate=0.3, reorder=0.3), "
            "n=20)[1].digest)")
    digests = {subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                              env={**os.environ, "PYTHONHASHSEED": h}, cwd=os.path.dirname(os.path.dirname(
                                  os.path.abspath(__file__)))).stdout for h in ("1", "2")}
    assert len(digests) == 1


def test_links_keep_order_unless_a_copy_is_held_back():
    in_order = ping_pong(2, link=Link(delay=0.001, jitter=0.05), n=1)[0]
    # 200 samples on one link with a large jitter: FIFO keeps them in order
    got = _burst(in_order.__class__, Link(delay=0.001, jitter=0.05))
    assert got == sorted(got)
    held = _burst(in_order.__class__, Link(delay=0.001, jitter=0.0, reorder=0.3, hold=0.01))
    assert held != sorted(held) and sorted(held) == list(range(200))
    dup = _burst(in_order.__class__, Link(delay=0.001, duplicate=0.5))
    assert len(dup) > 200 and sorted(set(dup)) == list(range(200))


class Burst:
    read = ev.Sample  # takes its samples as they are

    def __init__(self, boot):
        pass

    def start(self, now):
        return [ev.Publish("t/b", str(i).encode()) for i in range(200)]

    def handle(self, e, now):
        return []


class Sink:
    read = ev.Sample  # takes its samples as they are

    def __init__(self, boot):
        self.got = []

    def start(self, now):
        return [ev.Subscribe("t/*")]

    def handle(self, e, now):
        self.got.append(int(e.payload))
        return []


def _burst(cls, link):
    net = cls(5, link=link)
    net.add("sink", Sink)
    net.add("burst", Burst, at=0.001)
    return net.run().machines["sink"].got


def test_a_pause_shorter_than_the_lease_keeps_the_tokens_and_queues_what_came():
    faults = [Fault("pause", "pong", at=0.05, duration=5.0)]
    net, out = ping_pong(link=Link(delay=0.01), faults=faults, n=3, retry=2.0)
    pong, ping = out.machines["pong"], out.machines["ping"]
    assert [up for _, _, up in ping.tokens] == [True]
    woke = [(t, e) for t, e in pong.events if isinstance(e, ev.Woke)]
    assert woke == [(pytest.approx(5.05), ev.Woke(pytest.approx(5.0)))]
    # what came while it slept is handled right after it woke, in order
    after = [e for t, e in pong.events if t == pytest.approx(5.05) and isinstance(e, ev.Sample)]
    assert len(after) >= 2
    assert out.finishes["ping"].status == "done"


def test_a_pause_past_the_lease_drops_the_session_both_ways_and_reconnects():
    lease = Lease(lease=10.0, keepalive=0.0, reconnect=0.5)
    faults = [Fault("pause", "pong", at=0.025, duration=15.0)]
    net, out = ping_pong(link=Link(delay=0.01), faults=faults, lease=lease, n=3, retry=3.0)
    ping, pong = out.machines["ping"], out.machines["pong"]
    key = f"t/alive/pong/{pong.boot.nonce}"
    # gone at the lease (pause + 10 s), back after the wake-up and the reconnection
    assert ping.tokens == [(pytest.approx(0.01), key, True), (pytest.approx(10.035), key, False),
                           (pytest.approx(15.535), key, True)]
    # ping 2 and its retries until the lease ran out wait for the wake-up; the pongs it sends
    # before it reconnects, and the pings of 12.03 and 15.03, are lost; the retry of 18.03 goes through
    samples = [(round(t, 3), int(e.payload)) for t, e in pong.events if isinstance(e, ev.Sample)]
    assert samples == [(0.02, 1), (15.025, 2), (15.025, 2), (15.025, 2), (15.025, 2), (18.04, 2), (18.06, 3)]
    assert out.finishes["ping"].status == "done" and out.end == pytest.approx(18.07)


def test_a_crash_drops_tokens_at_once_or_after_the_lease_and_a_restart_is_a_new_nonce():
    for lease_crash, gone_at in ((False, 2.01), (True, 12.01)):
        faults = [Fault("crash", "pong", at=2.0, lease=lease_crash), Fault("restart", "pong", at=20.0)]
        net, out = ping_pong(link=Link(delay=0.01), faults=faults, n=10 ** 6, retry=100.0, give_up=30.0)
        ping = out.machines["ping"]
        (t0, k0, up0), (t1, k1, up1), (t2, k2, up2) = ping.tokens
        assert (up0, up1, up2) == (True, False, True)
        assert k0 == k1 != k2 and t1 == pytest.approx(gone_at) and t2 == pytest.approx(20.01)
        assert out.machines["pong"].boot.incarnation == 1


def test_a_query_gets_the_first_answer_or_none():
    class Asker:
        read = ev.Sample  # takes its samples as they are

        def __init__(self, boot):
            self.replies = []

        def start(self, now):
            return [ev.Ask(1, "t/ask/x", b"q", 1.0), ev.Ask(2, "t/nobody", b"q", 1.0), ev.SetTimer("t", now + 0.5)]

        def handle(self, e, now):
            if isinstance(e, ev.Reply):
                self.replies.append((now, e))
            if isinstance(e, ev.Timer):
                return [ev.Ask(3, "t/ask/y", b"late", 1.0)]
            return []

    net = SimNet(0, link=Link(delay=0.01))
    net.add("pong", Pong)
    net.add("twin", Pong)
    net.add("asker", Asker, at=0.1)
    net.plan([Fault("pause", "pong", at=0.3, duration=10.0), Fault("pause", "twin", at=0.3, duration=10.0)])
    out = net.run()
    assert out.machines["asker"].replies == [
        (pytest.approx(0.12), ev.Reply(1, b"answer:q")), (pytest.approx(0.12), ev.Reply(2, None)),
        (pytest.approx(1.6), ev.Reply(3, None))]


def test_the_access_rules_of_the_credentials_hold():
    policy = credentials.access_control("r", [1, 2], observer=False, router=False)

    class Agent:
        read = ev.Sample  # takes its samples as they are

        def __init__(self, boot):
            self.id = int(boot.identity.split("-")[1])
            self.got = []

        def start(self, now):
            other = 3 - self.id
            return [ev.Subscribe(f"diskf/r/agent/*/msg/$*_{self.id}_$*"),
                    ev.Subscribe(f"diskf/r/world/meas/{other}"),        # another's measurement: refused
                    ev.DeclareToken(f"diskf/r/alive/agent/{other}/x"),  # another's token: refused
                    ev.SetTimer("go", now + 0.1)]

        def handle(self, e, now):
            if isinstance(e, ev.Sample):
                self.got.append(e.key)
            if isinstance(e, ev.Timer):
                other = 3 - self.id
                return [ev.Publish(f"diskf/r/agent/{self.id}/msg/_{other}_", b"mine"),
                        ev.Publish(f"diskf/r/agent/{other}/msg/_{other}_", b"forged")]  # refused
            return []

    class World:
        read = ev.Sample  # takes its samples as they are

        def __init__(self, boot):
            pass

        def start(self, now):
            return [ev.Publish("diskf/r/world/meas/1", b"m1"), ev.Publish("diskf/r/world/meas/2", b"m2")]

        def handle(self, e, now):
            return []

    net = SimNet(0, policy=policy)
    net.add("agent-1", Agent)
    net.add("agent-2", Agent)
    net.add("twin", Agent, identity="agent-2")  # a second process with agent 2's identity hears as agent 2
    net.add("world", World, at=0.01)
    out = net.run()
    assert out.machines["agent-1"].got == ["diskf/r/agent/2/msg/_1_"] * 2  # agent 2 and its twin
    assert out.machines["agent-2"].got == out.machines["twin"].got == ["diskf/r/agent/1/msg/_2_"]
    # each forgery refused at every receiver it was bound for
    assert out.refused == {"declare_subscriber": 3, "liveliness_token": 3, "put": 4}


def test_a_subscription_reaches_only_the_keys_the_receivers_rules_let_it_receive():
    """A process whose rules let it subscribe to everything but receive only
    the world's keys: a put its subscription matches on another key is
    refused at it, whichever expression its subscription is."""
    rule = lambda rid, messages, keys, flows=("ingress",): {  # noqa: E731
        "id": rid, "permission": "allow", "flows": list(flows), "messages": list(messages), "key_exprs": keys}
    policy = {"enabled": True, "default_permission": "deny",
              "rules": [rule("sub", ["declare_subscriber"], ["diskf/r/**"]),
                        rule("recv", ["put"], ["diskf/r/world/**"], ("egress",)),
                        rule("speak", ["put"], ["diskf/r/**"])],
              "subjects": [{"id": s, "cert_common_names": [s]} for s in ("listener", "speaker")],
              "policies": [{"id": "l", "subjects": ["listener"], "rules": ["sub", "recv"]},
                           {"id": "s", "subjects": ["speaker"], "rules": ["speak"]}]}

    class Listener:
        read = ev.Sample

        def __init__(self, boot):
            self.got = []

        def start(self, now):
            return [ev.Subscribe("diskf/r/**"), ev.Subscribe("diskf/r/agent/*/msg/$*_2_$*")]

        def handle(self, e, now):
            self.got.append(e.key)
            return []

    class Speaker:
        read = ev.Sample

        def __init__(self, boot):
            pass

        def start(self, now):
            return [ev.SetTimer("go", now + 0.1)]

        def handle(self, e, now):
            return [ev.Publish("diskf/r/agent/1/msg/_2_", b"m"), ev.Publish("diskf/r/world/tick", b"t")]

    net = SimNet(0, policy=policy)
    net.add("listener", Listener, identity="listener")
    net.add("speaker", Speaker, identity="speaker")
    out = net.run()
    assert out.machines["listener"].got == ["diskf/r/world/tick"]  # once: one subscription matches it
    assert out.refused == {"put": 2}  # the message, at each of its two matching subscriptions


def test_a_machine_that_raises_names_the_seed():
    class Bad(Pong):
        def handle(self, e, now):
            raise ValueError("boom")

    net = SimNet(1234)
    net.add("pong", Bad)
    net.add("ping", Ping)
    with pytest.raises(Exception, match="seed 1234"):
        net.run()


chunk = st.sampled_from(["a", "b", "ab", "_1_", "_1_2_"])
pattern = st.sampled_from(["a", "b", "*", "**", "$*b", "a$*", "$*_1_$*", "$*"])


@settings(max_examples=300, deadline=None)
@given(st.lists(pattern, min_size=1, max_size=4), st.lists(chunk, min_size=1, max_size=4))
def test_key_matching_is_zenohs(expr, key):
    """The one key-expression matcher (the simulated network's routes, its
    access rules, the in-process bus) includes a key exactly where zenoh does."""
    import zenoh
    e, k = "/".join(expr), "/".join(key)
    try:
        ke = zenoh.KeyExpr.autocanonize(e)
    except Exception:  # not a key expression zenoh accepts
        return
    assert key_matches(e, k) == ke.includes(zenoh.KeyExpr(k))


def test_an_honest_agent_that_never_measures_is_carried_by_the_mesh():
    """The held-out case with the largest honest estimates: isolated agents
    tracking a constant-velocity target, ``diskf-r`` (covariance up to 8e12,
    condition 4.5e13 by tick 200). Every message and report is within what a
    message may carry (``wire.MAX_ABS``, ``wire.MAX_COND``): the run is
    exact. With the bounds at 1e12 and 1e10, 704 of its 1,200 agent-ticks
    were refused."""
    import numpy as np

    from diskf_mesh.data.scenario import simulate
    from diskf_mesh.engine import batch as engine
    from diskf_mesh.mesh.wire import codec as wire
    from diskf_mesh.mesh.simulated.simrun import simulate_run
    from diskf_mesh.studies import heldout

    case, = [c for c in heldout.cases() if c.label == "CV none, zero"]
    trace = simulate(case.scenario, [0])
    est = engine.run(trace, "diskf-r", case.scenario.params)
    w = np.linalg.eigvalsh(est.P)
    assert np.abs(est.P).max() > 1e12 and (w[..., -1] / w[..., 0]).max() > 1e10  # beyond the former bounds
    assert np.abs(est.P).max() <= wire.MAX_ABS
    run = simulate_run(case.scenario, trace, "diskf-r", 0)
    assert run.status.status == "exact", run.status


def test_an_agent_whose_estimator_diverges_leaves_at_once_with_its_reason():
    """C-DRKF on Scenario 1 with isolated agents diverges (the input is not
    strongly detectable from an x sensor): agent 1's covariance passes the
    condition number a report may carry at tick 530, agent 3's at tick 671,
    and the engine's own batch fails at tick 633. Each agent ends there
    with exit 3 (``exits.STOPPED``) and the reason, instead of reporting what the world refuses
    and holding every later tick for ``tick_timeout`` (10 virtual seconds
    a tick) or raising; the world's check replays the ticks before the
    engine's failure and says the rest is not verified."""
    from diskf_mesh.data.scenario import load_scenario, simulate
    from diskf_mesh.mesh.simulated.simrun import simulate_run

    scn = load_scenario("quadrants").with_overrides(topology="none", steps=700)
    trace = simulate(scn, [0])
    run = simulate_run(scn, trace, "cdrkf", 0)
    fin = run.outcome.finishes
    assert {p: (f.code, f.status) for p, f in fin.items()} == {
        "world": (0, "done"), "agent-1": (3, "diverged"), "agent-2": (0, "done"), "agent-3": (3, "diverged"),
        "agent-4": (0, "done")}
    assert "diverged at tick 530" in fin["agent-1"].reason and "ill-conditioned" in fin["agent-1"].reason
    assert "diverged at tick 671" in fin["agent-3"].reason
    rec = run.record
    assert rec.reported[:529].all() and not rec.reported[529:, 0].any() and not rec.reported[670:, 2].any()
    assert rec.reported[:, [1, 3]].all()
    assert run.outcome.end < 10.0  # no tick waited for a report that would be refused
    st = run.status
    assert st.status == "incomplete" and st.evidence["differing"] == 0, st.reason
    ended = st.evidence["replay_ended"]
    assert ended["tick"] == 633 and ended["reported_after"] == int(rec.reported[632:].sum()) > 0


def test_routes_find_addressed_subscriptions_as_a_scan_would():
    """An agent's subscription to the messages addressed to it
    (``.../msg/$*_<id>_$*``) is found by the key's address pieces; the
    answer is the one matching every expression gives."""
    from diskf_mesh.mesh.simulated.simnet import _Routes
    from diskf_mesh.mesh.wire.keys import Keys, key_matches

    class P:
        def __init__(self, order):
            self.order = order

    k, routes = Keys("r"), _Routes()
    procs = [P(i) for i in range(12)]
    exprs = [(p, k.msg_to(p.order)) for p in procs] + [(procs[3], k.msgs), (procs[4], f"{k.root}/agent/*/msg/$*_1$*"),
                                                      (procs[6], k.msg_to(6)), (procs[7], k.report(1))]  # twice: twice
    for p, e in exprs:
        routes.add(e, p)
    routes.remove(procs[5])
    for to in ([], [1], [3, 5, 11], [0, 10, 2], [1, 1], [12], [6]):
        for key in (k.msg(7, to=to), k.msg(7, to=to) + "x", k.report(1)):
            want = sorted((p.order, e) for p, e in exprs if p is not procs[5] and key_matches(e, key))
            assert sorted((p.order, e) for p, e in routes.match(key)) == want, key
