"""Result types of :func:`~selfcal.aoa.solve_aoa`: :class:`AoaCandidate`, :class:`AoaFit`,
:class:`AoaResult`."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .._result import Result
from ..errors import Status

Array = NDArray[Any]

__all__ = ["AoaCandidate", "AoaFit", "AoaResult", "COVARIANCE_PARAMETERS", "COVARIANCE_UNITS", "pose_summary"]


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
        (2-D, q = 3), in m and rad; from ML only. ``to_dict`` names the order and units
        (``covariance_parameters``, ``covariance_units``: :data:`COVARIANCE_PARAMETERS`) and adds
        ``position_std`` (m) and the rotation as a quaternion and yaw / pitch / roll with their
        standard deviations (:func:`pose_summary`).
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

        d = int(self.position.shape[-1])
        if self.position.ndim == 1:
            extra = pose_summary(self.rotation, self.covariance)
        else:
            per = [pose_summary(self.rotation[b], None if self.covariance is None else self.covariance[b])
                   for b in range(self.position.shape[0])]
            extra = {key: [p[key] for p in per] for key in per[0]} if per else {}
        pstd = None
        if self.covariance is not None:
            var = np.diagonal(np.asarray(self.covariance, float), axis1=-2, axis2=-1)[..., :d]
            pstd = np.sqrt(np.maximum(var, 0.0)).tolist()
        return {
            "position": j(self.position),
            "position_std": pstd,
            "rotation": j(self.rotation),
            **extra,
            "residual_rms": j(self.residual_rms),
            "method": self.method,
            "converged": j(self.converged),
            "iterations": j(self.iterations),
            "covariance": j(self.covariance),
            "covariance_parameters": list(COVARIANCE_PARAMETERS[d]) if self.covariance is not None else None,
            "covariance_units": list(COVARIANCE_UNITS[d]) if self.covariance is not None else None,
            "candidates": [c.to_dict() for c in self.candidates] if len(self.candidates) > 1 else None,
            "n_candidates": j(self.n_candidates),
            "fit": None if self.fit is None else self.fit.to_dict(),
        }


#: parameter order of ``AoaResult.covariance`` by dimension: the position, then the rotation vector
#: ``w`` in the receiver frame (``R_true = R exp([w]x)``) in 3-D or the heading angle in 2-D
COVARIANCE_PARAMETERS = {3: ("x", "y", "z", "wx", "wy", "wz"), 2: ("x", "y", "theta")}
#: units of the covariance's parameters (its entries are the products of their units)
COVARIANCE_UNITS = {3: ("m", "m", "m", "rad", "rad", "rad"), 2: ("m", "m", "rad")}


def _wrap_deg(a: Array) -> Array:
    return np.asarray((np.asarray(a) + 180.0) % 360.0 - 180.0)


def pose_summary(rotation: Any, covariance: Any = None) -> dict[str, Any]:
    """The rotation of one pose in the conventions users have, with standard deviations.

    3-D: ``quaternion`` ``[w, x, y, z]`` (scalar first, Hamilton, the active rotation of
    ``v_global = R v_receiver``, ``w >= 0``), ``yaw_pitch_roll_deg`` (intrinsic z-y'-x'':
    ``R = Rz(yaw) Ry(pitch) Rx(roll)``, the aerospace convention), ``rotation_std_deg`` (the
    standard deviation of the small rotation about each receiver axis, ``sqrt diag`` of the
    rotation block of the covariance) and ``yaw_pitch_roll_std_deg`` (the covariance propagated
    through the Euler angles by central differences; they grow without bound near pitch = +-90
    deg, gimbal lock). 2-D: ``heading_deg`` (``atan2(R_10, R_00)``) and ``heading_std_deg``.
    The stds are None without a covariance.

    Parameters
    ----------
    rotation : (3, 3) or (2, 2) rotation matrix (columns = receiver axes in the global frame).
    covariance : (6, 6) / (3, 3) pose covariance in the order of :data:`COVARIANCE_PARAMETERS`,
        or None.

    Returns
    -------
    dict of JSON-safe lists / floats.

    Examples
    --------
    >>> import numpy as np
    >>> c, s = np.cos(np.radians(30)), np.sin(np.radians(30))
    >>> R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])   # yaw 30 deg
    >>> out = pose_summary(R, np.diag([0.0, 0.0, 0.0, 0.0, 0.0, np.radians(2.0) ** 2]))
    >>> np.round(out["yaw_pitch_roll_deg"], 6).tolist(), np.round(out["yaw_pitch_roll_std_deg"], 6).tolist()
    ([30.0, 0.0, 0.0], [2.0, 0.0, 0.0])
    >>> np.round(out["quaternion"], 6).tolist()
    [0.965926, 0.0, 0.0, 0.258819]
    """
    from scipy.spatial.transform import Rotation

    R = np.asarray(rotation, dtype=float)
    cov = None if covariance is None else np.asarray(covariance, dtype=float)
    if R.shape == (2, 2):
        heading = float(np.degrees(np.arctan2(R[1, 0], R[0, 0])))
        hstd = None if cov is None else float(np.degrees(np.sqrt(max(cov[2, 2], 0.0))))
        return {"heading_deg": heading, "heading_std_deg": hstd}
    if not np.isfinite(R).all():
        return {"quaternion": None, "yaw_pitch_roll_deg": None, "rotation_std_deg": None,
                "yaw_pitch_roll_std_deg": None}
    rot = Rotation.from_matrix(R)
    q = rot.as_quat()  # (x, y, z, w)
    q = np.r_[q[3], q[:3]]
    q = q if q[0] >= 0 else -q
    ypr = rot.as_euler("ZYX", degrees=True)
    out: dict[str, Any] = {"quaternion": q.tolist(), "yaw_pitch_roll_deg": ypr.tolist(),
                           "rotation_std_deg": None, "yaw_pitch_roll_std_deg": None}
    if cov is None or not np.isfinite(cov).all():
        return out
    Sw = cov[3:6, 3:6]
    out["rotation_std_deg"] = np.degrees(np.sqrt(np.maximum(np.diag(Sw), 0.0))).tolist()
    h = 1e-6
    J = np.empty((3, 3))
    for a in range(3):
        e = np.zeros(3)
        e[a] = h
        plus = (rot * Rotation.from_rotvec(e)).as_euler("ZYX", degrees=True)
        minus = (rot * Rotation.from_rotvec(-e)).as_euler("ZYX", degrees=True)
        J[:, a] = _wrap_deg(plus - minus) / (2.0 * h)  # degrees per radian
    var = np.einsum("ia,ab,ib->i", J, Sw, J)
    out["yaw_pitch_roll_std_deg"] = np.sqrt(np.maximum(var, 0.0)).tolist()
    return out
