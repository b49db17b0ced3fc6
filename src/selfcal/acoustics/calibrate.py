"""Stages 2 + 3 of 004 on the per-sender TOA matrix: one model fit (onsets, delays, positions).

The per-sender TOA matrix ``t_ij = |r_i - s_j| / c + tau_j + delta_i`` (004 eq. 3.1) goes to
:func:`selfcal.toa.solve_toa` with ``offsets="both"``:

- **one model fit by default**: 3-D (or 2-D / 2-D with known heights when asked). With
  ``dim="auto"`` a test decides whether z is resolved
  (:func:`selfcal.toa.verdict.select.dimension_test`, the project's one planarity test: F test
  of a 2-D fit refined from the 3-D one and the thickness chi-square, level 1e-3); only a
  near-planar verdict (or a 3-D breakdown) searches and reports the 2-D model.
- **what the pipeline knows goes in**: the units (a microphone and a loudspeaker in one
  housing, :mod:`selfcal.acoustics.units`) start the search; known heights are a weighted
  least-squares fit (:func:`selfcal.acoustics.geometry.refine_known_heights`, 1 / std per
  entry) from the better of the 2-D and 3-D blind starts.

The robust event-level loop around it (outliers, re-detection, dropped units) is
:mod:`selfcal.acoustics.robust_fit`; the outlier statistics :mod:`selfcal.acoustics.leverage`;
the scale from known unit distances :mod:`selfcal.acoustics.scale`.
"""

from __future__ import annotations

import warnings
from dataclasses import replace
from functools import cache
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from ..errors import DegenerateGeometryError, InputError
from ..geometry import n_parameters
from ..requirements import TIMING_REQUIREMENT
from ..robust import TUNING, loss_rho
from ..toa.verdict.select import dimension_test
from .geometry import (
    PLANAR_ALPHA,
    ModelComparison,
    Planarity,
    one_side_of_plane,
    planarity,
    refine_known_heights,
)
from .solution import Calibration

if TYPE_CHECKING:
    from .pipeline import PipelineResult

__all__ = ["calibrate_matrix", "refit", "sender_matrix", "n_parameters_of"]

Array = NDArray[np.float64]


def _solve(T: Array, dim: int, speed: float, rng: int, init: Any = "auto", noise: float | None = None,
           f_scale: float | None = None, units: NDArray[np.intp] | None = None) -> Any:
    """One :func:`selfcal.toa.solve_toa` call with both offsets.

    ``init="auto"``: the search, started from the units' two-way start
    (:func:`selfcal.acoustics.units.unit_start`) when ``units`` pairs every receiver with
    a sender, else blind. An explicit ``init``: one refinement from it (``f_scale``: Cauchy).
    """
    from ..toa.solve import solve_toa

    if isinstance(init, str):
        from .units import unit_start

        first = None
        if units is not None:
            try:
                first = unit_start(T, units, speed, dim, rng=rng)
            except DegenerateGeometryError:
                first = None
        if first is not None:
            return solve_toa(T, dim=dim, offsets="both", speed=speed, rng=rng, noise=noise, init=first)
        return solve_toa(T, dim=dim, offsets="both", speed=speed, rng=rng, noise=noise)
    if f_scale is not None:
        return solve_toa(T, dim=dim, offsets="both", speed=speed, rng=rng, init=init, method="nls",
                         loss="cauchy", f_scale=f_scale, covariance=False)
    return solve_toa(T, dim=dim, offsets="both", speed=speed, rng=rng, init=init, method="nls")


def _solve_retrying(T: Array, speed: float, rng: int, attempts: int = 3, noise: float | None = None,
                    units: NDArray[np.intp] | None = None) -> Any:
    """3-D solve; a node that turns unobservable on the way (e.g. a microphone crossing the
    plane of coplanar loudspeakers during the iterations) gets new random starts."""
    for k in range(attempts):
        try:
            return _solve(T, 3, speed, rng + 1000 * k, noise=noise, units=units)
        except DegenerateGeometryError as exc:
            if exc.kind != "unobservable-node" or k == attempts - 1:
                raise
    raise AssertionError("unreachable")  # pragma: no cover


