"""Faults on the real mesh: lossy, slow, duplicating and reordering
links, agents killed and restarted, the world killed, another run on the same
network. Every run completes (or ends as it must), the message counters add up,
and the estimates are those of the in-process engine on what was delivered."""
from __future__ import annotations

import contextlib
import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from diskf_mesh.engine import batch as engine
from diskf_mesh.mesh.wire import codec as wire
from diskf_mesh.mesh.wire.counters import Counters
from diskf_mesh.data.faults import FaultConfig, delivered_links
from diskf_mesh.mesh.wire.keys import Keys
from diskf_mesh.mesh.process.runspec import RunSpec
from diskf_mesh.mesh.process.transport import ZenohTransport
from diskf_mesh.mesh.process.zenoh_config import ZenohOptions
from diskf_mesh.data.scenario import simulate
from sim.launcher import free_port

from mesh_helpers import Progress, assert_same, reference, spawn, start_mesh, up
from message_factory import tick_view

pytestmark = pytest.mark.mesh

SCENARIO = "dynamic"
SETTING = "range=120"


def on_delivered_links(spec: RunSpec, ticks: int, seed: int, faults: FaultConfig, deadline_s=np.inf):
    """Engine estimates on the links the seeded fault layer delivers."""
    scn = spec.load(ticks)
    trace = simulate(scn, [seed])
    links = delivered_links(trace.links[0], trace.sensors.ids, faults, seed, deadline_s)
    return trace, engine.run(trace.with_links(links[None]), spec.algorithm, scn.params)


def counters_of(res: dict, algorithm="diskf") -> dict:
    row = res[algorithm][SETTING]
    return {int(i): Counters.from_dict({k: v for k, v in c.items() if k != "rejected"}
                                       | {f"rejected.{r}": n for r, n in c["rejected"].items()})
            for i, c in row["counters"].items()}


def assert_books_balance(cs: dict, ticks: int) -> None:
    scn = RunSpec(SCENARIO).load(ticks)
    links = simulate(scn, [0]).links[0]  # (K, N, N): range links do not depend on the seed
    ids = [a.id for a in scn.agents]
    for i, c in cs.items():
        assert c.imbalance() == [], (i, c)
        assert c.published == ticks
        # a message is addressed to the agents in range at its tick (Keys.msg): every link into
        # this one carried one (those of the last tick from agents it did not wait for may come
        # after its last report), and nothing out of range reached it
        row = links[:, ids.index(i)].copy()
        row[:, ids.index(i)] = False
        into = int(row.sum())
        assert into - int(row[-1].sum()) <= c.sent + c.out_of_range <= into, (i, c)
        assert c.out_of_range == 0, (i, c)


@pytest.mark.parametrize("loss", [0.0, 0.1, 0.3, 0.5])
def test_lossy_links(tmp_path, loss):
    ticks, seed = 40, 3
    spec = RunSpec(SCENARIO, "diskf")
    done, est, res = up(tmp_path, "--scenario", SCENARIO, "--ticks", str(ticks), "--seed", str(seed),
                        "--loss", str(loss))
    assert done.returncode == 0, done.stderr
    cs = counters_of(res)
    assert_books_balance(cs, ticks)
    sent, lost = sum(c.sent for c in cs.values()), sum(c.lost for c in cs.values())
    assert sum(c.fused for c in cs.values()) == sent - lost          # nothing late: no latency
    assert abs(lost / sent - loss) < 0.08
    assert res["diskf"][SETTING]["faults"]["loss"] == loss
    _, ref = on_delivered_links(spec, ticks, seed, FaultConfig(loss=loss))
    assert_same(est, ref)   # the agents fused exactly what the fault layer delivered


def test_latency_beyond_the_tick_deadline(tmp_path):
    """Every neighbour's message arrives 400 ms after it was sent, agents
    collect for 150 ms: all late, counted, dropped; each agent fuses alone."""
    ticks, seed = 12, 1
    faults = FaultConfig(latency_ms=400)
    done, est, res = up(tmp_path, "--scenario", SCENARIO, "--ticks", str(ticks), "--seed", str(seed),
                        "--latency-ms", "400", "--collect-timeout", "0.15")
    assert done.returncode == 0, done.stderr
    cs = counters_of(res)
    assert_books_balance(cs, ticks)
    assert all(c.fused == 0 for c in cs.values())
    assert sum(c.late for c in cs.values()) > 0
    _, ref = on_delivered_links(RunSpec(SCENARIO, "diskf"), ticks, seed, faults, deadline_s=0.15)
    assert_same(est, ref)


