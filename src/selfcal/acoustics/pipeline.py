"""The whole system of paper 004: recordings -> arrival times -> delays -> positions.

Stages (004 fig. 1.3): (1) distance estimation: detect the direct-path arrival of every
event at every receiver (:mod:`selfcal.acoustics.detect`); (2) onset times and internal
delays and (3) localization, jointly: the per-sender TOA matrix ``t_ij = |r_i - s_j| / c +
tau_j + delta_i`` (004 eq. 3.1) goes to :func:`selfcal.toa.solve_toa` with
``offsets="both"`` (the 004 rank-3 initialiser followed by sparse nonlinear least squares).

Geometry (conference units sit at nearly one height). A near-planar network makes 3-D
self-calibration ill-posed: each point may be mirrored through the plane without
changing any distance to first order, so z is undetermined. The pipeline fits both a
2-D and a 3-D model and keeps z only when the 3-D fit is significantly better (nested-model
F test, :func:`compare_fits`) and its thickness is resolved by its own covariances
(:func:`planarity`); otherwise it calibrates in 2-D, or -- with known heights (``heights``) -- solves
for the horizontal positions and the offsets with each point's z fixed
(:func:`refine_known_heights`), so it never reports a z it cannot determine.
"""

from __future__ import annotations

import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .._checks import entry
from ..errors import DegenerateGeometryError, InputError

__all__ = [
    "PipelineResult",
    "Planarity",
    "ModelComparison",
    "planarity",
    "compare_fits",
    "one_side_of_plane",
    "sender_matrix",
    "refine_known_heights",
    "run_pipeline",
    "read_heights",
    "truth_errors",
    "timing_noise",
    "fit_test",
    "TIMING_REQUIREMENT",
    "POSITION_REQUIREMENT",
]

Array = NDArray[np.float64]
POSITION_REQUIREMENT = 0.10  # m, 004 sec. 2.1 requirement 1(a)
TIMING_REQUIREMENT = 58e-6  # s, 004 sec. 2.2 (2 cm at 343 m/s)
PLANAR_RATIO = 0.01  # thinnest / widest extent below which a layout counts as flat
PLANAR_SIGMAS = 3.0  # thickness below this many standard deviations along the normal = flat
PLANAR_ALPHA = 1e-3  # F-test level: a 3-D improvement less likely than this under a planar truth keeps z
NOISE_FLOOR = 1e-10  # s, below any real detection error; keeps the F test finite on exact data
TIMING_FLOOR = 20e-9  # s, floor of the per-detection timing std in the residual test (resampling, model)
MF_FACTOR = 3.0  # the residual test's detection std: this many theoretical matched-filter stds
FAIL_MESSAGE = "calibration failed the residual test: positions NOT reliable"


