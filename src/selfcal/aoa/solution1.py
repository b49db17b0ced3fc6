"""Solution 1 of paper 001: Newton-Raphson on the torus equations (eq. 5-18).

For each pair of beacons the angle ``theta_ij`` between their lines of sight does not depend on
the (unknown) orientation (eq. 5-8)::

    f_ij(m) = (b_i - m).(b_j - m) - |b_i - m| |b_j - m| ubar_i . ubar_j = 0

(a spindle-torus surface around the chord b_i b_j). Three such surfaces meet at the receiver.
Once ``m`` is known, the global unit vectors ``u_k = (b_k - m)/|b_k - m|`` (eq. 11) and the
measured local ones give ``A = Ubar U^-1`` (eq. 14), or its planar least-squares form
(eq. 15-18) when ``U`` is singular.

Initial guess (the paper: "one with the three component values taking sufficiently large
absolute values"): we run Newton from the eight points ``centroid + L (+-1, +-1, +-1)`` with
``L`` twice the largest beacon separation, keep the converged roots whose rotation is proper
(``det A > 0``; the mirror image of the receiver in the beacons' plane solves eq. 7 too but
needs a reflection), and take the one with the smallest residual, earlier starts winning ties.
"""

from __future__ import annotations

import itertools

import numpy as np
from numpy.typing import NDArray

from .orientation import nearest_rotation, orientation_from_vectors
from .solution2 import pairs_of

Array = NDArray[np.float64]

__all__ = ["torus_residuals", "torus_jacobian", "newton_location", "solution1", "default_starts"]


def torus_residuals(beacons: Array, cosines: Array, pairs: Array, m: Array) -> Array:
    """``f_ij(m)`` of eq. 8 for each pair: (B, P) in m^2; ``m`` is (B, 3), cosines (B, P)."""
    g = beacons[None] - m[:, None]
    n = np.linalg.norm(g, axis=-1)
    i, j = pairs[:, 0], pairs[:, 1]
    return np.sum(g[:, i] * g[:, j], -1) - n[:, i] * n[:, j] * cosines


def torus_jacobian(beacons: Array, cosines: Array, pairs: Array, m: Array) -> Array:
    """Analytic Jacobian of eq. 8 with respect to ``m``: (B, P, 3).

    ``d f_ij / d m = -(g_i + g_j) + c_ij (|g_j| g_i/|g_i| + |g_i| g_j/|g_j|)``, ``g_k = b_k - m``.
    """
    g = beacons[None] - m[:, None]
    n = np.linalg.norm(g, axis=-1)
    i, j = pairs[:, 0], pairs[:, 1]
    gi, gj, ni, nj = g[:, i], g[:, j], n[:, i][..., None], n[:, j][..., None]
    return -(gi + gj) + cosines[..., None] * (nj * gi / ni + ni * gj / nj)


def newton_location(
    beacons: Array, cosines: Array, pairs: Array, m0: Array, *, max_iter: int = 60, tol: float = 1e-13
) -> tuple[Array, Array, Array, Array]:
    """Newton-Raphson (Gauss-Newton for more than three beacons) on eq. 7, batched.

    Returns ``m`` (B, 3), iterations (B,), relative residual ``max|f| / max d_ij^2`` (B,) and
    converged (B,): residual below ``tol`` or (over-determined case) a negligible last step.
    """
    m = np.array(m0, float, copy=True)
    B = m.shape[0]
    d = beacons[pairs[:, 1]] - beacons[pairs[:, 0]]
    scale = float(np.max(np.sum(d**2, axis=1)))
    iters = np.zeros(B, int)
    active = np.ones(B, bool)
    small_step = np.zeros(B, bool)
    for _ in range(max_iter):
        f = torus_residuals(beacons, cosines, pairs, m)
        res = np.max(np.abs(f), axis=1) / scale
        active &= np.isfinite(res) & (res > tol) & (np.abs(m).max(axis=1) < 1e6 * np.sqrt(scale))
        active &= ~small_step
        if not active.any():
            break
        J = torus_jacobian(beacons, cosines, pairs, m)
        with np.errstate(all="ignore"):
            JtJ = np.swapaxes(J, 1, 2) @ J
            ok = np.isfinite(JtJ).all(axis=(1, 2)) & (np.abs(np.linalg.det(JtJ)) > 1e-300)
            step = np.zeros_like(m)
            sel = active & ok
            if sel.any():
                step[sel] = np.linalg.solve(JtJ[sel], np.einsum("bpk,bp->bk", J[sel], f[sel])[..., None])[..., 0]
        m[sel] -= step[sel]
        iters[sel] += 1
        small_step |= sel & (np.linalg.norm(step, axis=1) < 1e-12 * np.sqrt(scale))
        active &= ok
    f = torus_residuals(beacons, cosines, pairs, m)
    res = np.max(np.abs(f), axis=1) / scale
    converged = np.isfinite(res) & ((res < 1e-8) | small_step)
    return m, iters, res, converged


