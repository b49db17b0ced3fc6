"""Overdetermined initialisation of far-field calibration (paper 000, section 2.3).

:func:`reduce_matrix` (Lemma 1), :func:`initialize_farfield` (rank-3 factorisation, the
quadric ``ntilde^T B ntilde = 1``, ``A^T A = B``) and :func:`fit_A_nonlinear` (A when the
least-squares B is not positive definite).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import least_squares

from ..geometry import canonical_gauge
from .degeneracy import fit_quadric, top_svd
from .result import FarfieldInit

__all__ = ["reduce_matrix", "fit_A_nonlinear", "initialize_farfield"]

Array = NDArray[np.float64]


def reduce_matrix(D: Array) -> Array:
    """``Dbar_ij = D_ij - D_1j`` without the first row (paper 000, Lemma 1): (m-1, k)."""
    D = np.asarray(D, dtype=float)
    return D[1:] - D[:1]


def fit_A_nonlinear(nt: Array, A0: Array | None = None) -> Array:
    """Minimise ``sum_j (ntilde_j^T A^T A ntilde_j - 1)^2`` over 3x3 A (paper 000, sec. 2.3).

    Used when the least-squares B is not positive definite. Starts from ``A0`` (the paper:
    identity), Levenberg-Marquardt (scipy ``least_squares``; trust-region for k < 9).

    Parameters
    ----------
    nt : (k, d) rows ``ntilde_j`` (d = 3 in space, 2 in a plane); A0 : (d, d) start.
    """
    d = nt.shape[1]
    A0 = np.eye(d) if A0 is None else np.asarray(A0, dtype=float)

    def fun(a: Array) -> Array:
        v = nt @ a.reshape(d, d).T
        return np.sum(v * v, axis=1) - 1.0

    def jac(a: Array) -> Array:
        A = a.reshape(d, d)
        v = nt @ A.T  # (k, d)
        return (2.0 * v[:, :, None] * nt[:, None, :]).reshape(len(nt), d * d)

    # "lm" needs at least as many residuals as the d^2 unknowns
    meth = "lm" if len(nt) >= d * d else "trf"
    sol = least_squares(fun, A0.ravel(), jac=jac, method=meth, xtol=1e-14, ftol=1e-14, gtol=1e-14)
    return np.asarray(sol.x.reshape(d, d))


def initialize_farfield(X: Array, *, dim: int = 3) -> FarfieldInit:
    """Overdetermined initialisation (paper 000, section 2.3, modifications (i)-(iii)).

    (i) best rank-3 approximation ``Dbar ~ U_3 (S_3 V_3^T)``; (ii) B from the k equations
    ``ntilde_j^T B ntilde_j = 1`` in the least-squares sense, ``A^T A = B`` by Cholesky; when
    B is not positive definite, A from :func:`fit_A_nonlinear` (started at the identity, as
    in the paper, and at the square root of B's positive part; the better fit among those
    with cond(A) < 1e4 is kept, else that square root itself);
    (iii) ``N = A Ntilde`` with re-normalised columns, and positions ``Z = U_3 A^-1`` re-fitted
    by least squares to the normalised directions.

    Parameters
    ----------
    X : (r, k) complete reduced matrix (metres): ``D`` minus a per-column constant (Lemma 1),
        e.g. :func:`reduce_matrix` (r = m-1) or the column-centred D (r = m).
    dim : 3 (space, the paper) or 2 (the planar analogue: positions and directions in one
        plane, rank-2 factorisation and the 2 x 2 quadric ``ntilde^T B2 ntilde = 1``).

    Returns
    -------
    FarfieldInit with positions (r, dim), one per row of X, and directions (k, dim).
    """
    U, s, Vt = top_svd(X, dim)
    scale = float(s[0]) / np.sqrt(X.shape[1]) if s[0] > 0 else 1.0
    nt = (s[:dim, None] * Vt[:dim]).T / scale  # scaled for a well-conditioned quadric fit
    B, _, _ = fit_quadric(nt)
    w, Qe = np.linalg.eigh(B)
    pd = bool(w[0] > 0)
    if pd:
        A = np.linalg.cholesky(B).T  # B = L L^T = A^T A
    else:
        A_psd = np.sqrt(np.maximum(w, 1e-6 * max(w[-1], 1e-12)))[:, None] * Qe.T
        candidates = [fit_A_nonlinear(nt, np.eye(dim)), fit_A_nonlinear(nt, A_psd), A_psd]
        best, best_cost = A_psd, np.inf
        for A_try in candidates:
            c = float(np.sum((np.sum((nt @ A_try.T) ** 2, axis=1) - 1.0) ** 2))
            # with noise the fit can collapse A to rank 2 (all directions on one great
            # circle fit the norms better); such an A destroys the positions, so skip it
            if np.linalg.cond(A_try) < 1e4 and c < best_cost:
                best, best_cost = A_try, c
        A = best
    N = nt @ A.T
    N /= np.linalg.norm(N, axis=1, keepdims=True)
    # positions by least squares given the normalised directions (equal to U_3 A^-1 when
    # the normalisation is a no-op, better otherwise)
    Z, *_ = np.linalg.lstsq(N, X.T, rcond=None)
    return FarfieldInit(Z.T, N, B / scale**2, A / scale, pd)


def _canonical(pos: Array, dirs: Array) -> tuple[Array, Array, Array]:
    """Rotate so that the positions' principal axes are the coordinate axes (row 0 stays 0).

    Far-field TDOA cannot tell a solution from its mirror image (``z_i . n_j`` is unchanged
    when both are reflected), so the mirror is chosen by the same rule as every axis
    (:func:`selfcal.geometry.canonical_gauge` with ``proper=False``: non-negative third moment
    of the positions along each principal axis): the output does not depend on which of the
    two the solver's path reached.
    """
    d = pos.shape[1]
    if d == 1 or np.linalg.matrix_rank(pos, tol=1e-12 * (np.abs(pos).max() + 1e-300)) < d:
        return pos, dirs, np.eye(d)
    _, _, al = canonical_gauge(pos, proper=False)
    R = al.rotation
    return pos @ R.T, dirs @ R.T, R
