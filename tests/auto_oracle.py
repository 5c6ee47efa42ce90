"""A plain per-agent reference of ``diskf-auto`` (the test oracle), in the
spirit of ``robust_oracle``: explicit loops over seeds, ticks, agents,
neighbours and models; each model's joint (x, d) mean and covariance as one
(n + m)-vector and (n + m) x (n + m) matrix; the stacked H, R, y of the
neighbourhood's measurements in gain form (Joseph) and the likelihood as the
textbook Gaussian density N(y; H x, H P H^T + R); numpy.linalg only, no
code shared with ``equations``, ``input_models`` or ``linalg``.
"""
from __future__ import annotations

import numpy as np
import scipy.linalg

from robust_oracle import _replace, fast_ci, scales

FLOOR = 1e-6


def bank(qp, qs, none=True, walk=True, zero_mean=True):
    lo, hi = min(qp, qs), 100.0 * max(qp, qs)
    mid, rev = np.sqrt(lo * hi), np.exp(-0.1)
    out = [(0.0, 0.0)] if none else []
    out += [(1.0, lo), (1.0, mid), (1.0, hi)] if walk else []
    out += [(0.0, qs), (0.0, hi), (rev, mid), (rev, hi)] if zero_mean else []
    return out


def run_auto(trace, options):
    model, sensors = trace.model, trace.sensors
    B, K, N = trace.has.shape
    n, m = model.n, model.m
    G, Q = model.G, model.Q
    models = bank(*scales(model, sensors), options.none, options.walk, options.zero_mean)
    M = len(models)
    Pi = np.full((M, M), options.switch / (M - 1)) if M > 1 else np.ones((1, 1))
    np.fill_diagonal(Pi, 1.0 - options.switch if M > 1 else 1.0)
    prior = 100.0 * max(q for _, q in models)
    iv, idd = np.arange(n), np.arange(n, n + m)
    Tx = np.block([[np.eye(n), G], [np.zeros((m, n)), np.eye(m)]])
    out = dict(x=np.zeros((B, K, N, n)), P=np.zeros((B, K, N, n, n)), d=np.zeros((B, K, N, m)),
               v=np.zeros((B, K, N), dtype=bool))
    Hs = [sensors.H[i, : sensors.p[i]] for i in range(N)]
    Rs = [sensors.R[i, : sensors.p[i], : sensors.p[i]] for i in range(N)]
    for b in range(B):
        z0 = np.concatenate([model.x0.astype(float), np.zeros(m)])
        Z0 = scipy.linalg.block_diag(model.P0, prior * np.eye(m))
        agents = [dict(x=z0[:n].copy(), P=Z0[:n, :n].copy(), d=np.zeros(m), S=prior * np.eye(m), held=False,
                       mu=np.full(M, 1.0 / M), z=[z0.copy() for _ in range(M)], Z=[Z0.copy() for _ in range(M)])
                  for _ in range(N)]
        links = trace.links[min(b, trace.links.shape[0] - 1)]
        for k in range(1, K + 1):
            A = model.A_at(k)
            pred = [(A @ a["x"], A @ a["P"] @ A.T + Q) for a in agents]
            sent = [(a["d"].copy(), a["S"].copy(), a["held"]) for a in agents]
            sent_mu = [a["mu"].copy() for a in agents]
            new = []
            for i in range(N):
                a = agents[i]
                nb = list(np.flatnonzero(links[k - 1, i]))
                xc, Pc = fast_ci([pred[j][0] for j in nb], [pred[j][1] for j in nb])
                Mt = np.linalg.cholesky(Pc) @ np.linalg.inv(np.linalg.cholesky(pred[i][1]))
                # the neighbourhood's model probabilities: normalised geometric mean of the senders' (own included)
                logs = np.mean([np.log(np.maximum(sent_mu[s], FLOOR)) for s in nb], axis=0)
                mu0 = np.exp(logs - logs.max())
                mu0 = mu0 / mu0.sum()
                c = np.array([sum(Pi[s, j] * mu0[s] for s in range(M)) for j in range(M)])
                meas = [j for j in nb if trace.has[b, k - 1, j]]
                zs, Zs, ll, relayed = [], [], np.zeros(M), False
                for j, (rho, q) in enumerate(models):
                    wts = [Pi[s, j] * mu0[s] / c[j] for s in range(M)]
                    zm = sum(w * a["z"][s] for w, s in zip(wts, range(M)))
                    within = sum(w * a["Z"][s] for w, s in zip(wts, range(M)))
                    spread = sum(w * np.outer(a["z"][s] - zm, a["z"][s] - zm) for w, s in zip(wts, range(M)))
                    tw, ts = np.trace(within), np.trace(spread)
                    Zm = within + (spread * (tw / ts) if ts > tw else spread)
                    Tv = scipy.linalg.block_diag(A, rho * np.eye(m))
                    w = Tv @ zm
                    W = Tv @ Zm @ Tv.T + scipy.linalg.block_diag(Q, q * np.eye(m))
                    w, W = _replace(w, W, iv, xc + Mt @ (w[iv] - pred[i][0]), Mt @ W[np.ix_(iv, iv)] @ Mt.T)
                    others = [s for s in nb if s != i and sent[s][2]]
                    if rho > 0 and others:
                        dn, Sn = fast_ci([rho * sent[s][0] for s in others],
                                         [rho * rho * sent[s][1] + q * np.eye(m) for s in others])
                        dr, Sr = fast_ci([w[idd], dn], [W[np.ix_(idd, idd)], Sn])
                        w, W = _replace(w, W, idd, dr, Sr)
                        relayed = True
                    za, Pa = Tx @ w, Tx @ W @ Tx.T
                    if meas:
                        H = np.hstack([np.vstack([Hs[s] for s in meas]), np.zeros((sum(sensors.p[s] for s in meas), m))])
                        R = scipy.linalg.block_diag(*[Rs[s] for s in meas])
                        y = np.concatenate([trace.y[b, k - 1, s, : sensors.p[s]] for s in meas])
                        Sg = H @ Pa @ H.T + R
                        r = y - H @ za
                        ll[j] = -0.5 * (r @ np.linalg.solve(Sg, r) + np.linalg.slogdet(Sg)[1])
                        L = Pa @ H.T @ np.linalg.inv(Sg)
                        IL = np.eye(n + m) - L @ H
                        za, Pa = za + L @ r, IL @ Pa @ IL.T + L @ R @ L.T
                    zs.append(za)
                    Zs.append(Pa)
                mu = c * np.exp(ll - ll.max())
                mu = np.maximum(mu / mu.sum(), FLOOR)
                mu = mu / mu.sum()
                z = sum(mu[j] * zs[j] for j in range(M))
                Z = sum(mu[j] * (Zs[j] + np.outer(zs[j] - z, zs[j] - z)) for j in range(M))
                held = a["held"] or bool(meas) or relayed
                new.append(dict(x=z[:n], P=Z[:n, :n], d=z[n:], S=Z[n:, n:], held=held, mu=mu, z=zs, Z=Zs))
            agents = new
            for i, a in enumerate(agents):
                out["x"][b, k - 1, i], out["P"][b, k - 1, i] = a["x"], a["P"]
                out["d"][b, k - 1, i], out["v"][b, k - 1, i] = a["d"], a["held"]
    return out
