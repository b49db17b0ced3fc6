"""Solution 2 of paper 001: Newton-Raphson on the cosine-rule system in the ranges (eq. 19-27).

Unknowns are the ranges ``r_k = |b_k - m|``. For each beacon pair the cosine rule gives
(eq. 20)::

    f(r_i, r_j) = r_i^2 + r_j^2 - 2 r_i r_j ubar_i . ubar_j - d_ij^2 = 0

(three elliptic cylinders in r-space for three beacons). Then the local beacon-difference
vectors ``dbar_ij`` (eq. 21) and their global counterparts ``d_ij`` (eq. 22) give the paper's
rotation ``A = Dbar D^-1`` (eq. 23), or its planar least-squares variant (eq. 25 + 17-18), and
the location is the centroid of the three back-projections (eq. 27).

Notes on the paper's formulas (checked against their derivation):

* eq. 21 as printed, ``dbar_ij = r_i ubar_i - r_j ubar_j``, is the local image of
  ``b_i - b_j`` and is not normalised, while eq. 22 is ``(b_j - b_i)/|b_j - b_i|``. The pair
  must describe the same vector, so we use ``dbar_ij = (r_j ubar_j - r_i ubar_i) / d_ij``.
* Three beacons always give coplanar difference vectors (``d12 + d23 + d31`` spans a plane), so
  with the paper's three beacons ``D`` is always singular and eq. 25 is the only usable form.
"""

from __future__ import annotations

from itertools import combinations

import numpy as np
from numpy.typing import NDArray

from .orientation import orientation_from_vectors

Array = NDArray[np.float64]

__all__ = ["pairs_of", "newton_ranges", "solution2", "START_SCALES"]

#: equal-range Newton starts, in units of the largest beacon separation
START_SCALES = (1.0, 2.0, 4.0, 0.5)


def pairs_of(n: int) -> Array:
    """Index pairs used by the equation systems: (1,2), (2,3), (3,1) for three beacons as in
    the paper (eq. 24), all ``i < j`` pairs otherwise. Shape (P, 2)."""
    if n == 3:
        return np.array([[0, 1], [1, 2], [2, 0]])
    return np.array(list(combinations(range(n), 2)))


def newton_ranges(
    cosines: Array,
    d2: Array,
    pairs: Array,
    r0: Array,
    *,
    max_iter: int = 50,
    tol: float = 1e-13,
) -> tuple[Array, Array, Array]:
    """Solve the cosine-rule system (eq. 19-20) for the ranges, batched.

    Newton-Raphson for three beacons (square system); Gauss-Newton on all pairs for more.

    Parameters
    ----------
    cosines : (B, P) ``ubar_i . ubar_j`` for each pair.
    d2 : (P,) squared beacon distances ``d_ij^2`` (m^2).
    pairs : (P, 2) beacon index pairs.
    r0 : (B, N) initial ranges (m).

    Returns
    -------
    r : (B, N) ranges, iterations : (B,) int, residual : (B,) max |f| / max d_ij^2.
    """
    r = np.array(r0, float, copy=True)
    B, N = r.shape
    i, j = pairs[:, 0], pairs[:, 1]
    P = len(pairs)
    rows = np.arange(P)
    scale = float(np.max(d2))
    iters = np.zeros(B, int)
    active = np.ones(B, bool)
    for _ in range(max_iter):
        ri, rj = r[:, i], r[:, j]
        f = ri**2 + rj**2 - 2 * ri * rj * cosines - d2
        res = np.max(np.abs(f), axis=1) / scale
        active &= res > tol
        if not active.any():
            break
        J = np.zeros((B, P, N))
        J[:, rows, i] = 2 * ri - 2 * rj * cosines
        J[:, rows, j] = 2 * rj - 2 * ri * cosines
        with np.errstate(all="ignore"):
            JtJ = np.swapaxes(J, 1, 2) @ J
            g = np.einsum("bpn,bp->bn", J, f)
            ok = np.isfinite(JtJ).all(axis=(1, 2)) & (np.abs(np.linalg.det(JtJ)) > 1e-300)
            step = np.zeros_like(r)
            if ok.any():
                step[ok] = np.linalg.solve(JtJ[ok], g[ok][..., None])[..., 0]
        upd = active & ok
        r[upd] -= step[upd]
        iters[upd] += 1
        active &= ok
    ri, rj = r[:, i], r[:, j]
    f = ri**2 + rj**2 - 2 * ri * rj * cosines - d2
    return r, iters, np.max(np.abs(f), axis=1) / scale


