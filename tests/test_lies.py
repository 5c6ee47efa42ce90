"""Lies as planned faults (``data.lies``): parsed from a scenario's
[[faults.lies]] and from --lie, applied on the sending side, and the same
bits in the engine, on the simulated network and in real processes."""
from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from diskf_mesh.core.errors import InputError
from diskf_mesh.core.messages import Message
from diskf_mesh.data.lies import Liars, Lie, parse_text
from diskf_mesh.data.scenario import load_scenario, parse_scenario, simulate
from diskf_mesh.engine import batch
from diskf_mesh.engine.verify import announced
from diskf_mesh.mesh.process.runspec import RunSpec
from diskf_mesh.mesh.simulated.simrun import simulate_run

K = 40


@pytest.fixture(scope="module")
def dynamic():
    scn = load_scenario("dynamic").with_overrides(steps=K)
    return scn, simulate(scn, [0])


def _message(x, P, d=0.0):
    n = len(x)
    return Message(np.array([[x]], float), np.array([[P]], float), np.array([[x]], float), np.array([[P]], float),
                   np.array([[[d]]]), np.array([[[[1.0]]]]), np.array([[False]]))


def test_each_kind_changes_what_it_says_and_only_while_it_lies():
    P = np.eye(2)
    true = [_message([1.0 * k, 0.0], P) for k in range(1, 8)]
    liars = {kind: Liars([Lie(5, kind, size, start=3, until=6, on=2, off=1)], (5,), 2)
             for kind, size in (("offset", 10.0), ("drift", 2.0), ("shrink", 20.0), ("stale", 2.0), ("input", 7.0))}
    sent = {kind: [liar.message(k, m) for k, m in enumerate(true, start=1)] for kind, liar in liars.items()}
    lying = [3, 4, 6]  # from 3, on 2 off 1, until 6
    step = np.array([1.0, 1.0]) / np.sqrt(2)
    for kind, msgs in sent.items():
        for k, (m, t) in enumerate(zip(msgs, true), start=1):
            if k not in lying:
                assert m is t or all(np.array_equal(getattr(m, f), getattr(t, f)) for f in Message.ARRAY_FIELDS)
    o = sent["offset"][3 - 1]
    assert np.allclose(o.x_pred[0, 0] - true[2].x_pred[0, 0], 10 * step)
    assert np.allclose(sent["drift"][6 - 1].x_upd[0, 0] - true[5].x_upd[0, 0], 2 * 4 * step)  # 4 ticks since 3
    s = sent["shrink"][4 - 1]
    assert np.allclose(s.P_pred[0, 0], 1e-3 * P) and np.allclose(s.x_pred[0, 0] - true[3].x_pred[0, 0], 20 * step)
    assert np.array_equal(sent["stale"][6 - 1].x_pred, true[6 - 1 - 2].x_pred)  # tick 4's at tick 6
    i = sent["input"][3 - 1]
    assert i.d[0, 0, 0] == 7.0 and bool(i.d_valid[0, 0])


def test_a_lie_from_the_scenario_file_and_from_the_command_line_agree():
    text = "agent=3,kind=drift,size=0.5,from=20,until=60,on=5,off=2,reports=lying"
    lie = parse_text(text)
    assert lie == Lie(3, "drift", 0.5, start=20, until=60, on=5, off=2, reports="lying")
    assert parse_text(lie.to_text()) == lie
    raw = {"steps": 10, "model": {"dynamics": "rotation", "omega": 0.1, "G": [[1.0], [1.0]], "Q": [[0.2, 0], [0, 0.2]],
                                  "x0": [1.0, 0.0], "P0": [[1.0, 0], [0, 1.0]]},
           "agents": [{"id": "a", "H": [[1.0, 0.0]], "R": [[2.0]]}, {"id": "b", "H": [[0.0, 1.0]], "R": [[2.0]]}],
           "faults": {"loss": 0.1, "lies": [{"agent": "b", "kind": "offset", "size": 50, "from": 4}]}}
    scn = parse_scenario(raw)
    assert scn.faults == {"loss": 0.1}
    assert scn.lies == (Lie(scn.agents[1].id, "offset", 50.0, start=4),)


@pytest.mark.parametrize("table, field", [
    ({"agent": 1, "kind": "lie", "size": 1.0}, "kind"),
    ({"agent": 1, "kind": "stale", "size": 0.5}, "size"),
    ({"agent": 1, "kind": "offset", "size": float("inf")}, "size"),
    ({"agent": 1, "kind": "offset", "size": 1.0, "from": 0}, "from"),
    ({"agent": 1, "kind": "offset", "size": 1.0, "from": 5, "until": 4}, "until"),
    ({"agent": 1, "kind": "offset", "size": 1.0, "reports": "maybe"}, "reports"),
    ({"agent": 1, "kind": "shrink", "size": 1.0, "scale": 0}, "scale"),
    ({"agent": 1, "kind": "offset", "size": 1.0, "when": 3}, "when"),
    ({"kind": "offset", "size": 1.0}, "agent"),
])
def test_a_bad_lie_is_one_error_naming_its_field(table, field):
    with pytest.raises(InputError) as e:
        Lie.from_mapping(table, "faults.lies[0]")
    assert e.value.field == f"faults.lies[0].{field}"


