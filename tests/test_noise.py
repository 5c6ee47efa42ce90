"""The measurement noise diskf-auto learns (``core.noise``): the scale of a
sensor ten times noisier, or calmer, than it was told; an offset that
stays (a step of the input the prediction misses) moves it by one step
only; a tick without a measurement changes nothing; and the held-out
families where it is what wins (red with ``[estimator.auto] noise =
false``), and a fast input's NEES it keeps near its own."""
from __future__ import annotations


import numpy as np
import pytest
from scipy.stats import chi2

from diskf_mesh.core import noise
from diskf_mesh.studies import heldout
from diskf_mesh.studies.suite import observed

STEP = 0.2


def scalar_run(true_var, ticks=400, seed=0, jump=None):
    """r = exp(theta) of one scalar sensor (R = 1) scored against a sharp
    prediction (P = 0.01) of the truth, the world's noise variance
    ``true_var`` (the innovation ``jump[1]`` more on the ticks of
    ``jump[0]``); and theta after each tick."""
    rng = np.random.default_rng(seed)
    H, R, P, x = np.ones((1, 1)), np.ones((1, 1)), 0.01 * np.ones((1, 1)), np.zeros(1)
    theta, thetas, last = np.zeros(()), [], noise.first_innovation((), 1)
    for k in range(ticks):
        y = np.sqrt(true_var + 0.01) * rng.standard_normal(1) + (jump[1] if jump and k in jump[0] else 0.0)
        theta, last = noise.track(theta, last, x, P, y, H, R, np.ones((), dtype=int), np.array(True), chi2.median(1),
                                  STEP)
        thetas.append(float(theta))
    return float(np.exp(np.mean(thetas[-100:]))), np.array(thetas)


@pytest.mark.parametrize("true_var,lo,hi", [(10.0, 6.0, 16.0), (1.0, 0.7, 1.4), (0.1, 0.06, 0.16)])
def test_the_sensors_noise_scale_is_learned(true_var, lo, hi):
    r, _ = scalar_run(true_var)
    assert lo < r < hi


def test_an_offset_that_stays_moves_the_scale_by_one_step():
    """An innovation 1000 larger from tick 100 on (an input's step that the
    prediction misses): the difference of consecutive innovations holds it
    on tick 100 alone, so theta moves at most one step up there instead of down,
    and then as without it (the level of the innovation would move it up
    on every tick)."""
    _, calm = scalar_run(1.0, ticks=110)
    _, jumped = scalar_run(1.0, ticks=110, jump=(range(100, 110), 1e3))
    assert np.array_equal(calm[:100], jumped[:100])
    assert 0 <= jumped[100] - calm[100] <= 2 * STEP + 1e-12
    assert np.abs(jumped[101:] - calm[101:]).max() <= 2 * STEP + 1e-12


def test_a_tick_without_a_measurement_changes_nothing():
    theta = np.array([0.7])
    last = (np.array([[0.5]]), np.array([[[2.0]]]), np.array([True]))
    out, kept = noise.track(theta, last, np.zeros((1, 2)), np.eye(2)[None], np.zeros((1, 1)), np.array([[[1.0, 0.0]]]),
                            np.eye(1)[None], np.array([1]), np.array([False]), chi2.median(1), STEP)
    assert out is not theta and (out == theta).all()
    assert all((a == b).all() for a, b in zip(kept, last))


def test_the_first_measured_tick_keeps_its_innovation_only():
    theta = np.zeros(1)
    out, kept = noise.track(theta, noise.first_innovation((1,), 1), np.zeros((1, 2)), np.eye(2)[None],
                            np.array([[30.0]]), np.array([[[1.0, 0.0]]]), np.eye(1)[None], np.array([1]),
                            np.array([True]), chi2.median(1), STEP)
    assert (out == theta).all() and kept[0][0, 0] == 30.0 and kept[1][0, 0, 0] == 2.0 and kept[2].all()


def test_the_padding_rows_of_a_shorter_sensor_count_for_nothing():
    """A sensor of one row padded to two (H = 0, R = I there) moves theta as
    the same sensor unpadded."""
    x, P = np.zeros(2), 0.5 * np.eye(2)
    one_last = (np.array([-1.0]), 1.5 * np.eye(1), np.array(True))
    padded_last = (np.array([-1.0, 0.0]), np.diag([1.5, 1.0]), np.array(True))
    one, _ = noise.track(np.zeros(()), one_last, x, P, np.array([3.0]), np.array([[1.0, 0.0]]), np.eye(1),
                         np.ones((), dtype=int), np.array(True), chi2.median(1), STEP)
    padded, _ = noise.track(np.zeros(()), padded_last, x, P, np.array([3.0, 0.0]), np.array([[1.0, 0.0], [0.0, 0.0]]),
                            np.eye(2), np.ones((), dtype=int), np.array(True), chi2.median(1), STEP)
    assert one == pytest.approx(padded, abs=1e-12) and one > 0


@pytest.mark.parametrize("label,most", [("true R×10 S1 ring, zero", 0.8), ("true R×10 S2 range 120, step", 0.9)])
def test_learning_the_noise_is_what_wins(label, most):
    """Measured on seeds 0-9: R x 10, ring, no input: 4.46 against 7.85 with
    the noise as stated; Scenario 2 at range 120, the step: 18.7 against
    25.5 (seeds 0-3, as here: 4.18 against 7.07, 20.9 against 25.5)."""
    on, off = learning_and_not(label)
    assert on["mae_state"] < most * off["mae_state"]
    assert on["nees"] < 0.7 * off["nees"]


def test_bursts_are_learned_as_noise():
    """Bursts of 30 x the measurement noise, ring, no input (seeds 0-3):
    4.24 NEES against 7.01 with the noise as stated, 3.19 against 3.56 MAE
    (scored on the innovation's level rather than its difference, 5.49
    and 3.43)."""
    on, off = learning_and_not("bursts S1 ring, zero")
    assert on["mae_state"] < off["mae_state"]
    assert on["nees"] < 0.7 * off["nees"]


def test_a_fast_input_the_bank_predicts_is_not_read_as_noise():
    """A sine of period 10 in Scenario 2, all-to-all (seeds 0-3): NEES 1.51
    with the noise learned, 2.00 without; scored against the agent's own
    prediction with the input it last fused, rather than the bank's, the
    swing the oscillating models predict read as noise and took it to
    1.00, under the band."""
    on, off = learning_and_not("S2 all, sine fast")
    assert on["nees"] > 0.65 * off["nees"]
    assert on["mae_state"] < 1.05 * off["mae_state"]


def learning_and_not(label):
    """diskf-auto's rows on the case ``label`` (seeds 0-3, 200 ticks) with
    the noise learned and as stated (the default)."""
    (case,) = [c for c in heldout.cases() if c.label == label]
    scn, tr = case.simulate(range(4), 200)
    seen = observed(tr)
    learning = scn.params.with_setting("auto", noise=True)
    return heldout.case_row(tr, "diskf-auto", learning, seen), heldout.case_row(tr, "diskf-auto", scn.params, seen)
