"""Component vocabulary: the shared motion model, the agents' sensors, the
compensation gain forms and diskf-r's switches. Plain frozen dataclasses
over numpy arrays. The estimators' parameters are declared by each
estimator (``estimators.base.Setting``) and gathered in ``estimators.Params``."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True)
class LinearModel:
    """x_k = A_{k-1} x_{k-1} + G d_{k-1} + w_{k-1},  w ~ N(0, Q)  (eq1).

    A: (K, n, n), A[k-1] is A_{k-1}, used to go from tick k-1 to tick k
       (k = 1..K). A time-invariant model repeats one matrix.
    """

    A: np.ndarray
    G: np.ndarray
    Q: np.ndarray
    x0: np.ndarray
    P0: np.ndarray

    @property
    def n(self) -> int:
        return self.G.shape[0]

    @property
    def m(self) -> int:
        return self.G.shape[1]

    @property
    def steps(self) -> int:
        return self.A.shape[0]

    def A_at(self, k: int) -> np.ndarray:
        """A_{k-1}: the transition into tick k (k >= 1)."""
        return self.A[k - 1]


@dataclass(frozen=True)
class Sensors:
    """Heterogeneous sensors y^i = H^i x + v^i, v^i ~ N(0, R^i)  (eq2).

    Sensors of different p^i are padded to p_max rows: zero rows in H and an
    identity block in R, which adds no information (see
    ``equations.measurement_information``). ``p[i]`` is agent i's true p^i.
    """

    ids: tuple
    H: np.ndarray  # (N, p_max, n)
    R: np.ndarray  # (N, p_max, p_max)
    p: np.ndarray  # (N,)
    # the run's sensors this is a selection of (``select``): an agent process holds its own sensor
    # alone, and takes the run's scales (``input_models.input_scales``) from every sensor, as the engine
    run: "Sensors | None" = field(default=None, compare=False, repr=False)
    # what is computed once from every sensor of the run (``whole``) and shared by its selections
    derived: dict = field(default_factory=dict, compare=False, repr=False)

    @property
    def whole(self) -> "Sensors":
        """Every sensor of the run (these, unless they are a ``select``ion)."""
        return self if self.run is None else self.run

    @classmethod
    def from_list(cls, ids, Hs, Rs) -> "Sensors":
        Hs = [np.atleast_2d(np.asarray(h, dtype=float)) for h in Hs]
        Rs = [np.atleast_2d(np.asarray(r, dtype=float)) for r in Rs]
        n = Hs[0].shape[1]
        pmax = max(h.shape[0] for h in Hs)
        N = len(Hs)
        H = np.zeros((N, pmax, n))
        R = np.broadcast_to(np.eye(pmax), (N, pmax, pmax)).copy()
        for i, (h, r) in enumerate(zip(Hs, Rs)):
            H[i, : h.shape[0]] = h
            R[i, : h.shape[0], : h.shape[0]] = r
        return cls(tuple(ids), H, R, np.array([h.shape[0] for h in Hs]))

    @property
    def N(self) -> int:
        return self.H.shape[0]

    def select(self, idx) -> "Sensors":
        idx = np.atleast_1d(idx)
        return Sensors(tuple(self.ids[i] for i in idx), self.H[idx], self.R[idx], self.p[idx], run=self.whole)

    def pad(self, y_i, i: int) -> np.ndarray:
        """One agent's length-p^i measurement as a padded length-p_max vector."""
        out = np.zeros(self.H.shape[1])
        out[: self.p[i]] = y_i
        return out


COMPENSATION_FORMS = ("bounded", "paper", "normalized", "none")


