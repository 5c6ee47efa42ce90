"""``diskf-r``: robust DISKF, our extension of Algorithm 1 (not the paper's).

The name starts with ``diskf`` because it keeps DISKF's structure and every
constraint of the paper: one exchange round per tick, the same message
(``messages.Message``: x^, P^, x~, P~ and an input estimate with its
covariance; no raw measurement, no H, no R), so the same wire format and
bytes: 8 (2n + 2n^2 + m + m^2) bytes of float64 plus the msgpack header,
161 bytes in all for n = 2, m = 1 and the run id ``default``, whatever the
neighbourhood's size. And the same two steps per tick, local
(before sending) and fuse (after receiving). Switches: ``model.RobustOptions``.

Why the paper's input estimate cannot be the whole answer. Gillijns-De
Moor's input estimate is unbiased for *any* input sequence, so it reads as
input every output the input could have produced. With one sensor type and
one input (p = m = 1) that is the whole innovation, and the state error
follows the zero dynamics of (A, G, H), whose zero is cos w + sin w > 1 for
an x-sensor of the shipped scenarios: such a sensor cannot keep an
unbiased estimate stable (``equations.strongly_detectable``). An isolated
agent, or a neighbourhood of x-sensors, is in that case most of the time.

The model (``persist``, the default): the input persists, as a random walk

    d_{k-1} = d_{k-2} + eta,   eta ~ N(0, Qd),   Qd = input_walk * I
    d_0 ~ N(0, input_prior * I)

and every agent runs the Kalman filter of the joint state (x_k, d_{k-1})
(the "augmented state" filter), decentralised as DISKF decentralises the
state filter. A constant input is observable through any sensor with
H (I - A)^-1 G != 0 (an x-sensor included), so an isolated agent learns the
input while it measures and predicts with it, and with its covariance,
while it does not. With Qd -> infinity the model assumes nothing and the
filter tends to Gillijns-De Moor's; a finite Qd is an assumption (the input
changes by about sqrt(Qd) per tick), stated, and its sensitivity measured
in the report's ablation. Per tick, agent i:

1. local: x^ = A x_bar, P^ = A P_bar A^T + Q (eq. info_kf_prediction0) and
   the local update (eq. info_kf_update0), as DISKF. x^ is the prediction
   of v_k = x_k - G d_{k-1}, which does not depend on the input. The
   message's (d, S, d_valid) is the agent's last *fused* input (d_bar,
   S_bar), the exchanged value Algorithm 1 lists in step 2 (``relay``).
   The cross-covariance C = cov(x_bar, d_bar) stays with the agent (it is
   not on the wire).
2. fuse, the own joint prior of (v_k, d_{k-1}): cov(v) = P^, cov(v, d) = A C,
   cov(d) = S_bar + Qd (``equations.input_walk``).
3. fuse, the neighbourhood's prior (``prior_ci``): covariance intersection
   (the paper's fast CI, eqs. input_fusion, input_fusion_p, applied to the
   states) of the neighbourhood's x^_j: consistent for any correlation
   between the neighbours' errors, and a neighbour that saw the target lends
   its better prior. It replaces the own marginal of v, the conditional
   p(d | v) kept (``equations.replace_marginal``).
4. fuse, the relayed inputs (``relay``): fast CI of the neighbourhood's
   (d_bar_j, S_bar_j + Qd) (the agent's own included) replaces the marginal
   of d, p(v | d) kept. Information about the input travels one hop per
   tick; an agent that has never measured learns it from a neighbour.
   Measured, it changes little once every agent learns the input itself
   (the ablation: within 0.5 % of the state error in the shipped settings).
5. fuse, to the state (``inject``): x = v + G d with
   P = P_v + G B^T + B G^T + G S G^T and C = B + G S
   (``equations.input_to_state``; B = cov(v, d)). The paper's eq.
   (info_kf_prediction) is the mean of this with the input's covariance left
   out (P^* = P^), which is why DISKF's NEES is large wherever the input is
   uncertain.
6. fuse, the measurement: the neighbourhood's stacked information
   U = sum_j (P~_j^-1 - P^_j^-1) = sum_j H_j^T R_j^-1 H_j and u likewise
   (below eq. state_fusion), exact from the messages, added by the Kalman
   update in information form (``equations.local_update``). The measurement
   is of x only, so p(d | x) is unchanged and the input's update is
   ``replace_marginal`` of x (prior -> posterior): together the exact joint
   Kalman update of (x, d).

Where it is exact. Isolated (the neighbourhood is the agent) it is the joint
Kalman filter of the agent's own sensor. In all-to-all every agent fused the
same messages, so every CI returns the common prediction and input, the
replacements change nothing, and diskf-r is the centralized filter with
the same input model (``centralized.run_centralized_persist``; to round-off,
``tests/test_robust.py``). In between, steps 3 and 4 keep the agent's own
correlation between v and d for a fused prior whose correlation is not
known: an approximation (measured: NEES about 2 in every setting of the
report).

Other switches (off by default, rows of the ablation table):
* ``unbiased``: where the neighbourhood's sensors make the input strongly
  detectable (``gate``; ``equations.strongly_detectable``: rank(HG) = m and
  every invariant zero of (A, G, H_N) inside the unit circle; ``latch``:
  and after such a tick while rank(HG) = m holds), the exact Gillijns-De
  Moor update of ``rkf.rkf_update`` on the CI prior, the input's prior
  dropped: it assumes nothing about the input there. Its input and
  cross-covariance (``equations.free_input_gain``) continue the persistent
  model at the next tick. On by itself (``persist`` off) with ``inflate`` on,
  it is the first version of diskf-r (the relayed input assumed, not
  learned, where the gate fails).
* ``inflate``: the fading factor ``equations.innovation_scale`` on the prior
  where the measurement shows it too small. With ``persist`` the input's
  covariance already explains the innovations; measured, it makes the
  covariance conservative (NEES 1.5 in all-to-all) without lowering the
  error.
* ``window``, ``compensate``: the paper's observation window (for the
  unbiased update) and state compensation.
* ``joint_input`` off: the message carries the agent's own input estimate
  instead of its fused one (no relay), and the unbiased update uses the CI
  of the individual estimates.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from diskf_mesh.core import equations as eq
from diskf_mesh.core import input_models as im
from diskf_mesh.core.linalg import T, inv_spd, mv, nbr_sum, sym
from diskf_mesh.core.messages import Message, Neighbourhood, Output
from diskf_mesh.core.rkf import rkf_update
from diskf_mesh.core.model import RobustOptions
from diskf_mesh.estimators.base import DEFENCE, Estimator, Setting, run_scales
from diskf_mesh.estimators.diskf import COMPENSATION, EPS, RESET, WINDOW, HeldState

ROBUST = Setting("robust", RobustOptions(), "the switches of diskf-r (model.RobustOptions), "
                 "the [estimator.robust] table")


def input_model_of(o: RobustOptions, model, sensors):
    """(rho, q, prior) of ``[estimator.robust]``'s input model on this model
    and these sensors: the model's rho (``input_models.model_rho``), its
    scale per tick (``input_walk``; 0 for ``none``) and the input's prior
    variance (``input_prior``), each from the scenario's scales where not
    given (``input_models.default_scales``, over every sensor of the run:
    ``Sensors.whole``)."""
    walk, prior = im.default_scales(*run_scales(model, sensors))
    q = 0.0 if o.input_model == "none" else (walk if o.input_walk is None else o.input_walk)
    return im.model_rho(o.input_model, o.input_rho), q, (prior if o.input_prior is None else o.input_prior)


@dataclass(frozen=True)
class RobustState(HeldState):
    S_hold: np.ndarray | None = None  # (..., m, m) covariance of d_hold, the last fused input
    tick: int = 0                     # the tick of the last ``local`` (its A_{k-1} serves ``fuse``)
    fed: np.ndarray | None = None     # (...,) the last tick made the unbiased update (``latch``)
    C: np.ndarray | None = None       # (..., n, m) cov(x_bar error, d_hold error) (``persist``)


class DISKFRobust(Estimator):
    """``diskf-r`` (ours, not the paper's): DISKF with the input in the
    filter's model (a random walk by default, ``input_model``), so an input
    seen only now and then is carried between sightings; its other switches
    are this module's settings."""

    name = "diskf-r"
    label = "DISKF-R"
    color = "midnightblue"
    settings = (WINDOW, RESET, EPS, COMPENSATION, ROBUST, DEFENCE)
    extends = "diskf"  # an extension of DISKF under its constraints (the reports' "DISKF family")

    def __init__(self, model, sensors, params=None):
        super().__init__(model, sensors, params)
        self.rho, self.walk, self.prior = input_model_of(self.params.robust, model, sensors)

    @classmethod
    def refuse(cls, params, model, sensors):
        """``unbiased`` with no input (``input_model = "none"``), or where
        not even every sensor together sees every input component
        (rank(H G) < m for the stacked H): the unbiased update could never
        run."""
        o = params.robust
        if not o.unbiased:
            return None
        if o.persist and o.input_model == "none":
            return "estimator.robust.unbiased", "true needs an input; input_model = 'none' assumes there is none"
        rows = np.concatenate([sensors.H[i, : sensors.p[i]] for i in range(sensors.N)])
        r, m = np.linalg.matrix_rank(rows @ model.G), model.m
        if r < m:
            return "estimator.robust.unbiased", (f"true needs rank(H G) = m = {m} for some neighbourhood, but all "
                                                 f"sensors together reach rank {r}: the unbiased update can never run")
        return None

    def init(self, batch: tuple) -> RobustState:
        s = super().init(batch)
        n, m = self.model.n, self.model.m
        o = self.params.robust
        scale = self.prior if o.persist else 1.0  # persist: the input's prior; else a placeholder
        S = np.broadcast_to(scale * np.eye(m), batch + (m, m)).copy()
        C = np.zeros(batch + (n, m))
        return RobustState(s.x, s.P, s.since, np.zeros(batch + (m,)), np.zeros(batch, dtype=bool),
                           S_hold=S, fed=np.zeros(batch, dtype=bool), C=C)

    def local(self, state: RobustState, k: int, y, has):
        """Step 1 (prediction, local update) and the message."""
        o = self.params.robust
        loc = self.local_kf(state, k, y, has)
        since = state.since + 1
        if o.persist and o.input_model == "none":  # no input: nothing to share (S = I, a placeholder)
            d, S, valid = np.zeros_like(state.d_hold), np.broadcast_to(np.eye(self.model.m), state.S_hold.shape), \
                np.zeros_like(state.held)
        elif o.joint_input:
            d, S, valid = state.d_hold, state.S_hold, state.held  # the last fused input (relay)
        else:
            allowed = eq.window_allows(since, self.params.window) if o.window else None
            d, S, valid = self.local_input(loc, allowed)
        st = RobustState(state.x, state.P, np.where(has, 0, since), state.d_hold, state.held,
                         Y_pred=loc.Y, S_hold=state.S_hold, tick=k, fed=state.fed, C=state.C)
        return st, self.message(loc, d, S, valid)

    def fuse(self, state: RobustState, own: Message, senders: Message, nb: Neighbourhood):
        p, o = self.params, self.params.robust
        G = self.model.G
        A = self.model.A_at(state.tick)
        Ystar, Yp, Yu = self.fusion_inverses(state, own, senders)
        dy, dY = eq.information_contribution(senders.x_pred, Yp, senders.x_upd, Yu)
        U, u = nbr_sum(nb.adj, dY, 2), nbr_sum(nb.adj, dy, 1)
        # 2. the prior of v = x_k - G d_{k-1}: CI of the neighbourhood's predictions
        if o.prior_ci:
            ones = np.ones(senders.x_pred.shape[:-1], dtype=bool)
            x_c, P_c, _ = eq.input_fusion(nb.adj, senders.x_pred, senders.P_pred, ones)
            Yc = inv_spd(P_c)
        else:
            x_c, P_c, Yc = own.x_pred, own.P_pred, Ystar
        # 3-4. the state and the input
        if o.persist:
            x_bar, P_bar, d_bar, S_bar, C_bar, held = self._persist(state, own, senders, nb, x_c, P_c, U, u, A)
        else:
            x_bar, P_bar, d_bar, S_bar, held = self._assume(state, senders, nb, x_c, P_c, U, u)
            C_bar = state.C
        feed = np.zeros(held.shape, dtype=bool)
        if o.unbiased:  # 5. where the heard sensors detect the input: the exact unbiased update
            allowed = eq.window_allows(state.since, p.window) if o.window else None
            if o.joint_input:
                d_N, S_N, valid_N = eq.input_estimate(x_c, Yc, inv_spd(Yc + U), U, u, G, allowed)
            else:
                d_N, S_N, valid_N = eq.input_fusion(nb.adj, senders.d, senders.S, senders.d_valid)
            feed = eq.strongly_detectable(A, G, U, valid_N) if o.gate else valid_N
            latched = valid_N & state.fed & ~feed if o.gate and o.latch else np.zeros_like(feed)
            x_g, P_g = rkf_update(x_c, Yc, U, u, G, feed | latched)
            # the guard of the latch: where the heard sensors are not strongly detectable the unbiased error
            # need not decay (an invariant zero on or outside the unit circle), so a latched tick takes the
            # unbiased update only where it is at least as certain as the model's own (trace)
            feed = feed | (latched & (np.trace(P_g, axis1=-2, axis2=-1) <= np.trace(P_bar, axis1=-2, axis2=-1)))
            f2, f3 = feed[..., None], feed[..., None, None]
            x_bar, P_bar = np.where(f2, x_g, x_bar), np.where(f3, P_g, P_bar)
            d_bar, S_bar = np.where(f2, d_N, d_bar), np.where(f3, S_N, S_bar)
            C_bar = np.where(f3, np.matmul(P_g, T(eq.free_input_gain(Yc, G))), C_bar)
            held = held | feed
        if o.compensate and p.compensation != "none" and p.eps != 0.0:
            gain = eq.compensation_gain(P_bar, p.compensation, p.eps, nb.n_neighbours)
            x_bar = eq.compensation_state(nb.adj, x_bar, gain, own.x_pred, senders.x_pred, p.eps)
        since = state.since
        if o.window and p.reset:
            since = np.where(held, 0, since)
        st = RobustState(x_bar, P_bar, since, d_bar, held, S_hold=S_bar, tick=state.tick, fed=feed, C=C_bar)
        return st, Output(x_bar, P_bar, d_bar, held & (o.input_model != "none" or not o.persist))

    def _persist(self, state, own, senders, nb, x_c, P_c, U, u, A):
        """Steps 2-6 with the persistent input (``persist``): the joint Kalman
        filter of (x, d) under the random-walk input of ``equations.input_walk``.
        The input counts as held from the first tick the neighbourhood
        measures (or a neighbour relays a held one)."""
        o = self.params.robust
        G = self.model.G
        m = G.shape[-1]
        rho, q = self.rho, self.walk
        d1, B, S1 = im.input_predict(A, state.C, state.d_hold, state.S_hold, rho, q)
        if o.prior_ci:  # the neighbourhood's CI prior replaces the own v, p(d | v) kept
            d1, B, S1 = eq.replace_marginal(own.x_pred, own.P_pred, d1, B, S1, x_c, P_c)
        v, Pv = x_c, P_c
        has_p = state.held | (np.trace(U, axis1=-2, axis2=-1) > 0)
        if o.relay and o.joint_input and rho > 0:  # the relayed inputs replace the own d, p(v | d) kept
            d_r, S_r, has_r = eq.input_fusion(nb.adj, rho * senders.d, sym(rho * rho * senders.S + q * np.eye(m)),
                                              senders.d_valid)
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
        x_k, P_k = eq.local_update(x_s, P_s, *eq.information_pair(P_s, U), u)
        d_k, C_k, S_k = eq.replace_marginal(x_s, P_s, d1, C_s, S1, x_k, P_k)
        return x_k, P_k, d_k, S_k, C_k, has_p

    def _assume(self, state, senders, nb, x_c, P_c, U, u):
        """Without ``persist`` (the first diskf-r): the relayed input (or the
        last fused one) assumed, injected with its covariance
        (``equations.input_injection``), the prior inflated if ``inflate``,
        the Kalman update; the input is not updated from the measurement."""
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
        x_k, P_k = eq.local_update(x_s, P_s, *eq.information_pair(P_s, U), u)
        d_k = np.where(has_p[..., None], d_p, 0.0)
        return x_k, P_k, d_k, S_p, has_p


class DISKFNone(DISKFRobust):
    """``diskf-none``: DISKF's fusion (the CI prior, the neighbourhood's
    measurement information, ``diskf-r``'s other switches) with the input
    model ``none``: a target no unknown input pushes, or an input too fast
    and too weakly seen to estimate (it is left to the filter's noise). It
    is ``diskf-r`` with ``input_model = "none"`` whatever
    ``[estimator.robust]`` says of the input (``unbiased`` off: with no
    input there is nothing to keep unbiased); its message carries no input."""
    name = "diskf-none"
    label = "DISKF-none"
    color = "slategray"

    def __init__(self, model, sensors, params=None):
        super().__init__(model, sensors, _no_input(params))

    @classmethod
    def refuse(cls, params, model, sensors):
        return super().refuse(_no_input(params), model, sensors)


def _no_input(params):
    """``params`` with ``diskf-r``'s input model set to none."""
    if params is None:
        from diskf_mesh.estimators import Params  # the registry's, with every registered setting
        params = Params()
    return replace(params, robust=replace(params.robust, input_model="none", persist=True, unbiased=False))
