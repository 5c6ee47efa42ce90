"""``diskf-mesh up --network simulated``: the real protocol in one process,
the results of a process mesh, the engine's estimates bit for bit."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np

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
    row = next(iter(json.loads((tmp_path / "r.json").read_text())["diskf"].values()))
    assert row["status"] == "exact" and row["complete"]
    assert row["network"]["kind"] == "simulated" and row["network"]["virtual_s"] > 25 * 2 * 0.003
    doc = json.loads((tmp_path / "e.json").read_text())
    scn = load_scenario("random-geometric", agents=6).with_overrides(steps=25)
    eng = batch.run(simulate(scn, [4]), "diskf", scn.params)
    x = np.array(doc["x"], dtype=float).reshape(eng.x.shape)
    assert np.array_equal(x, eng.x)


def test_network_loss_degrades_a_run_and_one_seed_is_one_run(tmp_path):
    argv = ("--scenario", "random-geometric", "--agents", "9", "--ticks", "20", "--net-loss", "0.3",
            "--collect-timeout", "0.5", "--run-id", "loss", "--quiet")
    runs = [up(*argv, "--json", str(tmp_path / f"{n}.json"), cwd=tmp_path) for n in range(2)]
    assert [r.returncode for r in runs] == [5, 5]  # degraded, not accepted without --allow-degraded
    rows = [next(iter(json.loads((tmp_path / f"{n}.json").read_text())["diskf"].values())) for n in range(2)]
    assert rows[0]["status"] == "degraded" and rows[0]["evidence"]["degraded"]["agent_ticks"] > 0
    assert rows[0]["network"]["digest"] == rows[1]["network"]["digest"]
    ok = up(*argv, "--allow-degraded", "--json", str(tmp_path / "a.json"), cwd=tmp_path)
    assert ok.returncode == 0, ok.stderr


def test_net_options_need_the_simulated_network(tmp_path):
    r = subprocess.run([sys.executable, "-m", "diskf_mesh.cli.main", "up", "--scenario", "random-geometric",
                        "--agents", "3", "--net-loss", "0.1", "--insecure"], capture_output=True, text=True,
                       cwd=tmp_path, timeout=120, env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert r.returncode == 2 and r.stderr.strip().splitlines()[-1].startswith("error:")