def _mirror_matches(X: Array, alt: Array, amb: NDArray[np.bool_], plane_points: Array) -> NDArray[np.bool_]:
    """The ambiguous nodes whose alternative position is their mirror image through the plane
    of ``plane_points`` (within half the distance the alternative moves them)."""
    P = plane_points[np.isfinite(plane_points).all(axis=1)]
    ok = np.asarray(amb, bool) & np.isfinite(X).all(axis=1) & np.isfinite(alt).all(axis=1)
    if len(P) < 3 or not ok.any():
        return np.zeros(len(X), bool)
    c = P.mean(axis=0)
    n = np.linalg.svd(P - c, full_matrices=False)[2][-1]
    mirror = X - 2.0 * ((X - c) @ n)[:, None] * n[None, :]
    with np.errstate(invalid="ignore"):
        near = np.linalg.norm(alt - mirror, axis=1) <= 0.5 * np.linalg.norm(alt - X, axis=1)
    return ok & near


def _resolve_mirrors(T: Array, res: Any, speed: float, rng: int, notes: list[str], sided: list[str]) -> Any:
    """Apply :func:`one_side_of_plane` to the units whose side of their partners' plane the data leave open.

    Which units those are is the TOA solver's own flip test
    (:mod:`selfcal.toa.verdict.uniqueness`: a node whose partners are (nearly) coplanar is
    reflected through their plane, refitted and compared by a likelihood-ratio test at
    1e-3), not a separate planarity rule: when it lists a microphone whose alternative is
    its mirror image through the loudspeakers' plane, the loudspeakers are coplanar within
    the noise and every microphone is put on the side of their majority (004's convention:
    microphones above their desk loudspeakers); if none, the same for loudspeakers through
    the microphones' plane. The side put in order
    (``"receivers"`` or ``"sources"``) is appended to ``sided``: their flips through the
    partners' plane are resolved by this stated rule, not by the data.
    """
    r, s = np.asarray(res.receivers, float), np.asarray(res.sources, float)
    rc, sc = np.asarray(res.receiver_cov, float), np.asarray(res.source_cov, float)
    u = res.uniqueness
    if u is None:
        return res
    on_r = _mirror_matches(r, np.asarray(u.receiver_alternatives, float), res.ambiguous_receivers, s)
    on_s = _mirror_matches(s, np.asarray(u.source_alternatives, float), res.ambiguous_sources, r)
    if on_r.any():
        r, rc, flipped = one_side_of_plane(r, rc, s)
        what, k = ("microphones", "loudspeakers"), int(on_r.sum())
    elif on_s.any():
        s, sc, flipped = one_side_of_plane(s, sc, r)
        what, k = ("loudspeakers", "microphones"), int(on_s.sum())
    else:
        return res
    notes.append(f"the {what[1]} are coplanar within the noise ({k} {what[0]}' mirror images through their plane fit "
                 f"as well: flip test, level 1e-3), so each {what[0][:-1]}'s side of their plane is not observable; "
                 f"all {what[0]} were put on one side ({flipped} reflected)")
    dr, ds = np.asarray(res.receiver_offsets, float), np.asarray(res.source_offsets, float)
    if flipped and all(np.isfinite(a).all() for a in (r, s, dr, ds)):
        res = _solve(T, 3, speed, rng, init=(r, s, dr, ds))
    elif flipped:  # nodes the solver dropped (NaN rows): no warm start; the refits polish the flipped ones
        from ..toa.frame.nodes import replace_fields

        res = replace_fields(res, receivers=r, sources=s, receiver_cov=rc, source_cov=sc)
    sided.append("receivers" if what[0] == "microphones" else "sources")
    return res


