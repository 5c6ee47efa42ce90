"""The command line: bad input ends in one line naming the field, exit 2,
and writes nothing; good input gives the documented outputs."""
from __future__ import annotations

import copy
import importlib
import json
import math
import os
import signal
import stat
import subprocess
import sys
import time
from pathlib import Path

import pytest

from cli_helpers import run_cli, simulated_doc, write
from diskf_mesh.cli import main as cli
from diskf_mesh import estimators as algorithms
from diskf_mesh.data.metrics import METRIC_KEYS
from diskf_mesh.data.scenario import load_scenario
from diskf_mesh.studies import experiment

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
    "agent id empty text": (mutate(("agents", 1, "id"), ""), "agents[1].id"),  # "north" is a valid id
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
QUICK = ["--seeds", "1", "--ticks", "5", "--quiet"]
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
    "steps text": (["--ticks", "many"], "--ticks"),
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
    "steps zero": (["--ticks", "0"], "--ticks"),
}


@pytest.mark.parametrize("case", list(BAD_SIMULATIONS))
def test_simulate_rejects_bad_input(case, tmp_path, capsys):
    args, field = BAD_SIMULATIONS[case]
    out_path = tmp_path / "trace.json"
    assert_rejected(["simulate", *args, "--out", out_path], field, out_path, capsys)


def test_experiment_json_shape(tmp_path, capsys):
    out_path = tmp_path / "results.json"
    code, out, err = run_cli(["experiment", "--seeds", "2", "--ticks", "30", "--json", out_path], capsys)
    assert code == 0 and all(line.startswith("experiment: ") for line in err.splitlines())  # lines, not a bar
    results = json.loads(out_path.read_text())
    assert list(results) == [*algorithms.ALL, "provenance"]  # the estimators, then what made them
    assert list(results)[0] == algorithms.DEFAULT == "diskf-auto"  # the table leads with the default
    assert sorted(algorithms.ALL) == sorted(algorithms.NAMES)
    for per_topology in list(results.values())[:-1]:
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
    assert list(results) == ["diskf", "kcf", "provenance"]
    assert list(results["diskf"]) == ["none", "range=250"]