def timing_noise(quality_db: Array, band: tuple[float, float], event_senders: NDArray[np.int64],
                 n_senders: int, *, jitter: float = 0.0) -> float:
    """Timing-noise std of the per-sender TOA matrix, s (the ``noise`` of the residual test).

    Per detection (receiver i, event e) the matched-filter timing std is
    ``sigma_ie = 1 / (2 pi f_rms 10^(q_ie / 20))`` (the Cramer-Rao bound of a time delay,
    ``f_rms`` the RMS frequency of the Hann-weighted probe band, ``q_ie`` the detection's
    peak-to-noise ratio in dB, :mod:`selfcal.acoustics.detect`). The test uses
    ``max(MF_FACTOR sigma_ie, TIMING_FLOOR)`` (3x: reverberation and sub-sample effects the
    bound ignores; 20 ns floor) plus the clock ``jitter`` in quadrature; the events of one
    sender are averaged (:func:`sender_matrix`), so an entry's variance is the sum of its
    events' variances over the squared count. Returns the RMS of the entries' stds.

    Parameters
    ----------
    quality_db : (I, E) array
        Detection quality, dB; NaN = missed.
    band : (f0, f1)
        Probe band, Hz.
    event_senders : (E,) int array
        Sender of every event.
    n_senders : int
    jitter : float
        Clock jitter std per (receiver, event), s (simulated or declared).

    Returns
    -------
    float
        Noise std, s (NaN when nothing was detected).
    """
    f0, f1 = float(band[0]), float(band[1])
    f = np.linspace(f0, f1, 1025)
    w = np.sin(np.pi * (f - f0) / max(f1 - f0, 1e-12)) ** 2
    f_rms = float(np.sqrt(np.sum(f * f * w) / np.sum(w)))
    q = np.asarray(quality_db, dtype=float)
    mf = 1.0 / (2.0 * np.pi * f_rms * 10.0 ** (q / 20.0))
    var_e = np.maximum(MF_FACTOR * mf, TIMING_FLOOR) ** 2 + float(jitter) ** 2
    var_e = np.where(np.isfinite(q), var_e, np.nan)
    entries: list[Array] = []
    for j in range(int(n_senders)):
        cols = var_e[:, np.asarray(event_senders) == j]
        if cols.shape[1]:
            cnt = np.isfinite(cols).sum(axis=1)
            ok = cnt > 0
            entries.append(np.nansum(cols, axis=1)[ok] / cnt[ok] ** 2)
    allv = np.concatenate(entries) if entries else np.array([])
    return float(np.sqrt(np.mean(allv))) if allv.size else float("nan")


def fit_test(T: Array, solution: dict[str, Any], speed: float, noise: float) -> Any:
    """Chi-square residual test (:func:`selfcal.toa.residual_test`) of a calibrated solution.

    Residuals ``t_ij - |r_i - s_j| / c - delta_i - tau_j`` (004 eq. 3.1) over the observed
    entries of the (I, J) matrix ``T`` (s); parameters: the coordinates of the solution's
    dimension up to a rigid motion (2-D for ``"2d"`` and ``"2d+heights"``, whose z is given)
    plus I + J - 1 offsets. Returns a :class:`selfcal.toa.ResidualTest`.
    """
    from ..toa.solve import n_parameters, residual_test

    r, s = np.asarray(solution["receivers"], float), np.asarray(solution["sources"], float)
    pred = (np.linalg.norm(r[:, None, :] - s[None, :, :], axis=-1) / speed
            + np.asarray(solution["receiver_offsets"], float)[:, None]
            + np.asarray(solution["source_offsets"], float)[None, :])
    dim = 2 if str(solution["method"]).startswith("2d") else r.shape[1]
    return residual_test(np.asarray(T, float) - pred, noise, n_parameters(r.shape[0], s.shape[0], dim, "both"))


@dataclass(frozen=True)
class ModelComparison:
    """Nested-model F test of a 3-D fit against a 2-D fit of the same TOA matrix.

    Attributes
    ----------
    residual_2d, residual_3d : float
        RMS TOA residuals, s.
    observations : int
        Observed entries m.
    extra_parameters : int
        k = n - 3 unknowns the 3-D model adds (one coordinate per node, less the three
        extra rigid-motion gauge freedoms of 3-D).
    dof_3d : int
        m minus the 3-D model's free parameters, ``4 n - 7`` (n = I + J nodes).
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
                 alpha: float = PLANAR_ALPHA, noise_floor: float = NOISE_FLOOR) -> ModelComparison:
    """F test: does the 3-D model fit the TOAs significantly better than the planar one?

    With Gaussian noise, the planar model nested in the 3-D one and ``RSS = m rms^2``,
    ``F = ((RSS_2 - RSS_3) / k) / (RSS_3 / (m - p_3))`` follows F(k, m - p_3) when the
    network is planar (k = n - 3 extra unknowns, p_3 = 4 n - 7: 3 n coordinates plus
    n - 1 offset differences less 6 gauge freedoms; offsets ``"both"``). The noise
    variance ``RSS_3 / (m - p_3)`` is floored at ``noise_floor^2`` so exact data give a
    finite answer. Without residual degrees of freedom the test cannot reject, and z is
    kept only if the 2-D fit is off by more than the floor.

    Parameters
    ----------
    residual_2d, residual_3d : float
        RMS residuals of the two fits over the ``observations`` entries, s.
    observations : int
    nodes : int
        I + J.
    alpha : float
        Significance level.
    noise_floor : float
        s.

    Returns
    -------
    ModelComparison
    """
    from scipy.stats import f as f_dist

    k = max(nodes - 3, 1)
    dof = observations - (4 * nodes - 7)
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


@dataclass(frozen=True)
class Planarity:
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
    """

    near_planar: bool
    extents: Array
    normal: Array
    normal_std: float
    comparison: ModelComparison | None = None

    def to_dict(self) -> dict[str, Any]:
        """JSON-safe dictionary."""
        return {"near_planar": self.near_planar, "extents": self.extents, "normal": self.normal,
                "normal_std": self.normal_std,
                "comparison": None if self.comparison is None else self.comparison.to_dict()}


