"""The screen before fusion (``core.resilience``, ``Estimator.screened_fuse``):
its pieces on hand-made numbers, the same bits in every layout, a clean run
untouched, and the runs where it is what wins."""
from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from diskf_mesh.core import resilience as rs
from diskf_mesh.data import metrics
from diskf_mesh.data.lies import parse_text
from diskf_mesh.data.scenario import load_scenario, simulate
from diskf_mesh.engine import batch
from diskf_mesh.engine.verify import announced
from diskf_mesh.estimators import get
from diskf_mesh.mesh.simulated.simrun import simulate_run


def test_the_reference_is_the_median_of_three_or_more_and_ignores_the_unlinked():
    values = np.array([[0.0, 10.0], [1.0, 11.0], [500.0, -500.0], [2.0, 12.0]])  # (S, m)
    own = np.array([[9.0, 9.0], [8.0, 8.0]])                                      # (R, m)
    linked = np.array([[True, True, True, False], [True, False, True, False]])
    ref = rs.reference(linked, values, own)
    assert np.array_equal(ref[0], [1.0, 10.0])   # the median of three: the liar's far values do not move it
    assert np.array_equal(ref[1], own[1])       # two: its own
    # the same receiver in a layout of its linked senders alone: the same bits
    alone = rs.reference(np.ones((1, 3), dtype=bool), values[:3], own[:1])
    assert np.array_equal(alone[0], ref[0])


def test_gate_statistic_floor_and_evidence():
    q_own, q_ref = rs.gate_statistics(np.array([[3.0, 4.0]]), np.array([[[1.0, 0.0], [0.0, 1.0]]]),
                                      (np.zeros((1, 2)), np.array([[3.0, 4.0]])), np.array([[[1.0, 0.0], [0.0, 1.0]]]))
    assert q_own[0] == pytest.approx(12.5) and q_ref[0] == 0.0   # 25 / (1 + 1)
    Q = 0.2 * np.eye(2)
    assert rs.below_floor(np.array([0.19 * np.eye(2), 0.2 * np.eye(2), np.eye(2)]), Q).tolist() == [True, False, False]
    gate, allowance, limit, suspect = rs.thresholds()
    e = rs.accumulate(np.array([0.0, 50.0, 0.0]), np.array([allowance + 5, 0.0, 1.0]),
                      np.array([False, False, True]), allowance, suspect)
    assert e.tolist() == [5.0, 50.0 - allowance, suspect]
    assert (suspect - limit) / allowance == rs.RECOVERY  # ticks of honest messages to win a neighbour back


def test_evidence_follows_the_sender_not_its_slot():
    ev = np.array([[0.0, 1.0, 2.0, 3.0]])              # (R=1, N=4)
    cols = np.array([[3, 1]])                          # slots: agents 3 and 1
    assert rs.columns_of(ev, cols).tolist() == [[3.0, 1.0]]
    out = rs.put_columns(ev, cols, np.array([[30.0, 10.0]]), np.array([[True, False]]))
    assert out.tolist() == [[0.0, 1.0, 2.0, 30.0]]


@pytest.fixture(scope="module")
def dynamic():
    scn = load_scenario("dynamic")
    return scn, simulate(scn, [0, 1])


def _honest_mae(trace, est, scn, liar=None):
    keep = [j for j, a in enumerate(scn.agents) if a.id != liar]
    return metrics.compute(trace, est.agents(keep))["mae_state"]


def _on(scn):
    return dataclasses.replace(scn.params, defence=True)


def test_a_clean_run_is_the_undefended_run_bit_for_bit(dynamic):
    """No honest neighbour fails the screen on Scenario 2: with it, diskf-auto
    gives the undefended estimates exactly."""
    scn, trace = dynamic
    on = batch.run(trace, "diskf-auto", _on(scn))
    off = batch.run(trace, "diskf-auto", scn.params)
    assert get("diskf-auto")(trace.model, trace.sensors, _on(scn)).defends
    assert not get("diskf-auto")(trace.model, trace.sensors, scn.params).defends  # off by default
    assert np.array_equal(on.x, off.x) and np.array_equal(on.P, off.P)