def test_experiment_from_a_first_seed(tmp_path, capsys):
    """``--first-seed 3 --seeds 2`` runs seeds 3 and 4: its provenance and
    header name them, and its rows are ``run_experiment``'s on them, not
    those of seeds 0 and 1."""
    rows = {}
    for first in (0, 3):
        out_path = tmp_path / f"from{first}.json"
        code, out, _ = run_cli(["experiment", "--estimators", "diskf-auto", "--topology", "ring", "--seeds", "2",
                                "--first-seed", str(first), "--ticks", "30", "--json", out_path], capsys)
        assert code == 0
        rows[first] = json.loads(out_path.read_text())
    assert rows[3]["provenance"]["seeds"] == [3, 4] and "2 seeds (3..4) x 30 ticks" in out
    scn = load_scenario("quadrants")
    want = experiment.run_experiment(scn, experiment.settings_for(["ring"], None), ["diskf-auto"], range(3, 5), 30)
    assert rows[3]["diskf-auto"]["ring"]["mae_state"] == want["diskf-auto"]["ring"]["mae_state"]
    assert rows[3]["diskf-auto"]["ring"]["mae_state"] != rows[0]["diskf-auto"]["ring"]["mae_state"]


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
    ok = subprocess.run([exe, "simulate", "--ticks", "10", "--out", str(trace)],
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


# --------------------------------------------------------------------------
# scenario files: every field typed and range-checked
# --------------------------------------------------------------------------
QUADRANTS = (Path(__file__).parents[1] / "diskf_mesh" / "scenarios" / "quadrants.toml").read_text()
DYNAMIC = (Path(__file__).parents[1] / "diskf_mesh" / "scenarios" / "dynamic.toml").read_text()


def edited(text, old, new):
    assert old in text
    return text.replace(old, new, 1)


BAD_SCENARIOS = {  # scenario text, field named in the error
    "omega nan": (edited(QUADRANTS, "omega = 0.15707963267948966", "omega = nan"), "model.omega"),
    "omega text": (edited(QUADRANTS, "omega = 0.15707963267948966", 'omega = "fast"'), "model.omega"),
    "negative range": (edited(DYNAMIC, "range = 120.0", "range = -120.0"), "topology.range"),
    "period zero": (edited(DYNAMIC, "period = 120", "period = 0"), "agents[4].period"),
    "period negative": (edited(DYNAMIC, "period = 90", "period = -90"), "agents[7].period"),
    "phase inf": (edited(DYNAMIC, "phase = 0.25", "phase = inf"), "agents[7].phase"),
    "misspelled key": (edited(QUADRANTS, "eps = 0.05", "epss = 0.05"), "estimator.epss"),
    "unknown table": (QUADRANTS + "\n[topolgy]\nkind = \"ring\"\n", "topolgy"),
    "agent key misspelled": (edited(QUADRANTS, 'position = [150.0, 150.0]', 'positon = [150.0, 150.0]'),
                             "agents[0].positon"),
    "id 2^64": (edited(QUADRANTS, "id = 1", "id = 18446744073709551616"), "agents[0].id"),
    "id 2^63": (edited(QUADRANTS, "id = 1", "id = 9223372036854775808"), "agents[0].id"),
    "id float": (edited(QUADRANTS, "id = 1", "id = 1.0"), "agents[0].id"),
    "steps float": (edited(QUADRANTS, "steps = 200", "steps = 200.5"), "steps"),
    "steps bool": (edited(QUADRANTS, "steps = 200", "steps = true"), "steps"),
    "window float": (edited(QUADRANTS, "window = 5", "window = 2.5"), "estimator.window"),
    "reset text": (edited(QUADRANTS, "reset = true", 'reset = "yes"'), "estimator.reset"),
    "consensus_eps negative": (edited(QUADRANTS, "consensus_eps = 0.1", "consensus_eps = -0.1"),
                               "estimator.consensus_eps"),
    "input at negative": (edited(QUADRANTS, "at = 10", "at = -10"), "input.at"),
    "input at float": (edited(QUADRANTS, "at = 10", "at = 10.5"), "input.at"),
    "huge matrix entry": (edited(QUADRANTS, "x0 = [200.0, 0.0]", "x0 = [1e300, 0.0]"), "model.x0"),
    "tiny variance": (edited(QUADRANTS, "R = [[2.0]]", "R = [[1e-300]]"), "agents[0].R"),
    "A with rotation": (edited(QUADRANTS, "G = [[1.0], [1.0]]", "G = [[1.0], [1.0]]\nA = [[1.0, 0.0], [0.0, 1.0]]"),
                        "model.A"),
    "position and path": (edited(DYNAMIC, "period = 120", "period = 120\nposition = [0.0, 0.0]"),
                          "agents[4].position"),
    "fault unknown": (QUADRANTS.replace("[topology]", "[faults]\nlos = 0.1\n\n[topology]"), "faults.los"),
    "fault probability": (QUADRANTS.replace("[topology]", "[faults]\nloss = 2.0\n\n[topology]"), "faults.loss"),
    "agents not tables": (QUADRANTS.split("[[agents]]")[0] + "agents = [1, 2]\n", "agents"),
}


@pytest.mark.parametrize("case", list(BAD_SCENARIOS))
def test_experiment_rejects_bad_scenario(case, tmp_path, capsys):
    text, field = BAD_SCENARIOS[case]
    scenario = write(tmp_path / "scenario.toml", text)
    out_path = tmp_path / "results.json"
    assert_rejected(["experiment", *QUICK, "--scenario", scenario, "--json", out_path], field, out_path, capsys)


def test_misspelled_key_names_the_likely_one(tmp_path, capsys):
    scenario = write(tmp_path / "scenario.toml", BAD_SCENARIOS["misspelled key"][0])
    code, _, err = run_cli(["experiment", *QUICK, "--scenario", scenario], capsys)
    assert code == 2 and "'eps'" in err.split("estimator.epss", 1)[1]


def test_generated_agent_count_over_the_memory_bound(tmp_path, capsys):
    """Refused before numpy is asked for the arrays: fast, and exit 2."""
    out_path = tmp_path / "results.json"
    t0 = time.monotonic()
    assert_rejected(["experiment", *QUICK, "--scenario", "random-geometric", "--agents", "1000000",
                     "--json", out_path], "size", out_path, capsys)
    assert time.monotonic() - t0 < 5


def test_a_simulated_network_over_its_memory_bound_is_refused(tmp_path, capsys):
    """12,000 random-geometric agents fit the engine's bound (``experiment``
    runs them) but not the simulated network's (about 5.5 GiB): ``up
    --network simulated`` refuses them in one line, exit 2, before anything
    is written; 10,000 agents x 20 ticks (about 4.1 GiB) pass the check."""
    from diskf_mesh.data.scenario import load_scenario
    from diskf_mesh.mesh.simulated.simrun import check_size

    out_path = tmp_path / "results.json"
    assert_rejected(["up", "--network", "simulated", "--quiet", "--scenario", "random-geometric", "--agents", "12000",
                     "--ticks", "20", "--json", out_path], "size", out_path, capsys)
    check_size(load_scenario("random-geometric", agents=10000).with_overrides(steps=20))


def test_too_many_seeds_refused_before_allocating(tmp_path, capsys):
    out_path = tmp_path / "results.json"
    assert_rejected(["experiment", "--quiet", "--seeds", "100000000", "--json", out_path], "size", out_path, capsys)


def test_id_at_the_top_of_the_range_runs(tmp_path, capsys):
    scenario = write(tmp_path / "scenario.toml", edited(QUADRANTS, "id = 1", f"id = {2**63 - 1}"))
    code, out, err = run_cli(["experiment", *QUICK, "--scenario", scenario], capsys)
    assert code == 0, err


# --------------------------------------------------------------------------
# output files: checked before any work, atomic, umask, '-' for stdout
# --------------------------------------------------------------------------
def _trace(tmp_path):
    return write(tmp_path / "trace.json", DOC)


# command argv (before the output flag), the output flag, the field, the function doing the work
WRITERS = {
    "experiment": (lambda tmp: ["experiment", *QUICK], "--json", "json", "diskf_mesh.studies.experiment.run_experiment"),
    "simulate": (lambda tmp: ["simulate", "--ticks", "5"], "--out", "out", "diskf_mesh.cli.simulate.simulate"),
    "replay": (lambda tmp: ["replay", _trace(tmp)], "--out", "out", "diskf_mesh.engine.batch.run"),
}


def _bad_target(kind, tmp_path):
    """(path, a check that the node is unchanged afterwards)."""
    if kind in ("/dev/null", "/dev/full"):
        if not os.path.exists(kind) or not stat.S_ISCHR(os.lstat(kind).st_mode):
            pytest.skip(f"{kind} is not a character device here (a container's plain file); 'fifo' covers special nodes")
        return kind, lambda: stat.S_ISCHR(os.lstat(kind).st_mode)
    if kind == "fifo":  # a special node every machine can make
        fifo = tmp_path / "pipe.json"
        os.mkfifo(fifo)
        return str(fifo), lambda: stat.S_ISFIFO(os.lstat(fifo).st_mode)
    if kind == "symlink":
        target = tmp_path / "target.json"
        target.write_text("keep")
        link = tmp_path / "link.json"
        link.symlink_to(target)
        return str(link), lambda: link.is_symlink() and target.read_text() == "keep"
    if kind == "dangling symlink":
        link = tmp_path / "link.json"
        link.symlink_to(tmp_path / "nowhere.json")
        return str(link), lambda: link.is_symlink() and not (tmp_path / "nowhere.json").exists()
    if kind == "directory":
        folder = tmp_path / "folder"
        folder.mkdir()
        return str(folder), lambda: folder.is_dir() and not any(folder.iterdir())
    if kind == "missing folder":
        return str(tmp_path / "nowhere" / "r.json"), lambda: not (tmp_path / "nowhere").exists()
    if kind == "unwritable folder":  # /proc refuses new files even to root
        return "/proc/diskf-out.json", lambda: not os.path.exists("/proc/diskf-out.json")
    if kind == "read-only folder":
        if os.geteuid() == 0:
            pytest.skip("root writes into a 0500 folder")
        folder = tmp_path / "ro"
        folder.mkdir(mode=0o500)
        return str(folder / "r.json"), lambda: not any(folder.iterdir())
    raise AssertionError(kind)


BAD_TARGETS = ["/dev/null", "/dev/full", "fifo", "symlink", "dangling symlink", "directory", "missing folder",
               "unwritable folder", "read-only folder"]


@pytest.mark.parametrize("command", list(WRITERS))
@pytest.mark.parametrize("kind", BAD_TARGETS)
def test_bad_output_refused_before_any_work(command, kind, tmp_path, capsys, monkeypatch):
    argv, flag, field, work = WRITERS[command]
    path, unchanged = _bad_target(kind, tmp_path)
    ran = []
    module, _, name = work.rpartition(".")
    monkeypatch.setattr(importlib.import_module(module), name, lambda *a, **k: ran.append(1))
    code, out, err = run_cli([*argv(tmp_path), flag, path], capsys)
    assert code == 2 and err.startswith(f"error: {field}:") and err.count("\n") == 1, err
    assert out == "" and not ran
    assert unchanged()
    assert not [p for p in tmp_path.rglob("*.tmp")]


@pytest.mark.parametrize("kind", ["/dev/null", "fifo", "symlink", "directory", "unwritable folder"])
def test_up_and_world_refuse_bad_outputs_before_starting(kind, tmp_path, capsys):
    path, unchanged = _bad_target(kind, tmp_path)
    logs = tmp_path / "logs"
    cli.build_parser()  # imports every command: not part of the time below
    for argv in (["up", "--ticks", "2", "--logs", logs, "--json", path],
                 ["up", "--ticks", "2", "--logs", logs, "--estimates", path],
                 ["world", "--ticks", "2", "--startup-timeout", "120", "--json", path],
                 ["world", "--ticks", "2", "--startup-timeout", "120", "--estimates", path]):
        t0 = time.monotonic()
        code, out, err = run_cli(argv, capsys)
        assert code == 2 and err.startswith("error: ") and err.count("\n") == 1, err
        assert time.monotonic() - t0 < 60  # a world that ran would wait 120 s for its agents
        assert not logs.exists() and unchanged()  # up started no process (it would have made the logs)


def test_up_and_world_refuse_stdout_for_results(tmp_path, capsys):
    for argv in (["up", "--json", "-", "--logs", tmp_path / "logs"], ["world", "--estimates", "-"]):
        code, out, err = run_cli(argv, capsys)
        assert code == 2 and err.startswith("error: ") and out == ""
    assert not (tmp_path / "logs").exists()


@pytest.mark.parametrize("command", ["figures", "report"])
def test_study_output_folder_checked_first(command, tmp_path, capsys, monkeypatch):
    blocked = blocker(tmp_path)
    for out in (blocked, "/proc/diskf-figures"):
        code, _, err = run_cli([command, "--out", out, "--seeds", "1", "--ticks", "5", "--quiet"], capsys)
        assert code == 2 and err.startswith("error: out:") and err.count("\n") == 1, err
    assert blocked.read_text() == ""


@pytest.mark.parametrize("mask", [0o022, 0o077, 0o002])
def test_outputs_follow_the_umask(mask, tmp_path, capsys):
    out_path = tmp_path / "trace.json"
    old = os.umask(mask)
    try:
        code, _, _ = run_cli(["simulate", "--ticks", "5", "--out", out_path], capsys)
    finally:
        os.umask(old)
    assert code == 0
    assert stat.S_IMODE(out_path.stat().st_mode) == 0o666 & ~mask


def test_output_replaces_a_regular_file(tmp_path, capsys):
    out_path = tmp_path / "trace.json"
    out_path.write_text("old")
    code, _, _ = run_cli(["simulate", "--ticks", "5", "--out", out_path], capsys)
    assert code == 0 and json.loads(out_path.read_text())["format"] == "diskf-trace/1"
    assert [p.name for p in tmp_path.iterdir()] == ["trace.json"]


def test_json_dash_writes_to_stdout(tmp_path, capsys):
    code, out, err = run_cli(["experiment", *QUICK, "--algorithms", "diskf", "--json", "-"], capsys)
    assert code == 0
    results = json.loads(out)  # stdout carries the JSON alone; the table went to stderr
    assert list(results) == ["diskf", "provenance"] and "MAE(state)" in err
    code, out, err = run_cli(["simulate", "--ticks", "5", "--out", "-"], capsys)
    assert code == 0 and json.loads(out)["format"] == "diskf-trace/1"
    code, out, err = run_cli(["replay", _trace(tmp_path), "--out", "-"], capsys)
    assert code == 0 and json.loads(out)["format"] == "diskf-estimates/1"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["trace.json"]


WRITER_SCRIPT = """
import sys, time
from diskf_mesh.data.outputs import atomic_open
with atomic_open(sys.argv[1]) as f:
    f.write("partial")
    f.flush()
    print("writing", flush=True)
    time.sleep(60)
"""


@pytest.mark.parametrize("named", [False, True], ids=["unnamed", "named (no O_TMPFILE)"])
@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT, signal.SIGKILL])
def test_no_temporary_file_left_when_killed_mid_write(sig, named, tmp_path):
    """The file being written has no name (``O_TMPFILE``) until every byte
    is in: a kill at any moment, SIGKILL too, leaves the target as it was
    and nothing else. Where unnamed files are missing, a named temporary
    file is removed on every signal but SIGKILL."""
    target = tmp_path / "out.json"
    target.write_text("old")
    no_unnamed = "import diskf_mesh.data.outputs as o; o._unnamed = lambda folder: None\n"
    script = (no_unnamed if named else "") + WRITER_SCRIPT
    p = subprocess.Popen([sys.executable, "-c", script, str(target)], stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, text=True)
    try:
        assert p.stdout.readline() == "writing\n"
        assert len(list(tmp_path.glob(".out.json.*.tmp"))) == named  # the write is under way
        p.send_signal(sig)
        p.wait(30)
    finally:
        p.kill()
    assert p.returncode != 0
    left = sorted(tmp_path.iterdir())
    if named and sig == signal.SIGKILL:  # the control: SIGKILL leaves a named temporary file behind
        assert len(left) == 2 and left[0].stat().st_size == len("partial")
        return
    assert left == [target] and target.read_text() == "old"


