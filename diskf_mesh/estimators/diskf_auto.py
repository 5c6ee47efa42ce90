"""``diskf-auto``: DISKF with the input model chosen from the data (our
extension of Algorithm 1, not the paper's).

``diskf-r`` assumes one input model (a random walk of a given scale). Which
one fits depends on the input met: a persistent input wants the walk, an
input that switches or has no input at all wants a zero-mean model or none,
an input that oscillates wants a model that predicts its swing, and a scale
wrong by orders of magnitude costs either way. ``diskf-auto`` runs a bank of
the input models of ``core.input_models`` (``default_bank``: no input,
random walks, zero-mean and mean-reverting inputs, and oscillating inputs of
periods 4 to 32 ticks, at scales from the scenario's own Q, G and the
sensors' R) and mixes them as the interacting multiple model filter does
(Blom and Bar-Shalom 1988). Every model is the second-order recursion (IM2)
d_{k-1} = a1 d_{k-2} + a2 d_{k-3} + eta (a first-order model has a2 = 0), so
each carries the input pair e = (d_{k-1}, d_{k-2}) beside the state:

1. local, as ``diskf-r``: the prediction x^ = A x_bar and the local
   update of the agent's *combined* estimate; the message is diskf-r's
   (x^, P^, x~, P~, the combined fused input d, S) and the agent's model
   probabilities w (one float per model of ``input_models.BANK``, 0 for a
   model not in the bank). No H, R or y; one message per tick. With
   ``[estimator.auto] noise`` (off by default) the agent weighs this tick's
   measurement by 1 / r, the scale of its own R it learned by the last tick
   it measured (step 5): its local update carries the weight, and so does
   every receiver's fusion and every model's likelihood; the bank compares
   input models under the noise the world shows, and the message is
   unchanged.
2. fuse, mixing: on a tick whose neighbourhood measures nothing, the
   models' prior probabilities are the fused senders' (the agent's own
   included) pooled by their normalised geometric mean
   (``input_models.pool_probabilities``), so an agent whose neighbourhood
   has not measured lately weighs the models by its neighbours' evidence;
   on a tick it measures, they are the agent's own: its posterior already
   holds its neighbourhood's evidence, and the pool would lift a model
   that one neighbour's noise briefly favoured to a share a few ticks of
   noise at this agent then confirm (in a ring of constant-acceleration
   agents with no input, the bank read stretches of noise as an input:
   docs/estimators.md, "Where it is not"); each model's prior is the mixture of the agent's last posteriors under
   the models' Markov chain (``input_models.model_weights``, ``mix``; the
   spread between the posteriors' means counted at most as much as their
   own covariances, ``mix(bounded=True)``; a weight below ``PRUNE`` dropped,
   so a model of almost no probability, whose covariance grows through a
   silence, does not widen the others' priors). The oscillating models share
   one model's probability before any evidence, and a change of model
   moves to them by that share (``initial_probabilities``,
   ``transition_matrix``): which period an oscillation has is one question.
   A random walk also moves to each walk of a smaller scale with
   ``[estimator.auto] hand_down`` a tick (``input_models.hand_down``), so
   that a level a walk of larger scale learned reaches the smaller walks
   through the mixing (isolated agents with a step, docs/estimators.md).
3. fuse, per model: the input model's prediction of the pair
   (``pair_predict``); the neighbourhood's CI prior (as ``diskf-r``)
   reached by the affine map that takes the agent's published prediction
   to it (``affine_prior``: the identity where the agent is alone or every
   agent fused the same), the conditional of the input kept
   (``equations.replace_marginal``); the neighbours' relayed inputs for a
   persistent first-order model (a2 = 0, rho = a1 > 0); the input into the
   state, x = v + G d_{k-1} (``equations.input_to_state``); the
   neighbourhood's stacked measurement information (exact from the
   messages) by the joint Kalman update.
4. fuse, weights: each model's likelihood of the neighbourhood's
   measurement, from U and u alone (``information_loglik``), updates the
   model probabilities; the output is the mixture's mean and covariance,
   the state's over the models of probability ``PRUNE`` or more
   (``input_models.output_weights``: a model held at the floor whose
   covariance is orders of magnitude larger does not widen it), the
   input's over every model (the zero-input model alone would claim an
   input known exactly, S = 0, which no message may carry). Where the
   neighbourhood measured nothing, step 3's prediction is the posterior,
   bit for bit, and no model gains evidence (``measure``).
5. fuse, noise (``[estimator.auto] noise``): on a tick the agent measured,
   it learns how much noisier, or calmer, its own sensor is than stated
   (``core.noise``: a scale r of its R, one step of a stochastic
   approximation of the median of the difference between this tick's
   normalised innovation and that of the last tick it measured). The
   measurement is scored against the mean the bank predicted for the tick
   (step 3's, the models mixed by their predicted probabilities, their
   predictions of the input included: the part of a fast input the bank
   predicts is not read as noise) with the covariance of the agent's own
   prediction (the input's uncertainty left out: the models that would
   take noise for an input do not hide it). r weighs the next tick's
   measurement.

With ``[estimator.auto] noise_level`` (0, off, by default) the bank also
holds its models without input and its two smaller random walks under
measurement noise noise_level x R at every sensor of the neighbourhood
(``input_models.at_noise_level``): each such filter fuses the
neighbourhood's information at that level, (U / r, u / r), and its
likelihood adds the level's part of the measurements', -E / 2r - k log(r)
/ 2, E and k the senders' measurement energies y^T R^-1 y and ranks summed,
which each sender's published information gives
(``input_models.information_energy``: nothing is added to the message).
Noisy sensors are then one more model, weighed by their evidence beside an
input. The message carries the probabilities of the models at the stated
noise, renormalised (its 21 slots); a receiver pools those alone and keeps
its own for the models at the level. One bank only (m = 1, or per_channel
off).

With m > 1 input channels (``[estimator.auto] per_channel``, on) each
channel has a bank of its own: m banks of the same models, filter j of
bank c moving channel c by model j and every other channel by its own
bank's most probable model (``input_models.channel_models``); steps 2 and
4 run per bank (its mixing, its probabilities from its own filters'
likelihoods), a bank this tick told nothing follows the informed ones
(``input_models.follow_informed``), the output mixes every filter with
each bank's weights a share 1 / m, the message carries the banks' mean
probabilities, and a bank's relaying models take the neighbours' relayed
inputs on their own channel alone.

With one first-order model in the bank it is ``diskf-r`` with that input
model. Evidence accumulates over ticks in the model probabilities (the
chain's ``switch`` probability keeps them from locking) and spreads through
the pooling, so an agent that measures rarely still learns which model fits
from its neighbours' measurements and, through theirs, from further away.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from diskf_mesh.core import equations as eq
from diskf_mesh.core import input_models as im
from diskf_mesh.core import noise
from diskf_mesh.core.linalg import identity, nbr_sum
from diskf_mesh.core.messages import Message, Neighbourhood, Output
from diskf_mesh.core.model import AutoOptions
from diskf_mesh.estimators.base import DEFENCE, EXCHANGED, Estimator, Exchanged, Setting, State, run_scales

AUTO = Setting("auto", AutoOptions(), "the input models diskf-auto weighs and its chain (model.AutoOptions), "
               "the [estimator.auto] table")


@dataclass(frozen=True)
class AutoState(State):
    mu: np.ndarray | None = None      # (..., B, M) model probabilities, per bank (B: one per channel, or one)
    z: np.ndarray | None = None       # (..., B M, n + 2m) each filter's joint (x, e) posterior, bank after bank
    Z: np.ndarray | None = None       # (..., B M, n + 2m, n + 2m)
    d_hold: np.ndarray | None = None  # (..., m) the combined input (the message's d)
    S_hold: np.ndarray | None = None  # (..., m, m)
    held: np.ndarray | None = None    # (...,) an input estimate exists
    theta: np.ndarray | None = None   # (...,) log r, the own measurement noise scale (``core.noise``; 0 as stated)
    e_last: np.ndarray | None = None  # (..., p_max) the innovation of the last measured tick (``noise.track``)
    S_last: np.ndarray | None = None  # (..., p_max, p_max) its covariance
    seen: np.ndarray | None = None    # (...,) a tick was measured
    nu: np.ndarray | None = None      # (..., 3) the noise levels' probabilities (``noise_span``)
    # this tick's own measurement and sensor (H, R, rows, chi-square median), held from the local step to the
    # fusion, each with the agents' batch axes (so that a receiver fused apart is given its own)
    y: np.ndarray | None = None
    has: np.ndarray | None = None
    H: np.ndarray | None = None
    R: np.ndarray | None = None
    p: np.ndarray | None = None
    median: np.ndarray | None = None
    tick: int = 0


class DISKFAuto(Estimator):
    """``diskf-auto`` (ours, not the paper's): ``diskf-r`` over a bank of
    input models mixed by their evidence, as the interacting multiple model
    filter does (the module's docstring has the steps)."""

    name = "diskf-auto"
    label = "DISKF-auto"
    color = "crimson"
    settings = (AUTO, DEFENCE)
    extends = "diskf"
    exchanged = EXCHANGED + (Exchanged("w", str(len(im.BANK)), weights=True),)

    def __init__(self, model, sensors, params=None):
        super().__init__(model, sensors, params)
        o = self.params.auto
        q_process, q_sensor = run_scales(model, sensors)
        self.bank, self.a1, self.a2, self.q = im.default_bank(q_process, q_sensor, o.none, o.walk, o.zero_mean,
                                                              o.oscillating)
        self.r = np.ones(len(self.bank))  # each model's measurement noise level (``noise_level``; 1: as stated)
        if o.noise_level:
            self.bank, self.a1, self.a2, self.q, self.r = im.at_noise_level(self.bank, self.a1, self.a2, self.q,
                                                                            o.noise_level)
        self.stated = self.r == 1.0
        self.F = im.companion(self.a1, self.a2, model.m)  # (M, 2m, 2m): (IM2) on the pair (d_{k-1}, d_{k-2})
        # one bank per input channel (``per_channel``, m > 1): filter j of bank c holds channel c under model j
        # and every other channel under its bank's most probable model (``channel_models``)
        self.banks = model.m if o.per_channel else 1
        self.mu0 = im.initial_probabilities(self.a2, self.r)
        self.Pi = im.transition_matrix(len(self.bank), o.switch, self.mu0,
                                       im.hand_down(self.a1, self.a2, self.q, o.hand_down, self.r))
        # each model's place in a message's w (the models at the stated noise; the models at a level are not sent)
        self.slots = np.array([im.BANK.index(name) for name, r in zip(self.bank, self.r) if r == 1.0])
        self.whole_bank = tuple(self.bank) == im.BANK
        self.relaying = np.flatnonzero((self.a2 == 0.0) & (self.a1 != 0.0))  # persistent first-order models
        rho = self.a1[self.relaying][:, None, None]                                  # (J, 1, 1)
        # the relayed input: every channel with one bank, the bank's own channel with one per channel
        width = model.m if self.banks == 1 else 1
        self.relay_scales = rho, (rho * rho)[..., None], self.q[self.relaying][:, None, None, None] * identity(width)
        self.relay_pair = np.ones((1, 2))  # the fast CI of a model's own d_{k-1} with its neighbours' relayed one
        self.prior = 100.0 * float(self.q.max()) if self.q.max() > 0 else 1.0
        # the input into the state reads the pair's first half: x = v + G d_{k-1}
        self.G_pair = np.concatenate([model.G, np.zeros_like(model.G)], axis=-1)
        self.learn = o.noise
        self.levels = bool(o.noise_level)
        self.dof = float(o.evidence_dof)  # 0: Gaussian evidence
        # the neighbourhood's measurement noise weighed at R, sqrt(s) R and s R (``noise_span``), the stated level
        # as likely as the other two together before any evidence
        self.grid = None if not o.noise_span else np.array([1.0, float(np.sqrt(o.noise_span)), float(o.noise_span)])
        self.nu0, self.level_switch = np.array([0.5, 0.25, 0.25]), float(o.switch)
        self.median = chi2_median(sensors.p)  # (N,) m_p of (NL1)

    @classmethod
    def refuse(cls, params, model, sensors):
        """``noise_level`` with a bank per input channel: the level is one
        question for every sensor of the neighbourhood and every channel,
        which one bank asks."""
        o = params.auto
        if o.noise_level and o.per_channel and model.m > 1:
            return "estimator.auto.noise_level", (f"needs one bank: {model.m} input channels have one each "
                                                  "(per_channel = false shares one)")
        return None

    def init(self, batch: tuple) -> AutoState:
        s = super().init(batch)
        n, m, M, B = self.model.n, self.model.m, len(self.bank), self.banks
        S0 = np.broadcast_to(self.prior * np.eye(2 * m), batch + (2 * m, 2 * m)).copy()
        z, Z = im.joint(s.x, s.P, np.zeros(batch + (2 * m,)), S0, np.zeros(batch + (n, 2 * m)))
        return AutoState(s.x, s.P, s.since, mu=np.broadcast_to(self.mu0, batch + (B, M)).copy(),
                         z=np.repeat(z[..., None, :], B * M, axis=-2), Z=np.repeat(Z[..., None, :, :], B * M, axis=-3),
                         d_hold=np.zeros(batch + (m,)), S_hold=S0[..., :m, :m].copy(),
                         held=np.zeros(batch, dtype=bool), theta=np.zeros(batch),
                         nu=None if self.grid is None else np.broadcast_to(self.nu0, batch + (3,)).copy(),
                         **(dict(zip(("e_last", "S_last", "seen"),
                                     noise.first_innovation(batch, self.sensors.H.shape[-2]))) if self.learn else {}))

    def local(self, state: AutoState, k: int, y, has):
        # with the noise learned, the own measurement weighed by 1 / r (``core.noise``)
        loc = self.local_kf(state, k, y, has, np.exp(-state.theta) if self.learn else None)
        own = {}
        if self.learn:
            batch, sn = has.shape, self.sensors
            own = dict(y=y, has=has, H=np.broadcast_to(sn.H, batch + sn.H.shape[-2:]),
                       R=np.broadcast_to(sn.R, batch + sn.R.shape[-2:]), p=np.broadcast_to(sn.p, batch),
                       median=np.broadcast_to(self.median, batch))
        st = AutoState(state.x, state.P, np.where(has, 0, state.since + 1), Y_pred=loc.Y, mu=state.mu, z=state.z,
                       Z=state.Z, d_hold=state.d_hold, S_hold=state.S_hold, held=state.held, theta=state.theta,
                       e_last=state.e_last, S_last=state.S_last, seen=state.seen, nu=state.nu, tick=k, **own)
        # the message's w: the bank's probabilities (a new array every tick, never changed), the banks' mean
        # with one per channel
        mu = state.mu[..., 0, :] if self.banks == 1 else state.mu.mean(axis=-2)
        if self.levels:  # the models at the stated noise, renormalised
            mu = mu[..., self.stated] / im.sum_last(mu[..., self.stated])[..., None]
        if self.whole_bank:
            w = mu
        else:
            w = np.zeros(mu.shape[:-1] + (len(im.BANK),))
            w[..., self.slots] = mu
        return st, Message(loc.x_pred, loc.P_pred, loc.x_upd, loc.P_upd, state.d_hold, state.S_hold, state.held, w)

    def fuse(self, state: AutoState, own: Message, senders: Message, nb: Neighbourhood):
        n, m = self.model.n, self.model.m
        A = self.model.A_at(state.tick)
        _, Yp, Yu = self.fusion_inverses(state, own, senders)
        dy, dY = eq.information_contribution(senders.x_pred, Yp, senders.x_upd, Yu)
        U, u = nbr_sum(nb.adj, dY, 2), nbr_sum(nb.adj, dy, 1)
        ones = np.ones(senders.x_pred.shape[:-1], dtype=bool)
        x_c, P_c, _ = eq.input_fusion(nb.adj, senders.x_pred, senders.P_pred, ones)  # the CI prior
        # 2. mixing: the senders' model probabilities pooled where the neighbourhood measured nothing this tick,
        # the agent's own where it did
        informed = np.trace(U, axis1=-2, axis2=-1) > 0
        pooled = state.mu if informed.all() else self._pool(state.mu, senders, nb, ~informed)
        c, w = im.model_weights(pooled, self.Pi, PRUNE)                               # per bank
        z0, Z0 = self._flat(*im.mix(w, *self._banked(state.z, state.Z), bounded=True))
        x0, P0, e0, S0, C0 = im.split(z0, Z0, n)
        # 3. per model: predict (the input pair e = (d_{k-1}, d_{k-2})), the CI prior, the relayed inputs,
        # the input into the state
        if self.banks == 1:
            e1, B, S1 = im.pair_predict(A, C0, e0, S0, self.F, self.q)
        else:
            F, noise_e = im.channel_models(self.a1, self.a2, self.q, pooled.argmax(axis=-1))
            e1, B, S1 = im.pair_predict(A, C0, e0, S0, F, 0.0, noise_e)
        v, Pv = eq.predict(x0, P0, A, self.model.Q)
        v_c, Pv_c, _ = im.affine_prior(own.x_pred, own.P_pred, x_c, P_c, v, Pv, B)
        e1, B, S1 = eq.replace_marginal(v, Pv, e1, B, S1, v_c, Pv_c)
        v, Pv, e1, S1, B, relayed = self._relay(senders, nb, v_c, Pv_c, e1, S1, B)
        x_s, P_s, C_s = eq.input_to_state(v, Pv, B, e1, S1, self.G_pair)
        # 4. the measurement: likelihoods and the joint update
        nu = state.nu
        if self.grid is not None:  # the neighbourhood's noise weighed at three levels, with the models
            E, k = self._energies(dY, dy, nb)
            x_k, P_k, e_k, C_k, S_k, loglik, nu = measure_levels(
                x_s, P_s, e1, C_s, S1, U, u, informed, E, k, self.grid, self._over_banks(c), state.nu,
                self.level_switch)
        elif self.levels:  # the neighbourhood's information under each model's noise level
            U, u, level_ll, heavy = self._at_levels(*self._energies(dY, dy, nb), U, u)
            x_k, P_k, e_k, C_k, S_k, loglik = measure(x_s, P_s, e1, C_s, S1, U, u, informed, per_model=True,
                                                      heavy=heavy)
            loglik = loglik + np.where(informed[..., None], level_ll, 0.0)
        else:  # with evidence_dof, a Student-t's evidence from the senders' measurement energies
            heavy = None if not self.dof else (*(a[..., None] for a in self._energies(dY, dy, nb)), self.dof)
            x_k, P_k, e_k, C_k, S_k, loglik = measure(x_s, P_s, e1, C_s, S1, U, u, informed, heavy=heavy)
        mu = im.update_probabilities(c, loglik.reshape(c.shape), FLOOR)
        if self.banks > 1:
            mu = im.follow_informed(mu, loglik.reshape(c.shape), BLIND)
        theta, last = state.theta, (state.e_last, state.S_last, state.seen)
        if self.learn:  # 5. the own sensor's noise scale, scored against the bank's predicted mean
            theta, last = noise.track(theta, last, im.mixture_mean(self._over_banks(c), x_s), own.P_pred, state.y,
                                      state.H, state.R, state.p, state.has, state.median, NOISE_STEP)
        z, Z = im.joint(x_k, P_k, e_k, S_k, C_k)
        # the output (each entry of a mixture its own sums: the same bits as the whole joint's): the state's
        # mixture over the models of probability PRUNE or more; the input's over every model, so that it never
        # claims the zero-input model's certainty (S = 0) when that model alone holds the probability
        xc, Pc = im.mix(self._over_banks(im.output_weights(mu, PRUNE))[..., :, None], z[..., :n], Z[..., :n, :n])
        dc, Sc = im.mix(self._over_banks(mu)[..., :, None], z[..., n:n + m], Z[..., n:n + m, n:n + m])
        x, P, d, S = xc[..., 0, :], Pc[..., 0, :, :], dc[..., 0, :], Sc[..., 0, :, :]
        held = state.held | informed | relayed
        st = AutoState(x, P, state.since, mu=mu, z=z, Z=Z, d_hold=d, S_hold=S, held=held, theta=theta,
                       e_last=last[0], S_last=last[1], seen=last[2], nu=nu, tick=state.tick)
        return st, Output(x, P, d, held)

    def _pool(self, mu, senders, nb, blind):
        """``mu`` with the rows of ``blind`` (the receivers whose
        neighbourhood measured nothing) given their senders' probabilities
        of the models at the stated noise, pooled
        (``input_models.pool_probabilities``, each receiver's row alone: the
        same bits as over the whole batch): they take the share the
        receiver's own probabilities give those models, and the models at
        another noise level keep the receiver's own (the message carries
        the stated models' alone)."""
        adj = nb.adj[blind]                                                            # (K, S)
        w = np.broadcast_to(senders.w[..., None, :, :], nb.adj.shape + senders.w.shape[-1:])[blind]
        pooled = im.pool_probabilities(adj[:, None, :], w[..., self.slots], FLOOR)  # (K, 1, M): one for every bank
        out = mu.copy()
        if not self.levels:
            out[blind] = pooled
        else:
            own = mu[blind]
            own[..., self.stated] = pooled * im.sum_last(own[..., self.stated])[..., None]
            out[blind] = own
        return out

    def _at_levels(self, E, k, U, u):
        """The neighbourhood's measurement information (U, u) under each
        model's noise level r_j (every sensor's noise r_j R): (U / r_j, u /
        r_j) per model, (..., M, n, n) and (..., M, n); the part of each
        model's log-likelihood its level adds to ``information_loglik``'s,
        -E / (2 r_j) - k log(r_j) / 2, E and k the senders' measurement
        energies and ranks summed (``input_models.information_energy``,
        ``_energies``); and ``measure``'s ``heavy`` (None without
        ``evidence_dof``). With a Student-t's evidence the energy is E / r_j
        in the t (``heavy``) and the level's part -k log(r_j) / 2 alone
        (log det(r_j R))."""
        level = -0.5 * k[..., None] * np.log(self.r)
        if not self.dof:
            return U[..., None, :, :] / self.r[:, None, None], u[..., None, :] / self.r[:, None], \
                level - 0.5 * E[..., None] / self.r, None
        return U[..., None, :, :] / self.r[:, None, None], u[..., None, :] / self.r[:, None], level, \
            (E[..., None] / self.r, k[..., None], self.dof)

    @staticmethod
    def _energies(dY, dy, nb):
        """(E, k) of every receiver: its senders' measurement energies
        y^T R^-1 y and ranks (``input_models.information_energy``) summed
        over its neighbourhood, (...,) each."""
        energy, rank = im.information_energy(dY, dy)
        return tuple(nbr_sum(nb.adj, a[..., None], 1)[..., 0] for a in (energy, rank))

    def _banked(self, z, Z):
        """The filters' joints (..., B M, ...) as (..., B, M, ...)."""
        M = len(self.bank)
        return z.reshape(z.shape[:-2] + (self.banks, M) + z.shape[-1:]), \
            Z.reshape(Z.shape[:-3] + (self.banks, M) + Z.shape[-2:])

    def _flat(self, z, Z):
        """The inverse of ``_banked``."""
        return z.reshape(z.shape[:-3] + (-1,) + z.shape[-1:]), Z.reshape(Z.shape[:-4] + (-1,) + Z.shape[-2:])

    def _over_banks(self, w):
        """Per-bank weights (..., B, M) as one mixture over every filter
        (..., B M): each bank's weights the same share 1 / B."""
        return w[..., 0, :] if self.banks == 1 else w.reshape(w.shape[:-2] + (-1,)) / self.banks

    def _relay(self, senders, nb, v, Pv, e, S, B):
        """The neighbours' relayed inputs (``_relay_bank``) for the one
        bank, or for each bank per channel its own channel's. Returns (v,
        Pv, e, S, B) and whether any was relayed."""
        if self.banks == 1:
            return self._relay_bank(senders, nb, v, Pv, e, S, B, self.relaying, None)
        relayed = None
        for c in range(self.banks):
            v, Pv, e, S, B, got = self._relay_bank(senders, nb, v, Pv, e, S, B, c * len(self.bank) + self.relaying, c)
            relayed = got if relayed is None else relayed | got
        return v, Pv, e, S, B, relayed

    def _relay_bank(self, senders, nb, v, Pv, e, S, B, js, channel):
        """The neighbours' relayed inputs (their combined d, S) under each
        persistent first-order model (a2 = 0, rho = a1 > 0): the fast CI of
        the other neighbours' (rho d_j, rho^2 S_j + q I), then the fast CI of
        that with the model's own prediction of d_{k-1}, replaces the
        model's marginal of d_{k-1} in the joint (v, d_{k-1}, d_{k-2}), the
        conditional of the rest kept (``input_models.replace_input``). The
        agent's own message is left out: its combined input mixes the models
        this one is to stay apart from. (v, Pv, e, S, B): each model's joint
        as ``input_models.split`` gives it, (..., M, ...); the models are one
        more batch axis of the same functions. Returns them with the
        relaying models' replaced (in place: the arrays are this tick's
        own), and whether any was. ``js``: the relaying models' filters;
        ``channel``: with a bank per channel, the one channel the relay
        replaces (its d_{k-1} moved to the pair's front for
        ``replace_input``, then back), the senders' combined input read on
        it; None: every channel."""
        m = self.model.m
        d_s, S_s = senders.d, senders.S
        if channel is not None:
            m = 1
            d_s, S_s = d_s[..., channel:channel + 1], S_s[..., channel:channel + 1, channel:channel + 1]
            order = np.r_[channel, np.delete(np.arange(e.shape[-1]), channel)]   # the channel's d_{k-1} first
            back = np.argsort(order)
        others = nb.adj * ~nb.self_mask
        if js.size == 0 or not (others * senders.d_valid[..., None, :]).any():  # no other sender relays an input
            return v, Pv, e, S, B, np.zeros(v.shape[:-2], dtype=bool)
        rho, rho2, qI = self.relay_scales
        d_n, S_n, has_n = eq.input_fusion(others[..., None, :, :], rho * d_s[..., None, :, :],
                                          rho2 * S_s[..., None, :, :, :] + qI,
                                          senders.d_valid[..., None, :])           # (..., J, R, ...)
        d_n, S_n, has_n = d_n.swapaxes(-3, -2), S_n.swapaxes(-4, -3), has_n.swapaxes(-2, -1)
        parts = tuple(np.take(a, js, axis=axis) for a, axis in ((v, -2), (Pv, -3), (e, -2), (S, -3), (B, -3)))
        moved = parts if channel is None else _reorder(parts, order)
        dj, Sj = moved[2][..., :m], moved[3][..., :m, :m]                           # (..., R, J, ...)
        pair = eq.input_fusion_scalar if m == 1 else eq.input_fusion  # the same bits, faster on two senders
        d_r, S_r, _ = pair(self.relay_pair, np.stack([dj, d_n], axis=-2), np.stack([Sj, S_n], axis=-3),
                           np.stack([np.ones_like(has_n), has_n], axis=-1))
        new = im.replace_input(*moved, d_r[..., 0, :], S_r[..., 0, :, :])
        if channel is not None:
            new = _reorder(new, back)
        some = not has_n.all()
        for whole, old, part in zip((v, Pv, e, S, B), parts, new):
            core = (slice(None),) * (part.ndim - has_n.ndim)
            if some:
                part = np.where(has_n[(...,) + (None,) * len(core)], part, old)
            whole[(..., js) + core] = part
        return v, Pv, e, S, B, has_n.any(axis=-1)


def _reorder(parts, order):
    """(v, Pv, e, S, B) with the input pair's entries (e's, S's rows and
    columns, B's columns) in ``order``."""
    v, Pv, e, S, B = parts
    return v, Pv, e[..., order], S[..., order, :][..., order], B[..., order]


def measure(x_s, P_s, e1, C_s, S1, U, u, informed, per_model=False, heavy=None):
    """Step 4 on the agents whose neighbourhood measured (``informed``): each
    model's joint Kalman update of (x, e) by the neighbourhood's information
    (U, u) and its log-likelihood (``information_loglik``). Where nothing
    was measured the update is the prediction, bit for bit, and the
    log-likelihood 0 (no evidence for any model), so those agents' rows are
    neither computed nor rounded. ``per_model``: U (..., M, n, n) and u
    (..., M, n) each model's own (``noise_level``). ``heavy`` = (E, k, nu):
    a Student-t's evidence (``information_loglik``), E and k (..., 1) per
    agent, or (..., M) per agent and model (``noise_level``'s E / r_j).
    Returns (x, P, e, C, S, loglik)."""
    blank = np.zeros(x_s.shape[:-1])
    if not informed.any():
        return x_s, P_s, e1, C_s, S1, blank
    every = bool(informed.all())
    prior = (x_s, P_s, e1, C_s, S1)
    xs, Ps, e, C, S = prior if every else (a[informed] for a in prior)
    U_m, u_m = (U, u) if every else (U[informed], u[informed])
    if not per_model:
        U_m, u_m = U_m[..., None, :, :], u_m[..., None, :]
    Y, Ji, U_m = eq.information_pair_psd(Ps, U_m)
    if heavy is not None:
        E, k, nu = heavy
        if not every:
            E, k = E[informed], k[informed]
        heavy = (E, k, nu)
    loglik = im.information_loglik(xs, Ps, Y, Ji, U_m, u_m, heavy)
    x_k, P_k = eq.local_update(xs, Ps, Y, Ji, u_m)
    post = (x_k, P_k) + eq.replace_marginal(xs, Ps, e, C, S, x_k, P_k) + (loglik,)
    if every:
        return post
    out = []
    for whole, part in zip(prior + (blank,), post):
        whole = whole.copy()
        whole[informed] = part
        out.append(whole)
    return tuple(out)


def measure_levels(x_s, P_s, e1, C_s, S1, U, u, informed, E, k, grid, c, nu, switch: float):
    """``measure`` with the neighbourhood's measurement noise weighed at the
    levels of ``grid`` (L,) (``[estimator.auto] noise_span``): each model's
    log-likelihood at each level r (``information_loglik`` at (U / r,
    u / r), with the level's -E / (2 r) - k log(r) / 2; E, k (...,) the
    senders' measurement energies and ranks), the levels' probabilities
    ``nu`` (..., L) one step of their chain (stay with 1 - ``switch``)
    then weighed by the models' mixture ``c`` (..., M)
    (``input_models.level_posterior``), and each model's update at its
    posterior mean precision, sum_l resp_lj / r_l. Where nothing was
    measured: the prediction, log-likelihood 0 and ``nu`` as it was.
    Returns (x, P, e, C, S, loglik, nu)."""
    blank = np.zeros(x_s.shape[:-1])
    if not informed.any():
        return x_s, P_s, e1, C_s, S1, blank, nu
    every = bool(informed.all())
    prior = (x_s, P_s, e1, C_s, S1)
    xs, Ps, e, C, S = prior if every else (a[informed] for a in prior)
    U_i, u_i, E_i, k_i, c_i, nu_i = (U, u, E, k, c, nu) if every else \
        (a[informed] for a in (U, u, E, k, c, nu))
    U_i, u_i = U_i[..., None, :, :], u_i[..., None, :]
    lls, Y, logdet_Y = [], None, None
    for r in grid.tolist():
        Y, Ji, U_r = eq.information_pair_psd(Ps, U_i / r, Y)
        if logdet_Y is None:  # one prediction for every level: its log det once
            logdet_Y = np.linalg.slogdet(Y)[1]
        lls.append(im.information_loglik(xs, Ps, Y, Ji, U_r, u_i / r, logdet_Y=logdet_Y) - 0.5 * E_i[..., None] / r
                   - 0.5 * k_i[..., None] * np.log(r))
    L = len(grid)
    nu_pred = (1.0 - switch) * nu_i + switch * (1.0 - nu_i) / (L - 1)
    loglik, nu_post, resp = im.level_posterior(np.stack(lls, axis=-2), c_i, nu_pred, FLOOR)
    rho = resp[..., 0, :] / grid[0]
    for level in range(1, L):
        rho = rho + resp[..., level, :] / grid[level]
    Y, Ji, U_m = eq.information_pair_psd(Ps, U_i * rho[..., None, None], Y)
    x_k, P_k = eq.local_update(xs, Ps, Y, Ji, u_i * rho[..., None])
    post = (x_k, P_k) + eq.replace_marginal(xs, Ps, e, C, S, x_k, P_k) + (loglik, nu_post)
    if every:
        return post
    out = []
    for whole, part in zip(prior + (blank, nu), post):
        whole = whole.copy()
        whole[informed] = part
        out.append(whole)
    return tuple(out)


NOISE_STEP = 0.2  # step of (NL1) (``core.noise``): the most a measured tick moves log r
BLIND = 1e-3  # a bank whose models' log-likelihoods this tick differ by less learned nothing (``follow_informed``)
FLOOR = 1e-6  # the smallest model probability (``input_models.update_probabilities``)
PRUNE = 1e-3  # mixing and output weights below it are dropped (``input_models.model_weights``, ``output_weights``)


# the median of a chi-square of p = 1..16 degrees of freedom, scipy.stats.chi2.median's values to the last bit
# (tests/test_auto.py): importing scipy.stats takes 0.6 s of CPU, scipy.special 0.2 s, and every command
# imports this module
CHI2_MEDIANS = np.array([
    0.454936423119572, 1.386294361119891, 2.3659738843753377, 3.3566939800333224,
    4.351460191095526, 5.348120627447118, 6.345811195521515, 7.344121497701794,
    8.342832692252955, 9.34181776559197, 10.340998074391827, 11.34032237742414,
    12.339755882563905, 13.33927414909954, 14.338859510956645, 15.338498885001608,
])


def chi2_median(p: np.ndarray) -> np.ndarray:
    """The median of a chi-square of ``p`` degrees of freedom, as
    ``scipy.stats.chi2.median`` computes it (2 P^-1(p/2, 1/2), the inverse of
    the regularised lower incomplete gamma function): from ``CHI2_MEDIANS``
    up to 16 rows, from ``scipy.special`` (imported only then) beyond."""
    p = np.asarray(p)
    if p.size and 1 <= p.min() and p.max() <= len(CHI2_MEDIANS):
        return CHI2_MEDIANS[p - 1]
    from scipy.special import gammaincinv

    return 2 * gammaincinv(p / 2, 0.5)
