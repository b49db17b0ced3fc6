"""The whole system of paper 004: recordings -> arrival times -> delays -> positions.

Orchestration only; the jobs live in their modules:

- :mod:`.detect`     stage 1: matched-filter arrival times with their quality (CFAR floor)
- :mod:`.noise`      the timing-noise model of the detections (residual and outlier tests)
- :mod:`.calibrate`  stages 2 + 3 through :func:`selfcal.toa.solve_toa`: one model fit,
                     robust to a minority of wrong detections, dropping unobservable units
- :mod:`.geometry`   near-planarity, mirror ambiguities, known heights (2-D fallback)
- :mod:`.verdict`    PASS / FAIL against 004's requirements from the result's error bars
- :mod:`.scoring`    comparison with a simulation's ``truth.json``
- :mod:`.report`     the installer's HTML report
"""

from __future__ import annotations

import time
import warnings
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .._checks import entry
from .._result import Result
from ..errors import DegenerateGeometryError, InputError, Status
from ..requirements import POSITION_REQUIREMENT, TIMING_REQUIREMENT
from .calibrate import _predict, calibrate_matrix, sender_matrix
from .geometry import (
    ModelComparison,
    Planarity,
    compare_fits,
    one_side_of_plane,
    planarity,
    read_heights,
    refine_known_heights,
)
from .noise import MF_FACTOR, TIMING_FLOOR, detection_std, fit_test, residual_check, timing_noise
from .plausibility import extent_reason
from .robust_fit import Outlier, robust_calibrate
from .scale import apply_scale, scale_from_distances
from .scoring import truth_errors
from .solution import Calibration
from .units import unit_pairs
from .verdict import ErrorBars, Verdict, error_bars, judge

__all__ = [
    "PipelineResult",
    "Planarity",
    "ModelComparison",
    "planarity",
    "compare_fits",
    "one_side_of_plane",
    "sender_matrix",
    "refine_known_heights",
    "calibrate_matrix",
    "run_pipeline",
    "read_heights",
    "truth_errors",
    "timing_noise",
    "fit_test",
    "TIMING_REQUIREMENT",
    "POSITION_REQUIREMENT",
    "MF_FACTOR",
    "TIMING_FLOOR",
]

Array = NDArray[np.float64]
FAIL_MESSAGE = "calibration failed the residual test: positions NOT reliable"
SPEED_NOTE = ("scale: with unknown offsets the scale of the geometry comes from the speed of sound "
              "({c:.2f} m/s): a 1 % error in c scales every distance by 1 %")
BIAS_NOTE = ("a timing bias common to every detection (a probe differing from the declared one, a loudspeaker's "
             "group delay) is invisible in the residuals and lands in the onsets")


