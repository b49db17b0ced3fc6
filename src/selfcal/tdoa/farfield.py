"""Far-field TDOA self-calibration (paper 000): the solver entry point.

``D_ij = z_i . n_j + C_j`` (rows = receiver positions, columns = far transmitters,
``|n_j| = 1``, C_j unknown per column). :func:`solve_farfield` recovers the positions (first
at the origin), the unit directions and the offsets:

1. gross-error screen (optional) and, when entries are missing or a robust loss is asked
   for, a weighted / robust fit of the structure ``D = P Q^T + 1 c^T`` (rank 3 plus
   offsets, :func:`lowrank_fit`) that fills (and, robustly, cleans) the matrix for the
   factorisation steps;
2. failure-mode analysis of ``Dbar`` (:mod:`selfcal.tdoa.degeneracy`);
3. overdetermined initialisation (section 2.3 (i)-(iii), :func:`initialize_farfield`),
   with the nonlinear fit of A when the least-squares B is not positive definite;
4. refinement: Levenberg-Marquardt on the spheres (Algorithm 3) or alternating
   optimisation (Algorithm 2), with an optional robust loss.

Robustness (beyond the paper, its future work): with ``loss != "linear"`` the structured fit
and the refinement are iteratively re-weighted; entries whose final residual exceeds
``reject_k`` robust standard deviations are reported in ``rejected``. :func:`ransac_farfield`
additionally offers RANSAC over the minimal solver.

Length (1038 lines, above the ~600 guideline): the entry point with screening, rank
selection, the planar / linear cases and the partial reconstructions; the cases could move
to modules of their own.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import least_squares

from .._checks import as_matrix, as_rng, check_choice, check_positive, entry
from .._result import Result
from ..errors import ConvergenceWarning, DegenerateGeometryError, InputError
from ..geometry import canonical_gauge
from ..robust import TUNING, mad_std
from .degeneracy import (
    DegeneracyReport,
    analyse_degeneracy,
    fit_quadric,
    partial_collinear_motion,
    partial_coplanar_directions,
    partial_parallel_directions,
    partial_planar_motion,
    top_svd,
)
from .minimal import solve_minimal
from .refine import LOSSES, farfield_residuals, loss_weight, refine_alternating, refine_lm

__all__ = [
    "FarfieldResult",
    "FarfieldInit",
    "solve_farfield",
    "initialize_farfield",
    "fit_A_nonlinear",
    "reduce_matrix",
    "screen_gross_errors",
    "check_orientation",
    "lowrank_fit",
    "ransac_farfield",
    "METHODS",
]

Array = NDArray[np.float64]
METHODS = ("auto", "lm", "alternating", "init", "minimal")
#: Flag a refined solution whose directions are nearly coplanar (smallest / largest singular
#: value of the (k, 3) direction matrix below this). At high noise (sigma about a third of the array size) the
#: ML cost itself has such minima: the out-of-plane scale of the positions is then barely
#: determined and the array comes out stretched (see the audit note in :mod:`.refine`).
COLLAPSE_RATIO = 0.2


# ----------------------------------------------------------------------------- result
@dataclass(frozen=True, repr=False)
class FarfieldResult(Result):
    """Result of :func:`solve_farfield`.

    Attributes
    ----------
    positions : (m, 3) receiver positions, first row 0 (metres; D's unit). Canonical gauge:
        first position at the origin, principal axes of the positions along x, y, z (a
        proper rotation); the reconstruction is defined up to a rotation and reflection.
    directions : (k, 3) unit directions n_j (from the transmitter towards the receivers).
    offsets : (k,) C_j such that ``D_ij ~ z_i . n_j + C_j``.
    degeneracy : None or the failure mode (see :mod:`selfcal.tdoa.degeneracy`).
    residual_rms : rms of ``D_ij - z_i . n_j - C_j`` over used entries (metres).
    converged, iterations, method, loss : refinement status.
    rejected : (m, k) bool, entries treated as outliers (gross screen or robust fit).
    b_positive_definite : whether the least-squares B of the initialisation was positive
        definite (the paper's success criterion; False -> A came from the nonlinear fit).
    diagnostics : the degeneracy report (singular values, noise level, cone ratio...).
    cost_history : refinement cost after every iteration (first = initial cost).
    position_cov : (m, 3, 3) Gauss-Newton covariance of each position (m^2) after LM, in
        the gauge "best rotation about the first position" (None for other methods).
    warnings : human-readable cautions about this estimate (e.g. ``directions-collapsed``:
        the refinement drove the directions towards a common plane, see
        :data:`COLLAPSE_RATIO`); empty when there are none.
    dim : dimension of ``positions`` / ``directions`` (3 in space, 2 planar, 1 linear).
    case : ``"spatial"`` (3-D, Theorem 1), ``"planar"`` (positions and directions in one
        plane: the in-plane geometry; positions off that plane are projected onto it, the
        out-of-plane coordinate is not observable) or ``"linear"`` (positions on a line, or
        directions all parallel: one coordinate per position), or the degeneracy's name
        for a partial reconstruction.
    determined : what the data determine in this case (paper 000, section 2.2), in words.
    """

    positions: Array
    directions: Array
    offsets: Array
    degeneracy: str | None
    residual_rms: float
    converged: bool
    iterations: int
    method: str
    loss: str
    rejected: NDArray[np.bool_]
    b_positive_definite: bool
    diagnostics: DegeneracyReport | None = None
    cost_history: list[float] = field(default_factory=list)
    position_cov: Array | None = None
    warnings: tuple[str, ...] = ()
    dim: int = 3
    case: str = "spatial"
    determined: str = ""

    def to_dict(self) -> dict[str, Any]:
        """JSON-safe dictionary with the DESIGN.md keys (``rejected`` as [i, j] pairs)."""
        return {
            "positions": self.positions.tolist(),
            "directions": self.directions.tolist(),
            "offsets": self.offsets.tolist(),
            "residual_rms": float(self.residual_rms),
            "degeneracy": self.degeneracy,
            "converged": bool(self.converged),
            "iterations": int(self.iterations),
            "method": self.method,
            "loss": self.loss,
            "rejected": np.argwhere(self.rejected).tolist(),
            "b_positive_definite": bool(self.b_positive_definite),
            "diagnostics": None if self.diagnostics is None else self.diagnostics.to_dict(),
            "position_cov": None if self.position_cov is None else self.position_cov.tolist(),
            "warnings": list(self.warnings),
            "dim": int(self.dim),
            "case": self.case,
            "determined": self.determined,
        }


@dataclass(frozen=True)
class FarfieldInit:
    """Output of :func:`initialize_farfield`: positions (m, 3) (row 0 = 0), directions (k, 3),
    B (3, 3) least-squares quadric, A (3, 3) with ``N = A Ntilde``, and whether B was
    positive definite."""

    positions: Array
    directions: Array
    B: Array
    A: Array
    b_positive_definite: bool


# ----------------------------------------------------------------------------- building blocks
def reduce_matrix(D: Array) -> Array:
    """``Dbar_ij = D_ij - D_1j`` without the first row (paper 000, Lemma 1): (m-1, k)."""
    D = np.asarray(D, dtype=float)
    return D[1:] - D[:1]


def screen_gross_errors(D: Array, *, factor: float = 20.0) -> NDArray[np.bool_]:
    """Flag gross errors: (m, k) bool mask.

    Column medians remove the offsets C_j. In row i of the centred matrix an entry is gross
    when it lies more than ``factor`` robust spreads from the row median, the spread being
    ``max(1.4826 MAD_i, q90_i / 3, 0.05 q90)`` (q90_i: 90th percentile of the row's absolute
    deviations, q90 the same over the whole matrix). The quantile terms keep rows with
    two-valued or nearly constant data (parallel directions, a position near the median)
    from being flagged; the global term means a gross error must exceed the spread of the
    whole data set. Such entries cannot come from a far-field model with Gaussian noise;
    they are treated as missing.
    """
    X = D - np.nanmedian(D, axis=0, keepdims=True)
    med = np.nanmedian(X, axis=1, keepdims=True)
    dev = np.abs(X - med)
    mad = mad_std(X, axis=1, keepdims=True)
    q_row = np.nanpercentile(dev, 90, axis=1, keepdims=True) / 3.0
    q_all = 0.05 * float(np.nanpercentile(dev, 90))
    scale = np.maximum(np.maximum(mad, q_row), max(q_all, 1e-300))
    with np.errstate(invalid="ignore"):
        return np.asarray(np.isfinite(D) & (dev > factor * scale))


def lowrank_fit(
    D: Array,
    W: Array,
    *,
    rank: int = 3,
    loss: str = "linear",
    iterations: int = 50,
    start: Array | None = None,
) -> tuple[Array, float]:
    """Weighted (robust) fit of the far-field structure ``L = P Q^T + 1 c^T`` to D.

    ``P`` (m, rank), ``Q`` (k, rank), ``c`` (k,): the rank-3 factorisation plus one offset
    per column of the model ``D_ij = z_i . n_j + C_j`` without the unit-norm constraints,
    fitted by alternating least squares. Keeping the offsets structured (instead of a
    generic rank-4 fit) leaves no spare component in which a gross entry could hide.

    Parameters
    ----------
    D : (m, k), W : (m, k) weights (0 = missing / rejected).
    rank : rank of ``P Q^T`` (3 for far-field data).
    loss : IRLS loss on the residuals, scaled by 1.345 x their robust standard deviation
        (1.4826 MAD x sqrt(entries / residual dof)); robust losses also start from a
        winsorised D (each row of the column-centred matrix clipped to 3 robust spreads).
    start : optional complete (m, k) matrix whose structure starts the iteration
        (default: D with missing entries filled by column means).

    Returns
    -------
    L : (m, k) complete fitted matrix; sigma : robust noise estimate (1.4826 MAD of the
    residuals over used entries, inflated by the residual degrees of freedom).
    """
    m, k = D.shape
    obs = W > 0
    D0 = np.where(obs, D, 0.0)
    n_obs = int(obs.sum())
    dof_fac = np.sqrt(n_obs / max(n_obs - rank * (m + k - rank) - k, 1))
    # start: fill missing entries with the column means; with a robust loss, winsorise
    # first so that a gross entry cannot dominate the starting factorisation
    colmean = np.sum(D0 * obs, 0) / np.maximum(obs.sum(0), 1)
    if start is not None:
        F = np.asarray(start, dtype=float)
    elif loss == "linear":
        F = np.where(obs, D0, colmean[None, :])
    else:
        Dn = np.where(obs, D0, np.nan)
        cmed = np.nanmedian(Dn, axis=0, keepdims=True)
        Xc = Dn - cmed
        rmed = np.nanmedian(Xc, axis=1, keepdims=True)
        dev = np.abs(Xc - rmed)
        sc = np.maximum(mad_std(Xc, axis=1, keepdims=True),
                        np.nanpercentile(dev, 90, axis=1, keepdims=True) / 3.0)
        Xc = np.clip(Xc, rmed - 3.0 * sc, rmed + 3.0 * sc)
        F = np.where(obs, Xc + cmed, cmed)
    c = F.mean(axis=0)
    U, s, Vt = np.linalg.svd(F - c, full_matrices=False)
    P = U[:, :rank] * s[:rank]
    Q = Vt[:rank].T
    Wr = W.astype(float)
    eye_q = 1e-10 * np.eye(rank + 1)
    eye_p = 1e-10 * np.eye(rank)
    ones = np.ones((m, 1))
    for it in range(iterations):
        R = np.where(obs, D0 - P @ Q.T - c, 0.0)
        # robust scale corrected for the fit's degrees of freedom: without the correction
        # the scale shrinks from one iteration to the next and the weights collapse
        sigma = mad_std(R[obs], centre=False) * dof_fac
        if loss != "linear" and sigma > 0:
            Wr = W * loss_weight((R / (1.345 * sigma)) ** 2, loss)
        Pa = np.hstack([P, ones])
        Hq = np.einsum("ij,ia,ib->jab", Wr, Pa, Pa) + eye_q * (1.0 + np.trace(Pa.T @ Pa))
        Qa = np.linalg.solve(Hq, np.einsum("ij,ij,ia->ja", Wr, D0, Pa)[..., None])[..., 0]
        Q, c = Qa[:, :rank], Qa[:, rank]
        Hp = np.einsum("ij,ja,jb->iab", Wr, Q, Q) + eye_p * (1.0 + np.trace(Q.T @ Q))
        P = np.linalg.solve(Hp, np.einsum("ij,ij,ja->ia", Wr, D0 - c, Q)[..., None])[..., 0]
        if loss == "linear" and np.all(obs) and it >= 1:
            break
    L = P @ Q.T + c
    R = np.where(obs, D0 - L, 0.0)
    return L, mad_std(R[obs], centre=False) * dof_fac


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
    """Rotate so that the positions' principal axes are the coordinate axes (row 0 stays 0)."""
    d = pos.shape[1]
    if d == 1 or np.linalg.matrix_rank(pos, tol=1e-12 * (np.abs(pos).max() + 1e-300)) < d:
        return pos, dirs, np.eye(d)
    _, _, al = canonical_gauge(pos)
    R = al.rotation
    return pos @ R.T, dirs @ R.T, R


def ransac_farfield(
    D: Array,
    *,
    iterations: int = 200,
    threshold: float | None = None,
    rng: np.random.Generator | int | None = None,
) -> NDArray[np.bool_]:
    """RANSAC over the minimal solver (paper 000's future work): (m, k) inlier mask.

    Each hypothesis solves a random 4 x 6 sub-problem (Algorithm 1, batched over all
    hypotheses at once), extends it to every column by solving ``Dbar_j = Z n_j`` on the 3
    sampled position differences and to every row by least squares over the sampled
    columns, and scores it by the median absolute residual (LMedS). The best hypothesis's
    prediction starts a robust (Huber IRLS) structured fit (:func:`lowrank_fit`) of all entries (local optimisation);
    inliers are the entries within ``threshold`` of that fit (default 4 robust standard
    deviations). Missing entries are never inliers.
    """
    gen = as_rng(rng)
    D = np.asarray(D, dtype=float)
    m, k = D.shape
    finite = np.isfinite(D)
    rows = np.array([gen.choice(m, 4, replace=False) for _ in range(iterations)])
    cols = np.array([gen.choice(k, 6, replace=False) for _ in range(iterations)])
    sub = D[rows[:, :, None], cols[:, None, :]]
    ok = np.all(np.isfinite(sub), axis=(1, 2))
    sol = solve_minimal(np.where(np.isfinite(sub), sub, 0.0))
    good = np.flatnonzero(ok & sol.valid)
    if good.size == 0:
        return finite
    best_med, best_R, best_P = np.inf, None, None
    Df = np.where(finite, D, np.nan)
    for h in good:
        r, c = rows[h], cols[h]
        Zs = sol.positions[h]  # (4, 3), relative to row r[0]
        Ns = sol.directions[h]  # (6, 3)
        # every row: z_i - z_r0 from the sampled columns
        Y = Df[:, c] - Df[r[0], c][None, :]  # (m, 6)
        Zall = np.linalg.lstsq(Ns, np.nan_to_num(Y.T), rcond=None)[0].T
        # every column: n_j from the three sampled position differences, normalised
        Yc = Df[r[1:], :] - Df[r[0], :][None, :]  # (3, k)
        Nall = np.linalg.solve(Zs[1:], np.nan_to_num(Yc)).T
        Nall /= np.maximum(np.linalg.norm(Nall, axis=1, keepdims=True), 1e-300)
        Cj = Df[r[0], :]
        R = Df - Zall @ Nall.T - Cj[None, :]
        med = float(np.nanmedian(np.abs(R)))
        if med < best_med:
            best_med, best_R, best_P = med, R, Zall @ Nall.T + Cj[None, :]
    assert best_R is not None and best_P is not None
    # local optimisation: one minimal sample extrapolates poorly to the other rows and
    # columns, so refine the consensus model by a robust (Huber) structured fit of all entries
    # started from it, and threshold against that fit
    pred = np.where(np.isfinite(best_P), best_P, 0.0)
    L, sig = lowrank_fit(np.where(finite, D, 0.0), finite.astype(float), rank=3, loss="huber", start=pred)
    lim = 4.0 * sig if threshold is None else float(threshold)
    with np.errstate(invalid="ignore"):
        inl = np.asarray(finite & (np.abs(D - L) <= lim))
    return inl


# ----------------------------------------------------------------------------- entry point
#: robust-loss scale in units of the noise standard deviation (95 % Gaussian efficiency)
_TUNING = TUNING


def _robust_sigma(D: Array, Z: Array, N: Array, C: Array, used: NDArray[np.bool_], *, dim: int = 3) -> float:
    """1.4826 MAD of the model residuals, corrected for the model's degrees of freedom."""
    r = farfield_residuals(np.where(used, D, np.nan), Z, N, C)
    n_obs = int(used.sum())
    m, k = D.shape
    g = dim * (dim - 1) // 2
    dof = max(n_obs - (dim * (m - 1) + dim * k - g), 1)
    return mad_std(r[used], centre=False) * float(np.sqrt(n_obs / dof))

def _noise_from_double_centred(D: Array, rank: int) -> float:
    """Robust per-entry noise level of a complete matrix from its double-centred rank-r residual.

    Both orientations of far-field data (``Z N^T + 1 c^T`` and its transpose) are of rank
    ``r`` once row and column means are removed, so this estimate does not depend on the
    orientation: 1.4826 median |R| x sqrt(entries / dof), dof = (m-1-r)(k-1-r).
    """
    X = D - D.mean(axis=0, keepdims=True)
    X = X - X.mean(axis=1, keepdims=True)
    U, s, Vt = top_svd(X, rank)
    R = X - (U[:, :rank] * s[:rank]) @ Vt[:rank]
    dof = (D.shape[0] - 1 - rank) * (D.shape[1] - 1 - rank)
    return float(mad_std(R, centre=False) * np.sqrt(R.size / max(dof, 1)))


def check_orientation(D: Array, *, noise_std: float | None = None, rank: int = 3,
                      rank_factor: float = 1.5) -> None:
    """Refuse a far-field matrix that looks transposed (rows = transmitters): ``InputError``.

    Far-field data ``D = Z N^T + 1 c^T`` carry one offset per *column*: removing the column
    means leaves a matrix of rank <= ``rank`` (3 in space), while its transpose
    ``N Z^T + c 1^T`` keeps the rank-1 offset term after column centring (rank ``rank + 1``)
    and loses it only after row centring. The (rank+1)-th singular value of each centred
    matrix is compared with the Marchenko-Pastur edge ``sigma (sqrt(rows - 1) + sqrt(cols))``
    of an i.i.d. noise matrix, times ``rank_factor`` (the same noise-aware threshold as
    :func:`~selfcal.tdoa.analyse_degeneracy`; sigma = ``noise_std`` or the robust estimate
    of the double-centred rank-r residual, valid in both orientations). Significant after
    column centring but not after row centring -> transposed. A column that is exactly
    constant while no row is (a reference receiver gives a constant *row*: the Pyramic
    layout) is named too: in the far-field model it would be a transmitter orthogonal to
    the whole array.

    Only complete matrices with at least ``rank + 2`` rows and columns are tested (the test
    needs a (rank+1)-th singular value); others pass silently.

    Parameters
    ----------
    D : (m, k) relative distances (metres), NaN = missing.
    noise_std : known per-entry noise standard deviation (metres) or None.
    rank : rank of the position/direction factorisation (3 in space, 2 in a plane).

    Raises
    ------
    InputError
        When the matrix looks transposed; the message says "transposed?".

    Examples
    --------
    >>> import numpy as np
    >>> rng = np.random.default_rng(0)
    >>> Z, N = rng.normal(size=(10, 3)), rng.normal(size=(30, 3))
    >>> N /= np.linalg.norm(N, axis=1, keepdims=True)
    >>> D = Z @ N.T + rng.normal(size=30)
    >>> check_orientation(D)          # fine
    >>> check_orientation(D.T)        # doctest: +IGNORE_EXCEPTION_DETAIL
    Traceback (most recent call last):
    InputError: ... transposed? ...
    """
    D = np.asarray(D, dtype=float)
    m, k = D.shape
    if not np.isfinite(D).all():
        return
    scale = float(np.max(np.abs(D - D.mean(axis=0)))) + 1e-300
    const_col = np.ptp(D, axis=0) <= 1e-12 * scale
    const_row = np.ptp(D, axis=1) <= 1e-12 * scale
    if const_col.any() and not const_row.any() and not const_col.all():
        j = int(np.flatnonzero(const_col)[0])
        raise InputError(
            f"matrix ({m} x {k}): column {j} is constant, which in the far-field model is a transmitter "
            "orthogonal to the whole array, while a reference receiver gives a constant row: is the matrix "
            f"transposed? (rows must be receivers, columns transmitters; try the {k} x {m} transpose)")
    if min(m, k) < rank + 2:
        return
    sigma = noise_std if noise_std is not None else _noise_from_double_centred(D, rank)
    sigma = max(float(sigma), 1e-14 * scale)
    sc = top_svd(D - D.mean(axis=0, keepdims=True), rank + 1)[1]
    sr = top_svd(D - D.mean(axis=1, keepdims=True), rank + 1)[1]
    thr_c = rank_factor * sigma * (np.sqrt(m - 1) + np.sqrt(k))
    thr_r = rank_factor * sigma * (np.sqrt(m) + np.sqrt(k - 1))
    if sc[rank] > thr_c and sr[rank] <= thr_r:
        raise InputError(
            f"matrix ({m} x {k}) does not have the far-field structure with one offset per column "
            f"(singular value {rank + 1} after removing column means {sc[rank]:.3g} > noise threshold "
            f"{thr_c:.3g}) but has it with one offset per row ({sr[rank]:.3g} <= {thr_r:.3g}): is it "
            f"transposed? Rows must be receivers, columns transmitters (try the {k} x {m} transpose)")


def _raise_or_return(
    kind: str, message: str, result: FarfieldResult, allow_degenerate: bool
) -> FarfieldResult:
    if allow_degenerate:
        return result
    raise DegenerateGeometryError(
        message + " Pass allow_degenerate=True (CLI: --allow-degenerate) for the partial reconstruction.",
        kind=kind,
        partial=result,
    )


_DEGENERATE_MESSAGES = {
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


_DETERMINED = {
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


def _effective_dim(dim: int | str, report: DegeneracyReport) -> int:
    """The dimension to solve in: ``dim`` itself, or at "auto" the rank test's verdict.

    A rank-2 matrix whose 2-D quadric is inconsistent (``planar-motion``: directions off the
    positions' plane) has no determined planar solution; 3 is returned so that the caller
    reports it as a degeneracy. Asking for a dimension the data contradict raises.
    """
    rank = int(report.rank)
    sv = ", ".join(f"{v:.3g}" for v in report.singular_values[:4])
    detail = f"numerical rank {rank} (singular values {sv}; noise threshold {report.rank_threshold:.3g})"
    if dim == "auto":
        if rank == 2 and report.kind == "coplanar-directions":
            return 2
        if rank == 1:
            return 1
        return 3
    if dim == 2 and rank == 3:
        raise InputError(
            f"dim=2 but the data are 3-D: {detail}; use dim=3 (or 'auto'; gross errors also raise the rank: "
            "try loss='huber')")
    if dim == 2 and rank == 2 and report.kind == "planar-motion":
        return 3  # reported as planar-motion (not determined) by the caller
    if dim == 2 and rank < 2:
        raise InputError(
            f"dim=2 but the data have {detail}: positions on a line or parallel directions; use dim=1 "
            "(or 'auto')")
    if dim == 1 and rank > 1:
        raise InputError(f"dim=1 but the data have {detail}; use dim={min(rank, 3)} (or 'auto')")
    return int(dim)


def _solve_low_dim(D: Array, X: Array, used: NDArray[np.bool_], d: int, report: DegeneracyReport, *,
                   offsets: str, loss: str, f_scale: float | None, method: str, max_iter: int | None,
                   tol: float | None, cone_tol: float) -> dict[str, Any]:
    """Planar (d = 2) or linear (d = 1) far-field calibration from the complete centred X."""
    m, k = D.shape
    free = offsets == "free"
    if d == 1:
        # rank-1 model D_ij = x_i u_j + C_j: the SVD of the centred (filled) matrix is its least
        # squares fit; |u_j| <= 1 bounds the scale, fixed here at max |u_j| = 1
        U, s, Vt = top_svd(X, 1)
        u = s[0] * Vt[0]
        a = float(np.max(np.abs(u)))
        if a <= 0:
            raise InputError("matrix: every column is constant: no position is observable")
        x = U[:, 0] * a
        x = x - x[0]
        q = u / a
        parallel = report.kind == "parallel-directions"
        pos, dirs = x[:, None], q[:, None]
        C = np.asarray(np.nanmean(np.where(used, D - pos @ dirs.T, np.nan), axis=0))
        if offsets == "reference":
            C = D[0].copy()
        case = "parallel" if parallel else "linear"
        return {"positions": pos, "directions": dirs, "offsets": C, "cov": None, "converged": True,
                "iterations": 0, "method": "svd-rank1", "pd": True, "history": [], "case": case,
                "determined": _DETERMINED[case]}
    if k < 3 or m < 3:
        raise DegenerateGeometryError(f"{m} x {k}: planar far-field calibration needs at least 3 positions and "
                                      "3 directions", kind="too-few-sources" if k < 3 else "too-few-receivers")
    # the 2-D analogue of the cone (Theorem 2): the quadric system for B2 is rank deficient when
    # the directions lie on two lines through the origin
    Us, s, Vt = top_svd(X, 2)
    nt = (s[:2, None] * Vt[:2]).T
    a_, b_ = nt[:, 0], nt[:, 1]
    M = np.stack([a_ * a_, b_ * b_, np.sqrt(2.0) * a_ * b_], axis=1)
    _, mu, Wt = np.linalg.svd(M, full_matrices=False)
    om = Wt[-1]
    Om = np.array([[om[0], om[2] / np.sqrt(2.0)], [om[2] / np.sqrt(2.0), om[1]]])
    nu = 2.0 * report.noise_std * float(np.linalg.norm(nt @ Om))
    if k < 4 or mu[-1] / max(nu, 1e-300) < cone_tol:
        raise DegenerateGeometryError(
            f"planar calibration: the {k} directions lie on (at most) two lines through the origin "
            f"(quadric SNR {mu[-1] / max(nu, 1e-300):.3g} < {cone_tol:g}), so B2 in ntilde^T B2 ntilde = 1 is not "
            "determined; add directions from other angles", kind="cone")
    init = initialize_farfield(X, dim=2)
    Z, N = init.positions - init.positions[0], init.directions
    C = np.asarray(np.nanmean(np.where(used, D - Z @ N.T, np.nan), axis=0)) if free else D[0].copy()
    hist: list[float] = []
    cov = None
    its, conv, meth = 0, True, "init"
    if method in ("auto", "lm", "alternating"):
        meth = "lm"
        delta = 1.0
        if loss != "linear":
            rob = _robust_sigma(D, Z, N, C, used, dim=2)
            delta = f_scale if f_scale is not None else _TUNING[loss] * max(rob, 1e-12 * (np.nanmax(np.abs(X)) + 1e-300))
        out = refine_lm(D, Z, N, C, mask=used, free_offsets=free, loss=loss, delta=delta,
                        max_iter=max_iter or 200, tol=tol or 1e-12)
        Z, N, C, cov, hist, its, conv = (out.positions, out.directions, out.offsets, out.position_cov,
                                         out.history, out.iterations, out.converged)
    return {"positions": Z, "directions": N, "offsets": C, "cov": cov, "converged": conv, "iterations": its,
            "method": meth, "pd": init.b_positive_definite, "history": hist, "case": "planar",
            "determined": _DETERMINED["planar"]}


def _solve_known_directions(D: Array, used: NDArray[np.bool_], gross: NDArray[np.bool_], directions: Any, *,
                            loss: str) -> FarfieldResult:
    """Positions and offsets by least squares given the unit directions (see ``directions``)."""
    m, k = D.shape
    N = np.asarray(as_matrix(directions, "directions", allow_nan=False), dtype=float)
    if N.shape[0] != k or N.shape[1] not in (2, 3):
        raise InputError(f"directions: expected ({k}, 2 or 3) unit vectors (one per column of the matrix), got "
                         f"{N.shape}" + (" (transposed?)" if N.shape[::-1] == (k, 3) else ""))
    nrm = np.linalg.norm(N, axis=1)
    if np.any(np.abs(nrm - 1.0) > 1e-3):
        raise InputError(f"directions: row {int(np.argmax(np.abs(nrm - 1)))} has length "
                         f"{nrm[np.argmax(np.abs(nrm - 1))]:.4g}; directions must be unit vectors")
    d = N.shape[1]
    sv = np.linalg.svd(N, compute_uv=False)
    if sv[-1] <= 1e-9 * sv[0]:
        raise DegenerateGeometryError(f"the given directions span fewer than {d} dimensions: the positions' "
                                      "component across them is unobservable", kind="coplanar-directions")
    W = used.astype(float)
    D0 = np.where(used, D, 0.0)
    # least squares in (z_i, C_j) with z_1 = 0: alternate the exact per-column offsets and the
    # exact per-row positions (block coordinate descent on a convex quadratic: converges to the
    # unique minimum); complete data need one round from C = column means
    Z = np.zeros((m, d))
    C = np.sum(W * D0, axis=0) / np.maximum(W.sum(0), 1)
    H = np.einsum("ij,ja,jb->iab", W, N, N)
    prev = np.inf
    its = 0
    for its in range(1, 2001):  # noqa: B007
        g = np.einsum("ij,ij,ja->ia", W, D0 - C, N)
        Z = np.linalg.solve(H + 1e-12 * np.eye(d), g[..., None])[..., 0]
        C = np.sum(W * (D0 - Z @ N.T), axis=0) / np.maximum(W.sum(0), 1)
        cost = float(np.sum(W * (D0 - Z @ N.T - C) ** 2))
        if its > 1 and prev - cost <= 1e-14 * max(prev, 1e-300):
            break
        prev = cost
    C = C + Z[0] @ N.T
    Z = Z - Z[0]
    r = np.where(used, D - Z @ N.T - C, np.nan)
    rms = float(np.sqrt(np.nanmean(r**2)))
    res = FarfieldResult(Z, N.copy(), C, None, rms, True, its, "known-directions", loss, gross.copy(), True,
                         None, [], None, (), d, "known-directions",
                         "positions in the frame of the given directions (semi-blind: nothing left free but the "
                         "first position at the origin); as good as the directions are")
    return res


@entry(matrix="array", f_scale="positive?", noise_std="positive?", max_iter="count?", tol="positive?",
       rng="rng", reject_k="positive", cone_tol="positive")
def solve_farfield(
    matrix: Any,
    *,
    method: str = "auto",
    loss: str = "linear",
    f_scale: float | None = None,
    noise_std: float | None = None,
    offsets: str = "auto",
    direction_solver: str = "global",
    allow_degenerate: bool = False,
    screen: bool = True,
    reject_k: float = 4.0,
    max_iter: int | None = None,
    tol: float | None = None,
    cone_tol: float = 3.0,
    init_reference: str = "mean",
    check_degeneracy: bool = True,
    ransac: bool = False,
    rng: np.random.Generator | int | None = None,
    dim: int | str = 3,
    directions: Any = None,
) -> FarfieldResult:
    """Far-field TDOA self-calibration: positions, directions and offsets from D (paper 000).

    Parameters
    ----------
    matrix : (m, k) relative distances ``D_ij = z_i . n_j + C_j`` in metres (or any length
        unit; results come in the same unit). Rows = receiver positions (an antenna moved
        to m places, or m microphones), columns = k far transmitters. NaN = missing.
        Needs m >= 4 and k >= 6 for a full 3-D solution (Theorem 1).
    method : "lm" (Algorithm 3), "alternating" (Algorithm 2), "init" (section 2.3 only),
        "minimal" (Algorithm 1, 4 x 6 only) or "auto" ("minimal" for a complete 4 x 6
        matrix with the linear loss, else "lm").
    loss : "linear" (the paper's least squares) or a robust loss "huber", "soft_l1",
        "cauchy" (IRLS; then outliers are reported in ``rejected``).
    f_scale : robust loss scale (metres); default 1.345 (Huber, soft_l1) or 2.385 (Cauchy)
        x the robust noise estimate (1.4826 MAD of the residuals, dof-corrected).
    noise_std : known noise standard deviation of the entries (metres); used by the
        degeneracy thresholds (else estimated from the data).
    offsets : "reference" (C_j = D_1j, the paper's reduced cost), "free" (C_j estimated)
        or "auto" ("reference" for complete data with the linear loss, else "free").
    direction_solver : for "alternating": "global" or "local" (see :mod:`.refine`).
    allow_degenerate : return the partial reconstruction of a degenerate configuration
        (with ``degeneracy`` set) instead of raising.
    screen : treat gross errors (:func:`screen_gross_errors`) as missing.
    reject_k : with a robust loss, entries with ``|residual| > reject_k`` robust std are rejected.
    max_iter, tol : refinement limits (defaults 200 / 1e-12 for LM, 2000 / 1e-10 for
        alternating).
    cone_tol : threshold of the cone test (see :mod:`.degeneracy`).
    init_reference : per-column constant removed before the factorisation (Lemma 1):
        "mean" (column means; noise spread evenly, our default) or "first" (``D_1j``, the
        paper's Algorithm 1 step 1).
    check_degeneracy : run the failure-mode analysis and act on it (raise / partial result).
        With False the full 3-D pipeline runs regardless, as in the paper's experiments; the
        analysis is still reported in ``diagnostics`` but ``degeneracy`` stays None.
    ransac : screen outliers first with :func:`ransac_farfield` (RANSAC over the minimal
        solver); entries outside its inlier set are treated as missing and reported in
        ``rejected``. Combine with a robust loss for the best results.
    rng : random generator / seed (used by ``ransac``).
    dim : 3 (space, the paper), 2 (planar: positions and directions in one plane, e.g. a
        circular / rectangular board with sources around it in its plane; or any array with
        coplanar directions, whose positions are then seen projected onto that plane),
        1 (linear: positions on a line, or all directions parallel), or ``"auto"``: the
        numerical rank of the column-centred matrix against the noise (the Marchenko-Pastur
        edge test of :func:`~selfcal.tdoa.analyse_degeneracy`) and, at rank 2, the
        consistency of the 2-D quadric (chi-square per dof of ``ntilde^T B2 ntilde = 1``)
        decide. What is determined (paper 000, section 2.2) is in ``result.determined``:
        planar -- the in-plane geometry up to a rotation / reflection of the plane (needs
        k >= 3 directions not all on two lines); linear -- the positions along the line up
        to one scale factor (reported with the largest ``|projection|`` of a direction = 1:
        the smallest array consistent with the data, exact when a source is at endfire);
        parallel directions -- the coordinate along the direction, scale included.
        Positions with the directions off their plane (``planar-motion``) are not determined
        (a 2 x 2 family) and raise in every mode.
    directions : optional (k, d) known unit directions n_j (d = 3 or 2; e.g. from a
        turntable's angles). Then the problem is linear (semi-blind calibration): positions
        and offsets by least squares, ``case = "known-directions"``, in the frame of the given
        directions (no rotation is left free). The only way to calibrate data whose blind
        problem is degenerate (a ``cone``: all sources at one elevation), provided the
        directions are right.

    Raises
    ------
    InputError
        Malformed matrix or options.
    DegenerateGeometryError
        ``kind`` = "too-few-receivers" / "too-few-sources", or one of the failure modes
        (with ``partial`` = the partial FarfieldResult) unless ``allow_degenerate``.

    Examples
    --------
    Eight receiver positions, twelve far-away transmitters, 0.1 mm noise:

    >>> import numpy as np
    >>> import selfcal
    >>> rng = np.random.default_rng(4)
    >>> Z = rng.normal(size=(8, 3))
    >>> N = rng.normal(size=(12, 3))
    >>> N /= np.linalg.norm(N, axis=1, keepdims=True)
    >>> D = Z @ N.T + rng.normal(size=12) + 1e-4 * rng.standard_normal((8, 12))
    >>> res = selfcal.solve_farfield(D)
    >>> res.success, res.degeneracy, res.positions.shape
    (True, None, (8, 3))
    >>> bool(res.residual_rms < 2e-4)
    True
    """
    check_choice(method, "method", METHODS)
    if dim not in (1, 2, 3, "auto"):
        raise InputError(f"dim must be 1, 2, 3 or 'auto', got {dim!r}")
    if method == "minimal" and dim != 3:
        raise InputError("method='minimal' (Algorithm 1) is the 3-D 4 x 6 solver; use dim=3")
    check_choice(loss, "loss", LOSSES)
    check_choice(offsets, "offsets", ("auto", "reference", "free"))
    check_choice(direction_solver, "direction_solver", ("global", "local"))
    check_choice(init_reference, "init_reference", ("mean", "first"))
    check_positive(f_scale, "f_scale")
    if noise_std is not None and not (np.isfinite(noise_std) and noise_std >= 0):
        raise InputError(f"noise_std must be a finite non-negative number, got {noise_std!r}")
    gen = as_rng(rng)
    D = as_matrix(matrix, "matrix", allow_nan=True, min_shape=(1, 1))
    m, k = D.shape
    if m < 3:
        raise DegenerateGeometryError(
            f"{m} receiver positions: at least 4 are needed for 3-D far-field calibration (3 for a "
            "planar partial solution)", kind="too-few-receivers")
    if k < 3:
        raise DegenerateGeometryError(
            f"{k} transmitters: at least 6 are needed for 3-D far-field calibration (3 for a partial "
            "solution)", kind="too-few-sources")
    finite = np.isfinite(D)
    if (finite.sum(axis=0) < 2).any():
        j = int(np.flatnonzero(finite.sum(axis=0) < 2)[0])
        raise InputError(f"matrix: column {j} has fewer than 2 observed entries; it carries no information")
    if (finite.sum(axis=1) < 3).any():
        i = int(np.flatnonzero(finite.sum(axis=1) < 3)[0])
        raise InputError(f"matrix: row {i} has fewer than 3 observed entries; its position is undetermined")

    if method == "minimal" and ((m, k) != (4, 6) or not finite.all()):
        raise InputError(f"method='minimal' needs a complete 4 x 6 matrix, got {m} x {k}")
    check_orientation(D, noise_std=noise_std, rank=3)
    gross = screen_gross_errors(D) if screen else np.zeros_like(finite)
    if ransac:
        gross = gross | (finite & ~ransac_farfield(np.where(gross, np.nan, D), rng=gen))
    used = finite & ~gross
    complete = bool(used.all())
    if directions is not None:
        return _solve_known_directions(D, used, gross, directions, loss=loss)
    if offsets == "auto":
        offsets = "reference" if (complete and loss == "linear") else "free"
    if offsets == "reference" and not np.all(used[0]):
        raise InputError("offsets='reference' needs a complete first row; use offsets='free'")

    # ---- a complete, clean reduced matrix for analysis and initialisation
    sigma_entries = noise_std
    if complete and loss == "linear":
        Dfill = D
    else:
        fit_loss = "huber" if loss != "linear" else "linear"
        Dfill, sig = lowrank_fit(D, used.astype(float), rank=dim if isinstance(dim, int) else 3, loss=fit_loss)
        if sigma_entries is None:
            sigma_entries = sig
        if dim == "auto" or dim == 2:
            # a rank-r completion puts spurious components into the missing entries;
            # complete at rank 1, then 2, and keep the first whose next singular value is noise
            # (a real higher component stays visible in the observed entries); sigma from the
            # largest (rank-3) fit, unbiased whatever the true rank
            for r in range(1, 3 if dim == "auto" else 2):
                Lr, _ = lowrank_fit(D, used.astype(float), rank=r, loss=fit_loss)
                Fr = np.where(used, D, Lr) if loss == "linear" else Lr
                if analyse_degeneracy(Fr - Fr.mean(axis=0), noise_std=sigma_entries, cone_tol=cone_tol).rank <= r:
                    Dfill = Lr
                    break
    if loss == "linear":
        Dfill = np.where(used, D, Dfill)  # only the gaps are filled
    if init_reference == "first":
        X = np.vstack([np.zeros((1, k)), reduce_matrix(Dfill)])  # the paper's K_j = D_1j
    else:
        X = Dfill - Dfill.mean(axis=0, keepdims=True)  # K_j = column mean (Lemma 1)
    C0 = D[0].copy() if offsets == "reference" else Dfill[0].copy()
    report = analyse_degeneracy(X, noise_std=sigma_entries, cone_tol=cone_tol)

    def _offsets(pos: Array, dirs: Array) -> Array:
        if offsets == "reference":
            return D[0].copy()
        return np.asarray(np.nanmean(np.where(used, D - pos @ dirs.T, np.nan), axis=0))

    def _result(pos: Array, dirs: Array, C: Array, *, kind: str | None, conv: bool, its: int,
                meth: str, rej: NDArray[np.bool_], pd: bool, hist: list[float],
                cov: Array | None = None) -> FarfieldResult:
        pos, dirs, R = _canonical(pos, dirs)
        if cov is not None:
            cov = np.einsum("ab,ibc,dc->iad", R, cov, R)
        r = farfield_residuals(np.where(used & ~rej, D, np.nan), pos, dirs, C)
        rms = float(np.sqrt(np.nanmean(r**2))) if np.isfinite(r).any() else float("nan")
        return FarfieldResult(pos, dirs, C, kind, rms, conv, its, meth, loss, rej | gross, pd, report, hist,
                              cov)

    no_rej = np.zeros_like(finite)
    kind_found = report.kind if check_degeneracy else None
    dim_eff = _effective_dim(dim, report) if check_degeneracy or dim != 3 else 3
    if dim_eff in (1, 2):
        if dim_eff == 2 and (dim == 2 or report.kind == "coplanar-directions"):
            check_orientation(D, noise_std=noise_std, rank=2)
        sol = _solve_low_dim(D, X, used, dim_eff, report, offsets=offsets, loss=loss, f_scale=f_scale,
                             method=method, max_iter=max_iter, tol=tol, cone_tol=cone_tol)
        pos, dirs, C, cov = sol["positions"], sol["directions"], sol["offsets"], sol["cov"]
        res = _result(pos, dirs, C, kind=None, conv=sol["converged"], its=sol["iterations"], meth=sol["method"],
                      rej=no_rej, pd=sol["pd"], hist=sol["history"], cov=cov)
        return replace(res, dim=dim_eff, case=sol["case"], determined=sol["determined"])
    if check_degeneracy and report.rank < 3:
        kind = report.kind or "collinear-motion"
        partial_fn = {
            "planar-motion": partial_planar_motion,
            "coplanar-directions": partial_coplanar_directions,
            "collinear-motion": partial_collinear_motion,
            "parallel-directions": partial_parallel_directions,
        }[kind]
        pos, dirs = partial_fn(X)
        pos = pos - pos[0]
        hint = {"planar-motion": "", "coplanar-directions": " (dim=2 / --dim 2 gives the in-plane geometry)",
                "collinear-motion": " (dim=1 / --dim 1 gives the positions along the line, up to scale)",
                "parallel-directions": " (dim=1 / --dim 1 gives the coordinate along the direction)"}[kind]
        part = _result(pos, dirs, _offsets(pos, dirs), kind=kind, conv=False, its=0, meth=f"partial-{kind}",
                       rej=no_rej, pd=False, hist=[])
        sv = ", ".join(f"{v:.3g}" for v in report.singular_values[:4])
        detail = (f" (numerical rank {report.rank}: singular values {sv} against the noise-aware "
                  f"threshold {report.rank_threshold:.3g})")
        part = replace(part, case=kind, dim=3, determined=_DETERMINED[kind])
        return _raise_or_return(kind, _DEGENERATE_MESSAGES[kind] + detail + hint, part, allow_degenerate)
    if m < 4:
        raise DegenerateGeometryError(
            f"{m} receiver positions span 3-D but at least 4 are needed (Theorem 1)", kind="too-few-receivers")
    if k < 6:
        raise DegenerateGeometryError(
            f"{k} transmitters: at least 6 are needed to determine B (Theorem 1)", kind="too-few-sources")

    if method == "auto":
        method = "minimal" if (m, k) == (4, 6) and complete and loss == "linear" else "lm"
    if method == "minimal":
        if (m, k) != (4, 6) or not complete:
            raise InputError(f"method='minimal' needs a complete 4 x 6 matrix, got {m} x {k}")
        sol = solve_minimal(D)
        if kind_found == "cone":
            part = _result(np.nan_to_num(sol.positions), np.nan_to_num(sol.directions), C0, kind="cone",
                           conv=False, its=0, meth="minimal", rej=no_rej, pd=bool(sol.valid), hist=[])
            return _raise_or_return("cone", _DEGENERATE_MESSAGES["cone"], part, allow_degenerate)
        if sol.valid:
            return _result(sol.positions, sol.directions, C0, kind=None, conv=True, its=0,
                           meth="minimal", rej=no_rej, pd=True, hist=[])
        method = "init"  # B not positive definite: the nonlinear fit of A (section 2.3)

    if not np.isfinite(X).all():  # never hand LAPACK a non-finite matrix (its DLASCL noise on stderr)
        raise InputError("matrix: the completed matrix is not finite; check for huge or missing entries")
    init = initialize_farfield(X)
    if not (np.isfinite(init.positions).all() and np.isfinite(init.directions).all()):
        raise DegenerateGeometryError(
            "the initialisation gave non-finite positions (B and its nonlinear fit are singular): the "
            "geometry is numerically degenerate", kind="no-solution")
    Z, N = init.positions - init.positions[0], init.directions
    C = _offsets(Z, N)
    if kind_found == "cone":
        # B is not determined: refining one arbitrary member of the family is wasted work
        part = _result(Z, N, C, kind="cone", conv=False, its=0, meth="init", rej=no_rej,
                       pd=init.b_positive_definite, hist=[])
        return _raise_or_return("cone", _DEGENERATE_MESSAGES["cone"] + f" (cone SNR {report.cone_snr:.3g} < "
                                f"{cone_tol:g})", part, allow_degenerate)
    hist: list[float] = []
    cov: Array | None = None
    its, conv = 0, True
    rej = no_rej
    if method in ("lm", "alternating"):
        rounds = 1 if loss == "linear" else 2
        for _ in range(rounds):
            delta = 1.0
            if loss != "linear":
                rob = _robust_sigma(D, Z, N, C, used)
                delta = f_scale if f_scale is not None else _TUNING[loss] * max(
                    rob, 1e-12 * (np.nanmax(np.abs(X)) + 1e-300))
            if method == "lm":
                out = refine_lm(D, Z, N, C, mask=used, free_offsets=offsets == "free", loss=loss, delta=delta,
                                max_iter=max_iter or 200, tol=tol or 1e-12)
            else:
                out = refine_alternating(D, Z, N, C, mask=used, free_offsets=offsets == "free", loss=loss,
                                         delta=delta, direction_solver=direction_solver,
                                         max_iter=max_iter or 2000, tol=tol or 1e-10)
            Z, N, C = out.positions, out.directions, out.offsets
            cov = out.position_cov
            hist += out.history
            its += out.iterations
            conv = out.converged
        if not conv and kind_found is None:
            warnings.warn(f"far-field {method} stopped after {its} iterations without converging",
                          ConvergenceWarning, stacklevel=2)
        if loss != "linear":
            r = farfield_residuals(np.where(used, D, np.nan), Z, N, C)
            rob = _robust_sigma(D, Z, N, C, used)
            with np.errstate(invalid="ignore"):
                rej = np.asarray(used & (np.abs(r) > reject_k * max(rob, 1e-300)))
    res = _result(Z, N, C, kind=kind_found, conv=conv, its=its, meth=method, rej=rej,
                  pd=init.b_positive_definite, hist=hist, cov=cov)
    res = replace(res, case="cone" if kind_found == "cone" else "spatial",
                  determined=_DETERMINED["cone" if kind_found == "cone" else "spatial"])
    cautions = _collapse_warning(init.directions, res.directions)
    if method == "lm" and res.position_cov is None:
        cautions = cautions + ("position_cov not computed: both sides of the problem are large (the reduced "
                               "system exceeds selfcal.tdoa.refine.COV_DIRECT_MAX unknowns); call "
                               "refine.position_covariance for it",)
    if cautions:
        if cautions[0].startswith("directions-collapsed"):
            warnings.warn(cautions[0], ConvergenceWarning, stacklevel=2)
        res = replace(res, warnings=cautions)
    return res


def _direction_spread(N: Array) -> float:
    sv = np.linalg.svd(np.asarray(N, dtype=float), compute_uv=False)
    return float(sv[-1] / max(sv[0], 1e-300))


def _collapse_warning(N_init: Array, N_final: Array) -> tuple[str, ...]:
    """``("directions-collapsed: ...",)`` when the refined directions are nearly coplanar
    (:data:`COLLAPSE_RATIO`), else ``()``; the initial ratio is quoted for context."""
    before, after = _direction_spread(N_init), _direction_spread(N_final)
    if after < COLLAPSE_RATIO:
        return (f"directions-collapsed: the refined directions are nearly coplanar (singular-value "
                f"ratio {after:.3g}, initialisation {before:.3g}); the out-of-plane scale of the "
                "positions is then poorly determined — typical of noise that is large against the "
                "array; treat the positions with caution or add transmitters",)
    return ()
