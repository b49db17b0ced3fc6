"""The calibration's own verdict against paper 004's requirements, from its error bars.

004 sec. 2.1-2.2 asks for positions within 10 cm and for the timing offsets (internal
delay plus onset of every receiver-sender pair, which bias a range) within 58 us (2 cm at
343 m/s). Without the truth the calibration can only promise what its own error bars
say, so a result *meets* a requirement when twice its standard deviation is within it
(2 sigma, about 95 %): position std (RMS radius, ``sqrt(trace C)``) <= 5 cm and pair-offset
std <= 29 us. The residual test (:mod:`selfcal.acoustics.noise`) checks that the model fits
at all; this module checks that the fit is precise enough.

Error bars. The pair offset ``delta_i + tau_j`` is estimable (gauge-free), so its variance
``a^T N^+ a`` does not depend on the generalised inverse; ``N = J^T W J`` is the weighted
normal matrix of the TOA model (004 eq. 3.1) at the solution with ``W = diag(1 / std_ij^2)``
from the detection noise model, scaled by ``max(1, chi2 / dof)`` when the residuals are
larger than the model says. A pure noise term averages down as ``1 / sqrt(N)`` over N
repetitions of the probes, which gives the number of rounds that would meet the timing
requirement. A timing bias common to every detection (a probe that differs from the
declared one, a loudspeaker's group delay) is invisible here and in the residuals: it
shifts every onset alike.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import scipy.sparse
from numpy.typing import NDArray

from ..requirements import POSITION_REQUIREMENT, SIGMAS, TIMING_REQUIREMENT
from .plausibility import repeats_reason

__all__ = ["POSITION_REQUIREMENT", "TIMING_REQUIREMENT", "SIGMAS", "ErrorBars", "Verdict", "error_bars", "judge"]

Array = NDArray[np.float64]


@dataclass(frozen=True)
class ErrorBars:
    """Standard deviations of a calibration from its weighted normal matrix.

    Attributes
    ----------
    position_std : (I + J,) array
        RMS-radius std ``sqrt(trace C_k)`` of every receiver then sender, m (NaN = dropped).
    delay_std, onset_std : (I,), (J,) arrays
        Std of the internal delays and onsets with the first onset fixed (its std 0), s.
    pair_std : (I, J) array
        Std of ``delta_i + tau_j`` (gauge-free), s.
    inflation : float
        ``max(1, chi2 / dof)`` applied to the model variances.
    """

    position_std: Array
    delay_std: Array
    onset_std: Array
    pair_std: Array
    inflation: float

    def to_dict(self) -> dict[str, Any]:
        """JSON-safe dictionary."""
        return {"position_std": self.position_std, "delay_std": self.delay_std, "onset_std": self.onset_std,
                "pair_std_max": float(np.nanmax(self.pair_std)) if np.isfinite(self.pair_std).any() else None,
                "inflation": self.inflation}


def error_bars(T: Array, std: Array, receivers: Array, sources: Array, speed: float, *,
               free_z: bool = True, chi2_per_dof: float = 1.0) -> ErrorBars:
    """Error bars of a calibrated solution (module docstring).

    Parameters
    ----------
    T : (I, J) array
        Per-sender TOA matrix, s (NaN = missing or excluded).
    std : (I, J) array
        Std of every entry, s (:func:`selfcal.acoustics.noise.sender_std`).
    receivers, sources : (I, d), (J, d) arrays
        Positions, m (rows of dropped units may be NaN).
    speed : float
        m/s.
    free_z : bool
        False when the heights are given (only the horizontal coordinates are unknowns).
    chi2_per_dof : float
        Residual test's ``chi2 / dof``; variances are scaled by ``max(1, chi2_per_dof)``.

    Returns
    -------
    ErrorBars
    """
    r = np.asarray(receivers, float)
    s = np.asarray(sources, float)
    I, J = T.shape
    d = r.shape[1]
    dd = d if free_z else 2
    keep_r = np.isfinite(r).all(axis=1) & np.isfinite(T).any(axis=1)
    keep_s = np.isfinite(s).all(axis=1) & np.isfinite(T).any(axis=0)
    obs = np.isfinite(T) & np.isfinite(std) & (std > 0) & keep_r[:, None] & keep_s[None, :]
    ii, jj = np.nonzero(obs)
    ri, sj = np.flatnonzero(keep_r), np.flatnonzero(keep_s)
    mr = -np.ones(I, dtype=np.int64)
    ms = -np.ones(J, dtype=np.int64)
    mr[ri] = np.arange(len(ri))
    ms[sj] = np.arange(len(sj))
    nI, nJ = len(ri), len(sj)
    diff = r[ii] - s[jj]
    u = diff / np.maximum(np.linalg.norm(diff, axis=1), 1e-9)[:, None]
    u = u[:, :dd] / speed
    w = 1.0 / std[ii, jj]
    n_pos = dd * (nI + nJ)
    n = n_pos + nI + nJ
    m = len(ii)
    cols = [dd * mr[ii][:, None] + np.arange(dd), dd * (nI + ms[jj])[:, None] + np.arange(dd),
            (n_pos + mr[ii])[:, None], (n_pos + nI + ms[jj])[:, None]]
    vals = [u, -u, np.ones((m, 1)), np.ones((m, 1))]
    Cc = np.hstack(cols)
    V = np.hstack(vals) * w[:, None]
    Jw = scipy.sparse.csr_matrix((V.ravel(), (np.repeat(np.arange(m), Cc.shape[1]), Cc.ravel())), shape=(m, n))
    N = (Jw.T @ Jw).toarray()
    infl = max(1.0, float(chi2_per_dof)) if np.isfinite(chi2_per_dof) else 1.0
    C = np.linalg.pinv(N, hermitian=True) * infl
    pos_var = np.array([np.trace(C[dd * k: dd * k + dd, dd * k: dd * k + dd]) for k in range(nI + nJ)])
    pos_std = np.full(I + J, np.nan)
    pos_std[np.concatenate([ri, I + sj])] = np.sqrt(np.maximum(pos_var, 0.0))
    off = C[n_pos:, n_pos:]
    # pair std: var(d_i + t_j) = C_dd + C_tt + 2 C_dt (estimable, gauge-free)
    dv = np.diag(off)[:nI]
    tv = np.diag(off)[nI:]
    cross = off[:nI, nI:]
    pv = dv[:, None] + tv[None, :] + 2.0 * cross
    pair = np.full((I, J), np.nan)
    pair[np.ix_(ri, sj)] = np.sqrt(np.maximum(pv, 0.0))
    # first onset fixed: delta_i + tau_0 and tau_j - tau_0 are estimable too
    j0 = 0
    delay_std = np.full(I, np.nan)
    onset_std = np.full(J, np.nan)
    if nJ:
        delay_std[ri] = pair[ri, sj[j0]]
        ov = tv + tv[j0] - 2.0 * off[nI:, nI + j0]
        onset_std[sj] = np.sqrt(np.maximum(ov, 0.0))
    return ErrorBars(pos_std, delay_std, onset_std, pair, infl)


@dataclass(frozen=True)
class Verdict:
    """PASS / FAIL of a calibration against 004's requirements, from its own error bars.

    Attributes
    ----------
    passed : bool
        Residual test passed (when binding), position and timing requirements met, no
        requirement unjudged.
    reasons : tuple of str
        One line per requirement not met (empty when passed).
    position_std_max : float
        m (largest unit's RMS-radius std).
    timing_std_max : float
        s (largest pair-offset std).
    rounds_needed : int or None
        Probe repetitions (events per sender) that would bring the timing std within
        ``TIMING_REQUIREMENT / SIGMAS`` if it is noise (None when already met).
    """

    passed: bool
    reasons: tuple[str, ...] = field(default=())
    position_std_max: float = float("nan")
    timing_std_max: float = float("nan")
    rounds_needed: int | None = None

    def to_dict(self) -> dict[str, Any]:
        """JSON-safe dictionary."""
        return {"passed": self.passed, "reasons": list(self.reasons), "position_std_max": self.position_std_max,
                "timing_std_max": self.timing_std_max, "rounds_needed": self.rounds_needed}


def judge(bars: ErrorBars | None, *, rounds: int, fit_failed: bool, fit_reason: str = "",
          extra: tuple[str, ...] = (), names: tuple[str, ...] | None = None,
          round_seconds: float | None = None) -> Verdict:
    """Judge 004's requirements from the error bars (module docstring).

    Parameters
    ----------
    bars : ErrorBars or None
        None when the error bars could not be computed (a reason is added).
    rounds : int
        Events per sender in the recording (the smallest count over senders).
    fit_failed : bool
        The residual test rejected the fit.
    fit_reason : str
        Its line.
    extra : tuple of str
        Further reasons (e.g. units dropped).
    names : tuple of str, optional
        Labels of the receivers then the senders (for the worst unit).
    round_seconds : float, optional
        Duration of one round of the probes, s: rounds that would take longer than a working
        day are no remedy (:func:`selfcal.acoustics.plausibility.repeats_reason`).

    Returns
    -------
    Verdict
    """
    reasons: list[str] = []
    if fit_failed:
        reasons.append(fit_reason or "the residual test rejected the fit")
    pmax = tmax = float("nan")
    need: int | None = None
    if bars is None:
        reasons.append("requirement not judged: error bars not available")
    else:
        if np.isfinite(bars.position_std).any():
            pmax = float(np.nanmax(bars.position_std))
        if np.isfinite(bars.pair_std).any():
            tmax = float(np.nanmax(bars.pair_std))
        plim = POSITION_REQUIREMENT / SIGMAS
        tlim = TIMING_REQUIREMENT / SIGMAS
        if not np.isfinite(pmax) or pmax > plim:
            k = int(np.nanargmax(bars.position_std)) if np.isfinite(pmax) else -1
            reasons.append(f"requirement not met: position std {pmax * 100:.3g} cm > {plim * 100:.3g} cm "
                           f"({POSITION_REQUIREMENT * 100:.0f} cm at {SIGMAS:g} sigma)"
                           + (f", worst {names[k] if names is not None else f'unit #{k}'}" if k >= 0 else ""))
        if not np.isfinite(tmax) or tmax > tlim:
            need = int(math.ceil(max(rounds, 1) * (tmax / tlim) ** 2)) if np.isfinite(tmax) else None
            absurd = repeats_reason(need, float("nan") if round_seconds is None else round_seconds, tmax, tlim)
            if absurd is not None:
                reasons.append(absurd)
            else:
                    reasons.append(f"requirement not met: delay std {tmax * 1e6:.3g} us > {tlim * 1e6:.3g} us "
                               f"({TIMING_REQUIREMENT * 1e6:.0f} us at {SIGMAS:g} sigma)"
                               + (f": repeat the probes {need} times (rounds per loudspeaker; the std falls as "
                                  f"1/sqrt(rounds))" if need is not None else ""))
    reasons.extend(extra)
    return Verdict(not reasons, tuple(reasons), pmax, tmax, need)
