"""Stages 2 + 3 of 004 on the TOA matrix: onsets, internal delays and positions, robustly.

The per-sender TOA matrix ``t_ij = |r_i - s_j| / c + tau_j + delta_i`` (004 eq. 3.1) goes to
:func:`selfcal.toa.solve_toa` with ``offsets="both"``. Around it:

- **one model fit by default**: 3-D (or 2-D / 2-D with known heights when asked). With
  ``dim="auto"`` the 3-D fit's own geometry and covariances decide whether z is resolved
  (:func:`selfcal.acoustics.geometry.planarity`); only a near-planar verdict (or a 3-D
  breakdown) fits the 2-D model as well.
- **robust to a minority of wrong detections** (:func:`robust_calibrate`): after a fit the
  residual of every detection is standardised by its noise model
  (:mod:`selfcal.acoustics.noise`) and by ``sqrt(1 - p / m)`` (the mean leverage); a
  residual beyond the Bonferroni bound ``Phi^-1(1 - alpha / (2 m))`` (``alpha`` = 1 %
  family-wise) that is the largest of its receiver and of its sender is an outlier. It is
  excluded (or re-detected in a narrow window around its predicted time), and the fit is
  refined from where it stands; repeated until no outlier is left.
- **units without enough detections are dropped** (fewer than ``d + 2`` senders for a
  receiver or receivers for a sender: not identifiable with a check left), with a note,
  and the rest are calibrated.

Length (671 lines, above the ~600 guideline): the robust per-round flow (screening, 2-D /
3-D verdict, known heights, mirror resolution) is one pipeline stage whose steps share the
solver state.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..errors import DegenerateGeometryError, InputError
from ..robust import mad_std
from .geometry import (
    PLANAR_ALPHA,
    ModelComparison,
    Planarity,
    one_side_of_plane,
    planarity,
    refine_known_heights,
)
from .verdict import TIMING_REQUIREMENT

__all__ = ["calibrate_matrix", "refit", "robust_calibrate", "sender_matrix", "Outlier", "RobustFit", "OUTLIER_ALPHA",
           "n_parameters_of"]

Array = NDArray[np.float64]
OUTLIER_ALPHA = 0.01  # family-wise false-alarm probability of the outlier test over all detections
MAX_OUTLIER_ROUNDS = 12


def _solve(T: Array, dim: int, speed: float, rng: int, init: Any = "auto", noise: float | None = None,
           f_scale: float | None = None) -> Any:
    try:
        from ..toa import solve_toa
    except ImportError:  # the package re-export may lag behind the module
        from ..toa.solve import solve_toa

    if isinstance(init, str):
        return solve_toa(T, dim=dim, offsets="both", speed=speed, rng=rng, noise=noise)
    if f_scale is not None:
        return solve_toa(T, dim=dim, offsets="both", speed=speed, rng=rng, init=init, method="nls",
                         loss="cauchy", f_scale=f_scale, covariance=False)
    return solve_toa(T, dim=dim, offsets="both", speed=speed, rng=rng, init=init, method="nls")


def _solve_retrying(T: Array, speed: float, rng: int, attempts: int = 3, noise: float | None = None) -> Any:
    """3-D solve; a node that turns unobservable on the way (e.g. a microphone crossing the
    plane of coplanar loudspeakers during the iterations) gets new random starts."""
    for k in range(attempts):
        try:
            return _solve(T, 3, speed, rng + 1000 * k, noise=noise)
        except DegenerateGeometryError as exc:
            if exc.kind != "unobservable-node" or k == attempts - 1:
                raise
    raise AssertionError("unreachable")  # pragma: no cover


def _resolve_mirrors(T: Array, res: Any, speed: float, rng: int, notes: list[str]) -> Any:
    """Apply :func:`one_side_of_plane` when receivers or senders alone are (near-)coplanar."""
    r, s = np.asarray(res.receivers, float), np.asarray(res.sources, float)
    rc, sc = np.asarray(res.receiver_cov, float), np.asarray(res.source_cov, float)
    flipped = 0
    if planarity(s, sc).near_planar and not planarity(r, rc).near_planar:
        r, rc, flipped = one_side_of_plane(r, rc, s)
        what = "microphones", "loudspeakers"
    elif planarity(r, rc).near_planar and not planarity(s, sc).near_planar:
        s, sc, flipped = one_side_of_plane(s, sc, r)
        what = "loudspeakers", "microphones"
    else:
        return res
    notes.append(f"the {what[1]} are coplanar, so each {what[0][:-1]}'s side of their plane is not observable; "
                 f"all {what[0]} were put on one side ({flipped} reflected)")
    if flipped == 0:
        return res
    return _solve(T, 3, speed, rng, init=(r, s, np.asarray(res.receiver_offsets), np.asarray(res.source_offsets)))


def _place_dropped(T: Array, heights: tuple[Array, Array], r: Array, s: Array, dr: Array, ds: Array,
                   speed: float) -> tuple[Array, Array, Array, Array]:
    """Start positions for the nodes a 2-D initial solve left out (NaN rows), from their own entries.

    ``solve_toa`` drops a node whose entries turned outliers or too few; the known-height
    refinement needs a start for every node that :func:`robust_calibrate` kept. Each such
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
    """Shift the common offset so that the first onset is 0 (004 sec. 3.3, tau_1 = 0)."""
    a = float(ds[0])
    return dr + a, ds - a


