"""A plain per-agent reference of ``diskf-r`` (the test oracle for the
robust variant), in the spirit of ``diskf_mesh/engine/oracle.py``: explicit loops
over seeds, ticks, agents and neighbours, textbook formulas on stacked H, R,
y (never the messages' information form), numpy.linalg / scipy only, and no
code shared with ``equations``, ``rkf`` or ``linalg``. The invariant zeros
come from the Rosenbrock pencil (scipy's generalized eigenvalues), not from
the zero dynamics + Hautus test of ``equations.strongly_detectable``.

Implements the defaults of ``model.RobustOptions`` (every switch as shipped).
The fading factor is computed from the whitened innovation itself.
"""
from __future__ import annotations

import numpy as np
import scipy.linalg


def fast_ci(means, covs):
    """Trace-weighted fast CI (eqs. input_fusion, input_fusion_p)."""
    w = np.array([1.0 / np.trace(C) for C in covs])
    w = w / w.sum()
    info = sum(wi * np.linalg.inv(C) for wi, C in zip(w, covs))
    vec = sum(wi * np.linalg.inv(C) @ m for wi, m, C in zip(w, means, covs))
    C = np.linalg.inv(info)
    return C @ vec, C


def invariant_zeros(A, G, H):
    """Invariant zeros: the z where the Rosenbrock matrix [[A - z I, G], [H, 0]]
    drops rank. H is first reduced to independent rows (two x-sensors are one
    row space). With as many rows as inputs the pencil is square: its finite
    generalized eigenvalues. With more, the candidates of a random square
    combination of the rows, kept where the full matrix drops rank."""
    n, m = G.shape
    _, sv, Vt = np.linalg.svd(H)
    r = int((sv > 1e-12 * max(sv.max(), 1.0)).sum())
    H = Vt[:r]
    Hs = H if r == m else np.random.default_rng(0).standard_normal((m, r)) @ H
    M = np.block([[A, G], [Hs, np.zeros((m, m))]])
    N = np.block([[np.eye(n), np.zeros((n, m))], [np.zeros((m, n + m))]])
    z = scipy.linalg.eigvals(M, N)
    z = z[np.isfinite(z)]
    if r == m:
        return z
    full = lambda c: np.block([[A - c * np.eye(n), G], [H, np.zeros((r, m))]])  # noqa: E731
    return np.array([c for c in z if np.linalg.svd(full(c), compute_uv=False)[-1] < 1e-8])


def strongly_detectable(A, G, H):
    return (H.shape[0] > 0 and np.linalg.matrix_rank(H @ G) == G.shape[1]
            and bool(np.all(np.abs(invariant_zeros(A, G, H)) < 1.0)))


def run_robust(trace):
    model, sensors = trace.model, trace.sensors
    B, K, N = trace.has.shape
    n, m = model.n, model.m
    G = model.G
    out = dict(x=np.zeros((B, K, N, n)), P=np.zeros((B, K, N, n, n)), d=np.zeros((B, K, N, m)),
               v=np.zeros((B, K, N), dtype=bool))
    Hs = [sensors.H[i, : sensors.p[i]] for i in range(N)]
    Rs = [sensors.R[i, : sensors.p[i], : sensors.p[i]] for i in range(N)]
    for b in range(B):
        x = [model.x0.astype(float).copy() for _ in range(N)]
        P = [model.P0.astype(float).copy() for _ in range(N)]
        dh = [np.zeros(m) for _ in range(N)]
        Sh = [np.eye(m) for _ in range(N)]
        held = [False] * N
        fed = [False] * N
        links = trace.links[min(b, trace.links.shape[0] - 1)]
        for k in range(1, K + 1):
            A = model.A_at(k)
            pred = [(A @ x[i], A @ P[i] @ A.T + model.Q) for i in range(N)]
            new = []
            for i in range(N):
                nb = list(np.flatnonzero(links[k - 1, i]))
                xc, Pc = fast_ci([pred[j][0] for j in nb], [pred[j][1] for j in nb])
                meas = [j for j in nb if trace.has[b, k - 1, j]]
                if meas:
                    H = np.vstack([Hs[j] for j in meas])
                    R = scipy.linalg.block_diag(*[Rs[j] for j in meas])
                    y = np.concatenate([trace.y[b, k - 1, j, : sensors.p[j]] for j in meas])
                    rank = np.linalg.matrix_rank(H @ G) == m
                else:
                    H, R, y, rank = np.zeros((0, n)), np.zeros((0, 0)), np.zeros(0), False
                feed = rank and (strongly_detectable(A, G, H) or fed[i])
                if feed:
                    # textbook Gillijns-De Moor input estimate and the unbiased state update
                    Rt = H @ Pc @ H.T + R
                    F = H @ G
                    S = np.linalg.inv(F.T @ np.linalg.inv(Rt) @ F)
                    d = S @ F.T @ np.linalg.inv(Rt) @ (y - H @ xc)
                    Y = np.linalg.inv(Pc)
                    Yf = Y - Y @ G @ np.linalg.inv(G.T @ Y @ G) @ G.T @ Y
                    Pn = np.linalg.inv(Yf + H.T @ np.linalg.inv(R) @ H)
                    xn = Pn @ (Yf @ xc + H.T @ np.linalg.inv(R) @ y)
                    vn = True
                else:
                    relayed = [j for j in nb if held[j]]
                    if relayed:
                        d, S = fast_ci([dh[j] for j in relayed], [Sh[j] for j in relayed])
                        xs, Ps = xc + G @ d, Pc + G @ S @ G.T
                    else:
                        d, S = np.zeros(m), np.eye(m)
                        xs, Ps = xc, Pc
                    if meas:  # fading factor from the whitened innovation, then the Kalman update in gain form
                        Li = np.linalg.inv(np.linalg.cholesky(R))
                        Cw, nu = Li @ H, Li @ (y - H @ xs)
                        seen = Cw @ np.linalg.pinv(Cw) @ nu  # the part of nu in the range of Cw
                        alpha = max(1.0, (seen @ seen - np.linalg.matrix_rank(Cw)) / np.trace(Cw @ Ps @ Cw.T))
                        Ps = alpha * Ps
                        L = Ps @ H.T @ np.linalg.inv(H @ Ps @ H.T + R)
                        xn, Pn = xs + L @ (y - H @ xs), (np.eye(n) - L @ H) @ Ps
                    else:
                        xn, Pn = xs, Ps
                    vn = bool(relayed)
                new.append((xn, Pn, d, S, vn, feed))
            for i, (xn, Pn, d, S, vn, feed) in enumerate(new):
                x[i], P[i], dh[i], Sh[i], held[i], fed[i] = xn, Pn, d, S, vn, feed
                out["x"][b, k - 1, i], out["P"][b, k - 1, i] = xn, Pn
                out["d"][b, k - 1, i], out["v"][b, k - 1, i] = d, vn
    return out
