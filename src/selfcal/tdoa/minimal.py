"""Minimal far-field TDOA solver (paper 000, Algorithm 1), batched over a leading axis.

Model (paper 000, Problem 1 / Lemma 1): ``D_ij = z_i . n_j + C_j`` with unit directions
``n_j``. Subtracting the first row (``z_1 = 0``) removes the offsets; the remaining
``3 x 6`` matrix factors as ``Dbar = Z N`` (Lemma 2). With ``Ntilde = Dbar`` (i.e. the
trivial factorisation ``Ztilde = I``; for three rows the SVD of step 3-4 only rotates
``Dbar``, which changes nothing but the arbitrary gauge) the unit-norm constraints give six
linear equations ``ntilde_j^T B ntilde_j = 1`` in the six entries of the symmetric
``B = A^T A`` (step 5). ``A`` is any square root of ``B`` (step 6; we use the symmetric
eigen-square-root, equal to the paper's Cholesky factor up to a rotation, because it
never raises inside a batch), and ``Z = Ztilde A^-1``, ``N = A Ntilde`` (step 7).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from ..errors import InputError

__all__ = ["MinimalSolution", "quadric_design", "solve_minimal", "sym_from_vec"]

Array = NDArray[np.float64]


@dataclass(frozen=True)
class MinimalSolution:
    """Batched output of :func:`solve_minimal`.

    Attributes
    ----------
    positions : (..., 4, 3) receiver positions, first row 0 (metres, same unit as D).
    directions : (..., 6, 3) unit directions (NaN where ``valid`` is False).
    valid : (...) True where B was positive definite (the paper's success criterion).
    b_min_eig : (...) smallest eigenvalue of the normalised B (<= 0 means failure).
    """

    positions: Array
    directions: Array
    valid: NDArray[np.bool_]
    b_min_eig: Array


def quadric_design(nt: Array) -> Array:
    """Rows ``[a^2, b^2, c^2, 2ab, 2ac, 2bc]`` of ``n^T B n = 1`` (paper 000, Alg. 1 step 5).

    Parameters
    ----------
    nt : (..., k, 3) direction estimates ``ntilde_j`` (one per row).

    Returns
    -------
    (..., k, 6) design matrix acting on ``b = [B11, B22, B33, B12, B13, B23]``.
    """
    a, b, c = nt[..., 0], nt[..., 1], nt[..., 2]
    return np.stack([a * a, b * b, c * c, 2 * a * b, 2 * a * c, 2 * b * c], axis=-1)


def sym_from_vec(b: Array) -> Array:
    """(..., 6) ``[B11, B22, B33, B12, B13, B23]`` -> (..., 3, 3) symmetric matrix."""
    B = np.empty(b.shape[:-1] + (3, 3))
    B[..., 0, 0], B[..., 1, 1], B[..., 2, 2] = b[..., 0], b[..., 1], b[..., 2]
    B[..., 0, 1] = B[..., 1, 0] = b[..., 3]
    B[..., 0, 2] = B[..., 2, 0] = b[..., 4]
    B[..., 1, 2] = B[..., 2, 1] = b[..., 5]
    return B


def _solve6(M: Array) -> Array:
    ones = np.ones(M.shape[:-1] + (1,))
    try:
        return np.asarray(np.linalg.solve(M, ones)[..., 0], dtype=np.float64)
    except np.linalg.LinAlgError:
        # one exactly singular system (a cone) must not sink the whole batch
        return np.asarray((np.linalg.pinv(M) @ ones)[..., 0], dtype=np.float64)


def solve_minimal(D: Array) -> MinimalSolution:
    """Solve a batch of minimal far-field TDOA problems (paper 000, Algorithm 1).

    Parameters
    ----------
    D : (..., 4, 6) relative distances ``D_ij = z_i . n_j + C_j`` (metres or any length
        unit; rows = 4 receiver positions, columns = 6 far transmitters). Any leading
        batch shape.

    Returns
    -------
    MinimalSolution
        Positions (..., 4, 3) with ``z_1 = 0`` and unit directions (..., 6, 3), exact on
        exact data up to a common orthogonal transform (rotation / reflection). Problems
        whose B is not positive definite (noise, non-far-field data, a cone) are marked
        ``valid = False`` and carry NaN.
    """
    D = np.asarray(D, dtype=np.float64)
    if D.shape[-2:] != (4, 6):
        raise InputError(f"solve_minimal: expected (..., 4, 6) matrices, got shape {D.shape}")
    Dbar = D[..., 1:, :] - D[..., :1, :]  # Lemma 1: z_1 = 0 removes C_j
    # scale to unit rms so the 6x6 system is well conditioned whatever the length unit
    scale = np.sqrt(np.mean(Dbar**2, axis=(-2, -1)))
    scale = np.where(scale > 0, scale, 1.0)
    Nt = Dbar / scale[..., None, None]  # (..., 3, 6)
    M = quadric_design(np.swapaxes(Nt, -1, -2))  # (..., 6, 6)
    B = sym_from_vec(_solve6(M))
    w, Q = np.linalg.eigh(B)
    valid = np.all(np.isfinite(w), axis=-1) & (w[..., 0] > 0)
    root = np.sqrt(np.where(valid[..., None], w, np.nan))
    A = root[..., :, None] * np.swapaxes(Q, -1, -2)  # A = diag(sqrt w) Q^T, A^T A = B
    A_inv = Q / root[..., None, :]
    N = A @ Nt  # (..., 3, 6)
    Z = A_inv * scale[..., None, None]  # Ztilde = I, so Z = A^-1 (rows = z_2..z_4)
    positions = np.concatenate([np.zeros(D.shape[:-2] + (1, 3)), Z], axis=-2)
    return MinimalSolution(
        positions=positions,
        directions=np.swapaxes(N, -1, -2),
        valid=valid,
        b_min_eig=w[..., 0],
    )