def calibrate_matrix(
    T: Array,
    *,
    speed: float,
    dim: int | str = "auto",
    heights: tuple[Array, Array] | None = None,
    rng: int = 0,
    alpha: float = PLANAR_ALPHA,
    noise: float | None = None,
) -> tuple[dict[str, Any], Planarity | None, list[str]]:
    """Stages 2 + 3 of 004 on an (I, J) per-sender TOA matrix (seconds), one model fit.

    ``dim=3`` fits the 3-D model only. ``dim="auto"`` fits it and checks its own geometry
    and covariances (:func:`planarity`: thinnest extent below 1 % of the widest or below 3
    standard deviations along the normal); only a near-planar layout, or a 3-D solve that
    breaks down while a 2-D one fits, is solved in 2-D as well and reported in 2-D.

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
    alpha : float
        Unused (kept for the former F-test signature).
    noise : float, optional
        Timing-noise std, s: passed to :func:`selfcal.toa.solve_toa`, whose deep search then
        runs when a fit fails the residual test (slow; :func:`robust_calibrate` passes it only
        after the outliers are out).

    Returns
    -------
    solution : dict
        Keys of :func:`refine_known_heights` plus ``method`` and ``receiver_offset_std`` /
        ``source_offset_std`` when available.
    planarity : Planarity or None
    notes : list of str

    Raises
    ------
    DegenerateGeometryError
        ``kind="near-planar"`` when ``dim=3`` is asked of a near-planar layout.
    """
    notes: list[str] = []
    if heights is not None:
        init = _solve(T, 2, speed, rng)
        r0, s0, dr0, ds0 = _place_dropped(T, heights, np.asarray(init.receivers, float), np.asarray(init.sources, float),
                                          np.asarray(init.receiver_offsets, float), np.asarray(init.source_offsets, float),
                                          speed)
        dr, ds = _normalise_offsets(dr0, ds0)
        sol = refine_known_heights(T, heights[0], heights[1], r0, s0, dr, ds, speed=speed)
        sol["method"] = f"2d+heights ({init.method} init)"
        return sol, None, notes
    if dim not in (2, 3, "auto"):
        raise InputError(f"dim must be 2, 3 or 'auto', got {dim!r}")
    if dim == 2:
        return _as_solution(_solve(T, 2, speed, rng, noise=noise), "2d"), None, notes
    advice = "give known heights (--heights) for 3-D positions or use --dim 2"
    try:
        res3 = _solve_retrying(T, speed, rng, noise=noise)
    except DegenerateGeometryError as exc:
        if dim == 3:
            raise
        res2 = _try_solve(T, 2, speed, rng, noise=noise)
        # A 3-D solve that breaks down on data a 2-D solve fits (within half the 004
        # timing tolerance) means the layout is (numerically) planar.
        if res2 is None or not res2.residual_rms < 0.5 * TIMING_REQUIREMENT:
            raise
        pts2 = np.vstack([res2.receivers, res2.sources])
        plan = Planarity(True, np.append(planarity(pts2).extents, 0.0), np.array([0.0, 0.0, 1.0]), float("nan"))
        msg = (f"near-planar layout: the 3-D calibration is undetermined ({exc}) while a 2-D one fits "
               f"(residual {res2.residual_rms * 1e6:.2f} us); z is not determined by the data, {advice}")
        return _planar_verdict(res2, plan, msg, dim, notes)
    res3 = _resolve_mirrors(T, res3, speed, rng, notes)
    pts = np.vstack([res3.receivers, res3.sources])
    cov = np.concatenate([np.asarray(res3.receiver_cov), np.asarray(res3.source_cov)])
    plan = planarity(pts, cov)
    if not plan.near_planar:
        notes.append(_z_note(cov, None))
        return _as_solution(res3, "3d"), plan, notes
    msg = (f"near-planar layout (thickness {plan.extents[-1]:.3f} m vs extent {plan.extents[0]:.2f} m, "
           f"normal std {plan.normal_std:.3f} m): z is not determined by the data; {advice}")
    if dim == 3:
        raise DegenerateGeometryError(msg, kind="near-planar")
    res2 = _solve(T, 2, speed, rng, noise=noise)
    return _planar_verdict(res2, plan, msg, dim, notes)


