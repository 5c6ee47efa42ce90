"""diskf-auto: the batched engine == a plain per-agent loop (``auto_oracle``),
every agent alone (as in an agent process) == the engine bit for bit, and
its settings; the no-divergence cases of every estimator, and the settings
an estimator refuses before a run."""
from __future__ import annotations

import sys
from dataclasses import replace
from types import SimpleNamespace
from pathlib import Path

import numpy as np
import pytest

from diskf_mesh.core import input_models as im
from diskf_mesh.core.errors import InputError
from diskf_mesh.core.model import AutoOptions, RobustOptions
from diskf_mesh.data import metrics
from diskf_mesh.data.scenario import load_scenario, parse_scenario, simulate
from diskf_mesh.data.trace import load_trace
from diskf_mesh.engine import batch as engine
from diskf_mesh.estimators import NAMES
from diskf_mesh.estimators.diskf_auto import DISKFAuto
from diskf_mesh.mesh.protocol.estimator import lockstep
from diskf_mesh.studies import heldout
from diskf_mesh.mesh.simulated.simrun import simulate_run

sys.path.insert(0, str(Path(__file__).parent))
import auto_oracle  # noqa: E402


def assert_matches_oracle(scn, seeds, tol):
    """Each estimate to ``tol`` on its own scale: x against its standard
    deviation (the largest of P's diagonal), P against its largest entry,
    d against the run's largest input estimate. An entry-by-entry tolerance
    would judge the round-off of an entry 10^9 smaller than its matrix."""
    assert_trace_matches_oracle(scn, simulate(scn, seeds), tol)


def assert_trace_matches_oracle(scn, tr, tol):
    """``assert_matches_oracle`` on a given trace of ``scn``."""
    want = auto_oracle.run_auto(tr, scn.params.auto)
    est = engine.run(tr, "diskf-auto", scn.params)
    np.testing.assert_array_equal(est.d_valid, want["v"])
    sd = np.sqrt(np.diagonal(want["P"], axis1=-2, axis2=-1).max(axis=-1))
    assert (np.abs(est.x - want["x"]).max(axis=-1) / sd).max() < tol
    assert (np.abs(est.P - want["P"]).max(axis=(-2, -1)) / np.abs(want["P"]).max(axis=(-2, -1))).max() < tol
    assert np.abs(est.d - want["d"]).max() < tol * np.abs(want["d"]).max()


@pytest.mark.parametrize("name,topology,variant,tol", [
    ("quadrants", "ring", "R", 1e-9), ("dynamic", None, "R", 1e-7), ("quadrants", "all", "mixed", 1e-9)])
def test_auto_matches_oracle(name, topology, variant, tol):
    """To 1e-9 where the bank's wide input prior is well conditioned against
    the sensors (R x 0.1; mixed sensors of which one sees both axes). In
    Scenario 2 the round-off of the two orders of summation grows where the
    models' probabilities swing (ticks 12 to 15 of seed 1: 2.4e-8 of the
    state's standard deviation, back under 1e-9 by tick 20)."""
    scn = load_scenario(name).with_overrides(topology=topology, steps=40)
    scn = heldout.scaled_R(scn, 0.1) if variant == "R" else heldout.mixed_sensors(scn)
    assert_matches_oracle(scn, [0, 1], tol)


def test_auto_matches_oracle_learning_the_noise():
    """With [estimator.auto] noise = true, in a world whose measurement noise
    is 10 times what the sensors are told: the oracle learns each agent's
    scale in gain form on the sensor's own rows."""
    scn = heldout.scaled_R(load_scenario("quadrants").with_overrides(topology="ring", steps=40), 0.1)
    scn = scn.with_overrides(params=scn.params.with_setting("auto", noise=True))
    _, tr = heldout.Case("x", "x", scn, heldout.World(R=10.0)).simulate([0, 1])
    want = auto_oracle.run_auto(tr, scn.params.auto)
    est = engine.run(tr, "diskf-auto", scn.params)
    sd = np.sqrt(np.diagonal(want["P"], axis1=-2, axis2=-1).max(axis=-1))
    assert (np.abs(est.x - want["x"]).max(axis=-1) / sd).max() < 1e-9
    assert (np.abs(est.P - want["P"]).max(axis=(-2, -1)) / np.abs(want["P"]).max(axis=(-2, -1))).max() < 1e-9


def test_auto_matches_oracle_isolated_shipped():
    """Isolated agents of Scenario 1: long unobserved stretches under the
    wide prior, where the information form and the gain form agree to a few
    parts in 1e8 (measured at worst: x 9e-9, P 2.5e-8, d 1.7e-8)."""
    scn = load_scenario("quadrants").with_overrides(topology="none", steps=60)
    assert_matches_oracle(scn, [0], 1e-7)


