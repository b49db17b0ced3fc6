"""Model selection for TOA calibration: which offsets (``offsets="auto"``) and which dimension (``dim="auto"``).

- :func:`choose_offsets`: none / receivers / sources / both by held-out prediction
  (K-fold cross-validation over the sources with the one-standard-error rule,
  :mod:`selfcal.toa.verdict.crossval`) on the same entries for every candidate. It replaced the
  BIC, an in-sample criterion that on measured ranges (serially correlated, partly
  systematic residuals) accepts every extra parameter.
- :func:`compare_fits` / :class:`ModelComparison`: the nested-model F test of a 3-D fit
  against a 2-D one (the 3-D model contains every planar network).
- :func:`planarity` / :class:`Planarity`: the one planarity decision: the F test of a 2-D
  against a 3-D fit and the chi-square of the out-of-plane coordinates against their
  covariances, both at :data:`PLANAR_ALPHA`.
- :func:`dimension_test`: that decision on a 3-D fit (its 2-D fit refined from it); used by
  :func:`choose_dim` and the acoustic pipeline.
- :func:`choose_dim`: 3-D unless :func:`dimension_test` finds z undetermined; then 2-D, so a
  flat layout does not report a confident spurious z.
"""

from __future__ import annotations

import dataclasses
import math
import warnings
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
import scipy.stats
from numpy.typing import NDArray

from ..._result import Result
from ...errors import ConvergenceWarning, DegenerateGeometryError
from ...geometry import n_parameters

if TYPE_CHECKING:  # the result type sits one layer above the verdicts (docs/design.md)
    from ..options import ToaOptions
    from ..result import ToaResult

__all__ = [
    "NOISE_FLOOR",
    "PLANAR_ALPHA",
    "PLANAR_RATIO",
    "ModelComparison",
    "Planarity",
    "choose",
    "choose_dim",
    "choose_offsets",
    "compare_fits",
    "dimension_test",
    "planarity",
]

Array = NDArray[np.float64]

PLANAR_RATIO = 0.01  # without covariances (no noise to test against): thinner than this fraction = flat
PLANAR_ALPHA = 1e-3  # level of the planarity tests (F and thickness chi-square): false "3-D" on a planar layout
PLANE_ITERATIONS = 10  # re-weightings of the plane of the thickness chi-square (converges in 2-4)
NOISE_FLOOR = 1e-10  # s, below any real detection error; keeps the F test finite on exact data
OFFSET_CANDIDATES = ("none", "receivers", "sources", "both")


@dataclass(frozen=True)
class ModelComparison:
    """Nested-model F test of a 3-D fit against a 2-D fit of the same TOA matrix.

    Attributes
    ----------
    residual_2d, residual_3d : float
        RMS residuals (matrix units).
    observations : int
        Observed entries m.
    extra_parameters : int
        k = n - 3 unknowns the 3-D model adds (one coordinate per node, less the three
        extra rigid-motion gauge freedoms of 3-D).
    dof_3d : int
        m minus the 3-D model's free parameters (``4 n - 7`` with both offsets, n = I + J).
    f_statistic : float
        ``((RSS_2 - RSS_3) / k) / (RSS_3 / dof_3d)``.
    p_value : float
        Probability of an F at least this large under a planar truth (F(k, dof_3d)).
    significant : bool
        ``p_value < alpha``: z is determined by the data.
    """

    residual_2d: float
    residual_3d: float
    observations: int
    extra_parameters: int
    dof_3d: int
    f_statistic: float
    p_value: float
    significant: bool

    def to_dict(self) -> dict[str, Any]:
        """JSON-safe dictionary."""
        return {"residual_2d": self.residual_2d, "residual_3d": self.residual_3d,
                "observations": self.observations, "extra_parameters": self.extra_parameters,
                "dof_3d": self.dof_3d, "f_statistic": self.f_statistic, "p_value": self.p_value,
                "significant": self.significant}


