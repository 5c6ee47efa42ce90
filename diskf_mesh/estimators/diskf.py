"""DISKF, Algorithm 1 of the paper, on top of ``equations``."""
from __future__ import annotations

import numpy as np

from diskf_mesh.core import equations as eq
from diskf_mesh.core.messages import Message, Neighbourhood, Output
from diskf_mesh.estimators.base import Algorithm, State


class DISKF(Algorithm):
    name = "diskf"
    label = "DISKF"

    def local(self, state: State, k: int, y, has):
        """Step 1: prediction, local update, windowed input estimation."""
        loc = self.local_kf(state, k, y, has)
        since = state.since + 1
        allowed = eq.window_allows(since, self.params.window)
        d, S, valid = self.local_input(loc, allowed)
        return self.for_fuse(state, loc, np.where(has, 0, since)), self.message(loc, d, S, valid)

    def fuse(self, state: State, own: Message, senders: Message, nb: Neighbourhood):
        """Steps 3 and 4: input fusion, state fusion, state compensation."""
        p = self.params
        d_bar, S_bar, has = eq.input_fusion(nb.adj, senders.d, senders.S, senders.d_valid)
        d_hold, held = state.d_hold, state.held
        if p.hold_input:
            # Our extension (off by default): with no input to fuse this tick,
            # predict with the last fused input instead of none. Suits a
            # persistent input (a fault, a step manoeuvre); see Params.
            d_hold = np.where(has[..., None], d_bar, d_hold)
            held = has | held
            x_star = eq.input_prediction(own.x_pred, self.model.G, d_hold, held)
        else:
            x_star = eq.input_prediction(own.x_pred, self.model.G, d_bar)  # d_bar = 0 where not has
        Ystar, Yp, Yu = self.fusion_inverses(state, own, senders)
        dy, dY = eq.information_contribution(senders.x_pred, Yp, senders.x_upd, Yu)
        x_bar, P_bar = eq.state_fusion(nb.adj, x_star, Ystar, dy, dY)
        if p.compensation != "none" and p.eps != 0.0:
            gain = eq.compensation_gain(P_bar, p.compensation, p.eps, nb.n_neighbours)
            x_bar = eq.compensation_state(nb.adj, x_bar, gain, own.x_pred, senders.x_pred, p.eps)
        since = np.where(has, 0, state.since) if p.reset else state.since
        return State(x_bar, P_bar, since, d_hold, held), Output(x_bar, P_bar, d_bar, has)