def _planar_verdict(res2: Any, plan: Planarity, msg: str, dim: int | str,
                    notes: list[str]) -> tuple[dict[str, Any], Planarity, list[str]]:
    """Raise for an explicit ``dim=3``; otherwise warn and report the 2-D solution."""
    if dim == 3:
        raise DegenerateGeometryError(msg, kind="near-planar")
    warnings.warn(msg + "; reporting 2-D positions", stacklevel=3)
    notes.append(msg + "; reported 2-D positions")
    return _as_solution(res2, "2d"), plan, notes


def _z_note(cov: NDArray[np.float64], cmp: ModelComparison | None) -> str:
    """The z uncertainty of a kept 3-D answer, from its covariances (1 sigma)."""
    zvar = cov[:, 2, 2]
    zstd = np.sqrt(zvar[np.isfinite(zvar) & (zvar >= 0)])
    why = ("" if cmp is None else
           f"3-D fits significantly better than 2-D (F = {cmp.f_statistic:.3g}, p = {cmp.p_value:.2g}); ")
    if not zstd.size:
        return why + "z standard deviations are not available"
    return why + f"z standard deviation median {np.median(zstd) * 1e3:.2g} mm, max {zstd.max() * 1e3:.2g} mm"


def _try_solve(T: Array, dim: int, speed: float, rng: int, noise: float | None = None) -> Any:
    try:
        return _solve(T, dim, speed, rng, noise=noise)
    except DegenerateGeometryError:
        return None


def _refit_from_planar(T: Array, res2: Any, speed: float, rng: int) -> Any:
    """3-D refinement started from the 2-D solution lifted to z = small random heights.

    Exactly in the plane the out-of-plane gradient is zero, so the start is lifted by a
    random z of 1 % of the layout's extent; a thick network then leaves the plane, a flat
    one stays or turns unobservable (None).
    """
    pts = np.vstack([res2.receivers, res2.sources])
    scale = 0.01 * float(np.ptp(pts, axis=0).max() or 1.0)
    g = np.random.default_rng(rng)
    lift = [np.column_stack([a, g.normal(0.0, scale, len(a))]) for a in (res2.receivers, res2.sources)]
    try:
        return _solve(T, 3, speed, rng, init=(lift[0], lift[1], np.asarray(res2.receiver_offsets),
                                                np.asarray(res2.source_offsets)))
    except DegenerateGeometryError:
        return None