@dataclass(frozen=True)
class RobustOptions:
    """The ingredients of ``diskf-r`` (``estimators/diskf_robust.py``), one
    switch each; the derivations are in that module's docstrings and the
    ablation table of docs/reproduction.md turns each on or off.

    persist:     the input follows an input model (``input_model``): the joint
                 Kalman filter of (x, d), the cross-covariance carried (default on)
    input_model: ``walk`` (the random walk d_{k-1} = d_{k-2} + eta, default),
                 ``mean-reverting`` (d_{k-1} = input_rho d_{k-2} + eta) or
                 ``none`` (no input) (``input_models``, eq. IM)
    input_rho:   rho of the mean-reverting model, 0 <= rho < 1 (0: a zero-mean
                 input of variance input_walk per tick)
    input_walk:  eta ~ N(0, input_walk * I), the model's covariance per tick
                 (input units squared); None: from the scenario's scales,
                 sqrt(q_process q_sensor) (``input_models.default_scales``)
    input_prior: S0 = input_prior * I, the input's covariance before any
                 measurement (input units squared); None: 10^4 max(q_process,
                 q_sensor), an input a hundred times the larger noise scale
    prior_ci:    fuse the neighbours' predictions by covariance intersection
                 before adding their measurement information
    relay:       carry the fused input forward and share it: the message's
                 (d, S) is the sender's last fused input (Algorithm 1, step 2),
                 and the neighbours' relayed inputs are fused by CI
    inject:      the input's covariance in the prediction,
                 P* = P^ + G B^T + B G^T + G S G^T (the paper: P* = P^)
    joint_input: the message carries the fused input (not the local estimate);
                 the unbiased update uses the stacked measurement information
    unbiased:    where the heard sensors detect the input (``gate``), the exact
                 Gillijns-De Moor update, the input's prior dropped (off)
    gate:        ... only where the neighbourhood's sensors make the input
                 strongly detectable
    latch:       ... and after such a tick while rank(HG) = m holds
    inflate:     scale the prior by the innovation's fading factor when the
                 measurement shows it too small (off)
    window:      the paper's observation window (with Params.window, reset)
    compensate:  the paper's state compensation (Params.compensation, eps)
    """

    prior_ci: bool = True
    joint_input: bool = True
    gate: bool = True
    relay: bool = True
    inject: bool = True
    window: bool = False
    compensate: bool = False
    latch: bool = True
    inflate: bool = False
    persist: bool = True
    unbiased: bool = False
    input_model: str = "walk"
    input_rho: float = 0.0
    input_walk: float | None = None
    input_prior: float | None = None

    CHOICES = {"input_model": ("walk", "mean-reverting", "none")}  # the string fields' values (input_models.INPUT_MODELS)

    def __post_init__(self):
        for name in ("input_walk", "input_prior"):
            v = getattr(self, name)
            if v is not None and (not _number(v) or not np.isfinite(v) or v <= 0):
                raise ValueError(f"robust.{name}: must be a finite positive number, got {v!r}")
        if self.input_model not in self.CHOICES["input_model"]:
            raise ValueError(f"robust.input_model: must be one of {', '.join(self.CHOICES['input_model'])}, "
                             f"got {self.input_model!r}")
        if not _number(self.input_rho) or not 0 <= self.input_rho < 1:
            raise ValueError(f"robust.input_rho: must be a number with 0 <= rho < 1, got {self.input_rho!r}")


def _number(v) -> bool:
    return isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, (bool, np.bool_))