def _heights_fit(T: Array, heights: tuple[Array, Array], speed: float, rng: int,
                 weights: Array | None, units: NDArray[np.intp] | None = None) -> Calibration:
    """Known heights: :func:`refine_known_heights` from the better of two blind starts.

    The blind solves do not know the heights: the 2-D one (z ignored) and the 3-D one
    (z free, projected) are searches on different models and land in different basins when
    the matrix is sparse or holds a wrong detection. The 3-D start is tried only when the
    2-D one does not fit at the detections' stated noise (:func:`_fits_its_noise`). Each start is refined with the heights
    under a Cauchy loss (scale ``TUNING["cauchy"]`` = 2.385 stds, from ``weights``; least squares
    without them), the start whose robust cost ``sum log(1 + (z / 2.385)^2)`` is lower is kept and finished by
    (weighted) least squares; the outlier test of :func:`selfcal.acoustics.robust_fit.robust_calibrate` follows.
    """
    sd = None if weights is None else 1.0 / np.asarray(weights, float)
    f_sc = None if sd is None else TUNING["cauchy"] * float(np.nanmedian(sd[np.isfinite(sd)]))
    best: tuple[float, Calibration, Any] | None = None
    tried = 0
    for d in (2, 3):
        if d == 3 and best is not None and sd is not None and _fits_its_noise(best[0], T):
            break  # the 2-D start already fits at the detections' own noise: no second search
        try:
            init = _solve(T, d, speed, rng, units=units)
        except DegenerateGeometryError:
            continue
        tried += 1
        r0, s0, dr0, ds0 = _place_dropped(T, heights, np.asarray(init.receivers, float)[:, :2],
                                          np.asarray(init.sources, float)[:, :2],
                                          np.asarray(init.receiver_offsets, float),
                                          np.asarray(init.source_offsets, float), speed)
        dr, ds = _normalise_offsets(dr0, ds0)
        try:
            sol = refine_known_heights(T, heights[0], heights[1], r0, s0, dr, ds, speed=speed, f_scale=f_sc,
                                       weights=weights)
        except (DegenerateGeometryError, np.linalg.LinAlgError, ValueError):
            continue
        e = T - _predict(sol, speed)
        zz = e / (sd if sd is not None else float(np.nanstd(e)) or 1.0)
        cost = _cauchy_cost(zz)
        if np.isfinite(cost) and (best is None or cost < best[0]):
            best = (cost, sol, init)
    if not tried:
        raise DegenerateGeometryError("no blind start for the known-heights fit: the 2-D and 3-D solves both "
                                      "broke down", kind="unobservable-node")
    if best is None:
        raise DegenerateGeometryError("the known-heights fit broke down from every blind start", kind="unobservable-node")
    _, sol, init = best
    label = f"2d+heights ({init.method} init)"
    if f_sc is None:
        return replace(sol, method=label)
    return replace(refine_known_heights(T, heights[0], heights[1], sol.receivers[:, :2], sol.sources[:, :2],
                                        sol.receiver_offsets, sol.source_offsets, speed=speed, weights=weights),
                   method=label)


def _cauchy_cost(z: Array) -> float:
    """``sum rho((z / c)^2)`` of the Cauchy loss, ``c = TUNING["cauchy"]``, over the finite z (in stds)."""
    return float(np.nansum(loss_rho((z / TUNING["cauchy"]) ** 2, "cauchy")[0]))


@cache
def _cauchy_cost_moments() -> tuple[float, float]:
    """Mean and standard deviation of one term of :func:`_cauchy_cost` for ``z ~ N(0, 1)``.

    By quadrature (scipy.stats.norm.expect): 0.1447 and 0.1756 for ``c = 2.385``; the cost of
    a fit at its own noise is a sum of such i.i.d. terms.
    """
    from scipy.stats import norm

    def rho(z: float) -> float:
        return float(np.log1p((z / TUNING["cauchy"]) ** 2))

    mean = float(norm.expect(rho))
    second = float(norm.expect(lambda z: rho(z) ** 2))
    return mean, float(np.sqrt(second - mean**2))


