"""Bearing-only pose (paper 001): input validation, the degeneracy checks and the chi-square
residual test shared by every method."""

from __future__ import annotations

from itertools import combinations
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .._checks import as_points, check_magnitude
from ..errors import DegenerateGeometryError, InputError
from ..geometry import gauge_freedoms
from .ml import residuals_2d, residuals_3d
from .result import AoaFit

Array = NDArray[Any]

__all__ = ["residual_test", "JACOBIAN_TOL", "PLAUSIBLE_SIGMA", "RESIDUAL_TEST_LEVEL"]

#: inverse condition number of the pose Jacobian below which the pose is not determined
JACOBIAN_TOL = 1e-6
#: angular noise std (rad) assumed by the residual test when ``sigma`` is not given: 5 degrees,
#: a generous bound for DoA estimators (GCC-PHAT / MUSIC / SRP on small arrays give a few
#: degrees); a pose whose bearings do not fit at this level is not a pose
PLAUSIBLE_SIGMA = float(np.radians(5.0))
#: level of the chi-square residual test (false alarm probability 1e-3 for a correct pose)
RESIDUAL_TEST_LEVEL = 0.999


# ----------------------------------------------------------------------------- validation


def _validate(beacons: ArrayLike, bearings: ArrayLike) -> tuple[Array, Array, bool]:
    b = check_magnitude(as_points(beacons, "beacons"), "beacons")
    N, d = b.shape
    try:
        U = np.array(bearings, dtype=float)
    except (TypeError, ValueError) as exc:
        raise InputError(f"bearings: cannot be read as numbers ({exc})") from None
    batched = U.ndim == 3
    if U.ndim == 2:
        U = U[None]
    if U.ndim != 3 or U.shape[1:] != (N, d):
        raise InputError(
            f"bearings: expected shape ({N}, {d}) or (B, {N}, {d}) to match beacons {b.shape}, got "
            f"{np.shape(bearings)} (angles? convert with angles_to_bearings / --angles deg)"
        )
    if np.isinf(U).any():
        raise InputError("bearings: contain inf")
    nan_rows = np.isnan(U).any(axis=2)
    if nan_rows.any():
        if batched:
            raise InputError("bearings: NaN (missing beacon) is only supported for a single receiver")
        keep = ~nan_rows[0]
        b, U = b[keep], U[:, keep]
        N = len(b)
    norm = np.linalg.norm(U, axis=2, keepdims=True)
    if (norm < 1e-12).any():
        raise InputError("bearings: a bearing vector has zero length; bearings are directions")
    U = U / norm
    if N < 3:
        raise DegenerateGeometryError(
            f"{N} beacons with a bearing cannot fix position and orientation; at least 3 are needed",
            kind="too-few-beacons",
        )
    centred = b - b.mean(axis=0)
    s = np.linalg.svd(centred, compute_uv=False)
    if s[0] <= 0 or s[1] <= 1e-9 * s[0]:
        raise DegenerateGeometryError(
            "the beacons are collinear (or coincide): rotations about their line are unobservable; "
            "use beacons that span a plane",
            kind="collinear-beacons",
        )
    if d == 3:
        sv = np.linalg.svd(U, compute_uv=False)  # (B, 3)
        flat = sv[:, 2] <= 1e-9 * sv[:, 0]
        if flat.any():
            k = int(np.argmax(flat))
            raise DegenerateGeometryError(
                f"receiver {k}: all bearings lie in one plane, i.e. the receiver is in the plane of the "
                "beacons; its offset from that plane is unobservable (use the 2-D variant, or a beacon "
                "off the plane)",
                kind="receiver-on-beacon-plane",
            )
    return b, U, batched


def _area(b: Array, t: tuple[int, ...]) -> float:
    i, j, k = t
    return float(np.linalg.norm(np.cross(b[j] - b[i], b[k] - b[i])))


def _best_triple(b: Array) -> Array:
    """Indices of the beacon triple with the largest triangle area (best-conditioned P3P)."""
    N = len(b)
    if N == 3:
        return np.arange(3)
    idx = list(combinations(range(min(N, 12)), 3))
    areas = np.array([float(np.linalg.norm(np.cross(b[j] - b[i], b[k] - b[i]))) for i, j, k in idx])
    return np.asarray(idx[int(np.argmax(areas))], dtype=int)


def _rms(b: Array, U: Array, m: Array, R: Array) -> Array:
    if b.shape[1] == 3:
        e, _ = residuals_3d(b, U, m, R)
    else:
        e, _ = residuals_2d(b, U, m, np.arctan2(R[:, 1, 0], R[:, 0, 0]))
    return np.asarray(np.sqrt(np.mean(e**2, axis=1)))


