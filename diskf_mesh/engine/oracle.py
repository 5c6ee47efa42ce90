"""A plain, per-agent reference implementation of DISKF (the test oracle).

Deliberately naive: explicit Python loops over seeds, ticks, agents and
neighbours, one agent's matrices at a time, and the paper's textbook formulas
written out directly (gain form of the Kalman update, the direct
M = (F^T R~^-1 F)^-1 F^T R~^-1 of the input estimate with R~ = H P H^T + R, no
information-form shortcuts). It shares no code with ``equations`` or
``linalg`` (only the ``Message`` container, one agent's at a time), so
``tests/test_oracle.py`` comparing the two checks the batched
engine against the paper, not against itself.

Semantics follow ``estimators/diskf.py`` exactly: the observation window
counter, its reset on a valid fused input, the compensation gain forms, the
difference of published predictions in the compensation, "no measurement:
the update is the prediction", and the optional ``hold_input`` extension.
"""
from __future__ import annotations

import numpy as np

from diskf_mesh.core.messages import Message
from diskf_mesh.estimators import Params
from diskf_mesh.data.trace import Trace


def predict(x, P, A, Q):
    """Eq. (info_kf_prediction0)."""
    return A @ x, A @ P @ A.T + Q


def kalman_update(x_pred, P_pred, H, R, y):
    """Eq. (info_kf_update0) in gain form: P~^-1 = P^^-1 + H^T R^-1 H,
    L = P~ H^T R^-1, x~ = x^ + L (y - H x^)."""
    Ri = np.linalg.inv(R)
    P_upd = np.linalg.inv(np.linalg.inv(P_pred) + H.T @ Ri @ H)
    L = P_upd @ H.T @ Ri
    return x_pred + L @ (y - H @ x_pred), P_upd


def estimate_input(x_pred, P_pred, H, R, G, y):
    """Eqs. (input_estimation), (input_estimation_mk1), (input_estimation_mk2)
    and the covariance S^ below them, written directly."""
    R_tilde = H @ P_pred @ H.T + R
    F = H @ G
    Rti = np.linalg.inv(R_tilde)
    S = np.linalg.inv(F.T @ Rti @ F)
    M = S @ F.T @ Rti
    return M @ (y - H @ x_pred), S


def fuse_inputs(msgs):
    """Eqs. (input_fusion), (input_fusion_p) over the valid neighbours.
    Returns (d_bar, S_bar) or None when no neighbour had a valid estimate."""
    valid = [mj for mj in msgs if mj.d_valid]
    if not valid:
        return None
    inv_tr = [1.0 / np.trace(mj.S) for mj in valid]
    total = sum(inv_tr)
    info = 0.0
    vec = 0.0
    for mj, t in zip(valid, inv_tr):
        w = t / total
        Si = np.linalg.inv(mj.S)
        info = info + w * Si
        vec = vec + w * Si @ mj.d
    S_bar = np.linalg.inv(info)
    return S_bar @ vec, S_bar


def fuse_states(own: Message, msgs, x_star):
    """Eqs. (state_fusion), (state_fusion_p) with P^* = P^ (info_kf_prediction)."""
    Y_star = np.linalg.inv(own.P_pred)
    Y = Y_star.copy()
    y = Y_star @ x_star
    for mj in msgs:
        Yu, Yp = np.linalg.inv(mj.P_upd), np.linalg.inv(mj.P_pred)
        Y = Y + (Yu - Yp)
        y = y + (Yu @ mj.x_upd - Yp @ mj.x_pred)
    P_bar = np.linalg.inv(Y)
    return P_bar @ y, P_bar


def compensation_gain(P_bar, form: str, eps: float, n_neighbours: int):
    """M_i of eq. (compensation_state): the paper's P_bar, the bounded
    P_bar (I + eps |N_i| P_bar)^-1 (|N_i| without i itself), or the
    normalized P_bar / (1 + ||P_bar||_F)."""
    if form == "paper":
        return P_bar
    if form == "bounded":
        return P_bar @ np.linalg.inv(np.eye(len(P_bar)) + eps * n_neighbours * P_bar)
    if form == "normalized":
        return P_bar / (1.0 + np.linalg.norm(P_bar))
    raise ValueError(f"unknown compensation form {form!r}")