def solution2(
    beacons: Array,
    bearings: Array,
    *,
    r0: Array | None = None,
    orthonormalize: bool = False,
    max_iter: int = 50,
    _all_starts: bool = False,
) -> dict[str, Array]:
    """Paper 001 Solution 2 (eq. 19-27), batched.

    Parameters
    ----------
    beacons : (N, 3) beacon positions (m).
    bearings : (B, N, 3) unit bearings in the receiver frame.
    r0 : (B, N) or None
        Initial ranges. Default: equal ranges ``L * s`` for the scales :data:`START_SCALES`
        (``L`` the largest beacon separation) -- the paper only asks for "three positive
        values"; Newton pulls each to a root of the P3P system. The root with the smallest
        residual wins, ties (three beacons: all roots are exact) going to the earliest start.
    orthonormalize : project the paper's ``A`` onto SO(3) before eq. 27 (beyond the paper).

    Returns
    -------
    dict with ``position`` (B, 3), ``A`` (B, 3, 3) the paper's rotation (``local = A global``),
    ``ranges`` (B, N), ``iterations`` (B,), ``converged`` (B,), ``planar`` (B,).
    """
    b = np.asarray(beacons, float)
    U = np.asarray(bearings, float)
    B, N, _ = U.shape
    pairs = pairs_of(N)
    i, j = pairs[:, 0], pairs[:, 1]
    diff = b[j] - b[i]
    dist = np.linalg.norm(diff, axis=1)
    cosines = np.einsum("bpk,bpk->bp", U[:, i], U[:, j])
    if r0 is None:
        starts = float(dist.max()) * np.array(START_SCALES)
    else:
        starts = np.asarray(r0, float)[None]
    S = len(starts)
    if N > 3 and r0 is None:
        # beyond the paper: solve the paper's three-beacon system from each start, then start
        # the all-pairs Gauss-Newton at the ranges implied by each three-beacon pose; the
        # extra beacons then decide between the roots
        sub = solution2(b[:3], U[:, :3], orthonormalize=True, max_iter=max_iter, _all_starts=True)
        ms = sub["_positions"]  # (S, B, 3)
        r0s = np.linalg.norm(b[None, None] - ms[:, :, None], axis=-1).reshape(S * B, N)
        r0s = np.where(np.isfinite(r0s), r0s, float(dist.max()))
    else:
        r0s = np.broadcast_to(starts.reshape(S, 1, -1), (S, B, N)).reshape(S * B, N)
    rs, its, ress = newton_ranges(np.tile(cosines, (S, 1)), dist**2, pairs, r0s, max_iter=max_iter)
    rs, its, ress = rs.reshape(S, B, N), its.reshape(S, B), ress.reshape(S, B)
    if N == 3:
        good = (ress < 1e-8) & (rs > 0).all(axis=2)
    else:  # over-determined: compare the least-squares residuals of the positive solutions
        good = (rs > 0).all(axis=2) & np.isfinite(ress)
    score = np.where(good, np.round(ress / 1e-10), np.inf)
    pick = np.argmin(score, axis=0)  # ties (every exact root of three beacons): earliest start
    cols = np.arange(B)
    if _all_starts:
        Ds = np.broadcast_to(diff / dist[:, None], (S * B, len(pairs), 3))
        loc = rs.reshape(S * B, N)[..., None] * np.tile(U, (S, 1, 1))
        As, _ = orientation_from_vectors(Ds, (loc[:, j] - loc[:, i]) / dist[None, :, None], orthonormalize=True)
        ms = np.mean(b[None] - np.einsum("bji,bkj->bki", As, loc), axis=1).reshape(S, B, 3)
        return {"_positions": np.where(good[..., None], ms, np.nan)}
    r, iters, res = rs[pick, cols], its[pick, cols], ress[pick, cols]
    converged = good[pick, cols] & ((res < 1e-8) | (N > 3))
    # eq. 22 (global) and eq. 21 (local, corrected to the same vector b_j - b_i, normalised)
    D = np.broadcast_to(diff / dist[:, None], (B, len(pairs), 3))
    local = r[..., None] * U
    Dbar = (local[:, j] - local[:, i]) / dist[None, :, None]
    A, planar = orientation_from_vectors(D, Dbar, orthonormalize=orthonormalize)
    # eq. 27: centroid of b_k - A^T rbar_k (A^T stands in for A^-1, A being orthogonal)
    m = np.mean(b[None] - np.einsum("bji,bkj->bki", A, local), axis=1)
    return {"position": m, "A": A, "ranges": r, "iterations": iters, "converged": converged, "planar": planar}
