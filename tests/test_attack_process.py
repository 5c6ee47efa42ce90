"""Process faults on the real mesh, real processes on loopback:
a duplicate agent id (started mid-run, and two at once), an agent frozen
(SIGSTOP) past zenoh's lease then woken, a frozen world, kill -9 of three
agents, kill -9 and restart (re-initialised from the neighbour in range),
and a second world on one run id. Every case checks the exit statuses and
the result JSON's completeness and missing counts; zenoh's lease is cut to
``LEASE_MS`` so that a freeze past it takes seconds."""
from __future__ import annotations

import json
import os
import signal
import time

import numpy as np
import pytest

from diskf_mesh.data import metrics
from diskf_mesh.engine.batch import Estimates
from diskf_mesh.mesh.process.runspec import RunSpec, world_command
from diskf_mesh.mesh.process.transport import ALIVE_GATE_ENV
from diskf_mesh.mesh.process.zenoh_config import ZenohOptions
from sim.launcher import Child, free_port, loopback_options

from mesh_helpers import LEASE_MS, Progress, assert_same, error_lines, reference, spawn, start_mesh, with_credentials, \
    with_lease

pytestmark = pytest.mark.mesh

SCENARIO = "dynamic"
SETTING = "range=120"
FREEZE_S = 3 * LEASE_MS / 1000  # well past the lease
# 25 ms of link latency paces a run (about 40 ticks/s at most), so that it is still going when a
# frozen or restarted process comes back
PACED = ["--latency-ms", "25", "--collect-timeout", "1", "--world-timeout", "30"]


def lease_mesh(spec, ticks, seed, tmp_path, agent_extra=PACED, world_extra=()):
    world_z, agent_z = loopback_options(free_port(), with_credentials(spec, tmp_path, ticks))
    mesh = start_mesh(spec, ticks, seed, tmp_path, with_lease(world_z), with_lease(agent_z),
                      world_extra=["--progress", "lines", "--json", str(tmp_path / "res.json"), *world_extra],
                      agent_extra=agent_extra)
    return mesh, Progress(mesh)


def results(tmp_path) -> tuple:
    """(estimates doc, the results row of the run)."""
    est = json.loads((tmp_path / "est.json").read_text())
    res = json.loads((tmp_path / "res.json").read_text())
    return est, res["diskf"][SETTING]


def agent(mesh, i: int) -> Child:
    return next(a for a in mesh.agents if a.name == f"agent {i}")


def gap_of(est: dict, i: int) -> np.ndarray:
    reported = np.array(est["reported"])
    return 1 + np.flatnonzero(~reported[:, est["ids"].index(i)])


def assert_only_missing(est: dict, row: dict, victims) -> None:
    """Only ``victims`` miss ticks, and the counts say so everywhere."""
    reported = np.array(est["reported"])
    for j, i in enumerate(est["ids"]):
        if i not in victims:
            assert reported[:, j].all(), f"agent {i} missed ticks"
    expect = {str(i): int((~reported[:, est["ids"].index(i)]).sum()) for i in victims}
    assert {i: m["ticks"] for i, m in row["missing"].items()} == expect
    assert row["missing_agent_ticks"] == est["missing_agent_ticks"] == sum(expect.values()) > 0
    assert row["complete"] is False and est["complete"] is False
    assert row["agent_ticks"] == reported.size
    assert row["missing_ticks"] == {str(i): gap_of(est, i).tolist() for i in victims}