def test_a_large_file_is_written_whole(tmp_path):
    from diskf_mesh.data.outputs import atomic_open
    target, data = tmp_path / "big.bin", bytes(range(256)) * (3 * 4096 + 7)  # 3 MiB and a bit
    with atomic_open(target, "wb") as f:
        f.write(data)
    assert target.read_bytes() == data and list(tmp_path.iterdir()) == [target]


def test_temporary_file_removed_on_error(tmp_path):
    from diskf_mesh.data.outputs import atomic_open
    target = tmp_path / "out.json"
    with pytest.raises(ZeroDivisionError):
        with atomic_open(target) as f:
            f.write("partial")
            1 / 0
    assert list(tmp_path.iterdir()) == []


def test_closed_stdout_pipe_ends_quietly():
    read, write_end = os.pipe()
    os.close(read)
    try:
        p = subprocess.run([sys.executable, "-m", "diskf_mesh.cli.main", "experiment", *QUICK], stdout=write_end,
                           stderr=subprocess.PIPE, text=True, timeout=120)
    finally:
        os.close(write_end)
    assert p.stderr == "" and p.returncode == 141


# --------------------------------------------------------------------------
# printers take missing values
# --------------------------------------------------------------------------
def test_format_table_accepts_missing_values():
    from diskf_mesh.studies.experiment import TABLE_METRICS, format_table
    full = {k: 1.0 for k in TABLE_METRICS}
    results = {
        "diskf": {"all": {**full, "mae_state": math.nan}, "ring": full},
        "kcf": {"all": {**full, "mae_state": None, "rmse_state": "n/a"}},  # no ring at all
        "ldrkf": {"all": {}, "ring": None},
        "gdkf": {},
    }
    table = format_table(results)
    rows = table.splitlines()
    mae = next(r for r in rows if r.startswith("all-to-all"))
    assert mae.split()[2:] == ["-", "-", "-", "-"]
    assert sum(r.split()[0] == "1-hop" for r in rows if r.split()) == 1
    assert format_table({}).splitlines()[0].startswith("Comm.")
