"""Baselines built on the recursive Kalman filter of Gillijns & De Moor.

C-DRKF: the neighbourhood-centralised RKF (Liu et al. 2018): agent i runs the
        RKF on the stacked H, R, y of everyone in N_i. Stacking is exact in
        information form: the neighbourhood's H^T R^-1 H and H^T R^-1 y are the
        sums of the neighbours' own terms, which each neighbour's message
        carries as (P~^-1 - P^^-1, P~^-1 x~ - P^^-1 x^). No H, R or y travels.
L-DRKF: local RKF (input from the agent's own measurement only), then one
        round of state consensus: the equal-weight average of the
        neighbourhood's RKF estimates (Peng et al. 2023).
"""
from __future__ import annotations

from diskf_mesh.core import equations as eq
from diskf_mesh.core.linalg import inv_spd, nbr_sum
from diskf_mesh.core.messages import Message, Neighbourhood, Output
from diskf_mesh.core.rkf import rkf_update
from diskf_mesh.estimators.base import Estimator, State, uniform_weights


class CDRKF(Estimator):
    """C-DRKF (Liu et al. 2018): each agent runs the recursive Kalman filter
    of Gillijns and De Moor on its whole neighbourhood's measurement
    information, stacked in information form."""

    name = "cdrkf"
    label = "C-DRKF"
    color = "tab:orange"

    def local(self, state: State, k: int, y, has):
        loc = self.local_kf(state, k, y, has)
        d, S, valid = self.local_input(loc)
        return self.for_fuse(state, loc), self.message(loc, d, S, valid)

    def fuse(self, state: State, own: Message, senders: Message, nb: Neighbourhood):
        Y, Yp, Yu = self.fusion_inverses(state, own, senders)
        dy, dY = eq.information_contribution(senders.x_pred, Yp, senders.x_upd, Yu)
        U = nbr_sum(nb.adj, dY, 2)
        u = nbr_sum(nb.adj, dy, 1)
        G = self.model.G
        d, _, valid = eq.input_estimate(own.x_pred, Y, inv_spd(Y + U), U, u, G)
        x, P = rkf_update(own.x_pred, Y, U, u, G, valid)
        return State(x, P, state.since), Output(x, P, d, valid)


class LDRKF(Estimator):
    """L-DRKF (Peng et al. 2023): a local recursive Kalman filter on the
    agent's own measurement, then one round of equal-weight state consensus
    over the neighbourhood."""

    name = "ldrkf"
    label = "L-DRKF"
    color = "tab:green"
    information_check = False  # its x~, P~ is the RKF estimate, not an information update of x^, P^

    def local(self, state: State, k: int, y, has):
        loc = self.local_kf(state, k, y, has)
        d, S, valid = self.local_input(loc)
        x, P = rkf_update(loc.x_pred, loc.Y, loc.U, loc.u, self.model.G, valid)
        return state, self.message(loc, d, S, valid, x_upd=x, P_upd=P)

    def fuse(self, state: State, own: Message, senders: Message, nb: Neighbourhood):
        x = nbr_sum(uniform_weights(nb.adj), senders.x_upd, 1)
        P = own.P_upd
        return State(x, P, state.since), Output(x, P, own.d, own.d_valid)