# --------------------------------------------------------------------------
# duplicate ids
# --------------------------------------------------------------------------
def test_duplicate_id_mid_run_leaves_and_the_run_is_untouched(tmp_path):
    """A second process for agent 5 while the run goes: it exits 2 with one
    line naming the id; the world counts it; the run is complete and equals
    the engine bit for bit (nothing of the duplicate was fused)."""
    spec = RunSpec(SCENARIO, "diskf", run_id=f"dup{os.getpid()}")
    ticks, seed = 150, 3
    mesh, progress = lease_mesh(spec, ticks, seed, tmp_path, agent_extra=["--latency-ms", "10"])
    try:
        mesh.start_agents()
        progress.wait_for(10, 120)
        dup = spawn(Child("agent 5 (duplicate)", agent(mesh, 5).argv, tmp_path / "logs" / "dup.log"))
        assert dup.proc.wait(30) == 2
        assert progress.follow(240) == 0, mesh.world.last_error_line()
        assert [a.proc.wait(10) for a in mesh.agents] == [0] * len(mesh.agents)
    finally:
        mesh.stop_all()
    lines = error_lines(dup)
    assert len(lines) == 1 and "agent id 5" in lines[0], lines
    est, row = results(tmp_path)
    assert row["complete"] is True and row["missing_agent_ticks"] == 0
    assert row["duplicate_ids"] == {"5": 1}
    assert_same(est, reference(spec, ticks, seed)[1])


def test_two_processes_with_one_id_at_once(tmp_path):
    """Two processes for agent 3 started together with the others: exactly
    one exits 2, the run is complete and equals the engine."""
    spec = RunSpec(SCENARIO, "diskf", run_id=f"dup2{os.getpid()}")
    ticks, seed = 60, 1
    mesh, progress = lease_mesh(spec, ticks, seed, tmp_path, agent_extra=[])
    twin = Child("agent 3 (twin)", agent(mesh, 3).argv, tmp_path / "logs" / "twin.log")
    try:
        mesh.start_more([twin])  # started as the agents are, just before them
        mesh.start_agents()
        assert progress.follow(240) == 0, mesh.world.last_error_line()
        rcs, others = exit_statuses(mesh, twin)
    finally:
        stop_with_twin(mesh, twin)
    assert sorted(rcs) == [0, 2] and others == [0] * 8
    est, row = results(tmp_path)
    assert row["complete"] is True and row["rejoins"] == {}
    assert_all_fused(est, ticks)
    assert_same(est, reference(spec, ticks, seed)[1])


def test_a_twin_that_declares_after_the_run_started_leaves(tmp_path):
    """Two processes for agent 3, the first started (the smaller nonce)
    descheduled between its claim's query and its token (as on a loaded
    machine) until the run is ticking with the other: the late one leaves
    (exit 2), the one working since tick 1 keeps the id and keeps fusing its
    neighbours; the run equals the engine."""
    spec = RunSpec(SCENARIO, "diskf", run_id=f"duplate{os.getpid()}")
    ticks, seed = 300, 1  # long enough that the twin's token comes while the run ticks
    mesh, progress = lease_mesh(spec, ticks, seed, tmp_path, agent_extra=[])
    twin = Child("agent 3 (twin)", agent(mesh, 3).argv, tmp_path / "logs" / "twin.log")
    try:
        gate = tmp_path / "gate"
        spawn(twin, env={ALIVE_GATE_ENV: str(gate)})
        time.sleep(0.5)  # the twin's nonce is the smaller
        mesh.start_agents()
        progress.wait_for(20, 120)  # the run ticks with the other agent 3
        gate.touch()  # only now the twin declares its token
        assert progress.follow(240) == 0, mesh.world.last_error_line()
        rcs, others = exit_statuses(mesh, twin, twin_wait=30)
    finally:
        stop_with_twin(mesh, twin)
    assert rcs == [0, 2] and others == [0] * 8
    est, row = results(tmp_path)
    assert row["complete"] is True and row["rejoins"] == {} and row["duplicate_ids"] == {"3": 1}
    assert_all_fused(est, ticks)
    assert_same(est, reference(spec, ticks, seed)[1])


