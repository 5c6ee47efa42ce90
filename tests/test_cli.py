"""The command line: bad input ends in one line naming the field, exit 2,
and writes nothing; good input gives the documented outputs."""
from __future__ import annotations

import copy
import json
import math
import os
import subprocess
import sys

import pytest

from cli_helpers import run_cli, simulated_doc, write
from diskf_mesh import algorithms
from diskf_mesh.metrics import METRIC_KEYS

DOC = simulated_doc()


def mutate(path, value):
    """A copy of DOC with ``value`` set at ``path`` (a tuple of keys)."""
    doc = copy.deepcopy(DOC)
    *head, last = path
    node = doc
    for key in head:
        node = node[key]
    node[last] = value
    return doc


def two_row_agent(R):
    doc = copy.deepcopy(DOC)
    doc["agents"][0] = {"id": 1, "H": [[1.0, 0.0], [0.0, 1.0]], "R": R}
    return doc


BAD_TRACES = {
    "Q shape": (mutate(("Q",), [[0.2, 0.0, 0.0], [0.0, 0.2, 0.0]]), "Q"),
    "Q not symmetric": (mutate(("Q",), [[0.2, 0.1], [0.0, 0.2]]), "Q"),
    "Q not PD": (mutate(("Q",), [[0.2, 0.0], [0.0, -0.2]]), "Q"),
    "P0 not symmetric": (mutate(("P0",), [[1.0, 0.5], [0.0, 1.0]]), "P0"),
    "P0 not PD": (mutate(("P0",), [[1.0, 2.0], [2.0, 1.0]]), "P0"),
    "P0 missing": (mutate(("P0",), None), "P0"),
    "R not PD": (mutate(("agents", 0, "R"), [[0.0]]), "agents[0].R"),
    "R shape": (mutate(("agents", 1, "R"), [[2.0, 0.0], [0.0, 2.0]]), "agents[1].R"),
    "R not symmetric": (two_row_agent([[2.0, 1.0], [0.0, 2.0]]), "agents[0].R"),
    "H columns": (mutate(("agents", 2, "H"), [[1.0, 0.0, 0.0]]), "agents[2].H"),
    "agent id list": (mutate(("agents", 0, "id"), [1]), "agents[0].id"),
    "agent id text": (mutate(("agents", 1, "id"), "north"), "agents[1].id"),
    "agent id negative": (mutate(("agents", 2, "id"), -3), "agents[2].id"),
    "agent ids repeat": (mutate(("agents", 3, "id"), 1), "agents.id"),
    "agents empty": (mutate(("agents",), []), "agents"),
    "x0 length": (mutate(("x0",), [1.0]), "x0"),
    "G ragged": (mutate(("G",), [[1.0], [1.0, 2.0]]), "G"),
    "G empty": (mutate(("G",), [[], []]), "G"),
    "A shape": (mutate(("A",), [[1.0, 0.0]]), "A"),
    "A NaN": (mutate(("A",), [[math.nan, 0.0], [0.0, 1.0]]), "A"),
    "A_seq length": (mutate(("A_seq",), [[[1.0, 0.0], [0.0, 1.0]]] * 3), "A_seq"),
    "y empty": (mutate(("y",), []), "y"),
    "y row count": (mutate(("y", 2), [None, None]), "y[2]"),
    "y length": (mutate(("y", 3, 0), [1.0, 2.0]), "y[3][0]"),
    "y not numbers": (mutate(("y", 3, 0), ["a"]), "y[3][0]"),
    "links 3x3": (mutate(("links",), [[1, 1, 0], [1, 1, 1], [0, 1, 1]]), "links"),
    "links K wrong": (mutate(("links",), [[[1] * 4] * 4] * 3), "links"),
    "links diagonal": (mutate(("links",), [[0, 1, 1, 1]] + [[1] * 4] * 3), "links"),
    "links not 0/1": (mutate(("links",), [[2] * 4] * 4), "links"),
    "links missing": (mutate(("links",), None), "links"),
    "truth.x shape": (mutate(("truth", "x"), [[0.0, 0.0]]), "truth.x"),
    "truth.d shape": (mutate(("truth", "d"), [[0.0, 0.0]] * 20), "truth.d"),
    "format": (mutate(("format",), "diskf-trace/9"), "format"),
    "seed": (mutate(("seed",), -1), "seed"),
    "position_dims": (mutate(("position_dims",), [0, 5]), "position_dims"),
    "not an object": ([1, 2, 3], "trace"),
    "invalid JSON": ("{\"A\": [[1, 0]", "file"),
    "not UTF-8": (b"\xff\xfe\x00", "file"),
}


