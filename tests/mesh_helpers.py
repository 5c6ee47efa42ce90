"""Shared by the mesh tests: run mesh processes, compare with the engine."""
from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from diskf_mesh.engine import batch as engine
from diskf_mesh.mesh.security import credentials
from diskf_mesh.mesh.process.runspec import RunSpec
from diskf_mesh.mesh.process.zenoh_config import ZenohOptions
from diskf_mesh.data.scenario import simulate
from sim.launcher import Child, Launcher, build_children, free_port, loopback_options

TOL = 1e-9
# the estimator the mesh tests run (the paper's, the cheapest per tick); the
# default's own runs: test_simnet_up, test_provenance, test_packaging
MESH_ALGORITHM = "diskf"


def up(tmp_path: Path, *args, timeout: float = 120.0) -> tuple:
    """``diskf-mesh up`` as a child process; returns (completed, estimates
    doc or None, results doc or None)."""
    est, res = tmp_path / "estimates.json", tmp_path / "results.json"
    cmd = [sys.executable, "-m", "sim.launcher", "--algorithm", MESH_ALGORITHM, *args, "--estimates", str(est),
           "--json", str(res),
           "--logs", str(tmp_path / "logs"), "--quiet"]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)
    load = lambda p: json.loads(p.read_text()) if p.exists() else None  # noqa: E731
    return done, load(est), load(res)


def reference(spec: RunSpec, ticks: int, seed: int):
    """(trace, engine estimates) of the same run in-process."""
    scn = spec.load(ticks)
    trace = simulate(scn, [seed])
    return trace, engine.run(trace, spec.algorithm, scn.params)


def assert_same(doc: dict, ref: engine.Estimates, tol: float = TOL) -> None:
    """Every agent's fused x, P, and d (where valid) equal the engine's."""
    assert np.array(doc["reported"]).all(), "some agent-ticks had no report"
    x, P = np.array(doc["x"], dtype=float), np.array(doc["P"], dtype=float)
    np.testing.assert_allclose(x, ref.x[0], rtol=0, atol=tol)
    np.testing.assert_allclose(P, ref.P[0], rtol=0, atol=tol)
    valid = np.array([[row is not None for row in tick] for tick in doc["d"]])
    np.testing.assert_array_equal(valid, ref.d_valid[0])
    d = np.array([[row if row is not None else [np.nan] * ref.d.shape[-1] for row in tick] for tick in doc["d"]])
    np.testing.assert_allclose(d[valid], ref.d[0][valid], rtol=0, atol=tol)


def assert_engine_bit_for_bit(doc: dict, spec: RunSpec, ticks: int, seed: int = 0) -> None:
    """Every agent's x and P are the engine's bit for bit, and every agent
    fused exactly its neighbours in range at every tick (none lost)."""
    from diskf_mesh.mesh.protocol.estimator import neighbours

    trace, ref = reference(spec, ticks, seed)
    assert np.array(doc["reported"]).all()
    assert np.array_equal(np.array(doc["x"], dtype=float), ref.x[0])
    assert np.array_equal(np.array(doc["P"], dtype=float), ref.P[0])
    scn, ids = spec.load(ticks), doc["ids"]
    links = [[sorted(set(neighbours(scn, i, trace.positions[k])) - {i}) for i in ids] for k in range(ticks)]
    assert [[sorted(s) for s in tick] for tick in doc["fused"]] == links


def run_checked(cmd, **kw) -> str:
    return subprocess.run(cmd, check=True, capture_output=True, text=True, **kw).stdout


def with_credentials(spec: RunSpec, tmp_path: Path, ticks: int | None = None) -> ZenohOptions:
    """Zenoh options carrying fresh credentials of ``spec``'s run (world,
    every agent, observer) in ``tmp_path/credentials``."""
    ids = [a.id for a in spec.load(ticks).agents]
    return ZenohOptions(credentials=str(credentials.make(tmp_path / "credentials", spec.run_id, ids)))


