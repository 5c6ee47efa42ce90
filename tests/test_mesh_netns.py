"""Beyond one host: every process in its own network namespace, joined by
veth pairs on a bridge, meeting only on explicit --listen/--connect TLS
endpoints (no multicast), each with its own identity of the run's
credentials (``diskf-mesh credentials``). The result must equal the
single-host run.

Then namespaces as hosts (docs/hosts.md): the world in one, a zenoh router
and a shard of agents (``diskf-mesh host``) in each of the others, started
by ``up --hosts FILE`` or from the same command lines (``sim.hosts``): the
run equals the single-host run and the engine bit for bit; a shard started
late joins the run; a host whose router is killed loses its agents' ticks
(counted, exit status 3) and they rejoin once the router is back.

Needs root and ``ip netns``; skipped with the reason otherwise. Addresses
are 10.213.<n>.0/24 inside namespaces this test creates and deletes.
"""
from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess

from pathlib import Path

import numpy as np
import pytest

from diskf_mesh.cli import main as cli
from diskf_mesh.mesh.process.runspec import RunSpec, agent_command, world_command
from diskf_mesh.mesh.process.zenoh_config import ZenohOptions
from sim import hosts
from sim.launcher import Child, Launcher
from sim.netns import Namespaces

from mesh_helpers import MESH_ALGORITHM, Progress, assert_same, reference, spawn, up, with_credentials

pytestmark = pytest.mark.mesh

PORT = 7447


def _ip(*args) -> subprocess.CompletedProcess:
    return subprocess.run(["ip", *args], capture_output=True, text=True, timeout=20)


def _skip_reason() -> str | None:
    if shutil.which("ip") is None:
        return "the ip command (iproute2) is not installed"
    if os.geteuid() != 0:
        return "network namespaces need root"
    probe = f"dkmprobe{os.getpid() % 100000}"
    r = _ip("netns", "add", probe)
    if r.returncode != 0:
        return f"ip netns add is not permitted here: {r.stderr.strip()}"
    _ip("netns", "del", probe)
    return None


def _namespaces(count: int):
    reason = _skip_reason()
    if reason:
        pytest.skip(reason)
    spaces = Namespaces(count)
    try:
        spaces.create()
    except OSError as e:
        spaces.delete()
        pytest.skip(f"cannot build the namespaces: {e}")
    return spaces


@pytest.fixture
def namespaces():
    spaces = _namespaces(5)  # the world and Scenario 1's four agents
    yield spaces
    spaces.delete()


@pytest.fixture
def three_hosts():
    spaces = _namespaces(3)  # the world's host and two hosts of agents
    yield spaces
    spaces.delete()


def test_namespaced_run_equals_single_host_run(tmp_path, namespaces):
    spec = RunSpec("quadrants", "diskf", run_id="netns", topology="ring")
    ticks, seed = 20, 5
    single = tmp_path / "single"
    single.mkdir()
    done, single_est, _ = up(single, "--scenario", "quadrants", "--topology", "ring", "--ticks", str(ticks),
                             "--seed", str(seed))
    assert done.returncode == 0, done.stderr

    creds = str(tmp_path / "credentials")
    assert cli.main(["credentials", "--run-id", spec.run_id, "--out", creds, "--scenario", "quadrants"]) == 0
    world_addr = namespaces.addrs[0]
    est_path = tmp_path / "netns-estimates.json"
    world_z = ZenohOptions(listen=(f"tls/{world_addr}:{PORT}",), no_multicast_scouting=True, credentials=creds)
    world = Child("world", ["ip", "netns", "exec", namespaces.names[0],
                            *world_command(spec, ticks, seed, world_z,
                                           ["--progress", "none", "--estimates", str(est_path)])],
                  tmp_path / "world.log")
    agents = []
    for j, a in enumerate(spec.load(ticks).agents, start=1):
        z = ZenohOptions(connect=(f"tls/{world_addr}:{PORT}",), listen=(f"tls/{namespaces.addrs[j]}:{PORT}",),
                         no_multicast_scouting=True, credentials=creds)
        agents.append(Child(f"agent {a.id}", ["ip", "netns", "exec", namespaces.names[j],
                                              *agent_command(spec, a.id, z)], tmp_path / f"agent-{a.id}.log"))
    launcher = Launcher(world, agents)
    try:
        launcher.start()
        launcher.wait(90)
        assert not launcher.finish(), "an agent did not leave cleanly"
    finally:
        launcher.stop_all()
    netns_est = json.loads(est_path.read_text())
    for key in ("x", "P", "d", "reported"):
        assert netns_est[key] == single_est[key], key  # bit for bit, as on one host
    assert_same(netns_est, reference(spec, ticks, seed)[1])
    assert np.array(netns_est["reported"]).all()


# --------------------------------------------------------------------------
# hosts: a router and a shard of agents per namespace
# --------------------------------------------------------------------------
SHARDS = {"a": "1-4", "b": "5-9"}  # Scenario 2's nine agents on two hosts


def hosts_file(path, spaces) -> Path:
    """The world in the first namespace, hosts a and b (router + shard) in the others."""
    lines = ["[world]", f'listen = "tls/{spaces.addrs[0]}:{PORT}"', f'prefix = ["ip", "netns", "exec", "{spaces.names[0]}"]']
    for j, (name, ids) in enumerate(SHARDS.items(), start=1):
        lines += [f"[hosts.{name}]", f'agents = "{ids}"', f'router = "tls/{spaces.addrs[j]}:{PORT}"',
                  f'prefix = ["ip", "netns", "exec", "{spaces.names[j]}"]']
    path.write_text("\n".join(lines) + "\n")
    return path


