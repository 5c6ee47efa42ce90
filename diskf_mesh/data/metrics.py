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
    if mask is None:
        mask = np.ones(e_state.shape, dtype=bool)
    es = e_state[mask]
    ei = e_in[mask]
    ei = ei[~np.isnan(ei)]
    nan = float("nan")
    return {
        "mae_state": float(es.mean()) if es.size else nan,
        "rmse_state": float(np.sqrt((es ** 2).mean())) if es.size else nan,
        "mae_input": float(ei.mean()) if ei.size else nan,
        "rmse_input": float(np.sqrt((ei ** 2).mean())) if ei.size else nan,
        "input_coverage": float(ei.size / max(es.size, 1)),
        "nees": float(nees[mask].mean()) if es.size else nan,
    }


def compute(trace, est) -> dict:
    """Pooled metrics over seeds, ticks and agents."""
    return summarize(*errors(trace, est))


def per_seed(trace, est) -> dict:
    """{metric: array over seeds}, for spreads."""
    return per_seed_errors(*errors(trace, est))


def per_seed_errors(e_state, e_in, nees) -> dict:
    """``per_seed`` from the errors (``errors``)."""
    rows = [summarize(e_state[b], e_in[b], nees[b]) for b in range(e_state.shape[0])]
    return {k: np.array([r[k] for r in rows]) for k in METRIC_KEYS}