def assert_rejected(argv, field, out_path, capsys):
    """Exit 2, one stderr line naming ``field``, nothing on stdout, and no
    ``out_path`` written."""
    code, out, err = run_cli(argv, capsys)
    assert code == 2
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith("error: ") and field in lines[0], lines[0]
    assert "Traceback" not in err
    assert out == ""
    assert not out_path.exists()


@pytest.mark.parametrize("case", list(BAD_TRACES))
def test_replay_rejects_bad_trace(case, tmp_path, capsys):
    doc, field = BAD_TRACES[case]
    path = tmp_path / "trace.json"
    if isinstance(doc, bytes):
        path.write_bytes(doc)
    else:
        write(path, doc)
    out_path = tmp_path / "est.json"
    assert_rejected(["replay", path, "--out", out_path], field, out_path, capsys)


BAD_REPLAY_ARGS = {
    "unknown algorithm": (["--algorithm", "kalman"], "--algorithm"),
    "window negative": (["--window", "-1"], "--window"),
    "window text": (["--window", "five"], "--window"),
    "window float": (["--window", "2.5"], "--window"),
    "eps negative": (["--eps", "-0.1"], "--eps"),
    "eps nan": (["--eps", "nan"], "--eps"),
    "eps inf": (["--eps", "inf"], "--eps"),
    "eps text": (["--eps", "x"], "--eps"),
    "compensation": (["--compensation", "huge"], "--compensation"),
}


@pytest.mark.parametrize("case", list(BAD_REPLAY_ARGS))
def test_replay_rejects_bad_options(case, tmp_path, capsys):
    args, field = BAD_REPLAY_ARGS[case]
    trace = write(tmp_path / "trace.json", DOC)
    out_path = tmp_path / "est.json"
    assert_rejected(["replay", trace, "--out", out_path, *args], field, out_path, capsys)


@pytest.mark.parametrize("name", ["nope.json", "."])
def test_replay_unreadable_file(name, tmp_path, capsys):
    out_path = tmp_path / "est.json"
    assert_rejected(["replay", tmp_path / name, "--out", out_path], "file", out_path, capsys)


def blocker(tmp_path):
    """A plain file, so that a path below it cannot be written."""
    path = tmp_path / "a_file"
    path.write_text("")
    return path


def test_replay_unwritable_out(tmp_path, capsys):
    trace = write(tmp_path / "trace.json", DOC)
    out_path = blocker(tmp_path) / "est.json"
    assert_rejected(["replay", trace, "--out", out_path], "out", out_path, capsys)


SCENARIO_FILE = "<scenario file>"
QUICK = ["--seeds", "1", "--steps", "5", "--quiet"]
BAD_EXPERIMENTS = {
    "unknown scenario": (["--scenario", "atlantis"], "scenario"),
    "missing scenario file": (["--scenario", "nowhere.toml"], "scenario"),
    "invalid TOML": (["--scenario", SCENARIO_FILE], "scenario", "name = ["),
    "scenario Q not PD": (["--scenario", SCENARIO_FILE], "model.Q",
                          "[model]\nG = [[1.0]]\nA = [[1.0]]\nQ = [[-1.0]]\n"),
    "unknown algorithm": (["--algorithms", "diskf,kalman"], "--algorithms"),
    "empty algorithms": (["--algorithms", ","], "--algorithms"),
    "unknown topology": (["--topology", "all,star"], "topology"),
    "empty topology": (["--topology", ","], "topology"),
    "range without range topology": (["--topology", "ring", "--range", "100"], "range"),
    "range negative": (["--range", "-3"], "--range"),
    "seeds zero": (["--seeds", "0"], "--seeds"),
    "steps text": (["--steps", "many"], "--steps"),
    "window": (["--window", "-2"], "--window"),
    "eps": (["--eps", "-1"], "--eps"),
}


@pytest.mark.parametrize("case", list(BAD_EXPERIMENTS))
def test_experiment_rejects_bad_input(case, tmp_path, capsys):
    args, field, *toml = BAD_EXPERIMENTS[case]
    if toml:
        scenario = write(tmp_path / "scenario.toml", toml[0])
        args = [scenario if a == SCENARIO_FILE else a for a in args]
    out_path = tmp_path / "results.json"
    assert_rejected(["experiment", *QUICK, *args, "--json", out_path], field, out_path, capsys)


