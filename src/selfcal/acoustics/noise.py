"""Timing-noise model of the detections (the ``noise`` of the residual test and the outlier test).

Per detection (receiver i, event e) the matched-filter timing std is the Cramer-Rao bound
of a time delay, ``sigma_ie = 1 / (2 pi f_rms 10^(q_ie / 20))`` (``f_rms`` the RMS
frequency of the Hann-weighted probe band, ``q_ie`` the detection's peak-to-noise ratio in
dB, :mod:`selfcal.acoustics.detect`). The model uses ``max(MF_FACTOR sigma_ie,
TIMING_FLOOR)`` (3x: reverberation and sub-sample effects the bound ignores) plus the
declared clock jitter in quadrature. The floor is a thousandth of a sample period
(``FLOOR_SAMPLES / fs``; 20.8 ns at 48 kHz, 62.5 ns at 16 kHz): fractional-delay and
resampling errors of the recording chain are a fraction of a sample, not of a second.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from ..robust import mad_std

if TYPE_CHECKING:
    from .solution import Calibration

__all__ = ["timing_noise", "detection_std", "sender_std", "fit_test", "rms_frequency", "TIMING_FLOOR", "MF_FACTOR",
           "FLOOR_SAMPLES", "timing_floor", "ResidualCheck", "residual_check"]

Array = NDArray[np.float64]
FLOOR_SAMPLES = 1e-3  # floor of the per-detection timing std, in sample periods (resampling, model)
TIMING_FLOOR = 20e-9  # s, the floor at 48 kHz (rounded), kept for callers without a sample rate
MF_FACTOR = 3.0  # the residual test's detection std: this many theoretical matched-filter stds


def timing_floor(sample_rate: float | None) -> float:
    """Floor of a detection's timing std, s: ``FLOOR_SAMPLES / sample_rate`` (``TIMING_FLOOR`` if None)."""
    return TIMING_FLOOR if sample_rate is None else FLOOR_SAMPLES / float(sample_rate)


def rms_frequency(band: tuple[float, float]) -> float:
    """RMS frequency of the Hann-weighted probe band ``(f0, f1)``, Hz (the detector's band weight)."""
    f0, f1 = float(band[0]), float(band[1])
    f = np.linspace(f0, f1, 1025)
    w = np.sin(np.pi * (f - f0) / max(f1 - f0, 1e-12)) ** 2
    return float(np.sqrt(np.sum(f * f * w) / np.sum(w)))


def detection_std(quality_db: Array, band: tuple[float, float], *, jitter: float = 0.0,
                  sample_rate: float | None = None) -> Array:
    """Timing std of every detection, s: ``sqrt(max(MF_FACTOR sigma_ie, TIMING_FLOOR)^2 + jitter^2)``.

    Parameters
    ----------
    quality_db : (I, E) array
        Detection quality (peak-to-noise ratio), dB; NaN = missed.
    band : (f0, f1)
        Probe band, Hz.
    jitter : float
        Clock jitter std per (receiver, event), s.
    sample_rate : float, optional
        Hz, for the floor (:func:`timing_floor`).

    Returns
    -------
    (I, E) array
        s; NaN where ``quality_db`` is NaN.
    """
    q = np.asarray(quality_db, dtype=float)
    mf = 1.0 / (2.0 * np.pi * rms_frequency(band) * 10.0 ** (q / 20.0))
    var = np.maximum(MF_FACTOR * mf, timing_floor(sample_rate)) ** 2 + float(jitter) ** 2
    return np.where(np.isfinite(q), np.sqrt(var), np.nan)