def planarity(points: Array, cov: NDArray[np.float64] | None = None, *, ratio: float = PLANAR_RATIO,
              sigmas: float = PLANAR_SIGMAS) -> Planarity:
    """Decide whether (n, 3) ``points`` are too close to a plane for a 3-D calibration.

    Near-planar when the thinnest extent ``e_3`` is below ``ratio * e_1`` or below
    ``sigmas`` times the RMS standard deviation along the normal (``sqrt(mean n^T C_k n)``):
    then the thickness of the layout is not resolved by the data.

    Parameters
    ----------
    points : (n, d) array, m
    cov : (n, d, d) array, optional
        Per-point covariances, m^2 (non-finite ones are ignored).
    """
    P = np.asarray(points, dtype=float)
    P = P[np.isfinite(P).all(axis=1)]
    centred = P - P.mean(axis=0)
    _, s, vt = np.linalg.svd(centred, full_matrices=False)
    ext = s / np.sqrt(max(len(P), 1))
    normal = vt[-1]
    nstd = float("nan")
    if cov is not None:
        C = np.asarray(cov, dtype=float)
        ok = np.isfinite(C).all(axis=(1, 2))
        if ok.any():
            nstd = float(np.sqrt(np.mean(np.einsum("i,kij,j->k", normal, C[ok], normal))))
    flat = bool(ext[-1] < ratio * ext[0] or (np.isfinite(nstd) and ext[-1] < sigmas * nstd))
    return Planarity(flat, ext, normal, nstd)


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
        try:
            z = np.asarray(val, dtype=float)
        except (TypeError, ValueError):
            raise InputError(f"{p.name}: field '{key}' must be numbers (metres)") from None
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
    """Minimise ``|resid(theta)|^2`` by Levenberg-Marquardt on the sparse normal equations.

    Marquardt's scaling ``A + mu diag(A)`` keeps the gauge null space (rigid motions) from
    making the step singular; the problems here have a few hundred unknowns, so the
    normal matrix is solved densely.
    """
    theta = theta0.copy()
    r = resid(theta)
    cost = float(r @ r)
    mu = 1e-3
    converged = False
    it = 0
    Jm = jac(theta)
    while it < max_iterations:
        it += 1
        A = (Jm.T @ Jm).toarray()
        g = Jm.T @ r
        diag = np.diag(A).copy()
        diag[diag <= 0] = 1.0
        improved = False
        for _ in range(30):
            try:
                step = -np.linalg.solve(A + mu * np.diag(diag), g)
            except np.linalg.LinAlgError:
                mu *= 10.0
                continue
            trial = theta + step
            r_new = resid(trial)
            c_new = float(r_new @ r_new)
            if c_new < cost:
                improved = True
                break
            mu *= 10.0
        if not improved:
            converged = True  # no descent direction left: a stationary point
            break
        done = cost - c_new <= tol * max(cost, 1e-300) or np.linalg.norm(step) <= tol * (1 + np.linalg.norm(theta))
        theta, r, cost = trial, r_new, c_new
        mu = max(mu / 10.0, 1e-12)
        Jm = jac(theta)
        if done:
            converged = True
            break
    return theta, r, Jm, it, converged


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
    factor = cho_factor(N + scale * GG)
    return cho_solve(factor, np.eye(n)) - GG / scale


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

    def resid(th: Array) -> Array:
        xr, xs, dr, ds = unpack(th)
        dist = np.sqrt(((xr[rows] - xs[cols]) ** 2).sum(axis=1) + dz[rows, cols] ** 2)
        return y - dist - dr[rows] - ds[cols]

    def jac(th: Array) -> Any:
        xr, xs, _, _ = unpack(th)
        return _heights_jacobian(xr, xs, dz, rows, cols, I, J)[0]

    theta, r, Jm, iterations, converged = _levenberg_marquardt(resid, jac, theta0, max_iterations)
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
        "residual_rms": float(np.sqrt(np.mean(r**2))) / speed,
        "converged": converged,
        "iterations": iterations,
    }