def _as_solution(res: Any, label: str) -> dict[str, Any]:
    dr, ds = _normalise_offsets(np.asarray(res.receiver_offsets, float), np.asarray(res.source_offsets, float))
    return {
        "receivers": np.asarray(res.receivers, float), "sources": np.asarray(res.sources, float),
        "receiver_offsets": dr, "source_offsets": ds,
        "receiver_cov": np.asarray(res.receiver_cov, float), "source_cov": np.asarray(res.source_cov, float),
        "residual_rms": float(res.residual_rms), "converged": bool(res.converged),
        "iterations": int(getattr(res, "iterations", 0)), "method": f"{label} ({res.method})",
    }


def refit(T: Array, sol: dict[str, Any], speed: float, heights: tuple[Array, Array] | None = None, *,
          f_scale: float | None = None) -> dict[str, Any]:
    """Refine a solution on a changed TOA matrix from where it stands (same model, no search).

    Parameters
    ----------
    T : (I, J) array
        s, NaN = missing.
    sol : dict
        A solution of :func:`calibrate_matrix` (its ``method`` label names the model).
    speed : float
        m/s.
    heights : optional
        Known heights when ``sol`` is a ``2d+heights`` solution.
    f_scale : float, optional
        s: a Cauchy loss of this scale (robust start for the outlier test; covariances of
        such a refit are not computed for 2-D / 3-D).

    Returns
    -------
    dict
        The refined solution, same keys and label.
    """
    method = str(sol["method"])
    r, s = np.asarray(sol["receivers"], float), np.asarray(sol["sources"], float)
    dr, ds = np.asarray(sol["receiver_offsets"], float), np.asarray(sol["source_offsets"], float)
    if method.startswith("2d+heights"):
        assert heights is not None
        out = refine_known_heights(T, heights[0], heights[1], r[:, :2], s[:, :2], dr, ds, speed=speed,
                                   f_scale=f_scale)
        out["method"] = method
        return out
    d = 2 if method.startswith("2d") else 3
    res = _solve(T, d, speed, 0, init=(r[:, :d], s[:, :d], dr, ds), f_scale=f_scale)
    out = _as_solution(res, "")
    out["method"] = method
    return out


@dataclass(frozen=True)
class Outlier:
    """A detection the robust fit excluded (or re-detected).

    Attributes
    ----------
    receiver, event, sender : int
        Indices (rows of the TOA matrix, events of setup.json, senders).
    residual : float
        Detected minus modelled TOA, s.
    z : float
        Residual over its standard deviation (noise model and leverage).
    redetected : bool
        A new detection near the predicted time replaced it.
    new_residual : float
        Residual of the replacement, s (NaN when not re-detected).
    """

    receiver: int
    event: int
    sender: int
    residual: float
    z: float
    redetected: bool = False
    new_residual: float = float("nan")

    def to_dict(self) -> dict[str, Any]:
        """JSON-safe dictionary."""
        return {"receiver": self.receiver, "event": self.event, "sender": self.sender, "residual": self.residual,
                "z": self.z, "redetected": self.redetected, "new_residual": self.new_residual}


