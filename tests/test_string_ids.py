"""Agent ids may be names ("drone-1") in traces and scenarios.

Inside a run every agent has an integer id (``validate.internal_ids``: the
ids themselves when all are integers, else 1..N in order, the ids a scenario
without ids gets); the user's ids come back in every output. So a scenario
whose ids are names gives the estimates of the same scenario with integer
ids bit for bit (every estimator, in the engine and on the mesh), and its
outputs name the agents as the user did."""
from __future__ import annotations

import copy
import json
import re
import subprocess
import sys

import numpy as np
import pytest

from cli_helpers import run_cli, simulated_doc, write
from diskf_mesh.data.scenario import load_scenario, scenario_path
from diskf_mesh.data.trace import load_trace

from diskf_mesh.mesh.process.runspec import RunSpec
from mesh_helpers import assert_same, reference, up

NAMES = ["north-east", "north-west", "south-west", "south-east"]
DYNAMIC_NAMES = [f"drone-{k}" for k in range(1, 10)]


def named_dynamic(tmp_path, names=DYNAMIC_NAMES) -> str:
    """Scenario 2 (dynamic) with its ids 1..9 replaced by ``names``."""
    text = scenario_path("dynamic").read_text()
    ids = iter(names)
    text, count = re.subn(r"(?m)^id = \d+$", lambda m: f"id = {json.dumps(next(ids))}", text)
    assert count == len(names)
    path = tmp_path / "named.toml"
    path.write_text(text)
    return str(path)


def cli(*args, timeout=300) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "diskf_mesh.cli.main", *map(str, args)], capture_output=True,
                          text=True, timeout=timeout)


def estimates(path) -> dict:
    return json.loads(open(path).read())


def test_trace_with_names_replays_with_them(tmp_path, capsys):
    plain = simulated_doc()
    named = copy.deepcopy(plain)
    for a, name in zip(named["agents"], NAMES):
        a["id"] = name
    for doc, tag in ((plain, "plain"), (named, "named")):
        code, _, err = run_cli(["replay", write(tmp_path / f"{tag}.json", doc), "--algorithm", "gdkf",
                                "--out", tmp_path / f"est-{tag}.json"], capsys)
        assert code == 0, err
    a, b = estimates(tmp_path / "est-plain.json"), estimates(tmp_path / "est-named.json")
    assert b["ids"] == NAMES and a["ids"] == [1, 2, 3, 4]
    assert (b["x"], b["P"], b["d"], b["metrics"]) == (a["x"], a["P"], a["d"], a["metrics"])  # gossip draws too
    assert load_trace(tmp_path / "named.json").agent_labels == tuple(NAMES)


def test_scenario_with_names_experiment_and_simulate_replay(tmp_path, capsys):
    named = named_dynamic(tmp_path)
    assert load_scenario(named).labels == tuple(DYNAMIC_NAMES)
    for scn, tag in (("dynamic", "plain"), (named, "named")):
        code, _, err = run_cli(["experiment", "--scenario", scn, "--ticks", 40, "--seeds", 2,
                                "--json", tmp_path / f"exp-{tag}.json", "--quiet"], capsys)
        assert code == 0, err
        code, _, err = run_cli(["simulate", "--scenario", scn, "--ticks", 40, "--seed", 3,
                                "--out", tmp_path / f"trace-{tag}.json"], capsys)
        assert code == 0, err
        code, _, err = run_cli(["replay", tmp_path / f"trace-{tag}.json", "--algorithm", "diskf",
                                "--out", tmp_path / f"est-{tag}.json"], capsys)
        assert code == 0, err
    named_exp, plain_exp = estimates(tmp_path / "exp-named.json"), estimates(tmp_path / "exp-plain.json")
    assert named_exp.pop("provenance")["scenario"]["name"] == plain_exp.pop("provenance")["scenario"]["name"]
    assert named_exp == plain_exp  # every estimator
    trace = estimates(tmp_path / "trace-named.json")
    assert [a["id"] for a in trace["agents"]] == DYNAMIC_NAMES
    a, b = estimates(tmp_path / "est-plain.json"), estimates(tmp_path / "est-named.json")
    assert b["ids"] == DYNAMIC_NAMES and a["ids"] == list(range(1, 10))
    assert (b["x"], b["P"], b["d"]) == (a["x"], a["P"], a["d"])


