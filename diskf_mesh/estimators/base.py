"""What every estimator shares: state, prediction and the local step.

An algorithm is two pure functions per tick, split at the single exchange
round (Algorithm 1, step 2):

    local(state, k, y, has)          -> (state, Message)   before sending
    fuse(state, own, senders, nbhd)  -> (state, Output)    after receiving

Arrays carry leading batch axes (seeds, agents). The in-process engine calls
them on every agent at once; an agent process calls them on a batch of one,
with the messages it actually received as ``senders``.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from diskf_mesh.core import equations as eq
from diskf_mesh.core.linalg import inv_spd, inv_spd_each
from diskf_mesh.core.messages import Message, Neighbourhood
from diskf_mesh.core.model import LinearModel, Params, Sensors


@dataclass(frozen=True)
class State:
    x: np.ndarray      # (..., n)   x_bar_{k|k}, the fused estimate
    P: np.ndarray      # (..., n, n)
    since: np.ndarray  # (...,) ticks since the observation window was refreshed
    d_hold: np.ndarray | None = None  # (..., m) last fused input (DISKF, hold_input)
    held: np.ndarray | None = None    # (...,) whether d_hold holds an estimate
    # Set by ``local`` for the ``fuse`` of the same tick, which then need not
    # invert the agent's own P^ again: P^^-1 (None otherwise).
    Y_pred: np.ndarray | None = None


@dataclass(frozen=True)
class Local:
    """Quantities of the local step, shared by all algorithms."""

    x_pred: np.ndarray
    P_pred: np.ndarray
    U: np.ndarray
    u: np.ndarray
    x_upd: np.ndarray
    P_upd: np.ndarray
    Y: np.ndarray   # P^^-1, computed once for the whole tick
    Ji: np.ndarray  # (P^^-1 + U)^-1, P~ before the "no measurement" mask


class Algorithm:
    """Base class; subclasses set ``name`` and implement ``local``/``fuse``."""

    name = "base"
    label = "base"

    def __init__(self, model: LinearModel, sensors: Sensors, params: Params | None = None):
        self.model = model
        self.sensors = sensors
        self.params = params or Params()
        self.sensor_info = eq.sensor_information(sensors.H, sensors.R)  # constant per agent

    # -- helpers ---------------------------------------------------------
    def init(self, batch: tuple) -> State:
        """Every agent starts from the common prior (x0, P0) (Algorithm 1)."""
        n = self.model.n
        x = np.broadcast_to(self.model.x0, batch + (n,)).astype(float).copy()
        P = np.broadcast_to(self.model.P0, batch + (n, n)).astype(float).copy()
        m = self.model.m
        return State(x, P, np.zeros(batch, dtype=np.int64), np.zeros(batch + (m,)), np.zeros(batch, dtype=bool))

    def local_kf(self, state: State, k: int, y, has) -> Local:
        """Prediction (info_kf_prediction0) and local update (info_kf_update0)."""
        x_pred, P_pred = eq.predict(state.x, state.P, self.model.A_at(k), self.model.Q)
        U, u = eq.measurement_information(self.sensor_info, y, has)
        Y, Ji = eq.information_pair(P_pred, U)
        x_upd, P_upd = eq.local_update(x_pred, P_pred, Y, Ji, u, has)
        return Local(x_pred, P_pred, U, u, x_upd, P_upd, Y, Ji)

    @staticmethod
    def for_fuse(state: State, loc: Local, since=None) -> State:
        """``state`` after the local step: the window counter ``since`` if
        given, and the local step's P^^-1 for ``fusion_inverses``."""
        return State(state.x, state.P, state.since if since is None else since, state.d_hold, state.held, loc.Y)

    @staticmethod
    def fusion_inverses(state: State, own: Message, senders: Message):
        """(P^*^-1 of each receiver, P^_j^-1 and P~_j^-1 of each sender),
        every one inverted once per tick.

        A receiver's own P^^-1 comes from its local step (``State.Y_pred``);
        when the senders are the receivers themselves (the engine's dense
        layout), so do theirs. Otherwise they are inverted, in one stacked
        call, from the messages (as an agent process receives them)."""
        Y = state.Y_pred
        if Y is None:
            if senders is own:
                Y, Yu = inv_spd_each(own.P_pred, own.P_upd)
                return Y, Y, Yu
            return inv_spd_each(own.P_pred, senders.P_pred, senders.P_upd)
        if senders is own:
            return Y, Y, inv_spd(own.P_upd)
        Yp, Yu = inv_spd_each(senders.P_pred, senders.P_upd)
        return Y, Yp, Yu

    def local_input(self, loc: Local, allowed=None):
        """The agent's own RKF input estimate (input_estimation)."""
        return eq.input_estimate(loc.x_pred, loc.Y, loc.Ji, loc.U, loc.u, self.model.G, allowed)

    @staticmethod
    def message(loc: Local, d, S, valid, x_upd=None, P_upd=None) -> Message:
        return Message(
            loc.x_pred, loc.P_pred,
            loc.x_upd if x_upd is None else x_upd,
            loc.P_upd if P_upd is None else P_upd,
            d, S, valid,
        )

    # -- interface -------------------------------------------------------
    def local(self, state: State, k: int, y, has):  # pragma: no cover - abstract
        raise NotImplementedError

    def fuse(self, state: State, own: Message, senders: Message, nb: Neighbourhood):  # pragma: no cover
        raise NotImplementedError


def uniform_weights(adj: np.ndarray) -> np.ndarray:
    """Row-normalised adjacency: equal weight to every fused neighbour."""
    deg = adj.sum(axis=-1, keepdims=True)
    return adj / np.where(deg > 0, deg, 1.0)
