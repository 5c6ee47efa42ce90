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

A second centre, ``run_centralized_persist``, runs the joint Kalman filter
of (x, d) with ``diskf-r``'s persistent-input model (the input a random
walk): it is the bound of that model, which the first centre is not (an
estimator that assumes the input persists can be below the assumption-free
bound, and diskf-r is wherever the input does persist). In all-to-all
diskf-r equals it to round-off.

Both run on the engine's data only (one centre, not a mesh of agents).
"""
from __future__ import annotations

import numpy as np

from diskf_mesh.core import equations as eq
from diskf_mesh.core import input_models as im
from diskf_mesh.estimators.diskf_robust import input_model_of
from diskf_mesh.engine.batch import Estimates

from diskf_mesh.core.rkf import rkf_update
from diskf_mesh.data.trace import Trace

NAME = "centralized"
LABEL = "Centralized (bound)"
PERSIST_NAME = "centralized-persist"
PERSIST_LABEL = "Centralized, persistent input (bound of DISKF-R's model)"


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
        U, u = _stacked_information(trace, k, info)
        Y, Ji = eq.information_pair(P_pred, U)
        d, _, valid = eq.input_estimate(x_pred, Y, Ji, U, u, model.G)
        x, P = rkf_update(x_pred, Y, U, u, model.G, valid)
        xs[:, k - 1], Ps[:, k - 1], ds[:, k - 1], dv[:, k - 1] = x, P, d, valid
    return _every_agent(N, xs, Ps, ds, dv)


def _every_agent(N, xs, Ps, ds, dv) -> Estimates:
    rep = lambda a: np.repeat(a[:, :, None], N, axis=2)  # noqa: E731
    return Estimates(rep(xs), rep(Ps), rep(ds), rep(dv))


def _stacked_information(trace: Trace, k: int, info):
    """The stacked sensors' H^T R^-1 H and H^T R^-1 y at tick k (every agent)."""
    U_j, u_j = eq.measurement_information(info, trace.y[:, k - 1], trace.has[:, k - 1])
    return U_j.sum(axis=1), u_j.sum(axis=1)


def run_centralized_persist(trace: Trace, options) -> Estimates:
    """The centre with ``diskf-r``'s persistent-input model (``options``:
    ``model.RobustOptions``: its input model, ``input_walk`` and
    ``input_prior``): the joint Kalman filter of (x_k, d_{k-1}) with d
    following the input model (``input_models.input_predict``), every
    measurement stacked. This is the
    bound of diskf-r's own model, as ``run_centralized`` is the bound of the
    model that assumes nothing about the input: diskf-r in an all-to-all
    network is this filter (``tests/test_robust.py``). The input estimate is
    reported from the first tick with a measurement on."""
    model, sensors = trace.model, trace.sensors
    B, K, N = trace.has.shape
    n, m = model.n, model.m
    G = model.G
    rho, q, prior = input_model_of(options, model, sensors)
    info = eq.sensor_information(sensors.H, sensors.R)
    x = np.broadcast_to(model.x0, (B, n)).astype(float).copy()
    P = np.broadcast_to(model.P0, (B, n, n)).astype(float).copy()
    d, C = np.zeros((B, m)), np.zeros((B, n, m))
    S = np.broadcast_to(prior * np.eye(m), (B, m, m)).copy()
    held = np.zeros(B, dtype=bool)
    xs, Ps = np.empty((B, K, n)), np.empty((B, K, n, n))
    ds, dv = np.empty((B, K, m)), np.empty((B, K), dtype=bool)
    for k in range(1, K + 1):
        A = model.A_at(k)
        v, Pv = eq.predict(x, P, A, model.Q)
        d, Bc, S = im.input_predict(A, C, d, S, rho, q)
        U, u = _stacked_information(trace, k, info)
        x_s, P_s, C_s = eq.input_to_state(v, Pv, Bc, d, S, G)
        x, P = eq.local_update(x_s, P_s, *eq.information_pair(P_s, U), u)
        d, C, S = eq.replace_marginal(x_s, P_s, d, C_s, S, x, P)
        held = held | (np.trace(U, axis1=-2, axis2=-1) > 0)
        xs[:, k - 1], Ps[:, k - 1], ds[:, k - 1], dv[:, k - 1] = x, P, d, held & (options.input_model != "none")
    return _every_agent(N, xs, Ps, ds, dv)