def compare_fits(residual_2d: float, residual_3d: float, observations: int, nodes: int, *,
                 alpha: float = PLANAR_ALPHA, noise_floor: float = NOISE_FLOOR,
                 n_offsets: int | None = None) -> ModelComparison:
    """F test: does the 3-D model fit the TOAs significantly better than the planar one?

    With Gaussian noise, the planar model nested in the 3-D one and ``RSS = m rms^2``,
    ``F = ((RSS_2 - RSS_3) / k) / (RSS_3 / (m - p_3))`` follows F(k, m - p_3) when the
    network is planar (k = n - 3 extra unknowns, p_3 = 3 n - 6 + offsets: ``4 n - 7`` with
    both kinds, the default). The noise variance ``RSS_3 / (m - p_3)`` is floored at
    ``noise_floor^2`` so exact data give a finite answer. Without residual degrees of
    freedom the test cannot reject, and z is kept only if the 2-D fit is off by more than
    the floor.

    Parameters
    ----------
    residual_2d, residual_3d : float
        RMS residuals of the two fits over the ``observations`` entries.
    observations : int
    nodes : int
        I + J.
    alpha : float
        Significance level.
    noise_floor : float
        Same units as the residuals.
    n_offsets : int, optional
        Free offsets of the model (default ``nodes - 1``, both kinds).

    Returns
    -------
    ModelComparison

    Examples
    --------
    >>> compare_fits(1e-3, 1e-5, 400, 40).significant
    True
    """
    from scipy.stats import f as f_dist

    k = max(n_parameters(nodes, 0, 3) - n_parameters(nodes, 0, 2), 1)  # the n - 3 heights of a plane
    n_off = nodes - 1 if n_offsets is None else int(n_offsets)
    dof = observations - (n_parameters(nodes, 0, 3) + n_off)
    rss2 = observations * residual_2d**2
    rss3 = observations * residual_3d**2
    if dof < 1:
        stat = float("inf") if residual_2d > residual_3d + noise_floor else 0.0
        p = 0.0 if stat > 0 else 1.0
    else:
        var = max(rss3 / dof, noise_floor**2)
        stat = float((rss2 - rss3) / k / var)
        p = float(f_dist.sf(stat, k, dof)) if stat > 0 else 1.0
    return ModelComparison(float(residual_2d), float(residual_3d), int(observations), int(k), int(dof),
                           stat, p, bool(p < alpha))


@dataclass(frozen=True, repr=False)
class Planarity(Result):
    """How flat a network is.

    Attributes
    ----------
    near_planar : bool
    extents : (d,) array
        Standard deviations of the centred positions along their principal axes, m
        (singular values / sqrt(n)), largest first.
    normal : (d,) array
        Direction of least extent.
    normal_std : float
        RMS standard deviation of the positions along ``normal`` from their covariances, m
        (NaN without covariances).
    comparison : ModelComparison or None
        The 2-D / 3-D F test behind the verdict (:func:`compare_fits`), when one was made.
    thickness_chi2, thickness_p : float
        ``T = sum_k (n^T (p_k - c))^2 / (n^T C_k n)`` over the points with a covariance, at
        the plane (n, c) that minimises it, and its p-value under a planar layout (chi-square with ``n_points - d`` dof: the fitted
        plane takes ``d``); NaN without covariances. A small p means the data resolve the
        thickness jointly, even where no single point's offset from the plane is resolved.
    """

    near_planar: bool
    extents: Array
    normal: Array
    normal_std: float
    comparison: ModelComparison | None = None
    thickness_chi2: float = float("nan")
    thickness_p: float = float("nan")

    def to_dict(self) -> dict[str, Any]:
        """JSON-safe dictionary."""
        return {"near_planar": bool(self.near_planar), "extents": np.asarray(self.extents, float).tolist(),
                "normal": np.asarray(self.normal, float).tolist(),
                "normal_std": None if not math.isfinite(self.normal_std) else float(self.normal_std),
                "comparison": None if self.comparison is None else self.comparison.to_dict(),
                "thickness_chi2": None if not math.isfinite(self.thickness_chi2) else float(self.thickness_chi2),
                "thickness_p": None if not math.isfinite(self.thickness_p) else float(self.thickness_p)}