@dataclass(frozen=True)
class RobustFit:
    """Outcome of :func:`robust_calibrate`.

    Attributes
    ----------
    solution : dict
        Full-size solution (dropped units' rows NaN).
    planarity : Planarity or None
    notes : list of str
    outliers : list of Outlier
    toa : (I, E) array
        The event TOA matrix after exclusions / re-detections, s.
    matrix, matrix_std : (I, J) arrays
        Per-sender TOA matrix and its std, s (dropped units NaN).
    dropped_receivers, dropped_senders : list of int
    threshold : float
        Bonferroni bound on |z| used.
    std : (I, E) array
        Detection stds after re-detections, s.
    n_params : int
        Free parameters of the kept model.
    """

    solution: dict[str, Any]
    planarity: Planarity | None
    notes: list[str]
    outliers: list[Outlier]
    toa: Array
    matrix: Array
    matrix_std: Array
    dropped_receivers: list[int]
    dropped_senders: list[int]
    threshold: float
    std: Array
    n_params: int


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


def _drop_units(T: Array, need: int) -> tuple[NDArray[np.bool_], NDArray[np.bool_]]:
    """Receivers / senders kept: at least ``need`` observations among the kept others (iterated)."""
    kr = np.ones(T.shape[0], bool)
    ks = np.ones(T.shape[1], bool)
    obs = np.isfinite(T)
    while True:
        sub = obs & kr[:, None] & ks[None, :]
        nr = kr & (sub.sum(axis=1) >= need)
        ns = ks & (sub.sum(axis=0) >= need)
        if (nr == kr).all() and (ns == ks).all():
            return kr, ks
        kr, ks = nr, ns


def _scatter(sol: dict[str, Any], kr: NDArray[np.bool_], ks: NDArray[np.bool_]) -> dict[str, Any]:
    """Full-size solution with NaN rows for the dropped units."""
    I, J = len(kr), len(ks)
    out = dict(sol)
    for key, keep, n in (("receivers", kr, I), ("sources", ks, J), ("receiver_offsets", kr, I),
                         ("source_offsets", ks, J), ("receiver_cov", kr, I), ("source_cov", ks, J),
                         ("receiver_offset_std", kr, I), ("source_offset_std", ks, J)):
        if key not in sol or sol[key] is None:
            continue
        a = np.asarray(sol[key], float)
        full = np.full((n,) + a.shape[1:], np.nan)
        full[keep] = a
        out[key] = full
    return out


