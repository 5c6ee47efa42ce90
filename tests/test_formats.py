"""The JSON formats and their schemas (docs/formats.md): every schema accepts
what simulate, replay and up write, and rejects a broken document naming
the field; simulate + replay carries the scenario's estimator settings, so
it equals experiment bit for bit for every estimator."""
from __future__ import annotations

import copy
import dataclasses
import json
from importlib import resources
from pathlib import Path

import numpy as np
import pytest
from jsonschema import Draft202012Validator

from cli_helpers import run_cli, write
from diskf_mesh import estimators as algorithms
from diskf_mesh.engine import batch as engine
from diskf_mesh.data import schemas
from diskf_mesh.core.errors import InputError
from diskf_mesh.data.scenario import load_scenario, scenario_path, shipped_scenarios, simulate
from mesh_helpers import up

STEPS = 30


def test_every_schema_is_valid_and_shipped_as_package_data():
    names = sorted(p.name for p in resources.files("diskf_mesh.data.schemas").iterdir() if p.name.endswith(".json"))
    assert names == sorted(schemas.FILES.values())
    for fmt in schemas.FILES:
        s = schemas.schema(fmt)
        Draft202012Validator.check_schema(s)
        assert s["title"] == fmt


def simulate_replay(tmp_path, capsys, scenario, algorithm="diskf", steps=STEPS, extra=()):
    """(trace doc, estimates doc) written by simulate and replay."""
    trace, est = tmp_path / f"{algorithm}-trace.json", tmp_path / f"{algorithm}-est.json"
    code, _, err = run_cli(["simulate", "--scenario", scenario, "--ticks", steps, "--out", trace, *extra], capsys)
    assert code == 0, err
    code, _, err = run_cli(["replay", trace, "--algorithm", algorithm, "--out", est], capsys)
    assert code == 0, err
    return json.loads(trace.read_text()), json.loads(est.read_text())


@pytest.mark.parametrize("scenario", shipped_scenarios())
def test_simulate_and_replay_outputs_match_their_schemas(scenario, tmp_path, capsys):
    extra = ("--agents", "30") if scenario == "random-geometric" else ()
    trace, est = simulate_replay(tmp_path, capsys, scenario, extra=extra)
    schemas.check(trace, "diskf-trace/1")
    schemas.check(est, "diskf-estimates/1")
    assert trace["scenario"] == scenario and est["format"] == "diskf-estimates/1" and "metrics" in est


@pytest.mark.mesh
def test_up_estimates_match_their_schema(tmp_path):
    done, est, _ = up(tmp_path, "--scenario", "dynamic", "--ticks", "5")
    assert done.returncode == 0, done.stderr
    schemas.check(est, "diskf-mesh-estimates/1")
    broken = copy.deepcopy(est)
    broken["reported"][2][3] = 1
    with pytest.raises(InputError, match=r"^reported\[2\]\[3\]: "):
        schemas.check(broken, "diskf-mesh-estimates/1")
    del broken["run_id"]
    with pytest.raises(InputError, match=r"^run_id: is missing"):
        schemas.check(broken, "diskf-mesh-estimates/1")


def _set(doc, path, value):
    node = doc
    for key in path[:-1]:
        node = node[key]
    if value is KeyError:
        del node[path[-1]]
    else:
        node[path[-1]] = value


BROKEN_ESTIMATES = {
    "format": (("format",), "diskf-estimates/2", "format"),
    "x missing": (("x",), KeyError, "x"),
    "x entry": (("x", 3, 1, 0), "1.0", "x[3][1][0]"),
    "P not a matrix": (("P", 0, 2), "I", "P[0][2]"),
    "d entry": (("d", 4, 0), 2.5, "d[4][0]"),
    "metric missing": (("metrics", "nees"), KeyError, "metrics.nees"),
    "metric text": (("metrics", "mae_state"), "low", "metrics.mae_state"),
    "coverage above 1": (("metrics", "input_coverage"), 1.5, "metrics.input_coverage"),
}


@pytest.mark.parametrize("case", list(BROKEN_ESTIMATES))
def test_estimates_schema_names_the_broken_field(case, tmp_path, capsys):
    _, est = simulate_replay(tmp_path, capsys, "quadrants")
    path, value, field = BROKEN_ESTIMATES[case]
    _set(est, path, value)
    with pytest.raises(InputError) as e:
        schemas.check(est, "diskf-estimates/1")
    assert e.value.field == field


BROKEN_TRACES = {
    "links missing": (("links",), KeyError, "links"),
    "A and A_seq missing": (("A",), KeyError, "A"),
    "unknown field": (("postion_dims",), [0, 1], "postion_dims"),
    "unknown agent field": (("agents", 1, "h"), [[1.0, 0.0]], "agents[1].h"),
    "agent H missing": (("agents", 2, "H"), KeyError, "agents[2].H"),
    "measurement not a list": (("y", 3, 0), 3.0, "y[3][0]"),
    "measurement entry": (("y", 3, 0), ["a"], "y[3][0][0]"),
    "link entry": (("links", 1, 2), 2, "links[1][2]"),
    "link boolean": (("links", 0, 1), True, "links[0][1]"),
    "truth.d missing": (("truth", "d"), KeyError, "truth.d"),
    "seed float": (("seed",), 1.5, "seed"),
    "estimator window": (("estimator", "window"), -1, "estimator.window"),
    "estimator unknown": (("estimator", "epsilon"), 0.1, "estimator.epsilon"),
    "estimator compensation": (("estimator", "compensation"), "huge", "estimator.compensation"),
}


