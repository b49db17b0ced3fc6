"""``solve_aoa``: receiver position and orientation from bearings to known beacons (paper 001).

Methods (3-D unless stated):

``"sol1"``  paper Solution 1: Newton on the torus equations (eq. 7-8), orientation eq. 14/15-18.
``"sol2"``  paper Solution 2: Newton on the cosine-rule ranges (eq. 19-20), orientation eq. 23/25,
            location eq. 27.
``"p3p"``   every solution of the three-beacon problem in closed form (quartic), each
            candidate's pose by a rigid fit; a fourth beacon (if any) picks among them.
``"ml"``    the P3P candidates refined by maximum likelihood over all beacons (rotation on
            SO(3)), with covariance; the candidate of least cost wins.
``"linear"`` (2-D) the closed-form linear resection; ``"ml"`` refines it.
``"auto"``  ``"ml"``.

Length (687 lines, above the ~600 guideline): the entry point dispatches to six methods and
holds their shared validation, degeneracy checks, candidate bookkeeping and residual test.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from itertools import combinations
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .._checks import as_points, check_choice, entry
from .._result import Result
from ..errors import DegenerateGeometryError, InputError, Status
from .ml import refine_ml, residuals_2d, residuals_3d
from .orientation import nearest_rotation
from .p3p import p3p
from .planar2d import DANGER_TOL, linear_pose_2d
from .solution1 import solution1
from .solution2 import solution2

Array = NDArray[Any]

__all__ = ["AoaResult", "AoaCandidate", "solve_aoa", "residual_test", "METHODS_3D", "METHODS_2D",
           "PLAUSIBLE_SIGMA"]

METHODS_3D = ("auto", "sol1", "sol2", "p3p", "ml")
METHODS_2D = ("auto", "linear", "ml")
#: relative tolerance on a candidate's cost to call two candidates equally good (ambiguous)
TIE_TOL = 1e-6
#: inverse condition number of the pose Jacobian below which the pose is not determined
JACOBIAN_TOL = 1e-6
#: angular noise std (rad) assumed by the residual test when ``sigma`` is not given: 5 degrees,
#: a generous bound for DoA estimators (GCC-PHAT / MUSIC / SRP on small arrays give a few
#: degrees); a pose whose bearings do not fit at this level is not a pose
PLAUSIBLE_SIGMA = float(np.radians(5.0))
#: level of the chi-square residual test (false alarm probability 1e-3 for a correct pose)
RESIDUAL_TEST_LEVEL = 0.999


@dataclass(frozen=True)
class AoaCandidate:
    """One exact solution of an ambiguous (three-beacon) problem."""

    position: Array
    rotation: Array
    residual_rms: float

    def to_dict(self) -> dict[str, Any]:
        """JSON-safe form."""
        return {
            "position": self.position.tolist(),
            "rotation": self.rotation.tolist(),
            "residual_rms": float(self.residual_rms),
        }


@dataclass(frozen=True)
class AoaFit:
    """Chi-square test of a pose's angular residuals (see :func:`residual_test`).

    Attributes
    ----------
    chi2 : float or (B,): ``n_res rms^2 / noise^2``; dof : ``2N - 6`` (3-D) or ``N - 3`` (2-D);
    p_value : float or (B,) ``P(chi2_dof >= chi2)`` (NaN when dof <= 0); noise : rad;
    noise_given : whether ``noise`` came from the caller (else the bound
    :data:`PLAUSIBLE_SIGMA`); alpha : significance (1 - :data:`RESIDUAL_TEST_LEVEL`);
    passed : bool or (B,); rms : residual RMS (rad).
    """

    chi2: Any
    dof: int
    p_value: Any
    noise: float
    noise_given: bool
    alpha: float
    passed: Any
    rms: Any

    def describe(self) -> str:
        """One line: what the test says."""
        sig = np.degrees(self.noise)
        src = "given" if self.noise_given else "assumed bound"
        if self.dof <= 0:
            return "exactly determined (3 beacons in 3-D): no residual test possible"
        if np.ndim(self.passed):
            n = int(np.sum(~np.asarray(self.passed)))
            return (f"{n} of {np.size(self.passed)} poses fail the residual test (noise {sig:.3g} deg, {src})"
                    if n else f"every pose passes the residual test (noise {sig:.3g} deg, {src})")
        if not self.passed:
            return (f"the bearings fit this pose only to {np.degrees(self.rms):.3g} deg RMS (chi2 = {self.chi2:.4g} "
                    f"on {self.dof} dof, p = {self.p_value:.2g}) for noise {sig:.3g} deg ({src}): not a pose "
                    "(wrong angle convention, beacon order or gross errors?)")
        return f"residual {np.degrees(self.rms):.3g} deg RMS consistent with noise {sig:.3g} deg ({src})"

    def to_dict(self) -> dict[str, Any]:
        """JSON-safe dict."""
        def f(x: Any) -> Any:
            a = np.asarray(x, float)
            return [None if not np.isfinite(v) else float(v) for v in a.ravel()] if a.ndim else (
                float(a) if np.isfinite(a) else None)

        return {"chi2": f(self.chi2), "dof": int(self.dof), "p_value": f(self.p_value),
                "noise": float(self.noise), "noise_given": bool(self.noise_given), "alpha": float(self.alpha),
                "passed": np.asarray(self.passed).tolist(), "rms": f(self.rms)}


@dataclass(frozen=True, repr=False)
class AoaResult(Result):
    """Pose of a receiver (or a batch of receivers) from bearings.

    Attributes
    ----------
    position : (d,) or (B, d) metres.
    rotation : (d, d) or (B, d, d); columns are the receiver axes in the global frame
        (``v_global = R v_receiver``).
    residual_rms : float or (B,) rad, RMS angular residual (tangent-plane components).
    method : the method that produced the pose.
    converged : bool or (B,).
    iterations : int or (B,) (Newton / LM iterations; 0 for closed forms).
    covariance : (q, q) or (B, q, q) or None: covariance of ``(m, w)`` (3-D, ``w`` a rotation
        vector in the receiver frame, ``R_true = R exp([w]x)``, q = 6) or ``(m, theta)``
        (2-D, q = 3), in m and rad; from ML only.
    candidates : tuple of :class:`AoaCandidate` (unbatched only): every pose that explains
        the bearings (about) equally well. More than one means the data are ambiguous.
    n_candidates : int or (B,): number of distinct proper candidates found.
    fit : :class:`AoaFit` or None: the chi-square residual test (:func:`residual_test`) of
        the pose against the noise (``sigma``, else :data:`PLAUSIBLE_SIGMA`).

    ``status`` / ``success`` / ``message`` (the :class:`~selfcal._result.Result` convention):
    ``NOT_CONVERGED``; ``FAILED_TEST`` when the bearings do not fit the pose at the noise
    level (not a pose: wrong angle convention, beacon order, gross errors); ``AMBIGUOUS``
    when several poses explain the bearings equally well; else ``SUCCESS``.
    """

    position: Array
    rotation: Array
    residual_rms: Any
    method: str
    converged: Any
    iterations: Any
    covariance: Array | None = None
    candidates: tuple[AoaCandidate, ...] = field(default_factory=tuple)
    n_candidates: Any = 1
    fit: AoaFit | None = None

    @property
    def ambiguous(self) -> Any:
        """True where more than one pose explains the bearings equally well."""
        if self.position.ndim == 1:
            return len(self.candidates) > 1
        return np.asarray(self.n_candidates) > 1

    @property
    def pose_cov(self) -> Array | None:
        """Covariance of the pose ``(m, w)`` / ``(m, theta)`` (alias of ``covariance``)."""
        return self.covariance

    def _diagnose(self) -> tuple[Status, str]:
        conv = np.asarray(self.converged, bool)
        if not conv.all():
            what = "the solver" if conv.ndim == 0 else f"{int(np.sum(~conv))} of {conv.size} receivers"
            return Status.NOT_CONVERGED, f"{what} did not converge (or the pose is undetermined)"
        if self.fit is not None and not bool(np.all(self.fit.passed)):
            return Status.FAILED_TEST, self.fit.describe()
        status, message = Status.SUCCESS, "converged" if self.fit is None else self.fit.describe()
        if bool(np.any(self.ambiguous)):
            n = len(self.candidates) if self.position.ndim == 1 else int(np.count_nonzero(self.ambiguous))
            what = f"{n} poses explain the bearings equally well" if self.position.ndim == 1 else (
                f"{n} receivers have several equally good poses")
            return Status.AMBIGUOUS, f"ambiguous: {what}"
        return status, message

    @property
    def position_cov(self) -> Array | None:
        """Covariance of the position alone, (d, d) or (B, d, d)."""
        if self.covariance is None:
            return None
        d = self.position.shape[-1]
        return self.covariance[..., :d, :d]

    def to_dict(self) -> dict[str, Any]:
        """JSON-safe dict with the DESIGN.md keys ``position``, ``rotation``, ``residual_rms``,
        ``method`` plus ``converged``, ``iterations``, ``covariance``, ``candidates``."""

        def j(x: Any) -> Any:
            return np.asarray(x).tolist() if x is not None else None

        return {
            "position": j(self.position),
            "rotation": j(self.rotation),
            "residual_rms": j(self.residual_rms),
            "method": self.method,
            "converged": j(self.converged),
            "iterations": j(self.iterations),
            "covariance": j(self.covariance),
            "candidates": [c.to_dict() for c in self.candidates] if len(self.candidates) > 1 else None,
            "n_candidates": j(self.n_candidates),
            "fit": None if self.fit is None else self.fit.to_dict(),
        }


# ----------------------------------------------------------------------------- validation


def _validate(beacons: ArrayLike, bearings: ArrayLike) -> tuple[Array, Array, bool]:
    b = as_points(beacons, "beacons")
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
    residual_rms : float or (B,) rad; n_beacons : beacons used; dim : 2 or 3;
    sigma : angular noise std (rad) or None.

    Returns
    -------
    passed (bool array), ratio (statistic over the quantile; > 1 fails).
    """
    from scipy.stats import chi2

    n_res = (2 if dim == 3 else 1) * n_beacons
    dof = n_res - (6 if dim == 3 else 3)
    sig = PLAUSIBLE_SIGMA if sigma is None else float(sigma)
    rms = np.asarray(residual_rms, float)
    if dof <= 0:
        return np.ones(rms.shape, bool), np.zeros(rms.shape)
    ratio = n_res * rms**2 / sig**2 / chi2.ppf(RESIDUAL_TEST_LEVEL, dof)
    return np.asarray(np.isfinite(rms) & (ratio <= 1.0)), np.asarray(ratio)


