"""Insiders that lie, in real processes (``up``: TLS, access control; the
lies from the fault plan, ``--lie``): the world's check as the run goes
names the liar within 3 ticks of the first lie an honest agent fused and
cuts it off; a lie after a withheld report is ``unverifiable``, never exit
0 without ``--accept-unverifiable`` (``up``, and ``replay`` of its
recording)."""
from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from diskf_mesh.core import exits

pytestmark = pytest.mark.mesh

TICKS, LIAR, FROM, WITHHELD = 80, 3, 50, 49
LIE = f"agent={LIAR},kind=offset,size=200,from={FROM},reports=lying"


def up(tmp_path, *args):
    est, res = tmp_path / "est.json", tmp_path / "res.json"
    done = subprocess.run([sys.executable, "-m", "sim.launcher", "--scenario", "dynamic", "--algorithm", "diskf",
                           "--ticks", str(TICKS), "--tick-timeout", "2", "--estimates", str(est), "--json", str(res),
                           "--logs", str(tmp_path / "logs"), "--quiet", *args],
                          capture_output=True, text=True, timeout=300)
    row = next(iter(json.loads(res.read_text())["diskf"].values())) if res.exists() else None
    return done, row, json.loads(est.read_text()) if est.exists() else None


def test_the_world_names_a_liar_within_3_ticks_and_cuts_it_off(tmp_path):
    done, row, doc = up(tmp_path, "--lie", LIE, "--allow-missing", "0.5", "--allow-degraded")
    assert done.returncode == exits.DIVERGED, done.stderr
    assert row["status"] == "diverged", row["reason"]
    assert row["evidence"]["replayed_online"]  # the world's check in its thread replayed the run once, for both
    [q] = row["evidence"]["quarantined"]
    assert q["agent"] == LIAR and q["why"] == "lied" and FROM <= q["named_at"] < FROM + 3, q
    assert q["named_at"] < q["from"] <= q["named_at"] + 2
    live, fused = np.array(doc["live"], dtype=bool), doc["fused"]
    cut = q["from"] - 1
    assert not live[cut:, LIAR - 1].any()
    assert not any(LIAR in senders for tick in fused[cut:] for senders in tick)  # no honest agent fuses it
    assert f"agent {LIAR} cut off from tick {q['from']}" in done.stderr


def test_a_lie_after_a_withheld_report_never_exits_0_without_the_option(tmp_path):
    lie = f"{LIE},withhold={WITHHELD}"
    rec = tmp_path / "run.mcap"
    done, row, _ = up(tmp_path, "--lie", lie, "--allow-missing", "0.5", "--allow-degraded", "--record", str(rec))
    assert done.returncode == exits.UNVERIFIABLE, done.stderr
    assert row["status"] == "unverifiable", row["reason"]
    n = row["evidence"]["unverified"]
    assert n > 0 and row["evidence"]["unverifiable"]["withheld"] == [{"agent": LIAR, "tick": WITHHELD}]
    assert "quarantined" not in row["evidence"]  # not proven a liar: an honest agent's lost report looks the same
    assert f"unverifiable run: {n} reported agent-ticks cannot be verified" in done.stderr, done.stderr
    replay = lambda *a: subprocess.run([sys.executable, "-m", "diskf_mesh.cli.main", "replay", str(rec), *a],  # noqa
                                       capture_output=True, text=True, timeout=300)
    again = replay("--allow-missing", "0.5", "--allow-degraded")
    assert again.returncode == exits.UNVERIFIABLE, again.stderr
    ok = replay("--allow-missing", "0.5", "--accept-unverifiable")
    assert ok.returncode == exits.OK and f"{n} reported agent-ticks cannot be verified" in ok.stderr, ok.stderr
    accepted = tmp_path / "accepted"
    accepted.mkdir()
    done, row, _ = up(accepted, "--lie", lie, "--allow-missing", "0.5", "--accept-unverifiable")
    assert done.returncode == exits.OK, done.stderr
    assert row["status"] == "unverifiable" and "unverifiable run accepted (--accept-unverifiable)" in done.stderr