@pytest.mark.parametrize("neighbours,auto", [("dense", {}), ("gather", {}), ("dense", {"noise": True}),
                                             ("gather", {"noise": True}), ("dense", {"noise_level": 10.0}),
                                             ("gather", {"evidence_dof": 4.0}),
                                             ("gather", {"noise_level": 10.0, "evidence_dof": 4.0}),
                                             ("dense", {"noise_span": 10.0}), ("gather", {"noise_span": 10.0})],
                         ids=["dense", "gather", "dense, noise", "gather, noise", "dense, noise_level",
                              "gather, evidence_dof", "gather, noise_level and evidence_dof", "dense, noise_span",
                              "gather, noise_span"])
def test_auto_agents_alone_equal_engine(neighbours, auto):
    """Every agent a batch of one (as in an agent process): the engine's
    bits; with ``noise_level`` too (the own measurement at each level is
    read from each agent's own message, not across the batch)."""
    scn = load_scenario("dynamic").with_overrides(steps=40)
    scn = scn.with_overrides(params=scn.params.with_setting("auto", **auto))
    tr = simulate(scn, [0])
    ref = engine.run(tr, "diskf-auto", scn.params, neighbours=neighbours)
    for k, _, outs in lockstep(scn, "diskf-auto", tr):
        for j, a in enumerate(scn.agents):
            assert np.array_equal(outs[a.id].x[0, 0], ref.x[0, k - 1, j])
            assert np.array_equal(outs[a.id].P[0, 0], ref.P[0, k - 1, j])
            assert np.array_equal(outs[a.id].d[0, 0], ref.d[0, k - 1, j])


def test_auto_settings_from_a_scenario():
    raw = {"model": {"G": [[1.0], [1.0]], "Q": [[0.2, 0], [0, 0.2]], "x0": [0, 0], "P0": [[1, 0], [0, 1]],
                     "A": [[1, 0], [0, 1]]},
           "agents": [{"H": [[1.0, 0.0]], "R": [[2.0]]}], "estimator": {"auto": {"switch": 0.02, "none": False}}}
    assert parse_scenario(raw).params.auto == AutoOptions(switch=0.02, none=False)
    raw["estimator"]["auto"] = {"hand_down": 0}
    assert parse_scenario(raw).params.auto == AutoOptions(hand_down=0.0)
    raw["estimator"]["auto"] = {"per_channel": False}
    assert parse_scenario(raw).params.auto == AutoOptions(per_channel=False)
    for bad, field in (({"switch": 0.0}, "estimator.auto.switch"), ({"switch": 1}, "estimator.auto.switch"),
                       ({"none": False, "walk": False, "zero_mean": False, "oscillating": False},
                        "estimator.auto"),
                       ({"walk": 1}, "estimator.auto.walk"), ({"hand_down": 1.0}, "estimator.auto.hand_down"),
                       ({"hand_down": -0.1}, "estimator.auto.hand_down"),
                       ({"per_channel": "yes"}, "estimator.auto.per_channel")):
        raw["estimator"]["auto"] = bad
        with pytest.raises(InputError) as e:
            parse_scenario(raw)
        assert e.value.field == field


def test_auto_bank_choice_changes_the_estimate():
    scn = load_scenario("quadrants").with_overrides(topology="ring", steps=30)
    tr = simulate(scn, [0])
    a = engine.run(tr, "diskf-auto", scn.params)
    b = engine.run(tr, "diskf-auto", replace(scn.params, auto=AutoOptions(zero_mean=False)))
    assert not np.array_equal(a.x, b.x)


# --------------------------------------------------------------------------
# no divergence, and the settings that cannot work
# --------------------------------------------------------------------------
HARD = ["CV none, steps 0.1", "CV ring, white 0.05", "S1 none, sine fast", "S2 range 120, telegraph 3",
        "3-D none, step", "R×100 none, zero", "ω=0.6 none, sine fast"]


@pytest.mark.parametrize("label", HARD)
def test_no_estimator_diverges(label):
    """Every estimator's covariance stays finite and positive definite at
    every tick (a Cholesky factorisation exists), on cases where an
    unbiased input estimate has an invariant zero on or outside the unit
    circle, inputs switch faster than one agent can see, or sensors are
    poor."""
    case, = [c for c in heldout.cases() if c.label == label]
    scn = case.scenario.with_overrides(steps=100)
    tr = simulate(scn, [0, 1])
    for params in (scn.params, replace(scn.params, robust=RobustOptions(unbiased=True))):
        for name in NAMES:
            if params is not scn.params and name != "diskf-r":
                continue
            est = engine.run(tr, name, params)
            assert np.isfinite(est.x).all() and np.isfinite(est.P).all(), name
            np.linalg.cholesky(est.P)  # raises where not positive definite


