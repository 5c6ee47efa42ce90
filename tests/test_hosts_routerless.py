"""A host without a router (docs/hosts.md): its agents are zenoh clients of
the world, which forwards their traffic. Over TLS with the run's access
control that needs credentials that let the world route
(``credentials.make(world_routes=True)``): ``up --hosts`` makes them so when
a host has no router, and refuses given credentials that do not."""
from __future__ import annotations

import json

import pytest

from diskf_mesh.cli import main as cli
from diskf_mesh.mesh.security import credentials
from diskf_mesh.mesh.process.runspec import RunSpec
from mesh_helpers import assert_engine_bit_for_bit, up
from sim.launcher import free_port

pytestmark = pytest.mark.mesh


def hosts_file(tmp_path, creds=None) -> str:
    """Host a with a router (agents 1-4), host b without one (5-9)."""
    world, router = free_port(), free_port()
    path = tmp_path / "hosts.toml"
    path.write_text((f'credentials = "{creds}"\n' if creds else "")
                    + f'[world]\nlisten = "tls/127.0.0.1:{world}"\n'
                    + f'[hosts.a]\nagents = "1-4"\nrouter = "tls/127.0.0.1:{router}"\n'
                    + '[hosts.b]\nagents = "5-9"\n')
    return str(path)


def test_a_host_without_a_router_over_tls_equals_the_engine(tmp_path):
    """Host b's agents reach everyone through the world (and host a's
    through its router and the world): every estimate is the engine's, bit
    for bit, and the run's credentials are TLS with access control."""
    ticks = 20
    done, doc, _ = up(tmp_path, "--hosts", hosts_file(tmp_path), "--scenario", "dynamic", "--ticks", str(ticks),
                      timeout=180)
    assert done.returncode == 0, done.stderr
    spec = RunSpec("dynamic", "diskf")
    assert_engine_bit_for_bit(doc, spec, ticks)
    # some of host b's agents fused host a's: their messages crossed the world
    assert any(i >= 5 and j <= 4 for tick in doc["fused"] for i, s in zip(doc["ids"], tick) for j in s)


def test_given_credentials_that_do_not_let_the_world_route_are_refused(tmp_path, capsys):
    run_id = "rl1"
    creds = tmp_path / "creds"
    assert cli.main(["credentials", "--run-id", run_id, "--out", str(creds), "--scenario", "dynamic"]) == 0
    capsys.readouterr()
    argv = ["up", "--hosts", hosts_file(tmp_path, creds), "--run-id", run_id, "--scenario", "dynamic",
            "--ticks", "3", "--quiet"]
    assert cli.main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: hosts:") and "--world-routes" in err[0], err


def test_world_routes_is_recorded_and_grants_the_world_a_routers_rights(tmp_path):
    plain = credentials.load(credentials.make(tmp_path / "a", "r1", [1, 2]), credentials.WORLD, "r1")
    routes = credentials.load(credentials.make(tmp_path / "b", "r1", [1, 2], world_routes=True),
                              credentials.WORLD, "r1")
    assert (plain.world_routes, routes.world_routes) == (False, True)
    assert json.loads((tmp_path / "b" / "agent-1" / credentials.RUN_FILE).read_text())["world_routes"] is True

    def world_policy(acl):
        rules = {r["id"]: r for r in acl["rules"]}
        return [rules[i] for i in next(p for p in acl["policies"] if p["id"] == credentials.WORLD)["rules"]]

    def allowed(acl, message, key):
        return any(message in r["messages"] and "ingress" in r["flows"] and key in r["key_exprs"]
                   for r in world_policy(acl))

    tight = credentials.access_control("r1", [1, 2])
    wide = credentials.access_control("r1", [1, 2], world_routes=True)
    # an agent's message that reaches a process from the world's link: refused unless the world routes
    assert not allowed(tight, "put", "diskf/r1/**") and allowed(wide, "put", "diskf/r1/**")
    assert not allowed(tight, "liveliness_token", "diskf/r1/**") and allowed(wide, "liveliness_token", "diskf/r1/**")