# ----------------------------------------------------------------------------- solver


@entry(beacons="array", bearings="array", sigma="positive?", max_iter="count", position_hint="array")
def solve_aoa(
    beacons: ArrayLike,
    bearings: ArrayLike,
    *,
    method: str = "auto",
    noise: str = "sphere",
    sigma: float | None = None,
    orthonormalize: bool = True,
    max_iter: int = 50,
    position_hint: ArrayLike | None = None,
    sign_z_unknown: bool = False,
) -> AoaResult:
    """Receiver position and orientation from bearings to known beacons (paper 001).

    Parameters
    ----------
    beacons : (N, d) known beacon positions in metres, d in {2, 3}, N >= 3, not collinear.
    bearings : (N, d) or batched (B, N, d) direction of each beacon in the receiver frame
        (normalised here; a NaN row marks a missing beacon for a single receiver). In 3-D
        the model is ``bearing_k = R^T (b_k - m) / |b_k - m|`` (paper eq. 2, 11).
    method : 3-D ``"auto" | "sol1" | "sol2" | "p3p" | "ml"``; 2-D ``"auto" | "linear" | "ml"``
        (see the module notes; ``"auto"`` is ``"ml"``).
    noise : ML noise model, ``"sphere"`` (isotropic angular) or ``"angles"`` (Gaussian on the
        angles alpha, beta with the local x and y axes, the paper's simulation model).
    sigma : angular noise std (rad) for the ML covariance; None estimates it when N > 3 (3-D)
        or N > 3 (2-D) and leaves it NaN otherwise.
    orthonormalize : project the paper solutions' rotation (eq. 14/17-18/23/25) onto SO(3).
    max_iter : iteration cap for Newton / Levenberg-Marquardt.
    position_hint : (d,) or None
        Side information for ambiguous problems (three beacons in 3-D): among the candidates
        that explain the bearings equally well, return the one nearest to this point. It never
        enters the cost; without it ties go to the first candidate (all are in ``candidates``).
    sign_z_unknown : bool
        The bearings came from the angles with the receiver's x and y axes (paper eq. 2-4,
        ``--angles axes``), which do not tell on which side of the receiver's xy plane a
        beacon is (eq. 4 takes the front hemisphere). Then every method is followed by the
        maximum-likelihood refinement under the ``"angles"`` noise model (which depends only
        on those two angles), started from the method's solutions for every sign pattern of
        the beacons' z components (all 2^N for N <= 8, else those of the best-conditioned
        triple), and the least-cost pose is returned (``method`` = ``"<method>+ml"``); the
        reported bearings' z signs are the ones this pose predicts. 3-D, one receiver.

    Returns
    -------
    AoaResult

    Raises
    ------
    InputError
        Wrong shapes, inf, zero-length bearings, unknown method.
    DegenerateGeometryError
        ``too-few-beacons``, ``collinear-beacons``, ``receiver-on-beacon-plane`` (3-D, all
        bearings coplanar), ``danger-cylinder`` (3-D, every method) / ``danger-circle``
        (2-D): the pose Jacobian is singular at the solution.

    Notes
    -----
    ``success`` comes from :func:`residual_test` (chi-square on the angular residuals).

    Examples
    --------
    Noise-free bearings from a receiver at ``m`` (axes aligned with the global frame) to
    six beacons:

    >>> import numpy as np
    >>> import selfcal
    >>> rng = np.random.default_rng(5)
    >>> beacons = rng.uniform(-5, 5, (6, 3))
    >>> m = np.array([0.3, -0.2, 0.1])
    >>> bearings = (beacons - m) / np.linalg.norm(beacons - m, axis=1, keepdims=True)
    >>> res = selfcal.solve_aoa(beacons, bearings)
    >>> res.success, np.allclose(res.position, m), np.allclose(res.rotation, np.eye(3))
    (True, True, True)
    """
    if sign_z_unknown:
        return _solve_sign_ambiguous(beacons, bearings, method=method, sigma=sigma,
                                     orthonormalize=orthonormalize, max_iter=max_iter,
                                     position_hint=position_hint)
    b, U, batched = _validate(beacons, bearings)
    N, d = b.shape
    check_choice(method, "method", METHODS_3D if d == 3 else METHODS_2D)
    check_choice(noise, "noise", ("sphere", "angles"))
    if d == 2 and noise != "sphere":
        raise InputError("noise='angles' is a 3-D model; in 2-D the residual is the bearing angle")
    if method == "auto":
        method = "ml"
    hint = None
    if position_hint is not None:
        hint = np.asarray(position_hint, float).reshape(-1)
        if hint.shape != (d,) or not np.isfinite(hint).all():
            raise InputError(f"position_hint must be {d} finite numbers, got {position_hint!r}")
    B = U.shape[0]
    cov: Array | None = None
    cand: tuple[AoaCandidate, ...] = ()
    if d == 2:
        m, R, cond = linear_pose_2d(b, U)
        if (cond <= DANGER_TOL).any():
            k = int(np.argmax(cond <= DANGER_TOL))
            raise DegenerateGeometryError(
                f"receiver {k} lies on the circle through the beacons: every point of that arc sees "
                "the same bearing differences; add a beacon off that circle",
                kind="danger-circle",
            )
        iters = np.zeros(B, int)
        conv = np.ones(B, bool)
        ncand = np.ones(B, int)
        if method == "ml":
            out = refine_ml(b, U, m, R, sigma=sigma, max_iter=max_iter)
            m, R, cov = out["position"], out["rotation"], out["covariance"]
            iters, conv = out["iterations"], out["converged"]
        bad = _check_determined(b, U, m, R, "danger-circle", raise_=not batched)
        conv = np.array(conv, bool, copy=True)
        conv[bad] = False
    elif method in ("sol1", "sol2"):
        if method == "sol1":
            out = solution1(b, U, orthonormalize=orthonormalize, max_iter=max(max_iter, 60))
        else:
            out = solution2(b, U, orthonormalize=orthonormalize, max_iter=max_iter)
        m, A = out["position"], out["A"]
        R = np.swapaxes(A, -1, -2)
        iters, conv = out["iterations"], out["converged"]
        ncand = np.ones(B, int)
        if method == "sol1":
            ncand = _count_distinct(out["roots"], out["root_ok"])
            if not batched:
                cand = _sol1_candidates(b, U, out, orthonormalize)
        # the paper's solutions are as undetermined on the danger cylinder as P3P is
        bad = _check_determined(b, U, m, R, "danger-cylinder", raise_=not batched)
        conv = np.array(conv, bool, copy=True)
        conv[bad] = False
        if not conv.all():
            import warnings

            from ..errors import ConvergenceWarning

            warnings.warn(
                f"{method}: Newton did not converge for {int(np.sum(~np.asarray(conv, bool)))} of {B} receivers",
                ConvergenceWarning,
                stacklevel=2,
            )
    else:
        tri = _best_triple(b)
        pos, rot, valid = p3p(b[tri], U[:, tri])  # (B, 4, 3), (B, 4, 3, 3)
        if not batched and not valid.any() and N > 3:
            # noise can make one triple's cosines inconsistent; the others still start the ML
            for alt in sorted(combinations(range(min(N, 12)), 3), key=lambda t: -_area(b, t)):
                pos, rot, valid = p3p(b[list(alt)], U[:, list(alt)])
                if valid.any():
                    break
        if not batched and not valid.any():
            k = int(np.argmin(valid.any(axis=1)))
            raise DegenerateGeometryError(
                f"receiver {k}: the bearings admit no pose for beacons {tri.tolist()} (measurements "
                "inconsistent with the beacon triangle, or too noisy)",
                kind="no-solution",
            )
        S = pos.shape[1]
        flat_valid = valid.reshape(-1)
        Uc = np.repeat(U, S, axis=0)
        mc = np.where(flat_valid[:, None], pos.reshape(-1, 3), np.nan)
        Rc = np.where(flat_valid[:, None, None], rot.reshape(-1, 3, 3), np.eye(3))
        cost = np.full(B * S, np.inf)
        itc, convc = np.zeros(B * S, int), flat_valid.copy()
        covc = np.full((B * S, 6, 6), np.nan)
        v = flat_valid
        if method == "ml":
            out = refine_ml(b, Uc[v], mc[v], Rc[v], noise=noise, sigma=sigma, max_iter=max_iter)
            mc[v], Rc[v] = out["position"], out["rotation"]
            cost[v] = out["residual_rms"]
            covc[v] = out["covariance"]
            itc[v], convc[v] = out["iterations"], out["converged"]
        else:
            cost[v] = _rms(b, Uc[v], mc[v], Rc[v])
        cost = np.where(flat_valid, cost, np.inf).reshape(B, S)
        best = np.argmin(cost, axis=1)
        rows = np.arange(B)
        pick = rows * S + best
        m, R = mc[pick], Rc[pick]
        iters, conv = itc[pick], convc[pick]
        if method == "ml":
            cov = covc[pick]
        tie = cost <= cost[rows, best][:, None] * (1 + TIE_TOL) + 1e-9
        tie &= valid
        mcs = mc.reshape(B, S, 3)
        if hint is not None:
            # equally good candidates: the side information decides (nearest to the hint)
            dist = np.where(tie, np.linalg.norm(mcs - hint, axis=-1), np.inf)
            best = np.argmin(dist, axis=1)
            pick = rows * S + best
            m, R = mc[pick], Rc[pick]
            iters, conv = itc[pick], convc[pick]
            if method == "ml":
                cov = covc[pick]
        # distinct candidates among the ties (several P3P roots may refine to one optimum)
        ncand = _count_distinct(mcs, tie)
        if not batched:
            kept: list[AoaCandidate] = []
            for s_ in [int(best[0]), *np.argsort(cost[0]).tolist()]:
                p_ = mc[s_]
                if tie[0, s_] and all(np.linalg.norm(p_ - c.position) > 1e-6 * (1 + np.linalg.norm(p_)) for c in kept):
                    kept.append(AoaCandidate(p_.copy(), Rc[s_].copy(), float(cost[0, s_])))
            cand = tuple(kept)
        # a degenerate candidate among the equally good ones (the double root of the danger
        # cylinder comes with a regular twin) means the bearings do not determine the pose
        tb, ts = np.nonzero(tie)
        bad = _check_determined(
            b, U[tb], mcs[tb, ts], Rc.reshape(B, S, 3, 3)[tb, ts], "danger-cylinder", tb, raise_=not batched
        )
        conv = np.array(conv, bool, copy=True)
        conv[bad] = False  # batched: an undetermined receiver is flagged, not fatal
    rms = _rms(b, U, m, R)
    fit = _fit(rms, N, d, sigma, batched)
    if not batched:
        return AoaResult(
            position=m[0], rotation=R[0], residual_rms=float(rms[0]), method=method,
            converged=bool(conv[0]), iterations=int(iters[0]),
            covariance=None if cov is None else cov[0], candidates=cand, n_candidates=int(ncand[0]), fit=fit,
        )
    return AoaResult(
        position=m, rotation=R, residual_rms=rms, method=method, converged=conv,
        iterations=iters, covariance=cov, candidates=(), n_candidates=ncand, fit=fit,
    )