@dataclass(frozen=True)
class PipelineResult:
    """Positions, delays and onsets from a recording directory.

    Attributes
    ----------
    receivers : (I, d) array
        Microphone positions, m (d = 3, or 2 for a near-planar layout without heights).
    sources : (J, d) array
        Loudspeaker positions, m.
    receiver_offsets : (I,) array
        Internal delays, s.
    source_offsets : (J,) array
        Onset times, s, the first 0 (only differences are observable).
    receiver_cov, source_cov : (I, d, d), (J, d, d) arrays
        Position covariances, m^2.
    residual_rms : float
        RMS TOA residual, s.
    converged : bool
    iterations : int
    method : str
        ``"3d"``, ``"2d"`` or ``"2d+heights"`` plus the TOA solver's method.
    toa_matrix : (I, E) array
        Detected TOA per (receiver, event), s, NaN = missed.
    detections_missed : int
    quality_db : (I, E) array
    planarity : Planarity or None
    timings : dict
        Seconds per stage: ``load``, ``detect``, ``calibrate``.
    receiver_names, sender_names : tuple of str
    speed_of_sound : float
    notes : tuple of str
        Warnings a reader must see (near-planar layout, a failed residual test, ...).
    fit : ResidualTest or None
        Chi-square test of the final residuals against ``timing_noise`` (:func:`fit_test`):
        chi2, dof, p-value; ``failed`` when it rejects (p < 1e-3).
    timing_noise : float
        Noise std used by the test, s (:func:`timing_noise`).
    """

    receivers: Array
    sources: Array
    receiver_offsets: Array
    source_offsets: Array
    receiver_cov: NDArray[np.float64]
    source_cov: NDArray[np.float64]
    residual_rms: float
    converged: bool
    iterations: int
    method: str
    toa_matrix: Array
    detections_missed: int
    quality_db: Array
    planarity: Planarity | None
    timings: dict[str, float]
    receiver_names: tuple[str, ...]
    sender_names: tuple[str, ...]
    speed_of_sound: float
    notes: tuple[str, ...] = field(default=())
    fit: Any = None
    timing_noise: float = float("nan")
    fit_binding: bool = True

    @property
    def failed(self) -> bool:
        """True when the residual test rejected the calibration (positions not reliable).

        Not for the automatic near-planar 2-D fallback (``fit_binding`` False): its model
        ignores the small heights the F test found insignificant, so its chi2 is informative only.
        """
        return bool(self.fit_binding and self.fit is not None and not self.fit.passed)

    @property
    def dim(self) -> int:
        """Number of coordinates per position."""
        return int(self.receivers.shape[1])

    def to_dict(self) -> dict[str, Any]:
        """JSON-safe dictionary: DESIGN.md's toa keys plus the pipeline's."""
        return {
            "receivers": self.receivers, "sources": self.sources,
            "receiver_offsets": self.receiver_offsets, "source_offsets": self.source_offsets,
            "receiver_cov": self.receiver_cov, "source_cov": self.source_cov,
            "residual_rms": self.residual_rms, "converged": self.converged, "iterations": self.iterations,
            "method": self.method, "dim": self.dim,
            "toa_matrix": self.toa_matrix, "detections_missed": self.detections_missed,
            "quality_db": self.quality_db,
            "planarity": None if self.planarity is None else self.planarity.to_dict(),
            "timings": self.timings, "receiver_names": list(self.receiver_names),
            "sender_names": list(self.sender_names), "speed_of_sound": self.speed_of_sound,
            "notes": list(self.notes),
            "fit": None if self.fit is None else self.fit.to_dict(), "failed": self.failed,
            "timing_noise": self.timing_noise,
        }


