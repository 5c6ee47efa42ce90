"""A recording that cannot be written whole: ``up --record`` (and the world
under it) exits ``RECORDING_FAILED`` with one line naming the file and the
last tick it holds; the results say so; the file reads back up to that
tick. The disk that fills up is a tmpfs of 64 KiB (mounting it needs root);
the other case is a writer killed mid-run."""
from __future__ import annotations

import json
import re
import subprocess
import sys

import pytest

from diskf_mesh.core import exits
from diskf_mesh.core.errors import InputError
from diskf_mesh.recording import reader

TICKS = 200


@pytest.fixture
def small_disk(tmp_path):
    where = tmp_path / "disk"
    where.mkdir()
    made = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=64k", "tmpfs", str(where)], capture_output=True)
    if made.returncode != 0:
        pytest.skip(f"cannot mount a small tmpfs here: {made.stderr.decode().strip()}")
    yield where
    subprocess.run(["umount", "-l", str(where)], check=False)


@pytest.mark.mesh
def test_a_full_disk_while_recording_fails_the_run_with_one_line(tmp_path, small_disk):
    mcap, out = small_disk / "run.mcap", tmp_path / "r.json"
    proc = subprocess.run([sys.executable, "-m", "sim.launcher", "--scenario", "quadrants", "--ticks", str(TICKS),
                           "--quiet", "--record", str(mcap), "--json", str(out), "--logs", str(tmp_path / "logs")],
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == exits.RECORDING_FAILED, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1, lines
    held = re.fullmatch(rf"error: recording {re.escape(str(mcap))} failed: No space left on device; "
                        rf"it holds ticks 1 to (\d+) of {TICKS}", lines[0])
    assert held, lines[0]
    written = int(held.group(1))
    assert 0 < written < TICKS
    assert f"recording: {mcap}" not in proc.stdout  # not listed as written
    row = next(iter(next(iter(json.loads(out.read_text()).values())).values()))
    assert row["recording_failed"] == {"path": str(mcap), "written": written, "ticks": TICKS,
                                       "error": "No space left on device"}
    assert row["status"] == "exact"  # the run itself is whole: only its file is not
    rec = reader.read(mcap)
    assert rec.ticks >= written and not rec.finished
    done = subprocess.run([sys.executable, "-m", "diskf_mesh.cli.main", "replay", str(mcap)], capture_output=True,
                          text=True, timeout=120)  # its ticks replay exact, but the file is not the run
    assert done.returncode == exits.INCOMPLETE and f"its last whole tick is {rec.ticks} of {TICKS}" in done.stderr
    world_log = (tmp_path / "logs" / "world.log").read_text().strip().splitlines()
    assert world_log[-1] == f"error: world: {lines[0][len('error: '):]}"


def _writer_of(pid: int):
    """The pid of the recording writer under process ``pid``, or None."""
    from pathlib import Path

    for d in Path("/proc").iterdir():
        try:
            if not d.name.isdigit() or int((d / "stat").read_text().rsplit(")", 1)[1].split()[1]) != pid:
                continue
            if b"diskf_mesh.recording.writer" in (d / "cmdline").read_bytes():
                return int(d.name)
            found = _writer_of(int(d.name))
            if found:
                return found
        except (OSError, ValueError, IndexError):
            continue
    return None


def _ticks_held(path) -> int:
    try:
        return reader.read(path).ticks
    except InputError:
        return 0


@pytest.mark.mesh
def test_a_writer_killed_mid_run_fails_the_run_with_one_line(tmp_path):
    import os
    import signal
    import time

    mcap, out, ticks = tmp_path / "run.mcap", tmp_path / "r.json", 1000
    proc = subprocess.Popen([sys.executable, "-m", "sim.launcher", "--scenario", "quadrants", "--ticks", str(ticks),
                             "--quiet", "--record", str(mcap), "--json", str(out), "--logs", str(tmp_path / "logs")],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline, writer = time.monotonic() + 120, None
        while writer is None and time.monotonic() < deadline and proc.poll() is None:
            writer = _writer_of(proc.pid)
            time.sleep(0.1)
        assert writer, "no recording writer"
        while _ticks_held(mcap) < 5 and time.monotonic() < deadline:  # some ticks in the file
            time.sleep(0.1)
        os.kill(writer, signal.SIGKILL)
        _, err = proc.communicate(timeout=300)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate(timeout=10)
    assert proc.returncode == exits.RECORDING_FAILED, err
    line, = err.strip().splitlines()
    held = re.fullmatch(rf"error: recording {re.escape(str(mcap))} failed: the writer ended with status -9; "
                        rf"it holds ticks 1 to (\d+) of {ticks}", line)
    assert held, line
    assert reader.read(mcap).ticks == int(held.group(1)) > 0
