"""Measurement noise learned online (``diskf-auto``; our derivation, not the
paper's equations).

Each agent holds one scale r of its own sensor's stated covariance: the
world's measurement noise is taken to be N(0, r R). Its posterior is an
inverse gamma IG(alpha, beta), r's estimate beta / alpha, updated at each
tick the agent measures by one step of the variational Bayes adaptive
Kalman filter (Särkkä and Nummenmaa, "Recursive noise adaptive Kalman
filtering by variational Bayesian approximations", IEEE TAC 54(3), 2009),
for a scalar scale of a known R:

    forget   alpha- = f alpha + (1 - f) alpha0,  beta- = f beta + (1 - f) beta0   (NL1)
    update   r- = beta- / alpha-,  J = P^-1 + U / r-,  x+ = J^-1 (P^-1 x + u / r-)
             alpha = alpha- + p / 2
             beta  = beta- + (y^T R^-1 y - 2 x+^T u + x+^T U x+ + tr(U J^-1)) / 2   (NL2)

U = H^T R^-1 H and u = H^T R^-1 y are the measurement information under
the stated R, so the bracket of (NL2) is (y - H x+)^T R^-1 (y - H x+) +
tr(R^-1 H J^-1 H^T), the expected weighted residual under the posterior.
The forgetting pulls the posterior back towards the prior IG(alpha0,
alpha0) (r = 1, as stated) by 1 - f per measured tick only: a tick on which
the agent measures nothing changes nothing. ``(x, P)`` is the prediction
the measurement is scored against: in ``diskf-auto`` the state predicted
with the input the agent last fused, so that an input the bank already
follows is not read as noise.

Every function is pure, with leading batch axes.
"""
from __future__ import annotations

import numpy as np

from diskf_mesh.core.linalg import inv_spd, mv


def forget(alpha, beta, alpha0: float, f: float, has):
    """(NL1) where ``has``; unchanged elsewhere."""
    return (np.where(has, f * alpha + (1.0 - f) * alpha0, alpha),
            np.where(has, f * beta + (1.0 - f) * alpha0, beta))


def update(alpha, beta, x, P, y, Ri, U, u, p, has):
    """(NL2): the posterior (alpha, beta) after the measurement y (where
    ``has``), scored against the prediction N(x, P). Ri: (..., p, p) the
    stated R^-1 (padding rows: zero in y, so nothing); U, u the stated
    measurement information; p: (...,) the sensor's rows."""
    r = beta / alpha
    Y = inv_spd(P)
    J = inv_spd(Y + U / r[..., None, None])
    xp = mv(J, mv(Y, x) + u / r[..., None])
    quad = _dot(y, mv(Ri, y)) - 2.0 * _dot(xp, u) + _dot(xp, mv(U, xp)) + np.trace(U @ J, axis1=-2, axis2=-1)
    return (np.where(has, alpha + 0.5 * p, alpha),
            np.where(has, beta + 0.5 * np.maximum(quad, 0.0), beta))


def _dot(a, b):
    return np.einsum("...i,...i->...", a, b)