@pytest.mark.parametrize("text, undefended, defended", [
    ("agent=3,kind=shrink,size=20,from=50", 50.0, 1.3),    # measured: diverges (tick 141, seeds 0-1) and 1.09x
    ("agent=3,kind=offset,size=5000,from=50", 50.0, 1.3),  # 134x and 1.06x
])
def test_the_screen_is_what_keeps_honest_agents_right(dynamic, text, undefended, defended):
    """Scenario 2, one insider: the honest agents' error against the clean
    run's, without the screen and with it. Without it the error grows
    beyond ``undefended`` times the clean run's, or the honest agents'
    covariances diverge (an unbounded error: the engine's ``Diverged``)."""
    scn, trace = dynamic
    lies = scn.with_lies([parse_text(text)]).lies
    clean = _honest_mae(trace, batch.run(trace, "diskf-auto", scn.params), scn, 3)
    try:
        off = _honest_mae(trace, batch.run(trace, "diskf-auto", dataclasses.replace(scn.params, defence=False),
                                           lies=lies), scn, 3)
    except batch.Diverged:
        off = math.inf
    on = batch.run(trace, "diskf-auto", _on(scn), lies=lies)
    assert off > undefended * clean
    assert _honest_mae(trace, on, scn, 3) < defended * clean


def test_an_agent_process_screens_as_the_engine_does(dynamic):
    """The agent's batch of one (its own senders, their places in the run)
    keeps the evidence per neighbour as the engine's dense layout does: the
    same estimates bit for bit with a liar that the screen cuts."""
    scn, trace = dynamic
    scn = scn.with_overrides(steps=80, params=_on(scn)).with_lies([parse_text("agent=3,kind=shrink,size=20,from=30")])
    one = batch.take_seeds(trace, slice(0, 1))
    one = dataclasses.replace(one, y=one.y[:, :80], has=one.has[:, :80], links=one.links[:, :80],
                              truth_x=one.truth_x[:, :80], truth_d=one.truth_d[:, :80])
    eng = batch.run(one, "diskf-auto", scn.params, lies=scn.lies)
    dense = batch.run(one, "diskf-auto", scn.params, neighbours="dense")  # no lie: the dense layout screens too
    gathered = batch.run(one, "diskf-auto", scn.params, neighbours="gather")
    assert np.array_equal(dense.x, gathered.x)
    honest = [j for j, a in enumerate(scn.agents) if a.id != 3]
    undefended = batch.run(one, "diskf-auto", dataclasses.replace(scn.params, defence=False), lies=scn.lies)
    assert not np.array_equal(eng.x[:, :, honest], undefended.x[:, :, honest])  # the screen acted
    r = simulate_run(scn, one, "diskf-auto", 0)
    # the world's online check cuts the liar off when an agent fuses it; the engine takes the same live sets
    run = batch.run(announced(one, r.record.live), "diskf-auto", scn.params, lies=scn.lies)
    reported = r.record.reported
    assert np.array_equal(r.record.x[reported], run.x[0][reported])
    assert np.array_equal(eng.x[0, :20], run.x[0, :20])


def test_a_tick_where_nothing_can_grow_is_decided_from_the_own_statistics():
    """The screen's short way: no evidence, no floor failure and every
    statistic against the receiver's own prediction within the allowance
    means nothing changes; any one of them outside, and the whole screen runs."""
    zero, no = np.zeros((1, 3)), np.zeros(2, dtype=bool)
    small = np.array([1.0, 9.0])
    assert rs.nothing_grows(zero, no, small, None, 9.0)
    assert rs.nothing_grows(zero, no, small, np.array([0.0, 2.0]), 9.0)
    assert not rs.nothing_grows(zero, no, np.array([1.0, 9.5]), None, 9.0)
    assert not rs.nothing_grows(zero, no, small, np.array([0.0, 9.5]), 9.0)
    assert not rs.nothing_grows(zero, np.array([False, True]), small, None, 9.0)
    assert not rs.nothing_grows(np.array([[0.0, 1e-3, 0.0]]), no, small, None, 9.0)


