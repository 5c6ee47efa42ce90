"""The end-of-run check on real processes, for what only processes show:
one extreme message from an insider (agent 3's own certificate) that the
agents fuse makes the run ``diverged``, naming agent 3, and the world exits
``DIVERGED``; an agent paused (SIGSTOP) past ``--collect-timeout`` makes
it ``degraded`` (its neighbours closed the tick without its message) with
every estimate still the engine's replay, exit ``DEGRADED``, or ``exact``
when it still made its deadlines."""
from __future__ import annotations

import json
import os
import signal
import time
from dataclasses import replace

import numpy as np
import pytest

from diskf_mesh.core import exits
from diskf_mesh.mesh.security import credentials
from diskf_mesh.mesh.wire import codec as wire
from diskf_mesh.mesh.wire.keys import Keys
from diskf_mesh.mesh.process.runspec import RunSpec
from diskf_mesh.mesh.process.transport import ZenohTransport
from sim.launcher import free_port, loopback_options

from mesh_helpers import Progress, assert_engine_bit_for_bit, reference, start_mesh, with_credentials
from message_factory import tick_view

pytestmark = pytest.mark.mesh

SCENARIO, SETTING, INSIDER = "dynamic", "range=120", 3
# 100 ms of link latency paces the run at about 10 ticks/s, so the world's progress lines say where it is
SLOW = ["--latency-ms", "100", "--collect-timeout", "1", "--world-timeout", "30"]


def mesh_of(spec, ticks, seed, tmp_path, agent_extra=SLOW):
    world_z, agent_z = loopback_options(free_port(), with_credentials(spec, tmp_path, ticks))
    mesh = start_mesh(spec, ticks, seed, tmp_path, world_z, agent_z,
                      world_extra=["--progress", "lines", "--json", str(tmp_path / "res.json")],
                      agent_extra=agent_extra)
    return mesh, Progress(mesh), agent_z


def row_of(tmp_path) -> dict:
    return json.loads((tmp_path / "res.json").read_text())["diskf"][SETTING]


def extreme(run_id: str, tick: int, seed: int) -> bytes:
    """Agent ``INSIDER``'s message of ``tick``, well formed, with x = 9e11
    and P = 1e-6 I (within the guard's magnitude and conditioning limits)."""
    view = tick_view("diskf", SCENARIO, tick=tick, seed=seed)
    msg = view.messages[INSIDER]
    n = msg.x_pred.shape[-1]
    big, tight = np.full(n, 9e11), 1e-6 * np.eye(n)
    return wire.encode(run_id, INSIDER, tick, replace(msg, x_pred=big, x_upd=big, P_pred=tight, P_upd=tight))


def test_one_extreme_insider_message_is_diverged_naming_its_sender(tmp_path):
    spec = RunSpec(SCENARIO, "diskf", run_id=f"extreme{os.getpid()}")
    ticks, seed = 80, 0
    mesh, progress, agent_z = mesh_of(spec, ticks, seed, tmp_path)
    keys = Keys(spec.run_id)
    ids = [a.id for a in spec.load(ticks).agents]
    insider = replace(agent_z, identity=credentials.agent_identity(INSIDER), run_id=spec.run_id,
                      listen=("tls/127.0.0.1:0",))
    # agent 3 is linked to agent 8 from tick 39 on
    forged = {tick: extreme(spec.run_id, tick, seed) for tick in range(40, 70)}
    try:
        mesh.start_agents()
        with ZenohTransport(insider) as t:
            progress.wait_for(42, 120)
            k = progress.tick
            # ahead of the honest copy: a receiver holds a message up to two ticks early and fuses the first
            for tick in (k + 1, k + 2):
                t.put(keys.msg(INSIDER, to=[i for i in ids if i != INSIDER]), forged[tick])
            time.sleep(1.0)
        rc = progress.follow(300)
    finally:
        mesh.stop_all()
    row = row_of(tmp_path)
    assert rc == exits.DIVERGED, mesh.world.last_error_line()
    assert row["status"] == "diverged", row["reason"]
    dv = row["evidence"]["diverged"]
    assert dv["senders"] == [INSIDER] and k < dv["tick"] <= k + 2, dv
    # the honest agents fused it: their estimates are not the engine's
    _, ref = reference(spec, ticks, seed)
    est = json.loads((tmp_path / "est.json").read_text())
    x = np.array(est["x"], dtype=float)
    assert np.nanmax(np.abs(x - ref.x[0])) > 1e3
    assert est["status"] == "diverged"
    # the world named agent 3 (its identity sent it) as the run went and cut it off
    [q] = row["evidence"]["quarantined"]
    assert q["agent"] == INSIDER and q["named_at"] == dv["tick"] and q["from"] <= dv["tick"] + 2, q