def default_starts(beacons: Array) -> Array:
    """The eight initial guesses ``centroid + L (+-1, +-1, +-1)`` (see the module notes), (8, 3)."""
    c = beacons.mean(axis=0)
    L = 2.0 * float(np.max(np.linalg.norm(beacons[:, None] - beacons[None], axis=-1)))
    signs = np.array(list(itertools.product((-1.0, 1.0), repeat=3)))
    return c + L * signs


def solution1(
    beacons: Array,
    bearings: Array,
    *,
    starts: Array | None = None,
    orthonormalize: bool = False,
    max_iter: int = 60,
) -> dict[str, Array]:
    """Paper 001 Solution 1 (eq. 7-18), batched, with every converged root.

    Parameters
    ----------
    beacons : (N, 3) beacon positions (m), N >= 3.
    bearings : (B, N, 3) unit bearings in the receiver frame.
    starts : (S, 3) initial guesses (default :func:`default_starts`).
    orthonormalize : project ``A`` onto SO(3) (beyond the paper).

    Returns
    -------
    dict with ``position`` (B, 3), ``A`` (B, 3, 3) (the paper's ``local = A global``),
    ``iterations`` (B,), ``converged`` (B,), ``planar`` (B,), and the per-start roots
    ``roots`` (B, S, 3), ``root_A`` (B, S, 3, 3), ``root_ok`` (B, S) (converged and proper).
    """
    b = np.asarray(beacons, float)
    U = np.asarray(bearings, float)
    B, N, _ = U.shape
    pairs = pairs_of(N)
    i, j = pairs[:, 0], pairs[:, 1]
    cosines = np.sum(U[:, i] * U[:, j], -1)
    S0 = default_starts(b) if starts is None else np.asarray(starts, float)
    S = S0.shape[0]
    m0 = np.broadcast_to(S0, (B, S, 3)).reshape(-1, 3)
    m, iters, res, conv = newton_location(b, np.repeat(cosines, S, axis=0), pairs, m0, max_iter=max_iter)
    g = b[None] - m[:, None]
    with np.errstate(all="ignore"):
        u = g / np.linalg.norm(g, axis=-1, keepdims=True)  # eq. 11
    finite = np.isfinite(u).all(axis=(1, 2))
    A = np.full((B * S, 3, 3), np.nan)
    planar = np.zeros(B * S, bool)
    if finite.any():
        A[finite], planar[finite] = orientation_from_vectors(
            u[finite], np.repeat(U, S, axis=0)[finite], orthonormalize=False
        )
    with np.errstate(all="ignore"):
        det = np.linalg.det(np.where(np.isfinite(A), A, 0.0))
    if orthonormalize and finite.any():
        A[finite] = nearest_rotation(A[finite])
    ok = finite & conv & (det > 0)
    m = m.reshape(B, S, 3)
    A = A.reshape(B, S, 3, 3)
    ok = ok.reshape(B, S)
    score = np.where(ok, res.reshape(B, S), np.inf)
    # ties (three beacons: every root fits exactly) go to the earliest start
    best = np.argmin(np.round(score / 1e-10), axis=1)
    rows = np.arange(B)
    return {
        "position": m[rows, best],
        "A": A[rows, best],
        "iterations": iters.reshape(B, S)[rows, best],
        "converged": ok[rows, best],
        "planar": planar.reshape(B, S)[rows, best],
        "roots": m,
        "root_A": A,
        "root_ok": ok,
    }