def robust_calibrate(
    toa: Array,
    std: Array,
    event_senders: NDArray[np.int64],
    n_senders: int,
    *,
    speed: float,
    dim: int | str = "auto",
    heights: tuple[Array, Array] | None = None,
    rng: int = 0,
    noise: float | None = None,
    redetect: Callable[[NDArray[np.intp], NDArray[np.intp], Array, Array], tuple[Array, Array]] | None = None,
    alpha: float = OUTLIER_ALPHA,
    names: tuple[tuple[str, ...], tuple[str, ...]] | None = None,
) -> RobustFit:
    """Calibrate from the event TOA matrix with outlier exclusion and unit dropping (module docstring).

    Parameters
    ----------
    toa : (I, E) array
        Detected TOA of every event (arrival minus nominal time), s, NaN = missed.
    std : (I, E) array
        Noise-model std of every detection, s (:func:`selfcal.acoustics.noise.detection_std`).
    event_senders : (E,) int array
    n_senders : int
    speed : float
        m/s.
    dim, heights, rng :
        As :func:`calibrate_matrix`.
    noise : float, optional
        Timing-noise std of the residual test, s; when the cleaned fit fails that test the
        deep search of :func:`selfcal.toa.solve_toa` runs once on the cleaned matrix.
    redetect : callable, optional
        ``redetect(receivers, events, predicted_toa, half_width) -> (toa, std)`` (NaN =
        nothing acceptable): a new detection of an outlier near its predicted time.
    alpha : float
        Family-wise false-alarm probability of the outlier test.
    names : (receiver names, sender names), optional
        For the notes.

    Returns
    -------
    RobustFit

    Raises
    ------
    DegenerateGeometryError
        Fewer than ``d + 2`` units left on one side (``kind="unobservable-node"``), or as
        :func:`calibrate_matrix`.
    """
    from scipy.stats import norm

    toa = np.array(toa, dtype=float)
    std = np.asarray(std, float)
    es = np.asarray(event_senders, dtype=np.int64)
    I, E = toa.shape
    J = int(n_senders)
    rn, sn = names if names is not None else (tuple(f"#{i}" for i in range(I)), tuple(f"#{j}" for j in range(J)))
    d_model = 2 if (dim == 2 or heights is not None) else 3
    need = d_model + 2
    notes: list[str] = []
    T = sender_matrix(toa, es, J)
    kr, ks = _drop_units(T, need)
    if kr.sum() < need or ks.sum() < need:
        raise DegenerateGeometryError(
            f"only {int(kr.sum())} receivers and {int(ks.sum())} senders have >= {need} detections each; "
            "too few to calibrate (check levels, cabling and the event times)", kind="unobservable-node")
    dropped_r = [int(i) for i in np.flatnonzero(~kr)]
    dropped_s = [int(j) for j in np.flatnonzero(~ks)]
    for i in dropped_r:
        notes.append(f"dropped microphone {rn[i]}: {int(np.isfinite(T[i]).sum())} of {J} senders detected "
                     f"(need {need}); dead, disconnected or silent input")
    for j in dropped_s:
        notes.append(f"dropped loudspeaker {sn[j]}: heard by {int(np.isfinite(T[:, j]).sum())} of {I} "
                     f"microphones (need {need}); silent, or its events are missing from the audio")
    hz = None if heights is None else (np.asarray(heights[0])[kr], np.asarray(heights[1])[ks])
    ev_keep = ks[es]
    sub_es = np.cumsum(ks)[es] - 1  # sender index within the kept senders
    t_ev = toa[np.ix_(kr, ev_keep)]
    s_ev = std[np.ix_(kr, ev_keep)]
    es_k = sub_es[ev_keep]
    Jk = int(ks.sum())
    Tk = sender_matrix(t_ev, es_k, Jk)
    sol, plan, cnotes = calibrate_matrix(Tk, speed=speed, dim=dim, heights=hz, rng=rng)
    notes.extend(cnotes)
    n_par = n_parameters_of(sol, len(Tk), Jk)
    ri_full = np.flatnonzero(kr)
    ev_full = np.flatnonzero(ev_keep)
    outliers: list[Outlier] = []
    m = int(np.isfinite(t_ev).sum())
    zc = float(norm.isf(alpha / (2.0 * max(m, 1))))
    searched = False
    robust_start = False
    needs_ls = False
    for _ in range(MAX_OUTLIER_ROUNDS + 1):
        pred = _predict(sol, speed)
        res = t_ev - pred[:, es_k]
        m = int(np.isfinite(res).sum())
        lev = np.sqrt(max(1.0 - n_par / max(m, 1), 1e-3))
        z = res / (s_ev * lev)
        scale = max(1.0, mad_std(z, centre=False)) if np.isfinite(z).any() else 1.0
        z = z / scale
        az = np.where(np.isfinite(z), np.abs(z), 0.0)
        # the largest of its receiver and of its sender: one bad entry does not take its neighbours along
        sender_max = np.zeros((az.shape[0], Jk))
        for j in range(Jk):
            cols = es_k == j
            if cols.any():
                sender_max[:, j] = az[:, cols].max(axis=1)
        worst_in_sender = sender_max.max(axis=0)
        if not robust_start and (az > zc).any():
            # a wrong entry pulls a least-squares fit towards itself and spreads its error over
            # its receiver's and sender's other entries (masking): restart from a Cauchy fit
            # (scale 2.385 stds: 95 % efficiency under Gaussian noise), then rank the residuals
            robust_start = True
            try:
                f_sc = 2.385 * float(np.nanmedian(s_ev)) * scale
                sol = refit(Tk, sol, speed, hz, f_scale=f_sc)
                needs_ls = True
                continue
            except DegenerateGeometryError:
                pass
        flag = (az > zc) & (az >= az.max(axis=1, keepdims=True)) & (az >= worst_in_sender[es_k][None, :])
        # never below the identifiability bound
        cnt_r = np.isfinite(Tk).sum(axis=1)
        cnt_s = np.isfinite(Tk).sum(axis=0)
        fi, fe = np.nonzero(flag)
        ok = []
        for a, b in zip(fi, fe, strict=True):
            last = np.isfinite(t_ev[a, es_k == es_k[b]]).sum() == 1
            if last and (cnt_r[a] <= need or cnt_s[es_k[b]] <= need):
                continue
            ok.append((a, b))
        if not ok:
            if searched or noise is None:
                break
            # outliers are out: one deep search if the cleaned fit still fails its residual check
            from .noise import residual_check

            Tk = sender_matrix(t_ev, es_k, Jk)
            test = residual_check(t_ev - _predict(sol, speed)[:, es_k], s_ev, es_k, n_par, cap=zc)
            searched = True
            if test.passed:
                break
            try:
                sol2, plan2, cn2 = calibrate_matrix(Tk, speed=speed, dim=dim, heights=hz, rng=rng, noise=noise)
            except DegenerateGeometryError:
                break
            if sol2["residual_rms"] < sol["residual_rms"]:
                sol, plan = sol2, plan2
                n_par = n_parameters_of(sol, len(Tk), Jk)
                notes[:] = [n for n in notes if n not in cnotes] + cn2
                cnotes = cn2
            continue
        fi = np.array([a for a, _ in ok])
        fe = np.array([b for _, b in ok])
        new_t = np.full(len(fi), np.nan)
        new_s = np.full(len(fi), np.nan)
        if redetect is not None:
            half = np.maximum(zc * s_ev[fi, fe] * scale, 0.0)
            new_t, new_s = redetect(ri_full[fi], ev_full[fe], pred[fi, es_k[fe]], half)
            new_t = np.asarray(new_t, float)
            new_s = np.asarray(new_s, float)
        for k, (a, b) in enumerate(ok):
            nt = new_t[k]
            good = np.isfinite(nt) and abs(nt - pred[a, es_k[b]]) <= zc * new_s[k] * scale * lev
            outliers.append(Outlier(int(ri_full[a]), int(ev_full[b]), int(es[ev_full[b]]), float(res[a, b]),
                                    float(z[a, b]), bool(good),
                                    float(nt - pred[a, es_k[b]]) if good else float("nan")))
            t_ev[a, b] = nt if good else np.nan
            if good:
                s_ev[a, b] = new_s[k]
        Tk = sender_matrix(t_ev, es_k, Jk)
        try:
            sol = refit(Tk, sol, speed, hz)
            needs_ls = False
        except DegenerateGeometryError:
            break
    if needs_ls:  # the robust start found nothing to exclude: finish with least squares (covariances)
        sol = refit(sender_matrix(t_ev, es_k, Jk), sol, speed, hz)
    if outliers:
        redo = sum(o.redetected for o in outliers)
        worst = max(outliers, key=lambda o: abs(o.z))
        notes.append(f"{len(outliers)} outlier detection(s) (|z| > {zc:.2f}, Bonferroni at {alpha:g}) excluded, "
                     f"{redo} re-detected near the predicted time; worst: microphone {rn[worst.receiver]}, "
                     f"loudspeaker {sn[worst.sender]}, residual {worst.residual * 1e6:.3g} us")
    from .noise import sender_std

    Tk = sender_matrix(t_ev, es_k, Jk)
    Sk = sender_std(s_ev, t_ev, es_k, Jk)
    toa_out = toa.copy()
    toa_out[np.ix_(kr, ev_keep)] = t_ev
    Tf = np.full((I, J), np.nan)
    Sf = np.full((I, J), np.nan)
    Tf[np.ix_(kr, ks)] = Tk
    Sf[np.ix_(kr, ks)] = Sk
    std_out = np.array(std, dtype=float)
    std_out[np.ix_(kr, ev_keep)] = s_ev
    full = _scatter(sol, kr, ks)
    return RobustFit(full, plan, notes, outliers, toa_out, Tf, Sf, dropped_r, dropped_s, zc, std_out, n_par)