def _fits_its_noise(cost: float, T: Array) -> bool:
    """Whether a robust (Cauchy) cost is that of a fit at the detections' stated noise.

    The cost of m residuals at their own stds is a sum of m i.i.d. terms under the noise
    model; it is accepted below its mean + 3.09 standard deviations (the one-sided 0.1 %
    quantile of the normal approximation). A wrong basin leaves whole rows and columns at
    many stds and exceeds it by orders of magnitude; then the 3-D start is also tried.
    """
    m = int(np.isfinite(T).sum())
    mean, std = _cauchy_cost_moments()
    return bool(np.isfinite(cost) and cost <= m * mean + 3.09 * np.sqrt(m) * std)


def _place_dropped(T: Array, heights: tuple[Array, Array], r: Array, s: Array, dr: Array, ds: Array,
                   speed: float) -> tuple[Array, Array, Array, Array]:
    """Start positions for the nodes a 2-D initial solve left out (NaN rows), from their own entries.

    ``solve_toa`` drops a node whose entries turned outliers or too few; the known-height
    refinement needs a start for every node that :func:`selfcal.acoustics.robust_fit.robust_calibrate` kept. Each such
    node is placed alone against the placed others: its offset in closed form (the mean
    residual), its horizontal position by the smallest residual variance on a grid over the
    others' extent, then refined by least squares (one node: 3 unknowns).
    """
    from scipy.optimize import least_squares

    r, s, dr, ds = r.copy(), s.copy(), dr.copy(), ds.copy()
    for side in (0, 1):
        own, other = (r, s) if side == 0 else (s, r)
        own_off, other_off = (dr, ds) if side == 0 else (ds, dr)
        M = T if side == 0 else T.T
        zo, zt = (heights[0], heights[1]) if side == 0 else (heights[1], heights[0])
        placed = np.isfinite(other).all(axis=1) & np.isfinite(other_off)
        for k in np.flatnonzero(~(np.isfinite(own).all(axis=1) & np.isfinite(own_off))):
            cols = np.isfinite(M[k]) & placed
            if cols.sum() < 3:
                continue
            y = speed * (M[k, cols] - other_off[cols])
            pts = other[cols]
            dz2 = (zo[k] - zt[cols]) ** 2

            def resid(p: Array, y: Array = y, pts: Array = pts, dz2: Array = dz2) -> Array:
                return y - np.sqrt(((pts - p[:2]) ** 2).sum(axis=1) + dz2) - p[2]

            lo, hi = other[placed].min(axis=0), other[placed].max(axis=0)
            gx, gy = np.meshgrid(np.linspace(lo[0], hi[0], 9), np.linspace(lo[1], hi[1], 9))
            grid = np.column_stack([gx.ravel(), gy.ravel()])
            dist = np.sqrt(((grid[:, None, :] - pts[None]) ** 2).sum(axis=-1) + dz2[None])
            best = grid[int(np.argmin(np.var(y[None] - dist, axis=1)))]
            off0 = float(np.mean(y - np.sqrt(((pts - best) ** 2).sum(axis=1) + dz2)))
            p = least_squares(resid, np.array([best[0], best[1], off0])).x
            own[k] = p[:2]
            own_off[k] = p[2] / speed
    return r, s, dr, ds


def _normalise_offsets(dr: Array, ds: Array) -> tuple[Array, Array]:
    """Shift the common offset so that the first onset is 0 (004 sec. 3.3, tau_1 = 0).

    The first *located* one: a loudspeaker the solver dropped has a NaN onset.
    """
    ok = np.flatnonzero(np.isfinite(ds))
    a = float(ds[ok[0]]) if ok.size else 0.0
    return dr + a, ds - a


