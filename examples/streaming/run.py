"""DISKF inside your own loop: each tick your simulator (here a few lines of
numpy) moves a target, makes each agent's measurement and decides who hears
whom; ``diskf_mesh.Network`` turns one tick of that into every agent's
estimate with its covariance, and one ``diskf_mesh.Agent`` per agent does the
same with the messages carried by you, as bytes, as a node per robot would.
At the end the logged tick data go through the batched engine
(``diskf_mesh.estimate``): all three agree bit for bit, or the script exits 1.

    python examples/streaming/run.py [--ticks 120] [--estimator diskf-auto] [--seed 0]

The model, sensors and estimator settings are Scenario 2's (``dynamic``: 4
static and 5 moving agents, links within 120 m); the target, its input, the
noise and the radio are this script's own.
"""
from __future__ import annotations

import argparse
import sys

import numpy as np

import diskf_mesh
from diskf_mesh.data.trace import Trace


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--ticks", type=int, default=120)
    ap.add_argument("--estimator", default="diskf-auto")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()

    scn = diskf_mesh.load_scenario("dynamic")
    K, N = args.ticks, scn.N
    net = diskf_mesh.Network(scn, args.estimator, seed=args.seed, ticks=K)
    nodes = {i: diskf_mesh.Agent(scn, i, args.estimator, seed=args.seed, ticks=K) for i in net.ids}
    rng = np.random.default_rng(args.seed)
    A, G, Q = scn.A, scn.G, scn.Q
    x = scn.x0.copy()
    log = {"y": np.zeros((K, N, 1)), "has": np.zeros((K, N), bool), "links": np.zeros((K, N, N), bool),
           "x": np.zeros((K, 2)), "d": np.zeros((K, 1)),
           "x_hat": np.zeros((K, N, 2)), "P_hat": np.zeros((K, N, 2, 2))}      # what the loop got, tick by tick
    print(f"{args.estimator} on {N} agents, {K} ticks")
    print(f"{'tick':>5}{'error (m)':>11}{'sd (m)':>9}{'input':>8}{'its estimate':>14}")
    for k in range(1, K + 1):
        # your simulator: the target steers (the unknown input), agents see it in their own quadrant
        d = np.array([4.0 * np.sin(k / 15.0)])
        x = A @ x + G @ d + rng.multivariate_normal(np.zeros(2), Q)
        where = scn.positions_at([k])[0]                                   # the agents' positions (N, 2)
        rows = []
        for i, a in enumerate(scn.agents):
            sees = np.all(np.sign(x) == np.sign(where[i]))
            rows.append(a.H @ x + rng.multivariate_normal(np.zeros(1), a.R) if sees else None)
        gap = where[:, None] - where[None]
        radio = np.einsum("ijk,ijk->ij", gap, gap) <= scn.comm_range ** 2     # who hears whom

        est = net.step(rows, links=radio)                                  # the whole network at once

        sent = {i: nodes[i].encode(nodes[i].local(rows[n])) for n, i in enumerate(net.ids)}  # or one node each
        for n, i in enumerate(net.ids):
            heard = {j: sent[j] for m, j in enumerate(net.ids) if radio[n, m] and j != i}
            mine = nodes[i].fuse(heard)
            if not (np.array_equal(mine.x, est.x[n]) and np.array_equal(mine.P, est.P[n])):
                print(f"agent {i}, tick {k}: its own estimate differs from the network's", file=sys.stderr)
                return 1

        log["y"][k - 1] = [r if r is not None else [0.0] for r in rows]
        log["has"][k - 1], log["links"][k - 1] = [r is not None for r in rows], radio
        log["x"][k - 1], log["d"][k - 1] = x, d
        log["x_hat"][k - 1], log["P_hat"][k - 1] = est.x, est.P
        if k % 20 == 0 or k == K:
            err = np.linalg.norm(est.x - x, axis=-1).mean()
            sd = np.sqrt(np.trace(est.P, axis1=-2, axis2=-1)).mean()
            d_hat = est.d[est.d_valid, 0].mean() if est.d_valid.any() else float("nan")
            print(f"{k:>5}{err:>11.2f}{sd:>9.2f}{d[0]:>8.2f}{d_hat:>14.2f}")

    trace = Trace(scn.model(K), scn.sensors(), log["y"][None], log["has"][None], log["links"][None],
                  log["x"][None], log["d"][None], seeds=(args.seed,))
    run = diskf_mesh.estimate(trace, args.estimator, scenario=scn)         # the same data, batched
    same = np.array_equal(run.x[0], log["x_hat"]) and np.array_equal(run.P[0], log["P_hat"])
    print(f"the batched engine on the logged data: {'the same estimates, bit for bit' if same else 'DIFFERENT'}"
          f" (MAE(state) {run.metrics['mae_state']:.2f})")
    return 0 if same else 1


if __name__ == "__main__":
    sys.exit(main())