def test_duplicates_and_reordering(tmp_path):
    """Duplicated, jittered and reordered copies: each message is fused once,
    in time, in scenario order: the estimates are the fault-free ones."""
    ticks, seed = 30, 2
    done, est, res = up(tmp_path, "--scenario", SCENARIO, "--ticks", str(ticks), "--seed", str(seed),
                        "--duplicate", "0.3", "--reorder", "0.3", "--reorder-ms", "20", "--latency-ms", "2",
                        "--jitter-ms", "2")
    assert done.returncode == 0, done.stderr
    cs = counters_of(res)
    assert_books_balance(cs, ticks)
    assert sum(c.duplicate for c in cs.values()) > 0
    assert all(c.fused == c.received and c.lost == 0 and c.late == 0 for c in cs.values())
    assert_same(est, reference(RunSpec(SCENARIO, "diskf"), ticks, seed)[1])


# --------------------------------------------------------------------------
# node faults (kill -9 and rejoin, freezes, duplicates: tests/test_attack_process.py)
# --------------------------------------------------------------------------
def test_world_death_ends_every_agent_in_one_line(tmp_path):
    """The world killed: every agent waits ``--world-timeout`` for it to come
    back (a frozen world does), then exits 1 with one line."""
    spec = RunSpec(SCENARIO, "diskf", run_id="worlddeath")
    mesh = start_mesh(spec, 400, 0, tmp_path, world_extra=["--progress", "lines"],
                      agent_extra=["--world-timeout", "4"])
    try:
        progress = Progress(mesh)
        mesh.start_agents()
        progress.wait_for(10, 30)
        os.kill(mesh.world.proc.pid, signal.SIGKILL)
        t0 = time.monotonic()
        rcs = [a.proc.wait(20) for a in mesh.agents]
        took = time.monotonic() - t0
    finally:
        mesh.stop_all()
    assert rcs == [1] * len(mesh.agents)
    assert 3 < took < 15
    for a in mesh.agents:
        lines = [ln for ln in a.log.read_text().splitlines() if ln.strip()]
        errors = [ln for ln in lines if ln.startswith("error:")]
        assert len(errors) == 1 and "the world is gone" in errors[0], lines


def _pids_of(run_id: str) -> list:
    out = []
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            try:
                cmd = (d / "cmdline").read_bytes().split(b"\0")
            except OSError:
                continue
            if run_id.encode() in cmd:
                out.append((int(d.name), [c.decode(errors="replace") for c in cmd]))
    return out


def _wait_until_ready(run_id: str, n: int, timeout: float) -> None:
    """Until ``n`` agents of run ``run_id`` (under ``up``: its world's port from
    its command line) hold their ready tokens."""
    deadline = time.monotonic() + timeout
    port = None
    while port is None and time.monotonic() < deadline:
        port = next((cmd[cmd.index("--listen") + 1] for _, cmd in _pids_of(run_id) if "sim.world" in cmd), None)
        time.sleep(0.2)
    assert port is not None, "no world"
    seen, keys = set(), Keys(run_id)
    with ZenohTransport(ZenohOptions(connect=(port,), listen=("tcp/127.0.0.1:0",), no_multicast_scouting=True)) as z:
        z.watch_tokens(keys.ready("*"), lambda key, up: seen.add(key) if up else seen.discard(key))
        while len(seen) < n:
            assert time.monotonic() < deadline, f"{len(seen)} of {n} agents ready after {timeout} s"
            time.sleep(0.2)


