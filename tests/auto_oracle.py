"""A plain per-agent reference of ``diskf-auto`` (the test oracle), in the
spirit of ``robust_oracle``: explicit loops over seeds, ticks, agents,
neighbours and models; each model's joint (x, d_{k-1}, d_{k-2}) mean and
covariance as one (n + 2m)-vector and matrix, the input a second-order
recursion d_{k-1} = a1 d_{k-2} + a2 d_{k-3} + eta written out from its
period and radius; the stacked H, R, y of the
neighbourhood's measurements in gain form (Joseph) and the likelihood as the
textbook Gaussian density N(y; H x, H P H^T + R); numpy.linalg only, no
code shared with ``equations``, ``input_models`` or ``linalg``.
"""
from __future__ import annotations

import numpy as np
import scipy.linalg
import scipy.stats

from robust_oracle import _replace, fast_ci, scales

FLOOR = 1e-6
PRUNE = 1e-3
BLIND = 1e-3


def bank(qp, qs, none=True, walk=True, zero_mean=True, oscillating=True):
    """[(a1, a2, q)]: d_{k-1} = a1 d_{k-2} + a2 d_{k-3} + eta, eta ~ N(0, q)."""
    lo, hi = min(qp, qs), 100.0 * max(qp, qs)
    mid, rev = np.sqrt(lo * hi), np.exp(-0.1)
    out = [(0.0, 0.0, 0.0)] if none else []
    out += [(1.0, 0.0, lo), (1.0, 0.0, mid), (1.0, 0.0, hi)] if walk else []
    out += [(0.0, 0.0, qs), (0.0, 0.0, hi), (rev, 0.0, mid), (rev, 0.0, hi)] if zero_mean else []
    r = 0.95
    size = mid / (1.0 - rev ** 2)  # every oscillating model: the mean-reverting model's stationary variance
    for k in range(13) if oscillating else ():
        period = 4.0 * 2.0 ** (k / 4)  # poles r exp(+-2 pi i / period)
        a1, a2 = 2 * r * np.cos(2 * np.pi / period), -r * r
        # the stationary variance per unit noise, from the Yule-Walker equations of the AR(2) recursion
        g0 = np.linalg.solve([[1.0, -a1, -a2], [-a1, 1.0 - a2, 0.0], [-a2, -a1, 1.0]], [1.0, 0.0, 0.0])[0]
        out.append((a1, a2, size / g0))
    return out


def noise_scale(theta, last, x, P, H, R, y, step):
    """One measured tick of the measurement noise scale r = exp(theta)
    (``core.noise``) written out on the sensor's own rows: with the
    innovation e = y - H x, S = H P H^T + r R and ``last`` = (e_l, S_l,
    seen) of the last measured tick, theta moves by step * sqrt(tr(S^-1 r R)
    / p) up where (e - e_l)^T (S + S_l)^-1 (e - e_l) lies above the
    chi-square median of p degrees of freedom, down where below, within
    [log 0.01, log 1000], if an earlier tick was measured. Returns (theta,
    (e, S, True))."""
    e_l, S_l, seen = last
    r = np.exp(theta)
    S = H @ P @ H.T + r * R
    e = y - H @ x
    nis = (e - e_l) @ np.linalg.solve(S + S_l, e - e_l)
    share = min(1.0, r * np.trace(np.linalg.solve(S, R)) / len(y))
    sign = 1.0 if nis > scipy.stats.chi2.median(len(y)) else -1.0
    if seen:
        theta = float(np.clip(theta + step * np.sqrt(share) * sign, np.log(0.01), np.log(1e3)))
    return theta, (e, S, True)


