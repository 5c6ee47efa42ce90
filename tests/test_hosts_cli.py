"""``router``, ``host`` and ``up --hosts``: bad input is one ``error:`` line
and exit status 2, before any process starts; the hosts file's shape."""
from __future__ import annotations

import pytest

from diskf_mesh.cli import main as cli
from diskf_mesh.core.errors import InputError
from diskf_mesh.mesh.process import runspec
from diskf_mesh.mesh.process.runspec import RunSpec
from diskf_mesh.mesh.process.zenoh_config import ZenohOptions
from sim import hosts

WORLD = '[world]\nlisten = "tls/127.0.0.1:7447"\n'


def _one_error(capsys) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: "), err
    return err[0]


@pytest.mark.parametrize("ids, why", [("5-2", "bad range"), ("x", "expected"), ("1,1", "twice"), ("-3", "expected"),
                                      ("1-99", "not in scenario")])
def test_host_refuses_bad_agent_ranges(ids, why, capsys):
    argv = ["host", "--run-id", "r1", "--agents", ids, "--connect", "tls/127.0.0.1:9", "--insecure"]
    assert cli.main(argv) == 2
    assert why in _one_error(capsys)


def test_host_and_router_need_their_endpoints_and_credentials(tmp_path, capsys):
    assert cli.main(["host", "--run-id", "r1", "--agents", "1-4", "--insecure"]) == 2
    assert "connect" in _one_error(capsys)
    assert cli.main(["host", "--run-id", "r1", "--agents", "1-4", "--connect", "tls/127.0.0.1:9"]) == 2
    assert "credentials" in _one_error(capsys)
    assert cli.main(["host", "--agents", "1-4", "--connect", "tls/127.0.0.1:9", "--insecure"]) == 2
    assert "run-id" in _one_error(capsys)
    creds = tmp_path / "c"
    assert cli.main(["credentials", "--run-id", "r1", "--out", str(creds), "--ids", "1,2"]) == 0
    capsys.readouterr()
    assert cli.main(["host", "--run-id", "r1", "--agents", "1-3", "--connect", "tls/127.0.0.1:9",
                     "--credentials", str(creds), "--scenario", "quadrants"]) == 2
    assert "agent-3" in _one_error(capsys)  # no identity for agent 3 in these credentials
    assert cli.main(["router", "--credentials", str(creds)]) == 2
    assert "listen" in _one_error(capsys)
    assert cli.main(["router", "--listen", "tls/127.0.0.1:9", "--mode", "peer", "--insecure"]) == 2
    assert "router mode" in _one_error(capsys)
    assert cli.main(["router", "--listen", "tls/127.0.0.1:9", "--credentials", str(creds), "--run-id", "r2"]) == 2
    assert "r1" in _one_error(capsys)


@pytest.mark.parametrize("text, why", [
    (WORLD + 'colour = "red"\n[hosts.a]\nagents = "1-9"\n', "unknown key 'colour'"),
    (WORLD + '[hosts.a]\nagents = "1-9"\nrouterr = "tls/x:1"\n', "unknown key 'routerr'"),
    (WORLD + '[hosts.a]\nagents = "5-2"\n', "bad range"),
    (WORLD + '[hosts.a]\nagents = "1-5"\n[hosts.b]\nagents = "5-9"\n', "agent 5 is on two hosts"),
    (WORLD + '[hosts.a]\nagents = "1-8"\n', "agent 9 is on no host"),
    (WORLD + '[hosts.a]\nagents = "1-10"\n', "agent 10 is not in the scenario"),
    (WORLD, "no [hosts.NAME]"),
    ('[hosts.a]\nagents = "1-9"\n', "[world] needs 'listen'"),
    (WORLD + '[hosts.a]\nagents = "1-9"\nprefix = 3\n', "prefix"),
    ("[world\n", "not valid TOML"),
])
def test_up_hosts_refuses_a_bad_file(text, why, tmp_path, capsys):
    f = tmp_path / "hosts.toml"
    f.write_text(text)
    assert cli.main(["up", "--hosts", str(f), "--quiet", "--logs", str(tmp_path / "logs")]) == 2
    assert why in _one_error(capsys)


def test_up_hosts_takes_no_zenoh_flags(tmp_path, capsys):
    f = tmp_path / "hosts.toml"
    f.write_text(WORLD + '[hosts.a]\nagents = "1-9"\n')
    assert cli.main(["up", "--hosts", str(f), "--connect", "tls/127.0.0.1:1", "--quiet"]) == 2
    assert "zenoh flags" in _one_error(capsys)


def test_the_plan_becomes_the_command_lines(tmp_path):
    """World as a router; each router connects to the world and the routers
    before it; a shard's agents are clients of its router, or of the world
    when the host has none; a prefix goes in front of every command."""
    plan = hosts.parse({"world": {"listen": "tls/10.0.0.1:7447", "prefix": "ssh w"},
                        "hosts": {"a": {"agents": "1-4", "router": "tls/10.0.0.2:7447", "prefix": ["ssh", "a"]},
                                  "b": {"agents": "5,6", "router": "tls/10.0.0.3:7447"},
                                  "c": {"agents": "7-9"}}})
    spec = RunSpec(run_id="plan", agents=12, scenario="random-geometric")
    world, routers, shards = hosts.children(plan, spec, 10, 0, ZenohOptions(credentials="/c"), tmp_path)
    assert world.argv[:2] == ["ssh", "w"]
    flag = lambda argv, f: [argv[i + 1] for i, a in enumerate(argv) if a == f]  # noqa: E731
    assert flag(world.argv, "--mode") == ["router"] and flag(world.argv, "--listen") == ["tls/10.0.0.1:7447"]
    assert [flag(r.argv, "--connect") for r in routers] == [["tls/10.0.0.1:7447"],
                                                            ["tls/10.0.0.1:7447", "tls/10.0.0.2:7447"]]
    assert [flag(s.argv, "--connect") for s in shards] == [["tls/10.0.0.2:7447"], ["tls/10.0.0.3:7447"],
                                                           ["tls/10.0.0.1:7447"]]
    assert [flag(s.argv, "--agents") for s in shards] == [["1-4"], ["5-6"], ["7-9"]]
    assert all(flag(s.argv, runspec.HOST_COUNT_FLAG) == ["12"] for s in shards)
    assert routers[0].argv[:2] == ["ssh", "a"] and shards[0].argv[:2] == ["ssh", "a"]
    assert all("--no-multicast-scouting" in c.argv and flag(c.argv, "--credentials") == ["/c"]
               for c in (world, *routers, *shards))


def test_id_ranges_round_trip():
    for ids in [(1,), (1, 2, 3), (1, 3, 4, 5, 9), tuple(range(1, 101))]:
        assert runspec.parse_ids(runspec.id_ranges(ids)) == ids
    with pytest.raises(InputError):
        runspec.parse_ids("")
