"""Every result file says what made it: the same provenance keys in
``experiment --json``, ``replay --out``, ``up --json`` and ``--estimates``,
``replay RUN.mcap --out``, and a recording's ``/run`` channel (``report``'s
results.json: tests/test_figures.py)."""
from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from cli_helpers import run_cli
from diskf_mesh.data import provenance
from diskf_mesh.data.scenario import load_scenario
from diskf_mesh.estimators import DEFAULT


def assert_provenance(doc: dict, *, estimator, seeds, ticks, scenario="dynamic", command=None) -> dict:
    prov = doc["provenance"]
    assert list(prov) == list(provenance.KEYS)
    assert prov["estimator"] == estimator and prov["seeds"] == seeds and prov["ticks"] == ticks
    assert prov["scenario"]["name"] == scenario and len(prov["scenario"]["sha256"]) == 64
    assert prov["command"][0] == "diskf-mesh" and (command is None or prov["command"][1] == command)
    assert set(prov["versions"]) >= {"diskf-mesh", "python", "numpy", "eclipse-zenoh"}
    assert prov["versions"]["numpy"] == np.__version__
    assert prov["started"].endswith("+00:00")
    assert prov["git_commit"] is None or len(prov["git_commit"]) == 40
    return prov


def test_the_scenario_hash_follows_its_content():
    a, b = load_scenario("dynamic"), load_scenario("dynamic")
    assert provenance.scenario_ref(a) == provenance.scenario_ref(b)
    assert provenance.scenario_ref(a) != provenance.scenario_ref(a.with_overrides(comm_range=119.0))
    assert provenance.scenario_ref(a) != provenance.scenario_ref(load_scenario("dynamic", agents=None).with_overrides(
        steps=a.steps + 1))


def test_experiment_json_has_provenance(tmp_path, capsys):
    out = tmp_path / "r.json"
    code, _, err = run_cli(["experiment", "--scenario", "dynamic", "--algorithms", "diskf,kcf", "--seeds", "2",
                            "--ticks", "12", "--quiet", "--json", out], capsys)
    assert code == 0, err
    doc = json.loads(out.read_text())
    prov = assert_provenance(doc, estimator=["diskf", "kcf"], seeds=[0, 1], ticks=12, command="experiment")
    assert prov["scenario"] == provenance.scenario_ref(load_scenario("dynamic"))
    assert prov["settings"]["window"] == load_scenario("dynamic").params.window
    assert prov["status"] == "done" and "--seeds" in prov["command"]


def test_replay_out_has_provenance(tmp_path, capsys):
    trace, est = tmp_path / "t.json", tmp_path / "e.json"
    assert run_cli(["simulate", "--scenario", "dynamic", "--seed", "3", "--ticks", "10", "--out", trace], capsys)[0] == 0
    code, _, err = run_cli(["replay", trace, "--estimator", "kcf", "--out", est], capsys)
    assert code == 0, err
    prov = assert_provenance(json.loads(est.read_text()), estimator="kcf", seeds=[3], ticks=10, command="replay")
    assert prov["scenario"]["sha256"] == provenance.content_hash(json.loads(trace.read_text()))


@pytest.mark.mesh
def test_up_results_estimates_and_recording_have_provenance(tmp_path):
    res, est, mcap, again = (tmp_path / n for n in ("res.json", "est.json", "run.mcap", "replayed.json"))
    done = subprocess.run([sys.executable, "-m", "diskf_mesh.cli.main", "up", "--scenario", "dynamic", "--ticks", "6",
                           "--seed", "4", "--json", str(res), "--estimates", str(est), "--record", str(mcap),
                           "--logs", str(tmp_path / "logs"), "--quiet"], capture_output=True, text=True, timeout=240)
    assert done.returncode == 0, done.stderr
    for doc in (json.loads(res.read_text()), json.loads(est.read_text())):
        prov = assert_provenance(doc, estimator=DEFAULT, seeds=[4], ticks=6, command="world")
        assert prov["status"] is not None
        assert prov["scenario"] == provenance.scenario_ref(load_scenario("dynamic").with_overrides(steps=6))
    from diskf_mesh.recording.reader import read

    run = read(mcap).run
    assert_provenance(run, estimator=DEFAULT, seeds=[4], ticks=6, command="world")
    done = subprocess.run([sys.executable, "-m", "diskf_mesh.cli.main", "replay", str(mcap), "--out", str(again)],
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    prov = assert_provenance(json.loads(again.read_text()), estimator=DEFAULT, seeds=[4], ticks=6, command="replay")
    assert prov["status"] in ("equal", "exact", "as planned") and prov["scenario"] == run["provenance"]["scenario"]