def run_auto(trace, options, noise_step=0.2):
    model, sensors = trace.model, trace.sensors
    B, K, N = trace.has.shape
    n, m = model.n, model.m
    G, Q = model.G, model.Q
    models = bank(*scales(model, sensors), options.none, options.walk, options.zero_mean, options.oscillating)
    M = len(models)
    # one bank per input channel: filter j of bank c moves channel c by model j, every other channel by its
    # bank's most probable model; a bank the measurements told nothing follows the informed banks
    NB = m if getattr(options, "per_channel", True) and m > 1 else 1
    # before any evidence the oscillating models share one model's probability; a switch moves by those shares
    share = np.array([1.0 / sum(a2 != 0 for _, a2, _ in models) if a2 != 0 else 1.0 for _, a2, _ in models])
    mu_first = share / share.sum()
    Pi = np.ones((1, 1)) if M == 1 else np.array(
        [[1.0 - options.switch if i == j else options.switch * mu_first[j] / (1.0 - mu_first[i]) for j in range(M)]
         for i in range(M)])
    # a random walk also moves to each walk of a smaller scale with options.hand_down, each row renormalised
    walks = [i for i, (a1, a2, _) in enumerate(models) if a1 == 1.0 and a2 == 0.0]
    if M > 1 and options.hand_down > 0:
        for i in walks:
            for j in walks:
                if models[j][2] < models[i][2]:
                    Pi[i, j] += options.hand_down
        Pi = Pi / Pi.sum(axis=1, keepdims=True)
    prior = 100.0 * max(q for _, _, q in models)
    iv, idd = np.arange(n), np.arange(n, n + m)
    Tx = np.eye(n + 2 * m)
    Tx[:n, n:n + m] = G
    out = dict(x=np.zeros((B, K, N, n)), P=np.zeros((B, K, N, n, n)), d=np.zeros((B, K, N, m)),
               v=np.zeros((B, K, N), dtype=bool))
    Hs = [sensors.H[i, : sensors.p[i]] for i in range(N)]
    Rs = [sensors.R[i, : sensors.p[i], : sensors.p[i]] for i in range(N)]
    for b in range(B):
        z0 = np.concatenate([model.x0.astype(float), np.zeros(2 * m)])
        Z0 = scipy.linalg.block_diag(model.P0, prior * np.eye(2 * m))
        agents = [dict(x=z0[:n].copy(), P=Z0[:n, :n].copy(), d=np.zeros(m), S=prior * np.eye(m), held=False,
                       mu=np.tile(mu_first, (NB, 1)), z=[z0.copy() for _ in range(NB * M)],
                       Z=[Z0.copy() for _ in range(NB * M)],
                       theta=0.0, last=(np.zeros(sensors.p[i]), np.eye(sensors.p[i]), False))
                  for i in range(N)]
        links = trace.links[min(b, trace.links.shape[0] - 1)]
        for k in range(1, K + 1):
            A = model.A_at(k)
            pred = [(A @ a["x"], A @ a["P"] @ A.T + Q) for a in agents]
            # each agent's weight 1 / r of its own R, learned by its last measured tick
            scale = np.array([np.exp(a["theta"]) if options.noise else 1.0 for a in agents])
            sent = [(a["d"].copy(), a["S"].copy(), a["held"]) for a in agents]
            sent_mu = [a["mu"].mean(axis=0) for a in agents]  # the banks' mean
            new = []
            for i in range(N):
                a = agents[i]
                nb = list(np.flatnonzero(links[k - 1, i]))
                xc, Pc = fast_ci([pred[j][0] for j in nb], [pred[j][1] for j in nb])
                Mt = np.linalg.cholesky(Pc) @ np.linalg.inv(np.linalg.cholesky(pred[i][1]))
                meas = [j for j in nb if trace.has[b, k - 1, j]]
                if meas:  # the neighbourhood measured: the agent's own model probabilities
                    mu0 = a["mu"]
                else:  # normalised geometric mean of the senders' (own included), for every bank
                    logs = np.mean([np.log(np.maximum(sent_mu[s], FLOOR)) for s in nb], axis=0)
                    mu0 = np.exp(logs - logs.max())
                    mu0 = np.tile(mu0 / mu0.sum(), (NB, 1))
                top = [int(np.argmax(mu0[cb])) for cb in range(NB)]
                c = np.array([[sum(Pi[s, j] * mu0[cb, s] for s in range(M)) for j in range(M)] for cb in range(NB)])
                zs, Zs, ll, relayed, priors = [], [], np.zeros((NB, M)), False, []
                for cb, (j, (a1, a2, q)) in ((cb, jm) for cb in range(NB) for jm in enumerate(models)):
                    wts = [Pi[s, j] * mu0[cb, s] / c[cb, j] for s in range(M)]
                    kept = [w if w >= PRUNE else 0.0 for w in wts]  # small weights dropped, the column renormalised
                    total = sum(kept)
                    wts = [w / total for w in kept]
                    zm = sum(w * a["z"][cb * M + s] for w, s in zip(wts, range(M)))
                    within = sum(w * a["Z"][cb * M + s] for w, s in zip(wts, range(M)))
                    spread = sum(w * np.outer(a["z"][cb * M + s] - zm, a["z"][cb * M + s] - zm)
                                 for w, s in zip(wts, range(M)))
                    tw, ts = np.trace(within), np.trace(spread)
                    Zm = within + (spread * (tw / ts) if ts > tw else spread)
                    # each channel's model: j for this bank's channel, the most probable for the others
                    per = [models[j] if NB == 1 or ch == cb else models[top[ch]] for ch in range(m)]
                    F = np.block([[np.diag([p[0] for p in per]), np.diag([p[1] for p in per])],
                                  [np.eye(m), np.zeros((m, m))]])
                    Tv = scipy.linalg.block_diag(A, F)
                    w = Tv @ zm
                    W = Tv @ Zm @ Tv.T + scipy.linalg.block_diag(Q, np.diag([p[2] for p in per]), np.zeros((m, m)))
                    w, W = _replace(w, W, iv, xc + Mt @ (w[iv] - pred[i][0]), Mt @ W[np.ix_(iv, iv)] @ Mt.T)
                    others = [s for s in nb if s != i and sent[s][2]]
                    if NB == 1 and a2 == 0 and a1 > 0 and others:
                        dn, Sn = fast_ci([a1 * sent[s][0] for s in others],
                                         [a1 * a1 * sent[s][1] + q * np.eye(m) for s in others])
                        dr, Sr = fast_ci([w[idd], dn], [W[np.ix_(idd, idd)], Sn])
                        w, W = _replace(w, W, idd, dr, Sr)
                        relayed = True
                    elif NB > 1 and a2 == 0 and a1 > 0 and others:  # this bank's channel alone
                        ic = np.array([n + cb])
                        dn, Sn = fast_ci([a1 * sent[s][0][cb:cb + 1] for s in others],
                                         [a1 * a1 * sent[s][1][cb:cb + 1, cb:cb + 1] + q * np.eye(1) for s in others])
                        dr, Sr = fast_ci([w[ic], dn], [W[np.ix_(ic, ic)], Sn])
                        w, W = _replace(w, W, ic, dr, Sr)
                        relayed = True
                    za, Pa = Tx @ w, Tx @ W @ Tx.T
                    priors.append(za[:n])
                    if meas:
                        H = np.hstack([np.vstack([Hs[s] for s in meas]),
                                       np.zeros((sum(sensors.p[s] for s in meas), 2 * m))])
                        R = scipy.linalg.block_diag(*[scale[s] * Rs[s] for s in meas])
                        y = np.concatenate([trace.y[b, k - 1, s, : sensors.p[s]] for s in meas])
                        Sg = H @ Pa @ H.T + R
                        r = y - H @ za
                        ll[cb, j] = -0.5 * (r @ np.linalg.solve(Sg, r) + np.linalg.slogdet(Sg)[1])
                        L = Pa @ H.T @ np.linalg.inv(Sg)
                        IL = np.eye(n + 2 * m) - L @ H
                        za, Pa = za + L @ r, IL @ Pa @ IL.T + L @ R @ L.T
                    zs.append(za)
                    Zs.append(Pa)
                mu = c * np.exp(ll - ll.max(axis=1, keepdims=True))
                mu = np.maximum(mu / mu.sum(axis=1, keepdims=True), FLOOR)
                mu = mu / mu.sum(axis=1, keepdims=True)
                told = ll.max(axis=1) - ll.min(axis=1) >= BLIND
                if NB > 1 and told.any() and not told.all():
                    mu[~told] = mu[told].mean(axis=0)
                kept = np.where(mu < PRUNE, 0.0, mu)  # the state's output: the models of probability PRUNE or more
                kept = (kept / kept.sum(axis=1, keepdims=True)).reshape(-1) / NB
                every = mu.reshape(-1) / NB
                z = sum(kept[f] * zs[f] for f in range(NB * M))
                Z = sum(kept[f] * (Zs[f] + np.outer(zs[f] - z, zs[f] - z)) for f in range(NB * M))
                zd = sum(every[f] * zs[f] for f in range(NB * M))  # the input's: every model
                Zd = sum(every[f] * (Zs[f] + np.outer(zs[f] - zd, zs[f] - zd)) for f in range(NB * M))
                held = a["held"] or bool(meas) or relayed
                theta, last = a["theta"], a["last"]
                if options.noise and trace.has[b, k - 1, i]:  # scored against the bank's predicted mean
                    x_m = sum(cf * p for cf, p in zip(c.reshape(-1) / NB, priors))
                    theta, last = noise_scale(theta, last, x_m, pred[i][1], Hs[i], Rs[i],
                                              trace.y[b, k - 1, i, : sensors.p[i]], noise_step)
                new.append(dict(x=z[:n], P=Z[:n, :n], d=zd[n:n + m], S=Zd[n:n + m, n:n + m], held=held, mu=mu, z=zs,
                                Z=Zs, theta=theta, last=last))
            agents = new
            for i, a in enumerate(agents):
                out["x"][b, k - 1, i], out["P"][b, k - 1, i] = a["x"], a["P"]
                out["d"][b, k - 1, i], out["v"][b, k - 1, i] = a["d"], a["held"]
    return out
