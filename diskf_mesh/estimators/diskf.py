"""DISKF, Algorithm 1 of the paper, on top of ``equations``."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from diskf_mesh.core import equations as eq
from diskf_mesh.core.messages import Message, Neighbourhood, Output
from diskf_mesh.core.model import COMPENSATION_FORMS
from diskf_mesh.estimators.base import DEFENCE, Estimator, Setting, State

# DISKF's parameters; diskf-r shares the first four
WINDOW = Setting("window", 5, "observation time window in ticks (None: no window)", kind=int, low=0, optional=True)
RESET = Setting("reset", True, "reset the window counter when input fusion had a valid input")
EPS = Setting("eps", 0.05, "state compensation step (the paper's epsilon = 0.05)", low=0.0)
COMPENSATION = Setting("compensation", "bounded", "gain form of eq. (compensation_state): "
                       + "|".join(COMPENSATION_FORMS), choices=COMPENSATION_FORMS)
HOLD_INPUT = Setting("hold_input", False, "our extension, off by default (the paper's algorithm): when no "
                     "neighbour has an input estimate, predict with the last fused input instead of with none. "
                     "Helps a lasting input seen intermittently; hurts isolated agents whose own estimate is "
                     "poor (see docs/reproduction.md)")


@dataclass(frozen=True)
class HeldState(State):
    """DISKF's state: with ``hold_input``, the last fused input."""

    d_hold: np.ndarray | None = None  # (..., m) last fused input
    held: np.ndarray | None = None    # (...,) whether d_hold holds an estimate


class DISKF(Estimator):
    """DISKF, Algorithm 1 of Wu and Mehta: each agent predicts, updates with
    its own measurement and estimates the unknown input over a window of
    ticks (``local``); it then fuses its neighbours' inputs, predicts with
    the fused input, fuses the neighbours' state information and compensates
    the state towards their predictions (``fuse``). Settings: ``window``,
    ``reset``, ``eps``, ``compensation``, ``hold_input``."""

    name = "diskf"
    label = "DISKF"
    color = "tab:blue"
    settings = (WINDOW, RESET, EPS, COMPENSATION, HOLD_INPUT, DEFENCE)

    def init(self, batch: tuple) -> HeldState:
        s = super().init(batch)
        return HeldState(s.x, s.P, s.since, np.zeros(batch + (self.model.m,)), np.zeros(batch, dtype=bool))

    def local(self, state: HeldState, k: int, y, has):
        """Step 1: prediction, local update, windowed input estimation."""
        loc = self.local_kf(state, k, y, has)
        since = state.since + 1
        allowed = eq.window_allows(since, self.params.window)
        d, S, valid = self.local_input(loc, allowed)
        st = HeldState(state.x, state.P, np.where(has, 0, since), state.d_hold, state.held, Y_pred=loc.Y)
        return st, self.message(loc, d, S, valid)

    def fuse(self, state: State, own: Message, senders: Message, nb: Neighbourhood):
        """Steps 3 and 4: input fusion, state fusion, state compensation."""
        p = self.params
        d_bar, S_bar, has = eq.input_fusion(nb.adj, senders.d, senders.S, senders.d_valid)
        d_hold, held = state.d_hold, state.held
        if p.hold_input:
            # Our extension (off by default): with no input to fuse this tick,
            # predict with the last fused input instead of none. Suits a
            # persistent input (a fault, a step manoeuvre); see HOLD_INPUT.
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
        return HeldState(x_bar, P_bar, since, d_hold, held), Output(x_bar, P_bar, d_bar, has)
