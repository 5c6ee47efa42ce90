"""Long commands say how far they are (a bar on a terminal, a line per
stage otherwise, the first line at once) and stop within 2 s of Ctrl-C with
exit status 130, one line and no process left behind."""
from __future__ import annotations

import fcntl
import os
import pty
import select
import signal
import struct
import subprocess
import sys
import termios
import time

import pytest

from diskf_mesh.studies import report

CLI = [sys.executable, "-m", "diskf_mesh.cli.main"]
STOPPED_WITHIN_S = 2.0
pytestmark = pytest.mark.skipif(not os.path.exists("/proc/self/status"), reason="Linux")


def _started(argv, cwd):
    """The command in a session of its own (a terminal's Ctrl-C reaches its whole process group)."""
    return subprocess.Popen([*CLI, *argv], cwd=cwd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            start_new_session=True)


def _ctrl_c(proc, after: float) -> tuple[int, float, str]:
    """Ctrl-C ``after`` seconds after the command's first line; (exit status,
    seconds from Ctrl-C to its end, standard error)."""
    first = proc.stderr.readline()
    assert first, "no line before the end"
    time.sleep(after)
    t0 = time.monotonic()
    os.killpg(proc.pid, signal.SIGINT)
    proc.wait(timeout=60)
    took = time.monotonic() - t0
    err = first + proc.stderr.read()
    time.sleep(0.5)
    left = subprocess.run(["ps", "-o", "pid=,stat=,args=", "-s", str(proc.pid)], capture_output=True, text=True)
    alive = [ln for ln in left.stdout.splitlines() if ln.split()[1][:1] != "Z"]
    assert not alive, alive
    return proc.returncode, took, err


@pytest.mark.parametrize("argv", [
    ["report", "--out", "r", "--jobs", "2"],
    ["report", "--heldout", "--out", "r", "--jobs", "2"],
    ["report", "--out", "r", "--jobs", "1"],
    ["figures", "--out", "f"],
    ["experiment", "--scenario", "random-geometric", "--agents", "200", "--seeds", "10", "--ticks", "1000"],
], ids=["report", "report-heldout", "report-one-process", "figures", "experiment"])
def test_ctrl_c_stops_a_long_command_within_2_s(argv, tmp_path):
    code, took, err = _ctrl_c(_started(argv, tmp_path), after=2.0)
    assert code == 130 and "Traceback" not in err, err
    assert err.splitlines()[-1] == "interrupted", err
    assert took < STOPPED_WITHIN_S, f"{took:.2f} s"


def test_ctrl_c_stops_the_simulated_network_within_2_s(tmp_path):
    proc = subprocess.Popen([*CLI, "up", "--network", "simulated", "--scenario", "random-geometric", "--agents",
                             "300", "--ticks", "200", "--json", "r.json"], cwd=tmp_path, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, start_new_session=True)
    time.sleep(6.0)  # started, and running ticks
    assert proc.poll() is None
    t0 = time.monotonic()
    os.killpg(proc.pid, signal.SIGINT)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130 and "Traceback" not in err, err
    assert time.monotonic() - t0 < STOPPED_WITHIN_S


def test_report_says_what_runs_at_once_then_a_line_per_study_and_case(tmp_path):
    proc = _started(["report", "--heldout", "--out", "r", "--jobs", "2", "--seeds", "1", "--ticks", "5"], tmp_path)
    t0 = time.monotonic()
    first = proc.stderr.readline()
    assert time.monotonic() - t0 < 15.0  # the imports; the first study alone takes longer
    from diskf_mesh.studies import heldout

    cases = len(heldout.cases())
    assert first == f"report: {len(report.JOBS)} studies and {cases} held-out cases in 2 processes\n"
    lines = [first, proc.stderr.readline()]
    assert lines[1].startswith(f"report: [1/{len(report.JOBS) + cases + 1}] ")
    os.killpg(proc.pid, signal.SIGINT)
    proc.wait(timeout=60)