def _agent_pid(run_id: str, i: int, timeout: float, every: float) -> int:
    """The pid of agent ``i`` of run ``run_id`` once it is there (looking
    every ``every`` seconds)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        pid = next((pid for pid, cmd in _pids_of(run_id)
                    if "agents.agent" in cmd and cmd[cmd.index("--id") + 1] == str(i)), None)
        if pid is not None:
            return pid
        time.sleep(every)
    raise AssertionError(f"agent {i} never started")


@contextlib.contextmanager
def _killed_at_the_end(proc):
    """``proc`` (an ``up``) killed and reaped if it is still running when
    the block ends, however it ends."""
    try:
        yield proc
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate(timeout=10)


@pytest.mark.parametrize("allow", [None, "1"])
def test_up_names_the_child_that_died(tmp_path, allow):
    """An agent killed under ``up``: without ``--allow-missing`` up stops every
    child, names the dead one and exits 1, and the world (stopped) still
    writes what it measured, complete: false; with it, the run goes on
    without that agent and up exits 0 with one warning line."""
    run_id = f"upkill{os.getpid()}{'a' if allow else ''}"
    ticks = 300 if allow else 3000  # without: far more than the run lasts (25 ms latency: 40 ticks/s at most)
    up_proc = subprocess.Popen([sys.executable, "-m", "sim.launcher", "--scenario", SCENARIO, "--algorithm", "diskf",
                                "--ticks", str(ticks), "--run-id", run_id, "--quiet",
                                "--json", str(tmp_path / "r.json"),
                                "--logs", str(tmp_path / "logs"), "--latency-ms", "25", "--insecure",  # plain: the
                                *(["--allow-missing", allow] if allow else [])],  # test watches the tokens itself
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    with _killed_at_the_end(up_proc):
        victim = _agent_pid(run_id, 7, timeout=30, every=0.2)
        _wait_until_ready(run_id, 9, timeout=120)  # the run is about to start (a busy machine is slow to start)
        time.sleep(1)
        os.kill(victim, signal.SIGKILL)
        _, err = up_proc.communicate(timeout=150)
    row = json.loads((tmp_path / "r.json").read_text())["diskf"][SETTING]
    assert row["complete"] is False and "7" in row["missing"]
    if allow:
        assert list(row["missing"]) == ["7"]
        assert up_proc.returncode == 0, err
        assert len([ln for ln in err.splitlines() if ln.startswith("warning: incomplete run")]) == 1, err
        assert row["missing"]["7"]["ticks"] == row["missing_agent_ticks"] > 0
    else:
        assert up_proc.returncode == 1
        assert "agent 7 failed (killed by signal 9)" in err and "stopped 10 processes" in err, err
    time.sleep(0.5)
    assert _pids_of(run_id) == [], "children left behind"


@pytest.mark.parametrize("allow", [None, "0.5"])
def test_up_an_agent_that_dies_before_it_is_ready(tmp_path, allow):
    """An agent killed before it is ready (at its first sight): the run is
    not a failed process but a start-up the world gives up on after
    ``--startup-timeout``: incomplete, the world's reason first (as on the
    simulated network), one error line, exit 3, no traceback; with
    ``--allow-missing`` the world starts without it and up exits 0."""
    run_id = f"upearly{os.getpid()}{'a' if allow else ''}"
    up_proc = subprocess.Popen([sys.executable, "-m", "sim.launcher", "--scenario", SCENARIO, "--algorithm", "diskf",
                                "--ticks", "4", "--run-id", run_id, "--quiet", "--startup-timeout", "3",
                                "--json", str(tmp_path / "r.json"), "--logs", str(tmp_path / "logs"),
                                *(["--allow-missing", allow] if allow else [])],
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    with _killed_at_the_end(up_proc):
        os.kill(_agent_pid(run_id, 7, timeout=60, every=0.01), signal.SIGKILL)
        _, err = up_proc.communicate(timeout=120)
    row = json.loads((tmp_path / "r.json").read_text())["diskf"][SETTING]
    assert row["status"] == "incomplete" and list(row["missing"]) == (["7"] if allow else ["1", "2", "3", "4", "5",
                                                                                           "6", "7", "8", "9"])
    errors = [ln for ln in err.splitlines() if ln.startswith("error:")]
    if allow:
        assert up_proc.returncode == 0, err
        assert row["missing"]["7"] == {"ticks": 4, "why": {"never joined": 4}} and errors == [], err
    else:
        assert up_proc.returncode == 3, err
        assert row["reason"].startswith("after 3 s waiting for the agents: no agent process for id 7 ")
        assert row["ended_early"] in row["reason"] and row["missing_fraction"] == 1.0
        assert len(errors) == 1 and errors[0].startswith(f"error: incomplete run: {row['ended_early']}: "), err
    assert "Traceback" not in err + (tmp_path / "logs" / "world.log").read_text()
    time.sleep(0.5)
    assert _pids_of(run_id) == [], "children left behind"


def test_a_world_that_gives_up_at_start_up_ends_with_a_status(tmp_path):
    """The world started by hand with agent 9 never there: after
    ``--startup-timeout`` it gives up, and still writes its results and
    estimates with a status (incomplete, its reason first) and exits 3."""
    spec = RunSpec(SCENARIO, "diskf", run_id=f"giveup{os.getpid()}")
    mesh = start_mesh(spec, 4, 0, tmp_path, world_extra=["--startup-timeout", "2", "--json", str(tmp_path / "r.json")])
    mesh.agents = mesh.agents[:-1]
    try:
        mesh.start_agents()
        rc = mesh.world.proc.wait(60)
    finally:
        mesh.stop_all()
    row = json.loads((tmp_path / "r.json").read_text())["diskf"][SETTING]
    est = json.loads((tmp_path / "est.json").read_text())
    assert rc == 3, mesh.world.last_error_line()
    assert row["status"] == est["status"] == "incomplete" and not np.array(est["reported"]).any()
    assert row["reason"].startswith("after 2 s waiting for the agents: no agent process for id 9 (no liveliness token)")
    log = mesh.world.log.read_text()
    assert "Traceback" not in log and [ln for ln in log.splitlines() if ln.startswith("error:")] == [
        f"error: world: incomplete run: {row['ended_early']}: no tick ran (36 agent-ticks missing) "
        "(no agent-tick was reported: nothing to accept)"]


def test_a_world_interrupted_before_tick_1_ends_with_a_status(tmp_path):
    """The world stopped (SIGTERM) while it waits for its agents: its
    results say incomplete, interrupted before tick 1, and it exits 3."""
    spec = RunSpec(SCENARIO, "diskf", run_id=f"interrupt{os.getpid()}")
    mesh = start_mesh(spec, 4, 0, tmp_path, world_extra=["--json", str(tmp_path / "r.json")])
    host, port = mesh.world_endpoints[0].split("/", 1)[1].rsplit(":", 1)
    try:
        deadline = time.monotonic() + 60
        while True:  # the world listens: its session is open, it waits for the agents
            try:
                socket.create_connection((host, int(port)), timeout=1).close()
                break
            except OSError:
                assert time.monotonic() < deadline, "the world never listened"
                time.sleep(0.1)
        mesh.world.proc.send_signal(signal.SIGTERM)
        rc = mesh.world.proc.wait(60)
    finally:
        mesh.stop_all()
    row = json.loads((tmp_path / "r.json").read_text())["diskf"][SETTING]
    assert rc == 3, mesh.world.last_error_line()
    assert row["status"] == "incomplete" and row["ended_early"] == "interrupted (SIGTERM) before tick 1"
    assert row["reason"].startswith(row["ended_early"]) and row["missing_fraction"] == 1.0
    assert "Traceback" not in mesh.world.log.read_text()


def test_a_late_agent_joins_a_run_that_started_without_it(tmp_path):
    """``--allow-missing``: the world starts without agent 9 (not there after
    ``--startup-timeout``); agent 9 started once the run goes joins it
    (the world's answer to its start query), reports every tick from then
    on, and the run checks out: incomplete (its ticks before), every
    reported estimate the engine's, exit 0 within ``--allow-missing`` (and
    ``--allow-degraded``: a neighbour may fuse the first message of the
    agent that joins too late, as after any rejoin)."""
    spec = RunSpec(SCENARIO, "diskf", run_id=f"latejoin{os.getpid()}")
    mesh = start_mesh(spec, 300, 0, tmp_path, world_extra=["--progress", "lines", "--allow-missing", "0.9",
                                                           "--allow-degraded", "--startup-timeout", "2"])
    progress = Progress(mesh)
    late = mesh.agents[-1]
    mesh.agents = mesh.agents[:-1]
    try:
        mesh.start_agents()
        progress.wait_for(1, 60)
        mesh.agents.append(spawn(late))
        rc = progress.follow(120)
        rcs = [a.proc.wait(30) for a in mesh.agents]
    finally:
        mesh.stop_all()
    est = json.loads((tmp_path / "est.json").read_text())
    assert rc == 0 and rcs == [0] * 9, (mesh.world.last_error_line(), late.last_error_line())
    reported = np.array(est["reported"])
    ((joined,),) = est["rejoins"].values()
    assert list(est["rejoins"]) == ["9"] and joined["tick"] > 1
    assert reported[:, :-1].all() and not reported[:joined["tick"] - 1, -1].any() and reported[joined["tick"]:, -1].all()
    assert est["status"] == "incomplete" and est["evidence"]["differing"] == 0
    assert set(est["missing"]["9"]["why"]) <= {"never joined", "rejoining"}


# --------------------------------------------------------------------------
# access: another run on the same network
# --------------------------------------------------------------------------
def test_another_run_cannot_feed_this_one(tmp_path):
    """Run A (Scenario 2) and run B (Scenario 1: agent ids 1-4 again, other run
    id and seed) on one zenoh network, plus a process publishing run B's
    messages and garbage on run A's agent keys. Run A's agents, through their
    real subscriptions, never fuse any of it: run A equals the engine, and
    what reached its keys was rejected by reason."""
    ticks = 300  # about 1.5 s of lockstep: the rogue's session is on the mesh for most of it
    a_spec, b_spec = RunSpec(SCENARIO, "diskf", run_id="run-a"), RunSpec("quadrants", "diskf", run_id="run-b")
    pa, pb = free_port(), free_port()
    a_dir, b_dir = tmp_path / "a", tmp_path / "b"
    a_dir.mkdir()
    b_dir.mkdir()
    # plain zenoh (--insecure): this test is about the key space and the guard, not about credentials
    z = lambda listen, *connect: ZenohOptions(listen=(listen,), connect=connect, no_multicast_scouting=True,  # noqa
                                              insecure=True)
    a_ep, b_ep = f"tcp/127.0.0.1:{pa}", f"tcp/127.0.0.1:{pb}"
    a = start_mesh(a_spec, ticks, 11, a_dir, z(a_ep), z("tcp/127.0.0.1:0", a_ep),
                   world_extra=["--json", str(a_dir / "res.json")])
    b = start_mesh(b_spec, ticks, 12, b_dir, z(b_ep, a_ep), z("tcp/127.0.0.1:0", b_ep, a_ep))
    joined = z("tcp/127.0.0.1:0", a_ep)
    try:
        view = tick_view("diskf", tick=5)  # real, well-formed messages, but of run B
        keys_a = Keys(a_spec.run_id)
        with ZenohTransport(joined) as rogue:
            stop = time.monotonic() + 30
            while not rogue.tokens(keys_a.alive_world, 1.0) and time.monotonic() < stop:
                pass  # on the mesh (it sees run A's world) before any agent starts
            a.start_agents()
            b.start_agents()
            t_end, it = time.monotonic() + 60, 0
            while a.world.proc.poll() is None and time.monotonic() < t_end:
                k = it % ticks + 1
                for i in view.ids:
                    rogue.put(keys_a.msg(i, to=view.ids), wire.encode(b_spec.run_id, i, k, view.messages[i]))
                rogue.put(keys_a.msg(3, to=view.ids), b"\x00garbage")
                it += 1
                time.sleep(0.05)
        assert a.world.proc.wait(60) == 0, a.world.last_error_line()
        assert b.world.proc.wait(60) == 0, b.world.last_error_line()
    finally:
        a.stop_all()
        b.stop_all()
    est = json.loads((a_dir / "est.json").read_text())
    assert_same(est, reference(a_spec, ticks, 11)[1])
    cs = counters_of(json.loads((a_dir / "res.json").read_text()))
    rejected = sum((c.rejected.get("run", 0) for c in cs.values()))
    assert rejected > 0 and all(c.imbalance() == [] for c in cs.values())


def test_an_estimator_that_diverges_leaves_and_the_run_ends_incomplete(tmp_path):
    """DISKF on the random geometric network of 4 agents: agent 4's estimate
    passes what a report may carry (1e15) at tick 930. Its process tells the
    world why and leaves there with exit 3 (``exits.STOPPED``); the other
    three run every tick to the end, and ``up`` exits 3 (incomplete) with
    agent 4's line naming the tick and the results saying its 71 missing
    ticks are "diverged". No tick waits ``--tick-timeout`` for it."""
    t0 = time.monotonic()
    done, est, res = up(tmp_path, "--scenario", "random-geometric", "--agents", "4", "--ticks", "1000",
                        "--seed", "0", timeout=300)
    assert done.returncode == 3, done.stderr
    assert time.monotonic() - t0 < 120  # 3 s on two idle cores; 70 further ticks waiting would take 700 s
    line, = [ln for ln in done.stderr.splitlines() if "diverged at tick" in ln]
    assert "agent 4" in line and "diverged at tick 930" in line and "magnitude" in line, line
    row = res["diskf"]["range=100"]
    assert row["status"] == "incomplete", row["reason"]
    assert row["reason"].endswith("not reported (1.8 %): diverged 71"), row["reason"]
    reported = np.array(est["reported"])
    assert reported[:929].all() and not reported[929:, 3].any() and reported[:, :3].all()
