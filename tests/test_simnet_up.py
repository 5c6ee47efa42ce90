"""``diskf-mesh up --network simulated``: the real protocol in one process,
the results of a process mesh, the engine's estimates bit for bit."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from diskf_mesh.estimators import DEFAULT
from diskf_mesh.data.scenario import load_scenario, simulate
from diskf_mesh.engine import batch

ROOT = Path(__file__).resolve().parents[1]


def up(*argv, cwd):
    return subprocess.run([sys.executable, "-m", "diskf_mesh.cli.main", "up", "--network", "simulated", *argv],
                          capture_output=True, text=True, cwd=cwd, timeout=300,
                          env={**os.environ, "PYTHONPATH": str(ROOT)})


def test_a_simulated_run_is_the_engine_bit_for_bit(tmp_path):
    r = up("--scenario", "random-geometric", "--agents", "6", "--ticks", "25", "--seed", "4",
           "--net-delay-ms", "3", "--net-jitter-ms", "2", "--json", str(tmp_path / "r.json"),
           "--estimates", str(tmp_path / "e.json"), "--quiet", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    row = next(iter(json.loads((tmp_path / "r.json").read_text())[DEFAULT].values()))
    assert row["status"] == "exact" and row["complete"]
    assert row["network"]["kind"] == "simulated" and row["network"]["virtual_s"] > 25 * 2 * 0.003
    doc = json.loads((tmp_path / "e.json").read_text())
    scn = load_scenario("random-geometric", agents=6).with_overrides(steps=25)
    eng = batch.run(simulate(scn, [4]), DEFAULT, scn.params)  # the default, as up ran it
    x = np.array(doc["x"], dtype=float).reshape(eng.x.shape)
    assert np.array_equal(x, eng.x)


def test_network_loss_degrades_a_run_and_one_seed_is_one_run(tmp_path):
    argv = ("--scenario", "random-geometric", "--agents", "9", "--ticks", "20", "--net-loss", "0.3",
            "--collect-timeout", "0.5", "--run-id", "loss", "--quiet")
    runs = [up(*argv, "--json", str(tmp_path / f"{n}.json"), cwd=tmp_path) for n in range(2)]
    assert [r.returncode for r in runs] == [5, 5]  # degraded, not accepted without --allow-degraded
    rows = [next(iter(json.loads((tmp_path / f"{n}.json").read_text())[DEFAULT].values())) for n in range(2)]
    assert rows[0]["status"] == "degraded" and rows[0]["evidence"]["degraded"]["agent_ticks"] > 0
    assert rows[0]["network"]["digest"] == rows[1]["network"]["digest"]
    ok = up(*argv, "--allow-degraded", "--json", str(tmp_path / "a.json"), cwd=tmp_path)
    assert ok.returncode == 0, ok.stderr


def test_net_options_need_the_simulated_network(tmp_path):
    r = subprocess.run([sys.executable, "-m", "diskf_mesh.cli.main", "up", "--scenario", "random-geometric",
                        "--agents", "3", "--net-loss", "0.1", "--insecure"], capture_output=True, text=True,
                       cwd=tmp_path, timeout=120, env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert r.returncode == 2 and r.stderr.strip().splitlines()[-1].startswith("error:")


def test_link_latency_past_the_collect_timeout_is_planned_as_the_world_plans_it(tmp_path):
    # every copy is 3 s late, the agents wait 1 s: none is planned to be fused, so nothing fused less than planned
    r = up("--ticks", "6", "--latency-ms", "3000", "--collect-timeout", "1", "--json", str(tmp_path / "r.json"),
           "--quiet", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    row = next(iter(json.loads((tmp_path / "r.json").read_text())[DEFAULT].values()))
    assert row["status"] == "as planned" and row["evidence"]["plan_deadline_s"] == 1.0


def test_simulate_run_plans_with_the_agents_deadline():
    from diskf_mesh.data.faults import FaultConfig
    from diskf_mesh.mesh.protocol import clock as realtime
    from diskf_mesh.mesh.protocol.agent_machine import AgentTiming
    from diskf_mesh.mesh.simulated.simrun import SimPlan, simulate_run
    from diskf_mesh.mesh.protocol.world_machine import WorldTiming

    scn = load_scenario("quadrants").with_overrides(steps=4)
    trace = simulate(scn, [0])
    faults = FaultConfig(latency_ms=3000.0)
    lockstep = SimPlan(agent_timing=AgentTiming(collect_timeout=1.0))
    assert simulate_run(scn, trace, "diskf", 0, plan=lockstep, faults=faults).status.status == "as planned"
    clock = realtime.Clock(rate_hz=0.2, deadline_s=1.0)
    timed = SimPlan(world_timing=WorldTiming(clock=clock), agent_timing=AgentTiming(clock=clock))
    st = simulate_run(scn, trace, "diskf", 0, plan=timed, faults=faults).status
    assert st.status == "as planned" and st.evidence["plan_deadline_s"] == 1.0


def test_a_recording_not_written_whole_fails_a_simulated_run(tmp_path, monkeypatch, capsys):
    from cli_helpers import run_cli
    from diskf_mesh.core import exits
    from diskf_mesh.recording import writer

    failed = {"path": str(tmp_path / "r.mcap"), "error": "No space left on device", "written": 3, "ticks": 6}
    finish = writer.Recorder.finish
    monkeypatch.setattr(writer.Recorder, "finish", lambda self, *a: (finish(self, *a), failed)[1])
    code, out, err = run_cli(["up", "--network", "simulated", "--ticks", "6", "--record", tmp_path / "r.mcap",
                              "--json", tmp_path / "r.json", "--quiet"], capsys)
    assert code == exits.RECORDING_FAILED, err
    row = next(iter(json.loads((tmp_path / "r.json").read_text())[DEFAULT].values()))
    assert row["recording_failed"] == failed and row["status"] == "exact"


def test_a_simulated_real_time_run_writes_the_estimates_a_world_writes(tmp_path):
    from diskf_mesh.recording.replay import fused_record_from_json

    r = up("--ticks", "6", "--rate", "20", "--estimates", str(tmp_path / "e.json"), "--json",
           str(tmp_path / "r.json"), "--quiet", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    doc = json.loads((tmp_path / "e.json").read_text())
    assert doc["complete"] and doc["missing_agent_ticks"] == 0 and doc["rate_hz"] == 20.0
    assert fused_record_from_json(doc, doc["ids"]).miss_rate == doc["deadline_misses"]["miss_rate"] == 0.0


@pytest.mark.parametrize("clock", [[], ["--rate", "10", "--max-miss-rate", "1"]], ids=["lockstep", "real-time"])
def test_what_the_network_loses_is_lost_not_late(tmp_path, capsys, clock):
    from cli_helpers import run_cli
    from diskf_mesh.core import exits
    from diskf_mesh.recording import reader

    code, out, err = run_cli(["up", "--network", "simulated", "--ticks", "10", "--net-loss", "0.2", *clock, "--json",
                              tmp_path / "r.json", "--record", tmp_path / "r.mcap", "--quiet"], capsys)
    row = next(iter(json.loads((tmp_path / "r.json").read_text())[DEFAULT].values()))
    assert code == (exits.DEGRADED if not clock else 0), err  # real time accepts the degradation
    lost = row["network"]["lost"]
    assert lost > 0 and f"lost {lost})" in row["reason"] and "late" not in row["reason"]
    verdicts = [d["verdict"] for d in reader.read(tmp_path / "r.mcap").delivered]
    assert verdicts.count("lost") == lost and "late" not in verdicts
    if clock:  # a message lost is not a deadline missed
        assert row["deadline_misses"]["messages"] == 0


@pytest.mark.parametrize("argv", [
    ["--net-delay-ms", "1e308"], ["--net-delay-ms", "-1"], ["--net-delay-ms", "nan"], ["--net-delay-ms", "5000"],
    ["--net-jitter-ms", "inf"], ["--net-jitter-ms", "1e300"], ["--net-loss", "nan"], ["--net-loss", "1.01"],
    ["--net-loss", "-0.5"], ["--net-seed", "-1"], ["--net-seed", "1e3"], ["--latency-ms", "1e308"],
    ["--jitter-ms", "-5"], ["--reorder-ms", "nan"], ["--loss", "-0.1"], ["--duplicate", "1.5"], ["--reorder", "inf"],
    ["--tick-timeout", "1e308"], ["--collect-timeout", "0"], ["--startup-timeout", "nan"],
])
def test_absurd_network_and_fault_values_are_refused(tmp_path, monkeypatch, capsys, argv):
    from cli_helpers import run_cli

    monkeypatch.chdir(tmp_path)
    code, out, err = run_cli(["up", "--network", "simulated", "--ticks", "3", *argv], capsys)
    assert code == 2 and len(err.strip().splitlines()) == 1 and err.startswith("error:"), err
    assert not any(tmp_path.iterdir())


def test_absurd_fault_values_in_a_scenario_are_refused(tmp_path, monkeypatch, capsys):
    from cli_helpers import run_cli

    monkeypatch.chdir(tmp_path)
    shipped = (ROOT / "diskf_mesh" / "scenarios" / "quadrants.toml").read_text()
    (tmp_path / "s.toml").write_text(shipped.replace("[topology]", "[faults]\nlatency_ms = 1e308\n\n[topology]"))
    code, out, err = run_cli(["up", "--network", "simulated", "--ticks", "3", "--scenario", "s.toml"], capsys)
    assert code == 2 and len(err.strip().splitlines()) == 1 and "latency_ms" in err, err
    assert [p.name for p in tmp_path.iterdir()] == ["s.toml"]


def test_a_start_up_failure_ends_incomplete_with_its_reason(tmp_path, capsys):
    """The world gives up waiting for the agents: the run still ends with a
    status, incomplete, the world's reason in the JSON and exit 3."""
    from cli_helpers import run_cli
    from diskf_mesh.core import exits

    code, out, err = run_cli(["up", "--network", "simulated", "--ticks", "5", "--startup-timeout", "0.0001",
                              "--json", tmp_path / "r.json", "--quiet"], capsys)
    assert code == exits.INCOMPLETE, err
    row = next(iter(json.loads((tmp_path / "r.json").read_text())[DEFAULT].values()))
    assert row["status"] == "incomplete" and row["reason"].startswith("after 0.0001 s waiting for the agents: ")
    assert row["ended_early"] in row["reason"] and row["missing_fraction"] == 1.0
    assert len(err.strip().splitlines()) == 1 and "waiting for the agents" in err


