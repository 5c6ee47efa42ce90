"""The in-process engine: every agent of every seed at once, one tick at a time.

Per tick it calls the algorithm's ``local`` on the whole (seeds x agents)
batch, lets every agent "hear" the messages allowed by the links, and calls
``fuse``. There is no Python loop over agents or seeds; the agent process
(``agents/``) calls the very same two functions on a batch of one.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import algorithms
from .messages import Neighbourhood
from .model import Params
from .trace import Trace


@dataclass(frozen=True)
class Estimates:
    """Per tick and agent: fused state and covariance, fused input and
    whether it exists. Shapes (B, K, N, ...)."""

    x: np.ndarray
    P: np.ndarray
    d: np.ndarray
    d_valid: np.ndarray


def gossip_stream(trace: Trace) -> np.ndarray:
    """(B, K, N) uniform draws, the per-agent streams of ``gossip_draws``."""
    K = trace.y.shape[1]
    return np.stack([algorithms.gossip_draws(s, trace.sensors.ids, K).T for s in trace.seeds])


def run(trace: Trace, algorithm: str, params: Params | None = None, progress=None) -> Estimates:
    """Run one algorithm on every seed of ``trace``.

    ``progress``, if given, is called with the number of ticks done."""
    alg = algorithms.get(algorithm)(trace.model, trace.sensors, params)
    B, K, N = trace.has.shape
    n, m = trace.model.n, trace.model.m
    state = alg.init((B, N))
    self_mask = np.broadcast_to(np.eye(N, dtype=bool), (B, N, N))
    gossip = gossip_stream(trace) if algorithm == "gdkf" else None
    xs = np.empty((B, K, N, n))
    Ps = np.empty((B, K, N, n, n))
    ds = np.empty((B, K, N, m))
    dv = np.empty((B, K, N), dtype=bool)
    for k in range(1, K + 1):
        state, msg = alg.local(state, k, trace.y[:, k - 1], trace.has[:, k - 1])
        adj = np.broadcast_to(trace.links[:, k - 1], (B, N, N)).astype(float)
        nb = Neighbourhood(adj, self_mask, None if gossip is None else gossip[:, k - 1])
        state, out = alg.fuse(state, msg, msg, nb)
        xs[:, k - 1], Ps[:, k - 1], ds[:, k - 1], dv[:, k - 1] = out.x, out.P, out.d, out.d_valid
        if progress is not None:
            progress(k)
    return Estimates(xs, Ps, ds, dv)