def _fit(rms: Array, n: int, d: int, sigma: float | None, batched: bool) -> AoaFit:
    from scipy.stats import chi2 as chi2_dist

    passed, _ = residual_test(rms, n, d, sigma)
    n_res = (2 if d == 3 else 1) * n
    dof = n_res - (6 if d == 3 else 3)
    noise = PLAUSIBLE_SIGMA if sigma is None else float(sigma)
    stat = n_res * np.asarray(rms, float) ** 2 / noise**2
    p = chi2_dist.sf(stat, dof) if dof > 0 else np.full(stat.shape, np.nan)
    pick = (lambda x: x) if batched else (lambda x: np.asarray(x).reshape(-1)[0].item())
    return AoaFit(pick(stat), dof, pick(p), noise, sigma is not None, 1.0 - RESIDUAL_TEST_LEVEL,
                  pick(passed), pick(np.asarray(rms, float)))


def _solve_sign_ambiguous(beacons: ArrayLike, bearings: ArrayLike, *, method: str, sigma: float | None,
                          orthonormalize: bool, max_iter: int, position_hint: ArrayLike | None) -> AoaResult:
    """:func:`solve_aoa` for bearings whose z-signs are unknown (see ``sign_z_unknown``)."""
    b_all = as_points(beacons, "beacons")
    if b_all.shape[1] != 3:
        raise InputError("sign_z_unknown applies to 3-D bearings (angles with the receiver's x and y axes)")
    U0 = np.array(bearings, dtype=float)
    if U0.ndim != 2:
        raise InputError("sign_z_unknown: one receiver at a time (bearings (N, 3))")
    b, U1, _ = _validate(b_all, U0)
    U = U1[0]
    N = len(b)
    check_choice(method, "method", METHODS_3D)
    idx = np.arange(N) if N <= 8 else _best_triple(b)
    pats = np.array(np.meshgrid(*[[1.0, -1.0]] * len(idx), indexing="ij")).reshape(len(idx), -1).T
    Ub = np.repeat(U[None], len(pats), axis=0)
    Ub[:, idx, 2] *= pats
    ms, Rs = [], []
    base = "ml" if method == "auto" else method
    if base in ("sol1", "sol2"):
        import warnings

        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            out = (solution1(b, Ub, orthonormalize=True, max_iter=max(max_iter, 60)) if base == "sol1"
                   else solution2(b, Ub, orthonormalize=True, max_iter=max_iter))
        ms.append(out["position"])
        Rs.append(np.swapaxes(out["A"], -1, -2))
    else:
        tri = _best_triple(b)
        pos, rot, valid = p3p(b[tri], Ub[:, tri])
        ms.append(np.where(valid[..., None], pos, np.nan).reshape(-1, 3))
        Rs.append(rot.reshape(-1, 3, 3))
    mc, Rc = np.concatenate(ms), np.concatenate(Rs)
    ok = np.isfinite(mc).all(axis=1) & np.isfinite(Rc).all(axis=(1, 2))
    if not ok.any():
        raise DegenerateGeometryError("the bearings admit no pose for any side of the receiver plane",
                                      kind="no-solution")
    mc, Rc = mc[ok], nearest_rotation(Rc[ok])
    Uc = np.repeat(U[None], len(mc), axis=0)
    out = refine_ml(b, Uc, mc, Rc, noise="angles", sigma=sigma, max_iter=max(max_iter, 100))
    cost = np.where(np.asarray(out["converged"], bool), out["residual_rms"], np.inf)
    cost = np.where(np.isfinite(cost), cost, np.inf)
    best = int(np.argmin(cost))
    if position_hint is not None:
        hint = np.asarray(position_hint, float).reshape(-1)
        tie = cost <= cost[best] * (1 + TIE_TOL) + 1e-9
        best = int(np.argmin(np.where(tie, np.linalg.norm(out["position"] - hint, axis=1), np.inf)))
    m, R = out["position"][best], out["rotation"][best]
    # the bearings as this pose sees them: the measured x, y angles with the predicted z side
    g = b - m
    pz = (g @ R)[:, 2]
    Ufix = U.copy()
    Ufix[:, 2] = np.abs(U[:, 2]) * np.where(pz < 0, -1.0, 1.0)
    res = solve_aoa(b, Ufix, method="ml", sigma=sigma, max_iter=max_iter, position_hint=m)
    return replace(res, method=f"{base}+ml")


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


def _sol1_candidates(b: Array, U: Array, out: dict[str, Array], orthonormalize: bool) -> tuple[AoaCandidate, ...]:
    kept: list[AoaCandidate] = []
    for p, A, ok in zip(out["roots"][0], out["root_A"][0], out["root_ok"][0], strict=True):
        if not ok or any(np.linalg.norm(p - c.position) <= 1e-6 * (1 + np.linalg.norm(p)) for c in kept):
            continue
        R = A.T if not orthonormalize else nearest_rotation(A.T[None])[0]
        kept.append(AoaCandidate(p.copy(), R, float(_rms(b, U, p[None], R[None])[0])))
    return tuple(kept)