def _solve(T: Array, dim: int, speed: float, rng: int, init: Any = "auto", noise: float | None = None) -> Any:
    try:
        from ..toa import solve_toa
    except ImportError:  # the package re-export may lag behind the module
        from ..toa.solve import solve_toa

    if isinstance(init, str):
        return solve_toa(T, dim=dim, offsets="both", speed=speed, rng=rng, noise=noise)
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
    centre = plane_points.mean(axis=0)
    normal = np.linalg.svd(plane_points - centre, full_matrices=False)[2][-1]
    h = (points - centre) @ normal
    side = 1.0 if np.sum(h) >= 0 else -1.0
    flip = np.sign(h) == -side
    H = np.eye(3) - 2.0 * np.outer(normal, normal)
    out = points.copy()
    out[flip] = points[flip] - 2.0 * h[flip, None] * normal[None, :]
    C = np.array(cov, dtype=float)
    C[flip] = np.einsum("ab,nbc,cd->nad", H, C[flip], H)
    return out, C, int(flip.sum())


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
    """Stages 2 + 3 of 004 on an (I, J) per-sender TOA matrix (seconds).

    The 3-D model contains every planar network, so z is determined only when a 3-D fit
    explains the data significantly better than a 2-D one. Both are always fitted and
    compared by the nested-model F test of :func:`compare_fits` (Gaussian TOA noise, the
    noise level estimated from the 3-D residual); a 3-D answer in a worse basin than the
    planar one is first refined from the lifted 2-D solution, so the verdict does not
    depend on the solver's random starts. A 3-D answer that passes the test must also
    resolve its own thickness (:func:`planarity` with the covariances).

    Parameters
    ----------
    T : (I, J) array
        ``t_ij = |r_i - s_j| / c + tau_j + delta_i``, s, NaN = missing.
    speed : float
        m/s.
    dim : 2, 3 or "auto"
        "auto": 3-D, or 2-D if the layout is near-planar (F test or :func:`planarity`).
        An explicit 3 on a near-planar layout raises.
    heights : (receiver heights (I,), sender heights (J,)), optional
        Known heights, m: 2-D initialisation, then :func:`refine_known_heights`; the
        result is 3-D with z = the given heights.
    rng : int
        Seed of the solver's random initialisations.
    alpha : float
        Significance level of the F test: 3-D is kept only when a 3-D improvement as large
        as the observed one has probability below ``alpha`` under a planar truth.
    noise : float, optional
        Timing-noise std, s (:func:`timing_noise`): passed to :func:`selfcal.toa.solve_toa`,
        whose deep search then runs when a fit fails the residual test.

    Returns
    -------
    solution : dict
        Keys of :func:`refine_known_heights` plus ``method``.
    planarity : Planarity or None
        With the 2-D / 3-D comparison in ``comparison``.
    notes : list of str
        Verdicts a reader must see (near-planar fallback, z uncertainty of a 3-D answer).

    Raises
    ------
    DegenerateGeometryError
        ``kind="near-planar"`` when ``dim=3`` is asked of a near-planar layout.
    """
    notes: list[str] = []
    if heights is not None:
        init = _solve(T, 2, speed, rng)
        dr, ds = _normalise_offsets(np.asarray(init.receiver_offsets), np.asarray(init.source_offsets))
        sol = refine_known_heights(T, heights[0], heights[1], init.receivers, init.sources, dr, ds, speed=speed)
        sol["method"] = f"2d+heights ({init.method} init)"
        return sol, None, notes
    if dim not in (2, 3, "auto"):
        raise InputError(f"dim must be 2, 3 or 'auto', got {dim!r}")
    if dim == 2:
        return _as_solution(_solve(T, 2, speed, rng), "2d"), None, notes
    advice = "give known heights (--heights) for 3-D positions or use --dim 2"
    res2 = _try_solve(T, 2, speed, rng, noise=noise)
    try:
        res3 = _solve_retrying(T, speed, rng, noise=noise)
    except DegenerateGeometryError as exc:
        res3 = _refit_from_planar(T, res2, speed, rng) if res2 is not None else None
        if res3 is None:
            # A 3-D solve that breaks down on data a 2-D solve fits (within half the 004
            # timing tolerance) means the layout is (numerically) planar.
            if res2 is None or not res2.residual_rms < 0.5 * TIMING_REQUIREMENT:
                raise
            pts2 = np.vstack([res2.receivers, res2.sources])
            plan = Planarity(True, np.append(planarity(pts2).extents, 0.0), np.array([0.0, 0.0, 1.0]),
                             float("nan"))
            msg = (f"near-planar layout: the 3-D calibration is undetermined ({exc}) while a 2-D one fits "
                   f"(residual {res2.residual_rms * 1e6:.2f} us); z is not determined by the data, {advice}")
            return _planar_verdict(res2, plan, msg, dim, notes)
    if res2 is not None and res3.residual_rms > res2.residual_rms:
        # Worse than the nested planar model: a local minimum of the 3-D cost. Restart from
        # the planar solution so that the comparison is between the two models, not basins.
        alt = _refit_from_planar(T, res2, speed, rng)
        if alt is not None and alt.residual_rms < res3.residual_rms:
            res3 = alt
    cmp = None
    if res2 is not None:
        I, J = T.shape
        m = int(np.isfinite(T).sum())
        cmp = compare_fits(res2.residual_rms, res3.residual_rms, m, I + J, alpha=alpha)
        if not cmp.significant:
            pts2 = np.vstack([res2.receivers, res2.sources])
            plan = Planarity(True, np.append(planarity(pts2).extents, 0.0), np.array([0.0, 0.0, 1.0]),
                             float("nan"), cmp)
            msg = (f"near-planar layout: a 3-D fit is no significantly better than a 2-D one "
                   f"(residual {res3.residual_rms * 1e6:.3g} vs {res2.residual_rms * 1e6:.3g} us, "
                   f"F = {cmp.f_statistic:.3g}, p = {cmp.p_value:.3g} >= {alpha:g}); "
                   f"z is not determined by the data, {advice}")
            return _planar_verdict(res2, plan, msg, dim, notes)
    res3 = _resolve_mirrors(T, res3, speed, rng, notes)
    pts = np.vstack([res3.receivers, res3.sources])
    cov = np.concatenate([np.asarray(res3.receiver_cov), np.asarray(res3.source_cov)])
    plan = planarity(pts, cov)
    plan = Planarity(plan.near_planar, plan.extents, plan.normal, plan.normal_std, cmp)
    if not plan.near_planar:
        notes.append(_z_note(cov, cmp))
        return _as_solution(res3, "3d"), plan, notes
    msg = (f"near-planar layout (thickness {plan.extents[-1]:.3f} m vs extent {plan.extents[0]:.2f} m, "
           f"normal std {plan.normal_std:.3f} m): z is not determined by the data; {advice}")
    if res2 is None:
        if dim == 3:
            raise DegenerateGeometryError(msg, kind="near-planar")
        res2 = _solve(T, 2, speed, rng)
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