def planarity(points: Array, cov: NDArray[np.float64] | None = None, *,
              comparison: ModelComparison | None = None, alpha: float = PLANAR_ALPHA,
              ratio: float = PLANAR_RATIO) -> Planarity:
    """Decide whether (n, d) ``points`` are too close to a plane (a line in 2-D) for their dimension.

    The one planarity decision of the project (``dim="auto"``, the acoustic pipeline,
    coplanar partners in the pipeline's one-side rule): the layout is resolved, i.e. *not*
    near-planar, only when the data reject a planar layout at level ``alpha``:

    - its thickness is resolved by its own covariances: ``T = min over planes (n, c) of
      sum_k (n^T (p_k - c))^2 / (n^T C_k n)`` over the points with a covariance (the plane
      by re-weighted least squares from the direction of least extent) exceeds the
      chi-square quantile with ``n_points - d`` degrees of freedom (the plane takes ``d``):
      ``thickness_p <= alpha``. Judged jointly, not
      point by point: several hundred weakly determined points resolve a thickness no
      single one does;
    - and, when a 2-D fit was compared with the 3-D one (``comparison``,
      :func:`compare_fits`), the F test finds the 3-D model significantly better at ``alpha``.
      The covariances alone cannot decide a planar truth: there the out-of-plane
      coordinates are determined only to second order, the 3-D fit bends off the plane by
      about ``sqrt(noise x extent)`` and its linearised covariances (the Cramér-Rao bound
      at the bent fit) are too small for that bend (simulated planar layouts: the chi-square
      alone called 100 % of them resolved, ``benchmarks/planarity_rates.py``). The F test of
      the nested models is the better test there, but not an exact one: the heights enter
      the ranges only to second order, the 3-D model is not regular at a planar truth and
      the likelihood ratio has heavier tails than F(k, dof) (4 % of 200 planar 8 x 10
      draws called 3-D at a nominal 1e-3; the chi-square alone 80 %, the per-point rule
      this replaced 20 %).

    Without any covariance (no noise to test against) the fallback is geometric: thinner
    than ``ratio`` of the widest extent.

    Parameters
    ----------
    points : (n, d) array, m
    cov : (n, d, d) array, optional
        Per-point covariances, m^2 (non-finite ones are ignored): a fit's, or the
        Cramér-Rao bound of a planned layout.
    comparison : ModelComparison, optional
        The 2-D against 3-D F test of the same data (required for a verdict on a whole
        fitted layout; a subset of a determined 3-D fit, such as its senders, needs none).
    alpha : float
        Level of both tests (default :data:`PLANAR_ALPHA`).
    ratio : float
        The geometric fallback without covariances.

    Returns
    -------
    Planarity

    Examples
    --------
    >>> import numpy as np
    >>> P = np.random.default_rng(0).uniform(0, 10, (20, 3)) * [1, 1, 0.001]
    >>> planarity(P).near_planar
    True
    >>> C = np.tile(np.eye(3) * 1e-8, (20, 1, 1))  # 0.1 mm std: the 1 cm thickness is resolved
    >>> planarity(P, C).near_planar
    False
    """
    P = np.asarray(points, dtype=float)
    P = P[np.isfinite(P).all(axis=1)]
    centred = P - P.mean(axis=0)
    _, s, vt = np.linalg.svd(centred, full_matrices=False)
    ext = s / np.sqrt(max(len(P), 1))
    normal = vt[-1]
    nstd = chi2_t = p_t = float("nan")
    if cov is not None:
        C = np.asarray(cov, dtype=float)
        C = C[np.isfinite(np.asarray(points, float)).all(axis=1)]
        ok = np.isfinite(C).all(axis=(1, 2))
        if ok.any():
            var_n = np.einsum("i,kij,j->k", normal, C[ok], normal)
            nstd = float(np.sqrt(np.mean(var_n)))
            good = var_n > 0
            dof = int(good.sum()) - P.shape[1]
            if dof > 0:
                # the plane that minimises T itself (weights 1 / n^T C_k n, re-weighted: the
                # unweighted plane over-states T when the error bars differ from point to
                # point, 3.7 % false alarms at level 1e-3 for z stds of 1-10 mm)
                Q, Ck = P[ok][good], C[ok][good]
                nv = normal
                for _ in range(PLANE_ITERATIONS):
                    w = 1.0 / np.maximum(np.einsum("i,kij,j->k", nv, Ck, nv), 1e-300)
                    cw = (w @ Q) / w.sum()
                    D = Q - cw
                    nv_new = np.linalg.eigh((D * w[:, None]).T @ D)[1][:, 0]
                    if abs(float(nv_new @ nv)) > 1.0 - 1e-12:
                        nv = nv_new
                        break
                    nv = nv_new
                var_w = np.einsum("i,kij,j->k", nv, Ck, nv)
                cw = (Q / var_w[:, None]).sum(axis=0) / (1.0 / var_w).sum()
                chi2_t = float(np.sum(((Q - cw) @ nv) ** 2 / var_w))
                p_t = float(scipy.stats.chi2.sf(chi2_t, dof))
    thick = bool(p_t <= alpha) if math.isfinite(p_t) else bool(ext[-1] >= ratio * ext[0])
    flat = not (thick and (comparison is None or comparison.significant))
    return Planarity(flat, ext, normal, nstd, comparison, chi2_t, p_t)