def calibrate_matrix(
    T: Array,
    *,
    speed: float,
    dim: int | str = "auto",
    heights: tuple[Array, Array] | None = None,
    rng: int = 0,
    noise: float | None = None,
    weights: Array | None = None,
    units: NDArray[np.intp] | None = None,
) -> tuple[Calibration, Planarity | None, list[str]]:
    """Stages 2 + 3 of 004 on an (I, J) per-sender TOA matrix (seconds), one model fit.

    ``dim="auto"`` and ``dim=3`` fit the 3-D model and test it
    (:func:`selfcal.toa.verdict.select.dimension_test`: a 2-D fit refined from it, the F test
    of the two and the chi-square of the 3-D layout's out-of-plane coordinates against its
    covariances, both at level ``PLANAR_ALPHA`` = 1e-3). A near-planar layout, or a 3-D
    solve that breaks down while a 2-D one fits, is searched in 2-D and reported in 2-D
    (``dim="auto"``) or refused (``dim=3``).

    Parameters
    ----------
    T : (I, J) array
        ``t_ij = |r_i - s_j| / c + tau_j + delta_i``, s, NaN = missing.
    speed : float
        m/s.
    dim : 2, 3 or "auto"
        An explicit 3 on a near-planar layout raises.
    heights : (receiver heights (I,), sender heights (J,)), optional
        Known heights, m: 2-D initialisation, then :func:`refine_known_heights`; the
        result is 3-D with z = the given heights.
    rng : int
        Seed of the solver's random initialisations.
    noise : float, optional
        Timing-noise std, s: passed to :func:`selfcal.toa.solve_toa`, whose deep search then
        runs when a fit fails the residual test (slow; :func:`selfcal.acoustics.robust_fit.robust_calibrate` passes it only
        after the outliers are out).
    weights : (I, J) array, optional
        ``1 / std`` of every entry: weighted least squares in the known-heights refinement
        (:func:`refine_known_heights`); the 2-D / 3-D fits of :func:`selfcal.toa.solve_toa`
        take no weights and ignore them.
    units : (K, 2) int array, optional
        ``(receiver, sender)`` of the units (microphone and loudspeaker in one housing,
        :func:`selfcal.acoustics.units.unit_pairs`): the searches start from their two-way
        distances (:func:`selfcal.acoustics.units.unit_start`).

    Returns
    -------
    solution : Calibration
    planarity : Planarity or None
    notes : list of str

    Raises
    ------
    DegenerateGeometryError
        ``kind="near-planar"`` when ``dim=3`` is asked of a near-planar layout.
    """
    notes: list[str] = []
    if heights is not None:
        return _heights_fit(T, heights, speed, rng, weights, units), None, notes
    if dim not in (2, 3, "auto"):
        raise InputError(f"dim must be 2, 3 or 'auto', got {dim!r}")
    if dim == 2:
        return _as_solution(_solve(T, 2, speed, rng, noise=noise, units=units), "2d", 2), None, notes
    advice = "give known heights (--heights) for 3-D positions or use --dim 2"
    try:
        res3 = _solve_retrying(T, speed, rng, noise=noise, units=units)
    except DegenerateGeometryError as exc:
        if dim == 3:
            raise
        res2 = _try_solve(T, 2, speed, rng, noise=noise, units=units)
        # A 3-D solve that breaks down on data a 2-D solve fits (within half the 004
        # timing tolerance) means the layout is (numerically) planar.
        if res2 is None or not res2.residual_rms < 0.5 * TIMING_REQUIREMENT:
            raise
        pts2 = np.vstack([res2.receivers, res2.sources])
        plan = Planarity(True, np.append(planarity(pts2).extents, 0.0), np.array([0.0, 0.0, 1.0]), float("nan"))
        msg = (f"near-planar layout: the 3-D calibration is undetermined ({exc}) while a 2-D one fits "
               f"(residual {res2.residual_rms * 1e6:.2f} us); z is not determined by the data, {advice}")
        return _planar_verdict(res2, plan, msg, dim, notes)
    sided: list[str] = []
    res3 = _resolve_mirrors(T, res3, speed, rng, notes, sided)
    keep3, plan, _, stats, wide3 = dimension_test(T, res3, "both", _toa_solver(rng), _toa_options(speed, noise))
    if keep3:
        sol = _as_solution(wide3, "3d", 3, one_side=sided[0] if sided else None)
        if stats.get("bars_widened"):
            # the bootstrap's mean-square error (dimension_test) stays on through the refits
            n_r = len(res3.receivers)
            extra = np.concatenate([np.asarray(wide3.receiver_cov) - np.asarray(res3.receiver_cov),
                                    np.asarray(wide3.source_cov) - np.asarray(res3.source_cov)])
            sol = replace(sol, extra_cov=(extra[:n_r], extra[n_r:]))
        cov = np.concatenate([np.asarray(sol.receiver_cov), np.asarray(sol.source_cov)])
        notes.append(_z_note(cov, plan.comparison))
        if stats.get("bars_widened"):
            notes.append(stats["bars_note"])
        return sol, plan, notes
    cmp = plan.comparison
    why = ("" if cmp is None else f"3-D vs 2-D F = {cmp.f_statistic:.3g}, p = {cmp.p_value:.2g}; ")
    msg = (f"near-planar layout (thickness {plan.extents[-1]:.3f} m vs extent {plan.extents[0]:.2f} m, "
           f"{why}thickness chi-square p = {plan.thickness_p:.2g}; level {PLANAR_ALPHA:g}): "
           f"z is not determined by the data; {advice}")
    if dim == 3:
        raise DegenerateGeometryError(msg, kind="near-planar")
    res2 = _solve(T, 2, speed, rng, noise=noise, units=units)
    return _planar_verdict(res2, plan, msg, dim, notes)