@entry(rng="rng", jitter="nonnegative?")
def run_pipeline(
    directory: str | Path,
    *,
    dim: int | str = "auto",
    heights: str | Path | tuple[Array, Array] | None = None,
    progress: bool = True,
    rng: int = 0,
    detect_options: dict[str, Any] | None = None,
    jitter: float | None = None,
) -> PipelineResult:
    """Recordings -> arrival times -> onsets, delays and positions (004, all three stages).

    Parameters
    ----------
    directory : path
        A recording directory (:mod:`selfcal.acoustics.recording`).
    dim : 2, 3 or "auto"
        See :func:`calibrate_matrix`.
    heights : path or (receiver heights, sender heights), optional
        Known heights (JSON file, :func:`read_heights`, or arrays), m.
    progress : bool
        Progress bars.
    rng : int
        Seed of the TOA solver's random initialisations.
    detect_options : dict, optional
        Passed to :func:`selfcal.acoustics.detect.detect_recording`.
    jitter : float, optional
        Clock jitter std per (receiver, event), s, part of the timing noise of the residual
        test (:func:`timing_noise`); default: the ``clock_jitter`` declared in setup.json (0
        when absent). Never taken from ``truth.json``.

    Returns
    -------
    PipelineResult

    Raises
    ------
    InputError
        Invalid recording directory or heights file.
    DegenerateGeometryError
        Too few detections for the unknowns, or ``dim=3`` on a near-planar layout.
    """
    from .detect import detect_recording
    from .recording import load_recording

    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    rec = load_recording(directory)
    setup = rec.setup
    timings["load"] = time.perf_counter() - t0
    # validated before the (slow) detection: bad input fails fast
    if jitter is None:
        jitter = setup.clock_jitter
    if not np.isfinite(jitter) or jitter < 0:
        raise InputError(f"jitter must be a finite standard deviation >= 0 s, got {jitter!r}")
    hz = None
    if heights is not None:
        hz = (read_heights(heights, setup.receivers, setup.senders) if isinstance(heights, (str, Path))
              else (np.asarray(heights[0], float), np.asarray(heights[1], float)))
        if hz[0].shape != (len(setup.receivers),) or hz[1].shape != (len(setup.senders),):
            raise InputError("heights: need one height per receiver and per sender")
    t0 = time.perf_counter()
    det = detect_recording(rec, progress=progress, **(detect_options or {}))
    timings["detect"] = time.perf_counter() - t0
    T = sender_matrix(det.toa, setup.event_senders, len(setup.senders))
    if np.isnan(T).all():
        raise DegenerateGeometryError("no arrival was detected in any recording; check the probe and levels",
                                      kind="no-detections")
    noise = timing_noise(det.quality_db, rec.probe.band, setup.event_senders, len(setup.senders), jitter=jitter)
    t0 = time.perf_counter()
    sol, plan, notes = calibrate_matrix(T, speed=setup.speed_of_sound, dim=dim, heights=hz, rng=rng,
                                        noise=noise if np.isfinite(noise) else None)
    timings["calibrate"] = time.perf_counter() - t0
    fit = fit_test(T, sol, setup.speed_of_sound, noise) if np.isfinite(noise) else None
    binding = not (plan is not None and plan.near_planar and str(sol["method"]).startswith("2d (")
                   and hz is None and dim == "auto")
    if fit is not None and not fit.passed and not binding:
        notes.append(f"the 2-D fallback's residual test is informative only (chi2 {fit.chi2:.4g} on {fit.dof} dof): "
                     "its model ignores the heights")
    elif fit is not None and not fit.passed:
        msg = (f"{FAIL_MESSAGE} (chi2 {fit.chi2:.4g} on {fit.dof} dof, p = {fit.p_value:.2g} < {fit.alpha:g}, "
               f"timing noise {noise * 1e6:.3g} us): a wrong basin, bad detections or a larger noise than assumed")
        warnings.warn(msg, stacklevel=2)
        notes.append(msg)
    return PipelineResult(
        receivers=sol["receivers"], sources=sol["sources"], receiver_offsets=sol["receiver_offsets"],
        source_offsets=sol["source_offsets"], receiver_cov=sol["receiver_cov"], source_cov=sol["source_cov"],
        residual_rms=sol["residual_rms"], converged=sol["converged"], iterations=sol["iterations"],
        method=sol["method"], toa_matrix=det.toa, detections_missed=det.missed, quality_db=det.quality_db,
        planarity=plan, timings=timings, receiver_names=setup.receivers, sender_names=setup.senders,
        speed_of_sound=setup.speed_of_sound, notes=tuple(notes), fit=fit, timing_noise=noise,
        fit_binding=binding,
    )