@dataclass(frozen=True)
class AutoOptions:
    """The settings of ``diskf-auto`` (``estimators/diskf_auto.py``), the
    ``[estimator.auto]`` table: which input models its bank holds
    (``input_models.default_bank``; at least one) and the chance per tick
    that the input changes model (the IMM chain's ``switch``, 0 < switch < 1).

    none:      a model without input
    walk:      random walks at three scales (persistent inputs: steps, ramps)
    zero_mean: zero-mean inputs at two scales and mean-reverting ones
               (rho = exp(-1/10)) at two (noise-like, switching, fast inputs)
    oscillating: oscillating inputs, periods 4 to 32 ticks in quarter
               octaves (``input_models.oscillating``: vibration, weaving)
    switch:    the models' Markov chain: 1 - switch to stay (0.001: a change of
               input model expected about once in 1,000 ticks)
    hand_down: the chain's added chance per tick that a random walk moves to
               each walk of a smaller scale (``input_models.hand_down``): a
               persistent input learned at a larger scale reaches the
               smaller ones through the mixing (0 <= hand_down < 1)
    per_channel: with m > 1 input channels, one bank per channel, so that
               each channel has its own model probabilities (a step on one,
               an oscillation on another); off: the channels share one
               bank's models
    noise_level: the bank also holds its models without input and its two
               smaller random walks under measurement noise noise_level x R
               at every sensor of the neighbourhood
               (``input_models.at_noise_level``; 0: not; one bank only: m = 1
               or per_channel off)
    evidence_dof: the models' evidence of a tick read as a Student-t of
               evidence_dof degrees of freedom instead of a Gaussian
               (``input_models.information_loglik``): an innovation far
               beyond every model's spread (a burst, a sensor noisier than
               its R) moves the probabilities by the log of its size, not
               its square (0: Gaussian; with noise_level, each model's
               energy at its own level)
    noise_span: s > 1: each agent weighs the measurement noise of its
               neighbourhood at three levels, R, sqrt(s) R and s R, by their
               evidence (``input_models.level_posterior``): each model's
               likelihood at each level, a probability per level carried
               from tick to tick (the chain's ``switch``), and each model's
               update at its posterior mean precision (0: not; not with
               noise_level or noise)
    noise:     each agent learns the scale of its own measurement noise,
               above or below the stated R (``core.noise``), and weighs its
               measurement by it (off by default: with poor sensors and no
               input it costs up to 30 %, on inputs that switch or jump
               5-15 %, docs/estimators.md)
    """

    none: bool = True
    walk: bool = True
    zero_mean: bool = True
    oscillating: bool = True
    switch: float = 0.001
    hand_down: float = 0.001
    noise: bool = False
    per_channel: bool = True
    noise_level: float = 0.0
    evidence_dof: float = 0.0
    noise_span: float = 0.0

    def __post_init__(self):
        if not (self.none or self.walk or self.zero_mean or self.oscillating):
            raise ValueError("auto: at least one of none, walk, zero_mean, oscillating must be true")
        if isinstance(self.switch, bool) or not np.isfinite(self.switch) or not 0 < self.switch < 1:
            raise ValueError(f"auto.switch: must be a number between 0 and 1 (exclusive), got {self.switch!r}")
        if isinstance(self.hand_down, bool) or not np.isfinite(self.hand_down) or not 0 <= self.hand_down < 1:
            raise ValueError(f"auto.hand_down: must be a number from 0 to 1 (1 excluded), got {self.hand_down!r}")
        if isinstance(self.noise_level, bool) or not np.isfinite(self.noise_level) or self.noise_level < 0 \
                or self.noise_level == 1:
            raise ValueError(f"auto.noise_level: must be 0 (none) or a positive number other than 1, "
                             f"got {self.noise_level!r}")
        if self.noise_level and self.noise:
            raise ValueError("auto.noise_level: give either noise_level or noise = true, not both")
        if isinstance(self.noise_span, bool) or not np.isfinite(self.noise_span) or not (
                self.noise_span == 0 or self.noise_span > 1):
            raise ValueError(f"auto.noise_span: must be 0 (none) or a number above 1, got {self.noise_span!r}")
        if self.noise_span and (self.noise_level or self.noise):
            raise ValueError("auto.noise_span: give one of noise_span, noise_level and noise = true")
        if isinstance(self.evidence_dof, bool) or not np.isfinite(self.evidence_dof) or self.evidence_dof < 0:
            raise ValueError(f"auto.evidence_dof: must be 0 (Gaussian) or a positive number, got {self.evidence_dof!r}")