def _toa_solver(rng: int) -> Any:
    """:func:`selfcal.toa.solve_toa` in the ``solve(M, dim, offsets, opts, init=...)`` form of
    :func:`selfcal.toa.verdict.select.dimension_test` (every call seeded with ``rng``)."""
    from ..toa.solve import solve_toa

    def solve(M: Array, dim: int, offsets: str, opts: Any, init: Any = "auto") -> Any:
        if not isinstance(init, str) and opts.speed is not None:
            # the choice's starts carry offsets in metres (its own solver's form); solve_toa
            # takes them in the matrix's units (seconds here)
            r0, s0, d0, o0 = init
            init = (r0, s0, None if d0 is None else d0 / opts.speed, None if o0 is None else o0 / opts.speed)
        return solve_toa(M, dim=dim, offsets=offsets, speed=opts.speed, rng=rng, noise=opts.noise,
                         method=opts.method, init=init)

    return solve


def _toa_options(speed: float, noise: float | None) -> Any:
    """The options :func:`_toa_solver` reads (speed, noise: the user's units, as
    :func:`selfcal.toa.solve_toa` takes them; method "auto"), the rest at solve_toa's defaults."""
    from ..toa.options import ToaOptions

    return ToaOptions(speed=speed, loss="auto", method="auto", rng=np.random.default_rng(0), f_scale=None,
                      max_nfev=None, covariance=True, sweep=True, noise=noise, budget=None)


def _planar_verdict(res2: Any, plan: Planarity, msg: str, dim: int | str,
                    notes: list[str]) -> tuple[Calibration, Planarity, list[str]]:
    """Raise for an explicit ``dim=3``; otherwise warn and report the 2-D solution."""
    if dim == 3:
        raise DegenerateGeometryError(msg, kind="near-planar")
    warnings.warn(msg + "; reporting 2-D positions", stacklevel=3)
    notes.append(msg + "; reported 2-D positions")
    return _as_solution(res2, "2d", 2), plan, notes


def _z_note(cov: NDArray[np.float64], cmp: ModelComparison | None) -> str:
    """The z uncertainty of a kept 3-D answer, from its covariances (1 sigma)."""
    zvar = cov[:, 2, 2]
    zstd = np.sqrt(zvar[np.isfinite(zvar) & (zvar >= 0)])
    why = ("" if cmp is None else
           f"3-D fits significantly better than 2-D (F = {cmp.f_statistic:.3g}, p = {cmp.p_value:.2g}); ")
    if not zstd.size:
        return why + "z standard deviations are not available"
    return why + f"z standard deviation median {np.median(zstd) * 1e3:.2g} mm, max {zstd.max() * 1e3:.2g} mm"


