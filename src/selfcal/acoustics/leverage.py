"""Leverages of the calibration fit: the residual std of every detection (outlier and residual tests).

A least-squares residual has variance ``sigma^2 (1 - h_ij)`` with ``h_ij`` the diagonal of
the hat matrix: an entry of a sparsely observed node has a leverage near 1 and a small
residual whatever its error. The outlier test (:mod:`selfcal.acoustics.robust_fit`) and
the residual check (:func:`selfcal.acoustics.noise.residual_check`) standardise each
residual by its own factor instead of the mean ``sqrt(1 - p / m)``, which over-states the
residuals of well observed entries when few degrees of freedom are left (a recording whose
noise bursts took a third of the detections).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

if TYPE_CHECKING:
    from .solution import Calibration

__all__ = ["hat_diagonal", "event_leverage"]

Array = NDArray[np.float64]

def hat_diagonal(sol: Calibration, observed: NDArray[np.bool_], speed: float,
                 weights: Array | None = None) -> Array:
    """Leverages ``h_ij`` of the least-squares fit of a solution on its per-sender TOA matrix.

    ``h = diag(A (A^T A)^+ A^T)`` for the Jacobian ``A`` of the model ``|r_i - s_j| / c +
    delta_i + tau_j`` over the observed entries, with the coordinates the solution's model
    frees (x, y for ``2d`` and ``2d+heights``, x, y, z for ``3d``); the gauge is the null
    space of ``A^T A`` (pseudo-inverse). A residual's variance is ``sigma^2 (1 - h_ij)``: a
    sparsely observed node's entries have leverages near 1 and small residuals whatever
    their errors, a well observed one's near 0. Positions in metres and offsets in metres
    (times c) keep ``A^T A`` well scaled.

    Parameters
    ----------
    sol : Calibration
        ``receivers`` (I, d), ``sources`` (J, d), ``dim`` (the free coordinates).
    observed : (I, J) bool
    speed : float
        m/s.
    weights : (I, J) array, optional
        Row weights ``1 / std`` of a weighted fit (the hat matrix of ``W A``).

    Returns
    -------
    (I, J) array
        ``h_ij`` in [0, 1] (NaN where not observed).
    """
    import scipy.sparse as sp

    r, s = np.asarray(sol.receivers, float), np.asarray(sol.sources, float)
    d = sol.dim
    I, J = observed.shape
    ii, jj = np.nonzero(observed)
    out = np.full((I, J), np.nan)
    if ii.size == 0:
        return out
    diff = r[ii, :d] - s[jj, :d]
    full = r[ii] - s[jj]
    u = diff / np.maximum(np.linalg.norm(full, axis=1), 1e-12)[:, None]
    m = ii.size
    n = d * (I + J) + I + J
    rows = np.repeat(np.arange(m), 2 * d + 2)
    cols = np.concatenate([d * ii[:, None] + np.arange(d)[None], d * (I + jj)[:, None] + np.arange(d)[None],
                           (d * (I + J) + ii)[:, None], (d * (I + J) + I + jj)[:, None]], axis=1).ravel()
    vals = np.concatenate([u, -u, np.ones((m, 1)), np.ones((m, 1))], axis=1)
    if weights is not None:
        wv = np.asarray(weights, float)[ii, jj]
        vals = vals * np.where(np.isfinite(wv) & (wv > 0), wv / np.nanmedian(wv), 0.0)[:, None]
    vals = vals.ravel()
    A = sp.csr_matrix((vals, (rows, cols)), shape=(m, n))
    N = (A.T @ A).toarray()
    w, V = np.linalg.eigh(N)
    keep = w > w.max() * 1e-10
    B = A @ (V[:, keep] / np.sqrt(w[keep]))  # orthonormal basis of the column space of A
    out[ii, jj] = np.clip(np.einsum("ij,ij->i", B, B), 0.0, 1.0)
    return out


def event_leverage(sol: Calibration, toa: Array, event_senders: NDArray[np.int64], n_senders: int,
                   speed: float, weights: Array | None = None) -> Array:
    """Residual std factor ``sqrt(1 - h_ij / n_ij)`` of every event detection (I, E).

    The fit sees the per-sender mean of the ``n_ij`` events of sender j at receiver i; an
    event's residual from the model is its deviation from that mean (variance
    ``sigma^2 (1 - 1 / n)``) plus the mean's residual (``sigma^2 (1 - h) / n``):
    ``sigma^2 (1 - h / n)`` (:func:`hat_diagonal`, ``weights`` as there). Floored at 1e-3.
    """
    es = np.asarray(event_senders, dtype=np.int64)
    fin = np.isfinite(toa)
    cnt = np.zeros((toa.shape[0], n_senders))
    for j in range(n_senders):
        cnt[:, j] = fin[:, es == j].sum(axis=1)
    h = hat_diagonal(sol, cnt > 0, speed, weights)
    f = np.sqrt(np.maximum(1.0 - np.nan_to_num(h) / np.maximum(cnt, 1.0), 1e-6))
    return np.where(fin, f[:, es], np.nan)
