"""The generated random geometric scenario: agent count override, lean
static links, and the --agents option of the CLI."""
from __future__ import annotations

import json

import numpy as np

from diskf_mesh.engine import batch as engine
from diskf_mesh.data.scenario import load_scenario, simulate

from cli_helpers import run_cli


def test_agents_override_and_heterogeneous_sensors():
    scn = load_scenario("random-geometric", agents=30)
    assert scn.N == 30 and scn.topology == "range"
    assert {a.H.shape[0] for a in scn.agents} == {1, 2}  # x or y sensors, and xy sensors
    assert load_scenario("random-geometric").N == 100


def test_static_range_links_are_one_matrix_broadcast_over_ticks():
    scn = load_scenario("random-geometric", agents=200).with_overrides(steps=50)
    trace = simulate(scn, [0])
    links = trace.links[0]
    assert links.strides[0] == 0  # no (K, N, N) copy for static agents
    pos = np.array([a.position for a in scn.agents])
    dist = np.linalg.norm(pos[:, None] - pos[None], axis=-1)
    np.testing.assert_array_equal(links[0], dist <= scn.comm_range)
    assert 1 < links[0].sum(axis=1).mean() < scn.N / 2  # range-gated, not all-to-all


def test_large_sparse_network_runs_in_the_gathered_layout():
    scn = load_scenario("random-geometric", agents=300).with_overrides(steps=5)
    trace = simulate(scn, [0])
    assert isinstance(engine.choose_links(trace.links[:, 0], 1), engine.GatheredLinks)
    est = engine.run(trace, "diskf", scn.params)
    assert est.x.shape == (1, 5, 300, 2) and np.isfinite(est.x).all()


def test_cli_agents_option(tmp_path, capsys):
    out = tmp_path / "r.json"
    code, text, _ = run_cli(["experiment", "--scenario", "random-geometric", "--agents", "40", "--topology", "range",
                             "--ticks", "10", "--seeds", "1", "--algorithms", "diskf", "--quiet", "--json", out], capsys)
    assert code == 0 and "40 agents" in text
    assert "diskf" in json.loads(out.read_text())
    code, _, err = run_cli(["experiment", "--agents", "40", "--seeds", "1", "--quiet"], capsys)
    assert code == 2 and "agents" in err