def test_round_off_on_an_axis_nobody_measures_does_not_stop_the_run():
    """Isolated constant-acceleration agents measuring x alone, a slow
    ramp on both input channels, the trace of seed 38 that stopped (saved:
    its truth's round-off decides): by tick 34 a bank
    filter's variance on the unmeasured axes passes 10^9, and the
    information its agent published carries round-off of -2e-5 there. The
    joint update lost its Cholesky factor and the run stopped as diverged;
    with the cut to the nearest positive-semidefinite information
    (``equations.information_pair_psd``) it runs, finite and positive
    definite, and every agent alone (as in an agent process) computes the
    engine's bits."""
    case, = [c for c in heldout.cases() if c.label == "CA none, steps 0.01"]
    tr = load_trace(Path(__file__).parent / "data" / "ca_round_off.json")  # ticks 1-40 of that truth
    est = engine.run(tr, "diskf-auto", case.scenario.params)
    assert np.isfinite(est.x).all() and np.isfinite(est.P).all()
    np.linalg.cholesky(est.P)
    for k, _, outs in lockstep(case.scenario, "diskf-auto", tr):
        for j, a in enumerate(case.scenario.agents):
            assert np.array_equal(outs[a.id].x[0, 0], est.x[0, k - 1, j])
            assert np.array_equal(outs[a.id].P[0, 0], est.P[0, k - 1, j])