@dataclass(frozen=True, repr=False)
class PipelineResult(Result):
    """Positions, delays and onsets from a recording directory.

    Attributes
    ----------
    receivers : (I, d) array
        Microphone positions, m (d = 3, or 2 for a near-planar layout without heights);
        NaN rows for dropped microphones.
    sources : (J, d) array
        Loudspeaker positions, m (NaN rows for dropped loudspeakers).
    receiver_offsets : (I,) array
        Internal delays, s.
    source_offsets : (J,) array
        Onset times, s, the first kept one 0 (only differences are observable).
    receiver_cov, source_cov : (I, d, d), (J, d, d) arrays
        Position covariances, m^2.
    residual_rms : float
        RMS TOA residual, s.
    converged : bool
    iterations : int
    method : str
        ``"3d"``, ``"2d"`` or ``"2d+heights"`` plus the TOA solver's method.
    toa_matrix : (I, E) array
        TOA per (receiver, event) used by the fit, s, NaN = missed or excluded.
    detections_missed : int
    quality_db : (I, E) array
    planarity : Planarity or None
    timings : dict
        Seconds per stage: ``load``, ``detect``, ``calibrate``.
    receiver_names, sender_names : tuple of str
    speed_of_sound : float
    notes : tuple of str
    fit : ResidualTest or None
        Chi-square test of the final residuals against ``timing_noise``.
    timing_noise : float
        Noise std used by the test, s.
    outliers : tuple of Outlier
        Detections excluded (or re-detected) by the robust fit.
    dropped_receivers, dropped_senders : tuple of str
        Names of the units left out (not enough detections).
    error_bars : ErrorBars or None
        Position, delay, onset and pair-offset stds.
    verdict : Verdict or None
        004 requirements judged from the error bars (:func:`selfcal.acoustics.verdict.judge`).
    rounds : int
        Events per sender (the smallest count).
    event_senders : (E,) int array or None
        Sender of every event (columns of ``toa_matrix``).
    matrix_std : (I, J) array or None
        Noise-model std of the per-sender TOA matrix, s.
    timings_cpu : dict
        CPU seconds of this process per stage (comparable on a shared machine).
    uniqueness : UniquenessTest or None
        The TOA solver's uniqueness test of the final fit (:mod:`selfcal.toa.verdict.uniqueness`), in the
        recording's numbering and the solver's frame; None for the known-heights model.
    outlier_breakdown : str or None
        The TOA solver's outlier-breakdown verdict of the final fit, when it fired.
    known_heights : bool
        The ``2d+heights`` model: every z given, x and y fitted (``known_heights`` of
        :class:`selfcal.acoustics.solution.Calibration`); not in :meth:`to_dict` (``method`` says it).
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
    outliers: tuple[Outlier, ...] = field(default=())
    dropped_receivers: tuple[str, ...] = field(default=())
    dropped_senders: tuple[str, ...] = field(default=())
    error_bars: ErrorBars | None = None
    verdict: Verdict | None = None
    rounds: int = 1
    event_senders: NDArray[np.int64] | None = None
    matrix_std: Array | None = None
    timings_cpu: dict[str, float] = field(default_factory=dict)
    uniqueness: Any = None
    outlier_breakdown: str | None = None
    known_heights: bool = False

    @property
    def failed(self) -> bool:
        """True when the calibration does not meet its own test or 004's requirements.

        The residual test rejected the fit, or the error bars miss 10 cm / 58 us at 2 sigma,
        or they could not be judged (:attr:`verdict`).
        """
        if self.verdict is not None:
            return not self.verdict.passed
        return bool(self.fit is not None and not self.fit.passed)

    @property
    def success(self) -> bool:
        """``not failed``."""
        return not self.failed

    @property
    def status(self) -> Status:
        """``Status.SUCCESS`` (0) = trustworthy, ``Status.FAILED_TEST`` (2) = failed its own test
        (the CLI then exits 1)."""
        return Status.FAILED_TEST if self.failed else Status.SUCCESS

    @property
    def noise(self) -> float:
        """The timing-noise std the residual test used (alias of ``timing_noise``), s."""
        return self.timing_noise

    @property
    def message(self) -> str:
        """The verdict in one line."""
        if self.verdict is None or self.verdict.passed:
            return "calibration meets the 004 requirements by its own error bars"
        return "; ".join(self.verdict.reasons)

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
            "timings": self.timings, "timings_cpu": self.timings_cpu, "receiver_names": list(self.receiver_names),
            "sender_names": list(self.sender_names), "speed_of_sound": self.speed_of_sound,
            "notes": list(self.notes),
            "fit": None if self.fit is None else self.fit.to_dict(), "failed": self.failed,
            "status": self.status, "success": self.success, "message": self.message,
            "timing_noise": self.timing_noise,
            "outliers": [o.to_dict() for o in self.outliers],
            "dropped_receivers": list(self.dropped_receivers), "dropped_senders": list(self.dropped_senders),
            "error_bars": None if self.error_bars is None else self.error_bars.to_dict(),
            "verdict": None if self.verdict is None else self.verdict.to_dict(),
            "rounds": self.rounds,
            "event_senders": None if self.event_senders is None else [int(j) for j in self.event_senders],
            "uniqueness": None if self.uniqueness is None else self.uniqueness.to_dict(),
            "ambiguous_receivers": [] if self.uniqueness is None else
            [self.receiver_names[i] for i in np.flatnonzero(self.uniqueness.ambiguous_receivers)],
            "ambiguous_senders": [] if self.uniqueness is None else
            [self.sender_names[j] for j in np.flatnonzero(self.uniqueness.ambiguous_sources)],
            "outlier_breakdown": self.outlier_breakdown,
        }


def _alternative_moves(sol: Calibration) -> tuple[Array, Array]:
    """The move to every unit's farthest alternative position the data do not reject, m.

    Alternatives of :mod:`selfcal.toa.verdict.uniqueness` that the pipeline's stated one-side
    rule excludes (a unit placed on one side of its coplanar partners, moved to the other) are
    not counted. Returns ``(I, d)`` and ``(J, d)`` arrays: zero rows where a unit has none,
    ``inf`` rows where an alternative has no position (nothing can be promised).
    """
    R, S = np.asarray(sol.receivers, float), np.asarray(sol.sources, float)
    disp_r, disp_s = np.zeros_like(R), np.zeros_like(S)
    u = sol.uniqueness
    if u is None or u.passed:
        return disp_r, disp_s
    side = sol.one_side
    plane = None
    if side is not None:  # the one-side rule: these units all on one side of their partners' plane
        P = S if side == "receivers" else R
        P = P[np.isfinite(P).all(axis=1)]
        plane = (P.mean(axis=0), np.linalg.svd(P - P.mean(axis=0), full_matrices=False)[2][-1])

    def moves(X: Array, out: Array, role: str, cands: list[tuple[int, Array]]) -> None:
        for k, p in cands:
            p = np.asarray(p, float)
            if not np.isfinite(X[k]).all():
                continue
            if not np.isfinite(p).all():
                out[k] = np.inf
                continue
            if plane is not None and role == side:
                c, n = plane
                if np.sign((p - c) @ n) != np.sign((X[k] - c) @ n):
                    continue  # on the other side of the partners' plane: excluded by the stated rule
            if np.linalg.norm(p - X[k]) > np.linalg.norm(out[k]):
                out[k] = p - X[k]

    cand_r = [(int(i), u.receiver_alternatives[i]) for i in np.flatnonzero(u.ambiguous_receivers)]
    cand_s = [(int(j), u.source_alternatives[j]) for j in np.flatnonzero(u.ambiguous_sources)]
    for a in u.alternatives:  # every listed alternative, not only the first one found per unit
        cand_r += [(int(i), p) for i, p in zip(a.receivers, a.receiver_positions, strict=True)]
        cand_s += [(int(j), p) for j, p in zip(a.sources, a.source_positions, strict=True)]
    moves(R, disp_r, "receivers", cand_r)
    moves(S, disp_s, "sources", cand_s)
    return disp_r, disp_s


def _cover_alternatives(sol: Calibration, bars: ErrorBars | None) -> tuple[Calibration, ErrorBars | None]:
    """Error bars that cover the alternatives the data leave open (mixture covariance).

    Where the uniqueness test leaves a unit two positions ``x`` and ``x + m`` that fit equally
    well, the data give each the same weight: the covariance of that equal mixture is
    ``C + m m^T / 4``. It replaces the unit's local covariance ``C`` (and its RMS-radius std),
    so the reported error bar spans both answers (3 stds of ``sqrt(C + m m^T/4)`` along ``m``
    exceed ``|m|``) instead of claiming the one found. Units with no alternative are unchanged.
    """
    disp_r, disp_s = _alternative_moves(sol)
    if not (disp_r.any() or disp_s.any()):
        return sol, bars
    with np.errstate(invalid="ignore"):
        add_r = np.einsum("ki,kj->kij", disp_r, disp_r) / 4.0
        add_s = np.einsum("ki,kj->kij", disp_s, disp_s) / 4.0
    add_r[~np.isfinite(add_r)] = np.inf
    add_s[~np.isfinite(add_s)] = np.inf
    rc, sc = np.asarray(sol.receiver_cov, float), np.asarray(sol.source_cov, float)
    if rc.shape == add_r.shape:
        sol = replace(sol, receiver_cov=rc + add_r)
    if sc.shape == add_s.shape:
        sol = replace(sol, source_cov=sc + add_s)
    if bars is not None:
        extra = np.concatenate([np.sum(disp_r**2, axis=1), np.sum(disp_s**2, axis=1)]) / 4.0
        bars = replace(bars, position_std=np.sqrt(np.asarray(bars.position_std, float) ** 2 + extra))
    return sol, bars


def _unique_or_plausible(sol: Calibration, rn: tuple[str, ...], sn: tuple[str, ...],
                         room: tuple[float, ...] | None, notes: list[str]) -> tuple[str, ...]:
    """FAIL reasons from the TOA solver's own tests and the declared room (:mod:`.plausibility`).

    - the uniqueness test (:mod:`selfcal.toa.verdict.uniqueness`): a minimal problem, or units with an
      alternative position the data do not reject *farther than the position requirement*
      (10 cm: the truth may be there, so 004 cannot be promised), named with the remedy;
      alternatives closer than that leave the requirement met whichever is true and are a
      note. Alternatives that put a unit which :func:`calibrate_matrix` placed on one side of
      its coplanar partners (its note) on the other side are excluded by that stated rule,
      not by the data, and are not counted here. ``sol`` must be in the solver's frame
      (before any scale);
    - the outlier breakdown of the final fit;
    - positions spanning far more than the declared room.
    """
    out: list[str] = []
    u = sol.uniqueness
    if u is not None and not u.passed:
        disp_r, disp_s = _alternative_moves(sol)
        move_r, move_s = np.linalg.norm(disp_r, axis=1), np.linalg.norm(disp_s, axis=1)
        far_r = move_r > POSITION_REQUIREMENT
        far_s = move_s > POSITION_REQUIREMENT
        far_r &= np.asarray(u.ambiguous_receivers, bool)
        far_s &= np.asarray(u.ambiguous_sources, bool)
        who = ([f"microphone {rn[i]}" for i in np.flatnonzero(far_r)]
               + [f"loudspeaker {sn[j]}" for j in np.flatnonzero(far_s)])
        if who:
            worst = float(max(move_r[far_r].max(initial=0.0), move_s[far_s].max(initial=0.0)))
            more = f" and {len(who) - 12} more" if len(who) > 12 else ""
            out.append(f"not unique: {', '.join(who[:12])}{more} fit the data as well at another position up to "
                       f"{worst:.3g} m away (> {POSITION_REQUIREMENT * 100:.0f} cm; likelihood-ratio test, level "
                       f"{u.alpha:g}; alternatives in the JSON 'uniqueness'); remedy: give known heights (--heights) "
                       "or add a unit off the plane of their partners")
        near = int((move_r > 0).sum() + (move_s > 0).sum()) - len(who)
        if near > 0:
            notes.append(f"uniqueness: {near} unit(s) have an alternative position the data do not reject within "
                         f"{POSITION_REQUIREMENT * 100:.0f} cm (the requirement holds whichever is true)")
        if u.minimal:
            out.append("not tested: no spare measurement, the fit is exact whatever the geometry (a minimal "
                       "problem is not a determined one); add units or detections")
    if sol.outlier_breakdown:
        out.append(str(sol.outlier_breakdown) + ": positions NOT reliable")
    why = extent_reason(np.asarray(sol.receivers), np.asarray(sol.sources), room)
    if why is not None:
        out.append(why)
    return tuple(out)


@entry(rng="rng", jitter="nonnegative?", speed_of_sound="positive?")
def run_pipeline(
    directory: str | Path,
    *,
    dim: int | str = "auto",
    heights: str | Path | tuple[Array, Array] | None = None,
    progress: bool = True,
    rng: int = 0,
    detect_options: dict[str, Any] | None = None,
    jitter: float | None = None,
    speed_of_sound: float | None = None,
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
    speed_of_sound : float, optional
        m/s; default the setup's (``speed_of_sound``, or from ``temperature``).

    Returns
    -------
    PipelineResult

    Raises
    ------
    InputError
        Invalid recording directory or heights file.
    DegenerateGeometryError
        Too few detections for the unknowns, or ``dim=3`` on a near-planar layout.

    Examples
    --------
    A recording directory (:doc:`/recording_format`), e.g. simulated by
    ``selfcal simulate conference --units 20 --out rec/``; the run takes seconds to minutes:

    >>> from selfcal.acoustics import run_pipeline
    >>> res = run_pipeline("rec/")  # doctest: +SKIP
    >>> res.success, res.receivers.shape  # doctest: +SKIP
    (True, (20, 3))
    """
    from ..progress import stage
    from .detect import detect_recording, redetect_arrivals
    from .recording import MAX_SPEED_OF_SOUND, load_recording

    timings: dict[str, float] = {}
    cpu: dict[str, float] = {}
    t0, c0 = time.perf_counter(), time.process_time()
    rec = load_recording(directory)
    setup = rec.setup
    timings["load"] = time.perf_counter() - t0
    cpu["load"] = time.process_time() - c0
    # validated before the (slow) detection: bad input fails fast
    if jitter is None:
        jitter = setup.clock_jitter
    if not np.isfinite(jitter) or jitter < 0:
        raise InputError(f"jitter must be a finite standard deviation >= 0 s, got {jitter!r}")
    speed = float(setup.speed_of_sound if speed_of_sound is None else speed_of_sound)
    if not np.isfinite(speed) or speed <= 0:
        raise InputError(f"speed of sound must be a positive number of m/s, got {speed_of_sound!r}")
    if speed > MAX_SPEED_OF_SOUND:
        raise InputError(f"speed of sound {speed:g} m/s exceeds the physical bound {MAX_SPEED_OF_SOUND:g} m/s "
                         f"of any medium; is it in m/s?")
    hz = None
    if heights is not None:
        hz = (read_heights(heights, setup.receivers, setup.senders) if isinstance(heights, (str, Path))
              else (np.asarray(heights[0], float), np.asarray(heights[1], float)))
        if hz[0].shape != (len(setup.receivers),) or hz[1].shape != (len(setup.senders),):
            raise InputError("heights: need one height per receiver and per sender")
    t0, c0 = time.perf_counter(), time.process_time()
    det = detect_recording(rec, progress=progress, **(detect_options or {}))
    timings["detect"] = time.perf_counter() - t0
    cpu["detect"] = time.process_time() - c0
    es = setup.event_senders
    J = len(setup.senders)
    if np.isnan(det.toa).all():
        raise DegenerateGeometryError("no arrival was detected in any recording; check the probe and levels",
                                      kind="no-detections")
    fs = setup.sample_rate
    std_e = detection_std(det.quality_db, rec.probe.band, jitter=jitter, sample_rate=fs)
    noise = timing_noise(np.where(np.isfinite(det.toa), det.quality_db, np.nan), rec.probe.band, es, J,
                         jitter=jitter, sample_rate=fs)
    counts = np.bincount(es, minlength=J)
    rounds = int(counts[counts > 0].min()) if (counts > 0).any() else 1

    def redetect(ri: NDArray[np.intp], ev: NDArray[np.intp], pred: Array, half: Array) -> tuple[Array, Array]:
        t, q = redetect_arrivals(rec, det, ri, ev, pred, half)
        s = detection_std(q[None, :], rec.probe.band, jitter=jitter, sample_rate=fs)[0]
        return t, s

    t0, c0 = time.perf_counter(), time.process_time()
    with stage(f"calibrate {len(setup.receivers)} x {J}", show=None if progress else False):
        robust = robust_calibrate(det.toa, std_e, es, J, speed=speed, dim=dim, heights=hz, rng=rng,
                                  noise=noise if np.isfinite(noise) else None, redetect=redetect,
                                  names=(setup.receivers, setup.senders),
                                  units=unit_pairs(setup.receivers, setup.senders))
    sol, plan, notes = robust.solution, robust.planarity, list(robust.notes)
    timings["calibrate"] = time.perf_counter() - t0
    cpu["calibrate"] = time.process_time() - c0
    T, S = robust.matrix, robust.matrix_std
    extra = _unique_or_plausible(sol, setup.receivers, setup.senders, setup.room, notes)  # the solver's frame
    if setup.unit_offsets:
        idx = [(setup.receivers.index(n), setup.senders.index(n), d) for n, d in setup.unit_offsets.items()]
        ri = np.array([a for a, _, _ in idx])
        sj = np.array([b for _, b, _ in idx])
        Dk = np.array([c for _, _, c in idx])
        good = np.isfinite(np.asarray(sol.receivers)[ri]).all(axis=1) & np.isfinite(np.asarray(sol.sources)[sj]).all(axis=1)
        if good.any():
            lam, lam_std = scale_from_distances(sol, ri[good], sj[good], Dk[good])
            sol = apply_scale(sol, lam)
            notes.append(f"scale from {int(good.sum())} known microphone-loudspeaker distances (unit_offsets): "
                         f"effective speed of sound {speed * lam:.2f} +- {speed * lam_std:.2f} m/s "
                         f"(assumed {speed:.2f} m/s, distances x {lam:.5f})")
            speed = speed * lam
    fit = None
    kr = np.isfinite(np.asarray(sol.receivers)).all(axis=1)
    ks = np.asarray(np.isfinite(np.asarray(sol.sources)).all(axis=1), bool)
    pred = _predict(sol, speed)
    res_e = robust.toa - pred[:, es]
    res_e[~kr] = np.nan
    res_e[:, ~ks[es]] = np.nan
    if np.isfinite(res_e).any():
        fit = residual_check(res_e, robust.std, es, robust.n_params, cap=robust.threshold)
    fit_reason = ""
    if fit is not None and not fit.passed:
        where = []
        if fit.scale > fit.scale_limit:
            where.append(f"residual scale {fit.scale:.3g} > {fit.scale_limit:.3g} of the noise model")
        if fit.failed_receivers:
            where.append("microphones " + ", ".join(setup.receivers[i] for i in fit.failed_receivers[:8]))
        if fit.failed_senders:
            where.append("loudspeakers " + ", ".join(setup.senders[j] for j in fit.failed_senders[:8]))
        fit_reason = (f"{FAIL_MESSAGE} ({'; '.join(where)}; chi2 {fit.chi2:.4g} on {fit.dof} dof, "
                      f"timing noise {noise * 1e6:.3g} us): a wrong basin, bad detections or a larger noise than "
                      "assumed")
        if sol.dim == 2 and not sol.known_heights:
            fit_reason += "; the 2-D model ignores the heights: give them with --heights"
        warnings.warn(fit_reason, stacklevel=2)
        notes.append(fit_reason)
    bars = None
    try:
        bars = error_bars(T, S, np.asarray(sol.receivers), np.asarray(sol.sources), speed,
                          free_z=hz is None and np.asarray(sol.receivers).shape[1] == 3,
                          chi2_per_dof=(fit.chi2 / fit.dof) if fit is not None and fit.dof > 0 else 1.0)
    except (np.linalg.LinAlgError, ValueError):
        bars = None
    sol, bars = _cover_alternatives(sol, bars)  # error bars spanning the alternatives left open
    labels = tuple(f"microphone {n}" for n in setup.receivers) + tuple(f"loudspeaker {n}" for n in setup.senders)
    verdict = judge(bars, rounds=rounds, fit_failed=fit is not None and not fit.passed, fit_reason=fit_reason,
                    names=labels, extra=extra, round_seconds=rec.signals.shape[1] / fs / max(rounds, 1))
    if not setup.unit_offsets:
        notes.append(SPEED_NOTE.format(c=speed))
    notes.append(BIAS_NOTE)
    # units the TOA fit itself dropped (NaN rows, e.g. more flagged ranges than a position can hold)
    lost_r = [int(i) for i in np.flatnonzero(~np.isfinite(np.asarray(sol.receivers)).all(axis=1))
              if i not in robust.dropped_receivers]
    lost_s = [int(j) for j in np.flatnonzero(~np.isfinite(np.asarray(sol.sources)).all(axis=1))
              if j not in robust.dropped_senders]
    if lost_r or lost_s:
        notes.append("dropped by the TOA fit (not located): " + ", ".join(
            [f"microphone {setup.receivers[i]}" for i in lost_r] + [f"loudspeaker {setup.senders[j]}" for j in lost_s]))
    dr = tuple(setup.receivers[i] for i in sorted(int(k) for k in [*robust.dropped_receivers, *lost_r]))
    dsn = tuple(setup.senders[j] for j in sorted(int(k) for k in [*robust.dropped_senders, *lost_s]))
    return PipelineResult(
        receivers=sol.receivers, sources=sol.sources, receiver_offsets=sol.receiver_offsets,
        source_offsets=sol.source_offsets, receiver_cov=sol.receiver_cov, source_cov=sol.source_cov,
        residual_rms=sol.residual_rms, converged=sol.converged, iterations=sol.iterations,
        method=sol.method, toa_matrix=robust.toa, detections_missed=int(np.isnan(robust.toa).sum()),
        quality_db=det.quality_db, planarity=plan, timings=timings, receiver_names=setup.receivers,
        sender_names=setup.senders, speed_of_sound=speed, notes=tuple(notes), fit=fit, timing_noise=noise,
        outliers=tuple(robust.outliers), dropped_receivers=dr, dropped_senders=dsn,
        error_bars=bars, verdict=verdict, rounds=rounds, event_senders=np.asarray(es, dtype=np.int64),
        matrix_std=S, timings_cpu=cpu, uniqueness=sol.uniqueness,
        outlier_breakdown=sol.outlier_breakdown, known_heights=sol.known_heights,
    )