def test_progress_is_a_line_per_stage_off_a_terminal_and_a_bar_on_one(tmp_path):
    argv = ["--scenario", "random-geometric", "--agents", "4", "--ticks", "20", "--json", str(tmp_path / "r.json")]
    off = up(*argv, cwd=tmp_path)
    assert off.returncode == 0, off.stderr
    lines = off.stderr.splitlines()
    assert lines[0].startswith("up: random-geometric: 4 agents + world, 20 ticks")
    assert any(line.startswith("up: start-up: ") for line in lines)
    ticks = [line.split("]")[0] for line in lines if line.startswith("up: [")]
    assert ticks == [f"up: [{k}/20" for k in (1, 2, 4, 6, 8, 10, 12, 14, 16, 18, 20)]
    assert "s to go" in next(line for line in lines if line.startswith("up: [10/20]"))  # the time to go
    assert any(line.startswith("up: checking the run") for line in lines)
    assert "\r" not in off.stderr  # no bar

    import fcntl
    import pty
    import struct
    import termios
    main, sub = pty.openpty()
    fcntl.ioctl(sub, termios.TIOCSWINSZ, struct.pack("HHHH", 24, 100, 0, 0))  # a terminal's width for the bar
    try:
        on = subprocess.run([sys.executable, "-m", "diskf_mesh.cli.main", "up", "--network", "simulated", *argv],
                            stdout=subprocess.PIPE, stderr=sub, cwd=tmp_path, timeout=300,
                            env={**os.environ, "PYTHONPATH": str(ROOT)})
        os.close(sub)
        sub = None
        seen = b""
        while True:
            try:
                chunk = os.read(main, 65536)
            except OSError:
                break
            if not chunk:
                break
            seen += chunk
    finally:
        os.close(main)
        if sub is not None:
            os.close(sub)
    assert on.returncode == 0
    text = seen.decode(errors="replace")
    assert "up: random-geometric: 4 agents + world, 20 ticks" in text.split("\n")[0]  # above the bar, at once
    assert "20/20 [" in text and ("tick/s" in text or "s/tick" in text)  # tqdm's bar: ticks, elapsed<ETA, rate
    assert "up: [10/20]" not in text  # the bar, not the lines


