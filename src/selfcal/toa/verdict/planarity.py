"""The one planarity decision: is a fitted layout flat, or does the data determine z?

- :func:`compare_fits` / :class:`ModelComparison`: the nested-model F test of a 3-D fit
  against a 2-D one (the 3-D model contains every planar network).
- :func:`planarity` / :class:`Planarity`: the F test with the chi-square of the
  out-of-plane coordinates against their covariances, both at :data:`PLANAR_ALPHA`.
- :func:`bartlett_corrected` / :func:`in_bootstrap_band`: the F test's null distribution
  at a planar truth, from a parametric bootstrap of the 2-D fit (its replicates are made by
  :func:`selfcal.toa.verdict.select.dimension_test`), where the asymptotic F law is not valid.

Used on fits by :func:`selfcal.toa.verdict.select.dimension_test` (``dim="auto"``, the
acoustic pipeline) and on planned layouts by :mod:`selfcal.toa.plan`.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import scipy.stats
from numpy.typing import NDArray

from ..._result import Result
from ...geometry import n_parameters

__all__ = ["BOOT_BAND", "BOOT_F_BAND", "BOOT_REPLICATES", "NOISE_FLOOR", "PLANAR_ALPHA", "PLANAR_RATIO", "ModelComparison", "Planarity",
           "bartlett_corrected", "compare_fits", "in_bootstrap_band", "planarity"]

Array = NDArray[np.float64]

PLANAR_RATIO = 0.01  # without covariances (no noise to test against): thinner than this fraction = flat
PLANAR_ALPHA = 1e-3  # level of the planarity tests (F and thickness chi-square): false "3-D" on a planar layout
PLANE_ITERATIONS = 10  # re-weightings of the plane of the thickness chi-square (converges in 2-4)
NOISE_FLOOR = 1e-10  # s, below any real detection error; keeps the F test finite on exact data
BOOT_REPLICATES = 32  # parametric-bootstrap replicates of the F test's null (Monte Carlo error of the factor ~10 %)
BOOT_BAND = 10.0  # bootstrap only where the layout is thinner than this many bending scales sqrt(noise x extent)
BOOT_F_BAND = 4.0  # ... and F below this many critical values (Bartlett factors measured at planar truths: 1.2-2.3)


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
        Probability of an F at least this large under a planar truth: F(k, dof_3d) of
        ``f_statistic / bartlett``.
    significant : bool
        ``p_value < alpha``: z is determined by the data.
    bartlett : float
        The factor the statistic was divided by before F(k, dof_3d) was applied: the mean of
        the bootstrap replicates' F over the mean of F(k, dof_3d) (:func:`bartlett_corrected`);
        1 when no bootstrap ran.
    bartlett_se : float
        Monte Carlo standard error of ``bartlett`` (NaN when no bootstrap ran).
    replicates : int
        Bootstrap replicates behind ``bartlett`` (0: the asymptotic test).
    p_asymptotic : float
        The uncorrected p-value (F(k, dof_3d) of ``f_statistic``).
    """

    residual_2d: float
    residual_3d: float
    observations: int
    extra_parameters: int
    dof_3d: int
    f_statistic: float
    p_value: float
    significant: bool
    bartlett: float = 1.0
    bartlett_se: float = float("nan")
    replicates: int = 0
    p_asymptotic: float = float("nan")

    def to_dict(self) -> dict[str, Any]:
        """JSON-safe dictionary."""
        return {"residual_2d": self.residual_2d, "residual_3d": self.residual_3d,
                "observations": self.observations, "extra_parameters": self.extra_parameters,
                "dof_3d": self.dof_3d, "f_statistic": self.f_statistic, "p_value": self.p_value,
                "significant": self.significant, "bartlett": self.bartlett,
                "bartlett_se": None if not math.isfinite(self.bartlett_se) else self.bartlett_se,
                "replicates": self.replicates,
                "p_asymptotic": self.p_value if not math.isfinite(self.p_asymptotic) else self.p_asymptotic}


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
                           stat, p, bool(p < alpha), p_asymptotic=p)


