"""Measurement noise learned online (``diskf-auto``; our derivation, not the
paper's equations).

Each agent holds one scale r of its own sensor's stated covariance: the
world's measurement noise is taken to be N(0, r R). At each tick the agent
measures, with the prediction N(x, P) it scores the measurement against (in
``diskf-auto`` the state predicted with the input it last fused, so that an
input the bank already follows is not read as noise), e = y - H x,
S = H P H^T + r R and the normalised innovation s = e^T S^-1 e, theta =
log r takes one step of a stochastic approximation of the median:

    share   c = tr(S^-1 r R) / p                       (0 < c <= 1)
    theta <- clip(theta + step sqrt(c) sign(s - m_p), log LOW, log HIGH)     (NL1)

m_p the median of the chi-square distribution of p degrees of freedom (p
the sensor's rows; the padding rows of a shorter sensor, R = I and H = 0
there, left out of the trace). Its fixed point is the r at which s lies
above its median as often as below: where the sensor is r times noisier
(or calmer) than stated, and nothing else is wrong, that is r. A tick
moves theta by at most ``step`` whatever its innovation, so a jump of the
input that the bank follows within a few ticks moves r by a few steps
only, where a likelihood's score (recursive Fisher scoring, or the
variational Bayes step of Särkkä and Nummenmaa 2009) grows with the
innovation's square; the share c slows the step where r hardly moves S
(H P H^T large against r R), where s says little about r. r is allowed
below 1: a world calmer than stated is learned too. A tick on which the
agent measures nothing changes nothing.

The agent then weighs its measurement by 1 / r (its information U / r,
u / r).

Every function is pure, with leading batch axes.
"""
from __future__ import annotations

import numpy as np

from diskf_mesh.core.linalg import T, inv_spd, mv, sym

LOW, HIGH = np.log(1e-2), np.log(1e3)  # theta's bounds: r from 1/100 to 1000 times the stated R


def track(theta, x, P, y, H, R, p, has, median, step: float):
    """(NL1) where ``has``, theta unchanged elsewhere. H: (..., p_max, n)
    and R: (..., p_max, p_max), padded as ``model.Sensors`` (zero rows of
    H, an identity block of R); p: (...,) the true rows; y zero in the
    padding rows; ``median``: (...,) the chi-square median of p degrees of
    freedom."""
    r = np.exp(theta)
    S = sym(np.matmul(np.matmul(H, P), T(H)) + r[..., None, None] * R)
    Si = inv_spd(S)
    e = y - mv(H, x)
    nis = np.einsum("...i,...i->...", e, mv(Si, e))
    pad = H.shape[-2] - p
    share = np.clip((r * np.trace(np.matmul(Si, R), axis1=-2, axis2=-1) - pad) / p, 0.0, 1.0)
    moved = np.clip(theta + step * np.sqrt(share) * np.where(nis > median, 1.0, -1.0), LOW, HIGH)
    return np.where(has, moved, theta)