def exit_statuses(mesh, twin, twin_wait: float = 10.0) -> tuple:
    """([agent 3's exit status, its twin's], the other agents' exit statuses)."""
    rcs = [agent(mesh, 3).proc.wait(10), twin.proc.wait(twin_wait)]
    return rcs, [a.proc.wait(10) for a in mesh.agents if a.name != "agent 3"]


def stop_with_twin(mesh, twin) -> None:
    mesh.stop_all()
    if twin.proc.poll() is None:
        twin.proc.kill()


def assert_all_fused(est, ticks: int) -> None:
    """Every agent published every tick and fused every message sent to it."""
    for i, c in est["agent_counters"].items():
        assert c["published"] == ticks and c["fused"] == c["sent"] and c["late"] == 0, (i, c)


def test_a_second_world_on_one_run_id_is_refused(tmp_path):
    """Two runs started by hand with one run id (``default``) would mix: the
    second world exits 2 at once, the first is not disturbed."""
    port = free_port()
    ep = f"tcp/127.0.0.1:{port}"
    spec = RunSpec(SCENARIO, "diskf")  # run id "default"
    first = spawn(Child("world 1", world_command(spec, 20, 0, ZenohOptions(listen=(ep,), no_multicast_scouting=True, insecure=True),
                                                 ["--progress", "none", "--startup-timeout", "20"]),
                        tmp_path / "w1.log"))
    second = Child("world 2", world_command(spec, 20, 0, ZenohOptions(connect=(ep,), listen=("tcp/127.0.0.1:0",),
                                                                      no_multicast_scouting=True, insecure=True),
                                            ["--progress", "none"]), tmp_path / "w2.log")
    try:
        time.sleep(1.5)
        spawn(second)
        assert second.proc.wait(30) == 2
        assert first.proc.poll() is None  # still waiting for its agents
    finally:
        for c in (first, second):
            if c.proc.poll() is None:
                c.proc.kill()
                c.proc.wait(5)
    lines = error_lines(second)
    assert len(lines) == 1 and "default" in lines[0], lines


# --------------------------------------------------------------------------
# frozen processes
# --------------------------------------------------------------------------
def test_frozen_agent_rejoins_when_it_wakes(tmp_path):
    """Agent 6 frozen (SIGSTOP) past the lease: the world drops it and goes
    on; woken (SIGCONT), it rejoins with a new ready token and reports to the
    end. The world exits 3 (agent-ticks missing, all of agent 6's: it left,
    then rejoined), agent 6 exits 0 on the world's "done"."""
    spec = RunSpec(SCENARIO, "diskf", run_id=f"frozenagent{os.getpid()}")
    ticks, seed, victim = 400, 2, 6
    mesh, progress = lease_mesh(spec, ticks, seed, tmp_path)
    try:
        mesh.start_agents()
        progress.wait_for(20, 120)
        frozen = agent(mesh, victim)
        os.kill(frozen.proc.pid, signal.SIGSTOP)
        time.sleep(FREEZE_S)
        os.kill(frozen.proc.pid, signal.SIGCONT)
        assert progress.follow(300) == 3, mesh.world.last_error_line()
        rcs = [a.proc.wait(10) for a in mesh.agents]
    finally:
        mesh.stop_all()
    assert rcs == [0] * len(mesh.agents)
    est, row = results(tmp_path)
    assert_only_missing(est, row, [victim])
    gap = gap_of(est, victim)
    assert (np.diff(gap) == 1).all() and gap[-1] < ticks, gap  # one gap, and back before the end
    assert set(row["missing"][str(victim)]["why"]) <= {"left", "rejoining", "no report"}
    assert [r["tick"] for r in row["rejoins"][str(victim)]] == [gap[-1] + 1]
    assert len(error_lines(mesh.world)) == 1


