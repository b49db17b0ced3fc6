"""Geometry of conference networks: near-planarity, mirror ambiguities and known heights.

Conference units often sit at (nearly) one height. A near-planar network makes 3-D
self-calibration ill-posed: each point may be mirrored through the plane without changing
any distance to first order, so z is undetermined. This module holds the tests and the
fallbacks the calibration (:mod:`selfcal.acoustics.calibrate`) uses:

- :func:`planarity`: is the layout thinner than its own position uncertainty (or 1 % of
  its extent)? Judged on one 3-D fit's geometry and covariances (re-exported from
  :mod:`selfcal.toa.verdict.select`, the TOA package's model choice).
- :func:`compare_fits`: nested-model F test of a 3-D against a 2-D fit (likewise; the
  pipeline no longer fits both models by default).
- :func:`one_side_of_plane`: the microphone-side convention when only the loudspeakers are
  coplanar.
- :func:`refine_known_heights`: horizontal positions and offsets with every z given.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .._checks import check_magnitude, non_number_leaf
from ..errors import InputError
from ..optim.lm import levenberg_marquardt
from ..optim.steps import ResidualModel
from ..toa.verdict.select import (  # one implementation: the TOA package's model choice (dim="auto")
    PLANAR_ALPHA,
    PLANAR_RATIO,
    PLANAR_SIGMAS,
    ModelComparison,
    Planarity,
    compare_fits,
    planarity,
)

__all__ = ["Planarity", "ModelComparison", "planarity", "compare_fits", "one_side_of_plane",
           "read_heights", "refine_known_heights", "PLANAR_RATIO", "PLANAR_SIGMAS", "PLANAR_ALPHA"]

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


def _heights_jacobian(xy_r: Array, xy_s: Array, dz: Array, rows: NDArray[np.intp], cols: NDArray[np.intp],
                      I: int, J: int) -> Any:
    import scipy.sparse as sp

    diff = xy_r[rows] - xy_s[cols]
    dist = np.sqrt((diff**2).sum(axis=1) + dz[rows, cols] ** 2)
    g = diff / np.maximum(dist, 1e-9)[:, None]
    m = len(rows)
    n_xy = 2 * (I + J)
    # Parameter order: receiver xy (2I), sender xy (2J), receiver offsets (I), sender offsets 2..J.
    r_idx = np.repeat(np.arange(m), 6)
    c_idx = np.column_stack([2 * rows, 2 * rows + 1, 2 * I + 2 * cols, 2 * I + 2 * cols + 1,
                             n_xy + rows, n_xy + I + cols - 1])
    vals = np.column_stack([-g[:, 0], -g[:, 1], g[:, 0], g[:, 1], -np.ones(m), -np.ones(m)])
    keep = ~((c_idx == n_xy + I - 1) & (np.arange(6) == 5)[None, :])  # sender 0's offset is the gauge
    Jm = sp.csr_matrix((vals[keep], (r_idx[keep.ravel()], c_idx[keep])), shape=(m, n_xy + I + J - 1))
    return Jm, dist


def _levenberg_marquardt(resid: Any, jac: Any, theta0: Array, max_iterations: int,
                         tol: float = 1e-12) -> tuple[Array, Array, Any, int, bool]:
    """Minimise ``|resid(theta)|^2`` with :func:`selfcal.optim.levenberg_marquardt` (dense
    normal equations: the problems here have a few hundred unknowns; Marquardt's scaling keeps
    the gauge null space, the rigid motions, from making the step singular)."""
    out = levenberg_marquardt(ResidualModel(resid, jac), theta0, max_iter=max_iterations, xtol=tol, ftol=tol)
    return out.x, out.state, jac(out.x), out.iterations, out.converged


def _gauge_pinv(N: Array, xr: Array, xs: Array) -> Array:
    """Pseudo-inverse of the normal matrix whose null space is the horizontal rigid motions.

    With ``G`` an orthonormal basis of that null space (x and y translations and the
    rotation about z of every horizontal coordinate; offsets are untouched),
    ``N^+ = (N + G G^T)^-1 - G G^T`` -- one Cholesky instead of an eigendecomposition.
    """
    from scipy.linalg import cho_factor, cho_solve

    n = N.shape[0]
    pts = np.vstack([xr, xs])
    k = 2 * len(pts)
    G = np.zeros((n, 3))
    G[0:k:2, 0] = 1.0
    G[1:k:2, 1] = 1.0
    centred = pts - pts.mean(axis=0)
    G[0:k:2, 2] = -centred[:, 1]
    G[1:k:2, 2] = centred[:, 0]
    G, _ = np.linalg.qr(G)
    GG = G @ G.T
    scale = float(np.mean(np.diag(N))) or 1.0
    # Scaling G G^T like N keeps the sum well conditioned; N^+ = (N + a G G^T)^-1 - G G^T / a.
    try:
        factor = cho_factor(N + scale * GG)
    except np.linalg.LinAlgError:  # a further null direction (a node with too few entries): SVD
        return np.asarray(np.linalg.pinv(N, hermitian=True), dtype=np.float64)
    return np.asarray(cho_solve(factor, np.eye(n)) - GG / scale, dtype=np.float64)


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
) -> dict[str, Any]:
    """Least squares for horizontal positions and offsets with every height known.

    Minimises ``sum_ij (c t_ij - sqrt(|x_i - y_j|^2 + (z_i - w_j)^2) - c delta_i - c tau_j)^2``
    (004 eq. 3.1 with the heights z_i, w_j given) over the (I + J) x 2 horizontal
    positions, the I internal delays and the onsets tau_2..tau_J (tau_1 = 0, 004 sec. 3.3).
    The horizontal gauge (rotation, translation, reflection) stays free; the covariance is
    ``sigma^2 (J^T J)^+`` (minimum-norm inner constraints).

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
        s: a Cauchy loss of this scale instead of least squares (iteratively reweighted:
        weights ``1 / (1 + (e / f_scale)^2)``), robust to a minority of wrong entries.
    weights : (I, J) array, optional
        ``1 / std`` of every entry (1/s): weighted least squares, the ML fit when the entries'
        noise differs (a detection in a noise burst against a clean one). Default equal
        weights. The covariance is then ``s^2 (J^T W J)^+`` with ``s^2`` the weighted
        residual sum over the degrees of freedom.

    Returns
    -------
    dict
        ``receivers`` (I, 3), ``sources`` (J, 3), ``receiver_offsets`` (I,) s,
        ``source_offsets`` (J,) s (first 0), ``receiver_cov`` (I, 3, 3), ``source_cov``
        (J, 3, 3) (zero z variance: heights are given), ``residual_rms`` (s),
        ``converged``, ``iterations``.
    """
    T = np.asarray(matrix, dtype=float)
    I, J = T.shape
    rows, cols = np.nonzero(np.isfinite(T))
    y = speed * T[rows, cols]
    dz = np.asarray(receiver_heights, float)[:, None] - np.asarray(sender_heights, float)[None, :]
    shift = float(source_offsets[0])
    theta0 = np.concatenate([np.asarray(receivers_xy, float).ravel(), np.asarray(senders_xy, float).ravel(),
                             speed * (np.asarray(receiver_offsets, float) + shift),
                             speed * (np.asarray(source_offsets, float)[1:] - shift)])
    n_xy = 2 * (I + J)

    def unpack(th: Array) -> tuple[Array, Array, Array, Array]:
        xr = th[: 2 * I].reshape(I, 2)
        xs = th[2 * I: n_xy].reshape(J, 2)
        dr = th[n_xy: n_xy + I]
        ds = np.concatenate([[0.0], th[n_xy + I:]])
        return xr, xs, dr, ds

    if weights is None:
        wt = np.ones(len(rows))
    else:
        wt = np.asarray(weights, float)[rows, cols]
        wt = np.where(np.isfinite(wt) & (wt > 0), wt, 0.0)
        wt = wt / (float(np.exp(np.mean(np.log(wt[wt > 0])))) if (wt > 0).any() else 1.0)  # geometric mean 1
    import scipy.sparse as _sp

    Wt = _sp.diags(wt)

    def resid(th: Array) -> Array:
        xr, xs, dr, ds = unpack(th)
        dist = np.sqrt(((xr[rows] - xs[cols]) ** 2).sum(axis=1) + dz[rows, cols] ** 2)
        return wt * (y - dist - dr[rows] - ds[cols])

    def jac(th: Array) -> Any:
        xr, xs, _, _ = unpack(th)
        return Wt @ _heights_jacobian(xr, xs, dz, rows, cols, I, J)[0]

    if f_scale is None:
        theta, r, Jm, iterations, converged = _levenberg_marquardt(resid, jac, theta0, max_iterations)
    else:
        import scipy.sparse as sp

        theta, iterations, converged = theta0, 0, False
        fs_m = float(f_scale) * speed
        for _ in range(8):  # IRLS: weights from the current residuals, then weighted LM
            w = np.sqrt(1.0 / (1.0 + (resid(theta) / fs_m) ** 2))
            W = sp.diags(w)

            def wres(th: Array, w: Array = w) -> Array:
                return w * resid(th)

            def wjac(th: Array, W: Any = W) -> Any:
                return W @ jac(th)

            theta_new, r, Jm, it, converged = _levenberg_marquardt(wres, wjac, theta, max_iterations)
            iterations += it
            step = float(np.abs(theta_new - theta).max())
            theta = theta_new
            if step < 1e-9:
                break
        r = resid(theta)
        Jm = jac(theta)
    xr, xs, dr, ds = unpack(theta)
    m, n = len(r), len(theta)
    dof = max(m - n + 3, 1)  # 3 = horizontal rigid-motion gauge freedoms
    sigma2 = float(r @ r) / dof
    cov = sigma2 * _gauge_pinv((Jm.T @ Jm).toarray(), xr, xs)
    rcov = np.zeros((I, 3, 3))
    scov = np.zeros((J, 3, 3))
    for i in range(I):
        rcov[i, :2, :2] = cov[2 * i: 2 * i + 2, 2 * i: 2 * i + 2]
    for j in range(J):
        k = 2 * I + 2 * j
        scov[j, :2, :2] = cov[k: k + 2, k: k + 2]
    return {
        "receivers": np.column_stack([xr, receiver_heights]),
        "sources": np.column_stack([xs, sender_heights]),
        "receiver_offsets": dr / speed,
        "source_offsets": ds / speed,
        "receiver_cov": rcov,
        "source_cov": scov,
        "residual_rms": float(np.sqrt(np.mean((r[wt > 0] / wt[wt > 0]) ** 2))) / speed if (wt > 0).any() else float("nan"),
        "converged": converged,
        "iterations": iterations,
    }