def test_figures_and_experiment_show_lines_off_a_terminal(tmp_path):
    done = subprocess.run([*CLI, "figures", "--out", "f", "--seeds", "1", "--ticks", "10"], cwd=tmp_path,
                          capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr
    lines = done.stderr.splitlines()
    assert lines and lines[0].endswith(" runs") and any(ln.endswith(" s") for ln in lines), lines
    done = subprocess.run([*CLI, "experiment", "--seeds", "1", "--ticks", "5", "--estimators", "diskf,kcf"],
                          cwd=tmp_path, capture_output=True, text=True, timeout=600)
    lines = done.stderr.splitlines()
    assert lines[0] == "experiment: 6 runs (2 estimators x 3 settings), 1 seeds x 5 ticks each"
    assert lines[1:] == [f"experiment: [{i}/6] runs of 1 seeds" for i in range(1, 7)]
    quiet = subprocess.run([*CLI, "experiment", "--seeds", "1", "--ticks", "5", "--quiet"], cwd=tmp_path,
                           capture_output=True, text=True, timeout=600)
    assert quiet.returncode == 0 and quiet.stderr == ""


def _on_a_terminal(argv, cwd) -> str:
    """What ``argv`` writes to its terminal (a pty)."""
    leader, follower = pty.openpty()
    fcntl.ioctl(follower, termios.TIOCSWINSZ, struct.pack("HHHH", 24, 100, 0, 0))  # a terminal has a size
    proc = subprocess.Popen([*CLI, *argv], cwd=cwd, stdin=follower, stdout=follower, stderr=follower)
    os.close(follower)
    seen = b""
    while True:
        ready, _, _ = select.select([leader], [], [], 60)
        try:
            chunk = os.read(leader, 65536) if ready else b""
        except OSError:  # the terminal closed
            chunk = b""
        if not chunk:
            break
        seen += chunk
    proc.wait(timeout=60)
    os.close(leader)
    assert proc.returncode == 0, seen
    return seen.decode(errors="replace")


@pytest.mark.parametrize("argv, bar", [
    (["experiment", "--seeds", "1", "--ticks", "5", "--estimators", "diskf,kcf"], "experiment: 100%"),
    (["report", "--out", "r", "--seeds", "1", "--ticks", "5", "--jobs", "2"], "report: 100%"),
])
def test_a_terminal_gets_a_bar(argv, bar, tmp_path):
    seen = _on_a_terminal(argv, tmp_path)
    assert bar in seen and "\r" in seen, seen[-500:]
    assert "] runs of" not in seen and "report: [" not in seen  # no lines: the bar


@pytest.mark.mesh
def test_the_process_mesh_shows_lines_off_a_terminal_and_a_bar_on_one(tmp_path):
    argv = ["up", "--scenario", "dynamic", "--ticks", "20", "--json", "r.json"]
    done = subprocess.run([*CLI, *argv], cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    lines = done.stderr.splitlines()
    assert lines[0] == "up: diskf-auto x 9 agents, 20 ticks", lines
    ticks = [ln for ln in lines if ln.startswith("up: [")]
    assert ticks[0].startswith("up: [1/20] tick 1") and ticks[-1].startswith("up: [20/20] tick 20"), lines
    seen = _on_a_terminal(argv, tmp_path)
    assert "up: 100%" in seen and "20/20 [" in seen and "\r" in seen, seen[-500:]
    assert "up: [" not in seen  # the bar, not the lines


def test_experiment_shows_how_far_a_long_run_is(capsys, monkeypatch):
    """Off a terminal, a run's ticks as lines (at most one every
    ``STATUS_EVERY_S``, here every tick), between the lines of the runs."""
    from cli_helpers import run_cli
    from diskf_mesh.cli import experiment as command

    monkeypatch.setattr(command, "STATUS_EVERY_S", 0.0)
    code, _, err = run_cli(["experiment", "--scenario", "random-geometric", "--agents", "40", "--ticks", "3",
                            "--seeds", "1", "--estimators", "diskf,kcf"], capsys)
    lines = err.splitlines()
    assert code == 0
    assert lines[1:] == ["experiment: DISKF: tick 1 done", "experiment: DISKF: tick 2 done",
                         "experiment: DISKF: tick 3 done", "experiment: [1/2] runs of 1 seeds",
                         "experiment: KCF: tick 1 done", "experiment: KCF: tick 2 done",
                         "experiment: KCF: tick 3 done", "experiment: [2/2] runs of 1 seeds"], err
    monkeypatch.setattr(command, "STATUS_EVERY_S", 3600.0)
    code, _, err = run_cli(["experiment", "--scenario", "random-geometric", "--agents", "40", "--ticks", "3",
                            "--seeds", "1", "--estimators", "diskf,kcf"], capsys)
    assert code == 0 and " done" not in err