def test_a_lie_of_an_agent_not_in_the_scenario_is_refused(dynamic):
    scn, _ = dynamic
    with pytest.raises(InputError, match="no agent 12"):
        scn.with_lies([parse_text("agent=12,kind=offset,size=5")])


@pytest.mark.parametrize("text", [
    "agent=3,kind=offset,size=200,from=12",
    "agent=3,kind=drift,size=2,from=5,on=6,off=3,reports=lying",
    "agent=5,kind=shrink,size=20,from=8,until=30,reports=lying",
    "agent=3,kind=stale,size=7,from=10,reports=lying",
    "agent=7,kind=input,size=50,from=15",
])
def test_the_engine_and_the_simulated_network_send_the_same_lies(dynamic, text):
    """The liar's messages (and with reports = lying its reports) are the
    same bits in the engine and on the simulated network with the real
    machines; every honest estimate follows."""
    scn, trace = dynamic
    scn = scn.with_lies([parse_text(text)])
    honest = batch.run(trace, "diskf-auto", scn.params)
    r = simulate_run(scn, trace, "diskf-auto", 0)
    # the world cuts the liar off as the run goes (the ticks' live sets): the engine applies the same ticks
    rec = r.record
    assert [q["agent"] for q in rec.quarantined] == [scn.lies[0].agent]
    eng = batch.run(announced(trace, rec.live), "diskf-auto", scn.params, lies=scn.lies)
    rep = rec.reported
    assert np.array_equal(rec.x[rep], eng.x[0][rep]) and np.array_equal(rec.P[rep], eng.P[0][rep])
    assert np.array_equal(rec.d[rep], eng.d[0][rep])
    assert not np.array_equal(eng.x, honest.x)  # the lie reached someone
    assert r.status.status == "diverged"  # the end-of-run check does not reproduce the liar's messages


def test_a_liar_fuses_its_own_true_message(dynamic):
    """With honest reports the liar's own estimates are what it computes
    from its true message; with lying reports they carry the lie."""
    scn, trace = dynamic
    lie = parse_text("agent=3,kind=offset,size=500,from=30")
    honest = batch.run(trace, "diskf-auto", scn.params, lies=scn.with_lies([lie]).lies)
    lying = batch.run(trace, "diskf-auto", scn.params, lies=scn.with_lies([parse_text(lie.to_text()
                                                                                     + ",reports=lying")]).lies)
    col = [a.id for a in scn.agents].index(3)
    assert np.array_equal(np.delete(honest.x, col, axis=2), np.delete(lying.x, col, axis=2))
    shift = lying.x[0, 29:, col] - honest.x[0, 29:, col]
    assert np.allclose(shift, 500 / np.sqrt(2))


def test_experiment_takes_a_lie_and_scores_the_honest_agents(tmp_path):
    out = tmp_path / "r.json"
    run = lambda *a: subprocess.run([sys.executable, "-m", "diskf_mesh.cli.main", "experiment", "--scenario",  # noqa
                                     "dynamic", "--ticks", "60", "--seeds", "1", "--estimators", "diskf-auto",
                                     "--quiet", *a], capture_output=True, text=True, timeout=300)
    lie = ("--lie", "agent=3,kind=offset,size=5000,from=20", "--defence", "off")  # undefended: the lie shows
    clean, lied = run("--json", str(out)), run(*lie, "--json", str(tmp_path / "l.json"))
    assert clean.returncode == lied.returncode == 0, lied.stderr
    mae = lambda p: next(iter(json.loads(p.read_text())["diskf-auto"].values()))["mae_state"]  # noqa: E731
    assert mae(tmp_path / "l.json") > 2 * mae(out)
    bad = run("--lie", "agent=3,kind=offset")
    assert bad.returncode == 2 and bad.stderr.count("\n") == 1 and "size" in bad.stderr


@pytest.mark.mesh
def test_up_sends_the_lies_the_engine_sends(tmp_path):
    """Real processes (``up``): the run's estimates are the engine's for the
    same lie plan, bit for bit, and the lie reaches the children from the
    command line."""
    lie = "agent=3,kind=drift,size=2,from=5,reports=lying"
    est = tmp_path / "e.json"
    done = subprocess.run([sys.executable, "-m", "sim.launcher", "--scenario", "dynamic", "--ticks", "20", "--lie", lie,
                           "--estimates", str(est), "--logs", str(tmp_path / "logs"), "--quiet"],
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 6, done.stderr  # diverged: the check does not reproduce agent 3's messages
    scn = RunSpec("dynamic", lies=(parse_text(lie),)).load(20)
    doc = json.loads(est.read_text())
    live, rep = np.array(doc["live"], dtype=bool), np.array(doc["reported"], dtype=bool)
    assert not live[-1, 2]  # the world cut agent 3 off as the run went; the engine applies the same ticks
    eng = batch.run(announced(simulate(scn, [0]), live), "diskf-auto", scn.params, lies=scn.lies)
    assert np.array_equal(np.array(doc["x"], dtype=float)[rep], eng.x[0][rep])
