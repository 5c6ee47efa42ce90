"""A router opens no hole (docs/hosts.md): one run over two "hosts" on
loopback (the world a zenoh router, a router and a shard of agents per
host, fresh credentials, as ``up --hosts`` starts them) while, from before
the first tick to the end, sessions try to hear it through host a's router:

* plain TCP (no credentials);
* TLS with certificates of another CA named ``router`` and ``world`` (the
  identities a router trusts with everything);
* agent 3's real certificate (a compromised agent of host a), asking for
  agent 1's measurements and every agent's messages.

None of them hears a sample or a token of the run; the run completes
(exit 0) and equals the engine bit for bit.
"""
from __future__ import annotations

import json
import time

import pytest

from diskf_mesh.mesh.security import credentials
from diskf_mesh.mesh.wire.keys import Keys
from diskf_mesh.mesh.process.runspec import RunSpec
from diskf_mesh.mesh.process.transport import MeshError, ZenohTransport
from diskf_mesh.mesh.process.zenoh_config import ZenohOptions
from sim import hosts
from sim.launcher import Launcher, free_port

from mesh_helpers import Progress, assert_same, reference, with_credentials

pytestmark = pytest.mark.mesh

TICKS, SEED = 200, 7


def _session(options, heard: list, exprs):
    try:
        t = ZenohTransport(options)
    except MeshError:
        return None  # cannot even open: hears nothing
    for e in exprs:
        t.subscribe(e, lambda k, p: heard.append(k))
        t.watch_tokens(e, lambda k, up: heard.append(k))
    return t


def test_a_session_without_the_runs_credentials_hears_nothing_through_a_router(tmp_path):
    spec = RunSpec(run_id="hostsacl")
    keys = Keys(spec.run_id)
    ports = [free_port() for _ in range(3)]
    plan = hosts.parse({"world": {"listen": f"tls/127.0.0.1:{ports[0]}"},
                        "hosts": {"a": {"agents": "1-4", "router": f"tls/127.0.0.1:{ports[1]}"},
                                  "b": {"agents": "5-9", "router": f"tls/127.0.0.1:{ports[2]}"}}})
    base = with_credentials(spec, tmp_path)
    logs = tmp_path / "logs"
    logs.mkdir()
    est = tmp_path / "est.json"
    world, routers, shards = hosts.children(plan, spec, TICKS, SEED, base, logs,
                                            ["--progress", "lines", "--estimates", str(est)],
                                            ["--latency-ms", "20"])  # the ticks last while the sessions listen
    evil = credentials.make(tmp_path / "evil", spec.run_id, [1, 2, 3])  # another CA, same names
    router_a = f"tls/127.0.0.1:{ports[1]}"
    everything = [f"{keys.root}/**"]
    outsiders = {
        "plain tcp": ZenohOptions(mode="peer", connect=(router_a.replace("tls/", "tcp/"),),
                                  no_multicast_scouting=True, insecure=True),
        **{f"other CA as {who}": ZenohOptions(mode="peer", connect=(router_a,), listen=("tls/127.0.0.1:0",),
                                              no_multicast_scouting=True, credentials=str(evil),
                                              identity=who, run_id=spec.run_id)
           for who in (credentials.ROUTER, credentials.WORLD)},
    }
    insider = ZenohOptions(mode="client", connect=(router_a,), credentials=base.credentials,
                           identity=credentials.agent_identity(3), run_id=spec.run_id)
    heard = {name: [] for name in [*outsiders, "agent 3"]}
    mesh = Launcher(world, shards, services=routers)
    progress = Progress(mesh)
    sessions = []
    try:
        mesh.start()
        time.sleep(1.0)
        for name, opts in outsiders.items():
            sessions.append(_session(opts, heard[name], everything))
        sessions.append(_session(insider, heard["agent 3"], [keys.meas(1), f"{keys.root}/agent/*/msg/**"]))
        assert progress.follow(300) == 0
        for h in shards:
            assert h.proc.wait(30) == 0, h.last_error_line()
    finally:
        for s in sessions:
            if s is not None:
                s.close()
        mesh.stop_all()
    assert {name: len(v) for name, v in heard.items()} == dict.fromkeys(heard, 0), heard
    assert sessions[-1] is not None  # the insider did connect: its requests were refused, not its link
    doc = json.loads(est.read_text())
    assert_same(doc, reference(spec, TICKS, SEED)[1])
