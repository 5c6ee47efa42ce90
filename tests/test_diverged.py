"""A numerical failure of an estimator ends that run, and only that run,
with ``diverged`` and one line: in the engine, in ``experiment``, in
``replay`` and on the mesh. Never a traceback. The constant-acceleration
model (n = 6) in a ring breaks C-DRKF and L-DRKF (their covariance stops
being positive definite) and sends DISKF's estimates past 1e15."""
from __future__ import annotations

import json

import numpy as np
import pytest

from diskf_mesh.data.scenario import simulate
from diskf_mesh.data.trace import trace_to_json
from diskf_mesh.engine import batch as engine
from diskf_mesh.mesh.simulated.simnet import Link
from diskf_mesh.mesh.simulated.simrun import SimPlan, simulate_run
from diskf_mesh.studies import experiment, heldout
from cli_helpers import run_cli, write

K = 40


@pytest.fixture(scope="module")
def ca():
    scn = heldout.constant_acceleration("ring").with_overrides(steps=K)
    return scn, simulate(scn, [0, 1])


def test_the_engine_names_whose_covariance_failed_and_when(ca):
    scn, tr = ca
    for name in ("cdrkf", "ldrkf"):
        with pytest.raises(engine.Diverged) as e:
            engine.run(tr, name, scn.params)
        assert 1 <= e.value.tick <= K and str(e.value).startswith(f"{name}, tick {e.value.tick}:")
    with np.errstate(all="ignore"):
        est = engine.run(tr, "diskf", scn.params)
    k = experiment.diverged_tick(est)
    assert k is not None and np.abs(est.x[:, k - 1]).max() > 1e15 >= np.abs(est.x[:, k - 2]).max()
    assert experiment.diverged_tick(engine.run(tr, "kcf", scn.params)) is None


def test_experiment_rows_say_diverged_and_the_others_run(ca):
    scn, _ = ca
    st = experiment.settings_for(["ring"])
    res = experiment.run_experiment(scn, st, ["diskf", "cdrkf", "ldrkf", "kcf", "diskf-auto"], range(2), K)
    assert [res[a]["ring"]["diverged"] is True for a in ("diskf", "cdrkf", "ldrkf")] == [True] * 3
    assert not res["kcf"]["ring"].get("diverged") and res["kcf"]["ring"]["mae_state"] < 10
    assert not res["diskf-auto"]["ring"].get("diverged")


def test_experiment_command_one_line_per_diverged_estimator(ca, tmp_path, capsys):
    path = tmp_path / "ca.toml"
    path.write_text(_toml(ca[0]))
    out = tmp_path / "r.json"
    code, text, err = run_cli(["experiment", "--scenario", path, "--estimators", "cdrkf,kcf", "--topology", "ring",
                               "--seeds", 1, "--ticks", K, "--json", out, "--quiet"], capsys)
    assert code == 0 and "Traceback" not in err
    assert [line for line in err.splitlines() if line.startswith("diverged:")] == [
        "diverged: C-DRKF in 1-hop (its covariance stopped being positive definite, or an estimate left what a "
        "message may carry): no metrics there"]
    doc = json.loads(out.read_text())
    assert doc["cdrkf"]["ring"]["diverged"] is True and "diverged" not in doc["kcf"]["ring"]


@pytest.mark.parametrize("name,what", [("cdrkf", "not positive definite"), ("diskf", "it diverged")])
def test_replay_of_a_diverging_estimator_is_one_line_and_writes_nothing(ca, tmp_path, capsys, name, what):
    scn, tr = ca
    trace = write(tmp_path / "t.json", trace_to_json(engine.take_seeds(tr, slice(0, 1))))
    out = tmp_path / "est.json"
    code, _, err = run_cli(["replay", trace, "--estimator", name, "--out", out], capsys)
    assert code == 1 and not out.exists()
    assert len(err.strip().splitlines()) == 1 and err.startswith(f"error: {name}, tick ") and what in err


def test_on_the_mesh_the_diverging_agents_stop_and_say_so(ca):
    scn, tr = ca
    r = simulate_run(scn, engine.take_seeds(tr, slice(0, 1)), "cdrkf", 0, run_id="ca", plan=SimPlan(Link(delay=0.002)))
    assert r.status.status == "incomplete", r.status.reason
    stopped = [f for f in r.outcome.finishes.values() if f.status == "diverged"]
    assert stopped and all(f.code == 3 and "diverged at tick" in f.reason for f in stopped)
    assert r.outcome.finishes["world"].status == "done"


def _toml(scn) -> str:
    """The scenario as a TOML file the command line loads."""
    rows = lambda a: "[" + ", ".join("[" + ", ".join(repr(float(v)) for v in r) + "]" for r in np.atleast_2d(a)) + "]"  # noqa: E731
    vec = lambda a: "[" + ", ".join(repr(float(v)) for v in a) + "]"  # noqa: E731
    lines = [f'name = "{scn.name}"', f"steps = {scn.steps}", "[model]", 'dynamics = "matrix"',
             f"A = {rows(scn.A)}", f"G = {rows(scn.G)}", f"Q = {rows(scn.Q)}", f"x0 = {vec(scn.x0)}",
             f"P0 = {rows(scn.P0)}", f"position_dims = {list(scn.position_dims)}", "[topology]", 'kind = "ring"']
    for a in scn.agents:
        lines += ["[[agents]]", f"id = {a.id}", f"H = {rows(a.H)}", f"R = {rows(a.R)}", 'sense = "always"',
                  "position = [0.0, 0.0]"]
    return "\n".join(lines) + "\n"