def n_parameters_of(sol: dict[str, Any], I: int, J: int) -> int:
    """Free parameters of a solution's model (gauge removed): coordinates plus I + J - 1 offsets.

    ``2d+heights``: 2 (I + J) horizontal coordinates less 3 (planar rigid motion); ``2d``
    likewise; 3-D: 3 (I + J) less 6.
    """
    d = 2 if str(sol["method"]).startswith("2d") else 3
    return d * (I + J) - d * (d + 1) // 2 + I + J - 1


def _predict(sol: dict[str, Any], speed: float) -> Array:
    r, s = np.asarray(sol["receivers"], float), np.asarray(sol["sources"], float)
    return (np.linalg.norm(r[:, None, :] - s[None, :, :], axis=-1) / speed
            + np.asarray(sol["receiver_offsets"], float)[:, None] + np.asarray(sol["source_offsets"], float)[None, :])


def scale_from_distances(sol: dict[str, Any], receivers: NDArray[np.intp], senders: NDArray[np.intp],
                         distances: Array) -> tuple[float, float]:
    """Scale factor of a solution from known receiver-sender distances (a unit's microphone and loudspeaker).

    With unknown offsets, positions and the speed of sound are confounded exactly: the
    model ``|r_i - s_j| / c + delta_i + tau_j`` is unchanged by ``r, s, c -> lam r, lam s,
    lam c``. Known distances ``D_k`` fix ``lam``: weighted least squares ``lam = sum w_k d_k
    D_k / sum w_k d_k^2`` over the estimated distances ``d_k`` with ``w_k = 1 / var(d_k)``
    (``var(d_k) = u^T (C_i + C_j) u``, u the unit vector, cross-covariance neglected).

    Parameters
    ----------
    sol : dict
        Solution with ``receivers``, ``sources``, ``receiver_cov``, ``source_cov``.
    receivers, senders : (K,) int arrays
        The pairs.
    distances : (K,) array
        Known distances, m.

    Returns
    -------
    lam : float
        Scale factor (1 = the assumed speed of sound is right).
    lam_std : float
        Its standard deviation.
    """
    r = np.asarray(sol["receivers"], float)[receivers]
    s = np.asarray(sol["sources"], float)[senders]
    rc = np.asarray(sol["receiver_cov"], float)[receivers]
    sc = np.asarray(sol["source_cov"], float)[senders]
    D = np.asarray(distances, float)
    diff = r - s
    d = np.linalg.norm(diff, axis=1)
    u = diff / np.maximum(d, 1e-12)[:, None]
    var = np.einsum("ki,kij,kj->k", u, rc + sc, u)
    ok = np.isfinite(d) & np.isfinite(var) & (d > 0)
    var = np.where(var > 0, var, np.nanmedian(var[ok & (var > 0)]) if (ok & (var > 0)).any() else 1e-8)
    w = 1.0 / var[ok]
    lam = float(np.sum(w * d[ok] * D[ok]) / np.sum(w * d[ok] ** 2))
    lam_std = float(lam / np.sqrt(np.sum(d[ok] ** 2 / var[ok])))
    return lam, lam_std


def apply_scale(sol: dict[str, Any], lam: float) -> dict[str, Any]:
    """Positions times ``lam``, covariances times ``lam^2`` (offsets unchanged)."""
    out = dict(sol)
    for key in ("receivers", "sources"):
        out[key] = np.asarray(sol[key], float) * lam
    for key in ("receiver_cov", "source_cov"):
        out[key] = np.asarray(sol[key], float) * lam**2
    return out
