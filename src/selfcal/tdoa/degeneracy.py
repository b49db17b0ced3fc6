"""Failure modes of far-field TDOA self-calibration (paper 000, sections 2.1-2.2).

Given a reduced matrix ``X = Z N`` (Lemma 1: D minus a per-column constant ``K_j``; we use
the column means, so that the rows of Z are the positions relative to their centroid and
the noise is not concentrated in a rank-1 term as it is with ``K_j = D_1j``):

* rank 3 but the directions on a common quadratic cone ``n^T Omega n = 0`` (Theorem 2):
  the linear system ``ntilde_j^T B ntilde_j = 1`` for B is rank deficient -> ``cone``;
* rank 2: either the positions are coplanar (``planar-motion``) or the directions are
  (``coplanar-directions``); the two are told apart by whether the 2-D analogue of the B
  system, ``ntilde_j^T B2 ntilde_j = 1``, is consistent (it is exactly when the directions
  lie in a plane, because then the 2-D directions have unit norm);
* rank 1: parallel directions (``parallel-directions``: all ``|ntilde_j|`` equal) or
  collinear positions (``collinear-motion``).

Noise-aware thresholds (documented contract)
--------------------------------------------
``sigma`` is the noise level of an entry: the user's ``noise_std``, else estimated from the
residual ``R`` of the best rank-r approximation (r = the tested rank) as
``1.4826 median|R_ij| sqrt(m k / ((m-1-r)(k-r)))`` (a robust version of
``sum_{i>r} s_i^2 / ((m-1-r)(k-r))``; m-1 because centring removes one row's freedom),
floored at ``1e-14 s_1`` (rounding).
The rank is chosen by nested tests (rank r - 1 against rank r, r = 3, 2, 1): ``s_r`` counts
as signal when it exceeds ``sigma q`` and ``rel_floor * s_1``. With a given noise, sigma is
that noise and q = :func:`noise_edge` ``(m - r, k - r + 1, alpha)``: the (1 - alpha) quantile
of the largest singular value of the (m-1-(r-1)) x (k-(r-1)) noise matrix that remains under
the smaller model (Tracy-Widom, Johnstone 2001). With an estimated noise, sigma comes from
the rank-r residual with the largest noise component's expected energy added back
(:func:`_sigma_null`), so a real ``s_r`` never sets the level it is compared with, and q =
:func:`null_edge`, the quantile of that estimated-noise statistic (exact by a seeded
Monte-Carlo for small matrices, where it matters). A classical F test of the two nested fits would be wrong here: the r-th
singular direction is chosen by the data, so under the smaller model ``s_r^2 / sigma^2`` is
the largest eigenvalue of a Wishart matrix (about ``(sqrt(m) + sqrt(k))^2``), not a
chi-square with ``m + k - 2r + 1`` degrees of freedom (mean ``m + k``): for 47 x 180 the F
test would call pure noise signal nearly always. The false-alarm rate alpha (default
1e-3) is checked over many seeds in the tests. The cone test asks whether a quadric ``Omega`` (unit Frobenius norm)
with ``ntilde_j^T Omega ntilde_j = 0`` for all j exists up to noise: the smallest singular
value ``mu_6`` of the design matrix of ``ntilde_j^T B ntilde_j = 1`` is compared with the
size that noise alone gives it along its singular vector ``Omega_6``,
``nu = sqrt(sum_j (2 sigma |Omega_6 ntilde_j|)^2)`` (first-order propagation of
``delta(n^T Omega n) = 2 n^T Omega delta n``); ``cone_snr = mu_6 / nu < cone_tol`` -> cone.
The coplanar-directions test accepts the 2-D quadric fit when its chi-square per degree of
freedom under the same propagation is below ``chi2_tol``; parallel directions when the
rms spread of ``|ntilde_j|`` is within ``2 sigma``.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..robust import mad_std
from .minimal import quadric_design, sym_from_vec

__all__ = [
    "RANK_ALPHA",
    "noise_edge",
    "null_edge",
    "rank_threshold",
    "tw1_quantile",
    "top_svd",
    "DEGENERACIES",
    "DegeneracyReport",
    "analyse_degeneracy",
    "fit_quadric",
    "partial_planar_motion",
    "partial_coplanar_directions",
    "partial_collinear_motion",
    "partial_parallel_directions",
    "min_volume_ellipse",
]

Array = NDArray[np.float64]
DEGENERACIES = ("planar-motion", "coplanar-directions", "cone", "collinear-motion", "parallel-directions")
_SQ2 = np.sqrt(2.0)


@dataclass(frozen=True)
class DegeneracyReport:
    """Outcome of :func:`analyse_degeneracy`.

    kind: None or one of :data:`DEGENERACIES`; rank: numerical rank of X (0-3);
    singular_values: leading singular values of X (metres); noise_std: sigma used
    (metres, per entry of X); rank_threshold: threshold for the third singular value;
    cone_snr: ``mu_6 / nu`` of the cone test (NaN unless rank 3); quadric_residual: chi-square per dof of the 2-D quadric fit (NaN unless rank 2).
    """

    kind: str | None
    rank: int
    singular_values: Array
    noise_std: float
    rank_threshold: float
    cone_snr: float
    quadric_residual: float

    def to_dict(self) -> dict[str, Any]:
        """JSON-safe dictionary."""
        def num(x: float) -> float | None:
            return float(x) if np.isfinite(x) else None

        return {
            "kind": self.kind,
            "rank": int(self.rank),
            "singular_values": [float(v) for v in self.singular_values[:8]],
            "noise_std": num(self.noise_std),
            "rank_threshold": num(self.rank_threshold),
            "cone_snr": num(self.cone_snr),
            "quadric_residual": num(self.quadric_residual),
        }


def fit_quadric(nt: Array) -> tuple[Array, Array, Array]:
    """Least-squares ``B`` (symmetric, d x d) from ``ntilde_j^T B ntilde_j = 1`` (paper 000, sec. 2.3 (ii)).

    Parameters
    ----------
    nt : (k, d) rows ``ntilde_j``, d in {2, 3}.

    Returns
    -------
    B : (d, d) minimum-norm least-squares solution; mu : singular values of the design
    matrix in the orthonormal (Frobenius) parametrisation, descending; res : (k,) residuals
    ``ntilde_j^T B ntilde_j - 1``.
    """
    d = nt.shape[1]
    if d == 3:
        M = quadric_design(nt) * np.array([1, 1, 1, _SQ2 / 2, _SQ2 / 2, _SQ2 / 2])
    else:
        a, b = nt[:, 0], nt[:, 1]
        M = np.stack([a * a, b * b, _SQ2 * a * b], axis=1)
    x, *_ = np.linalg.lstsq(M, np.ones(len(nt)), rcond=None)
    mu = np.linalg.svd(M, compute_uv=False)
    if d == 3:
        B = sym_from_vec(x * np.array([1, 1, 1, _SQ2 / 2, _SQ2 / 2, _SQ2 / 2]))
    else:
        B = np.array([[x[0], x[2] / _SQ2], [x[2] / _SQ2, x[1]]])
    res = np.einsum("ja,ab,jb->j", nt, B, nt) - 1.0
    return B, mu, res


#: matrices with both sides above this use a truncated SVD (the leading singular triplets only)
TRUNCATED_SVD_MIN = 300


def top_svd(X: Array, r: int) -> tuple[Array, Array, Array]:
    """Leading ``r`` singular triplets of X (``U`` (m, r), ``s`` (r,), ``Vt`` (r, k)), descending.

    ``numpy.linalg.svd`` for small matrices; for large ones (both sides above
    :data:`TRUNCATED_SVD_MIN`) ``scipy.sparse.linalg.svds`` (ARPACK, tolerance 0 = machine
    precision), O(m k r) per iteration instead of O(m k min(m, k)).
    """
    X = np.asarray(X, dtype=float)
    r = max(1, min(int(r), min(X.shape)))
    if min(X.shape) <= TRUNCATED_SVD_MIN or r >= min(X.shape) - 1:
        U, s, Vt = np.linalg.svd(X, full_matrices=False)
        return U[:, :r], s[:r], Vt[:r]
    from scipy.sparse.linalg import svds

    U, s, Vt = svds(X, k=r, tol=0.0, random_state=0)
    order = np.argsort(s)[::-1]
    return U[:, order], s[order], Vt[order]


def _sigma(X: Array, U: Array, s: Array, Vt: Array, r: int, rows: int, cols: int) -> float:
    """Noise level from the residual of the rank-r approximation.

    The median absolute residual (x 1.4826, corrected by sqrt(entries / dof)) rather than the
    residual energy, so that a few gross errors do not inflate it.
    """
    dof = (rows - r) * (cols - r)
    if dof <= 0:
        return 0.0
    R = X - (U[:, :r] * s[:r]) @ Vt[:r]
    return float(mad_std(R, centre=False) * np.sqrt(R.size / dof))


def _sigma_null(X: Array, U: Array, s: Array, Vt: Array, r: int, rows: int, cols: int) -> float | None:
    """Noise level under "rank <= r - 1" from the residual of the rank-r approximation.

    Under the smaller model the r-th singular value is the largest of the
    (rows - r + 1) x (cols - r + 1) noise matrix that remains, so the rank-r residual holds the
    noise energy less that largest component: sigma^2 ((rows - r + 1)(cols - r + 1) - mu), with
    mu = E[s_max^2] (Johnstone's centre). Estimating sigma there, rather than from the rank-(r - 1)
    residual, keeps a real r-th component out of the noise estimate: from the rank-(r - 1)
    residual a noise-free rank-3 matrix of 8 x 12 was called rank 2, because its s_3 then sets
    the noise level it is compared with. ``None`` when fewer than two degrees of freedom remain
    (the numerical rank decides there). The median absolute residual is used, as in
    :func:`_sigma`, so that a few gross errors do not inflate it.
    """
    nr, nc = rows - r + 1, cols - r + 1
    n, p = max(nr, nc), min(nr, nc)
    if p < 1:
        return None
    mu = (np.sqrt(max(n - 1, 1)) + np.sqrt(p)) ** 2
    left = nr * nc - mu
    if left < 2.0:
        return None
    R = X - (U[:, :r] * s[:r]) @ Vt[:r]
    return float(mad_std(R, centre=False) * np.sqrt(R.size / left))


#: false-alarm rate of each step of the nested rank test (the probability that a matrix of
#: rank r plus i.i.d. Gaussian noise is called rank r + 1)
RANK_ALPHA = 1e-3
#: upper quantiles of the Tracy-Widom law for real matrices (beta = 1), by tail probability
#: (Tracy and Widom 1996; the tables of Bejan 2005); checked against a Monte-Carlo of the
#: Gaussian orthogonal ensemble in the tests
_TW1 = {0.05: 0.9793, 0.01: 2.0234, 0.005: 2.4224, 0.001: 3.2724}


def tw1_quantile(alpha: float) -> float:
    """Upper ``alpha`` quantile of the Tracy-Widom (beta = 1) law, log-interpolated in alpha.

    Tabulated for 0.001 <= alpha <= 0.05 (:data:`_TW1`); outside that range a ``ValueError``.
    """
    a = float(alpha)
    keys = sorted(_TW1)
    if not keys[0] <= a <= keys[-1]:
        raise ValueError(f"alpha must be in [{keys[0]}, {keys[-1]}], got {alpha!r}")
    return float(np.interp(np.log(a), np.log(keys), [_TW1[q] for q in keys]))


def noise_edge(rows: int, cols: int, alpha: float = RANK_ALPHA) -> float:
    """(1 - alpha) quantile of the largest singular value of a rows x cols matrix of i.i.d. N(0, 1).

    Johnstone's (2001) Tracy-Widom approximation of the largest eigenvalue ``l`` of the
    Wishart matrix ``X^T X`` (n = max(rows, cols), p = min(rows, cols)):
    ``(l - mu) / s ~ TW1`` with ``mu = (sqrt(n - 1) + sqrt(p))^2`` and
    ``s = (sqrt(n - 1) + sqrt(p)) (1/sqrt(n - 1) + 1/sqrt(p))^(1/3)``; returns
    ``sqrt(mu + s q_alpha)``. Its centre is the Marchenko-Pastur edge ``sqrt(n) + sqrt(p)``.

    Examples
    --------
    >>> round(noise_edge(47, 180, 0.001), 2)   # vs the MP edge sqrt(180) + sqrt(47) = 20.28
    21.2
    """
    n, p = max(int(rows), int(cols)), min(int(rows), int(cols))
    if p < 1:
        return 0.0
    a, b = np.sqrt(max(n - 1, 1)), np.sqrt(p)
    mu = (a + b) ** 2
    sd = (a + b) * (1.0 / a + 1.0 / b) ** (1.0 / 3.0)
    return float(np.sqrt(max(mu + sd * tw1_quantile(alpha), 0.0)))


#: matrices with at most this many entries get the exact (Monte-Carlo) null quantile of the
#: estimated-noise statistic in :func:`null_edge`; larger ones the Tracy-Widom edge
NULL_MC_MAX_ENTRIES = 1500


@functools.lru_cache(maxsize=256)
def null_edge(rows: int, cols: int, alpha: float = RANK_ALPHA) -> float:
    """(1 - alpha) quantile of ``s_max / sigma_hat`` for a rows x cols Gaussian noise matrix.

    ``sigma_hat`` is the estimate :func:`_sigma_null` makes from the same matrix (the median
    absolute residual of its rank-1 approximation, scaled by ``sqrt(entries / (entries - mu))``),
    so the quantile accounts for the noise being estimated from the data it is tested on, which
    the Tracy-Widom edge of :func:`noise_edge` (known noise) does not; that matters for the
    small matrices of real arrays (8 x 12: 2 % false alarms with the known-noise edge). Exact by
    a Monte-Carlo of ``max(20 / alpha, 2000)`` draws with a fixed seed (deterministic, cached)
    for matrices of at most :data:`NULL_MC_MAX_ENTRIES` entries; :func:`noise_edge` above, where
    the estimate's own scatter is negligible.
    """
    nr, nc = int(rows), int(cols)
    if nr * nc > NULL_MC_MAX_ENTRIES or min(nr, nc) < 1:
        return noise_edge(nr, nc, alpha)
    n, p = max(nr, nc), min(nr, nc)
    left = nr * nc - (np.sqrt(max(n - 1, 1)) + np.sqrt(p)) ** 2
    if left < 2.0:
        return noise_edge(nr, nc, alpha)
    draws = int(max(20.0 / alpha, 2000))
    rng = np.random.default_rng(20011)
    stats = []
    chunk = max(1, min(draws, 2_000_000 // (nr * nc)))
    done = 0
    while done < draws:
        b = min(chunk, draws - done)
        G = rng.standard_normal((b, nr, nc))
        Ub, sb, Vb = np.linalg.svd(G, full_matrices=False)
        R = G - sb[:, 0, None, None] * Ub[:, :, :1] * Vb[:, :1, :]
        mad = mad_std(R.reshape(b, -1), axis=1, centre=False)
        stats.append(sb[:, 0] / np.maximum(mad * np.sqrt(nr * nc / left), 1e-300))
        done += b
    return float(np.quantile(np.concatenate(stats), 1.0 - alpha))



def rank_threshold(
    X: Array,
    r: int,
    *,
    rows: int,
    cols: int,
    noise_std: float | None = None,
    alpha: float = RANK_ALPHA,
    rel_floor: float = 1e-9,
    svd: tuple[Array, Array, Array] | None = None,
) -> float:
    """Threshold on ``s_r`` of the nested test "rank >= r" against "rank <= r - 1" (metres).

    The test of the module docstring, shared by :func:`analyse_degeneracy` and the orientation
    check (:func:`~selfcal.tdoa.orientation.check_orientation`): ``s_r`` of X is signal at
    false-alarm rate ``alpha`` when it exceeds the returned value. Under the smaller model
    ``s_r`` is the largest singular value of the ``(rows - r + 1) x (cols - r + 1)`` noise
    matrix that remains; with a given ``noise_std`` the threshold is
    ``noise_std x noise_edge(rows - r + 1, cols - r + 1, alpha)``, without it the noise is
    estimated under the smaller model (:func:`_sigma_null`) and the quantile is
    :func:`null_edge` of that estimated-noise statistic. Never below ``rel_floor x s_1``
    (numerical rank) nor ``1e-14 s_1`` per unit of noise (rounding); where too few degrees
    of freedom remain to estimate the noise, the numerical rank alone decides.

    Parameters
    ----------
    X : (M, K) matrix whose r-th singular value is tested (e.g. a column-centred far-field
        matrix, metres).
    r : the rank tested (1-based index of the singular value).
    rows, cols : degrees of freedom of X's two sides (``M - 1`` for a side whose mean was
        removed).
    noise_std : per-entry noise standard deviation (metres) when known.
    alpha : false-alarm rate (default :data:`RANK_ALPHA`).
    rel_floor : numerical-rank floor relative to ``s_1``.
    svd : the leading singular triplets ``(U, s, Vt)`` of X (at least r of them) if
        already computed (:func:`top_svd`).

    Returns
    -------
    float, the threshold on ``s_r``.

    Examples
    --------
    >>> import numpy as np
    >>> G = np.random.default_rng(0).standard_normal((30, 40))
    >>> s = np.linalg.svd(G, compute_uv=False)
    >>> bool(s[0] > rank_threshold(G, 1, rows=30, cols=40, noise_std=1.0))   # pure noise: no signal
    False
    """
    U, s, Vt = svd if svd is not None else top_svd(X, r)
    s1 = float(s[0]) if len(s) else 0.0
    floor = 1e-14 * s1
    if noise_std is not None:
        return max(max(float(noise_std), floor) * noise_edge(rows - r + 1, cols - r + 1, alpha), rel_floor * s1)
    est = _sigma_null(X, U, s, Vt, r, rows, cols)
    if est is None:
        return rel_floor * s1
    return max(max(est, floor) * null_edge(rows - r + 1, cols - r + 1, alpha), rel_floor * s1)


def analyse_degeneracy(
    X: Array,
    *,
    noise_std: float | None = None,
    alpha: float = RANK_ALPHA,
    rel_floor: float = 1e-9,
    cone_tol: float = 3.0,
    chi2_tol: float = 25.0,
) -> DegeneracyReport:
    """Classify a complete, column-centred matrix ``X = D - mean_i D_ij`` (m x k) by failure mode.

    Parameters
    ----------
    X : (m, k) complete column-centred relative distances (metres).
    noise_std : noise standard deviation of the entries of D (metres) if known.
    alpha : false-alarm rate of each step of the nested rank test (:data:`RANK_ALPHA`).
    rel_floor, cone_tol, chi2_tol : thresholds (see the module docstring).

    Returns
    -------
    DegeneracyReport
    """
    a, k = X.shape[0] - 1, X.shape[1]
    U, s, Vt = top_svd(X, 8)
    s1 = float(s[0]) if s.size else 0.0
    floor = 1e-14 * s1

    def sig(r: int) -> float:
        est = noise_std if noise_std is not None else _sigma(X, U, s, Vt, r, a, k)
        return max(float(est), floor)

    def thr(r: int) -> float:
        # nested test of "rank >= r" against "rank <= r - 1": under the smaller model the r-th
        # singular value is the largest of an (a - r + 1) x (k - r + 1) noise matrix
        # sigma under the smaller model, estimated from the rank-r residual with the expected
        # energy of the largest noise component added back (_sigma_null), so a real s_r does not
        # set the level it is compared with. With too few remaining degrees of freedom (e.g.
        # r = 3 in a 4 x 6 matrix) noise and s_r cannot be told apart: the numerical rank
        # (rel_floor) decides, as for exact data
        return rank_threshold(X, r, rows=a, cols=k, noise_std=noise_std, alpha=alpha, rel_floor=rel_floor,
                              svd=(U, s, Vt))

    rank = 0
    for r in (3, 2, 1):
        if len(s) >= r and s[r - 1] > thr(r):
            rank = r
            break
    sigma = sig(max(rank, 1))
    cone_snr = float("nan")
    quad = float("nan")
    kind: str | None = None
    if rank == 3:
        nt = (s[:3, None] * Vt[:3]).T
        if k >= 6:
            mu, omega = _weakest_quadric(nt)
            nu = 2.0 * sigma * float(np.linalg.norm(nt @ omega))
            cone_snr = float(mu / max(nu, 1e-300))
            if cone_snr < cone_tol:
                kind = "cone"
    elif rank == 2:
        nt = (s[:2, None] * Vt[:2]).T
        B2, _, res = fit_quadric(nt)
        pd = bool(np.all(np.linalg.eigvalsh(B2) > 0))
        if k > 3:
            seq = 2.0 * sigma * np.linalg.norm(nt @ B2, axis=1) + 1e-300
            quad = float(np.sum((res / seq) ** 2) / (k - 3))
            kind = "coplanar-directions" if (pd and quad < chi2_tol) else "planar-motion"
        else:
            kind = "coplanar-directions" if pd else "planar-motion"
    elif rank == 1:
        # parallel: every |ntilde_j| equals the same |z-extent|, up to noise sigma each
        mag = np.abs(s[0] * Vt[0])
        spread = float(np.sqrt(np.mean((mag - mag.mean()) ** 2)))
        kind = "parallel-directions" if spread <= 2.0 * sigma + 1e-9 * np.max(mag) else "collinear-motion"
    else:
        kind = "collinear-motion"
    return DegeneracyReport(kind, rank, s, sigma, thr(3), cone_snr, quad)


def _weakest_quadric(nt: Array) -> tuple[float, Array]:
    """Smallest singular value of the quadric design (Frobenius-orthonormal) and its Omega."""
    M = quadric_design(nt) * np.array([1, 1, 1, _SQ2 / 2, _SQ2 / 2, _SQ2 / 2])
    _, mu, Vt = np.linalg.svd(M, full_matrices=False)
    w = Vt[-1] * np.array([1, 1, 1, _SQ2 / 2, _SQ2 / 2, _SQ2 / 2])
    return float(mu[-1]), sym_from_vec(w)


# ----------------------------------------------------------------------------- partial reconstructions
def min_volume_ellipse(points: Array, *, tol: float = 1e-7, max_iter: int = 2000) -> Array:
    """Smallest origin-centred ellipse ``{x : x^T P x <= 1}`` containing (k, d) points.

    Khachiyan / Kumar-Yildirim first-order algorithm on the symmetric point set.
    Returns the (d, d) matrix P.
    """
    X = np.asarray(points, dtype=float)
    k, d = X.shape
    u = np.full(k, 1.0 / k)
    for _ in range(max_iter):
        S = (X * u[:, None]).T @ X
        kappa = np.einsum("ja,ab,jb->j", X, np.linalg.pinv(S), X)
        j = int(np.argmax(kappa))
        if kappa[j] <= d * (1.0 + tol):
            break
        step = (kappa[j] - d) / (d * (kappa[j] - 1.0))
        u *= 1.0 - step
        u[j] += step
    S = (X * u[:, None]).T @ X
    P = np.linalg.pinv(S) / d
    kappa = np.einsum("ja,ab,jb->j", X, P, X)
    return P / max(float(kappa.max()), 1e-300)  # exact containment after the tolerance


def _sqrt_psd(P: Array) -> tuple[Array, Array]:
    w, Q = np.linalg.eigh(P)
    w = np.maximum(w, 1e-12 * max(float(w.max()), 1e-300))
    return (np.sqrt(w)[:, None] * Q.T), (Q / np.sqrt(w)[None, :])


def partial_planar_motion(X: Array) -> tuple[Array, Array]:
    """Planar positions: one member of the family of section 2.2 (rank 2, coplanar z_i).

    ``Z = U_2 A^-1``, ``(n_x, n_y) = A S_2 V_2^T`` with ``|A ntilde_j| <= 1``; we pick the A
    whose ellipse ``|A x| <= 1`` is the smallest containing all ``ntilde_j`` (directions as
    close to the plane of motion as the data allow, hence the smallest motion) and complete
    ``n_z = +sqrt(1 - n_x^2 - n_y^2)`` (the sign of each n_z is not determined).

    Returns positions (one per row of ``X``, third coordinate 0) and directions (k, 3).
    """
    U, s, Vt = np.linalg.svd(X, full_matrices=False)
    nt = (s[:2, None] * Vt[:2]).T
    A, A_inv = _sqrt_psd(min_volume_ellipse(nt))
    n2 = nt @ A.T
    nz = np.sqrt(np.clip(1.0 - np.sum(n2**2, axis=1), 0.0, None))
    Z2 = U[:, :2] @ A_inv
    return np.column_stack([Z2, np.zeros(len(Z2))]), np.column_stack([n2, nz])


def partial_coplanar_directions(X: Array) -> tuple[Array, Array]:
    """Coplanar directions (section 2.2): 2-D quadric ``ntilde^T B2 ntilde = 1`` fixes A.

    Gives the in-plane coordinates of positions and directions up to a Euclidean motion;
    the out-of-plane coordinate of the positions is unobservable and set to 0.
    """
    U, s, Vt = np.linalg.svd(X, full_matrices=False)
    nt = (s[:2, None] * Vt[:2]).T
    B2, _, _ = fit_quadric(nt)
    A, A_inv = _sqrt_psd(B2)
    n2 = nt @ A.T
    n2 /= np.linalg.norm(n2, axis=1, keepdims=True)
    Z2 = U[:, :2] @ A_inv
    return np.column_stack([Z2, np.zeros(len(Z2))]), np.column_stack([n2, np.zeros(len(n2))])


def partial_collinear_motion(X: Array) -> tuple[Array, Array]:
    """Collinear positions (section 2.2): ``Z = U_1 / a``, ``n_x = a S_1 V_1``, ``a <= 1/l``.

    We take the boundary member ``a = 1/l``, ``l = max_j |S_1 V_1j|`` (smallest motion), and
    complete each direction in the x-y plane.
    """
    U, s, Vt = np.linalg.svd(X, full_matrices=False)
    v = s[0] * Vt[0]
    a = 1.0 / max(float(np.max(np.abs(v))), 1e-300)
    nx = np.clip(a * v, -1.0, 1.0)
    pos = np.zeros((X.shape[0], 3))
    pos[:, 0] = U[:, 0] / a
    return pos, np.column_stack([nx, np.sqrt(1.0 - nx**2), np.zeros_like(nx)])


def partial_parallel_directions(X: Array) -> tuple[Array, Array]:
    """Parallel directions (section 2.2): only the coordinate along the common direction."""
    U, s, Vt = np.linalg.svd(X, full_matrices=False)
    sign = np.where(Vt[0] >= 0, 1.0, -1.0)
    pos = np.zeros((X.shape[0], 3))
    pos[:, 0] = X @ sign / len(sign)
    dirs = np.zeros((len(sign), 3))
    dirs[:, 0] = sign
    return pos, dirs


#: what each failure mode means, in words (the refusal messages)
MESSAGES = {
    "planar-motion": "the receiver positions lie in a plane (rank 2) and the directions leave it: far-field "
    "TDOA then fixes the in-plane geometry only up to a 2 x 2 linear map (each direction's in-plane length is "
    "unknown), with dim=2 too; add a position off the plane, or use sources in the array's plane (dim=2).",
    "coplanar-directions": "the transmitter directions lie in a plane (rank 2): the out-of-plane "
    "coordinate of the positions is unobservable; add a transmitter off that plane.",
    "collinear-motion": "the receiver positions lie on a line (rank <= 1): only a one-parameter "
    "family of reconstructions exists.",
    "parallel-directions": "all transmitter directions are parallel (rank <= 1): only the "
    "coordinate along that direction is observable.",
    "cone": "the transmitter directions lie on a common quadratic cone (e.g. all at one elevation): the "
    "constraints n^T B n = 1 do not determine B, so the geometry is ambiguous; add transmitters "
    "off the cone.",
}


#: what the data determine in each case (``FarfieldResult.determined``)
DETERMINED = {
    "spatial": "positions and directions up to a rotation / reflection (first position at the origin)",
    "planar": "in-plane positions and directions up to a rotation / reflection of the plane; positions off "
    "the plane of the directions are seen projected onto it (their out-of-plane coordinate is unobservable)",
    "linear": "positions along the line up to one scale factor >= 1 (reported for the smallest array "
    "consistent with the data: the largest |projection| of a direction onto the line is 1, exact when a "
    "source is at endfire); directions' angles to the line only through that projection",
    "parallel": "the coordinate of each position along the common direction (scale included); nothing across it",
    "planar-motion": "not determined: with the directions off the positions' plane the in-plane geometry is "
    "known only up to a 2 x 2 linear map (each direction's in-plane length is unknown); one member shown",
    "coplanar-directions": "the in-plane geometry (use dim=2); the out-of-plane coordinate is not observable",
    "collinear-motion": "positions along the line up to scale (use dim=1)",
    "parallel-directions": "the coordinate along the common direction (use dim=1)",
    "cone": "not determined: a one-parameter family of geometries fits the data equally well",
}
