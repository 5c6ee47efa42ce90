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
        return Sensors(tuple(self.ids[i] for i in idx), self.H[idx], self.R[idx], self.p[idx])

    def pad(self, y_i, i: int) -> np.ndarray:
        """One agent's length-p^i measurement as a padded length-p_max vector."""
        out = np.zeros(self.H.shape[1])
        out[: self.p[i]] = y_i
        return out


COMPENSATION_FORMS = ("bounded", "paper", "normalized", "none")


@dataclass(frozen=True)
class RobustOptions:
    """The ingredients of ``diskf-r`` (``algorithms/diskf_robust.py``), one
    switch each, all on by default; the derivations are in that module's
    docstrings and the ablation table of docs/reproduction.md turns each off.

    prior_ci:    fuse the neighbours' predictions by covariance intersection
                 before adding their measurement information
    joint_input: the input from the neighbourhood's stacked measurement
                 information (exact Gillijns-De Moor), not CI of the
                 individual estimates
    gate:        feed the input into the state (unbiased update) only where
                 the neighbourhood's sensors make it strongly detectable
    relay:       carry the fused input forward and share it: the message's
                 (d, S) is the sender's last fused input (Algorithm 1, step 2)
    inject:      the input covariance in the prediction, P^* = P^ + G S G^T
    latch:       once the unbiased update ran, keep running it while rank(HG) = m
                 (until a tick without any usable measurement)
    inflate:     where the input is assumed (not detectable), scale the prior
                 by the innovation's fading factor when the measurement shows
                 it too small
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
    inflate: bool = True
