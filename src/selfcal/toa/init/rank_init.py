"""Rank factorisation initialiser: rank-d factorisation of the double-centred squared ranges
plus a linear upgrade (Kuang, Burgess, Torstensson & Astrom 2013 style), with low-rank
completion of missing entries; ``O(I J d)``, scales to 1000 x 1000. One of the
initialisers of :func:`selfcal.toa.init.mds.initialize_toa`.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..._checks import as_rng, check_dim
from ...errors import DegenerateGeometryError
from .mds_core import _double_centre, _validated_ranges, multilaterate, range_residual_rms

__all__ = ["rank_init"]

Array = NDArray[np.float64]


# ---------------------------------------------------------------------------------------
# rank factorisation + linear upgrade
# ---------------------------------------------------------------------------------------


def _truncated_svd(X: Array, k: int, rng: np.random.Generator, basis: Array | None = None,
                   power: int = 2) -> tuple[Array, Array, Array]:
    """Top-``k`` SVD by randomized subspace iteration (Halko, Martinsson & Tropp 2011)."""
    m, n = X.shape
    if min(m, n) <= 4 * k + 10:
        U, s, Vt = np.linalg.svd(X, full_matrices=False)
        return U[:, :k], s[:k], Vt[:k]
    Q = basis if basis is not None else X @ rng.standard_normal((n, k + 8))
    Q, _ = np.linalg.qr(Q)
    for _ in range(power):
        Z, _ = np.linalg.qr(X.T @ Q)
        Q, _ = np.linalg.qr(X @ Z)
    Ub, s, Vt = np.linalg.svd(Q.T @ X, full_matrices=False)
    return (Q @ Ub)[:, :k], s[:k], Vt[:k]


def _masked_grams(Mf: Array, F: Array) -> Array:
    """``G_i = sum_j Mf_ij f_j f_j^T`` for every row i, as one matrix product: (m, k, k)."""
    k = F.shape[1]
    return (Mf @ (F[:, :, None] * F[:, None, :]).reshape(F.shape[0], k * k)).reshape(-1, k, k)


def _complete_low_rank(S: Array, mask: NDArray[np.bool_], rank: int, rng: np.random.Generator,
                       iters: int = 200, tol: float = 1e-12) -> Array:
    """Fill the unobserved entries of ``S`` with a rank-``rank`` fit to the observed ones.

    ``S`` (squared ranges) has rank <= d + 2 exactly. Start: the additive (row + column
    effect) fill and its truncated SVD; then alternating least squares on the observed
    entries only (each row factor, then each column factor, by batched ``rank x rank``
    normal equations), which converges much faster than iterated SVD imputation when
    many entries are missing.
    """
    miss = ~mask
    if not miss.any():
        return S
    Mf = mask.astype(float)
    X = np.where(mask, S, 0.0)
    cnt_r = np.maximum(mask.sum(axis=1, keepdims=True), 1)
    cnt_c = np.maximum(mask.sum(axis=0, keepdims=True), 1)
    grand = X.sum() / mask.sum()
    row = X.sum(axis=1, keepdims=True) / cnt_r - grand
    col = X.sum(axis=0, keepdims=True) / cnt_c - grand
    X0 = np.where(mask, S, grand + row + col)
    U, s, Vt = _truncated_svd(X0, rank, rng, power=1)
    P = U * np.sqrt(s)
    Q = Vt.T * np.sqrt(s)
    scale = float(np.mean(X[mask] ** 2)) or 1.0
    eye = np.eye(rank)
    prev = np.inf
    for _ in range(iters):
        # rows: min_p sum_j m_ij (S_ij - p^T q_j)^2; a tiny ridge keeps rows with < rank
        # observations solvable (they get the least-norm factor)
        N = _masked_grams(Mf, Q) + 1e-10 * np.trace(Q.T @ Q) * eye
        P = np.linalg.solve(N, (X @ Q)[..., None])[..., 0]
        N = _masked_grams(Mf.T, P) + 1e-10 * np.trace(P.T @ P) * eye
        Q = np.linalg.solve(N, (X.T @ P)[..., None])[..., 0]
        err = float(np.sum(Mf * (X - P @ Q.T) ** 2)) / (mask.sum() * scale)
        if prev - err <= tol * max(err, 1e-300) or err < 1e-28:
            break
        prev = err
    return np.where(mask, S, P @ Q.T)


def _upgrade_candidates(Sq: Array, dim: int, rng: np.random.Generator) -> list[tuple[Array, Array]]:
    """Linear upgrade of the rank-``dim`` factorisation of the double-centred squared ranges.

    With receiver centroid at the origin and ``b`` the source centroid:
    ``C = -1/2 (Sq - row - col + grand) = X^T Y'`` where X (d, I) are receivers and Y' (d, J)
    the centred sources. A rank-d SVD ``C = A B`` fixes ``X^T = A L`` and ``Y' = L^{-1} B``
    up to an invertible ``L``. The row means of ``Sq`` are
    ``m_i = a_i^T H a_i - 2 a_i^T v + c0`` with ``H = L L^T``, ``v = L b`` — linear in
    (H, v, c0); the column means are ``n_j = b_j^T G b_j + 2 b_j^T w + c1`` with
    ``G = H^{-1}``, ``w = G v`` — linear too. Each side that has enough points
    (d(d+1)/2 + d + 1) gives one candidate; ``L`` is the Cholesky factor of the PSD-projected H.
    """
    I, J = Sq.shape
    C = _double_centre(Sq)
    U, s, Vt = _truncated_svd(C, dim, rng, power=1)
    if s[-1] <= 1e-9 * s[0]:
        raise DegenerateGeometryError(
            f"the double-centred squared ranges have rank < {dim}: receivers or transmitters do not "
            f"span {dim}-D space (coplanar / collinear)",
            kind="rank-deficient",
        )
    A = U * np.sqrt(s)  # (I, d)
    B = np.sqrt(s)[:, None] * Vt  # (d, J)
    iu = np.triu_indices(dim)
    n_unk = len(iu[0]) + dim + 1
    out: list[tuple[Array, Array]] = []

    def sym_design(P: Array) -> Array:
        # p^T H p for symmetric H in its upper-triangle parameters
        cols = [P[:, a] * P[:, b] * (1.0 if a == b else 2.0) for a, b in zip(*iu, strict=True)]
        return np.stack(cols, axis=1)

    def unpack(h: Array) -> Array:
        H = np.zeros((dim, dim))
        H[iu] = h
        return H + np.triu(H, 1).T

    def psd_chol(H: Array) -> Array | None:
        w, V = np.linalg.eigh(0.5 * (H + H.T))
        if w[-1] <= 0:
            return None
        w = np.maximum(w, 1e-6 * w[-1])
        return np.linalg.cholesky((V * w) @ V.T)

    if I >= n_unk:
        M = np.hstack([sym_design(A), -2.0 * A, np.ones((I, 1))])
        sol = np.linalg.lstsq(M, Sq.mean(axis=1), rcond=None)[0]
        H = unpack(sol[: len(iu[0])])
        v = sol[len(iu[0]) : len(iu[0]) + dim]
        L = psd_chol(H)
        if L is not None:
            b = np.linalg.solve(L, v)
            out.append((A @ L, np.asarray(np.linalg.solve(L, B).T + b, dtype=float)))
    if J >= n_unk:
        Bt = B.T
        M = np.hstack([sym_design(Bt), 2.0 * Bt, np.ones((J, 1))])
        sol = np.linalg.lstsq(M, Sq.mean(axis=0), rcond=None)[0]
        G = unpack(sol[: len(iu[0])])
        w = sol[len(iu[0]) : len(iu[0]) + dim]
        Lg = psd_chol(G)  # G = H^{-1} = L^{-T} L^{-1}: with K = chol(G), L^{-1} = K^T up to rotation
        if Lg is not None:
            Linv = Lg.T
            # b = L^{-1} v and v = H w  =>  b = L^{-1} L L^T w = L^T w = Linv^{-T} w
            b = np.linalg.solve(Linv.T, w)
            out.append((A @ np.linalg.inv(Linv), (Linv @ B).T + b))
    return out


def rank_init(ranges: Array, dim: int, *, rng: Any = None) -> tuple[Array, Array]:
    """Scalable initialiser: rank-``dim`` factorisation of the double-centred squared ranges.

    Steps: squared ranges (rank <= d+2) with missing entries filled by low-rank completion;
    double centring (rank d, eq. 7 generalised to a rectangular matrix); truncated SVD;
    linear upgrade from the row and the column means (:func:`_upgrade_candidates`);
    the candidate with the smallest range residual is kept and polished by one alternation
    of linear multilateration (sources from receivers, receivers from sources). Cost
    ``O(I J d)`` per completion sweep; exact on noise-free complete data.

    Needs ``max(I, J) >= d(d+1)/2 + d + 1`` (6 in 2-D, 10 in 3-D).

    Returns receivers (I, dim), sources (J, dim).
    """
    dim = check_dim(dim)
    Y = _validated_ranges(ranges, dim)
    gen = as_rng(rng)
    mask = ~np.isnan(Y)
    Sq = _complete_low_rank(np.where(mask, Y, 0.0) ** 2, mask, dim + 2, gen)
    cands = _upgrade_candidates(Sq, dim, gen)
    if not cands:
        need = dim * (dim + 1) // 2 + dim + 1
        raise DegenerateGeometryError(
            f"rank initialiser: the linear upgrade needs at least {need} receivers or "
            f"transmitters in {dim}-D (got {Y.shape[0]} x {Y.shape[1]}), or the upgrade "
            "matrix was not positive definite (noise too large for this size)",
            kind="upgrade-failed",
        )
    polished = []
    for r, s in cands:
        polished.append((r, s))
        s2 = multilaterate(r, Y.T)
        polished.append((multilaterate(s2, Y), s2))
    scores = [range_residual_rms(Y, r, s) for r, s in polished]
    return polished[int(np.nanargmin(scores))]
