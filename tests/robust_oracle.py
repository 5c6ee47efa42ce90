"""A plain per-agent reference of ``diskf-r`` (the test oracle for the
robust variant), in the spirit of ``engine/oracle.py``: explicit loops
over seeds, ticks, agents and neighbours, textbook formulas on stacked H, R,
y (never the messages' information form) and on the joint (x, d) covariance
matrix as one (n + m) x (n + m) array, numpy.linalg / scipy only, and no
code shared with ``equations``, ``rkf`` or ``linalg``. The invariant zeros
come from the Rosenbrock pencil (scipy's generalized eigenvalues), not from
the zero dynamics + Hautus test of ``equations.strongly_detectable``.

``run_robust`` implements the defaults of ``model.RobustOptions`` (the
persistent input, every default switch as shipped): the joint Kalman filter
of (x, d) with a random-walk input, the neighbourhood's CI prior and relayed
inputs replacing the agent's own marginals (conditionals kept), the Kalman
update in gain form on the stacked sensors.
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


def _replace(mean, cov, idx_a, a_new, Paa_new):
    """The joint Gaussian (mean, cov) with the marginal of the components
    ``idx_a`` replaced, the conditional of the others kept (textbook
    regression on the full matrix)."""
    idx_b = np.setdiff1d(np.arange(len(mean)), idx_a)
    Paa, Pba = cov[np.ix_(idx_a, idx_a)], cov[np.ix_(idx_b, idx_a)]
    K = Pba @ np.linalg.inv(Paa)
    out, C = mean.copy(), cov.copy()
    out[idx_a] = a_new
    out[idx_b] = mean[idx_b] + K @ (a_new - mean[idx_a])
    C[np.ix_(idx_a, idx_a)] = Paa_new
    C[np.ix_(idx_b, idx_a)] = K @ Paa_new
    C[np.ix_(idx_a, idx_b)] = (K @ Paa_new).T
    C[np.ix_(idx_b, idx_b)] = cov[np.ix_(idx_b, idx_b)] - K @ Paa @ K.T + K @ Paa_new @ K.T
    return out, C


def scales(model, sensors):
    """(q_process, q_sensor) written out: tr(G^+ Q G^+T) / m and the median
    over sensors of tr(F^+ R F^+T) / m, F = H G."""
    m = model.m
    Gp = np.linalg.pinv(model.G)
    qp = np.trace(Gp @ model.Q @ Gp.T) / m
    qs = []
    for i in range(sensors.N):
        F = sensors.H[i, : sensors.p[i]] @ model.G
        if np.any(F != 0):
            Fp = np.linalg.pinv(F)
            qs.append(np.trace(Fp @ sensors.R[i, : sensors.p[i], : sensors.p[i]] @ Fp.T) / m)
    return qp, (np.median(qs) if qs else qp)


def run_robust(trace, options):
    """diskf-r with the default switches; ``options`` gives the input model
    (walk, mean-reverting with input_rho, none), input_walk and input_prior
    (None: sqrt(q_process q_sensor) and 1e4 max(q_process, q_sensor))."""
    model, sensors = trace.model, trace.sensors
    B, K, N = trace.has.shape
    n, m = model.n, model.m
    G = model.G
    qp, qs = scales(model, sensors)
    rho = {"walk": 1.0, "mean-reverting": options.input_rho, "none": 0.0}[options.input_model]
    q = 0.0 if options.input_model == "none" else (np.sqrt(qp * qs) if options.input_walk is None else options.input_walk)
    prior = 1e4 * max(qp, qs) if options.input_prior is None else options.input_prior
    Qd = q * np.eye(m)
    iv, idd = np.arange(n), np.arange(n, n + m)
    out = dict(x=np.zeros((B, K, N, n)), P=np.zeros((B, K, N, n, n)), d=np.zeros((B, K, N, m)),
               v=np.zeros((B, K, N), dtype=bool))
    Hs = [sensors.H[i, : sensors.p[i]] for i in range(N)]
    Rs = [sensors.R[i, : sensors.p[i], : sensors.p[i]] for i in range(N)]
    for b in range(B):
        z = [np.concatenate([model.x0.astype(float), np.zeros(m)]) for _ in range(N)]
        Pi = [scipy.linalg.block_diag(model.P0, prior * np.eye(m)) for _ in range(N)]
        held = [False] * N
        links = trace.links[min(b, trace.links.shape[0] - 1)]
        for k in range(1, K + 1):
            A = model.A_at(k)
            Tv = scipy.linalg.block_diag(A, rho * np.eye(m))      # (x_{k-1}, d_{k-2}) -> (v_k, d_{k-1})
            Tx = np.block([[np.eye(n), G], [np.zeros((m, n)), np.eye(m)]])  # (v, d) -> (x, d)
            pred = [(A @ z[i][:n], A @ Pi[i][:n, :n] @ A.T + model.Q) for i in range(N)]
            relay = [(rho * z[i][n:], rho * rho * Pi[i][n:, n:] + Qd) for i in range(N)]
            new = []
            for i in range(N):
                nb = list(np.flatnonzero(links[k - 1, i]))
                w = Tv @ z[i]
                W = Tv @ Pi[i] @ Tv.T + scipy.linalg.block_diag(model.Q, Qd)
                xc, Pc = fast_ci([pred[j][0] for j in nb], [pred[j][1] for j in nb])
                w, W = _replace(w, W, iv, xc, Pc)
                relayed = [j for j in nb if held[j]] if rho > 0 else []
                if relayed:
                    dr, Sr = fast_ci([relay[j][0] for j in relayed], [relay[j][1] for j in relayed])
                    w, W = _replace(w, W, idd, dr, Sr)
                za, Pa = Tx @ w, Tx @ W @ Tx.T
                meas = [j for j in nb if trace.has[b, k - 1, j]]
                if meas:
                    H = np.hstack([np.vstack([Hs[j] for j in meas]), np.zeros((sum(sensors.p[j] for j in meas), m))])
                    R = scipy.linalg.block_diag(*[Rs[j] for j in meas])
                    y = np.concatenate([trace.y[b, k - 1, j, : sensors.p[j]] for j in meas])
                    L = Pa @ H.T @ np.linalg.inv(H @ Pa @ H.T + R)
                    IL = np.eye(n + m) - L @ H  # Joseph form: well conditioned with the wide input prior
                    za, Pa = za + L @ (y - H @ za), IL @ Pa @ IL.T + L @ R @ L.T
                new.append((za, Pa, held[i] or bool(meas) or bool(relayed)))
            for i, (za, Pa, h) in enumerate(new):
                z[i], Pi[i], held[i] = za, Pa, h
                out["x"][b, k - 1, i], out["P"][b, k - 1, i] = za[:n], Pa[:n, :n]
                out["d"][b, k - 1, i], out["v"][b, k - 1, i] = za[n:], h and options.input_model != "none"
    return out
