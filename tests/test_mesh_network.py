"""``up --network``: on one host a peer mesh up to ``PEERS_UP_TO`` agents,
every agent a client of one zenoh router above (the shape of one host of
``up --hosts``). The shape changes how messages travel, never an estimate."""
from __future__ import annotations

import pytest

from diskf_mesh.cli import main as cli
from diskf_mesh.mesh.process.runspec import RunSpec
from diskf_mesh.mesh.process.zenoh_config import ZenohOptions
from mesh_helpers import assert_engine_bit_for_bit, up
from sim import launcher
from sim.launcher import PEERS_UP_TO, network_of

pytestmark = pytest.mark.mesh


def test_auto_is_a_peer_mesh_up_to_the_limit_and_a_router_above():
    assert network_of("auto", PEERS_UP_TO) == "peers"
    assert network_of("auto", PEERS_UP_TO + 1) == "router"
    assert network_of("peers", 100) == "peers" and network_of("router", 2) == "router"


def flag(argv, name):
    return [argv[i + 1] for i, a in enumerate(argv) if a == name]


@pytest.mark.parametrize("n, routed", [(PEERS_UP_TO, False), (PEERS_UP_TO + 1, True)])
def test_above_the_limit_every_agent_is_a_client_of_the_router_and_only_of_it(tmp_path, n, routed):
    spec = RunSpec("random-geometric", "diskf", agents=n)
    ids = [a.id for a in spec.load().agents]
    world, services, agents, _ = launcher.one_host_children(spec, 5, 0, ids, tmp_path, ZenohOptions(insecure=True))
    assert len(agents) == n
    if not routed:  # peers: each agent connects to the world and listens for the others
        assert services == [] and all(flag(a.argv, "--mode") == [] and flag(a.argv, "--listen") for a in agents)
        return
    (router,) = services
    world_at, router_at = flag(world.argv, "--listen"), flag(router.argv, "--listen")
    assert flag(world.argv, "--mode") == ["router"] and flag(router.argv, "--connect") == world_at
    assert router_at != world_at
    for a in agents:
        assert flag(a.argv, "--mode") == ["client"] and flag(a.argv, "--connect") == router_at
        assert flag(a.argv, "--listen") == []


def test_up_through_a_router_equals_the_engine(tmp_path):
    ticks = 30
    done, doc, _ = up(tmp_path, "--scenario", "dynamic", "--ticks", str(ticks), "--network", "router")
    assert done.returncode == 0, done.stderr
    assert (tmp_path / "logs" / "router.log").exists()  # the router was one of the run's processes
    assert_engine_bit_for_bit(doc, RunSpec("dynamic", "diskf"), ticks)


def test_more_agents_than_the_limit_go_through_a_router_by_default(tmp_path):
    n, ticks = PEERS_UP_TO + 1, 10
    done, doc, _ = up(tmp_path, "--scenario", "random-geometric", "--agents", str(n), "--ticks", str(ticks),
                      timeout=180)
    assert done.returncode == 0, done.stderr
    assert (tmp_path / "logs" / "router.log").exists()
    assert_engine_bit_for_bit(doc, RunSpec("random-geometric", "diskf", agents=n), ticks)


@pytest.mark.parametrize("extra", [["--mode", "peer"], ["--hosts", "hosts.toml"]])
def test_network_is_refused_with_zenoh_flags_or_hosts(tmp_path, capsys, monkeypatch, extra):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "hosts.toml").write_text('[world]\nlisten = "tls/127.0.0.1:9"\n[hosts.a]\nagents = "1-9"\n')
    assert cli.main(["up", "--network", "router", "--insecure", "--ticks", "2", "--quiet", *extra]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: network:"), err


@pytest.mark.parametrize("version, one_way", [((1, 5), False), ((1, 8), False), ((1, 9), True), ((1, 10), True)])
def test_one_way_gossip_only_on_zenoh_that_connects_every_pair_with_it(monkeypatch, version, one_way):
    """Before zenoh 1.9 "greater-zid" sometimes left a pair of peers
    unconnected (the run failed its start-up): those get zenoh's default."""
    monkeypatch.setattr(launcher, "zenoh_version", lambda: version)
    _, agent = launcher.loopback_options(7447)
    assert (launcher.GOSSIP_ONE_WAY in agent.cfg) is one_way
    assert launcher.CONNECT_RETRY in agent.cfg
