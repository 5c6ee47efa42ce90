"""The recursive Kalman filter (RKF) of Gillijns & De Moor (2007), state part.

After the input estimate of ``equations.input_estimate``, the RKF measurement
update gives the minimum-variance unbiased state estimate. In information
form (equal to the textbook recursion with its pseudo-inverse of R~*, checked
in ``tests/test_filters.py``):

    Y   = P^^-1
    Y_G = Y - Y G (G^T Y G)^-1 G^T Y      prior information with the input
                                          direction left free (unknown input)
    P   = (Y_G + H^T R^-1 H)^-1
    x   = P (Y_G x^ + H^T R^-1 y)

Where input estimation is not possible (rank(HG) < m, no measurement) the
filter falls back to the plain Kalman update. Working on (U, u) = (H^T R^-1 H,
H^T R^-1 y) lets the same function run one sensor (L-DRKF) or a stacked
neighbourhood (C-DRKF) without forming stacked matrices.
"""
from __future__ import annotations

import numpy as np

from diskf_mesh.core.linalg import T, congruence, inv_spd, mv, sym


def rkf_update(x_pred, Y, U, u, G, valid):
    """The update above, from the prediction in information form (``Y`` = P^^-1)."""
    YG = np.matmul(Y, G)
    GYG = congruence(G, Y)
    Y_free = sym(Y - np.matmul(np.matmul(YG, inv_spd(GYG)), T(YG)))
    Y_prior = np.where(np.asarray(valid)[..., None, None], Y_free, Y)
    P = inv_spd(sym(Y_prior + U))
    x = mv(P, mv(Y_prior, x_pred) + u)
    return x, P