def _try_solve(T: Array, dim: int, speed: float, rng: int, noise: float | None = None,
               units: NDArray[np.intp] | None = None) -> Any:
    try:
        return _solve(T, dim, speed, rng, noise=noise, units=units)
    except DegenerateGeometryError:
        return None


def _toa_outliers(res: Any, shape: tuple[int, int]) -> NDArray[np.bool_]:
    """The (I, J) mask of entries :func:`selfcal.toa.solve_toa`'s outlier rule excluded."""
    mask = res.outliers
    if mask is None or np.shape(mask) != tuple(shape):
        return np.zeros(shape, bool)
    return np.asarray(mask, bool)


def _as_solution(res: Any, label: str, dim: int, *, method: str | None = None,
                 one_side: str | None = None) -> Calibration:
    """A :class:`Calibration` of a :func:`selfcal.toa.solve_toa` result (offsets normalised);
    ``method`` (default ``"{label} ({res.method})"``) overrides the label."""
    dr, ds = _normalise_offsets(np.asarray(res.receiver_offsets, float), np.asarray(res.source_offsets, float))
    return Calibration(
        toa_outliers=_toa_outliers(res, (len(res.receivers), len(res.sources))),
        receivers=np.asarray(res.receivers, float), sources=np.asarray(res.sources, float),
        receiver_offsets=dr, source_offsets=ds,
        receiver_cov=np.asarray(res.receiver_cov, float), source_cov=np.asarray(res.source_cov, float),
        residual_rms=float(res.residual_rms), converged=bool(res.converged),
        iterations=int(res.iterations), method=f"{label} ({res.method})" if method is None else method, dim=dim,
        # the TOA solver's own tests (selfcal.toa.verdict.uniqueness, outlier breakdown) for the verdict
        uniqueness=res.uniqueness, outlier_breakdown=res.outlier_breakdown, one_side=one_side,
    )


def refit(T: Array, sol: Calibration, speed: float, heights: tuple[Array, Array] | None = None, *,
          f_scale: float | None = None, weights: Array | None = None) -> Calibration:
    """Refine a solution on a changed TOA matrix from where it stands (same model, no search).

    Parameters
    ----------
    T : (I, J) array
        s, NaN = missing.
    sol : Calibration
        A solution of :func:`calibrate_matrix` (its ``dim`` and ``known_heights`` name the model).
    speed : float
        m/s.
    heights : optional
        Known heights when ``sol`` is a ``2d+heights`` solution.
    f_scale : float, optional
        s: a Cauchy loss of this scale (robust start for the outlier test; covariances of
        such a refit are not computed).
    weights : (I, J) array, optional
        ``1 / std`` per entry (known-heights model only, as :func:`calibrate_matrix`).

    Returns
    -------
    Calibration
        The refined solution, same model and label.
    """
    r, s = np.asarray(sol.receivers, float), np.asarray(sol.sources, float)
    dr, ds = np.asarray(sol.receiver_offsets, float), np.asarray(sol.source_offsets, float)
    if sol.known_heights:
        assert heights is not None
        return replace(refine_known_heights(T, heights[0], heights[1], r[:, :2], s[:, :2], dr, ds, speed=speed,
                                            f_scale=f_scale, weights=weights), method=sol.method)
    d = sol.dim
    kr = np.isfinite(r[:, :d]).all(axis=1) & np.isfinite(dr)
    ks = np.isfinite(s[:, :d]).all(axis=1) & np.isfinite(ds)
    if kr.sum() < d + 1 or ks.sum() < d + 1:
        raise DegenerateGeometryError(f"the fit kept {int(kr.sum())} microphones and {int(ks.sum())} loudspeakers: "
                                      f"too few for a {d}-D refinement", kind="unobservable-node")
    if not (kr.all() and ks.all()):
        # nodes the solver dropped (e.g. more flagged ranges than a position can hold) stay
        # dropped: the others are refined from where they stand
        sub = refit(T[np.ix_(kr, ks)], replace(sol, receivers=r[kr], sources=s[ks], receiver_offsets=dr[kr],
                                               source_offsets=ds[ks], extra_cov=None), speed, f_scale=f_scale)
        return _with_extra(_scatter_nodes(sub, kr, ks, outliers=True), sol.extra_cov)
    res = _solve(T, d, speed, 0, init=(r[:, :d], s[:, :d], dr, ds), f_scale=f_scale)
    return _with_extra(_as_solution(res, "", d, method=sol.method, one_side=sol.one_side), sol.extra_cov)