def test_hosts_with_routers_equal_the_single_host_run(tmp_path, three_hosts):
    ticks, seed = 20, 4
    single = tmp_path / "single"
    single.mkdir()
    done, single_est, _ = up(single, "--ticks", str(ticks), "--seed", str(seed))
    assert done.returncode == 0, done.stderr
    multi = tmp_path / "multi"
    multi.mkdir()
    done, est, res = up(multi, "--ticks", str(ticks), "--seed", str(seed), "--run-id", "hosts",
                        "--hosts", str(hosts_file(tmp_path / "hosts.toml", three_hosts)))
    assert done.returncode == 0, done.stderr
    assert "on 2 hosts" in done.stdout
    for key in ("x", "P", "d", "reported"):
        assert est[key] == single_est[key], key  # bit for bit, as on one host
    assert_same(est, reference(RunSpec(algorithm=MESH_ALGORITHM, run_id="hosts"), ticks, seed)[1])
    routers = [ln for ln in (multi / "logs" / "router-a.log").read_text().splitlines() if ln.startswith("error")]
    assert not routers


def _hosts_run(tmp_path, spaces, ticks, seed, world_extra=(), agent_extra=()):
    """(launcher, world, routers, shards, estimates path) of a run over the
    namespaces, from the command lines ``up --hosts`` starts; nothing started."""
    spec = RunSpec(algorithm=MESH_ALGORITHM, run_id="hostsrun")
    plan = hosts.load(hosts_file(tmp_path / "hosts.toml", spaces))
    logs = tmp_path / "logs"
    logs.mkdir()
    est = tmp_path / "est.json"
    world, routers, shards = hosts.children(
        plan, spec, ticks, seed, with_credentials(spec, tmp_path), logs,
        ["--progress", "lines", "--estimates", str(est), "--tick-timeout", "10", *world_extra],
        ["--collect-timeout", "2", "--world-timeout", "60", *agent_extra])
    for h in shards:
        h.argv += ["--logs", str(logs / h.name.replace(" ", "-"))]
    return spec, world, routers, shards, est


def test_a_shard_started_late_joins_the_run(tmp_path, three_hosts):
    ticks, seed = 800, 2  # host a alone ticks fast: the run must outlast host b's start (~20 s under load)
    spec, world, routers, (a, b), est_path = _hosts_run(
        tmp_path, three_hosts, ticks, seed, ["--allow-missing", "0.9", "--startup-timeout", "6"])
    mesh = Launcher(world, [a], services=routers)
    progress = Progress(mesh)
    try:
        mesh.start()
        progress.wait_for(3, 120)  # host a's agents tick alone
        spawn(b)  # host b comes up late
        mesh.agents.append(b)
        mesh.children.append(b)
        assert progress.follow(240) == 0  # within --allow-missing
        assert a.proc.wait(30) == 0 and b.proc.wait(30) == 0
    finally:
        mesh.stop_all()
    est = json.loads(est_path.read_text())
    reported = np.array(est["reported"])
    late = [i for i in est["ids"] if i >= 5]
    cols = [est["ids"].index(i) for i in late]
    assert reported[:, [j for j in range(len(est["ids"])) if j not in cols]].all()  # host a: every tick
    assert not reported[:3, cols].any() and reported[-1, cols].all()  # host b: not at first, then yes
    assert set(est["rejoins"]) == {str(i) for i in late}
    for i in late:
        assert set(est["missing"][str(i)]["why"]) <= {"never joined", "rejoining"}


def test_a_hosts_router_killed_costs_its_agents_ticks_and_they_rejoin(tmp_path, three_hosts):
    # 600 ticks: forked processes tick 200 in about 3 s, less than the cut-off agents may need to find their
    # router again (zenoh's reconnect), re-initialise and be live; the run must outlast that to show the rejoin
    ticks, seed = 600, 6
    spec, world, routers, shards, est_path = _hosts_run(tmp_path, three_hosts, ticks, seed)
    mesh = Launcher(world, shards, services=routers)
    progress = Progress(mesh)
    router_b = routers[1]
    try:
        mesh.start()
        progress.wait_for(10, 120)
        router_b.proc.send_signal(signal.SIGKILL)  # host b is cut off
        router_b.proc.wait(10)
        killed_at = progress.tick
        progress.wait_for(killed_at + 5, 60)  # the others tick on without it
        spawn(router_b)  # back, on the same endpoint
        assert progress.follow(300) == 3  # incomplete: agent-ticks are missing
        for h in shards:
            assert h.proc.wait(30) == 0, h.last_error_line()  # every agent saw "done"
    finally:
        mesh.stop_all()
    est = json.loads(est_path.read_text())
    reported = np.array(est["reported"])
    ids = est["ids"]
    on_b = [ids.index(i) for i in ids if i >= 5]
    on_a = [j for j in range(len(ids)) if j not in on_b]
    assert reported[:, on_a].all()  # host a lost nothing
    assert set(est["missing"]) == {str(ids[j]) for j in on_b}  # host b's agents, each
    for j in on_b:
        m = est["missing"][str(ids[j])]
        assert m["ticks"] >= 5 and set(m["why"]) <= {"left", "rejoining", "no report"}
    assert reported[-1, on_b].all()  # they rejoined
    assert set(est["rejoins"]) == {str(ids[j]) for j in on_b}
    assert est["missing_agent_ticks"] == int((~reported).sum()) > 0
