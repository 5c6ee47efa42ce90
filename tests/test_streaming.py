"""The streaming API (``diskf_mesh.Network``, ``diskf_mesh.Agent``): one tick
at a time, it gives what the batched engine gives on the same data, bit for
bit, at both levels, on a moving network."""
from __future__ import annotations

import numpy as np
import pytest

import diskf_mesh
from diskf_mesh import InputError

TICKS = 60
SEED = 3
# the default; DISKF itself; the robust variant; a baseline with per-tick draws (gossip); a consensus baseline
ESTIMATORS = ["diskf-auto", "diskf", "diskf-r", "gdkf", "kcf"]


@pytest.fixture(scope="module")
def moving():
    """Scenario 2 (agents move, links change with range) and a trace of it."""
    scn = diskf_mesh.load_scenario("dynamic")
    trace = diskf_mesh.simulate(scn, seeds=[SEED], steps=TICKS)
    assert (trace.links[0, 1:] != trace.links[0, :-1]).any()  # the topology changes
    return scn, trace


def rows(trace, k: int, p) -> list:
    """Tick k's measurements as the agents have them: their p values or None."""
    return [trace.y[0, k, i, :p[i]] if trace.has[0, k, i] else None for i in range(len(p))]


@pytest.mark.parametrize("name", ESTIMATORS)
def test_a_network_fed_tick_by_tick_equals_the_engine(moving, name):
    scn, trace = moving
    ref = diskf_mesh.estimate(trace, name, scenario=scn)
    net = diskf_mesh.Network(scn, name, seed=SEED, ticks=TICKS)
    got = [net.step(rows(trace, k, net.sensors.p), links=trace.links[0, k]) for k in range(TICKS)]
    assert [e.tick for e in got] == list(range(1, TICKS + 1)) and net.tick == TICKS
    for field in ("x", "P", "d", "d_valid"):
        np.testing.assert_array_equal(np.array([getattr(e, field) for e in got]), getattr(ref, field)[0])


def test_a_network_without_links_uses_the_scenarios_own(moving):
    """No links given: the scenario's range gating of its agents' positions
    at that tick, as ``simulate`` makes them; padded rows and ``has``."""
    scn, trace = moving
    ref = diskf_mesh.estimate(trace, "diskf-auto", scenario=scn)
    net = diskf_mesh.Network(scn, seed=SEED, ticks=TICKS)
    x = [net.step(trace.y[0, k], has=trace.has[0, k]).x for k in range(TICKS)]
    np.testing.assert_array_equal(np.array(x), ref.x[0])
    net = diskf_mesh.Network(scn, seed=SEED, ticks=TICKS)
    x = [net.step(rows(trace, k, net.sensors.p), positions=trace.positions[k]).x for k in range(TICKS)]
    np.testing.assert_array_equal(np.array(x), ref.x[0])


@pytest.mark.parametrize("name, as_bytes", [("diskf-auto", True), ("diskf", False), ("gdkf", True)])
def test_agents_carrying_their_own_messages_equal_the_engine(moving, name, as_bytes):
    scn, trace = moving
    ref = diskf_mesh.estimate(trace, name, scenario=scn)
    ids = [a.id for a in scn.agents]
    agents = {i: diskf_mesh.Agent(scn, i, name, seed=SEED, ticks=TICKS) for i in ids}
    p = scn.sensors().p
    x, P = np.zeros(ref.x[0].shape), np.zeros(ref.P[0].shape)
    for k in range(TICKS):
        y = rows(trace, k, p)
        sent = {i: agents[i].local(y[n]) for n, i in enumerate(ids)}
        if as_bytes:
            sent = {i: agents[i].encode(m) for i, m in sent.items()}
            assert all(isinstance(b, bytes) for b in sent.values())
        for n, i in enumerate(ids):
            heard = {j: sent[j] for m, j in enumerate(ids) if trace.links[0, k, n, m] and j != i}
            est = agents[i].fuse(heard)
            assert est.tick == k + 1 and est.x.shape == (2,) and isinstance(est.d_valid, bool)
            x[k, n], P[k, n] = est.x, est.P
    np.testing.assert_array_equal(x, ref.x[0])
    np.testing.assert_array_equal(P, ref.P[0])


def test_estimates_are_read_only(moving):
    scn, trace = moving
    est = diskf_mesh.Network(scn).step(rows(trace, 0, scn.sensors().p))
    with pytest.raises(ValueError):
        est.x[0, 0] = 1.0
    agent = diskf_mesh.Agent(scn, 1)
    agent.local(None)
    with pytest.raises(ValueError):
        agent.fuse({}).P[0, 0] = 1.0


