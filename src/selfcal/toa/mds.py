"""Initialisers for anchor-free TOA calibration: MDS (paper 003) and a scalable rank method.

The range matrix has rows = receivers (sensors, ``s_n`` in 003) and columns =
transmitters (source positions, ``x_k`` in 003); entries are metres, NaN = missing.

Functions
---------
:func:`classical_mds`
    003 Algorithm 1 (eq. 7-9): double centring + truncated eigendecomposition.
:func:`estimate_receiver_distances`
    003 eq. 11: receiver-receiver distances from the reverse triangle inequality.
:func:`mds_alg2`
    003 Algorithm 2: MDS on eq. 11, then one extended MDS per source (eq. 13) aligned
    by Procrustes (eq. 14-15). Batched over sources with the same observation pattern.
:func:`rank_init`
    Rank factorisation of the double-centred squared-range matrix (Kuang, Burgess,
    Torstensson & Astrom 2013 style): rank-``d`` factorisation plus a *linear* upgrade,
    with low-rank completion of missing entries. ``O(I J d)``; scales to 1000 x 1000.
:func:`mds_multilateration`
    Receivers by MDS on eq. 11 (sub-sampled sources when large), then vectorised linear
    multilateration of every source.
:func:`initialize_toa`
    ``method="auto"`` runs the candidates that are affordable for the problem size and
    keeps the one with the smallest range residual.

Length (643 lines, above the ~600 guideline): the three 003 initialisers (MDS, Algorithm 2,
multilateration), the rank method with low-rank completion and the selector share the
distance-matrix helpers; one module per initialiser is the natural split.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .._checks import as_matrix, as_rng, check_choice, check_dim
from ..errors import DegenerateGeometryError, InputError
from ..geometry import align, canonical_gauge

__all__ = [
    "INIT_METHODS",
    "InitResult",
    "classical_mds",
    "estimate_receiver_distances",
    "complete_distances",
    "mds_alg2",
    "rank_init",
    "mds_multilateration",
    "multilaterate",
    "range_residual_rms",
    "initialize_toa",
    "initialize_toa_info",
]

Array = NDArray[np.float64]

INIT_METHODS = ("auto", "alg2", "rank", "mds-multilat")

# Above these sizes the per-source eigendecompositions of Algorithm 2 (cost ~ J (I+1)^3)
# and the O(I^2 J) reverse-triangle estimate stop being cheap next to the rank method.
_ALG2_MAX_FLOPS = 3e7
_EQ11_MAX_FLOPS = 5e7


# ---------------------------------------------------------------------------------------
# Algorithm 1
# ---------------------------------------------------------------------------------------


def _double_centre(sq: Array) -> Array:
    """``-1/2 J_n sq J_m`` with ``J_n = I - 11^T/n`` (003 eq. 7): the one double centring.

    For (..., n, m) stacks of (square or rectangular) squared-distance matrices.
    """
    row = sq.mean(axis=-1, keepdims=True)
    col = sq.mean(axis=-2, keepdims=True)
    return -0.5 * (sq - row - col + sq.mean(axis=(-1, -2), keepdims=True))


def _top_eig_coords(B: Array, dim: int) -> Array:
    """Coordinates ``U_r Sigma_r^{1/2}`` from the top-``dim`` eigenpairs of symmetric ``B``.

    Works on a stack (..., n, n). Negative eigenvalues (non-Euclidean noise) are clipped to 0,
    which is the best PSD rank-``dim`` approximation (003 eq. 8).
    """
    w, V = np.linalg.eigh(0.5 * (B + np.swapaxes(B, -1, -2)))
    w = w[..., ::-1][..., :dim]
    V = V[..., :, ::-1][..., :, :dim]
    return V * np.sqrt(np.maximum(w, 0.0))[..., None, :]


def classical_mds(distances: Array, dim: int) -> Array:
    """Classical multidimensional scaling, 003 Algorithm 1 (eq. 7-9).

    Parameters
    ----------
    distances:
        (n, n) symmetric matrix of Euclidean distances (metres), zero diagonal, no NaN.
    dim:
        Embedding dimension ``r`` (2 or 3).

    Returns
    -------
    (n, dim) coordinates, centred at the origin, defined up to an orthogonal transform.
    The 003 text writes ``s_MDS = Sigma_r^{1/2} U_r^T`` (points as columns); we return its
    transpose, one point per row. The truncated SVD of eq. 8 is taken as the symmetric
    eigendecomposition (the same thing for a PSD matrix, and well defined when noise makes
    ``B`` indefinite).
    """
    dim = check_dim(dim)
    D = as_matrix(distances, "distances", allow_nan=False, nonnegative=True)
    n = D.shape[0]
    if D.shape[1] != n:
        raise InputError(f"distances: expected a square matrix, got shape {D.shape}")
    if n < dim + 1:
        raise DegenerateGeometryError(
            f"classical MDS of {n} points cannot give a {dim}-D configuration; need at least {dim + 1}",
            kind="too-few-points",
        )
    D = 0.5 * (D + D.T)
    return _top_eig_coords(_double_centre(D**2), dim)


# ---------------------------------------------------------------------------------------
# eq. 11 and distance completion
# ---------------------------------------------------------------------------------------


def estimate_receiver_distances(ranges: Array, *, block_elements: int = 4_000_000) -> Array:
    """Receiver-receiver distances by the reverse triangle inequality, 003 eq. 11.

    ``d_ij = max_k |y_ik - y_jk|`` over the transmitters ``k`` observed by both receivers
    (eq. 10 makes every term a lower bound of ``|r_i - r_j|``; equality when a transmitter
    lies on the line through the pair, outside the segment).

    Parameters
    ----------
    ranges:
        (I, J) ranges in metres, rows = receivers, NaN = missing.
    block_elements:
        Memory cap for the vectorised (block, I, J) difference tensor.

    Returns
    -------
    (I, I) symmetric matrix, zero diagonal; NaN where a pair shares no transmitter.
    """
    Y = as_matrix(ranges, "ranges")
    I, J = Y.shape
    out = np.empty((I, I))
    block = max(1, int(block_elements // max(1, I * J)))
    for a in range(0, I, block):
        diff = np.abs(Y[a : a + block, None, :] - Y[None, :, :])
        # all-NaN rows of a pair are expected (no shared transmitter): silence nanmax warnings
        diff = np.where(np.isnan(diff), -np.inf, diff)
        m = diff.max(axis=2)
        out[a : a + block] = np.where(np.isneginf(m), np.nan, m)
    out = np.fmax(out, out.T)
    np.fill_diagonal(out, 0.0)
    return out


def complete_distances(distances: Array) -> Array:
    """Fill NaN entries of a distance matrix with shortest-path lengths (triangle bound).

    The sum of known distances along a path is an upper bound of the missing distance
    (the MDS-MAP completion). Raises :class:`DegenerateGeometryError` if the graph of known
    distances is disconnected, since the relative placement of the parts is then undetermined.
    """
    from scipy.sparse.csgraph import connected_components, shortest_path

    D = np.array(distances, dtype=float)
    missing = np.isnan(D)
    if not missing.any():
        return D
    W = np.where(missing, 0.0, D)
    # csgraph treats 0 as "no edge": keep genuine zero distances as tiny positive weights
    W = np.where(~missing & (W <= 0), 1e-12, W)
    np.fill_diagonal(W, 0.0)
    ncomp, _ = connected_components(W, directed=False)
    if ncomp > 1:
        raise DegenerateGeometryError(
            f"the receivers split into {ncomp} groups that share no transmitter; their relative "
            "placement is undetermined (add transmitters heard by both groups)",
            kind="disconnected",
        )
    P = shortest_path(W, method="D", directed=False)
    return np.where(missing, P, D)


# ---------------------------------------------------------------------------------------
# Algorithm 2
# ---------------------------------------------------------------------------------------


def _procrustes_stack(X: Array, Y: Array) -> tuple[Array, Array]:
    """Batched orthogonal Procrustes (reflection allowed), 003 eq. 14.

    X, Y: (B, n, d). Returns R (B, d, d), t (B, d) minimising ``sum |Y - (X R^T + t)|^2``.
    """
    a = align(X, Y, reflection=True)  # the one Procrustes (selfcal.geometry)
    return a.rotation, a.translation


def _alg2_sources(D_hat: Array, receivers: Array, Y: Array, dim: int) -> Array:
    """Steps 3-7 of 003 Algorithm 2 for every source, batched by observation pattern."""
    I, J = Y.shape
    obs = ~np.isnan(Y)
    sources = np.full((J, dim), np.nan)
    patterns, inverse = np.unique(obs.T, axis=0, return_inverse=True)
    inverse = np.asarray(inverse).ravel()
    for p, pattern in enumerate(patterns):
        cols = np.flatnonzero(inverse == p)
        rows = np.flatnonzero(pattern)
        n = rows.size
        if n < dim + 1:
            continue  # located afterwards by multilateration (or not at all)
        # eq. 13: extended distance matrix, the source as the last point
        Dk = np.zeros((cols.size, n + 1, n + 1))
        Dk[:, :n, :n] = D_hat[np.ix_(rows, rows)]
        Dk[:, :n, n] = Y[np.ix_(rows, cols)].T
        Dk[:, n, :n] = Dk[:, :n, n]
        coords = _top_eig_coords(_double_centre(Dk**2), dim)  # (B, n+1, d)
        ref = np.broadcast_to(receivers[rows], (cols.size, n, dim))
        R, t = _procrustes_stack(coords[:, :n], ref)
        sources[cols] = np.einsum("bij,bj->bi", R, coords[:, n]) + t  # eq. 15
    return sources


def mds_alg2(ranges: Array, dim: int) -> tuple[Array, Array]:
    """003 Algorithm 2: MDS initialisation of receivers and sources.

    1. ``D_hat`` from eq. 11 (:func:`estimate_receiver_distances`); pairs that share no
       source are completed by shortest paths (:func:`complete_distances`).
    2. Receivers ``s_MDS`` = :func:`classical_mds` of ``D_hat``.
    3.-7. For each source k: MDS of the extended matrix ``D_hat_k`` (eq. 13) that appends the
       measured ranges ``y_k``; align its receiver part to ``s_MDS`` (eq. 14, reflection
       allowed since MDS is defined up to an isometry) and map the source with it (eq. 15).

    Sources with missing ranges use only the receivers that observed them; sources seen by
    fewer than ``dim + 1`` receivers are placed by linear multilateration (least norm).

    Parameters
    ----------
    ranges: (I, J) metres, rows = receivers, NaN = missing.
    dim: 2 or 3.

    Returns
    -------
    receivers (I, dim), sources (J, dim), in the frame of ``s_MDS``.
    """
    dim = check_dim(dim)
    Y = _validated_ranges(ranges, dim)
    D_hat = complete_distances(estimate_receiver_distances(Y))
    receivers = classical_mds(D_hat, dim)
    sources = _alg2_sources(D_hat, receivers, Y, dim)
    lost = np.isnan(sources).any(axis=1)
    if lost.any():
        sources[lost] = multilaterate(receivers, Y[:, lost].T)
    return receivers, sources


# ---------------------------------------------------------------------------------------
# linear multilateration (vectorised)
# ---------------------------------------------------------------------------------------


def multilaterate(anchors: Array, ranges: Array, *, ridge: float = 1e-9) -> Array:
    """Linear least-squares multilateration of many points at once.

    For a point ``x`` and anchors ``p_i`` with ranges ``y_i``:
    ``|x|^2 - 2 p_i^T x = y_i^2 - |p_i|^2`` is linear in ``(x, |x|^2)`` (the auxiliary
    unknown is treated as free). Solved per point over its observed anchors through
    batched (d+1) x (d+1) normal equations.

    Parameters
    ----------
    anchors: (n, d) known positions (metres).
    ranges: (m, n) ranges from each of the m points to the anchors, NaN = missing.
    ridge: relative Tikhonov term so that points with fewer than d+1 observations get the
        least-norm solution instead of a singular solve.

    Returns
    -------
    (m, d) positions.
    """
    P = np.asarray(anchors, float)
    Yr = np.asarray(ranges, float)
    n, d = P.shape
    if Yr.ndim != 2 or Yr.shape[1] != n:
        raise InputError(f"multilaterate: ranges must be (m, {n}), got {Yr.shape}")
    centre = P.mean(axis=0)
    Pc = P - centre  # conditioning: the auxiliary |x|^2 is smaller near the anchors' centroid
    M = ~np.isnan(Yr)
    A = np.hstack([-2.0 * Pc, np.ones((n, 1))])  # (n, d+1)
    b = np.where(M, Yr, 0.0) ** 2 - (Pc**2).sum(axis=1)[None, :]  # (m, n)
    Mf = M.astype(float)
    # batched normal equations as two BLAS products (einsum over m x n x (d+1)^2 is slow)
    N = (Mf @ (A[:, :, None] * A[:, None, :]).reshape(n, -1)).reshape(-1, d + 1, d + 1)
    rhs = (Mf * b) @ A
    scale = np.trace(N, axis1=1, axis2=2)[:, None, None] / (d + 1)
    N = N + ridge * np.maximum(scale, 1e-12) * np.eye(d + 1)
    z = np.linalg.solve(N, rhs[..., None])[..., 0]
    return z[:, :d] + centre


def mds_multilateration(ranges: Array, dim: int, *, rng: Any = None) -> tuple[Array, Array]:
    """Receivers by MDS on eq. 11, then every source by linear multilateration.

    The reverse-triangle estimate costs ``O(I^2 J)``; above a size cap it uses a random
    subset of the transmitters (the max in eq. 11 only needs a few well-aligned ones).
    Two alternations (receivers multilaterated from the sources, then the sources again)
    remove most of the eq. 11 under-estimation bias.

    Returns receivers (I, dim), sources (J, dim).
    """
    dim = check_dim(dim)
    Y = _validated_ranges(ranges, dim)
    I, J = Y.shape
    gen = as_rng(rng)
    cols = np.arange(J)
    max_cols = max(dim + 1, int(_EQ11_MAX_FLOPS // max(1, I * I)))
    if J > max_cols:
        cols = np.sort(gen.choice(J, size=max_cols, replace=False))
    D_hat = complete_distances(estimate_receiver_distances(Y[:, cols]))
    receivers = classical_mds(D_hat, dim)
    sources = multilaterate(receivers, Y.T)
    for _ in range(2):
        receivers = multilaterate(sources, Y)
        sources = multilaterate(receivers, Y.T)
    return receivers, sources


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


# ---------------------------------------------------------------------------------------
# the entry point
# ---------------------------------------------------------------------------------------


def range_residual_rms(ranges: Array, receivers: Array, sources: Array) -> float:
    """RMS of ``y_ij - |r_i - s_j|`` over the observed entries (metres); inf if not finite."""
    Y = np.asarray(ranges, float)
    r = np.asarray(receivers, float)
    s = np.asarray(sources, float)
    if not (np.isfinite(r).all() and np.isfinite(s).all()):
        return float("inf")
    D = np.sqrt(np.maximum(((r[:, None, :] - s[None, :, :]) ** 2).sum(-1), 0.0))
    res = (Y - D)[~np.isnan(Y)]
    return float(np.sqrt(np.mean(res**2)))


@dataclass(frozen=True)
class InitResult:
    """An initial guess and how it was chosen.

    ``receivers`` (I, d) and ``sources`` (J, d) in metres, in selfcal's canonical gauge;
    ``method`` the candidate kept; ``residual_rms`` its range residual (metres);
    ``candidates`` the residual of every candidate tried (inf for a failed one).
    """

    receivers: Array
    sources: Array
    method: str
    residual_rms: float
    candidates: dict[str, float] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        """JSON-safe dict."""
        return {
            "receivers": self.receivers.tolist(),
            "sources": self.sources.tolist(),
            "method": self.method,
            "residual_rms": self.residual_rms,
            "candidates": dict(self.candidates),
        }


def _validated_ranges(ranges: Array, dim: int) -> Array:
    Y = as_matrix(ranges, "ranges", nonnegative=True, min_shape=(dim + 1, dim + 1))
    return Y


def _candidate_methods(shape: tuple[int, int], dim: int) -> list[str]:
    I, J = shape
    methods = ["rank"]
    if I * I * J <= _EQ11_MAX_FLOPS * 4:
        methods.append("mds-multilat")
    if J * (I + 1) ** 3 <= _ALG2_MAX_FLOPS:
        methods.append("alg2")
    return methods


def initialize_toa_info(ranges: Array, dim: int = 3, *, method: str = "auto",
                        rng: Any = None) -> InitResult:
    """Initial receivers and sources for anchor-free TOA calibration, with diagnostics.

    Parameters
    ----------
    ranges:
        (I, J) ranges in metres (rows = receivers, columns = transmitters), NaN = missing.
    dim:
        2 or 3.
    method:
        ``"alg2"`` (003 Algorithm 2), ``"rank"`` (:func:`rank_init`), ``"mds-multilat"``
        (:func:`mds_multilateration`) or ``"auto"``: every candidate affordable at this size
        (Algorithm 2 only while ``J (I+1)^3`` is small) and keep the smallest range residual.
    rng:
        Generator / seed for the randomized SVD and sub-sampling.

    Returns
    -------
    :class:`InitResult` in the canonical gauge (:func:`selfcal.geometry.canonical_gauge`).
    """
    dim = check_dim(dim)
    check_choice(method, "method", INIT_METHODS)
    Y = _validated_ranges(ranges, dim)
    gen = as_rng(rng)
    methods = _candidate_methods(Y.shape, dim) if method == "auto" else [method]
    # large problems try only the rank method; the sub-sampled eq. 11 route is the fallback
    fallback = ["mds-multilat"] if method == "auto" and "mds-multilat" not in methods else []
    funcs = {
        "alg2": lambda: mds_alg2(Y, dim),
        "rank": lambda: rank_init(Y, dim, rng=gen),
        "mds-multilat": lambda: mds_multilateration(Y, dim, rng=gen),
    }
    scores: dict[str, float] = {}
    best: tuple[Array, Array] | None = None
    best_name = ""
    last_error: DegenerateGeometryError | None = None
    for name in methods + fallback:
        if name in fallback and best is not None:
            break
        try:
            with np.errstate(all="ignore"):
                r, s = funcs[name]()
        except (np.linalg.LinAlgError, FloatingPointError, ValueError) as exc:
            # a matrix no eigen/SVD routine can digest (e.g. one 1e300 entry): not a geometry
            exc = DegenerateGeometryError(f"initialiser {name!r} failed on this matrix ({exc}); check for "
                                          "absurd entries (solve_toa screens them)", kind="init-failed")
            if method != "auto":
                raise exc from None
            last_error = exc
            scores[name] = float("inf")
            continue
        except DegenerateGeometryError as exc:
            if method != "auto":
                raise
            last_error = exc
            scores[name] = float("inf")
            continue
        scores[name] = range_residual_rms(Y, r, s)
        if best is None or scores[name] < scores[best_name]:
            best, best_name = (r, s), name
    if best is None or not np.isfinite(scores[best_name]):
        if last_error is not None:
            raise last_error
        raise DegenerateGeometryError("no initialiser produced a finite geometry", kind="init-failed")
    r, s_opt, _ = canonical_gauge(best[0], best[1])
    assert s_opt is not None
    return InitResult(receivers=r, sources=s_opt, method=best_name, residual_rms=scores[best_name],
                      candidates=scores)


def initialize_toa(ranges: Array, dim: int = 3, *, method: str = "auto",
                   rng: Any = None) -> tuple[Array, Array]:
    """Initial (receivers (I, dim), sources (J, dim)) for the TOA NLS; see :func:`initialize_toa_info`.

    This is what :func:`selfcal.toa.solve_toa` calls for ``init="auto"``; noise-free data
    gives the exact geometry (up to a rigid motion) for ``"rank"`` and, with enough sources
    around the receivers, a start from which the NLS converges for every method.
    """
    res = initialize_toa_info(ranges, dim, method=method, rng=rng)
    return res.receivers, res.sources