class Mesh(Launcher):
    """World and agents started by the tests themselves (explicit endpoints)."""

    world_endpoints: tuple = ()
    run_id: str = ""
    credentials: str | None = None

    def observer(self, **kw) -> ZenohOptions:
        """Options of a session that joins this run to listen: the run's
        observer identity (or plain, if the run is insecure)."""
        opts = ZenohOptions(connect=self.world_endpoints, no_multicast_scouting=True, **kw)
        if self.credentials is None:
            return replace(opts, listen=opts.listen or ("tcp/127.0.0.1:0",))
        return replace(opts, listen=opts.listen or ("tls/127.0.0.1:0",), credentials=self.credentials,
                       identity=credentials.OBSERVER, run_id=self.run_id)


def start_mesh(spec: RunSpec, ticks: int, seed: int, tmp_path: Path, world_zenoh=None, agent_zenoh=None,
               world_extra=(), agent_extra=(), wrap=None) -> Mesh:
    """Start the world (agents: ``mesh.start_agents()``). Default endpoints:
    loopback, the world listening on a free port, with fresh credentials
    of the run (``with_credentials``). ``wrap(name, argv)`` may prefix a
    child's command line (e.g. ``ip netns exec``)."""
    if world_zenoh is None:
        world_zenoh, agent_zenoh = loopback_options(free_port(), with_credentials(spec, tmp_path, ticks))
    logs = tmp_path / "logs"
    logs.mkdir(exist_ok=True)
    world, agents = build_children(spec, ticks, seed, [a.id for a in spec.load(ticks).agents], logs, world_zenoh,
                                   agent_zenoh, ["--progress", "none", "--estimates", str(tmp_path / "est.json"),
                                                 *world_extra], agent_extra)
    if wrap is not None:
        for c in (world, *agents):
            c.argv = wrap(c.name, c.argv)
    mesh = Mesh(world, agents)
    mesh.world_endpoints = tuple(world_zenoh.listen)
    mesh.run_id, mesh.credentials = spec.run_id, world_zenoh.credentials
    mesh.start_world()
    return mesh


LEASE_MS = 3000  # zenoh's lease in the process-fault tests (default 10 s): a freeze past it is detected fast


def with_lease(options, lease_ms: int = LEASE_MS):
    """ZenohOptions with zenoh's link lease shortened (``--cfg``)."""
    return replace(options, cfg=(*options.cfg, f"transport/link/tx/lease:{int(lease_ms)}"))


class Progress:
    """The world's ``tick k K`` lines (``--progress lines``) as they come."""

    def __init__(self, mesh):
        self.mesh, self.tick = mesh, 0
        mesh.progress = self._on

    def _on(self, k, K):
        self.tick = k

    def wait_for(self, k: int, timeout: float) -> None:
        deadline = time.monotonic() + timeout
        while self.tick < k:
            self.mesh._drain()
            assert self.mesh.world.proc.poll() is None, f"world ended at tick {self.tick}"
            assert time.monotonic() < deadline, f"tick {k} not reached in {timeout} s (at {self.tick})"
            time.sleep(0.01)

    def follow(self, timeout: float) -> int:
        """Until the world ends; its exit status."""
        deadline = time.monotonic() + timeout
        while self.mesh.world.proc.poll() is None:
            self.mesh._drain()
            assert time.monotonic() < deadline, f"the world still runs after {timeout} s (at tick {self.tick})"
            time.sleep(0.02)
        self.mesh._drain()
        return self.mesh.world.proc.returncode


def spawn(child: Child, env=None) -> Child:
    """Start one more process (a restart, a duplicate) with the launcher's
    settings; ``env``: variables added to this process's environment."""
    with open(child.log, "wb") as err:
        child.proc = subprocess.Popen(child.argv, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=err,
                                      start_new_session=True, env=None if env is None else {**os.environ, **env})
    return child


def error_lines(child: Child) -> list:
    return [ln for ln in child.log.read_text().splitlines() if ln.startswith("error:")]
