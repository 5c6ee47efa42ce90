"""Measurement noise learned online (``diskf-auto``; our derivation, not the
paper's equations).

Each agent holds one scale r of its own sensor's stated covariance: the
world's measurement noise is taken to be N(0, r R / lambda_k), r lasting
and lambda_k a tick's own (a Student-t measurement of ``dof`` degrees of
freedom: a burst is a tick of small lambda, not a change of r). At each
tick the agent measures, with the prediction N(x, P) it scores the
measurement against (in ``diskf-auto`` the state predicted with the input
it last fused, so that an input the bank already follows is not read as
noise), e = y - H x and S = H P H^T + r R:

    weight  w = min(1, (dof + p) / (dof + e^T S^-1 e))                       (NL1)

the Student-t update's weight of the measurement (one step of its EM; only
ever down: a tick is never trusted more than stated), and theta = log r
takes one step of recursive Fisher scoring on the Gaussian log-likelihood
log N(e; 0, S(r)) (the residual weighted by w):

    score   g = r / 2 [w e^T S^-1 R S^-1 e - tr(S^-1 R)]
    info    i = r^2 / 2 tr(S^-1 R S^-1 R)
            I <- f I + (1 - f) I0 + i,   theta <- theta + g / I              (NL2)

(the padding rows of a shorter sensor, R = I and H = 0 there, left out of
both traces). I is the information gathered on theta, forgotten by 1 - f
per measured tick towards the prior's I0, so that r follows a world that
changes; a tick on which the agent measures nothing changes nothing.
Recursive scoring reaches r = 10 where one variational Bayes step
(Särkkä and Nummenmaa 2009) per tick crawls: where H P H^T is not small
against r R its update of r is mostly its own prior.

The agent then weighs its measurement by w / r (its information U w / r,
u w / r).

Every function is pure, with leading batch axes.
"""
from __future__ import annotations

import numpy as np

from diskf_mesh.core.linalg import T, inv_spd, mv, sym

LOW, HIGH = 0.0, np.log(1e3)  # theta's bounds: r from 1 (as stated) to 10^3


def learn(theta, info, x, P, y, H, R, p, has, info0: float, f: float, dof: float):
    """(NL1), (NL2) where ``has``: (theta, info, w), unchanged (w = 1) elsewhere.
    H: (..., p_max, n) and R: (..., p_max, p_max), padded as ``model.Sensors``
    (zero rows of H, an identity block of R); p: (...,) the true rows; y
    zero in the padding rows."""
    r = np.exp(theta)
    pad = H.shape[-2] - p
    S = sym(np.matmul(np.matmul(H, P), T(H)) + r[..., None, None] * R)
    Si = inv_spd(S)
    e = y - mv(H, x)
    SiR = np.matmul(Si, R)
    nis = _dot(e, mv(Si, e))
    w = np.minimum(1.0, (dof + p) / (dof + nis))
    quad = _dot(e, mv(np.matmul(SiR, Si), e))
    score = 0.5 * r * (w * quad - (np.trace(SiR, axis1=-2, axis2=-1) - pad / r))
    fisher = 0.5 * r * r * (np.einsum("...ij,...ji->...", SiR, SiR) - pad / (r * r))
    gathered = f * info + (1.0 - f) * info0 + fisher
    step = np.clip(theta + score / gathered, LOW, HIGH)
    return np.where(has, step, theta), np.where(has, gathered, info), np.where(has, w, 1.0)


def _dot(a, b):
    return np.einsum("...i,...i->...", a, b)