# ------------------------------------------------------------------ choices on solve_toa results

Solver = Callable[..., "ToaResult"]


def _quiet(solve: Solver, M: Array, dim: int, offsets: str, opts: ToaOptions,
           init: Any = "auto") -> ToaResult | None:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ConvergenceWarning)
        try:
            return solve(M, dim, offsets, opts, init=init)
        except DegenerateGeometryError:
            return None


def _n_off(mode: str, I: int, J: int) -> int:
    return {"none": 0, "receivers": I, "sources": J, "both": I + J - 1}[mode]


def _rss(res: ToaResult) -> float:
    assert res.residuals is not None
    e = res.residuals[np.isfinite(res.residuals) & ~np.asarray(res.outliers, bool)]
    return float(e @ e)


def _nested_init(res: ToaResult, mode: str, speed: float | None) -> tuple[Any, ...]:
    """A fit as a start of ``mode`` (dropped nodes at the centroid, missing offsets 0).

    In metres, offsets too (the fit reports them in the matrix's units: times ``speed``):
    the form of the ``init`` of the solver the choice runs (:func:`selfcal.toa.solve._solve_fixed`,
    the search's internal units). A solver in :func:`selfcal.toa.solve_toa`'s form (offsets in
    the matrix's units) converts back (:func:`selfcal.acoustics.calibrate._toa_solver`).
    """
    k = 1.0 if speed is None else float(speed)

    def fill(P: Array) -> Array:
        P = np.array(P, dtype=float)
        bad = ~np.isfinite(P).all(axis=1)
        P[bad] = np.nanmean(P[~bad], axis=0) if (~bad).any() else 0.0
        return P

    def off(a: Array | None, n: int) -> Array:
        return np.zeros(n) if a is None else np.nan_to_num(np.asarray(a, float) * k)

    r, s = fill(res.receivers), fill(res.sources)
    d = off(res.receiver_offsets, len(r)) if mode in ("receivers", "both") else None
    o = off(res.source_offsets, len(s)) if mode in ("sources", "both") else None
    return r, s, d, o


def _misfit(res: ToaResult) -> bool:
    """True when the fit's own residual test (chi-square at a given noise, else the geometry
    test) rejects it: the model does not explain the data (not merely undetermined)."""
    tests = (res.fit, res.geometry)
    return any(t is not None and not bool(t.passed) for t in tests)