def test_model_mixing_stays_finite_where_a_state_is_unseen():
    """One agent measuring only a velocity, beside the position it drives
    and a third state no other state drives, all pushed by a 2-D constant
    input: two directions are never measured. The bank's models disagree
    there and nothing corrects them; with the spread between their
    estimates entering every model's prior in full it doubled about every
    tick (state MAE 3e20, then no Cholesky factor). With the spread bounded
    by the models' own covariances (``input_models.mix(bounded=True)``)
    diskf-auto stays finite, positive definite, and within twice diskf-r's
    state error."""
    raw = {"name": "velocity-only", "steps": 100,
           "model": {"dynamics": "matrix", "A": [[1.0, 1.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
                     "G": [[0.9, 0.4], [1.5, 0.7], [2.1, -1.3]], "Q": (0.002 * np.eye(3)).tolist(),
                     "x0": [0.0, 1.0, 0.0], "P0": np.eye(3).tolist(), "position_dims": [0, 1]},
           "topology": {"kind": "none"}, "input": {"kind": "constant", "value": [1.4, 1.4]},
           "agents": [{"id": 1, "H": [[0.0, 1.0, 0.0]], "R": [[0.001]], "sense": "always", "position": [0.0, 0.0]}]}
    scn = parse_scenario(raw)
    tr = simulate(scn, [0, 1])
    auto = engine.run(tr, "diskf-auto", scn.params)
    assert np.isfinite(auto.x).all() and np.isfinite(auto.P).all()
    np.linalg.cholesky(auto.P)
    mae = {name: np.nanmean(metrics.errors(tr, est)[0])
           for name, est in (("diskf-auto", auto), ("diskf-r", engine.run(tr, "diskf-r", scn.params)))}
    assert mae["diskf-auto"] < 2 * mae["diskf-r"], mae


def _cv_raw(**robust):
    cv = heldout.constant_velocity("none")
    agent = {"H": [[1.0, 0.0, 0.0, 0.0]], "R": [[1.0]], "sense": "always"}
    return {"model": {"dynamics": "matrix", "A": cv.A.tolist(), "G": cv.G.tolist(), "Q": cv.Q.tolist(),
                      "x0": cv.x0.tolist(), "P0": cv.P0.tolist(), "position_dims": [0, 2]},
            "agents": [agent], "estimator": {"robust": robust}}


def test_unbiased_refused_where_it_can_never_run():
    """A position sensor of a 2-D acceleration input: rank(H G) = 1 < m = 2
    for every neighbourhood, so unbiased = true cannot work: refused when
    the scenario is read, naming the setting."""
    with pytest.raises(InputError) as e:
        parse_scenario(_cv_raw(unbiased=True))
    assert e.value.field == "estimator.robust.unbiased"
    with pytest.raises(InputError) as e:
        parse_scenario(_cv_raw(unbiased=True, input_model="none"))
    assert e.value.field == "estimator.robust.unbiased"
    parse_scenario(_cv_raw(unbiased=False))  # the same scenario without it loads


def test_engine_refuses_before_the_run():
    scn = parse_scenario(_cv_raw())
    tr = simulate(scn, [0], 5)
    with pytest.raises(InputError) as e:
        engine.run(tr, "diskf-r", replace(scn.params, robust=RobustOptions(unbiased=True)))
    assert e.value.field == "estimator.robust.unbiased"


def test_model_evidence_reaches_an_agent_whose_neighbourhood_never_measures():
    """Scenario 1 in a ring of four, the step, only agent 1 measures: agent
    3 (not linked to agent 1, nor is anyone it hears measuring) weighs the
    input models as agent 1 does, through its neighbours' pooled
    probabilities; without them its weights would stay where they began
    (``initial_probabilities``: no measurement in its neighbourhood, no
    evidence). Agent 1, whose neighbourhood measures every tick, keeps its
    own probabilities: at tick 150 two oscillating models hold 0.27 and
    0.24 and "walk lo" 0.15, and so does agent 3."""
    from diskf_mesh import estimators as algorithms
    scn = load_scenario("quadrants").with_overrides(topology="ring", steps=150)
    tr = simulate(scn, [0])
    assert not tr.links[0, :, 0, 2].any()  # agent 3 (index 2) never hears agent 1 (index 0)
    tr.has[0, :, 1:] = False
    est = algorithms.get("diskf-auto")(tr.model, tr.sensors, scn.params)
    state = est.init((1, 4))
    for k in range(1, 151):
        state, msg = est.local(state, k, tr.y[:, k - 1], tr.has[:, k - 1])
        state, _ = engine.DenseLinks(tr.links[:, k - 1], 1).fuse(est, state, msg, None)
    mu = state.mu[0]
    assert np.abs(mu[2] - est.mu0).max() > 0.2  # evidence reached agent 3
    np.testing.assert_allclose(mu[2], mu[0], atol=0.02)  # agent 1's


def test_a_silent_neighbourhood_is_neither_updated_nor_weighed(monkeypatch):
    """Scenario 2 at range 120: on a tick where some agents' neighbourhoods
    measured nothing (most of the ticks there), step 4 leaves those agents'
    model predictions as they are, bit for bit, and gives them no evidence
    (log-likelihood 0); the agents whose neighbourhood measured get the same
    bits as when every agent of the batch is updated."""
    from diskf_mesh.estimators import diskf_auto
    seen = []
    measure = diskf_auto.measure

    def keep(*args, **kw):
        if not args[-1].all() and args[-1].any() and not seen:
            seen.append(args)
        return measure(*args, **kw)

    monkeypatch.setattr(diskf_auto, "measure", keep)
    scn = load_scenario("dynamic").with_overrides(comm_range=120, steps=30)
    engine.run(simulate(scn, [0]), "diskf-auto", scn.params)
    x_s, P_s, e1, C_s, S1, U, u, informed = seen[0]
    got = measure(x_s, P_s, e1, C_s, S1, U, u, informed)
    every = measure(x_s, P_s, e1, C_s, S1, U, u, np.ones_like(informed))
    for g, prior, whole in zip(got, (x_s, P_s, e1, C_s, S1, np.zeros(x_s.shape[:-1])), every):
        np.testing.assert_array_equal(g[~informed], prior[~informed])
        np.testing.assert_array_equal(g[informed], whole[informed])
    assert informed.any() and not informed.all()


def test_a_measuring_neighbourhood_keeps_its_own_model_probabilities():
    """The constant-acceleration model in a ring of six, no input, seeds 2
    and 3, 100 ticks: where every agent measures, the senders' pooled
    probabilities would lift an input model one neighbour's noise favoured
    to a share a few ticks of this agent's noise confirm. With each
    measuring neighbourhood keeping its own, diskf-auto's state MAE is
    1.21 x diskf-none's (measured; 1.42 x with the pool on every tick)."""
    case = next(c for c in heldout.grown_cases() if c.label == "CA ring, zero")
    scn, tr = case.simulate([2, 3], 100)
    mae = {name: metrics.errors(tr, engine.run(tr, name, scn.params))[0].mean() for name in ("diskf-auto", "diskf-none")}
    assert mae["diskf-auto"] < 1.3 * mae["diskf-none"], mae


def test_oscillating_models_follow_a_sine_between_their_periods():
    """A sine of period 13 ticks (between the bank's 11.3 and 13.5) on
    Scenario 2 at range 120, seeds 0..3: diskf-auto's state MAE is below half
    of every other estimator's and of its own without the oscillating models
    (measured: 9.74 against 23.3 for the paper's DISKF, 23.6 for DiffKF, 33.2
    without them)."""
    scn = heldout._topo(heldout._with_input(load_scenario("dynamic"), dict(kind="sine", amplitude=10.0, period=13.0)),
                        "range", 120.0)
    tr = simulate(scn, [0, 1, 2, 3])

    def mae(name, params):
        e_state, e_in, nees = metrics.errors(tr, engine.run(tr, name, params))
        return metrics.summarize(e_state, e_in, nees)["mae_state"]

    auto = mae("diskf-auto", scn.params)
    others = {name: mae(name, scn.params) for name in NAMES if name != "diskf-auto"}
    others["diskf-auto without oscillating"] = mae(
        "diskf-auto", scn.params.with_setting("auto", oscillating=False))
    assert all(auto < 0.5 * v for v in others.values()), (auto, others)


def test_the_chi_square_medians_are_scipy_stats_bit_for_bit():
    """diskf-auto's m_p of (NL1) without importing scipy (0.6 s at every
    command's start): the same numbers as ``scipy.stats.chi2.median``, from
    the table and beyond it."""
    import scipy.stats

    from diskf_mesh.estimators.diskf_auto import chi2_median

    for p in (np.array([1, 2, 3, 2, 1, 5, 7, 12, 16]), np.array([2, 33, 64]), np.arange(1, 200)):
        np.testing.assert_array_equal(chi2_median(p), scipy.stats.chi2.median(p))


def test_the_output_leaves_out_the_models_under_the_prune():
    """The constant-acceleration model all-to-all with no input, seeds 0..3,
    100 ticks: the model without input holds all but 10^-3 of the
    probability, and diskf-auto's mean NEES is diskf-none's within 5 %
    (measured: 6.15 against 6.26). With the zero-mean models of 10^-5
    left in the output mixture their covariance, a hundred times the
    others', widens the output where the measurements pin the state down
    least (the acceleration): NEES 4.87, 22 % under."""
    case = next(c for c in heldout.grown_cases() if c.label == "CA all, zero")
    scn, tr = case.simulate([0, 1, 2, 3], 100)
    seen = heldout.observed(tr)
    nees = {name: metrics.errors(tr, engine.run(tr, name, scn.params))[2][seen].mean()
            for name in ("diskf-auto", "diskf-none")}
    assert abs(nees["diskf-auto"] / nees["diskf-none"] - 1) < 0.05, nees


def test_no_message_claims_an_input_known_exactly():
    """The constant-velocity model in a ring with no input: from tick 8 the
    zero-input model alone holds the output's probability. Its input
    covariance is 0, which the receivers' guard rejects (not positive
    definite): the input's output mixture keeps every model, and the
    simulated run fuses every link and equals the engine."""
    case = next(c for c in heldout.cases() if c.label == "CV ring, zero")
    scn, tr = case.simulate([0], 20)
    run = simulate_run(scn, tr, "diskf-auto", 0)
    assert run.status.status == "exact", run.status.reason


def test_a_walk_that_learned_a_step_hands_its_level_to_the_smaller_walks():
    """Scenario 1, isolated agents, the step, seeds 0..3 (200 ticks): with
    the walks handing down (``AutoOptions.hand_down``) the state MAE is
    under 0.8 of the bank's without it, and under diskf-r's (measured:
    26.9, against 37.6 without and diskf-r's 32.4). Without it "walk lo"
    learns the step's level alone, slowly, and the bank holds the larger
    walks' noisier estimates and a zero-mean model for a hundred ticks."""
    case = next(c for c in heldout.cases() if c.label == "S1 none, step")
    scn, tr = case.simulate([0, 1, 2, 3], None)
    mae = {hd: float(np.mean(metrics.errors(tr, engine.run(tr, "diskf-auto", replace(
        scn.params, auto=AutoOptions(hand_down=hd))))[0])) for hd in (AutoOptions().hand_down, 0.0)}
    walk_r = float(np.mean(metrics.errors(tr, engine.run(tr, "diskf-r", scn.params))[0]))
    assert AutoOptions().hand_down > 0
    assert mae[AutoOptions().hand_down] < 0.8 * mae[0.0], mae
    assert mae[AutoOptions().hand_down] < walk_r, (mae, walk_r)


def test_each_input_channel_has_its_own_models():
    """Two input channels of different kinds (G = I, a step on one, the
    fast sine on the other), all-to-all, seeds 0..3: with a bank per
    channel (``AutoOptions.per_channel``) the state MAE is under a third
    of the one shared bank's, and the input MAE under half (measured: 5.97
    against 26.9, and 2.51 against 8.11; diskf-r 31.5). One bank must give
    both channels one model: the walk the step wants cannot follow the
    sine, and an oscillating model cannot hold the step."""
    case = next(c for c in heldout.selected(None) if c.label == "m=2 all, step | sine fast")
    scn, tr = case.simulate([0, 1, 2, 3], None)
    err = {pc: metrics.errors(tr, engine.run(tr, "diskf-auto", replace(scn.params, auto=AutoOptions(per_channel=pc))))
           for pc in (True, False)}
    assert AutoOptions().per_channel
    assert np.mean(err[True][0]) < np.mean(err[False][0]) / 3, err
    assert np.nanmean(err[True][1]) < np.nanmean(err[False][1]) / 2, err


def test_banks_per_channel_run_exact_on_the_simulated_network():
    """Two input channels in a ring, 30 ticks: the agents' banks per
    channel, each agent sending the banks' mean probabilities (a vector
    that sums to 1, as every receiver's guard checks), give on the
    simulated network what the engine computes, bit for bit."""
    case = next(c for c in heldout.selected(None) if c.label == "m=2 ring, step | sine fast")
    scn, tr = case.simulate([0], 30)
    run = simulate_run(scn, tr, "diskf-auto", 0)
    assert run.status.status == "exact", run.status.reason


@pytest.mark.parametrize("label", ["m=2 ring, step | sine fast", "CV ring, steps 0.1"])
def test_banks_per_channel_match_the_oracle(label):
    """Two input channels, a bank each: the engine equals the plain loop of
    ``auto_oracle`` (each filter's transition written out channel by
    channel) to 1e-9, 30 ticks. In the two-channel ring some neighbourhoods
    measure one axis at a tick, and the other axis's bank follows the
    informed one (``input_models.follow_informed``; red without it)."""
    case = next(c for c in heldout.selected(None) if c.label == label)
    scn, tr = case.simulate([0, 1], 30)
    assert_trace_matches_oracle(scn, tr, 1e-9)


def test_a_bank_nobody_informs_follows_the_informed_ones(monkeypatch):
    """The constant-acceleration model, isolated agents, no input, seeds 0
    and 1, 200 ticks: an agent that measures one axis tells its bank of
    the other axis nothing. That bank follows the measured axis's
    (``input_models.follow_informed``), and the state MAE is the one shared
    bank's within 1 % (measured: 354.28 both); left at its prior it
    weighs the walks of large scale, whose covariances on the unmeasured
    axis pass 10^14 by tick 60, and the MAE is over five times larger
    (4,103)."""
    case = next(c for c in heldout.grown_cases() if c.label == "CA none, zero")
    scn, tr = case.simulate([0, 1], None)
    mae = lambda: float(np.mean(metrics.errors(tr, engine.run(tr, "diskf-auto", scn.params))[0]))  # noqa: E731
    shared = float(np.mean(metrics.errors(tr, engine.run(tr, "diskf-auto", replace(
        scn.params, auto=AutoOptions(per_channel=False))))[0]))
    assert abs(mae() / shared - 1) < 0.01, (mae(), shared)
    monkeypatch.setattr(im, "follow_informed", lambda mu, loglik, blind: mu)
    assert mae() > 5 * shared


def test_banks_per_channel_agents_alone_equal_engine():
    """Two input channels in a ring, every agent a batch of one (as in an
    agent process): the engine's bits, so no step of the banks per channel
    reads across the agents of a batch."""
    case = next(c for c in heldout.selected(None) if c.label == "m=2 ring, step | sine fast")
    scn, tr = case.simulate([0], 30)
    ref = engine.run(tr, "diskf-auto", scn.params)
    for k, _, outs in lockstep(scn, "diskf-auto", tr):
        for j, a in enumerate(scn.agents):
            assert np.array_equal(outs[a.id].x[0, 0], ref.x[0, k - 1, j])
            assert np.array_equal(outs[a.id].P[0, 0], ref.P[0, k - 1, j])
            assert np.array_equal(outs[a.id].d[0, 0], ref.d[0, k - 1, j])


def test_a_noise_level_in_the_bank_tells_noisy_sensors_from_an_input():
    """All-to-all, every sensor 10 times noisier than its R says, no input,
    seeds 0..3: with three of the bank's models also under 10 R at every
    sensor (``noise_level``) the state MAE is under half of the bank's
    without them, which takes the noise for a zero-mean input. The level's
    filters fuse the whole neighbourhood's information at 10 R and weigh
    the measurements' energy (``information_energy``); a level for the own
    sensor alone stays near the bank's error here, the neighbours'
    information published under the stated noise outweighing it."""
    err = _state_mae("true R×10 S1 all, zero", "noise_level", (0.0, 10.0))
    assert err[10.0] < 0.5 * err[0.0], err


def _state_mae(label: str, field: str, values) -> dict:
    """{value: diskf-auto's state MAE} on seeds 0..3 of the held-out case
    ``label`` with ``[estimator.auto] field`` at each value."""
    case = next(c for c in heldout.selected(None) if c.label == label)
    scn, tr = case.simulate([0, 1, 2, 3], None)
    return {v: np.mean(metrics.errors(tr, engine.run(tr, "diskf-auto", scn.params.with_setting("auto", **{field: v})))[0])
            for v in values}


def test_a_noise_level_runs_exact_on_the_simulated_network():
    """A ring whose sensors are 10 times noisier than stated, 30 ticks,
    with ``noise_level``: the messages carry the probabilities of the
    models at the stated noise alone (a vector that sums to 1, as every
    receiver's guard checks), and the simulated network gives the engine's
    bits."""
    case = next(c for c in heldout.selected(None) if c.label == "true R×10 S1 ring, step")
    scn, tr = case.simulate([0], 30)
    run = simulate_run(scn.with_overrides(params=scn.params.with_setting("auto", noise_level=10.0)), tr, "diskf-auto", 0)
    assert run.status.status == "exact", run.status.reason


def test_a_noise_level_setting():
    raw = {"model": {"G": [[1.0], [1.0]], "Q": [[0.2, 0], [0, 0.2]], "x0": [0, 0], "P0": [[1, 0], [0, 1]],
                     "A": [[1, 0], [0, 1]]},
           "agents": [{"H": [[1.0, 0.0]], "R": [[2.0]]}], "estimator": {"auto": {"noise_level": 10}}}
    assert parse_scenario(raw).params.auto == AutoOptions(noise_level=10.0)
    for bad in ({"noise_level": 1}, {"noise_level": -2}, {"noise_level": 10, "noise": True}):
        raw["estimator"]["auto"] = bad
        with pytest.raises(InputError) as e:
            parse_scenario(raw)
        assert e.value.field == "estimator.auto.noise_level"
    two = dict(raw, model=dict(raw["model"], G=[[1.0, 0.0], [0.0, 1.0]]))  # two channels: a bank each
    two["estimator"] = {"auto": {"noise_level": 10}}
    with pytest.raises(InputError) as e:
        parse_scenario(two)
    assert e.value.field == "estimator.auto.noise_level"
    two["estimator"] = {"auto": {"noise_level": 10, "per_channel": False}}
    assert parse_scenario(two).params.auto.noise_level == 10.0
    bank = im.at_noise_level(("none", "walk lo", "walk mid", "walk hi"), np.array([0.0, 1, 1, 1]), np.zeros(4),
                             np.array([0.0, 1, 2, 3]), 10.0)
    assert bank[0][4:] == ("none x10", "walk lo x10", "walk mid x10")
    np.testing.assert_array_equal(bank[4], [1, 1, 1, 1, 10, 10, 10])
    np.testing.assert_allclose(im.initial_probabilities(bank[2], bank[4]), [0.2, 0.2, 0.2, 0.2] + [0.2 / 3] * 3)


def test_a_students_evidence_keeps_bursts_from_reading_as_an_input():
    """All-to-all, no input, every sensor in bursts 30 times noisier than
    its R for 10 ticks (about one in 50 per agent), seeds 0..3: with the
    models' evidence read as a Student-t of 4 degrees of freedom
    (``evidence_dof``) a burst moves the model probabilities by the log of
    its innovations' size, not by its square, and the state MAE is under
    0.8 of the Gaussian evidence's (2.50 against 3.46), which takes the
    bursts for an input."""
    err = _state_mae("bursts S1 all, zero", "evidence_dof", (0.0, 4.0))
    assert err[4.0] < 0.8 * err[0.0], err


def test_a_students_evidence_by_hand():
    """``information_loglik`` with ``heavy``: -(nu + k)/2 log(1 + E/nu) -
    log det(H P H^T + R)/2 up to a constant, E the innovation's
    Mahalanobis energy, for two priors of one 2-row measurement (the
    constant cancels in their difference)."""
    rng = np.random.default_rng(5)
    H, R, y = rng.normal(size=(2, 3)), np.diag([0.5, 2.0]), rng.normal(size=2)
    Ri = np.linalg.inv(R)
    U, u = H.T @ Ri @ H, H.T @ Ri @ y
    out = []
    for x, P in ((rng.normal(size=3), np.eye(3)), (rng.normal(size=3), np.diag([3.0, 1.0, 0.2]))):
        S = H @ P @ H.T + R
        e = y - H @ x
        E = e @ np.linalg.solve(S, e)
        want = -0.5 * (4.0 + 2) * np.log1p(E / 4.0) - 0.5 * np.linalg.slogdet(S)[1]
        Y = np.linalg.inv(P)
        got = im.information_loglik(x, P, Y, np.linalg.inv(Y + U), U, u, (y @ Ri @ y, 2.0, 4.0))
        out.append((want, got))
    (w0, g0), (w1, g1) = out
    assert g1 - g0 == pytest.approx(w1 - w0, rel=1e-9)
    E_y, k = im.information_energy(U, u)
    assert (E_y, k) == (pytest.approx(y @ Ri @ y, rel=1e-9), 2.0)


def test_a_students_evidence_at_a_noise_level_by_hand():
    """With ``noise_level`` and ``evidence_dof`` together, a model at level
    r reads the measurement as a Student-t of scale H P H^T + r R: its
    log-likelihood (``information_loglik`` on the level's (U / r, u / r),
    the energy E / r, plus ``_at_levels``'s part) less the stated model's
    is the difference of the two t densities' logs."""
    rng = np.random.default_rng(6)
    H, R, y = rng.normal(size=(2, 3)), np.diag([0.5, 2.0]), 3.0 * rng.normal(size=2)
    Ri = np.linalg.inv(R)
    U, u = H.T @ Ri @ H, H.T @ Ri @ y
    x, P, nu = rng.normal(size=3), np.diag([3.0, 1.0, 0.2]), 4.0
    levels = SimpleNamespace(r=np.array([1.0, 10.0]), dof=nu)
    E, k = im.information_energy(U, u)
    U_m, u_m, level, (E_m, k_m, _) = DISKFAuto._at_levels(levels, np.array(E), np.array(k), U, u)
    Y = np.linalg.inv(P)
    got, want = [], []
    for j, r in enumerate(levels.r):
        got.append(im.information_loglik(x, P, Y, np.linalg.inv(Y + U_m[j]), U_m[j], u_m[j], (E_m[j], k_m[0], nu))
                   + level[j])
        S = H @ P @ H.T + r * R
        e = y - H @ x
        want.append(-0.5 * (nu + 2) * np.log1p(e @ np.linalg.solve(S, e) / nu) - 0.5 * np.linalg.slogdet(S)[1])
    assert got[1] - got[0] == pytest.approx(want[1] - want[0], rel=1e-9)


def test_the_noise_levels_and_the_models_evidence_by_hand():
    """``level_posterior``: each model's likelihood with the level summed
    out, the levels' probabilities weighed by the models' mixture, and each
    model's level given the measurement, against the sums written out."""
    rng = np.random.default_rng(7)
    loglik, c, nu = rng.normal(size=(3, 4)) * 3.0, rng.dirichlet(np.ones(4)), rng.dirichlet(np.ones(3))
    got_ll, got_nu, got_resp = im.level_posterior(loglik, c, nu, 1e-6)
    p = nu[:, None] * np.exp(loglik)                       # p_lj
    want_ll = np.log(p.sum(axis=0))
    assert np.allclose(got_ll - got_ll[0], want_ll - want_ll[0], rtol=0, atol=1e-12)
    want_nu = (c[None, :] * p).sum(axis=1)
    assert np.allclose(got_nu, want_nu / want_nu.sum(), rtol=1e-12)
    assert np.allclose(got_resp, p / p.sum(axis=0), rtol=1e-12)
    # a batch of two rows gives each row's own bits
    both = im.level_posterior(np.stack([loglik, 2 * loglik]), np.stack([c, c]), np.stack([nu, nu]), 1e-6)
    assert all(np.array_equal(a[0], b) for a, b in zip(both, (got_ll, got_nu, got_resp)))


def test_weighing_the_noise_levels_keeps_a_noisy_sensor_from_reading_as_an_input():
    """A ring of sensors 10 times noisier than stated, no input: with the
    levels weighed (``noise_span``) the bank no longer takes the noise for
    an input, the error falls below 0.5 of what it is without them, and
    each model's update at its level's precision brings the NEES from
    above the band into it."""
    case = next(c for c in heldout.selected(None) if c.label == "true R×10 S1 ring, zero")
    scn, tr = case.simulate([0, 1, 2, 3], None)
    rows = {v: heldout.case_row(tr, "diskf-auto", scn.params.with_setting("auto", noise_span=v)) for v in (0.0, 10.0)}
    lo, hi = heldout.chi2_band(tr.model.n, 4)
    assert rows[10.0]["mae_state"] < 0.5 * rows[0.0]["mae_state"], rows
    assert rows[0.0]["nees"] > hi and lo <= rows[10.0]["nees"] <= hi, (rows, lo, hi)


def test_weighing_the_noise_levels_runs_exact_on_the_simulated_network():
    """Bursts of noise in a ring, 30 ticks, with ``noise_span``: each
    agent's level probabilities are its own (not on the wire), and the
    simulated network gives the engine's bits."""
    case = next(c for c in heldout.selected(None) if c.label == "bursts S1 ring, step")
    scn, tr = case.simulate([0], 30)
    run = simulate_run(scn.with_overrides(params=scn.params.with_setting("auto", noise_span=10.0)), tr, "diskf-auto", 0)
    assert run.status.status == "exact", run.status.reason


def test_a_noise_span_setting():
    assert AutoOptions(noise_span=10).noise_span == 10
    for bad in ({"noise_span": 1.0}, {"noise_span": 0.5}, {"noise_span": float("nan")}, {"noise_span": True},
                {"noise_span": 10.0, "noise_level": 10.0}, {"noise_span": 10.0, "noise": True}):
        with pytest.raises(ValueError, match="auto.noise_span"):
            AutoOptions(**bad)


def test_a_students_evidence_setting():
    assert AutoOptions(evidence_dof=4).evidence_dof == 4
    for bad in ({"evidence_dof": -1.0}, {"evidence_dof": float("inf")}, {"evidence_dof": True}):
        with pytest.raises(ValueError, match="auto.evidence_dof"):
            AutoOptions(**bad)
