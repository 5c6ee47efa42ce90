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
from diskf_mesh.core.linalg import T, inv_spd, mv, nbr_sum
from diskf_mesh.core.messages import Message, Neighbourhood, Output
from diskf_mesh.core.rkf import rkf_update
from diskf_mesh.estimators.base import Algorithm, State


@dataclass(frozen=True)
class RobustState(State):
    S_hold: np.ndarray | None = None  # (..., m, m) covariance of d_hold, the last fused input
    tick: int = 0                     # the tick of the last ``local`` (its A_{k-1} serves ``fuse``)
    fed: np.ndarray | None = None     # (...,) the last tick made the unbiased update (``latch``)
    C: np.ndarray | None = None       # (..., n, m) cov(x_bar error, d_hold error) (``persist``)


class DISKFRobust(Algorithm):
    name = "diskf-r"
    label = "DISKF-R"

    def init(self, batch: tuple) -> RobustState:
        s = super().init(batch)
        n, m = self.model.n, self.model.m
        o = self.params.robust
        scale = o.input_prior if o.persist else 1.0  # persist: the input's prior; else a placeholder
        S = np.broadcast_to(scale * np.eye(m), batch + (m, m)).copy()
        C = np.zeros(batch + (n, m))
        return RobustState(s.x, s.P, s.since, s.d_hold, s.held, S_hold=S, fed=np.zeros(batch, dtype=bool), C=C)

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
                         loc.Y, loc.Yx, S_hold=state.S_hold, tick=k, fed=state.fed, C=state.C)
        return st, self.message(loc, d, S, valid)

    def fuse(self, state: RobustState, own: Message, senders: Message, nb: Neighbourhood):
        p, o = self.params, self.params.robust
        G = self.model.G
        A = self.model.A_at(state.tick)
        m = G.shape[-1]
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
        if o.unbiased:
            feed = eq.strongly_detectable(A, G, U, valid_N) if o.gate else valid_N
            if o.gate and o.latch:
                feed = feed | (valid_N & state.fed)
        else:
            feed = np.zeros_like(valid_N)
        # 5a. detectable: the exact unbiased (Gillijns-De Moor) update
        x_g, P_g = rkf_update(x_c, P_c, U, u, G, feed, Y=Yc)
        if o.persist:
            x_k, P_k, d_k, S_k, C_k, has_p = self._persist(state, own, senders, nb, x_c, P_c, U, u, A)
            C_g = np.matmul(P_g, T(eq.free_input_gain(Yc, G)))
        else:
            x_k, P_k, d_k, S_k, has_p = self._assume(state, senders, nb, x_c, P_c, U, u)
            C_k = C_g = state.C
        f2, f3 = feed[..., None], feed[..., None, None]
        x_bar, P_bar = np.where(f2, x_g, x_k), np.where(f3, P_g, P_k)
        if o.compensate and p.compensation != "none" and p.eps != 0.0:
            gain = eq.compensation_gain(P_bar, p.compensation, p.eps, nb.n_neighbours)
            x_bar = eq.compensation_state(nb.adj, x_bar, gain, own.x_pred, senders.x_pred, p.eps)
        d_bar = np.where(f2, d_N, d_k)
        S_bar = np.where(f3, S_N, S_k)
        C_bar = np.where(f3, C_g, C_k)
        held = feed | has_p
        since = state.since
        if o.window and p.reset:
            since = np.where(held, 0, since)
        st = RobustState(x_bar, P_bar, since, d_bar, held, S_hold=S_bar, tick=state.tick, fed=feed, C=C_bar)
        return st, Output(x_bar, P_bar, d_bar, held)

    def _persist(self, state, own, senders, nb, x_c, P_c, U, u, A):
        """Step 5b with the persistent input (``persist``): the joint Kalman
        filter of (x, d) under the random-walk input of ``equations.input_walk``."""
        o = self.params.robust
        G = self.model.G
        m = G.shape[-1]
        Qd = o.input_walk * np.eye(m)
        B, S1 = eq.input_walk(A, state.C, state.S_hold, Qd)
        d1 = state.d_hold
        if o.prior_ci:  # the neighbourhood's CI prior replaces the own v, p(d | v) kept
            d1, B, S1 = eq.replace_marginal(own.x_pred, own.P_pred, d1, B, S1, x_c, P_c)
        v, Pv = x_c, P_c
        has_p = state.held | (np.trace(U, axis1=-2, axis2=-1) > 0)
        if o.relay and o.joint_input:  # the relayed inputs replace the own d, p(v | d) kept
            d_r, S_r, has_r = eq.input_fusion(nb.adj, senders.d, senders.S + Qd, senders.d_valid)
            v_r, Bt_r, Pv_r = eq.replace_marginal(d1, S1, v, T(B), Pv, d_r, S_r)
            r1, r2 = has_r[..., None], has_r[..., None, None]
            v, Pv, B = np.where(r1, v_r, v), np.where(r2, Pv_r, Pv), np.where(r2, T(Bt_r), B)
            d1, S1 = np.where(r1, d_r, d1), np.where(r2, S_r, S1)
            has_p = has_p | has_r
        if o.inject:
            x_s, P_s, C_s = eq.input_to_state(v, Pv, B, d1, S1, G)
        else:
            x_s, P_s, C_s = v + mv(G, d1), Pv, np.zeros_like(B)
        if o.inflate:
            alpha = eq.innovation_scale(P_s, U, u, x_s)
            a3 = alpha[..., None, None]
            P_s, C_s, S1 = P_s * a3, C_s * a3, S1 * a3
        x_k, P_k = eq.local_update(x_s, P_s, U, u)
        d_k, C_k, S_k = eq.replace_marginal(x_s, P_s, d1, C_s, S1, x_k, P_k)
        return x_k, P_k, d_k, S_k, C_k, has_p

    def _assume(self, state, senders, nb, x_c, P_c, U, u):
        """Step 5b without ``persist``: the relayed input assumed, injected
        with its covariance, the prior inflated, the Kalman update."""
        o = self.params.robust
        G = self.model.G
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
        d_k = np.where(has_p[..., None], d_p, 0.0)
        return x_k, P_k, d_k, S_p, has_p