def _projected_init(res: ToaResult, mode: str, speed: float | None) -> tuple[Any, ...]:
    """A 3-D fit projected onto its best-fitting plane: a 2-D start (metres, in-plane axes)."""
    r, s, d, o = _nested_init(res, mode, speed)
    P = np.vstack([r, s])
    c = P.mean(axis=0)
    _, _, vt = np.linalg.svd(P - c, full_matrices=False)
    return (r - c) @ vt[:2].T, (s - c) @ vt[:2].T, d, o


def _lsq(res: ToaResult) -> float:
    """Sum of squares over every entry the fit used (outliers included): the objective a
    refinement (``method="nls"``) minimises, comparable between two refinements of one model."""
    assert res.residuals is not None
    e = res.residuals[np.isfinite(res.residuals)]
    return float(e @ e)


def _own_starts(M: Array, dim: int, mode: str, opts: ToaOptions) -> list[tuple[Any, ...]]:
    """The model's own start, from the solver's registry initialiser for offsets: the rank-d
    iteration (both offset kinds at once, :mod:`selfcal.toa.init.offsets_init`) on the matrix
    the search would see (:func:`selfcal.toa.verdict.robust.screened`), collapsed to ``mode``; of its
    candidates the one of least sum of squares (metres, original order; none where the
    initialiser does not apply). Inside :func:`choose_offsets` the initialiser runs once per
    matrix (:func:`selfcal.toa.init.starts.shared_rank3`): every candidate and the final search
    reuse it."""
    from ..engine.nls import toa_model
    from ..init.starts import _rank3
    from .robust import screened

    Y = np.asarray(M, float) * (1.0 if opts.speed is None else float(opts.speed))
    I, J = Y.shape
    try:
        pr, pc, Yc, _, used, kr, ks = screened(Y, dim, mode)
        found = _rank3(np.where(used, Yc, np.nan)[np.ix_(kr, ks)], dim, mode, opts.rng)
    except (DegenerateGeometryError, ValueError, np.linalg.LinAlgError, FloatingPointError):
        return []
    rows, cols = pr[kr], pc[ks]

    def back(r: Array, s: Array, d: Array | None, o: Array | None) -> tuple[Any, ...]:
        R, S = np.full((I, dim), np.nan), np.full((J, dim), np.nan)
        R[rows], S[cols] = r, s
        D = None if d is None else np.zeros(I)
        O = None if o is None else np.zeros(J)
        if D is not None:
            D[rows] = d
        if O is not None:
            O[cols] = o
        return R, S, D, O

    def cost(st: tuple[Any, ...]) -> float:
        with np.errstate(all="ignore"):
            e = Y - toa_model(*st)
        e = e[np.isfinite(e)]
        return float(e @ e) if e.size else math.inf

    out = [back(*st) for st in found]
    return [min(out, key=cost)] if out else []


def choose_offsets(M: Array, dim: int, solve: Solver, opts: ToaOptions) -> tuple[ToaResult, dict[str, Any]]:
    """Fit every offsets mode and keep the one chosen by held-out prediction; (result, statistics).

    The offsets-free mode is fitted by ``solve``'s search; each larger mode by a cheap search:
    one refinement (``method="nls"``) started from the best fit of the modes it nests, its new
    offsets at zero (so it never ends above them; a full search per mode cost 4x the blind
    solve), and a refinement from the model's own start (the rank-d offsets initialiser of
    the solver's registry, computed once for all modes, its best start by sum of squares)
    where the first is certainly not the model's fit: it fails its own residual test
    (:func:`_misfit`; with a given noise the chi-square test), or the mode is the widest
    ("both"), which no narrower fit certifies (a nested chain of wrong models led it to a
    wrong basin, held-out RMS 0.3 m against 1 cm noise, where its own start finds the truth).
    The lower sum of squares over the same entries wins (:func:`_lsq`): a fit stuck in a wrong
    basin is a search failure, not evidence against its model.
    :func:`selfcal.toa.verdict.crossval.cross_validate` then refits each on K - 1 blocks of
    the sources, locates the held-out sources with the fitted receivers (and offsets) and
    scores their leave-one-range-out prediction residuals; the one-standard-error rule
    keeps the simplest mode within one paired standard error of the best. Every mode is
    judged on the same entries: those kept by the candidate that removed the fewest as
    outliers (a model that cannot fit good entries must not hide its misfit by removing
    them), of the nodes every candidate kept. An in-sample criterion (BIC, F) is not used:
    on measured ranges (serially correlated, partly systematic residuals) it accepts any
    extra parameter. The chosen mode, if not the offsets-free one, is finally searched
    from its refinement (the search accepts only lower costs).
    ``statistics`` is :meth:`selfcal.toa.verdict.crossval.CvChoice.to_dict` plus ``observations``,
    each mode's in-sample ``rss`` and ``own_start`` (the modes whose own start was tried).
    """
    from ..init.starts import shared_rank3

    with shared_rank3():  # the rank-d initialiser runs once for every candidate and the final search
        return _choose_offsets(M, dim, solve, opts)


