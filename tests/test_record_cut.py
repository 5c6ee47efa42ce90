"""A recording cut short stays readable up to its last complete tick: a
world killed with SIGKILL mid-run, and the same file cut at every kind of
offset; and a recording cut, truncated or with one bit flipped never
replays ``exact`` with exit 0: ``replay`` checks the file whole first (MCAP's
CRCs, summary and footer, the run's result, every planned tick). Also the
report fields a recording is built on."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from diskf_mesh.mesh.wire import codec as wire
from diskf_mesh.core import exits
from diskf_mesh.core.errors import InputError
from diskf_mesh.mesh.process.runspec import RunSpec
from diskf_mesh.recording import reader
from diskf_mesh.recording.replay import compare, replay
from diskf_mesh.mesh.protocol.verdicts import TickVerdicts

from mesh_helpers import start_mesh


def closed_ticks(path) -> int:
    try:
        return reader.read(path).ticks
    except InputError:  # not even the first tick yet
        return 0


def children(pid: int) -> list:
    """The child processes of ``pid`` (Linux)."""
    with open(f"/proc/{pid}/task/{pid}/children") as f:
        return [int(c) for c in f.read().split()]


def zombie(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] == "Z"
    except OSError:
        return True


@pytest.mark.mesh
def test_killed_world_leaves_a_readable_recording(tmp_path):
    path = tmp_path / "killed.mcap"
    spec = RunSpec("dynamic", "diskf", run_id="reckill")
    mesh = start_mesh(spec, 400, 2, tmp_path, world_extra=["--record", str(path), "--loss", "0.2"],
                      agent_extra=["--world-timeout", "30", "--loss", "0.2"])
    try:
        mesh.start_agents()
        deadline = time.monotonic() + 90
        while closed_ticks(path) < 20:
            assert mesh.world.proc.poll() is None, mesh.world.last_error_line()
            assert time.monotonic() < deadline, "the world did not reach tick 20"
            time.sleep(0.2)
        writers = children(mesh.world.proc.pid)  # the recording's writer process
        assert writers
        os.kill(mesh.world.proc.pid, signal.SIGKILL)
        assert mesh.world.proc.wait(10) == -signal.SIGKILL
    finally:
        mesh.stop_all()
    deadline = time.monotonic() + 60  # it writes what the pipe still held, then leaves
    while any(os.path.exists(f"/proc/{pid}") and not zombie(pid) for pid in writers):
        assert time.monotonic() < deadline, "the writer did not end after the world was killed"
        time.sleep(0.1)
    rec = reader.read(path)
    assert not rec.finished and rec.result is None
    assert 20 <= rec.ticks < 400
    assert rec.reported.all()                  # every tick it holds is complete
    assert {d["tick"] for d in rec.delivered} == set(range(1, rec.ticks + 1))
    assert compare(rec, replay(rec)).equal     # and replays bit for bit
    done = subprocess.run([sys.executable, "-m", "diskf_mesh.cli.main", "inspect", str(path), "--json"],
                          capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    s = json.loads(done.stdout)
    assert (s["finished"], s["ticks"], s["planned_ticks"], s["status"]) == (False, rec.ticks, 400, "cut short")
    done = subprocess.run([sys.executable, "-m", "diskf_mesh.cli.main", "replay", str(path)], capture_output=True,
                          text=True, timeout=60)
    assert done.returncode == exits.INCOMPLETE, done.stderr  # its ticks replay exact, but the run is not all there
    assert f"its last whole tick is {rec.ticks} of 400" in done.stderr
    # cut it further anywhere: never an error once the first tick is in, never a partial tick
    data = path.read_bytes()
    cut_path = tmp_path / "cut.mcap"
    seen = []
    for end in np.linspace(len(data) // 4, len(data), 40).astype(int):
        cut_path.write_bytes(data[:end])
        try:
            cut = reader.read(cut_path)
        except InputError:  # cut before its first tick closed
            assert not seen, f"unreadable at {end} bytes after a readable shorter cut"
            continue
        assert cut.reported.all()
        np.testing.assert_array_equal(cut.x, rec.x[:cut.ticks])
        seen.append(cut.ticks)
    assert seen == sorted(seen) and seen[-1] == rec.ticks and any(0 < t < rec.ticks for t in seen)


# --------------------------------------------------------------------------
# a recording that is not whole never replays exact with exit 0
# --------------------------------------------------------------------------
@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    """The bytes of a whole recording of an exact simulated run (60 ticks)."""
    d = tmp_path_factory.mktemp("whole")
    done = subprocess.run([sys.executable, "-m", "diskf_mesh.cli.main", "up", "--network", "simulated",
                           "--scenario", "dynamic", "--ticks", "60", "--seed", "3",
                           "--estimator", "diskf", "--record", "run.mcap", "--quiet"],
                          capture_output=True, text=True, timeout=300, cwd=d)
    assert done.returncode == 0, done.stderr
    return (d / "run.mcap").read_bytes()


def replayed(path, capsys, *flags):
    """(exit status, the recording's status or None if unreadable, stderr) of ``replay path``."""
    from cli_helpers import run_cli

    code, _, err = run_cli(["replay", path, *flags], capsys)
    try:
        rec = reader.read(path)
    except InputError:
        return code, None, err
    if not rec.ticks:  # not even its first tick
        return code, None, err
    from diskf_mesh.recording.replay import recording_status

    return code, recording_status(rec), err


def test_a_whole_recording_is_whole_and_replays_exact(tmp_path, recorded, capsys):
    path = tmp_path / "run.mcap"
    path.write_bytes(recorded)
    rec = reader.read(path)
    assert rec.finished and rec.damage == "" and rec.not_whole() == "" and rec.ticks == 60
    code, st, err = replayed(path, capsys)
    assert (code, st.status) == (0, "exact"), err
    assert st.evidence["recording"] == {"whole": True, "damage": None, "last_whole_tick": 60, "planned_ticks": 60,
                                        "replayed_status": "exact"}


@pytest.mark.parametrize("share", [0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9, 0.99])
def test_a_cut_recording_never_replays_exact(tmp_path, recorded, capsys, share):
    path = tmp_path / "cut.mcap"
    path.write_bytes(recorded[:int(len(recorded) * share)])
    code, st, err = replayed(path, capsys)
    assert code != 0 and len(err.strip().splitlines()) == 1, err
    if st is None:  # cut before its first tick: bad input, one line
        assert code == exits.BAD_INPUT
        return
    K = reader.read(path).ticks
    assert st.status == "incomplete" and code == exits.INCOMPLETE and K <= 60
    assert f"its last whole tick is {K} of 60" in err and st.evidence["recording"]["last_whole_tick"] == K
    # no tolerance accepts it
    code, _, err = replayed(path, capsys, "--allow-missing", "1", "--allow-degraded")
    assert code == exits.INCOMPLETE and f"its last whole tick is {K} of 60" in err


def test_a_recording_without_its_end_is_not_whole(tmp_path, recorded):
    """The MCAP file whole, but the run's result record or ticks missing."""
    import dataclasses

    path = tmp_path / "run.mcap"
    path.write_bytes(recorded)
    rec = reader.read(path)
    assert "no result record" in dataclasses.replace(rec, result=None).not_whole()
    assert "holds 59 of the 60 ticks" in dataclasses.replace(rec, ticks=59).not_whole()


def test_single_bit_flips_never_replay_exact(tmp_path, recorded, capsys):
    """50 single-bit flips, one in each fiftieth of the file (the last one
    holds the summary and footer): each is caught by a CRC, the summary or
    the footer, and the replay says so and exits non-zero."""
    rng = np.random.default_rng(50)
    path = tmp_path / "flipped.mcap"
    bits = len(recorded) * 8
    caught = {}
    for i in range(50):
        at = int((i + rng.random()) * bits / 50)
        data = bytearray(recorded)
        data[at // 8] ^= 1 << (at % 8)
        path.write_bytes(bytes(data))
        code, st, err = replayed(path, capsys)
        assert code != 0 and len(err.strip().splitlines()) == 1, (at // 8, err)
        if st is None:  # no whole tick left (the run's first chunk, its trace): bad input, one line
            assert code == exits.BAD_INPUT, err
        else:
            assert st.status != "exact", (at // 8, st.reason)
            assert "not whole" in st.reason and "its last whole tick is" in err, (at // 8, err)
        for kind in ("a chunk", "attachment", "data section", "summary"):
            if kind in err:
                caught[kind] = at // 8
    assert len(caught) == 4, caught


def test_inspect_says_whether_its_verdict_was_rechecked(tmp_path, recorded, capsys):
    from cli_helpers import run_cli

    path = tmp_path / "cut.mcap"
    path.write_bytes(recorded[:len(recorded) * 2 // 3])
    code, out, err = run_cli(["inspect", path, "--json"], capsys)
    s = json.loads(out)
    assert code == 0 and s["whole"] is False and s["run_status"] == {"rechecked": False}
    code, out, err = run_cli(["inspect", path, "--json", "--check"], capsys)
    s = json.loads(out)
    assert s["run_status"]["rechecked"] is True and s["run_status"]["status"] == "incomplete"
    assert f"its last whole tick is {reader.read(path).ticks} of 60" in s["run_status"]["reason"]
    path.write_bytes(recorded)
    code, out, err = run_cli(["inspect", path], capsys)
    assert "not re-checked" in out.splitlines()[1] and "exact" in out.splitlines()[1]
    code, out, err = run_cli(["inspect", path, "--check"], capsys)
    assert out.splitlines()[1].startswith("re-checked by the engine now: exact")


def test_what_is_not_a_recording(tmp_path):
    p = tmp_path / "x.mcap"
    p.write_bytes(b"not an mcap file")
    with pytest.raises(InputError, match="not an MCAP file"):
        reader.read(p)
    with pytest.raises(InputError, match="cannot read"):
        reader.read(tmp_path / "absent.mcap")
    p.write_bytes(reader.MAGIC + b"\x01\x05")  # cut inside the header record
    with pytest.raises(InputError, match="not a diskf-mesh recording"):
        reader.read(p)


# --------------------------------------------------------------------------
# the report's fused senders and verdicts
# --------------------------------------------------------------------------
def _report(**kw) -> bytes:
    return wire.encode_report("r", 3, 7, np.zeros(2), np.eye(2), np.zeros(1), True, {"fused": 2}, **kw)


def test_report_carries_fused_senders_and_verdicts():
    r = wire.decode_report(_report(fused=(1, 4), not_fused=((2, "lost"), (5, "rejected:not-spd")),
                                   sent_digest=b"\x81" * 8), run_id="r")
    assert r.fused == (1, 4) and r.not_fused == ((2, "lost"), (5, "rejected:not-spd")) and r.sent_digest == b"\x81" * 8
    old = wire.decode_report(wire.encode_report("r", 3, 7, np.zeros(2), np.eye(2), np.zeros(1), True))
    assert old.fused == () and old.not_fused == () and old.sent_digest == b""


@pytest.mark.parametrize("fields", [
    {"f": list(range(wire.MAX_LINKS + 1))}, {"f": ["1"]}, {"f": [True]}, {"nf": [[1]]}, {"nf": [[1, 2]]},
    {"nf": [[1, "x" * (wire.MAX_VERDICT + 1)]]}, {"nf": {"1": "lost"}}, {"od": "not bytes"}, {"od": b"\x81"},
])
def test_report_verdicts_are_bounded(fields):
    import msgpack

    doc = msgpack.unpackb(_report(), raw=False)
    doc.update(fields)
    with pytest.raises(wire.Rejected) as e:
        wire.decode_report(msgpack.packb(doc, use_bin_type=True))
    assert e.value.reason == "schema"


def test_tick_verdicts():
    v = TickVerdicts()
    fused, others = v.of_tick(7, linked={2, 4, 5, 6}, heard={2, 4, 5, 6}, rejected={2: "not-spd"}, fused={4, 6})
    assert fused == (4, 6) and others == ((2, "rejected:not-spd"), (5, "lost"))
    fused, others = v.of_tick(8, linked={2, 4}, heard=set(), rejected={}, fused={4}, fusion_failed=True)
    assert fused == () and others == ((2, "late"), (4, "rejected:fusion"))


@pytest.mark.parametrize("argv", [
    ["up", "--ticks", "3", "--record", "/proc/no/such/run.mcap"],   # a folder that cannot be made
    ["up", "--ticks", "3", "--record", "."],                        # a folder, not a file
    ["inspect", "/etc/hostname"],                                   # not MCAP
    ["replay", "absent.mcap"],
    ["figures", "--from", "absent.mcap", "--out", "figs"],
])
def test_bad_recording_input_is_one_line_and_status_2(tmp_path, argv):
    done = subprocess.run([sys.executable, "-m", "diskf_mesh.cli.main", *argv], capture_output=True, text=True,
                          timeout=60, cwd=tmp_path)
    assert done.returncode == 2
    assert len(done.stderr.strip().splitlines()) == 1 and done.stderr.startswith("error: ")
    assert not (tmp_path / "figs").exists() or not any((tmp_path / "figs").iterdir())
