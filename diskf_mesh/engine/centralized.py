"""The centralized filter over all agents: a reference bound, not a competitor.

One fusion centre receives every agent's measurement at every tick (stacked
H, R, y of all agents) and runs the exact recursion of Gillijns & De Moor
(2007): the unbiased minimum-variance input estimate of eq.
(input_estimation) on the stacked measurement, then the RKF state update of
``rkf.rkf_update`` (the input direction of the prior left free). No one-round
decentralized method can see more than this centre sees, so among estimators
that assume nothing about the input (an arbitrary d_k each tick) it is the
least error-covariance one; its error tells a user how far a one-round method
is from the optimum. A method that also assumes the input persists (e.g.
``diskf-r``'s held input) uses a model the centre does not, and can be
below it where the stacked sensors cannot separate input from state.

Stacking is exact in information form: the stacked H^T R^-1 H and H^T R^-1 y
are the sums of the agents' own terms (``equations.measurement_information``).
Where no agent measures, or the rank condition (eq10) fails on the stacked
sensors, the centre makes the plain Kalman update without input (as C-DRKF).
In an all-to-all network this is exactly C-DRKF (every neighbourhood is
every agent); ``tests/test_robust.py`` checks the two agree.

It runs on the engine's data only (one centre, not a mesh of agents).
"""
from __future__ import annotations

import numpy as np

from diskf_mesh.core import equations as eq
from diskf_mesh.engine.batch import Estimates
from diskf_mesh.core.rkf import rkf_update
from diskf_mesh.data.trace import Trace

NAME = "centralized"
LABEL = "Centralized (bound)"


def run_centralized(trace: Trace) -> Estimates:
    """The centre's estimates on every seed of ``trace``, shaped like
    ``engine.run``'s (B, K, N, ...): every agent reports the centre's
    estimate, so every metric weighs it as the engine's rows do."""
    model, sensors = trace.model, trace.sensors
    B, K, N = trace.has.shape
    n, m = model.n, model.m
    info = eq.sensor_information(sensors.H, sensors.R)
    x = np.broadcast_to(model.x0, (B, n)).astype(float).copy()
    P = np.broadcast_to(model.P0, (B, n, n)).astype(float).copy()
    xs, Ps = np.empty((B, K, n)), np.empty((B, K, n, n))
    ds, dv = np.empty((B, K, m)), np.empty((B, K), dtype=bool)
    for k in range(1, K + 1):
        x_pred, P_pred = eq.predict(x, P, model.A_at(k), model.Q)
        U_j, u_j = eq.measurement_information(info, trace.y[:, k - 1], trace.has[:, k - 1])
        U, u = U_j.sum(axis=1), u_j.sum(axis=1)  # the stacked sensors' H^T R^-1 H, H^T R^-1 y
        Y, Ji = eq.information_pair(P_pred, U)
        d, _, valid = eq.input_estimate(x_pred, Y, Ji, U, u, model.G)
        x, P = rkf_update(x_pred, Y, U, u, model.G, valid)
        xs[:, k - 1], Ps[:, k - 1], ds[:, k - 1], dv[:, k - 1] = x, P, d, valid
    rep = lambda a: np.repeat(a[:, :, None], N, axis=2)  # noqa: E731
    return Estimates(rep(xs), rep(Ps), rep(ds), rep(dv))
