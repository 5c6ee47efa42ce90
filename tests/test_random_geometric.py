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


def test_range_links_formed_in_blocks_are_those_of_all_pairs_at_once(monkeypatch):
    from diskf_mesh.data import scenario

    rng = np.random.default_rng(3)
    lattice = np.stack(np.divmod(np.arange(150), 12), axis=-1) * 10.0  # pairs exactly at the range
    for pos in (rng.uniform(-300, 300, (150, 2)), lattice, rng.uniform(-50, 50, (3, 40, 2))):
        diff = pos[..., :, None, :] - pos[..., None, :, :]
        for r in (0.0, 10.0, 100.0, np.inf):
            every = np.einsum("...k,...k->...", diff, diff) <= r * r
            for pairs in (1, 7 * pos.shape[-2], 1 << 20):
                monkeypatch.setattr(scenario, "PAIRS_PER_BLOCK", pairs)
                np.testing.assert_array_equal(scenario.range_links(pos, r), every)


def test_receivers_fused_in_blocks_give_the_same_bits(monkeypatch):
    """A tick over the working-set bound fuses its receivers in blocks (one
    receiver, then seven at a time): every estimator's estimates equal
    those of one block, bit for bit, with lies and with the screen on."""
    from dataclasses import replace

    from diskf_mesh import estimators
    from diskf_mesh.data.lies import Lie

    scn = load_scenario("random-geometric", agents=60).with_overrides(steps=8)
    trace = simulate(scn, [0, 1])
    assert isinstance(engine.choose_links(trace.links[:, 0], 2), engine.GatheredLinks)
    D = int(trace.links[0, 0].sum(axis=-1).max())
    cases = [(name, scn.params, ()) for name in estimators.NAMES]
    cases += [("diskf-auto", replace(scn.params, defence=True), ()),
              ("diskf", scn.params, (Lie(agent=4, kind="offset", size=50.0),))]
    for name, params, lies in cases:
        whole = engine.run(trace, name, params, lies=lies)
        for rows in (1, 7):
            monkeypatch.setattr(engine, "slot_bytes", lambda n, msg: 1)
            monkeypatch.setattr(engine, "BLOCK_BYTES_MAX", rows * 2 * D)  # both seeds in each block
            blocks = engine.run(trace, name, params, lies=lies)
            monkeypatch.undo()
            for a, b in zip(whole.__dict__.values(), blocks.__dict__.values()):
                np.testing.assert_array_equal(a, b, err_msg=f"{name}, {rows} receivers a block")