def _choose_offsets(M: Array, dim: int, solve: Solver, opts: ToaOptions) -> tuple[ToaResult, dict[str, Any]]:
    fits: dict[str, ToaResult] = {}
    own: list[str] = []
    # the candidates' refinements are starts and scores only: no covariances (the chosen one is searched)
    nls = dataclasses.replace(opts, method="nls", covariance=False)
    for mode in OFFSET_CANDIDATES:
        # every model is also started from the best fit of the models it nests (offsets of the
        # other kinds at zero): a refinement only lowers the cost, so it never ends above them
        nested = [fits[k] for k in fits if k == "none" or mode == "both"]
        base = min(nested, key=_rss) if nested else None
        res = _quiet(solve, M, dim, mode, nls, init=_nested_init(base, mode, opts.speed)) if base else None
        if base is None or res is None:
            res = _quiet(solve, M, dim, mode, opts)
        elif mode == "both" or _misfit(res):
            own.append(mode)
            for st in _own_starts(M, dim, mode, opts):
                try:  # a start the engine cannot refine (singular normal equations) is skipped
                    alt = _quiet(solve, M, dim, mode, nls, init=st)
                except (np.linalg.LinAlgError, ValueError):
                    alt = None
                if alt is not None and _lsq(alt) < _lsq(res):
                    res = alt
        if res is not None:
            fits[mode] = res
    if not fits:
        raise DegenerateGeometryError("no offsets model could be fitted to this matrix", kind="too-few-measurements")
    from .crossval import cross_validate

    # every candidate judged on the same entries: those kept by the candidate that removed the
    # fewest as outliers (a gross error is removed by every model that fits the rest; a model
    # that cannot fit good entries removes them too, and must not hide its misfit that way)
    k = 1.0 if opts.speed is None else float(opts.speed)
    fewest = min(fits.values(), key=lambda r: (int(np.asarray(r.outliers).sum()), _rss(r)))
    kept = np.isfinite(M) & ~np.asarray(fewest.outliers, bool)
    kr = np.logical_and.reduce([np.isfinite(r.receivers).all(axis=1) for r in fits.values()])
    ks = np.logical_and.reduce([np.isfinite(r.sources).all(axis=1) for r in fits.values()])
    Z = np.where(kept, M * k, np.nan)[np.ix_(kr, ks)]

    def start(res: ToaResult) -> tuple[Any, ...]:
        d = None if res.receiver_offsets is None else np.nan_to_num(np.asarray(res.receiver_offsets)[kr] * k)
        o = None if res.source_offsets is None else np.nan_to_num(np.asarray(res.source_offsets)[ks] * k)
        return res.receivers[kr], res.sources[ks], d, o

    choice = cross_validate(Z, {mode: start(res) for mode, res in fits.items()})
    stats = {**choice.to_dict(), "observations": int(np.isfinite(Z).sum()),
             "rss": {mode: _rss(res) for mode, res in fits.items()}, "own_start": own}
    chosen = choice.chosen
    if chosen != "none":
        # the chosen model (only it) gets the full search, started from its refinement: the
        # refinement alone can stop in a worse basin (room 7 x 220: anchor RMSE 0.146 vs 0.071 m)
        full = _quiet(solve, M, dim, chosen, opts, init=_nested_init(fits[chosen], chosen, opts.speed))
        if full is not None:
            fits[chosen] = full
            stats["searched"] = chosen
        else:  # the candidates' refinements skip the covariances: the chosen one's, refitted in place
            fits[chosen] = _quiet(solve, M, dim, chosen, dataclasses.replace(opts, method="nls"),
                                  init=_nested_init(fits[chosen], chosen, opts.speed)) or fits[chosen]
    return fits[chosen], stats


