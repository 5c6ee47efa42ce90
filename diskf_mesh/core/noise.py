"""Measurement noise learned online (``diskf-auto``; our derivation, not the
paper's equations).

Each agent holds one scale r of its own sensor's stated covariance: the
world's measurement noise is taken to be N(0, r R). At each tick the agent
measures, with the prediction N(x, P) it scores the measurement against (in
``diskf-auto`` the mean the bank predicts for the tick, its input models'
predictions of the input included, and the covariance of the agent's own
prediction without an input), the innovation e_k = y - H x and its
covariance S_k = H P H^T + r R are compared with those of the agent's last
measured tick, e_l and S_l: theta = log r takes one step of a stochastic
approximation of the median of the normalised innovation difference

    s = (e_k - e_l)^T (S_k + S_l)^-1 (e_k - e_l)
    share   c = tr(S_k^-1 r R) / p                     (0 < c <= 1)
    theta <- clip(theta + step sqrt(c) sign(s - m_p), log LOW, log HIGH)     (NL1)

m_p the median of the chi-square distribution of p degrees of freedom (p
the sensor's rows; the padding rows of a shorter sensor, R = I and H = 0
there, left out of the trace). Where the prediction is right the
innovations of different ticks are independent, e_k - e_l ~ N(0, S_k +
S_l), and the fixed point is the r at which s lies above its median as
often as below: where the sensor is r times noisier (or calmer) than
stated, and nothing else is wrong, that is r. The difference is what
tells noise from an input the bank does not predict: such an input (a
ramp, the drift after a step until the bank follows it) moves the
innovations of consecutive ticks together, and their difference leaves
most of it out, where the noise of two ticks adds. A tick moves theta by
at most ``step`` whatever its innovation, so a jump moves r by a few steps
only, where a likelihood's score (recursive Fisher scoring, or the
variational Bayes step of Särkkä and Nummenmaa 2009) grows with the
innovation's square; the share c slows the step where r hardly moves S
(H P H^T large against r R), where s says little about r. r is allowed
below 1: a world calmer than stated is learned too. A tick on which the
agent measures nothing changes nothing; the first measured tick only
keeps its innovation.

The agent then weighs its measurement by 1 / r (its information U / r,
u / r).

Every function is pure, with leading batch axes.
"""
from __future__ import annotations

import numpy as np

from diskf_mesh.core.linalg import T, inv_spd_each, mv, sym

LOW, HIGH = np.log(1e-2), np.log(1e3)  # theta's bounds: r from 1/100 to 1000 times the stated R


def track(theta, last, x, P, y, H, R, p, has, median, step: float):
    """(NL1) where ``has`` and an earlier tick was measured: (theta, last),
    theta unchanged elsewhere. ``last``: (e_l (..., p_max), S_l (..., p_max,
    p_max), seen (...,)) the innovation and its covariance of the last
    measured tick and whether there was one (``first_innovation``); returned
    with this tick's where ``has``. H: (..., p_max, n) and R: (..., p_max,
    p_max), padded as ``model.Sensors`` (zero rows of H, an identity block of
    R); p: (...,) the true rows; y zero in the padding rows; ``median``:
    (...,) the chi-square median of p degrees of freedom."""
    e_l, S_l, seen = last
    r = np.exp(theta)
    S = sym(np.matmul(np.matmul(H, P), T(H)) + r[..., None, None] * R)
    e = y - mv(H, x)
    diff = e - e_l
    Si, Sdi = inv_spd_each(S, S + S_l)
    nis = np.einsum("...i,...i->...", diff, mv(Sdi, diff))
    pad = H.shape[-2] - p
    share = np.clip((r * np.trace(np.matmul(Si, R), axis1=-2, axis2=-1) - pad) / p, 0.0, 1.0)
    moved = np.clip(theta + step * np.sqrt(share) * np.where(nis > median, 1.0, -1.0), LOW, HIGH)
    return np.where(has & seen, moved, theta), (np.where(has[..., None], e, e_l), np.where(has[..., None, None], S, S_l),
                                                 seen | has)


def first_innovation(batch: tuple, p_max: int):
    """``track``'s ``last`` before any measured tick."""
    return np.zeros(batch + (p_max,)), np.broadcast_to(np.eye(p_max), batch + (p_max, p_max)).copy(), \
        np.zeros(batch, dtype=bool)
