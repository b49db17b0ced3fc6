"""Geometry of conference networks: near-planarity, mirror ambiguities and known heights.

Conference units often sit at (nearly) one height. A near-planar network makes 3-D
self-calibration ill-posed: each point may be mirrored through the plane without changing
any distance to first order, so z is undetermined. This module holds the tests and the
fallbacks the calibration (:mod:`selfcal.acoustics.calibrate`) uses:

- :func:`planarity`: the project's one planarity decision (re-exported from
  :mod:`selfcal.toa.verdict.select`, the TOA package's ``dim="auto"``): the F test of a 2-D
  fit against the 3-D one and the chi-square of the 3-D fit's out-of-plane coordinates
  against its covariances, both at level :data:`PLANAR_ALPHA`
  (:func:`selfcal.toa.verdict.select.dimension_test` runs it on a fit).
- :func:`compare_fits`: that nested-model F test (likewise).
- :func:`one_side_of_plane`: the microphone-side convention when only the loudspeakers are
  coplanar.
- :func:`refine_known_heights`: horizontal positions and offsets with every z given (the TOA
  fit with a fixed z column and per-entry weights).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .._checks import check_magnitude, non_number_leaf
from ..errors import InputError
from ..toa.verdict.planarity import (  # one implementation: the TOA package's model choice (dim="auto")
    PLANAR_ALPHA,
    PLANAR_RATIO,
    ModelComparison,
    Planarity,
    compare_fits,
    planarity,
)
from .solution import Calibration

__all__ = ["Planarity", "ModelComparison", "planarity", "compare_fits", "one_side_of_plane",
           "read_heights", "refine_known_heights", "PLANAR_RATIO", "PLANAR_ALPHA"]

Array = NDArray[np.float64]


def one_side_of_plane(points: Array, cov: NDArray[np.float64], plane_points: Array) -> tuple[Array, NDArray[np.float64], int]:
    """Reflect ``points`` onto the majority side of the plane fitted to ``plane_points``.

    When every sender lies in one plane (loudspeakers in desk units on a flat floor),
    each receiver's distances to all senders are unchanged by reflecting that receiver
    alone through the plane: 2^I solutions fit equally well, and a solver may return a
    mix (some microphones under the desk). Self-calibration cannot tell them apart; the
    physical convention that all microphones are on one side (above their desk
    loudspeakers) picks one, and the global reflection gauge does the rest. The same
    holds with the roles swapped.

    Parameters
    ----------
    points : (n, 3) array
    cov : (n, 3, 3) array
    plane_points : (m, 3) array

    Returns
    -------
    points, cov : reflected where needed (covariance ``H C H``, ``H = I - 2 n n^T``)
    flipped : int
        How many points were reflected.
    """
    pp = plane_points[np.isfinite(plane_points).all(axis=1)]  # NaN rows: nodes the solver dropped
    centre = pp.mean(axis=0)
    normal = np.linalg.svd(pp - centre, full_matrices=False)[2][-1]
    h = (points - centre) @ normal
    side = 1.0 if np.nansum(h) >= 0 else -1.0
    flip = np.isfinite(h) & (np.sign(h) == -side)
    H = np.eye(3) - 2.0 * np.outer(normal, normal)
    out = points.copy()
    out[flip] = points[flip] - 2.0 * h[flip, None] * normal[None, :]
    C = np.array(cov, dtype=float)
    C[flip] = np.einsum("ab,nbc,cd->nad", H, C[flip], H)
    return out, C, int(flip.sum())


def read_heights(path: str | Path, receivers: tuple[str, ...], senders: tuple[str, ...]) -> tuple[Array, Array]:
    """Read known heights: JSON ``{"receivers": [...] | {name: z}, "senders": ...}`` in metres.

    Raises
    ------
    InputError
        Missing keys, wrong lengths, unknown names or non-finite values (file and field named).
    """
    from ..io import read_json

    p = Path(path)
    raw = read_json(p, p.name)
    if not isinstance(raw, dict):
        raise InputError(f"{p.name}: expected an object with fields 'receivers' and 'senders'")
    out = []
    for key, names in (("receivers", receivers), ("senders", senders)):
        if key not in raw:
            raise InputError(f"{p.name}: field '{key}' is missing")
        val = raw[key]
        if isinstance(val, dict):
            unknown = set(val) - set(names)
            if unknown:
                raise InputError(f"{p.name}: field '{key}' names unknown {sorted(unknown)[0]!r}")
            missing = [n for n in names if n not in val]
            if missing:
                raise InputError(f"{p.name}: field '{key}' lacks {missing[0]!r}")
            val = [val[n] for n in names]
        bad = non_number_leaf(val)
        if bad is not None:
            raise InputError(f"{p.name}: field '{key}' must be numbers (metres), found {bad}")
        try:
            z = np.asarray(val, dtype=float)
        except (TypeError, ValueError):
            raise InputError(f"{p.name}: field '{key}' must be numbers (metres)") from None
        check_magnitude(z, f"{p.name}: field '{key}'")
        if z.shape != (len(names),) or not np.isfinite(z).all():
            raise InputError(f"{p.name}: field '{key}' must hold {len(names)} finite heights, got shape {z.shape}")
        out.append(z)
    return out[0], out[1]


def refine_known_heights(
    matrix: Array,
    receiver_heights: Array,
    sender_heights: Array,
    receivers_xy: Array,
    senders_xy: Array,
    receiver_offsets: Array,
    source_offsets: Array,
    *,
    speed: float,
    max_iterations: int = 50,
    f_scale: float | None = None,
    weights: Array | None = None,
) -> Calibration:
    """Least squares for horizontal positions and offsets with every height known.

    Minimises ``sum_ij (c t_ij - sqrt(|x_i - y_j|^2 + (z_i - w_j)^2) - c delta_i - c tau_j)^2``
    (004 eq. 3.1 with the heights z_i, w_j given) over the (I + J) x 2 horizontal
    positions, the I internal delays and the onsets tau_2..tau_J (tau_1 = 0, 004 sec. 3.3).
    It is the TOA fit (:func:`selfcal.toa.engine.nls.refine_toa`, offsets "both") with the
    z column of every node fixed and per-entry weights, on the driver (``solver="lm"``): the
    constrained path of :mod:`selfcal.toa.engine.constrained`, which holds the horizontal gauge (translation,
    rotation about z) at the start's and reports the covariance free of it,
    ``sigma^2 (J^T W J)^+`` (minimum-norm inner constraints).

    Parameters
    ----------
    matrix : (I, J) array
        TOA in seconds, NaN = missing.
    receiver_heights, sender_heights : (I,), (J,) arrays, m
    receivers_xy, senders_xy : (I, 2), (J, 2) arrays
        Initial horizontal positions, m.
    receiver_offsets, source_offsets : (I,), (J,) arrays
        Initial delays / onsets, s (shifted so that the first onset is 0).
    speed : float
        m/s.
    f_scale : float, optional
        s: a Cauchy loss of this scale on the weighted residuals instead of least squares
        (``sum log(1 + (e / f_scale)^2)``), robust to a minority of wrong entries: IRLS, at most
        8 weighted fits each from the last (the driver's one Cauchy minimisation stops in worse
        local minima from poor starts, docs/design.md); a robust start, its covariances NaN.
    weights : (I, J) array, optional
        ``1 / std`` of every entry (1/s): weighted least squares, the ML fit when the entries'
        noise differs (a detection in a noise burst against a clean one). Default equal
        weights. The covariance is then ``s^2 (J^T W J)^+`` with ``s^2`` the weighted
        residual sum over the degrees of freedom.

    Returns
    -------
    Calibration
        The ``2d+heights`` model (``dim=2``, ``known_heights=True``, ``method="2d+heights"``):
        ``receivers`` (I, 3), ``sources`` (J, 3), ``receiver_offsets`` (I,) s,
        ``source_offsets`` (J,) s (first 0), ``receiver_cov`` (I, 3, 3), ``source_cov``
        (J, 3, 3) (zero z variance: heights are given), ``residual_rms`` (s),
        ``converged``, ``iterations``.
    """
    from ..toa.engine.nls import refine_toa, toa_model

    T = np.asarray(matrix, dtype=float)
    I, J = T.shape
    obs = np.isfinite(T)
    zr, zs = np.asarray(receiver_heights, float), np.asarray(sender_heights, float)
    shift = float(source_offsets[0])
    wt = np.ones((I, J))
    if weights is not None:
        w = np.asarray(weights, float)
        wt = np.where(np.isfinite(w) & (w > 0), w, 0.0)
        pos = obs & (wt > 0)
        wt = wt / (float(np.exp(np.mean(np.log(wt[pos])))) if pos.any() else 1.0)  # geometric mean 1
    fixed_r = np.zeros((I, 3), bool)
    fixed_s = np.zeros((J, 3), bool)
    fixed_r[:, 2] = fixed_s[:, 2] = True  # the known heights: a fixed z column
    Y = speed * T

    def fit(w: Array | None, r: Array, s: Array, d: Array, o: Array) -> Any:
        # a robust (Cauchy) fit is a start: no covariance (as solve_toa's robust refits)
        return refine_toa(Y, r, s, offsets="both", receiver_offsets0=d, source_offsets0=o,
                          max_nfev=max_iterations, xtol=1e-12, solver="lm", fixed_receivers=fixed_r, fixed_sources=fixed_s,
                          weights=w, covariance=f_scale is None)

    cur = (np.column_stack([np.asarray(receivers_xy, float), zr]), np.column_stack([np.asarray(senders_xy, float), zs]),
           speed * (np.asarray(receiver_offsets, float) + shift), speed * (np.asarray(source_offsets, float) - shift))
    if f_scale is None:
        sol = fit(None if weights is None else wt, *cur)
    else:  # Cauchy by IRLS from the start: weights sqrt(rho') of the weighted residuals, weighted fits
        fs_m = float(f_scale) * speed
        iterations = 0
        for _ in range(8):
            e = np.where(obs, wt * (Y - toa_model(*cur)), 0.0)
            sol = fit(wt * np.sqrt(1.0 / (1.0 + (e / fs_m) ** 2)), *cur)
            iterations += sol.iterations
            new = (sol.receivers, sol.sources, sol.receiver_offsets, sol.source_offsets)
            step = max(float(np.abs(x - y).max()) for x, y in zip(new, cur, strict=True))  # type: ignore[operator]
            cur = new  # type: ignore[assignment]
            if step < 1e-9:
                break
        sol = dataclasses.replace(sol, iterations=iterations)
    assert sol.receiver_offsets is not None and sol.source_offsets is not None
    e = sol.residuals[obs & (wt > 0)]
    return Calibration(
        receivers=np.asarray(sol.receivers, float), sources=np.asarray(sol.sources, float),
        receiver_offsets=np.asarray(sol.receiver_offsets, float) / speed,
        source_offsets=np.asarray(sol.source_offsets, float) / speed,
        receiver_cov=np.asarray(sol.receiver_cov, float), source_cov=np.asarray(sol.source_cov, float),
        residual_rms=float(np.sqrt(np.mean(e**2))) / speed if e.size else float("nan"),
        converged=bool(sol.converged), iterations=int(sol.iterations), method="2d+heights", dim=2,
        known_heights=True)
