"""Dense linear algebra of the SLAC filter and smoother: Cholesky factors, triangular solves, inverses.

Direct LAPACK calls (``dpotrf`` / ``dpotri`` / ``dtrtrs``) without scipy's wrapper checks, which
cost more than the ~100 x 100 factorisations themselves; :func:`safe_cholesky` adds a growing
relative jitter to a matrix that rounding made indefinite by a hair. Shared by
:mod:`selfcal.slac.laplace` (the MAP update), :mod:`selfcal.slac.filter` and
:mod:`selfcal.slac.smoother`.
"""

from __future__ import annotations

import numpy as np
import scipy.linalg as sla
from numpy.typing import NDArray

__all__ = ["cholesky_lower", "safe_cholesky", "tri_solve", "inverse_from_cholesky", "spd_inverse"]

FArray = NDArray[np.float64]

_LAPACK = sla.get_lapack_funcs(("potrf", "potri", "trtrs"), (np.empty((1, 1)),))
_POTRF, _POTRI, _TRTRS = _LAPACK


def cholesky_lower(S: FArray) -> FArray:
    """Lower Cholesky factor by LAPACK ``dpotrf`` (no wrapper checks); LinAlgError if not PD."""
    c, info = _POTRF(S, lower=1, clean=1, overwrite_a=0)
    if info != 0:
        raise np.linalg.LinAlgError("matrix is not positive definite")
    return np.asarray(c, dtype=float)


def safe_cholesky(M: FArray) -> FArray:
    """Lower Cholesky factor of a symmetric matrix that should be positive definite.

    Long static phases drive some variances to ~1e-10 m^2 while others stay ~1: rounding can
    then make the matrix indefinite by a hair, so a growing relative jitter is added.
    """
    S = 0.5 * (M + M.T)
    try:
        return cholesky_lower(S)
    except np.linalg.LinAlgError:
        d = np.sqrt(np.clip(np.diag(S), 1e-300, None))
        C = S / np.outer(d, d)  # scale to unit diagonal, then regularise the correlation
        for eps in (1e-12, 1e-10, 1e-8, 1e-6, 1e-4):
            try:
                return cholesky_lower(C + eps * np.eye(S.shape[0])) * d[:, None]
            except np.linalg.LinAlgError:
                continue
        raise


def tri_solve(C: FArray, b: FArray, *, trans: bool = False) -> FArray:
    """Solve ``C z = b`` (or ``C^T z = b``) for a lower-triangular factor C (D, D), b (D,) or (D, K).

    Direct LAPACK ``dtrtrs`` (the scipy wrapper's argument checks cost more than a 123 x 123
    solve). Used for the whitening of the MAP update (eq. 22): ``x = x_bar + C^-T u``.
    """
    z, info = _TRTRS(C, b, lower=1, trans=1 if trans else 0)
    if info != 0:
        raise np.linalg.LinAlgError("singular triangular factor")
    return np.asarray(z, dtype=float)


def inverse_from_cholesky(C: FArray) -> FArray:
    """Symmetric ``(C C^T)^-1`` (D, D) from its lower Cholesky factor C by LAPACK ``dpotri``.

    The Laplace covariance of eq. 22 (inverse Hessian) and the prior information ``P_bar^-1``.
    """
    Pi, info = _POTRI(C, lower=1)
    if info != 0:
        raise np.linalg.LinAlgError("singular Cholesky factor")
    Pi = np.tril(Pi)
    return Pi + np.tril(Pi, -1).T


def spd_inverse(P: FArray) -> FArray:
    """Symmetric inverse (D, D) of a symmetric positive definite P (:func:`safe_cholesky`, then ``dpotri``)."""
    return inverse_from_cholesky(safe_cholesky(P))