def sender_std(std_e: Array, toa: Array, event_senders: NDArray[np.int64], n_senders: int) -> Array:
    """Std of the per-sender averages (:func:`selfcal.acoustics.calibrate.sender_matrix`), (I, J) s.

    The entry averages the observed events of sender j at receiver i, so its variance is the
    sum of their variances over the squared count. NaN where no event was observed.
    """
    var = np.where(np.isfinite(toa), np.asarray(std_e, float) ** 2, np.nan)
    I = var.shape[0]
    out = np.full((I, int(n_senders)), np.nan)
    es = np.asarray(event_senders)
    for j in range(int(n_senders)):
        cols = var[:, es == j]
        if cols.shape[1]:
            cnt = np.isfinite(cols).sum(axis=1)
            out[:, j] = np.where(cnt > 0, np.sqrt(np.nansum(cols, axis=1) / np.maximum(cnt, 1) ** 2), np.nan)
    return out


def timing_noise(quality_db: Array, band: tuple[float, float], event_senders: NDArray[np.int64],
                 n_senders: int, *, jitter: float = 0.0, sample_rate: float | None = None) -> float:
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
    sample_rate : float, optional
        Hz, for the floor (:func:`timing_floor`; default the 48 kHz value).

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
    var_e = np.maximum(MF_FACTOR * mf, timing_floor(sample_rate)) ** 2 + float(jitter) ** 2
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


def fit_test(T: Array, solution: Calibration, speed: float, noise: float) -> Any:
    """Chi-square residual test (:func:`selfcal.toa.residual_test`) of a calibrated solution.

    Residuals ``t_ij - |r_i - s_j| / c - delta_i - tau_j`` (004 eq. 3.1) over the observed
    entries of the (I, J) matrix ``T`` (s); parameters: the coordinates of the solution's
    dimension up to a rigid motion (``solution.dim``: 2-D for the 2-D model and known heights)
    plus I + J - 1 offsets. Returns a :class:`selfcal.toa.ResidualTest`.
    """
    from ..toa.solve import n_parameters, residual_test

    r, s = np.asarray(solution.receivers, float), np.asarray(solution.sources, float)
    pred = (np.linalg.norm(r[:, None, :] - s[None, :, :], axis=-1) / speed
            + np.asarray(solution.receiver_offsets, float)[:, None]
            + np.asarray(solution.source_offsets, float)[None, :])
    dim = solution.dim
    return residual_test(np.asarray(T, float) - pred, noise, n_parameters(r.shape[0], s.shape[0], dim, "both"))


RESIDUAL_ALPHA = 1e-3  # level of the residual check (scale and per-unit parts together)
MAD_VAR = 1.3605  # asymptotic variance * m of the normal-consistent MAD scale estimate (Hampel 1974)


@dataclass(frozen=True)
class ResidualCheck:
    """Does the calibrated model explain the detections within their noise model?

    Detection errors in a reverberant room are a Gaussian core plus a tail (a reflection
    overlapping the direct path biases a few detections by a fraction of a microsecond),
    so a plain chi-square over all residuals rejects correct fits at large m and is driven
    by the tail. The check has two robust parts, each at ``alpha / 2``:

    1. *scale*: the normal-consistent MAD ``s = 1.4826 median |z|`` of the standardised
       residuals ``z = e / (std sqrt(1 - p / m))`` must not exceed 1 (the noise model is an
       upper bound of the core) by more than ``Phi^-1(1 - alpha / 2)`` of its sampling std
       ``sqrt(1.3605 / m)``. A wrong basin, a wrong speed of sound or more noise than
       declared raise the whole distribution.
    2. *per unit*: the same MAD scale over each receiver's and each sender's ``n_k``
       detections against ``1 + Phi^-1(1 - alpha / (2 K)) sqrt(1.3605 / n_k)`` (Bonferroni
       over the K units). A unit in a wrong place (a mirrored node) has most of its
       residuals large and fails here; a few detections biased by a grazing reflection do
       not (they are the tail, which a sum of squares would be driven by).

    Attributes
    ----------
    passed : bool
    scale, scale_limit : float
        MAD scale of z and its bound.
    failed_receivers, failed_senders : tuple of int
        Units whose residuals are too large.
    chi2, dof, p_value : float, int, float
        Plain chi-square of all residuals (informative: driven by the tail; its ``chi2 / dof``
        inflates the error bars).
    noise : float
        RMS of the detections' model std, s.
    alpha : float
    """

    passed: bool
    scale: float
    scale_limit: float
    failed_receivers: tuple[int, ...]
    failed_senders: tuple[int, ...]
    chi2: float
    dof: int
    p_value: float
    noise: float
    alpha: float

    def to_dict(self) -> dict[str, Any]:
        """JSON-safe dictionary."""
        return {"passed": self.passed, "scale": self.scale, "scale_limit": self.scale_limit,
                "failed_receivers": list(self.failed_receivers), "failed_senders": list(self.failed_senders),
                "chi2": self.chi2, "dof": self.dof, "p_value": self.p_value, "noise": self.noise,
                "alpha": self.alpha}


