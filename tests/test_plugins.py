"""A third-party estimator: examples/estimator-plugin, pip-installed into a
folder of this test's own (``pip install --target``, entry point and all)
that the commands and every process they start see on PYTHONPATH. It runs
in ``experiment`` and, over Zenoh, in ``up``, and its declared setting is
read from the scenario and the command line. The registry's refusals are
checked in-process."""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from diskf_mesh import estimators
from diskf_mesh.core.model import AutoOptions
from diskf_mesh.engine.batch import Estimates
from diskf_mesh.estimators.base import Estimator, Setting
from diskf_mesh.estimators.diskf import WINDOW

from mesh_helpers import assert_same

ROOT = Path(__file__).resolve().parents[1]
PLUGIN = ROOT / "examples" / "estimator-plugin"
NAME = "example-local"
TICKS, SEED = 25, 3


@pytest.fixture(scope="module")
def env(tmp_path_factory):
    """The environment of a process that has the plugin installed."""
    tmp = tmp_path_factory.mktemp("plugin")
    src, site = tmp / "src", tmp / "site"
    shutil.copytree(PLUGIN, src)  # pip builds in the source folder: not in the checkout
    subprocess.run([sys.executable, "-m", "pip", "install", "--quiet", "--no-deps", "--disable-pip-version-check",
                    "--target", str(site), str(src)], check=True, timeout=600)
    out = dict(os.environ)
    out["PYTHONPATH"] = os.pathsep.join(p for p in (str(site), str(ROOT), os.environ.get("PYTHONPATH")) if p)
    return out


def cli(env, *args, timeout=300) -> subprocess.CompletedProcess:
    done = subprocess.run([sys.executable, "-m", "diskf_mesh.cli.main", *map(str, args)], env=env,
                          capture_output=True, text=True, timeout=timeout)
    assert done.returncode == 0, done.stderr
    return done


def test_the_registry_loads_the_plugin_by_its_entry_point(env):
    assert NAME not in estimators.NAMES  # this process has no plugin: the test is not vacuous
    code = ("import json; from diskf_mesh import estimators as e; c = e.get('example-local'); "
            "print(json.dumps([list(e.NAMES), c.label, c.color, e.Params().report_input]))")
    done = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    names, label, color, report_input = json.loads(done.stdout)
    assert names[:len(estimators.NAMES)] == list(estimators.NAMES) and names[-1] == NAME
    assert (label, color, report_input) == ("Local KF", "tab:gray", True)


def test_experiment_runs_the_plugin(env, tmp_path):
    out = tmp_path / "res.json"
    cli(env, "experiment", "--scenario", "quadrants", "--estimators", f"diffkf,{NAME}", "--topology", "all,none",
        "--seeds", 2, "--ticks", 40, "--quiet", "--json", out)
    res = json.loads(out.read_text())
    local = res[NAME]
    # no fusion: the topology changes nothing, and it is DiffKF without neighbours
    assert local["all"] == local["none"]
    assert local["all"]["mae_state"] != res["diffkf"]["all"]["mae_state"]
    for key in ("mae_state", "rmse_state", "mae_input", "nees"):
        assert local["none"][key] == pytest.approx(res["diffkf"]["none"][key], rel=1e-9)
    assert local["all"]["input_coverage"] > 0


def _no_input(res) -> bool:
    row = res[NAME]["all"]
    return row["input_coverage"] == 0 and row["mae_input"] is None