def test_frozen_world_makes_the_agents_wait(tmp_path):
    """The world frozen past the lease: every agent sees it go and waits; the
    world wakes, finds its links closed, pauses until every agent is back,
    sends its open tick again and goes on. Nothing is missing: exit 0 for
    every process, complete, the estimates bit for bit the engine's."""
    spec = RunSpec(SCENARIO, "diskf", run_id=f"frozenworld{os.getpid()}")
    ticks, seed = 200, 5
    mesh, progress = lease_mesh(spec, ticks, seed, tmp_path)
    try:
        mesh.start_agents()
        progress.wait_for(20, 120)
        os.kill(mesh.world.proc.pid, signal.SIGSTOP)
        time.sleep(FREEZE_S)
        frozen_at = progress.tick
        os.kill(mesh.world.proc.pid, signal.SIGCONT)
        assert progress.follow(300) == 0, mesh.world.last_error_line()
        rcs = [a.proc.wait(10) for a in mesh.agents]
    finally:
        mesh.stop_all()
    assert rcs == [0] * len(mesh.agents)
    est, row = results(tmp_path)
    assert row["complete"] is True and row["missing_agent_ticks"] == 0 and row["missing"] == {}
    # (a busy machine may add a short pause of its own: a late main thread looks like a freeze)
    assert any(p["why"] == "the world was frozen" and abs(p["tick"] - frozen_at) <= 1 and p["seconds"] >= 1
               for p in row["pauses"]), row["pauses"]
    assert_same(est, reference(spec, ticks, seed)[1])


# --------------------------------------------------------------------------
# kills
# --------------------------------------------------------------------------
def test_kill_9_of_three_agents(tmp_path):
    """Three agents killed mid-run: the world goes on with six and exits 3;
    with ``--allow-missing`` 0.9 it exits 0, and the results say complete:
    false either way, with the three agents' ticks from their death on
    (they left) and nothing else missing. The others exit 0."""
    spec = RunSpec(SCENARIO, "diskf", run_id=f"kill3{os.getpid()}")
    ticks, victims = 300, [2, 5, 8]
    mesh, progress = lease_mesh(spec, ticks, 6, tmp_path, world_extra=["--allow-missing", "0.9"])
    try:
        mesh.start_agents()
        progress.wait_for(20, 120)
        for i in victims:
            os.kill(agent(mesh, i).proc.pid, signal.SIGKILL)
        killed_at = progress.tick
        assert progress.follow(300) == 0, mesh.world.last_error_line()
        rcs = {int(a.name.split()[1]): a.proc.wait(10) for a in mesh.agents}
    finally:
        mesh.stop_all()
    assert rcs == {i: (-signal.SIGKILL if i in victims else 0) for i in rcs}
    est, row = results(tmp_path)
    assert_only_missing(est, row, victims)
    for i in victims:
        gap = gap_of(est, i)
        assert killed_at - 1 <= gap[0] <= killed_at + 1 and gap[-1] == ticks and (np.diff(gap) == 1).all(), gap
        assert row["missing"][str(i)]["why"].keys() <= {"left", "no report"}
    assert error_lines(mesh.world) == []  # accepted: an info line, no error