def test_quiet_prints_no_progress(tmp_path):
    r = up("--scenario", "random-geometric", "--agents", "3", "--ticks", "5", "--quiet",
           "--json", str(tmp_path / "r.json"), cwd=tmp_path)
    assert r.returncode == 0 and r.stderr == "", r.stderr


def test_the_memory_estimate_is_within_twice_a_measured_peak(tmp_path):
    """``simrun.simulated_bytes``, the estimate ``check_size`` refuses a run
    by, against the peak resident memory of a run of 200 agents (the
    process's whole peak, start-up included). The run is started by a small
    interpreter that reports its child's peak: Linux counts the memory of
    the process that executes a command in the command's peak (the test
    process's own, hundreds of MB after many tests in one pytest run)."""
    from diskf_mesh.mesh.simulated.simrun import simulated_bytes
    run = ["-m", "diskf_mesh.cli.main", "up", "--network", "simulated", "--scenario", "random-geometric",
           "--agents", "200", "--ticks", "5", "--quiet"]
    launcher = ("import resource, subprocess, sys; "
                "code = subprocess.run([sys.executable, *sys.argv[1:]], stdout=subprocess.DEVNULL, "
                "stderr=subprocess.DEVNULL).returncode; "
                "print(code, resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss)")
    out = subprocess.run([sys.executable, "-c", launcher, *run], cwd=tmp_path, capture_output=True, text=True,
                         env={**os.environ, "PYTHONPATH": str(ROOT)}, check=True).stdout.split()
    assert out[0] == "0"
    peak = int(out[1]) * 1024
    scn = load_scenario("random-geometric", agents=200).with_overrides(steps=5)
    estimate = simulated_bytes(200, scn.largest_neighbourhood(scn.steps), scn.steps)
    assert peak / 2 <= estimate <= 2 * peak, (estimate / 2**20, peak / 2**20)