def residual_check(residuals: Array, std: Array, event_senders: NDArray[np.int64], n_params: int, *,
                   cap: float, alpha: float = RESIDUAL_ALPHA, leverage: Array | None = None) -> ResidualCheck:
    """Robust residual check of a calibration (:class:`ResidualCheck`).

    Parameters
    ----------
    residuals : (I, E) array
        Detected minus modelled TOA per (receiver, event), s, NaN = not used.
    std : (I, E) array
        Model std of every detection, s (:func:`detection_std`).
    event_senders : (E,) int array
    n_params : int
        Free parameters of the fitted model (gauge removed).
    cap : float
        ``|z|`` bound of the outlier test (larger ``|z|`` were excluded; the per-unit sums cap at it).
    alpha : float
    leverage : (I, E) array, optional
        Residual std factor of every entry, ``sqrt(1 - h)``
        (:func:`selfcal.acoustics.leverage.event_leverage`); default the mean one,
        ``sqrt(1 - n_params / m)``.

    Returns
    -------
    ResidualCheck
    """
    from scipy.stats import chi2 as chi2_dist
    from scipy.stats import norm

    e = np.asarray(residuals, float)
    sd = np.asarray(std, float)
    ok = np.isfinite(e) & np.isfinite(sd) & (sd > 0)
    m = int(ok.sum())
    if leverage is None:
        lev: Any = np.sqrt(max(1.0 - n_params / max(m, 1), 1e-3))
    else:
        lev = np.asarray(leverage, float)
        ok &= np.isfinite(lev) & (lev > 0)
        m = int(ok.sum())
    z = np.where(ok, e / np.where(ok, sd, 1.0) / np.where(ok, lev, 1.0), np.nan)
    zf = z[ok]
    scale = mad_std(zf, centre=False) if m else float("nan")
    limit = 1.0 + float(norm.isf(alpha / 2.0)) * float(np.sqrt(MAD_VAR / max(m, 1)))
    az = np.where(ok, np.abs(z), np.nan)
    es = np.asarray(event_senders)
    J = int(es.max()) + 1 if es.size else 0
    units = [az[i] for i in range(az.shape[0])] + [az[:, es == j].ravel() for j in range(J)]
    n_k = np.array([int(np.isfinite(u).sum()) for u in units])
    K = int((n_k > 0).sum())
    q_unit = float(norm.isf(alpha / 2.0 / max(K, 1)))
    bad = []
    for k, u in enumerate(units):
        if n_k[k] == 0:
            continue
        sk = mad_std(u, centre=False)  # u = |z|: the same scale
        if sk > 1.0 + q_unit * np.sqrt(MAD_VAR / n_k[k]):
            bad.append(k)
    I = az.shape[0]
    bad_r = tuple(int(k) for k in bad if k < I)
    bad_s = tuple(int(k - I) for k in bad if k >= I)
    chi2 = float(np.sum((e[ok] / sd[ok]) ** 2))
    dof = int(m - n_params)
    p = float(chi2_dist.sf(chi2, dof)) if dof > 0 else float("nan")
    passed = bool(m > 0 and not scale > limit and not bad_r and not bad_s)
    noise = float(np.sqrt(np.mean(sd[ok] ** 2))) if m else float("nan")
    return ResidualCheck(passed, scale, limit, bad_r, bad_s, chi2, dof, p, noise, float(alpha))