def test_experiment_unwritable_json(tmp_path, capsys):
    out_path = blocker(tmp_path) / "results.json"
    assert_rejected(["experiment", *QUICK, "--json", out_path], "json", out_path, capsys)


BAD_SIMULATIONS = {
    "unknown scenario": (["--scenario", "atlantis"], "scenario"),
    "unknown topology": (["--topology", "star"], "topology"),
    "range with ring": (["--topology", "ring", "--range", "50"], "range"),
    "seed negative": (["--seed", "-1"], "--seed"),
    "steps zero": (["--steps", "0"], "--steps"),
}


@pytest.mark.parametrize("case", list(BAD_SIMULATIONS))
def test_simulate_rejects_bad_input(case, tmp_path, capsys):
    args, field = BAD_SIMULATIONS[case]
    out_path = tmp_path / "trace.json"
    assert_rejected(["simulate", *args, "--out", out_path], field, out_path, capsys)


def test_experiment_json_shape(tmp_path, capsys):
    out_path = tmp_path / "results.json"
    code, out, err = run_cli(["experiment", "--seeds", "2", "--steps", "30", "--json", out_path], capsys)
    assert code == 0 and err == ""  # no progress bar when stderr is not a terminal
    results = json.loads(out_path.read_text())
    assert list(results) == list(algorithms.NAMES)
    for per_topology in results.values():
        assert list(per_topology) == ["all", "ring", "none"]
        for row in per_topology.values():
            assert set(METRIC_KEYS) <= set(row)
            assert all(v is None or isinstance(v, float) for v in row.values())
    for label in ("all-to-all", "1-hop", "none", "DISKF", "C-DRKF", "GDKF", "MAE(state)", "RMSE(input)"):
        assert label in out


def test_experiment_subset_and_range(tmp_path, capsys):
    out_path = tmp_path / "results.json"
    code, out, _ = run_cli(["experiment", "--algorithms", "diskf,kcf", "--topology", "none,range",
                            "--range", "250", *QUICK, "--json", out_path], capsys)
    assert code == 0
    results = json.loads(out_path.read_text())
    assert list(results) == ["diskf", "kcf"]
    assert list(results["diskf"]) == ["none", "range=250"]


def test_replay_writes_estimates(tmp_path, capsys):
    trace = write(tmp_path / "trace.json", DOC)
    out_path = tmp_path / "est.json"
    code, out, _ = run_cli(["replay", trace, "--algorithm", "ldrkf", "--window", "none", "--out", out_path], capsys)
    assert code == 0 and "mae_state" in out
    est = json.loads(out_path.read_text())
    K, N = len(DOC["y"]), len(DOC["agents"])
    assert est["format"] == "diskf-estimates/1" and est["algorithm"] == "ldrkf"
    assert [len(est["x"]), len(est["x"][0]), len(est["x"][0][0])] == [K, N, 2]
    assert [len(est["P"]), len(est["P"][0][0]), len(est["P"][0][0][0])] == [K, 2, 2]
    assert len(est["d"]) == K and all(d is None or len(d) == 1 for tick in est["d"] for d in tick)
    assert set(METRIC_KEYS) <= set(est["metrics"])


def test_replay_without_truth_has_no_metrics(tmp_path, capsys):
    doc = copy.deepcopy(DOC)
    del doc["truth"]
    out_path = tmp_path / "est.json"
    code, _, _ = run_cli(["replay", write(tmp_path / "t.json", doc), "--out", out_path], capsys)
    assert code == 0 and "metrics" not in json.loads(out_path.read_text())


def test_installed_entry_point(tmp_path):
    """The console script: a good run, then bad input without a traceback."""
    trace = tmp_path / "trace.json"
    env = dict(os.environ, PYTHONWARNINGS="ignore")
    bindir = os.path.dirname(sys.executable)
    exe = os.path.join(bindir, "diskf-mesh") if os.path.exists(os.path.join(bindir, "diskf-mesh")) else "diskf-mesh"
    ok = subprocess.run([exe, "simulate", "--steps", "10", "--out", str(trace)],
                        capture_output=True, text=True, env=env, timeout=60)
    assert ok.returncode == 0, ok.stderr
    assert json.loads(trace.read_text())["format"] == "diskf-trace/1"
    trace.write_text("not json")
    out_path = tmp_path / "est.json"
    bad = subprocess.run([exe, "replay", str(trace), "--out", str(out_path)],
                         capture_output=True, text=True, env=env, timeout=60)
    assert bad.returncode == 2
    assert bad.stderr.count("\n") == 1 and bad.stderr.startswith("error: file:")
    assert not out_path.exists()