def run_diskf(trace: Trace, params: Params | None = None):
    """DISKF on every seed of ``trace``, one agent at a time.

    Returns (x, P, d, d_valid) shaped like ``engine.Estimates``:
    (B, K, N, n), (B, K, N, n, n), (B, K, N, m), (B, K, N)."""
    p = params or Params()
    model, sensors = trace.model, trace.sensors
    B, K, N = trace.has.shape
    n, m = model.n, model.m
    xs = np.zeros((B, K, N, n))
    Ps = np.zeros((B, K, N, n, n))
    ds = np.zeros((B, K, N, m))
    dv = np.zeros((B, K, N), dtype=bool)
    Hs = [sensors.H[i, : sensors.p[i]] for i in range(N)]
    Rs = [sensors.R[i, : sensors.p[i], : sensors.p[i]] for i in range(N)]
    for b in range(B):
        x = [np.array(model.x0, dtype=float) for _ in range(N)]
        P = [np.array(model.P0, dtype=float) for _ in range(N)]
        since = [0] * N
        hold = [None] * N  # last fused input (Params.hold_input), None before the first
        links = trace.links[min(b, trace.links.shape[0] - 1)]
        for k in range(1, K + 1):
            msgs = []
            for i in range(N):
                has = bool(trace.has[b, k - 1, i])
                y = trace.y[b, k - 1, i, : Hs[i].shape[0]] if has else None
                msg, since[i] = local_step(x[i], P[i], since[i], model, k, Hs[i], Rs[i], y, p)
                msgs.append(msg)
            for i in range(N):
                nbrs = [msgs[j] for j in np.flatnonzero(links[k - 1, i])]  # in id order, itself included
                x[i], P[i], d_bar, has, hold[i] = fuse_step(msgs[i], nbrs, model.G, p, hold[i])
                if p.reset and has:
                    since[i] = 0
                xs[b, k - 1, i], Ps[b, k - 1, i], ds[b, k - 1, i], dv[b, k - 1, i] = x[i], P[i], d_bar, has
    return xs, Ps, ds, dv


def local_step(x, P, since: int, model, k: int, H, R, y, p: Params):
    """Step 1 of Algorithm 1 for one agent; ``y`` is None without a measurement.
    Returns (message, window counter after the tick's measurement)."""
    x_pred, P_pred = predict(x, P, model.A_at(k), model.Q)
    since += 1
    allowed = p.window is None or since <= p.window
    m = model.m
    if y is None:
        x_upd, P_upd = x_pred, P_pred
    else:
        x_upd, P_upd = kalman_update(x_pred, P_pred, H, R, y)
    if y is not None and allowed and np.linalg.matrix_rank(H @ model.G) == m:
        d, S = estimate_input(x_pred, P_pred, H, R, model.G, y)
        valid = True
    else:
        d, S, valid = np.zeros(m), np.eye(m), False
    if y is not None:
        since = 0
    return Message(x_pred, P_pred, x_upd, P_upd, d, S, valid), since


def fuse_step(own: Message, nbrs, G, p: Params, hold=None):
    """Steps 3 and 4 of Algorithm 1 for one receiver. ``nbrs`` includes itself.

    ``hold`` is the last fused input, used in the prediction when nothing is
    fused this tick if ``p.hold_input`` (our extension, off by default).
    Returns (x_bar, P_bar, d_bar, fused or not, hold for the next tick)."""
    fused = fuse_inputs(nbrs)
    if fused is not None:
        hold = fused[0]
    d_star = (hold if p.hold_input else None) if fused is None else fused[0]
    x_star = own.x_pred if d_star is None else own.x_pred + G @ d_star
    x_bar, P_bar = fuse_states(own, nbrs, x_star)
    if p.compensation != "none" and p.eps != 0.0:
        total = sum(mj.x_pred - own.x_pred for mj in nbrs)
        gain = compensation_gain(P_bar, p.compensation, p.eps, len(nbrs) - 1)
        x_bar = x_bar + p.eps * gain @ total
    d_bar = np.zeros(G.shape[1]) if fused is None else fused[0]
    return x_bar, P_bar, d_bar, fused is not None, hold
