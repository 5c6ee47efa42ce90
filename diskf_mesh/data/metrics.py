"""Error metrics over agents and ticks (and seeds).

State errors are Euclidean distances over the position components; input
errors are Euclidean norms over the input vector, counted only where an agent
has an input estimate. NEES uses the full state and the reported covariance.
"""
from __future__ import annotations

import numpy as np

from diskf_mesh.core.linalg import mv

METRIC_KEYS = ("mae_state", "rmse_state", "mae_input", "rmse_input", "input_coverage", "nees")


def errors(trace, est):
    """Per (B, K, N): state position error, input error (NaN where no
    estimate), NEES."""
    dims = list(trace.position_dims)
    ex = est.x - trace.truth_x[:, :, None, :]
    e_state = np.linalg.norm(ex[..., dims], axis=-1)
    e_in = np.linalg.norm(est.d - trace.truth_d[:, :, None, :], axis=-1)
    e_in = np.where(est.d_valid, e_in, np.nan)
    nees = np.einsum("...i,...i->...", ex, np.linalg.solve(est.P, ex[..., None])[..., 0])
    return e_state, e_in, nees


def summarize(e_state, e_in, nees, mask=None) -> dict:
    """Pooled metrics; ``mask`` (same shape) restricts to some agent-ticks."""
    pick = np.ravel if mask is None else (lambda a: a[mask])  # all of them: the same order, no copy
    es = pick(e_state)
    ei = pick(e_in)
    ei = ei[~np.isnan(ei)]
    nan = float("nan")
    return {
        "mae_state": float(es.mean()) if es.size else nan,
        "rmse_state": float(np.sqrt((es ** 2).mean())) if es.size else nan,
        "mae_input": float(ei.mean()) if ei.size else nan,
        "rmse_input": float(np.sqrt((ei ** 2).mean())) if ei.size else nan,
        "input_coverage": float(ei.size / max(es.size, 1)),
        "nees": float(pick(nees).mean()) if es.size else nan,
    }


def compute(trace, est) -> dict:
    """Pooled metrics over seeds, ticks and agents."""
    return summarize(*errors(trace, est))


def per_seed(trace, est) -> dict:
    """{metric: array over seeds}, for spreads."""
    return per_seed_errors(*errors(trace, est))


def per_seed_errors(e_state, e_in, nees) -> dict:
    """``per_seed`` from the errors (``errors``): each seed's ``summarize``.

    The state errors and NEES of a seed are a row of (B, K N), whose mean
    over the row adds in the same order as the mean of the seed alone (the
    same bits, one call for all seeds); the input errors, counted only where
    they exist, go seed by seed."""
    B = e_state.shape[0]
    if B == 0 or e_state[0].size == 0:
        return {k: np.zeros(B) if k == "input_coverage" else np.full(B, np.nan) for k in METRIC_KEYS}
    es, nees = e_state.reshape(B, -1), nees.reshape(B, -1)
    inputs = [ei[~np.isnan(ei)] for ei in e_in.reshape(B, -1)]
    nan = float("nan")
    return {
        "mae_state": es.mean(axis=1),
        "rmse_state": np.sqrt((es ** 2).mean(axis=1)),
        "mae_input": np.array([ei.mean() if ei.size else nan for ei in inputs]),
        "rmse_input": np.array([np.sqrt((ei ** 2).mean()) if ei.size else nan for ei in inputs]),
        "input_coverage": np.array([ei.size / es.shape[1] for ei in inputs]),
        "nees": nees.mean(axis=1),
    }