def dimension_test(M: Array, fit3: ToaResult, offsets: str, solve: Solver,
                   opts: ToaOptions) -> tuple[bool, Planarity, ToaResult | None, dict[str, Any]]:
    """Is the 3-D fit ``fit3`` of ``M`` determined in z, or is the layout (near-)planar?

    The 2-D model is fitted by one refinement from ``fit3`` projected onto its best plane
    (a full 2-D search only when that refinement fails): the 2-D model is nested in the 3-D
    one, so on planar data that start is usually the 2-D solution up to the noise, and on
    data with a resolved thickness no 2-D start approaches the 3-D residual. When that
    refinement fails its own residual test or removes more entries than the 3-D fit (a
    wrong 2-D basin, reached from a 3-D fit bent off a planar truth: it inflated F to 1e4-1e6
    on planar 8 x 10 draws), the 2-D model is also searched and the better fit kept. The decision is
    :func:`planarity` with the F test of the two fits over the entries both fitted
    (:func:`compare_fits`) and the 3-D fit's covariances, both at :data:`PLANAR_ALPHA`:
    z is kept when the F test rejects the plane and the 3-D layout resolves its thickness.
    Two exceptions keep z: no residual degree of freedom for the F test (the fits kept
    different entries: no evidence for dropping z), and an F test that rejects the plane
    while the 2-D fit fails its own residual test (the data reject the plane; the 3-D
    answer is then judged by its own determinacy test, never replaced by a failed 2-D fit).

    Parameters
    ----------
    M : (I, J) array
        The matrix both fits are of (NaN = missing).
    fit3 : ToaResult
        Its 3-D fit.
    offsets : str
        The offsets model of both fits.
    solve : callable
        ``solve(M, dim, offsets, opts, init=...)`` (:func:`selfcal.toa.solve._solve_fixed`'s form).
    opts : ToaOptions
        Passed to ``solve`` (the 2-D refinement with ``method="nls"``).

    Returns
    -------
    keep3 : bool
        True: z is determined (report the 3-D fit).
    planarity : Planarity
        With the comparison; ``near_planar`` is the test's verdict (``not keep3`` except
        in the two exceptions above).
    fit2 : ToaResult or None
        The 2-D fit (None when none could be fitted: then ``keep3`` is True).
    statistics : dict
        ``criterion``, ``chosen``, ``f_statistic``, ``p_value``, ``residual_2d``,
        ``residual_3d``, ``dof_3d``, ``near_planar``, ``thickness``, ``normal_std``,
        ``thickness_chi2``, ``thickness_p``, ``alpha``.
    """
    r3 = fit3
    r2 = _quiet(solve, M, 2, offsets, dataclasses.replace(opts, method="nls"), init=_projected_init(r3, offsets, opts.speed))
    if r2 is None or _misfit(r2) or (r2.outliers is not None and np.asarray(r2.outliers).sum() >
                                     np.asarray(r3.outliers).sum()):
        # at a planar truth the 3-D fit bends off the plane by ~sqrt(noise x extent); the
        # refinement from its projection can then stop in a wrong 2-D basin (removing good
        # entries as outliers), which would inflate F: the 2-D model is searched as well and
        # the better fit (fewer entries removed, then lower RSS) is the 2-D model's
        searched = _quiet(solve, M, 2, offsets, opts)
        cands = [f for f in (r2, searched) if f is not None]
        r2 = min(cands, key=lambda f: (int(np.asarray(f.outliers).sum()), _rss(f))) if cands else None
    pts = np.vstack([r3.receivers, r3.sources])
    cov = np.concatenate([r3.receiver_cov, r3.source_cov])
    if r2 is None:
        plan = planarity(pts, cov)
        return True, plan, None, {"criterion": "F", "chosen": 3, "reason": "only the 3-D fit exists",
                                  "alpha": PLANAR_ALPHA}
    assert r2.residuals is not None and r3.residuals is not None and r2.outliers is not None
    assert r3.outliers is not None
    common = np.isfinite(r2.residuals) & np.isfinite(r3.residuals) & ~r2.outliers & ~r3.outliers
    m = int(common.sum())
    I, J = M.shape
    rms2 = float(np.sqrt(np.mean(r2.residuals[common] ** 2))) if m else float("nan")
    rms3 = float(np.sqrt(np.mean(r3.residuals[common] ** 2))) if m else float("nan")
    floor = float(np.sqrt(np.finfo(float).eps) * np.nanmedian(np.abs(M)))  # the solver's precision
    cmp = compare_fits(rms2, rms3, m, I + J, noise_floor=floor, n_offsets=_n_off(offsets, I, J))
    plan = planarity(pts, cov, comparison=cmp)
    untestable = cmp.dof_3d <= 0
    keep3 = untestable or not plan.near_planar or (cmp.significant and _misfit(r2))
    stats = {"criterion": "F", "chosen": 3 if keep3 else 2, "f_statistic": cmp.f_statistic,
             "p_value": cmp.p_value, "residual_2d": rms2, "residual_3d": rms3, "dof_3d": cmp.dof_3d,
             "near_planar": plan.near_planar, "thickness": float(plan.extents[-1]),
             "normal_std": plan.normal_std, "thickness_chi2": plan.thickness_chi2,
             "thickness_p": plan.thickness_p, "alpha": PLANAR_ALPHA}
    return keep3, plan, r2, stats