def truth_errors(result: PipelineResult, truth: dict[str, Any]) -> dict[str, Any]:
    """Errors of a pipeline result against a simulation's ``truth.json``.

    Positions are aligned to the truth by a rigid motion with reflection (the gauge of
    self-calibration), fitted on receivers and senders together; in 2-D the horizontal
    coordinates are compared; with known heights only the horizontal plane is aligned.
    Only the sums ``delta_i + tau_j`` of internal delays and onsets are observable (a common
    shift between the two is not), and a sum is what biases a range (004 sec. 2.2: 58 us
    = 2 cm). The timing error is therefore the error of the total offset of every
    (receiver, sender) pair, ``|(delta_i^ + tau_j^) - (delta_i + tau_j)|``; the per-unit
    ``delay_errors`` / ``onset_errors`` are shown after removing the best common shift.

    Returns
    -------
    dict
        ``position_errors`` (I + J,) m (receivers then senders), ``receiver_errors``,
        ``sender_errors``, ``delay_errors`` (I,) s, ``onset_errors`` (J,) s, summary
        ``position_median``, ``position_max``, ``timing_median``, ``timing_max`` (pair
        offsets), ``delay_onset_max`` (per unit, common shift removed) and
        ``pass_position``, ``pass_timing``, ``passed`` against 10 cm / 58 us (004).
    """
    from ..geometry import align

    tr = np.asarray(truth["receivers"], float)
    ts = np.asarray(truth["senders"], float)
    er, es = result.receivers, result.sources
    d = er.shape[1]
    true_all = np.vstack([tr, ts])
    est_all = np.vstack([er, es])
    if d == 2 or result.method.startswith("2d+heights"):
        al = align(est_all[:, :2], true_all[:, :2], reflection=True)
        aligned = al.apply(est_all[:, :2])
        if d == 3:
            aligned = np.column_stack([aligned, est_all[:, 2]])
        ref = true_all[:, : aligned.shape[1]]
    else:
        al = align(est_all, true_all, reflection=True)
        aligned, ref = al.apply(est_all), true_all
    perr = np.linalg.norm(aligned - ref, axis=1)
    onset = np.asarray(truth["sender_onsets"], float)
    delay = np.asarray(truth["receiver_delays"], float)
    raw_de = result.receiver_offsets - delay
    raw_on = result.source_offsets - onset
    # Only delta_i + tau_j is observable: remove the common shift that fits best.
    a = 0.5 * (float(np.nanmean(raw_de)) - float(np.nanmean(raw_on)))
    e_de, e_on = raw_de - a, raw_on + a
    pair = np.abs(raw_de[:, None] + raw_on[None, :])
    I = len(tr)
    out = {
        "position_errors": perr, "receiver_errors": perr[:I], "sender_errors": perr[I:],
        "delay_errors": e_de, "onset_errors": e_on,
        "aligned_receivers": aligned[:I], "aligned_sources": aligned[I:],
        "position_median": float(np.nanmedian(perr)), "position_max": float(np.nanmax(perr)),
        "timing_median": float(np.nanmedian(pair)), "timing_max": float(np.nanmax(pair)),
        "delay_onset_max": float(np.nanmax(np.abs(np.concatenate([e_de, e_on])))),
        "horizontal_only": bool(d == 2),
    }
    out["pass_position"] = bool(out["position_max"] <= POSITION_REQUIREMENT)
    out["pass_timing"] = bool(out["timing_max"] <= TIMING_REQUIREMENT)
    out["passed"] = bool(out["pass_position"] and out["pass_timing"])
    return out
