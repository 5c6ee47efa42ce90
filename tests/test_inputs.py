"""The [input] kinds of a scenario: each against hand-worked numbers, its
seed rule, and its validation (one error naming the key)."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from diskf_mesh.core.errors import InputError
from diskf_mesh.data.inputs import parse_input
from diskf_mesh.data.scenario import load_scenario, simulate


def d(table, steps=8, seed=0, m=1):
    return parse_input(table, m).values(steps, seed)[:, 0] if m == 1 else parse_input(table, m).values(steps, seed)


def test_step_and_constant_as_before():
    np.testing.assert_array_equal(d(dict(kind="step", at=2, before=[1.0], after=[4.0]), 4), [1, 1, 4, 4])
    np.testing.assert_array_equal(d(dict(kind="constant", value=[3.0]), 3), [3, 3, 3])


def test_sine_hand_worked():
    # amplitude 2, period 4, phase pi/2, from tick 1: 2 sin(pi/2 (k-1) + pi/2) = 2 cos(pi/2 (k-1))
    got = d(dict(kind="sine", amplitude=2.0, period=4.0, phase=np.pi / 2, at=1), 6)
    np.testing.assert_allclose(got, [0, 2, 0, -2, 0, 2], atol=1e-12)


def test_ramp_hand_worked():
    np.testing.assert_allclose(d(dict(kind="ramp", at=2, slope=0.5, before=1.0), 5), [1, 1, 1, 1.5, 2])


def test_telegraph_every_interval():
    np.testing.assert_array_equal(d(dict(kind="telegraph", amplitude=5.0, interval=3, random=False), 8),
                                  [5, 5, 5, -5, -5, -5, 5, 5])


def test_random_kinds_follow_the_seed_rule():
    # without input.seed: simulation seed s draws from default_rng([s, 1])
    rng = np.random.default_rng([7, 1])
    np.testing.assert_allclose(d(dict(kind="white", scale=2.0), 5, seed=7), 2.0 * rng.standard_normal(5))
    # steps: a new level where the uniform draw is below 1 / interval
    rng = np.random.default_rng([3, 1])
    starts = rng.random(6) < 0.5
    levels = 1.5 * rng.standard_normal(6)
    want, cur = [], 0.0
    for k in range(6):
        cur = levels[k] if starts[k] else cur
        want.append(cur)
    np.testing.assert_allclose(d(dict(kind="steps", interval=2.0, scale=1.5), 6, seed=3), want)
    # random telegraph: the sign flips where the draw is below 1 / interval
    rng = np.random.default_rng([3, 1])
    flips = rng.random(6) < 0.25
    np.testing.assert_allclose(d(dict(kind="telegraph", interval=4.0, amplitude=2.0), 6, seed=3),
                               2.0 * (-1.0) ** np.cumsum(flips))
    # with input.seed: the same input for every simulation seed
    a, b = d(dict(kind="white", seed=5), 5, seed=0), d(dict(kind="white", seed=5), 5, seed=9)
    np.testing.assert_array_equal(a, b)
    np.testing.assert_allclose(a, np.random.default_rng(5).standard_normal(5))


def test_series_values_and_file(tmp_path):
    np.testing.assert_array_equal(d(dict(kind="series", values=[1.0, 2.0, 3.0]), 5), [1, 2, 3, 3, 3])
    f = tmp_path / "d.csv"
    f.write_text("# tick, d0, d1\n1, 2\n3 4\n")
    np.testing.assert_array_equal(parse_input(dict(kind="series", file=str(f)), 2).values(3), [[1, 2], [3, 4], [3, 4]])


def test_simulation_uses_the_seeded_input():
    scn = load_scenario("quadrants")
    raw_input = dict(kind="white", scale=3.0)
    scn2 = replace(scn, input=parse_input(raw_input, 1))
    tr = simulate(scn2, [0, 4], 10)
    for b, s in enumerate((0, 4)):
        np.testing.assert_allclose(tr.truth_d[b, :, 0], 3.0 * np.random.default_rng([s, 1]).standard_normal(10))
    # the input's stream is not the noise's: a white input of scale 0 gives the noise of a zero input
    zero = simulate(replace(scn, input=parse_input(dict(kind="constant", value=0.0), 1)), [4], 10)
    white0 = simulate(replace(scn, input=parse_input(dict(kind="white", scale=0.0), 1)), [4], 10)
    assert np.array_equal(zero.y, white0.y) and np.array_equal(zero.truth_x, white0.truth_x)


@pytest.mark.parametrize("table,field", [
    (dict(kind="sine", period=0.0), "input.period"),
    (dict(kind="wave"), "input.kind"),
    (dict(kind="white", slope=1.0), "input.slope"),
    (dict(kind="sine", seed=1), "input.seed"),
    (dict(kind="steps", interval=0.5), "input.interval"),
    (dict(kind="white", scale=[-1.0]), "input.scale"),
    (dict(kind="series"), "input.values"),
    (dict(kind="series", values=[[1.0, 2.0]]), "input.values"),
    (dict(kind="series", file="/nonexistent/d.csv"), "input.file"),
    (dict(kind="sine", amplitude=[1.0, 2.0]), "input.amplitude"),
])
def test_bad_input_names_the_key(table, field):
    with pytest.raises(InputError) as e:
        parse_input(table, 1)
    assert e.value.field == field
