"""The public Python API (docs/api.md): the calls give the command line's
numbers, results carry provenance and convert to the documented documents,
bad input raises InputError naming the field, and ``import diskf_mesh``
loads none of it until used."""
from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

import diskf_mesh
from cli_helpers import run_cli
from diskf_mesh.data import provenance, schemas
from diskf_mesh.engine import batch as engine


def test_import_is_cheap_and_the_api_loads_on_use():
    code = ("import sys, diskf_mesh; print('diskf_mesh.api' in sys.modules, 'numpy' in sys.modules); "
            "diskf_mesh.load_scenario; print('diskf_mesh.api' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.split()
    assert out == ["False", "False", "True"]
    assert set(diskf_mesh.__all__) >= {"load_scenario", "simulate", "estimate", "run", "experiment", "replay", "up"}
    with pytest.raises(AttributeError):
        diskf_mesh.no_such_thing  # noqa: B018


def test_the_package_is_typed():
    from importlib import resources

    assert resources.files("diskf_mesh").joinpath("py.typed").is_file()


def test_run_equals_the_engine_bit_for_bit():
    scn = diskf_mesh.load_scenario("dynamic")
    run = diskf_mesh.run(scn, "kcf", seeds=[3, 4], steps=25)
    trace = diskf_mesh.simulate(scn, seeds=[3, 4], steps=25)
    ref = engine.run(trace, "kcf", scn.params)
    assert run.x.shape == (2, 25, scn.N, 2)
    np.testing.assert_array_equal(run.x, ref.x)
    np.testing.assert_array_equal(run.P, ref.P)
    assert run.metrics["mae_state"] > 0 and run.agents == scn.labels
    assert run.provenance["seeds"] == [3, 4] and run.provenance["scenario"]["name"] == "dynamic"


def test_experiment_equals_the_command_line(tmp_path, capsys):
    out = tmp_path / "r.json"
    assert run_cli(["experiment", "--scenario", "quadrants", "--algorithms", "diskf,gdkf", "--seeds", "2",
                    "--ticks", "20", "--quiet", "--json", out], capsys)[0] == 0
    cli = provenance.split(json.loads(out.read_text()))[1]
    res = diskf_mesh.experiment("quadrants", "diskf,gdkf", seeds=2, steps=20)
    assert provenance.split(res.to_dict())[1] == cli
    assert list(res.to_dict())[-1] == "provenance" and res.provenance["estimator"] == ["diskf", "gdkf"]
    assert "MAE(state)" in res.table() and set(res.metric("mae_state")) == {"diskf", "gdkf"}


def test_replay_of_a_written_trace_and_its_document(tmp_path):
    trace = diskf_mesh.simulate("quadrants", seeds=[5], steps=15)
    path = tmp_path / "t.json"
    diskf_mesh.write_trace(trace, path, scenario="quadrants")
    again = diskf_mesh.read_trace(path)
    np.testing.assert_array_equal(again.y, trace.y)
    run = diskf_mesh.replay(path, "diskf")
    np.testing.assert_array_equal(run.x, engine.run(trace, "diskf").x)
    doc = run.to_dict()
    schemas.check(doc, "diskf-estimates/1")
    assert doc["provenance"]["scenario"]["name"] == "quadrants" and doc["provenance"]["seeds"] == [5]


def test_settings_override_and_bad_input_names_the_field():
    scn = diskf_mesh.load_scenario("quadrants")
    a = diskf_mesh.run(scn, "diskf", steps=60, topology="ring", settings={"eps": 0.3})
    b = diskf_mesh.run(scn, "diskf", steps=60, topology="ring")
    assert a.provenance["settings"]["eps"] == 0.3 and not np.array_equal(a.x, b.x)
    with pytest.raises(diskf_mesh.InputError, match="settings.windw"):
        diskf_mesh.run(scn, "diskf", settings={"windw": 2})
    with pytest.raises(diskf_mesh.InputError, match="estimator"):
        diskf_mesh.run(scn, "no-such-estimator")
    with pytest.raises(diskf_mesh.InputError, match="scenario"):
        diskf_mesh.load_scenario("no-such-scenario")
    with pytest.raises(diskf_mesh.InputError, match="seeds"):
        diskf_mesh.run(scn, seeds=0)


@pytest.mark.mesh
def test_up_runs_a_mesh_from_python():
    res = diskf_mesh.up("dynamic", ticks=5, timeout=240)
    assert res.exit_status == 0, res.stderr
    assert res.row["complete"] is True and res.provenance["ticks"] == 5
    assert np.array(res.estimates["x"]).shape[:2] == (5, 9)
