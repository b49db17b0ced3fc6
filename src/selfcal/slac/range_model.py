"""The inputs and the result of range-only SLAC (:func:`selfcal.slac.ranging.solve_range_slac`).

:class:`RangeModelConfig` (priors and robustness settings, each default by principle),
:class:`RangeLog` (odometry and ranges, validated on construction) and
:class:`RangeSlacResult` (the :class:`~selfcal._result.Result` convention). The engine
that reads them is :mod:`selfcal.slac.ranging`, which re-exports them.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np
from numpy.typing import NDArray

from .._result import Result
from ..errors import InputError, Status
from ..robust import TUNING

__all__ = ["RangeLog", "RangeModelConfig", "RangeSlacResult"]

FArray = NDArray[np.float64]
IArray = NDArray[np.int64]


@dataclass(frozen=True)
class RangeModelConfig:
    """Priors and robustness settings of :func:`~selfcal.slac.ranging.solve_range_slac` (each default by principle).

    Attributes
    ----------
    range_noise : float
        Prior std of one range (m), used by the causal filter. 0.3 m: the ranging error of
        narrow-band radio / UWB time-of-flight ranging outdoors (decimetres; multipath is
        left to the robust loss). The smoother re-estimates it from the data.
    scale_std : float
        Prior std of each scale ``s_b`` around 1. Clock-rate mismatch, propagation-speed and
        calibration errors of time-of-flight radios give scale errors of a few percent;
        0.1 keeps the prior weak over that range (a 7 % error is 0.7 sigma).
    scale_prior : str
        The smoother's prior of the scales: ``"empirical"`` (default) estimates it from the
        log (empirical Bayes: ``s ~ N(1, a^2 11^T + tau^2 I)``, a part ``a`` common to all
        beacons and a per-beacon part ``tau``, both at their type-II maximum likelihood given
        the data's Laplace information about the scales under the ``scale_std`` prior; then
        the MAP again under that prior). Exact scales shrink to 1 (the offset-only model), one
        shared scale error is fitted as one scale, independent errors per beacon. ``"fixed"``:
        ``N(1, scale_std^2 I)`` as given. The filter and the fixed-lag smoother always use the
        fixed prior (they are causal; the estimate needs the whole log).
    offset_std : float
        Prior std (m) of each offset ``o_b`` around 0: antenna / electronics delays of
        ranging radios are up to about a metre.
    odo_distance : float
        Odometry distance noise density (m^0.5): ``var(dd) = odo_distance^2 |dd|``, a random
        walk in the distance travelled (wheel slip / radius errors of a few percent: 5 % of
        one metre). Variances are additive over pieces, so splitting a row does not change them.
        A wheel-only bound: the smoother multiplies it by the factor of
        :data:`selfcal.slac.ranging.DISTANCE_NOISE_GRID` (1, 0.3, 0.1) of largest predictive
        likelihood, as it chooses the heading factor.
    odo_turn : float
        Heading noise per turned angle (rad^0.5): ``var(dpsi) += odo_turn^2 |dpsi|`` (5 %).
    odo_drift : float
        Heading noise per distance (rad / m^0.5): ``var(dpsi) += odo_drift^2 |dd|``; 1 deg
        per square-root metre, the drift of a wheel-odometry / low-cost gyro heading.
    init_position_std, init_heading_std : float
        Std of the given first pose (m, rad): it is known (ground truth of the first row), so
        the numbers only keep the first linearisation honest; beacons fix the frame anyway.
    huber : float
        Huber threshold in standard deviations; 1.345 gives 95 % efficiency at the Gaussian.
    gate_quantile : float
        A range whose squared standardised innovation (filter) or residual (smoother) exceeds
        the chi2(1) quantile at this level is rejected (0.999: one good range in 1000 lost).
    max_iter, tol : int, float
        Smoother: at most ``max_iter`` Gauss-Newton iterations, stopped when no pose moves
        more than ``tol`` metres (and no heading more than ``tol`` rad).
    estimate_noise : bool
        Learn the noise levels from the log instead of keeping the priors: the causal filter
        re-estimates the range noise from its own past innovations (a robust median estimator
        over the last ``noise_window`` ranges, so it stays causal); the smoother estimates the
        range noise and the three odometry densities by expectation-maximisation (ML, Shumway &
        Stoffer 1982) inside its Gauss-Newton iterations.
    heading_noise_grid : tuple of float
        Candidate factors on ``odo_turn`` and ``odo_drift``: the heading noise is chosen by
        (robust) maximum likelihood over this grid, since a gyro-aided heading is far better
        than the wheel-only prior (the largest, 1.0). The filter runs one robust EKF per
        candidate and reports their mixture weighted by the predictive likelihood of the ranges
        so far (multiple-model adaptive estimation, Magill 1965: causal); the smoother uses the
        candidate of largest likelihood over the whole log. Log-spaced over 1.5 decades.
    noise_window : int
        Ranges in the filter's noise window: the median's relative standard error is about
        ``1.25 / sqrt(window)`` (~6 % at 400) while a change of the radio environment is followed.
    noise_rounds : int
        Smoother with ``estimate_noise``: at most this many expectation-maximisation rounds of
        the noise levels after the first solve (0 = keep the first estimate); an integer >= 0.
    noise_tol : float
        The EM rounds stop when no noise level changes by more than this relative amount
        (``|log(new / old)|``); a finite number > 0.
    lag_s : float
        ``method="fixed-lag"``: seconds of data after a pose that its estimate uses (the
        delay of the estimate when run online); a finite number > 0.

    Raises
    ------
    InputError
        A field of the wrong type or outside its range (named, with the value).
    """

    range_noise: float = 0.3
    scale_std: float = 0.1
    scale_prior: str = "empirical"
    offset_std: float = 1.0
    odo_distance: float = 0.05
    odo_turn: float = 0.05
    odo_drift: float = float(np.deg2rad(1.0))
    init_position_std: float = 0.1
    init_heading_std: float = float(np.deg2rad(2.0))
    huber: float = TUNING["huber"]
    gate_quantile: float = 0.999
    max_iter: int = 30
    tol: float = 1e-4
    estimate_noise: bool = True
    noise_window: int = 400
    heading_noise_grid: tuple[float, ...] = (1.0, 0.3, 0.1, 0.03)
    noise_rounds: int = 8
    noise_tol: float = 0.05
    lag_s: float = 30.0

    def __post_init__(self) -> None:
        for name in ("range_noise", "scale_std", "offset_std", "init_position_std", "init_heading_std", "huber", "tol",
                     "noise_tol", "lag_s"):
            v = getattr(self, name)
            if isinstance(v, (bool, np.bool_)) or not isinstance(v, (int, float, np.integer, np.floating)):
                raise InputError(f"RangeModelConfig.{name} must be a positive number, got {type(v).__name__} {v!r}")
            if not (np.isfinite(v) and v > 0):
                raise InputError(f"RangeModelConfig.{name} must be a positive number, got {v!r}")
        for name in ("odo_distance", "odo_turn", "odo_drift"):
            v = getattr(self, name)
            if isinstance(v, (bool, np.bool_)) or not isinstance(v, (int, float, np.integer, np.floating)) \
                    or not (np.isfinite(v) and v >= 0):
                raise InputError(f"RangeModelConfig.{name} must be >= 0, got {v!r}")
        q = self.gate_quantile
        if isinstance(q, (bool, np.bool_)) or not isinstance(q, (int, float, np.integer, np.floating)) \
                or not 0.5 < q <= 1.0:
            raise InputError(f"RangeModelConfig.gate_quantile must be in (0.5, 1], got {self.gate_quantile!r}")
        for name, low in (("max_iter", 1), ("noise_window", 1), ("noise_rounds", 0)):
            v = getattr(self, name)
            if isinstance(v, (bool, np.bool_)) or not isinstance(v, (int, np.integer)):
                raise InputError(f"RangeModelConfig.{name} must be an integer >= {low}, got {type(v).__name__} {v!r}")
            if v < low:
                raise InputError(f"RangeModelConfig.{name} must be >= {low}, got {v!r}")
        if self.scale_prior not in ("empirical", "fixed"):
            raise InputError(f"RangeModelConfig.scale_prior must be 'empirical' or 'fixed', got {self.scale_prior!r}")
        if not isinstance(self.estimate_noise, (bool, np.bool_)):
            raise InputError(f"RangeModelConfig.estimate_noise must be True or False, got {self.estimate_noise!r}")
        try:
            grid = np.asarray(self.heading_noise_grid, dtype=float)
        except (TypeError, ValueError):
            grid = np.array([np.nan])
        if grid.ndim != 1 or not (np.isfinite(grid).all() and (grid > 0).all()):
            raise InputError("RangeModelConfig.heading_noise_grid must be a sequence of positive factors, got "
                             f"{self.heading_noise_grid!r}")


@dataclass(frozen=True)
class RangeLog:
    """The inputs of :func:`~selfcal.slac.ranging.solve_range_slac` (seconds, metres, radians).

    Attributes
    ----------
    beacons : (B, 2); beacon_ids : (B,) int (labels only)
    start_time : float; start_pose : (3,) the given first pose
    odo_times : (M,) increasing end times of the odometry rows; odo : (M, 2) ``[dd, dpsi]``
    range_times, range_beacon, ranges : (K,) time, index into ``beacons``, measured range (m)
    """

    beacons: FArray
    beacon_ids: IArray
    start_time: float
    start_pose: FArray
    odo_times: FArray
    odo: FArray
    range_times: FArray
    range_beacon: IArray
    ranges: FArray

    @classmethod
    def from_dataset(cls, data: Any) -> RangeLog:
        """From any object with the attributes of :class:`~selfcal.datasets.plaza.PlazaData`."""
        return cls(beacons=np.asarray(data.beacons, dtype=float), beacon_ids=np.asarray(data.beacon_ids),
                   start_time=float(data.start_time), start_pose=np.asarray(data.start_pose, dtype=float),
                   odo_times=np.asarray(data.odo_times, dtype=float), odo=np.asarray(data.odo, dtype=float),
                   range_times=np.asarray(data.range_times, dtype=float),
                   range_beacon=np.asarray(data.range_beacon), ranges=np.asarray(data.ranges, dtype=float))

    def __post_init__(self) -> None:
        B = np.asarray(self.beacons).shape
        if len(B) != 2 or B[1] != 2 or B[0] < 1:
            raise InputError(f"beacons must be (B, 2), got {B}")
        if np.asarray(self.start_pose).shape != (3,):
            raise InputError("start_pose must be (3,) [x, y, psi]")
        M = np.asarray(self.odo_times).shape
        if len(M) != 1 or M[0] < 1 or np.asarray(self.odo).shape != (M[0], 2):
            raise InputError("odo_times must be (M,) and odo (M, 2) with M >= 1")
        K = np.asarray(self.ranges).shape
        if len(K) != 1 or np.asarray(self.range_times).shape != K or np.asarray(self.range_beacon).shape != K:
            raise InputError("range_times, range_beacon and ranges must be (K,) arrays of one length")
        for name in ("beacons", "start_pose", "odo_times", "odo", "range_times", "ranges"):
            if not np.all(np.isfinite(getattr(self, name))):
                raise InputError(f"{name} must be finite")
        rb = np.asarray(self.range_beacon)
        if rb.size and (rb.min() < 0 or rb.max() >= B[0]):
            raise InputError("range_beacon must index beacons")
        if np.any(np.diff(self.odo_times) < 0) or self.odo_times[0] <= self.start_time:
            raise InputError("odo_times must be non-decreasing and after start_time")


@dataclass(frozen=True, repr=False)
class RangeSlacResult(Result):
    """Outcome of :func:`~selfcal.slac.ranging.solve_range_slac` (the :class:`~selfcal._result.Result` convention).

    Attributes
    ----------
    method : "filter" or "smoother".
    times : (P,) pose times (the start, then each odometry row's end).
    poses : (P, 3) ``[x, y, psi]``; pose_std : (P, 3) their standard deviations.
    beacon_ids : (B,); scale, scale_std, offset, offset_std : (B,) range calibration (R1)
        (filter: at the end of the log).
    noise : float the prior range noise (m); noise_estimate : float the robust estimate from
        the filter's innovations, for the smoother from its own final residuals (m; NaN with
        fewer than 10 ranges, None in ``to_dict``).
    heading_noise_factor : float the grid factor selected by maximum likelihood;
        heading_noise_loglik : (G,) the robust log-likelihood of each grid factor.
    ranges_used, ranges_rejected, ranges_outside : int (used in the final pass, gated, outside
        the odometry span).
    iterations : int (smoother Gauss-Newton iterations; 1 for the filter); converged : bool.
    pose_cov : (P, 2, 2) position covariance of each pose (m^2; the 95 % ellipse is
        ``e^T C^-1 e <= chi2_2(0.95)``); not in ``to_dict`` (use ``pose_std`` there).
    odometry_noise_factor : (2,) the smoother's factors on the distance and heading noise
        variances (1, 1 for the filter): the first is the square of the distance-grid factor
        times EM's, the second EM's; ``heading_noise_factor`` already includes the square root
        of the second.
    calibration_cov : (B, 2, 2) covariance of each beacon's (scale, offset) at the end.
    odometry_scale, odometry_scale_std : float; odometry_scale_weight : float
        Filter: the estimated distance scale of the odometry (``dd_true = k dd``) mixed over
        the candidates, its std, and the mixture weight of the candidates that estimate it
        (the rest take it as exactly 1). Smoother with ``scale_prior="empirical"``: the
        average of the models ``k ~ N(1, 0.05^2)`` and ``k = 1``, its std (the mixture's), and
        the posterior probability of the first (:func:`selfcal.slac.scale_prior.odo_scale_weight`);
        with ``"fixed"``: 1, 0, 0 (no such state).
    odometry_scale_prior_std : float
        The prior std of ``k`` of the more probable model (filter 0.05; smoother: 0.05 when
        the weight of ``k ~ N(1, 0.05^2)`` is at least 1/2, else 1e-4 = no odometry scale
        error; 0 with the fixed prior).
    innovation_test : dict
        Filter: :func:`selfcal.slac.consistency.innovation_tests` on the innovations of the candidate of largest
        weight (NIS level and whiteness); a failure sets ``status`` to ``FAILED_TEST`` and
        warns (:class:`~selfcal.errors.ConvergenceWarning`). Empty for the smoother.
    scale_prior_std : (2,)
        The std ``[a, tau]`` of the scales' prior ``N(1, a^2 11^T + tau^2 I)`` the result used:
        the smoother's empirical-Bayes estimate (``RangeModelConfig.scale_prior``), else
        ``[0, scale_std]``. ``tau`` at its floor (1e-4) means "no per-beacon scale error
        detectable", both at the floor "no scale error": the offset-only model.
    calibration_resets : int
        Filter: beacon calibrations re-initialised by the M-of-N gate test (:data:`selfcal.slac.ranging.RECOVER_M`).
    ``status`` / ``message`` / ``success`` come from :class:`~selfcal._result.Result`.
    """

    _repr_fields: ClassVar[tuple[str, ...]] = ("method", "scale", "offset", "noise_estimate", "iterations")

    method: str
    times: FArray
    poses: FArray
    pose_std: FArray
    beacon_ids: IArray
    scale: FArray
    scale_std: FArray
    offset: FArray
    offset_std: FArray
    noise: float
    noise_estimate: float
    heading_noise_factor: float
    heading_noise_loglik: FArray
    ranges_used: int
    ranges_rejected: int
    ranges_outside: int
    iterations: int
    converged: bool
    pose_cov: FArray = field(default_factory=lambda: np.zeros((0, 2, 2)))
    odometry_noise_factor: FArray = field(default_factory=lambda: np.ones(2))
    calibration_cov: FArray = field(default_factory=lambda: np.zeros((0, 2, 2)))
    odometry_scale: float = 1.0
    odometry_scale_std: float = 0.0
    odometry_scale_weight: float = 0.0
    innovation_test: dict[str, float] = field(default_factory=dict)
    calibration_resets: int = 0
    scale_prior_std: FArray = field(default_factory=lambda: np.array([0.0, 0.1]))
    odometry_scale_prior_std: float = 0.0

    def _diagnose(self) -> tuple[Status, str]:
        if not self.converged:
            return Status.NOT_CONVERGED, f"smoother stopped at its iteration limit ({self.iterations} iterations)"
        if self.method == "filter":
            t = self.innovation_test
            if t and not t.get("passed", 1.0):
                if t["nis_mean"] > t["nis_hi"]:
                    why = (f"time-averaged NIS {t['nis_mean']:.3f} above its bound {t['nis_hi']:.3f} "
                           "(the innovations are larger than the filter predicts)")
                else:
                    why = (f"innovations correlated from one range to the next (lag-one rho {t['whiteness_rho']:.2f}, "
                           f"z = {t['whiteness_z']:.1f}: a persistent state error)")
                return Status.FAILED_TEST, (f"causal filter failed its innovation test: {why}; "
                                            "the reported covariances are overconfident")
            if t and t.get("conservative", 0.0):
                return Status.SUCCESS, (f"causal filter pass finished; time-averaged NIS {t['nis_mean']:.3f} below "
                                        f"{t['nis_lo']:.3f}: the reported covariances are conservative (too large)")
            return Status.SUCCESS, "causal filter pass finished; its innovations pass the NIS and whiteness tests"
        return Status.SUCCESS, f"Gauss-Newton converged in {self.iterations} iterations"

    def to_dict(self) -> dict[str, Any]:
        """JSON-safe dict of every field (arrays as lists, NaN as None) + status / message / success."""
        d = {f.name: getattr(self, f.name) for f in dataclasses.fields(self) if f.name != "pose_cov"}
        d["units"] = {"position": "m", "heading": "rad", "offset": "m", "time": "s"}
        return d