def test_kill_9_and_rejoin_from_the_neighbour_in_range(tmp_path):
    """kill -9 of agent 5 mid-run, then the same command again: the restart
    re-initialises from the fused estimate of tick J - 1 (J: its first tick)
    of the most certain agent in range at J - 1 (positions from the
    scenario, computed here), its state error is within 2x of the run
    without the kill 20 ticks later, and the world exits 3 counting exactly
    the ticks it did not report."""
    spec = RunSpec(SCENARIO, "diskf", run_id=f"rejoin{os.getpid()}")
    ticks, seed, victim = 200, 4, 5
    mesh, progress = lease_mesh(spec, ticks, seed, tmp_path)
    restarted = None
    try:
        mesh.start_agents()
        progress.wait_for(15, 120)
        old = agent(mesh, victim)
        os.kill(old.proc.pid, signal.SIGKILL)
        assert old.proc.wait(5) == -signal.SIGKILL
        killed_at = progress.tick
        restarted = spawn(Child(f"agent {victim} (restarted)", old.argv, tmp_path / "logs" / "restarted.log"))
        assert progress.follow(300) == 3, mesh.world.last_error_line()
        assert restarted.proc.wait(10) == 0, restarted.last_error_line()
        assert all(a.proc.wait(10) == 0 for a in mesh.agents if a is not old)
    finally:
        mesh.stop_all()
        if restarted is not None and restarted.proc.poll() is None:
            restarted.proc.kill()
            restarted.proc.wait(5)
    est, row = results(tmp_path)
    assert_only_missing(est, row, [victim])
    gap = gap_of(est, victim)
    assert gap[0] >= killed_at - 1 and (np.diff(gap) == 1).all(), gap
    J = int(gap[-1]) + 1
    assert J + 30 <= ticks, f"rejoined too late to judge (tick {J})"
    assert row["missing"][str(victim)]["why"].keys() <= {"left", "rejoining", "no report"}

    # the source, from the scenario's geometry at J - 1 and the fused estimates the world recorded
    trace, ref = reference(spec, ticks, seed)
    ids = est["ids"]
    j = ids.index(victim)
    pos = trace.positions[J - 2]
    reported = np.array(est["reported"])
    P = np.array(est["P"], dtype=float)
    near = [i for q, i in enumerate(ids) if q != j and reported[J - 2, q]
            and np.sum((pos[q] - pos[j]) ** 2) <= spec.load().comm_range ** 2]
    assert near, "no agent in range of the victim at its rejoin: pick another victim or seed"
    expected = min(near, key=lambda i: (np.trace(P[J - 2, ids.index(i)]), i))
    assert row["rejoins"] == {str(victim): [{"tick": J, "source": expected}]}
    assert est["rejoins"] == row["rejoins"]

    # its error 20 ticks on, against the run without the kill (= the engine, bit for bit)
    x = np.array(est["x"], dtype=float)
    mesh_est = Estimates(np.nan_to_num(x)[None], np.array([[np.eye(2)] * len(ids)] * ticks)[None],
                         np.zeros((1, ticks, len(ids), 1)), np.zeros((1, ticks, len(ids)), dtype=bool))
    e_kill = metrics.errors(trace, mesh_est)[0][0, :, j]
    e_clean = metrics.errors(trace, ref)[0][0, :, j]
    window = slice(J + 20 - 1, J + 30 - 1)  # ticks J+20 .. J+29
    assert e_kill[window].mean() <= 2 * e_clean[window].mean(), (e_kill[window], e_clean[window])


def test_completeness_in_the_results():
    """The world's accounting of a record, without processes: counts, reasons,
    the one line."""
    from collections import Counter

    from diskf_mesh.mesh.protocol.reports import RunReports
    from sim.world import WorldRecord, completeness, missing_line

    K, N = 4, 3
    rep = np.ones((K, N), dtype=bool)
    why = np.full((K, N), "", dtype=object)
    rep[1:, 1], why[1, 1], why[2, 1] = False, "left", "rejoining"   # tick 4: never opened ("not run")
    rec = WorldRecord(**{**RunReports.empty(K, N, 2, 1), "reported": rep}, ids=(1, 2, 3), why=why,
                      duplicates=Counter({3: 1}), rejoins={2: [{"tick": 4, "source": 1}]})
    c = completeness(rec)
    assert c["complete"] is False and c["agent_ticks"] == 12 and c["missing_agent_ticks"] == 3
    assert c["missing"] == {"2": {"ticks": 3, "why": {"left": 1, "not run": 1, "rejoining": 1}}}
    assert c["duplicate_ids"] == {"3": 1} and c["rejoins"] == {"2": [{"tick": 4, "source": 1}]}
    assert missing_line(c).startswith("3 of 12 agent-ticks missing (25.0 %): agent 2: 3")
    rep[:] = True
    assert completeness(rec)["complete"] is True
