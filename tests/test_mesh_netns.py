"""Beyond one host: every process in its own network namespace, joined by
veth pairs on a bridge, meeting only on explicit --listen/--connect TLS
endpoints (no multicast), each with its own identity of the run's
credentials (``diskf-mesh credentials``). The result must equal the
single-host run.

Needs root and ``ip netns``; skipped with the reason otherwise. Addresses
are 10.213.<n>.0/24 inside namespaces this test creates and deletes.
"""
from __future__ import annotations

import json
import os
import shutil
import subprocess

import numpy as np
import pytest

from diskf_mesh.cli import main as cli
from diskf_mesh.mesh.runspec import RunSpec, agent_command, world_command
from diskf_mesh.mesh.zenoh_config import ZenohOptions
from sim.launcher import Child, Launcher

from mesh_helpers import assert_same, reference, up

pytestmark = pytest.mark.mesh

PORT = 7447


def _ip(*args) -> subprocess.CompletedProcess:
    return subprocess.run(["ip", *args], capture_output=True, text=True, timeout=20)


class Namespaces:
    """A hub namespace with a bridge, and one namespace per node with a veth
    pair to the bridge and the address 10.213.<net>.<j + 1>."""

    def __init__(self, count: int):
        tag = f"dkm{os.getpid() % 100000}"
        self.hub = f"{tag}h"
        self.names = [f"{tag}n{j}" for j in range(count)]
        self.net = os.getpid() % 200 + 20
        self.addrs = [f"10.213.{self.net}.{j + 1}" for j in range(count)]
        self.tag = tag

    def create(self) -> None:
        steps = [("netns", "add", self.hub),
                 ("netns", "exec", self.hub, "ip", "link", "add", "br0", "type", "bridge"),
                 ("netns", "exec", self.hub, "ip", "link", "set", "br0", "up")]
        for j, (ns, addr) in enumerate(zip(self.names, self.addrs)):
            a, b = f"{self.tag}a{j}", f"{self.tag}b{j}"
            steps += [("netns", "add", ns),
                      ("link", "add", a, "netns", ns, "type", "veth", "peer", "name", b, "netns", self.hub),
                      ("netns", "exec", self.hub, "ip", "link", "set", b, "master", "br0", "up"),
                      ("netns", "exec", ns, "ip", "addr", "add", f"{addr}/24", "dev", a),
                      ("netns", "exec", ns, "ip", "link", "set", a, "up"),
                      ("netns", "exec", ns, "ip", "link", "set", "lo", "up")]
        for s in steps:
            r = _ip(*s)
            if r.returncode != 0:
                raise OSError(f"ip {' '.join(s)}: {r.stderr.strip()}")

    def delete(self) -> None:
        for ns in (*self.names, self.hub):
            _ip("netns", "del", ns)


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


@pytest.fixture
def namespaces():
    reason = _skip_reason()
    if reason:
        pytest.skip(reason)
    spaces = Namespaces(5)  # the world and Scenario 1's four agents
    try:
        spaces.create()
    except OSError as e:
        spaces.delete()
        pytest.skip(f"cannot build the namespaces: {e}")
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