@pytest.mark.parametrize("case", list(BROKEN_TRACES))
def test_replay_of_a_broken_trace_names_the_field(case, tmp_path, capsys):
    trace, _ = simulate_replay(tmp_path, capsys, "quadrants")
    path, value, field = BROKEN_TRACES[case]
    _set(trace, path, value)
    out = tmp_path / "est.json"
    code, stdout, err = run_cli(["replay", write(tmp_path / "broken.json", trace), "--out", out], capsys)
    assert code == 2 and stdout == "" and not out.exists()
    (line,) = err.splitlines()
    assert line.startswith(f"error: {field}: ")


def test_both_A_and_A_seq_is_rejected(tmp_path, capsys):
    trace, _ = simulate_replay(tmp_path, capsys, "quadrants")
    trace["A_seq"] = [trace["A"]] * STEPS
    with pytest.raises(InputError) as e:
        schemas.check(trace, "diskf-trace/1")
    assert e.value.field == "A_seq"


def test_large_trace_arrays_are_checked_too():
    """The quick path for big regular arrays never lets a bad one through."""
    scn = load_scenario("random-geometric", agents=50).with_overrides(steps=10)
    from diskf_mesh.data.trace import trace_to_json

    doc = trace_to_json(simulate(scn, [0]))
    schemas.check(doc, "diskf-trace/1")
    for path, value in ((("links", 49, 3), 0.5), (("truth", "x", 9, 1), None), (("y", 9, 7), [True])):
        broken = copy.deepcopy(doc)
        _set(broken, path, value)
        with pytest.raises(InputError) as e:
            schemas.check(broken, "diskf-trace/1")
        assert e.value.field.startswith(f"{path[0]}")


# --------------------------------------------------------------------------
# simulate + replay == experiment, with the scenario's estimator settings
# --------------------------------------------------------------------------
@pytest.fixture(scope="module")
def odd_scenario(tmp_path_factory):
    """Scenario 2 with every [estimator] setting off its default."""
    text = scenario_path("dynamic").read_text()
    start, end = text.index("[estimator]"), text.index("[topology]")
    table = ('[estimator]\nwindow = "none"\nreset = false\neps = 0.2\ncompensation = "paper"\n'
             'consensus_eps = 0.05\nhold_input = true\n\n')
    path = tmp_path_factory.mktemp("scenario") / "odd.toml"
    path.write_text(text[:start] + table + text[end:])
    return str(path)


@pytest.mark.parametrize("algorithm", algorithms.NAMES)
@pytest.mark.parametrize("scenario", ["random-geometric", "odd"])
def test_simulate_replay_equals_experiment(algorithm, scenario, odd_scenario, tmp_path, capsys):
    name = odd_scenario if scenario == "odd" else scenario
    trace_doc, est = simulate_replay(tmp_path, capsys, name, algorithm, steps=60)
    scn = load_scenario(name).with_overrides(steps=60)
    assert trace_doc["estimator"] == dataclasses.asdict(scn.params)
    res = tmp_path / "experiment.json"
    code, _, err = run_cli(["experiment", "--scenario", name, "--algorithms", algorithm, "--seeds", "1",
                            "--ticks", "60", "--json", res], capsys)
    assert code == 0, err
    (row,) = json.loads(res.read_text())[algorithm].values()
    assert {k: row[k] for k in est["metrics"]} == est["metrics"]  # bit for bit
    want = engine.run(simulate(scn, [0]), algorithm, scn.params)
    assert np.array_equal(np.array(est["x"]), want.x[0]) and np.array_equal(np.array(est["P"]), want.P[0])


def test_experiment_on_dynamic_defaults_to_its_own_range(tmp_path, capsys):
    res = tmp_path / "experiment.json"
    code, _, err = run_cli(["experiment", "--scenario", "dynamic", "--algorithms", "diskf", "--seeds", "1",
                            "--ticks", "20", "--json", res], capsys)
    assert code == 0, err
    assert list(json.loads(res.read_text())["diskf"]) == ["range=120"]


# --------------------------------------------------------------------------
# docs/formats.md
# --------------------------------------------------------------------------
FORMATS_MD = Path(__file__).resolve().parents[1] / "docs" / "formats.md"


def test_formats_md_names_every_field_and_its_example_replays(tmp_path, capsys):
    text = FORMATS_MD.read_text()
    for fmt in schemas.FILES:
        s = schemas.schema(fmt)
        props = dict(s.get("properties", {}))
        for d in s.get("$defs", {}).values():
            props.update(d.get("properties", {}))
        for name in props:
            assert f"`{name}`" in text or f"`{name}." in text, (fmt, name)
    example = text.split("```json\n", 1)[1].split("```", 1)[0]
    out = tmp_path / "est.json"
    code, _, err = run_cli(["replay", write(tmp_path / "example.json", example), "--out", out], capsys)
    assert code == 0, err
    schemas.check(json.loads(out.read_text()), "diskf-estimates/1")