@pytest.mark.parametrize("pause_s", [2.5])
def test_a_paused_agent_is_degraded_and_still_reproduced(tmp_path, pause_s):
    """SIGSTOP of agent 5 for ``pause_s`` (past the 1 s collect timeout,
    short of zenoh's lease and the world's tick timeout): its neighbours
    fuse without its late message, or it wakes past its own deadline and
    fuses without theirs; the world waits for its report."""
    spec = RunSpec(SCENARIO, "diskf", run_id=f"pause{os.getpid()}")
    ticks, seed, victim = 60, 0, 5
    mesh, progress, _ = mesh_of(spec, ticks, seed, tmp_path)
    try:
        mesh.start_agents()
        progress.wait_for(20, 120)
        pid = next(a for a in mesh.agents if a.name == f"agent {victim}").proc.pid
        os.kill(pid, signal.SIGSTOP)
        time.sleep(pause_s)
        os.kill(pid, signal.SIGCONT)
        rc = progress.follow(300)
    finally:
        mesh.stop_all()
    row = row_of(tmp_path)
    ev = row["evidence"]
    assert ev["differing"] == 0 and ev["unverified"] == 0, row["reason"]  # every estimate is the engine's replay
    est = json.loads((tmp_path / "est.json").read_text())
    if row["status"] == "exact":  # it made its deadlines after all: then every link was fused
        assert rc == 0
        assert_engine_bit_for_bit(est, spec, ticks, seed)
        return
    trace, _ = reference(spec, ticks, seed)
    ids = est["ids"]
    short = sum(1 for k, tick in enumerate(est["fused"]) for j, senders in enumerate(tick)
                if set(ids[s] for s in np.flatnonzero(trace.links[0, k, j]) if s != j) - set(senders))
    assert row["status"] == "degraded", row["reason"]
    assert rc == exits.DEGRADED, mesh.world.last_error_line()
    dg = ev["degraded"]
    assert dg["agent_ticks"] == short >= 1 and set(dg["why"]) <= {"late", "lost"}
    # the paused agent closed its tick late without its neighbours' messages, or they closed without its message
    assert all(e["agent"] == victim or set(e["not_fused"]) == {str(victim)} for e in dg["listed"]), dg["listed"]


def test_a_restarted_agent_replays_exactly_from_its_recording(tmp_path):
    """kill -9 of agent 5 mid-run and the same command again: the world
    hands the restart its starting state; its own check and ``replay
    RUN.mcap`` replay the restart from it and reproduce every reported
    estimate (status incomplete: the ticks it missed; accepted with
    --allow-missing)."""
    from diskf_mesh.cli import main as cli
    from sim.launcher import Child

    from mesh_helpers import spawn

    spec = RunSpec(SCENARIO, "diskf", run_id=f"restart{os.getpid()}")
    ticks, seed, victim = 120, 4, 5
    record = tmp_path / "run.mcap"
    world_z, agent_z = loopback_options(free_port(), with_credentials(spec, tmp_path, ticks))
    mesh = start_mesh(spec, ticks, seed, tmp_path, world_z, agent_z,
                      world_extra=["--progress", "lines", "--json", str(tmp_path / "res.json"), "--record", str(record)],
                      agent_extra=["--latency-ms", "25", "--collect-timeout", "1", "--world-timeout", "30"])
    progress = Progress(mesh)
    restarted = None
    try:
        mesh.start_agents()
        progress.wait_for(15, 120)
        old = next(a for a in mesh.agents if a.name == f"agent {victim}")
        os.kill(old.proc.pid, signal.SIGKILL)
        old.proc.wait(5)
        restarted = spawn(Child(f"agent {victim} (restarted)", old.argv, tmp_path / "logs" / "restarted.log"))
        rc = progress.follow(300)
    finally:
        mesh.stop_all()
        if restarted is not None and restarted.proc.poll() is None:
            restarted.proc.kill()
            restarted.proc.wait(5)
    row = row_of(tmp_path)
    assert rc == exits.INCOMPLETE, mesh.world.last_error_line()
    ev = row["evidence"]
    assert row["status"] == "incomplete", row["reason"]
    assert [r["agent"] for r in ev["restarts"]] == [victim], ev["restarts"]
    assert ev["differing"] == 0 and ev["unverified"] == 0, row["reason"]
    # the recording: replay restarts the agent from the recorded starting state
    assert cli.main(["replay", str(record)]) == exits.INCOMPLETE
    assert cli.main(["replay", str(record), "--allow-missing", "1"]) == 0
    from diskf_mesh.recording.reader import read
    from diskf_mesh.recording.replay import compare, recording_status, replay
    from diskf_mesh.recording.summary import summary

    rec = read(record)
    assert summary(rec)["run_status"]["status"] == "incomplete"  # inspect: the world's own check, recorded
    assert compare(rec, replay(rec)).equal
    st = recording_status(rec)
    assert st.status == "incomplete" and st.evidence["differing"] == 0 and st.evidence["digests_checked"] > 0