def in_bootstrap_band(comparison: ModelComparison, thickness: float, noise: float, extent: float, *,
                      alpha: float = PLANAR_ALPHA, band: float = BOOT_BAND, f_band: float = BOOT_F_BAND) -> bool:
    """Is the asymptotic F test's "3-D" verdict one a parametric bootstrap could overturn?

    True when the F test rejects the plane (``p_value < alpha``), the layout is in the
    second-order regime: thinner than ``band`` times the bending scale ``sqrt(noise x
    extent)``, the height by which a 3-D fit of a planar truth bends off the plane (there the
    heights enter the ranges only as ``h^2 / (2 rho)`` and the 3-D model is not regular at
    the plane, so F(k, dof) is not the statistic's law, :func:`bartlett_corrected`), and F
    is below ``f_band`` critical values of F(k, dof) at ``alpha``: the bootstrap's factor
    divides F, and the factors measured at planar truths are 1.2-2.3 (8 x 10 draws and
    simulated pipeline rooms), so a larger F is 3-D under any of them. Generic 3-D
    networks are outside on both counts (200 draws at 8 x 10: thickness 2-20 bending
    scales, F at least 8 critical values, ``benchmarks/planarity_rates.py``): no replicate
    runs there.

    Parameters
    ----------
    comparison : ModelComparison
        The asymptotic F test.
    thickness : float
        Standard deviation of the fitted positions along their direction of least extent, m.
    noise : float
        Range-noise standard deviation, m.
    extent : float
        Largest extent of the layout, m.
    alpha : float
    band : float
        In bending scales.
    f_band : float
        In critical values of F(k, dof) at ``alpha``.

    Returns
    -------
    bool

    Examples
    --------
    >>> cmp = compare_fits(1.15e-3, 1e-3, 400, 40)
    >>> in_bootstrap_band(cmp, 0.01, 3e-4, 8.0), in_bootstrap_band(cmp, 1.0, 3e-4, 8.0)
    (True, False)
    """
    from scipy.stats import f as f_dist

    if not comparison.significant or not (noise > 0 and extent > 0) or comparison.dof_3d < 1:
        return False
    f_crit = float(f_dist.isf(alpha, comparison.extra_parameters, comparison.dof_3d))
    return bool(thickness < band * math.sqrt(noise * extent) and comparison.f_statistic < f_band * f_crit)


def bartlett_corrected(comparison: ModelComparison, replicates: Array, *,
                       alpha: float = PLANAR_ALPHA) -> ModelComparison:
    """The F test with its statistic scaled by a bootstrap Bartlett factor.

    ``replicates`` are F statistics of data simulated from the 2-D fit (the null: planar)
    with its noise estimate, each refitted in 2-D and 3-D as the observed data were
    (:func:`selfcal.toa.verdict.select.dimension_test`). The factor is
    ``b = mean(F*) / E[F(k, dof)]`` (``E = dof / (dof - 2)``), and the p-value that of
    ``F / b`` under F(k, dof): a Bartlett-type correction of the mean, estimated by the
    bootstrap since no closed form exists here (the 3-D model is not regular at a planar
    truth: the heights enter the ranges at second order). A fixed number of replicates
    estimates a factor where a bootstrap p-value at ``alpha`` = 1e-3 would need thousands;
    measured on planar 8 x 10 draws (100 replicates each) the scaled replicates' 90 % and
    99 % quantiles are at or below F(k, dof)'s, so the scaled law is not lighter-tailed than
    the null. ``bartlett_se`` is the Monte Carlo standard error of ``b`` (the replicates'
    standard deviation over ``sqrt(n)``, divided by ``E``).

    Parameters
    ----------
    comparison : ModelComparison
        The asymptotic test of the observed data.
    replicates : (B,) array
        The replicates' F statistics (non-finite ones are ignored).
    alpha : float

    Returns
    -------
    ModelComparison
        ``comparison`` with ``p_value``, ``significant``, ``bartlett``, ``bartlett_se`` and
        ``replicates`` set; unchanged when fewer than 2 replicates or ``dof_3d <= 2``.

    Examples
    --------
    >>> cmp = compare_fits(1.15e-3, 1e-3, 400, 40)
    >>> round(cmp.p_value, 4), cmp.significant
    (0.0003, True)
    >>> cor = bartlett_corrected(cmp, np.full(32, 2.0))
    >>> round(cor.bartlett, 2), cor.significant
    (1.98, False)
    """
    from scipy.stats import f as f_dist

    F = np.asarray(replicates, float)
    F = F[np.isfinite(F)]
    dof, k = comparison.dof_3d, comparison.extra_parameters
    if F.size < 2 or dof <= 2:
        return comparison
    mean_null = dof / (dof - 2.0)
    b = float(F.mean() / mean_null)
    se = float(F.std(ddof=1) / math.sqrt(F.size) / mean_null)
    stat = comparison.f_statistic
    p = float(f_dist.sf(stat / b, k, dof)) if stat > 0 and b > 0 else 1.0
    return dataclasses.replace(comparison, p_value=p, significant=bool(p < alpha), bartlett=b, bartlett_se=se,
                               replicates=int(F.size), p_asymptotic=comparison.p_value)


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
      the likelihood ratio has heavier tails than F(k, dof) (4-5 % of 200 planar 8 x 10
      draws called 3-D at a nominal 1e-3; the chi-square alone 80 %, the per-point rule
      this replaced 20 %). Where that matters (a "3-D" F near its critical value on a
      layout near flat), :func:`selfcal.toa.verdict.select.dimension_test` passes a
      ``comparison`` corrected by its bootstrap null (:func:`bartlett_corrected`; 0 of
      those 200 draws called 3-D).

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