def test_the_plugins_setting_from_the_command_line_and_the_scenario(env, tmp_path):
    out = tmp_path / "res.json"
    common = ("--estimators", NAME, "--topology", "all", "--seeds", 1, "--ticks", 20, "--quiet", "--json", out)
    cli(env, "experiment", "--scenario", "quadrants", "--report-input", "off", *common)
    assert _no_input(json.loads(out.read_text()))
    text = (ROOT / "diskf_mesh" / "scenarios" / "quadrants.toml").read_text()
    assert "\n[estimator]\n" in text
    scn = tmp_path / "off.toml"
    scn.write_text(text.replace("\n[estimator]\n", "\n[estimator]\nreport_input = false\n"))
    cli(env, "experiment", "--scenario", scn, *common)
    assert _no_input(json.loads(out.read_text()))
    cli(env, "experiment", "--scenario", scn, "--report-input", "on", *common)  # the flag overrides the table
    assert not _no_input(json.loads(out.read_text()))


@pytest.mark.mesh
def test_up_runs_the_plugin_and_equals_the_engine(env, tmp_path):
    """A real mesh run: every agent process loads the plugin; its estimates
    are the engine's (``replay`` of the same seed's trace)."""
    est, res = tmp_path / "est.json", tmp_path / "res.json"
    done = subprocess.run([sys.executable, "-m", "sim.launcher", "--scenario", "dynamic", "--estimator", NAME,
                           "--ticks", str(TICKS), "--seed", str(SEED), "--estimates", str(est), "--json", str(res),
                           "--logs", str(tmp_path / "logs"), "--quiet"],
                          env=env, capture_output=True, text=True, timeout=240)
    assert done.returncode == 0, done.stderr
    trace, ref = tmp_path / "trace.json", tmp_path / "ref.json"
    cli(env, "simulate", "--scenario", "dynamic", "--ticks", TICKS, "--seed", SEED, "--out", trace)
    cli(env, "replay", trace, "--estimator", NAME, "--out", ref)
    doc = json.loads(ref.read_text())
    d = np.array([[r if r is not None else [np.nan] for r in tick] for tick in doc["d"]])
    valid = ~np.isnan(d[..., 0])
    assert valid.any()
    assert_same(json.loads(est.read_text()), Estimates(np.array(doc["x"])[None], np.array(doc["P"])[None],
                                                       d[None], valid[None]))
    assert list(json.loads(res.read_text())) == [NAME, "provenance"]


# -- the registry's rules, in-process --------------------------------------
class _Named(Estimator):
    name, label = "x-test", "X"


def test_register_refuses_what_would_be_ambiguous():
    reg, settings = dict(estimators.REGISTRY), dict(estimators.SETTINGS)
    estimators.register(_Named, reg, settings)
    assert reg["x-test"] is _Named
    with pytest.raises(ValueError, match="taken"):
        estimators.register(type("Again", (_Named,), {}), reg, settings)
    clash = type("Clash", (_Named,), {"name": "x-clash", "settings": (Setting("window", 7, "another window"),)})
    with pytest.raises(ValueError, match="declared differently"):
        estimators.register(clash, reg, settings)
    shared = type("Shared", (_Named,), {"name": "x-shared", "settings": (WINDOW,)})
    estimators.register(shared, reg, settings)  # the same declaration is shared
    with pytest.raises(ValueError, match="subclass"):
        estimators.register(object, reg, settings)
    with pytest.raises(ValueError, match="must be"):
        estimators.register(type("Bad", (_Named,), {"name": "x-bad", "settings": (Setting("w", -1, "", low=0),)}),
                            reg, settings)
    assert "x-test" not in estimators.REGISTRY  # copies: the process's registry is unchanged


def test_one_tables_fields_changed_the_rest_kept():
    """``Params.with_setting``: the named fields of one table changed, every
    other field and table as it was, and the settings' checks run."""
    base = estimators.Params(window=3, auto=AutoOptions(hand_down=0.01))
    p = base.with_setting("auto", noise_level=10.0, switch=0.01)
    assert (p.auto.noise_level, p.auto.switch, p.auto.hand_down) == (10.0, 0.01, 0.01)
    assert p.window == 3 and p.robust == base.robust and base.auto.noise_level == 0.0
    with pytest.raises(ValueError, match="noise_level"):
        base.with_setting("auto", noise_level=1.0)