def choose_dim(M: Array, offsets: str, solve: Solver, opts: ToaOptions, *,
               fit3: ToaResult | None = None) -> tuple[ToaResult, dict[str, Any]]:
    """3-D unless z is not determined by the data (:func:`dimension_test`); (result, statistics).

    ``fit3``: the 3-D fit of this model when the caller already searched it
    (:func:`choose` after :func:`choose_offsets`); it is not searched again. Without a 3-D
    fit (the solver breaks down in 3-D) the 2-D model is searched.
    """
    r3 = fit3 if fit3 is not None else _quiet(solve, M, 3, offsets, opts)
    if r3 is None:
        r2 = _quiet(solve, M, 2, offsets, opts)
        if r2 is None:
            raise DegenerateGeometryError("neither a 2-D nor a 3-D geometry could be fitted to this matrix",
                                          kind="degenerate-geometry")
        return r2, {"criterion": "F", "chosen": 2, "reason": "only the 2-D fit exists"}
    keep3, _, r2, stats = dimension_test(M, r3, offsets, solve, opts)
    return (r3 if keep3 or r2 is None else r2), stats


def choose(M: Array, dim: int | str, offsets: str, opts: ToaOptions, *, solve: Solver) -> ToaResult:
    """``solve_toa`` with ``dim`` and / or ``offsets`` set to "auto": the chosen fit with its statistics."""
    sel: dict[str, Any] = {}
    fit3 = None
    if offsets == "auto":
        d0 = 3 if dim == "auto" else int(dim)
        res, sel["offsets"] = choose_offsets(M, d0, solve, opts)
        offsets = res.offsets
        # the chosen model's 3-D fit, searched (its refinement alone is searched again)
        searched = res.offsets == "none" or "searched" in sel["offsets"]
        fit3 = res if d0 == 3 and searched else None
    if dim == "auto":
        res, sel["dim"] = choose_dim(M, offsets, solve, opts, fit3=fit3)
    return dataclasses.replace(res, selection=sel)
