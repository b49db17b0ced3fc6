"""Cramer-Rao bound of far-field positions (gauge removed)."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from .model import _tangent

Array = NDArray[np.float64]


def farfield_crlb(positions: Array, directions: Array, sigma: float, *, free_offsets: bool = True) -> Array:
    """Cramer-Rao bound of the far-field model for the positions, gauge removed: (m, d, d).

    Fisher information ``J^T J / sigma^2`` of ``D_ij = z_i . n_j + C_j + e_ij`` with i.i.d.
    ``e_ij ~ N(0, sigma^2)`` (paper 000, section 3.3 noise model) in all unknowns: every
    ``z_i`` (d each, z_1 included), each ``n_j`` in d-1 tangent coordinates of the unit
    sphere (d = 3) or circle (d = 2) and, with ``free_offsets``, each ``C_j``. For d = 1
    (a linear array) ``directions`` are the projections ``u_j`` in [-1, 1], each a free
    scalar. The information is singular along the gauge (translations trade against
    ``C_j``, rotations of Z against those of N, and for d = 1 the scale ``x -> a x``,
    ``u -> u / a``); its pseudo-inverse is projected onto the complement of the gauge
    motions of the positions, which is the error that remains after aligning an estimate to
    the truth by such a motion (rigid; rigid + scale for d = 1). ``trace(sum_i cov_i) / m``
    bounds the expected aligned mean squared position error (to first order).

    Parameters
    ----------
    positions : (m, d) true z_i, metres; directions : (k, d) true unit n_j ((k, 1)
        projections for d = 1); sigma : noise standard deviation of D (metres);
    free_offsets : C_j unknown (True).

    Returns
    -------
    (m, d, d) covariance blocks of the aligned positions, metres^2.
    """
    Z = np.asarray(positions, dtype=float)
    N = np.asarray(directions, dtype=float)
    if Z.ndim == 1:
        Z = Z[:, None]
    if N.ndim == 1:
        N = N[:, None]
    m, d = Z.shape
    k = N.shape[0]
    if d == 1:
        T = np.ones((k, 1, 1))
    else:
        N = N / np.linalg.norm(N, axis=1, keepdims=True)
        T = _tangent(N)
    q = T.shape[2]
    n_par = d * m + q * k + (k if free_offsets else 0)
    J = np.zeros((m, k, n_par))
    for i in range(m):
        J[i, :, d * i : d * i + d] = N
    zt = np.einsum("ia,jab->ijb", Z, T)
    for j in range(k):
        J[:, j, d * m + q * j : d * m + q * j + q] = zt[:, j]
        if free_offsets:
            J[:, j, d * m + q * k + j] = 1.0
    J = J.reshape(m * k, n_par)
    cov = np.linalg.pinv(J.T @ J, rcond=1e-10, hermitian=True)[: d * m, : d * m] * sigma**2
    gens = [np.tile(np.eye(d)[a], (m, 1)).ravel() for a in range(d)]
    if d == 3:
        gens += [np.cross(np.eye(3)[a], Z).ravel() for a in range(3)]
    elif d == 2:
        gens += [np.column_stack([-Z[:, 1], Z[:, 0]]).ravel()]
    else:
        gens += [Z.ravel()]  # the scale of a linear array
    G = np.array(gens).T
    proj = np.eye(d * m) - G @ np.linalg.pinv(G)
    full = proj @ cov @ proj
    idx = np.arange(m)
    return np.asarray(full.reshape(m, d, m, d)[idx, :, idx, :])
