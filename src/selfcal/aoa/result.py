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

__all__ = ["AoaCandidate", "AoaFit", "AoaResult"]


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
