"""Rotations from corresponding vectors: paper 001 eq. 14, 17-18, 23, 25 and helpers.

Conventions
-----------
Paper 001 writes the rotation as ``A`` with ``u_local = A u_global`` (eq. 10, its rows are the
receiver axes in the global frame). selfcal's result holds ``R = A^T`` (columns = receiver axes
in the global frame, ``v_global = R v_receiver``, DESIGN.md). Everything here is batched over
a leading axis ``B``.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..geometry import align, rotation_from_rotvec

Array = NDArray[Any]

__all__ = [
    "PLANAR_TOL",
    "nearest_rotation",
    "orientation_from_vectors",
    "kabsch",
    "rotvec_to_matrix",
    "tangent_basis",
]

#: relative singular value below which a set of global vectors counts as planar (eq. 15-18)
PLANAR_TOL = 1e-9


def nearest_rotation(M: Array) -> Array:
    """Closest proper rotation (Frobenius norm) to each (..., 3, 3) matrix, via the SVD."""
    U, _, Vt = np.linalg.svd(M)
    d = np.sign(np.linalg.det(U @ Vt))
    d = np.where(d == 0, 1.0, d)
    U = U.copy()
    U[..., :, -1] *= d[..., None]
    return U @ Vt


def orientation_from_vectors(
    global_vecs: Array, local_vecs: Array, *, orthonormalize: bool = False
) -> tuple[Array, Array]:
    """Paper matrix ``A`` (``local = A global``) from n >= 3 vector pairs, batched.

    Full rank (the vectors span 3-D): the least-squares solution of ``Ubar = A U``, which for
    n = 3 is exactly eq. 14 (``A = Ubar U^-1``) / eq. 23 (``A = Dbar D^-1``).
    Planar (the global vectors lie in one plane, smallest singular value below
    ``PLANAR_TOL`` relative): eq. 15-17 solve the two in-plane columns of ``A`` by least
    squares and eq. 18 completes ``a3 = a1 x a2``. The paper states it for the plane z = c;
    here the global frame is first rotated into a right-handed basis (e1, e2, n = e1 x e2)
    of the vectors' plane so that it holds for any plane (for z = c it is the identity).

    Parameters
    ----------
    global_vecs, local_vecs : (B, n, 3)
        Corresponding vectors (rows), in the global and the receiver frame.
    orthonormalize : bool
        Project ``A`` onto SO(3) (beyond the paper, whose ``A`` is not orthonormal with noise).

    Returns
    -------
    A : (B, 3, 3)
        The paper's matrix (rows = receiver axes in the global frame).
    planar : (B,) bool
        Whether the planar least-squares variant was used.
    """
    G = np.asarray(global_vecs, float)
    L = np.asarray(local_vecs, float)
    _, s, Vt = np.linalg.svd(G, full_matrices=True)
    planar = s[:, 2] <= PLANAR_TOL * s[:, 0]
    A = np.empty((G.shape[0], 3, 3))
    full = ~planar
    if full.any():
        # L_k = A G_k for every row  <=>  G A^T = L  (least squares, exact for n = 3)
        At = _lstsq(G[full], L[full])
        A[full] = np.swapaxes(At, -1, -2)
    if planar.any():
        E = np.swapaxes(Vt[planar], -1, -2).copy()  # columns e1, e2, n
        E[..., :, 2] = np.cross(E[..., :, 0], E[..., :, 1])  # right-handed, or eq. 18 flips
        W = G[planar] @ E  # coordinates in the plane basis, third column ~ 0
        C2t = _lstsq(W[..., :2], L[planar])  # (2, 3): eq. 17 for both in-plane axes at once
        c1, c2 = C2t[:, 0, :], C2t[:, 1, :]
        C = np.stack([c1, c2, np.cross(c1, c2)], axis=-1)  # eq. 18
        A[planar] = C @ np.swapaxes(E, -1, -2)
    if orthonormalize:
        A = nearest_rotation(A)
    return A, planar


def _lstsq(M: Array, Y: Array) -> Array:
    """Batched least squares ``argmin_X |M X - Y|`` through the pseudo-inverse."""
    return np.linalg.pinv(M) @ Y


def kabsch(local_pts: Array, global_pts: Array) -> tuple[Array, Array]:
    """Proper rigid transform with ``global ~ R local + t`` (batched Kabsch).

    Parameters
    ----------
    local_pts, global_pts : (B, n, 3)

    Returns
    -------
    R : (B, 3, 3) rotation (det +1), t : (B, 3) translation.
    """
    a = align(np.asarray(local_pts, float), np.asarray(global_pts, float), reflection=False)
    return a.rotation, a.translation


def rotvec_to_matrix(w: Array) -> Array:
    """Rodrigues' formula for (..., 3) rotation vectors (the SO(3) exponential map)."""
    return rotation_from_rotvec(w)


def tangent_basis(n: Array) -> Array:
    """(..., 3, 2) orthonormal basis of the tangent plane of the unit sphere at (..., 3) ``n``."""
    n = np.asarray(n, float)
    a = np.zeros_like(n)
    use_x = np.abs(n[..., 0]) < 0.9
    a[..., 0] = np.where(use_x, 1.0, 0.0)
    a[..., 1] = np.where(use_x, 0.0, 1.0)
    t1 = a - np.sum(a * n, axis=-1, keepdims=True) * n
    t1 /= np.linalg.norm(t1, axis=-1, keepdims=True)
    t2 = np.cross(n, t1)
    return np.stack([t1, t2], axis=-1)
