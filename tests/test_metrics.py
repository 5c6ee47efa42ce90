"""The pooled and per-seed metrics: the per-seed ones, computed for all
seeds at once, are each seed's own ``summarize`` bit for bit."""
import numpy as np
import pytest

from diskf_mesh.data import metrics


def errors(rng, B, K, N, missing):
    e_state = np.abs(rng.standard_normal((B, K, N))) * 10.0 ** rng.uniform(-3, 3, (B, K, N))
    e_in = np.abs(rng.standard_normal((B, K, N))) * 10.0 ** rng.uniform(-3, 3, (B, K, N))
    e_in[rng.random((B, K, N)) < missing] = np.nan
    nees = rng.chisquare(2, (B, K, N))
    return e_state, e_in, nees


@pytest.mark.parametrize("B,K,N,missing", [(20, 200, 4, 0.3), (3, 17, 9, 0.9), (5, 1, 1, 0.5), (4, 30, 7, 1.0)])
def test_per_seed_is_each_seeds_summarize(B, K, N, missing):
    e_state, e_in, nees = errors(np.random.default_rng(B * K + N), B, K, N, missing)
    got = metrics.per_seed_errors(e_state, e_in, nees)
    for b in range(B):
        alone = metrics.summarize(e_state[b], e_in[b], nees[b])
        for key in metrics.METRIC_KEYS:
            assert got[key][b] == alone[key] or (np.isnan(got[key][b]) and np.isnan(alone[key])), (key, b)
    assert all(got[key].shape == (B,) for key in metrics.METRIC_KEYS)


def test_summarize_without_a_mask_is_with_an_all_true_one():
    e_state, e_in, nees = errors(np.random.default_rng(7), 3, 50, 6, 0.4)
    everything = np.ones(e_state.shape, dtype=bool)
    assert metrics.summarize(e_state, e_in, nees) == metrics.summarize(e_state, e_in, nees, everything)


def test_no_agent_ticks_give_no_values():
    empty = np.zeros((2, 0, 3))
    got = metrics.per_seed_errors(empty, empty, empty)
    assert np.isnan(got["mae_state"]).all() and np.isnan(got["nees"]).all()
    assert (got["input_coverage"] == 0.0).all() and got["input_coverage"].shape == (2,)
