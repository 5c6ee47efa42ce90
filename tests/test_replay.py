"""simulate -> replay round trip: replaying a simulated trace file gives
exactly the engine's run on the same scenario and seed."""
from __future__ import annotations

import json

import numpy as np
import pytest

from cli_helpers import run_cli
from diskf_mesh import estimators as algorithms
from diskf_mesh.engine import batch as engine
from diskf_mesh.data import metrics, provenance
from diskf_mesh.estimators import Params
from diskf_mesh.data.scenario import load_scenario, simulate
from diskf_mesh.data.trace import load_trace, trace_from_json, trace_to_json

SEED, STEPS, TOPOLOGY = 7, 60, "ring"


@pytest.fixture(scope="module")
def reference():
    scn = load_scenario("quadrants").with_overrides(topology=TOPOLOGY, steps=STEPS)
    assert scn.params == Params(), "replay's defaults must be the scenario's estimator settings"
    return scn, simulate(scn, [SEED])


def simulate_file(path, capsys):
    code, _, err = run_cli(["simulate", "--topology", TOPOLOGY, "--ticks", STEPS, "--seed", SEED,
                            "--out", path], capsys)
    assert code == 0, err


def test_trace_file_round_trips_exactly(reference, tmp_path, capsys):
    scn, trace = reference
    path = tmp_path / "trace.json"
    simulate_file(path, capsys)
    assert json.loads(path.read_text()) == trace_to_json(trace, scenario=scn.name, params=scn.params)
    back = load_trace(path)
    for name in ("y", "has", "links", "truth_x", "truth_d"):
        np.testing.assert_array_equal(np.broadcast_to(getattr(back, name), getattr(trace, name).shape),
                                      getattr(trace, name), err_msg=name)
    assert back.seeds == (SEED,)


@pytest.mark.parametrize("name", algorithms.NAMES)
def test_replay_equals_engine(name, reference, tmp_path, capsys):
    scn, trace = reference
    path, out_path = tmp_path / "trace.json", tmp_path / "est.json"
    simulate_file(path, capsys)
    code, _, err = run_cli(["replay", path, "--algorithm", name, "--out", out_path], capsys)
    assert code == 0, err
    got = json.loads(out_path.read_text())
    want = engine.run(trace, name, scn.params)
    np.testing.assert_allclose(got["x"], want.x[0], rtol=0, atol=1e-9)
    np.testing.assert_allclose(got["P"], want.P[0], rtol=0, atol=1e-9)
    valid = np.array([[d is not None for d in tick] for tick in got["d"]])
    np.testing.assert_array_equal(valid, want.d_valid[0])
    d = np.array([[d if d is not None else [np.nan] * scn.G.shape[1] for d in tick] for tick in got["d"]])
    np.testing.assert_allclose(d[valid], want.d[0][valid], rtol=0, atol=1e-9)
    for key, value in metrics.compute(trace, want).items():
        assert got["metrics"][key] == pytest.approx(value, abs=1e-9, nan_ok=True) or \
            (got["metrics"][key] is None and not np.isfinite(value))


def general_doc(seed=0, n=3, m=2, K=30, ps=(1, 2, 3, 1, 2)) -> dict:
    """A trace unlike Scenario 1: time-varying A, m = 2 inputs, sensors of
    different sizes, an agent that never measures, links changing every tick,
    no truth."""
    rng = np.random.default_rng(seed)
    N = len(ps)
    links = rng.random((K, N, N)) < 0.4
    links = links | np.swapaxes(links, 1, 2) | np.eye(N, dtype=bool)
    return {
        "format": "diskf-trace/1",
        "A_seq": (np.eye(n) + 0.01 * rng.standard_normal((K, n, n))).tolist(),
        "G": rng.standard_normal((n, m)).tolist(), "Q": (0.1 * np.eye(n)).tolist(),
        "x0": [0.0] * n, "P0": np.eye(n).tolist(),
        "agents": [{"id": i + 1, "H": rng.standard_normal((p, n)).tolist(), "R": ((1 + i) * np.eye(p)).tolist()}
                   for i, p in enumerate(ps)],
        "y": [[rng.standard_normal(p).tolist() if i != N - 1 and rng.random() < 0.6 else None
               for i, p in enumerate(ps)] for _ in range(K)],
        "links": links.astype(int).tolist(),
    }


@pytest.mark.parametrize("name", algorithms.NAMES)
def test_replay_general_trace(name, tmp_path, capsys):
    doc = general_doc()
    path, out_path = tmp_path / "trace.json", tmp_path / "est.json"
    path.write_text(json.dumps(doc))
    code, _, err = run_cli(["replay", path, "--algorithm", name, "--out", out_path], capsys)
    assert code == 0, err
    got = json.loads(out_path.read_text())
    assert "metrics" not in got
    want = engine.run(trace_from_json(doc), name, Params())
    np.testing.assert_allclose(got["x"], want.x[0], rtol=0, atol=1e-9)
    assert [d is not None for d in got["d"][-1]] == want.d_valid[0, -1].tolist()


def test_a_real_time_run_is_judged_on_replay_as_the_run_judged_it(tmp_path, capsys):
    """A real-time run degraded by deadline misses within --max-miss-rate
    exits 0; so do ``replay RUN.mcap`` and ``replay TRACE --fused EST``."""
    rec, est, res, trace = (tmp_path / n for n in ("r.mcap", "e.json", "r.json", "t.json"))
    code, _, err = run_cli(["up", "--network", "simulated", "--algorithm", "diskf", "--ticks", 10, "--rate", 10,
                            "--net-delay-ms", 20,
                            "--net-jitter-ms", 40, "--max-miss-rate", 1, "--record", rec, "--estimates", est,
                            "--json", res, "--quiet"], capsys)
    row = next(iter(json.loads(res.read_text())["diskf"].values()))
    assert code == 0 and row["status"] == "degraded" and row["deadline_misses"]["miss_rate"] > 0, err
    assert run_cli(["simulate", "--scenario", "dynamic", "--ticks", 10, "--out", trace], capsys)[0] == 0
    assert run_cli(["replay", trace, "--fused", est], capsys)[0] == 0
    code, _, err = run_cli(["replay", rec, "--out", tmp_path / "again.json"], capsys)
    assert code == 0, err
    assert provenance.split(json.loads((tmp_path / "again.json").read_text()))[0]["status"] == "degraded"
