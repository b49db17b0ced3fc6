"""The scale of the geometry from known microphone-loudspeaker distances (setup.json ``unit_offsets``).

With unknown offsets the scale of the geometry is not observable from times alone: it comes
from the speed of sound (a 1 % error in c scales every distance by 1 %). Known intra-unit
distances fix it (:func:`scale_from_distances`, :func:`apply_scale`).
"""

from __future__ import annotations

from dataclasses import replace
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

if TYPE_CHECKING:
    from .solution import Calibration

__all__ = ["scale_from_distances", "apply_scale"]

Array = NDArray[np.float64]

def scale_from_distances(sol: Calibration, receivers: NDArray[np.intp], senders: NDArray[np.intp],
                         distances: Array) -> tuple[float, float]:
    """Scale factor of a solution from known receiver-sender distances (a unit's microphone and loudspeaker).

    With unknown offsets, positions and the speed of sound are confounded exactly: the
    model ``|r_i - s_j| / c + delta_i + tau_j`` is unchanged by ``r, s, c -> lam r, lam s,
    lam c``. Known distances ``D_k`` fix ``lam``: weighted least squares ``lam = sum w_k d_k
    D_k / sum w_k d_k^2`` over the estimated distances ``d_k`` with ``w_k = 1 / var(d_k)``
    (``var(d_k) = u^T (C_i + C_j) u``, u the unit vector, cross-covariance neglected).

    Parameters
    ----------
    sol : Calibration
        Its ``receivers``, ``sources``, ``receiver_cov``, ``source_cov``.
    receivers, senders : (K,) int arrays
        The pairs.
    distances : (K,) array
        Known distances, m.

    Returns
    -------
    lam : float
        Scale factor (1 = the assumed speed of sound is right).
    lam_std : float
        Its standard deviation.
    """
    r = np.asarray(sol.receivers, float)[receivers]
    s = np.asarray(sol.sources, float)[senders]
    rc = np.asarray(sol.receiver_cov, float)[receivers]
    sc = np.asarray(sol.source_cov, float)[senders]
    D = np.asarray(distances, float)
    diff = r - s
    d = np.linalg.norm(diff, axis=1)
    u = diff / np.maximum(d, 1e-12)[:, None]
    var = np.einsum("ki,kij,kj->k", u, rc + sc, u)
    ok = np.isfinite(d) & np.isfinite(var) & (d > 0)
    var = np.where(var > 0, var, np.nanmedian(var[ok & (var > 0)]) if (ok & (var > 0)).any() else 1e-8)
    w = 1.0 / var[ok]
    lam = float(np.sum(w * d[ok] * D[ok]) / np.sum(w * d[ok] ** 2))
    lam_std = float(lam / np.sqrt(np.sum(d[ok] ** 2 / var[ok])))
    return lam, lam_std


def apply_scale(sol: Calibration, lam: float) -> Calibration:
    """Positions times ``lam``, covariances times ``lam^2`` (offsets unchanged)."""
    u = sol.uniqueness
    if u is not None:  # its alternative positions at the same scale
        d = np.asarray(sol.receivers).shape[1]
        u = u.moved(lam * np.eye(d), np.zeros(d))
    return replace(sol, receivers=np.asarray(sol.receivers, float) * lam, sources=np.asarray(sol.sources, float) * lam,
                   receiver_cov=np.asarray(sol.receiver_cov, float) * lam**2,
                   source_cov=np.asarray(sol.source_cov, float) * lam**2, uniqueness=u)