def _check_determined(
    b: Array, U: Array, m: Array, R: Array, kind: str, ids: Array | None = None, *, raise_: bool = True
) -> Array:
    """Raise when the pose Jacobian is (numerically) rank deficient at the solution.

    ``ids`` maps the rows to receiver indices for the message (default: the row number)."""
    ids = np.arange(len(m)) if ids is None else np.asarray(ids)
    fin = np.isfinite(m).all(axis=1) & np.isfinite(R).all(axis=(1, 2))
    if not fin.all():
        U, m, R, ids = U[fin], m[fin], R[fin], ids[fin]
        if not fin.any():
            return np.zeros(0, int)
    if b.shape[1] == 3:
        _, J = residuals_3d(b, U, m, R, jacobian=True)
    else:
        _, J = residuals_2d(b, U, m, np.arctan2(R[:, 1, 0], R[:, 0, 0]), jacobian=True)
    assert J is not None
    scale = np.sqrt(np.mean(np.sum((b - b.mean(0)) ** 2, axis=1)))
    J = J.copy()
    J[..., : b.shape[1]] *= scale  # metres vs radians: compare in beacon-spread units
    s = np.linalg.svd(J, compute_uv=False)
    bad = s[:, -1] <= JACOBIAN_TOL * s[:, 0]
    if not raise_:
        return np.unique(ids[bad])
    if bad.any():
        k = int(ids[int(np.argmax(bad))])
        where = "circle through the beacons" if kind == "danger-circle" else (
            "danger cylinder (the cylinder through the beacons' circumcircle, normal to their plane)"
        )
        raise DegenerateGeometryError(
            f"receiver {k} lies on the {where}: the bearings do not determine its pose; "
            "add a beacon off that circle",
            kind=kind,
        )
    return np.zeros(0, int)


# ----------------------------------------------------------------------------- residual test
def residual_test(residual_rms: Any, n_beacons: int, dim: int, sigma: float | None = None) -> tuple[Array, Array]:
    """Chi-square test of a pose's angular residuals: (passed, statistic / quantile) arrays.

    Under the model (independent angular noise of std ``sigma`` per tangent component) the
    residual sum of squares at the least-squares pose is ``sigma^2 chi2(dof)`` with
    ``dof = 2N - 6`` in 3-D (two angles per beacon, six pose unknowns) and ``N - 3`` in
    2-D. The pose passes when ``n_res rms^2 / sigma^2 <= chi2.ppf(RESIDUAL_TEST_LEVEL, dof)``
    (``n_res`` = 2N or N residuals). Without ``sigma`` the bound :data:`PLAUSIBLE_SIGMA`
    (5 degrees) is used. With ``dof = 0`` (three beacons) the fit is exact and the test
    passes trivially.

    Parameters
    ----------
    residual_rms : float or (B,) array
        RMS angular residual of each pose, rad (``AoaResult.residual_rms``).
    n_beacons : int
        Beacons used (N).
    dim : {2, 3}
    sigma : float, optional
        Angular noise std, rad; None uses :data:`PLAUSIBLE_SIGMA`.

    Returns
    -------
    passed : bool array, the shape of ``residual_rms``
    ratio : float array
        The statistic over the quantile; above 1 fails.

    Notes
    -----
    Gaussian angular noise is the model of paper 001's simulations; the chi-square count of
    the least-squares residuals is the standard fit test under it, here at level
    :data:`RESIDUAL_TEST_LEVEL` (0.999).

    Examples
    --------
    Six beacons in 3-D (6 degrees of freedom): an RMS of 1 sigma passes, 3 sigma fails.

    >>> passed, ratio = residual_test([0.01, 0.03], 6, 3, sigma=0.01)
    >>> passed.tolist(), bool(ratio[1] > 1)
    ([True, False], True)
    """
    from scipy.stats import chi2

    n_res, dof = _n_residuals_dof(n_beacons, dim)
    sig = PLAUSIBLE_SIGMA if sigma is None else float(sigma)
    rms = np.asarray(residual_rms, float)
    if dof <= 0:
        return np.ones(rms.shape, bool), np.zeros(rms.shape)
    ratio = n_res * rms**2 / sig**2 / chi2.ppf(RESIDUAL_TEST_LEVEL, dof)
    return np.asarray(np.isfinite(rms) & (ratio <= 1.0)), np.asarray(ratio)


def _n_residuals_dof(n_beacons: int, dim: int) -> tuple[int, int]:
    """Angle residuals (two per beacon in 3-D, one in 2-D) and their degrees of freedom.

    The unknown pose is a rigid motion (position and orientation), so it takes
    :func:`~selfcal.geometry.gauge_freedoms` parameters: 6 in 3-D, 3 in 2-D.
    """
    n_res = (2 if dim == 3 else 1) * int(n_beacons)
    return n_res, n_res - gauge_freedoms(dim)


def _fit(rms: Array, n: int, d: int, sigma: float | None, batched: bool) -> AoaFit:
    from scipy.stats import chi2 as chi2_dist

    passed, _ = residual_test(rms, n, d, sigma)
    n_res, dof = _n_residuals_dof(n, d)
    noise = PLAUSIBLE_SIGMA if sigma is None else float(sigma)
    stat = n_res * np.asarray(rms, float) ** 2 / noise**2
    p = chi2_dist.sf(stat, dof) if dof > 0 else np.full(stat.shape, np.nan)
    pick = (lambda x: x) if batched else (lambda x: np.asarray(x).reshape(-1)[0].item())
    return AoaFit(pick(stat), dof, pick(p), noise, sigma is not None, 1.0 - RESIDUAL_TEST_LEVEL,
                  pick(passed), pick(np.asarray(rms, float)))


def _count_distinct(roots: Array, ok: Array) -> Array:
    B, S, _ = roots.shape
    out = np.zeros(B, int)
    for bi in range(B):
        pts = roots[bi][ok[bi]]
        kept: list[Array] = []
        for p in pts:
            if all(np.linalg.norm(p - q) > 1e-6 * (1 + np.linalg.norm(q)) for q in kept):
                kept.append(p)
        out[bi] = len(kept)
    return out
