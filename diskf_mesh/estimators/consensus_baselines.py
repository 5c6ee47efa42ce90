"""Consensus, diffusion and gossip Kalman filters (no input in the state).

All three exchange, in one message, the prior x^_j and what the sender's own
measurement adds in information form (derived from x^, P^, x~, P~). For
comparison only they report the sender's local RKF input estimate; it never
enters their state (as in the paper's comparison).

KCF    (Olfati-Saber, Kalman-consensus filter, Algorithm 3 of the 2007 CDC
        paper): M_i = (P^_i^-1 + sum_j U_j)^-1,
        x_i = x^_i + M_i (sum_j u_j - sum_j U_j x^_i)
              + gamma M_i sum_j (x^_j - x^_i),  gamma = eps / (1 + ||M_i||_F)
DiffKF (Cattivelli & Sayed 2010, combine-then-adapt with measurement
        exchange, one round): x'_i = mean_j x^_j, then the information
        update of x'_i with sum_j U_j, sum_j u_j.
GDKF   (gossip): DiffKF restricted to the agent and ONE neighbour drawn at
        random every tick (seeded per agent, see ``gossip_draws``).
"""
from __future__ import annotations

import numpy as np

from diskf_mesh.core import equations as eq
from diskf_mesh.core.linalg import nbr_sum
from diskf_mesh.core.messages import Message, Neighbourhood, Output
from diskf_mesh.estimators.base import Estimator, Setting, State, uniform_weights

CONSENSUS_EPS = Setting("consensus_eps", 0.1, "KCF consensus step (Olfati-Saber's epsilon)", low=0.0)


class _Consensus(Estimator):
    def local(self, state: State, k: int, y, has):
        loc = self.local_kf(state, k, y, has)
        d, S, valid = self.local_input(loc)
        return self.for_fuse(state, loc), self.message(loc, d, S, valid)


class KCF(_Consensus):
    """KCF, Olfati-Saber's Kalman-consensus filter (no input in the state;
    the module's docstring has its update)."""

    name = "kcf"
    label = "KCF"
    color = "tab:red"
    settings = (CONSENSUS_EPS,)

    @classmethod
    def warning(cls, params, links):
        return consensus_step_problem(params.consensus_eps, links)

    def fuse(self, state: State, own: Message, senders: Message, nb: Neighbourhood):
        Ystar, Yp, Yu = self.fusion_inverses(state, own, senders)
        dy, dY = eq.information_contribution(senders.x_pred, Yp, senders.x_upd, Yu)
        x, M = eq.state_fusion(nb.adj, own.x_pred, Ystar, dy, dY)
        gain = eq.compensation_gain(M, "normalized")
        x = eq.compensation_state(nb.adj, x, gain, own.x_pred, senders.x_pred, self.params.consensus_eps)
        return State(x, M, state.since), Output(x, M, own.d, own.d_valid)


def diffusion_update(adj, own: Message, senders: Message, inverses):
    """Combine the neighbours' priors with equal weights, then adapt with
    their measurement information. ``inverses``: ``fusion_inverses`` (P^*^-1,
    P^_j^-1, P~_j^-1)."""
    Ystar, Yp, Yu = inverses
    x_comb = nbr_sum(uniform_weights(adj), senders.x_pred, 1)
    dy, dY = eq.information_contribution(senders.x_pred, Yp, senders.x_upd, Yu)
    return eq.state_fusion(adj, x_comb, Ystar, dy, dY)


def consensus_step_problem(eps: float, links: np.ndarray) -> str | None:
    """Why KCF's consensus step may diverge on ``links``, or None.

    Olfati-Saber's consensus term converges for eps x (largest degree) < 1:
    KCF's step gamma M_i is below eps in norm, so the sum over a receiver's
    neighbours moves at most eps x degree of the way. ``links`` (..., N, N)
    bool, self-links included or not."""
    deg = int((links.sum(axis=-1) - np.diagonal(links, axis1=-2, axis2=-1)).max(initial=0))
    if deg and eps * deg >= 1.0:
        return (f"KCF: consensus_eps = {eps:g} with up to {deg} neighbours (eps x max degree = {eps * deg:g}, "
                f"not below 1): the consensus step may diverge; set [estimator] consensus_eps below {1 / deg:.3g}")
    return None


class DiffKF(_Consensus):
    """DiffKF, Cattivelli and Sayed's diffusion Kalman filter, combine then
    adapt, one round (no input in the state)."""

    name = "diffkf"
    label = "DiffKF"
    color = "tab:purple"

    def fuse(self, state: State, own: Message, senders: Message, nb: Neighbourhood):
        x, P = diffusion_update(nb.adj, own, senders, self.fusion_inverses(state, own, senders))
        return State(x, P, state.since), Output(x, P, own.d, own.d_valid)


def gossip_draws(seed: int, agent_ids, steps: int) -> np.ndarray:
    """One uniform draw per agent and tick, (N, steps).

    Each agent has its own stream, seeded by (run seed, agent id), so an agent
    process reproduces exactly what the in-process engine draws for it.
    """
    return np.stack([np.random.default_rng([int(seed), int(a), 0x6055]).random(steps) for a in agent_ids])


def gossip_adjacency(adj, self_mask, u):
    """Keep self plus the floor(u * deg)-th neighbour (senders in id order)."""
    cand = (adj > 0) & ~self_mask
    deg = cand.sum(axis=-1)
    idx = np.minimum(np.floor(u * deg), np.maximum(deg - 1, 0)).astype(np.int64)
    rank = np.cumsum(cand, axis=-1) - 1
    pick = cand & (rank == idx[..., None])
    return (self_mask | pick).astype(float)


class GDKF(_Consensus):
    """GDKF, gossip: DiffKF with the agent and one neighbour drawn at random
    every tick (seeded per agent)."""

    name = "gdkf"
    label = "GDKF"
    color = "tab:cyan"

    def draws(self, seed, agent_ids, steps):
        return gossip_draws(seed, agent_ids, steps)

    def fuse(self, state: State, own: Message, senders: Message, nb: Neighbourhood):
        adj = gossip_adjacency(nb.adj, nb.self_mask, nb.draws)
        x, P = diffusion_update(adj, own, senders, self.fusion_inverses(state, own, senders))
        return State(x, P, state.since), Output(x, P, own.d, own.d_valid)