@pytest.mark.parametrize("name, agents, chosen, lie, ticks, gain", [
    ("dynamic", None, (3,), ("offset", 500.0), 70, 0.8),
    ("random-geometric", 25, 2, ("stale", 20.0), 56, None),
])
def test_the_studys_world_column_is_the_simulated_network_bit_for_bit(name, agents, chosen, lie, ticks, gain):
    """``studies.resilience.with_world`` (the engine on the live sets the
    world announces: a liar named at the first tick another agent receives
    its lie, cut off two ticks later) gives the run on the simulated network
    (``world_run``: the world's online check naming and quarantining it)
    bit for bit: the same quarantines, the same honest errors; on Scenario 2
    the honest errors are below ``gain`` times the screen's alone (a 500 m
    offset: agent 8 fuses it while both are uncertain)."""
    from diskf_mesh.data.lies import Lie
    from diskf_mesh.studies import resilience as study

    scn = load_scenario(name, agents=agents).with_overrides(steps=ticks)
    trace = simulate(scn, [0])
    liars = study.insiders(scn, trace, chosen)
    scn = scn.with_overrides(params=_on(scn)).with_lies([Lie(i, *lie, start=study.START) for i in liars])
    honest = [j for j, a in enumerate(scn.agents) if a.id not in liars]
    e_sim, cuts_sim, status = study.world_run(scn, 0, honest)
    e_eng, cuts_eng = study.with_world(scn, trace, scn.params, honest)
    assert status == "diverged" and len(cuts_sim) == len(liars)
    assert sorted(cuts_eng) == sorted(cuts_sim)
    assert np.array_equal(e_eng, e_sim)
    if gain is not None:
        screen_only = batch.run(trace, "diskf-auto", scn.params, lies=scn.lies)
        assert e_eng.mean() < gain * metrics.errors(trace, screen_only.agents(honest))[0].mean()


def test_inputs_both_sides_are_certain_of_are_gated_without_raising():
    eye, zero = np.eye(2), np.zeros((2, 2))
    d_send = np.array([[0.0, 0.0], [0.0, 1.0], [3.0, 0.0], [3.0, 0.5]])
    S_send = np.array([zero, zero, np.diag([0.0, 1.0]), eye])
    S_own = np.array([zero, zero, np.diag([0.0, 1.0]), zero])
    valid = np.array([True, True, True, False])
    q, = rs.input_gate_statistics(d_send, S_send, (np.zeros((4, 2)),), S_own, valid)
    assert q[0] == 0.0              # both certain of the same input
    assert q[1] == np.inf           # both certain, and they differ
    assert q[2] == np.inf           # they differ along the direction neither has variance in
    assert q[3] == 0.0              # not valid: no statistic
    q, = rs.input_gate_statistics(np.array([[0.0, 2.0]]), S_send[2:3], (np.zeros((1, 2)),), S_own[2:3], valid[:1])
    assert q[0] == pytest.approx(2.0)   # 4 / (1 + 1) along the direction with variance



def test_positive_definite_is_the_test_the_inverse_raises_on():
    """3 x 3 sums of rank 2 (an input of m = 3 certain in one direction),
    at the edge of positive definiteness: ``positive_definite`` says of each
    what ``inv_spd`` does (its smallest eigenvalue can come out positive
    where the Cholesky factor does not exist), so the input gate takes the
    certain-direction branch there instead of raising."""
    from diskf_mesh.core.linalg import inv_spd
    rng = np.random.default_rng(0)
    v = rng.normal(size=(200, 3, 2))
    M = v @ np.swapaxes(v, -1, -2) + rng.choice([0.0, 1e-17, 1e-16], size=(200, 1, 1)) * np.eye(3)
    factors = []
    for one in M:
        try:
            inv_spd(one[None])
            factors.append(True)
        except np.linalg.LinAlgError:
            factors.append(False)
    assert 0 < sum(factors) < len(factors)
    np.testing.assert_array_equal(rs.positive_definite(M), factors)
    zero = np.zeros((200, 3))
    q, = rs.input_gate_statistics(zero, 0.5 * M, (zero,), 0.5 * M, np.ones(200, dtype=bool))
    assert (q == 0.0).all()
