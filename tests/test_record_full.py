"""A recording on a disk that fills up: ``up --record`` (and the world under
it) exits ``RECORDING_FAILED`` with one line naming the file and the last
tick it holds; the results say so; the file reads back up to that tick.
The disk is a tmpfs of 64 KiB (mounting it needs root)."""
from __future__ import annotations

import json
import re
import subprocess
import sys

import pytest

from diskf_mesh.core import exits
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
    world_log = (tmp_path / "logs" / "world.log").read_text().strip().splitlines()
    assert world_log[-1] == f"error: world: {lines[0][len('error: '):]}"