def _with_extra(sol: Calibration, extra: tuple[Array, Array] | None) -> Calibration:
    """``sol`` with ``extra`` (the covariance a refit does not recompute: the bootstrap's
    mean-square error of :func:`calibrate_matrix`'s 3-D answer) added back and kept."""
    if extra is None or np.shape(extra[0]) != np.shape(sol.receiver_cov) or np.shape(extra[1]) != np.shape(sol.source_cov):
        return sol
    return replace(sol, receiver_cov=np.asarray(sol.receiver_cov, float) + extra[0],
                   source_cov=np.asarray(sol.source_cov, float) + extra[1], extra_cov=extra)


def _scatter_nodes(sol: Calibration, kr: NDArray[np.bool_], ks: NDArray[np.bool_], *,
                   outliers: bool = False) -> Calibration:
    """A solution on the kept nodes at full size: NaN rows for the others (with ``outliers``, a
    full-size outlier mask too); the uniqueness verdict in the full numbering."""
    I, J = len(kr), len(ks)

    def full(a: Array, keep: NDArray[np.bool_]) -> Array:
        a = np.asarray(a, float)
        out = np.full((len(keep),) + a.shape[1:], np.nan)
        out[keep] = a
        return out

    mask = sol.toa_outliers
    if outliers:
        mask = np.zeros((I, J), bool)
        mask[np.ix_(kr, ks)] = np.asarray(sol.toa_outliers, bool)
    u = sol.uniqueness
    if u is not None and len(u.ambiguous_receivers) == int(kr.sum()):
        u = u.relabel(kr, ks, np.arange(I), np.arange(J))
    return replace(sol, receivers=full(sol.receivers, kr), sources=full(sol.sources, ks),
                   receiver_offsets=full(sol.receiver_offsets, kr), source_offsets=full(sol.source_offsets, ks),
                   receiver_cov=full(sol.receiver_cov, kr), source_cov=full(sol.source_cov, ks), toa_outliers=mask,
                   uniqueness=u)


def sender_matrix(toa: Array, event_senders: NDArray[np.int64], n_senders: int) -> Array:
    """Average the (I, E) event TOA matrix into an (I, J) per-sender matrix (NaN-aware).

    Events of one sender share its position and onset, so their TOAs (relative to their
    nominal times) estimate the same ``t_ij``; the mean lowers the noise.
    """
    I = toa.shape[0]
    out = np.full((I, n_senders), np.nan)
    for j in range(n_senders):
        cols = toa[:, event_senders == j]
        if cols.shape[1]:
            cnt = np.isfinite(cols).sum(axis=1)
            total = np.nansum(cols, axis=1)
            out[:, j] = np.where(cnt > 0, total / np.maximum(cnt, 1), np.nan)
    return out


def n_parameters_of(sol: Calibration, I: int, J: int) -> int:
    """Free parameters of a solution's model (gauge removed): coordinates plus I + J - 1 offsets.

    ``2d+heights``: 2 (I + J) horizontal coordinates less 3 (planar rigid motion); ``2d``
    likewise; 3-D: 3 (I + J) less 6.
    """
    return n_parameters(I, J, sol.dim, "both")


def _predict(sol: Calibration | PipelineResult, speed: float) -> Array:
    """The model TOA matrix ``|r_i - s_j| / c + delta_i + tau_j`` (004 eq. 3.1) of a solution, s."""
    r, s = np.asarray(sol.receivers, float), np.asarray(sol.sources, float)
    return (np.linalg.norm(r[:, None, :] - s[None, :, :], axis=-1) / speed
            + np.asarray(sol.receiver_offsets, float)[:, None] + np.asarray(sol.source_offsets, float)[None, :])
