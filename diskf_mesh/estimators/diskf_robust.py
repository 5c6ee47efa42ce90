"""``diskf-r``: robust DISKF, our extension of Algorithm 1 (not the paper's).

The name starts with ``diskf`` because it keeps DISKF's structure and every
constraint of the paper: one exchange round per tick, the same message
(``messages.Message``: x^, P^, x~, P~ and an input estimate with its
covariance; no raw measurement, no H, no R), so the same wire format and
bytes: 8 (2n + 2n^2 + m + m^2) bytes of float64 plus the msgpack header,
161 bytes in all for n = 2, m = 1 and the run id ``default``, whatever the
neighbourhood's size. And the same two steps per tick, local
(before sending) and fuse (after receiving). What changes is how a receiver
uses what it hears. Per tick, agent i (switches in ``model.RobustOptions``):

1. local: x^ = A x_bar, P^ = A P_bar A^T + Q (eq. info_kf_prediction0) and
   the local update (eq. info_kf_update0), as DISKF. The message's (d, S,
   d_valid) is the agent's last *fused* input (d_bar, S_bar), the exchanged
   value Algorithm 1 lists in step 2 (``relay``); DISKF sends its local
   estimate there instead.
2. fuse, the prior (``prior_ci``): covariance intersection (the paper's fast
   CI, eqs. input_fusion, input_fusion_p, applied to states) of the
   neighbourhood's predictions (x^_j, P^_j). CI is consistent for any
   correlation between the neighbours' errors, so the fused prior P_c is
   never overconfident, and a neighbour that saw the target recently lends
   its better prior: information travels one hop per tick, not only through
   the compensation step. Where every prediction is the same (all-to-all:
   every agent fused the same messages) CI returns that prediction.
3. fuse, the measurement: the neighbourhood's stacked information
   U = sum_j (P~_j^-1 - P^_j^-1) = sum_j H_j^T R_j^-1 H_j and u likewise
   (below eq. state_fusion), exact from the messages.
4. fuse, the input (``joint_input``): the unbiased minimum-variance input
   estimate of eq. (input_estimation) on the stacked sensors, relative to the
   fused prior (d_N, S_N): what a centre holding the neighbourhood's
   measurements would estimate. DISKF instead fuses the individual estimates
   by CI, which share the prediction error, and loses the joint estimate.
5. fuse, the state. Two cases:
   * the neighbourhood's sensors make the input strongly detectable
     (``gate``; ``equations.strongly_detectable``: rank(HG) = m and every
     invariant zero of (A, G, H_N) inside the unit circle): the exact
     Gillijns-De Moor update of ``rkf.rkf_update`` on (x_c, P_c, U, u), with
     the input direction of the prior left free. Its error decays whatever
     the input, and its covariance is the true one given the prior. The fused
     input is (d_N, S_N).
     ``latch``: once an agent has made this update, it keeps making it at
     the following ticks while rank(HG) = m holds, even where the sensors of
     that one tick alone are not strongly detectable: its prior already
     carries the information of the earlier sensors (e.g. a y-sensor's),
     so the error of a short stretch of x-sensor ticks grows from a small
     value, as in the centralized filter, which never stops. A tick without
     a usable measurement ends the latch; it restarts at the next
     detectable tick. An agent that has only ever heard x-sensors never
     latches.
   * otherwise (no measurement, rank(HG) < m, or an invariant zero on or
     outside the unit circle, e.g. only x-sensors heard while the target
     turns anticlockwise): feeding the input estimate into the state would
     make the error grow like that zero's powers. Instead the input is
     predicted from the last fused inputs the neighbourhood relays
     (``relay``: fast CI of their (d_bar, S_bar), the agent's own included),
     injected with its covariance (``inject``; ``equations.input_injection``:
     x* = x_c + G d, P* = P_c + G S G^T), the prior is scaled up where the
     measurement shows it too small (``inflate``;
     ``equations.innovation_scale``: an assumed input may have changed, or
     none is known yet, and the prior cannot know), and the neighbourhood's
     measurement information is added by the Kalman update in information
     form (``equations.local_update``). The fused input is the relayed one.
     Where nothing is known about the input yet, it is taken as zero (the
     paper's prediction without input).
6. The paper's window and compensation are switches (``window``,
   ``compensate``), off by default: with honest covariances the input
   estimate's S already grows after a gap (R~ = H P^ H^T + R), and CI of the
   priors does what the compensation step approximates.

What it assumes that Gillijns-De Moor does not: in step 5's second case the
input is taken to persist from the last tick it was detectable (its
covariance is not inflated: without an input model there is no principled
rate). Where the gate holds at every tick, nothing is assumed about the
input. In particular, in an all-to-all network whose stacked sensors are
strongly detectable at every tick, diskf-r *is* the centralized
Gillijns-De Moor filter (``centralized.py``; ``tests/test_robust.py``).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from diskf_mesh.core import equations as eq
from diskf_mesh.core.linalg import inv_spd, nbr_sum
from diskf_mesh.core.messages import Message, Neighbourhood, Output
from diskf_mesh.core.rkf import rkf_update
from diskf_mesh.core.model import RobustOptions
from diskf_mesh.estimators.base import Estimator, Setting
from diskf_mesh.estimators.diskf import COMPENSATION, EPS, RESET, WINDOW, HeldState

ROBUST = Setting("robust", RobustOptions(), "the switches of diskf-r (model.RobustOptions), "
                 "the [estimator.robust] table")


@dataclass(frozen=True)
class RobustState(HeldState):
    S_hold: np.ndarray | None = None  # (..., m, m) covariance of d_hold, the last fused input
    tick: int = 0                     # the tick of the last ``local`` (its A_{k-1} serves ``fuse``)
    fed: np.ndarray | None = None     # (...,) the last tick made the unbiased update (``latch``)


class DISKFRobust(Estimator):
    name = "diskf-r"
    label = "DISKF-R"
    color = "midnightblue"
    settings = (WINDOW, RESET, EPS, COMPENSATION, ROBUST)

    def init(self, batch: tuple) -> RobustState:
        s = super().init(batch)
        m = self.model.m
        S = np.broadcast_to(np.eye(m), batch + (m, m)).copy()  # placeholder where nothing is held
        return RobustState(s.x, s.P, s.since, np.zeros(batch + (m,)), np.zeros(batch, dtype=bool),
                           S_hold=S, fed=np.zeros(batch, dtype=bool))

    def local(self, state: RobustState, k: int, y, has):
        """Step 1 (prediction, local update) and the message."""
        o = self.params.robust
        loc = self.local_kf(state, k, y, has)
        since = state.since + 1
        if o.joint_input:
            d, S, valid = state.d_hold, state.S_hold, state.held  # the last fused input (relay)
        else:
            allowed = eq.window_allows(since, self.params.window) if o.window else None
            d, S, valid = self.local_input(loc, allowed)
        st = RobustState(state.x, state.P, np.where(has, 0, since), state.d_hold, state.held,
                         Y_pred=loc.Y, Yx_pred=loc.Yx, S_hold=state.S_hold, tick=k, fed=state.fed)
        return st, self.message(loc, d, S, valid)

    def fuse(self, state: RobustState, own: Message, senders: Message, nb: Neighbourhood):
        p, o = self.params, self.params.robust
        G = self.model.G
        Ystar, Yp, Yu, Ypx = self.fusion_inverses(state, own, senders)
        dy, dY = eq.information_contribution(senders.x_pred, senders.P_pred, senders.x_upd, senders.P_upd,
                                             Yp=Yp, Yu=Yu, Ypx=Ypx)
        U, u = nbr_sum(nb.adj, dY, 2), nbr_sum(nb.adj, dy, 1)
        # 2. the prior: CI of the neighbourhood's predictions
        if o.prior_ci:
            ones = np.ones(senders.x_pred.shape[:-1], dtype=bool)
            x_c, P_c, _ = eq.input_fusion(nb.adj, senders.x_pred, senders.P_pred, ones)
            Yc = inv_spd(P_c)
        else:
            x_c, P_c, Yc = own.x_pred, own.P_pred, Ystar
        # 4. the input
        allowed = eq.window_allows(state.since, p.window) if o.window else None
        if o.joint_input:
            d_N, S_N, valid_N = eq.input_estimate(x_c, P_c, U, u, G, allowed, Y=Yc)
        else:
            d_N, S_N, valid_N = eq.input_fusion(nb.adj, senders.d, senders.S, senders.d_valid)
        feed = eq.strongly_detectable(self.model.A_at(state.tick), G, U, valid_N) if o.gate else valid_N
        if o.gate and o.latch:
            feed = feed | (valid_N & state.fed)
        # 5a. detectable: the exact unbiased (Gillijns-De Moor) update
        x_g, P_g = rkf_update(x_c, P_c, U, u, G, feed, Y=Yc)
        # 5b. otherwise: the relayed input, injected with its covariance, then the Kalman update
        if o.relay and o.joint_input:
            d_p, S_p, has_p = eq.input_fusion(nb.adj, senders.d, senders.S, senders.d_valid)
        else:
            d_p, S_p, has_p = state.d_hold, state.S_hold, state.held
        if o.inject:
            x_s, P_s = eq.input_injection(x_c, P_c, G, d_p, S_p, has_p)
        else:
            x_s, P_s = eq.input_injection(x_c, P_c, G, d_p, np.zeros_like(S_p), has_p)
        if o.inflate:
            alpha = eq.innovation_scale(P_s, U, u, x_s)
            P_s = P_s * alpha[..., None, None]
        x_k, P_k = eq.local_update(x_s, P_s, U, u)
        f2, f3 = feed[..., None], feed[..., None, None]
        x_bar, P_bar = np.where(f2, x_g, x_k), np.where(f3, P_g, P_k)
        if o.compensate and p.compensation != "none" and p.eps != 0.0:
            gain = eq.compensation_gain(P_bar, p.compensation, p.eps, nb.n_neighbours)
            x_bar = eq.compensation_state(nb.adj, x_bar, gain, own.x_pred, senders.x_pred, p.eps)
        d_bar = np.where(f2, d_N, np.where(has_p[..., None], d_p, 0.0))
        S_bar = np.where(f3, S_N, S_p)
        held = feed | has_p
        since = state.since
        if o.window and p.reset:
            since = np.where(held, 0, since)
        st = RobustState(x_bar, P_bar, since, d_bar, held, S_hold=S_bar, tick=state.tick, fed=feed)
        return st, Output(x_bar, P_bar, d_bar, held)