def test_bad_input_names_the_field(moving):
    scn, _ = moving
    net = diskf_mesh.Network(scn, ticks=1)
    with pytest.raises(InputError, match=r"^y: one row per agent: 9 rows, got 2"):
        net.step([[1.0], [2.0]])
    with pytest.raises(InputError, match=r"^y\[0\]: agent 1 measures 1 values, got 3"):
        net.step([[1.0, 2.0, 3.0]] + [None] * 8)
    with pytest.raises(InputError, match=r"^links: must be 9 x 9"):
        net.step([None] * 9, links=np.ones((3, 3)))
    assert net.tick == 0  # nothing happened
    net.step([None] * 9)
    with pytest.raises(InputError, match=r"^ticks: the horizon of 1 ticks is reached"):
        net.step([None] * 9)
    with pytest.raises(InputError, match=r"^estimator: "):
        diskf_mesh.Network(scn, "nosuch")
    with pytest.raises(InputError, match=r"^settings\.windw: unknown estimator setting"):
        diskf_mesh.Network(scn, settings={"windw": 3})
    with pytest.raises(InputError, match=r"^agent_id: 99 is not an agent of 'dynamic' \(ids 1, 2, 3, 4, 5, 6, 7, 8, 9\)"):
        diskf_mesh.Agent(scn, 99)


def test_an_agent_keeps_the_order_of_a_tick(moving):
    scn, _ = moving
    a, b = diskf_mesh.Agent(scn, 1, "diskf"), diskf_mesh.Agent(scn, 2, "diskf")
    with pytest.raises(InputError, match=r"^fuse: tick 1: call local first"):
        a.fuse({})
    old = b.encode(b.local([0.5]))
    b.fuse({})
    a.local([0.5])
    with pytest.raises(InputError, match=r"^local: tick 1: call fuse"):
        a.local([0.5])
    with pytest.raises(InputError, match=r"^received\[2\]: "):
        a.fuse({2: b"\x80"})  # not a message
    with pytest.raises(InputError, match=r"^received\[2\]: a message of tick 2, this is tick 1"):
        a.fuse({2: b.encode(b.local(None))})
    with pytest.raises(InputError, match=r"^received\[99\]: sender 99 is not an agent"):
        a.fuse({99: old})
    assert a.fuse({2: old}).tick == 1


def test_the_examples_of_docs_api_run():
    """docs/api.md's two loops run as shown; the network's agents end near
    the target they tracked."""
    from pathlib import Path
    import re

    text = (Path(__file__).resolve().parents[1] / "docs" / "api.md").read_text()
    section = text.split("## One tick at a time", 1)[1].split("\n## ", 1)[0]
    network, agent = re.findall(r"```python\n(.*?)```", section, re.S)
    ns: dict = {}
    exec(compile(network, "api.md", "exec"), ns)
    assert ns["est"].tick == 40 and ns["est"].P.shape == (4, 2, 2)
    assert np.linalg.norm(ns["est"].x - ns["x"], axis=-1).max() < 20  # metres, on a circle of 200
    exec(compile(agent, "api.md", "exec"), ns)
    assert ns["est"].tick == 40 and ns["est"].x.shape == (2,) and ns["b"].tick == 40


def test_agents_named_in_the_scenario_go_by_their_names(moving, tmp_path):
    """A scenario whose ids are names ("drone-1"): both levels take and give
    the names, and compute what the same scenario with integer ids does."""
    import re

    from diskf_mesh.data.scenario import scenario_path

    scn, trace = moving
    names = iter(f"drone-{k}" for k in range(1, 10))
    named = tmp_path / "named.toml"
    named.write_text(re.sub(r"(?m)^id = \d+$", lambda m: f'id = "{next(names)}"', scenario_path("dynamic").read_text()))
    net = diskf_mesh.Network(str(named), seed=SEED, ticks=TICKS)
    assert net.ids == tuple(f"drone-{k}" for k in range(1, 10))
    ref = diskf_mesh.estimate(trace, "diskf-auto", scenario=scn)
    x = [net.step(rows(trace, k, net.sensors.p), links=trace.links[0, k]).x for k in range(TICKS)]
    np.testing.assert_array_equal(np.array(x), ref.x[0])
    got = []
    for scenario, one, two in ((str(named), "drone-1", "drone-2"), (scn, 1, 2)):
        a, b = diskf_mesh.Agent(scenario, one), diskf_mesh.Agent(scenario, two)
        to_b, to_a = a.encode(a.local([1.0])), b.encode(b.local(None))
        got.append((a.fuse({two: to_a}).x, b.fuse({one: to_b}).x))
    np.testing.assert_array_equal(got[0], got[1])
    a.local(None)
    with pytest.raises(InputError, match=r"^received\['drone-2'\]: sender 'drone-2' is not an agent"):
        a.fuse({"drone-2": to_a})