@pytest.mark.mesh
def test_up_with_names_keeps_them_in_results_estimates_and_recording(tmp_path):
    named = named_dynamic(tmp_path)
    rec = tmp_path / "run.mcap"
    done, est, res = up(tmp_path, "--scenario", named, "--ticks", "20", "--seed", "4", "--algorithm", "gdkf",
                        "--record", str(rec), timeout=240)
    assert done.returncode == 0, done.stderr
    assert est["ids"] == DYNAMIC_NAMES
    assert sorted(est["agent_counters"]) == sorted(DYNAMIC_NAMES)
    (row,) = [r for name, settings in res.items() if name != "provenance" for r in settings.values()]
    assert sorted(row["counters"]) == sorted(DYNAMIC_NAMES)
    # mesh == engine: the named run is the engine's run of Scenario 2 with its integer ids (gossip draws too)
    assert_same(est, reference(RunSpec("dynamic", "gdkf"), 20, 4)[1], tol=0.0)
    summary = json.loads(cli("inspect", rec, "--json").stdout)
    assert summary["ids"] == DYNAMIC_NAMES and summary["finished"]
    replayed = cli("replay", rec, "--out", tmp_path / "replayed.json")
    assert replayed.returncode == 0, replayed.stderr  # bit for bit
    doc = estimates(tmp_path / "replayed.json")
    assert doc["ids"] == DYNAMIC_NAMES and doc["x"] == est["x"]
    from diskf_mesh.recording.reader import read
    r = read(rec)
    agents = {e["agent"] for m in r.messages_by_topic["/agents/estimates"] for e in m["estimates"]}
    senders = {d["sender"] for d in r.delivered} | {m["sender"] for m in r.sent}
    assert agents == set(DYNAMIC_NAMES) and senders <= set(DYNAMIC_NAMES)
    assert r.run["ids"] == DYNAMIC_NAMES


BAD_SCENARIO_IDS = {
    "repeated name": (["a", "b", "a"], "agents.id"),
    "1 and '1'": ([1, "1"], "agents.id"),
    "empty name": (["a", ""], "agents[1].id"),
    "spaces around": ([" a"], "agents[0].id"),
    "float": ([1.5], "agents[0].id"),
    "boolean": ([True], "agents[0].id"),
    "list": ([[1]], "agents[0].id"),
    "table": ([{"x": 1}], "agents[0].id"),
}


def toml_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, dict):
        return "{ " + ", ".join(f"{k} = {toml_value(x)}" for k, x in v.items()) + " }"
    if isinstance(v, list):
        return "[" + ", ".join(toml_value(x) for x in v) + "]"
    return json.dumps(v)


@pytest.mark.parametrize("case", list(BAD_SCENARIO_IDS))
def test_bad_scenario_ids_rejected(case, tmp_path, capsys):
    ids, field = BAD_SCENARIO_IDS[case]
    text = scenario_path("quadrants").read_text()
    values = iter(ids + [f"other-{k}" for k in range(10)])
    text = re.sub(r"(?m)^id = \d+$", lambda m: f"id = {toml_value(next(values))}", text)
    path = tmp_path / "bad.toml"
    path.write_text(text)
    out = tmp_path / "out.json"
    code, stdout, err = run_cli(["experiment", "--scenario", path, "--ticks", 5, "--json", out, "--quiet"], capsys)
    lines = err.strip().splitlines()
    assert code == 2 and len(lines) == 1 and lines[0].startswith(f"error: {field}"), err
    assert not out.exists()


BAD_TRACE_IDS = {
    "repeated name": (["a", "b", "a", "c"], "agents.id"),
    "1 and '1'": ([1, "1", 3, 4], "agents.id"),
    "empty name": (["a", "", "c", "d"], "agents[1].id"),
    "boolean": ([True, 2, 3, 4], "agents[0].id"),
    "null": ([None, 2, 3, 4], "agents[0].id"),
    "too long": (["x" * 65, 2, 3, 4], "agents[0].id"),
}


@pytest.mark.parametrize("case", list(BAD_TRACE_IDS))
def test_bad_trace_ids_rejected(case, tmp_path, capsys):
    ids, field = BAD_TRACE_IDS[case]
    doc = simulated_doc()
    for a, i in zip(doc["agents"], ids):
        a["id"] = i
    out = tmp_path / "est.json"
    code, _, err = run_cli(["replay", write(tmp_path / "t.json", doc), "--out", out], capsys)
    lines = err.strip().splitlines()
    assert code == 2 and len(lines) == 1 and lines[0].startswith(f"error: {field}"), err
    assert not out.exists()


def test_internal_ids():
    from diskf_mesh.data.validate import internal_ids
    assert internal_ids((5, 3, 9)) == (5, 3, 9)
    assert internal_ids(("a", "b", "c")) == (1, 2, 3)
    assert internal_ids((7, "b")) == (1, 2)
    assert np.array_equal(internal_ids(tuple(range(1, 5))), [1, 2, 3, 4])
