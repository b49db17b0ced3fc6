"""Robust calibration from the event TOA matrix: outliers, re-detection, dropped units (004, issue 15).

Around the one model fit of :func:`selfcal.acoustics.calibrate.calibrate_matrix`:

- **the TOA package's outlier rule first**: entries :func:`selfcal.toa.solve_toa` rejected
  are the first outliers, re-detected near the time its fit predicts;
- **event-level outliers** (:func:`robust_calibrate`): after a fit the residual of every
  detection is standardised by its noise model (:mod:`selfcal.acoustics.noise`) and its own
  leverage (:func:`selfcal.acoustics.leverage.event_leverage`); a residual beyond the
  Bonferroni bound ``Phi^-1(1 - alpha / (2 m))`` (``alpha`` = 1 % family-wise) that is the
  largest of its receiver and of its sender is an outlier. It is excluded (or re-detected in
  a narrow window around its predicted time), and the fit is refined from where it stands;
  repeated until no outlier is left. The loop works on events (several per sender), which
  ``solve_toa`` never sees: it fits the per-sender means.
- **units without enough detections are dropped** (fewer than ``d + 2`` senders for a
  receiver or receivers for a sender: not identifiable with a check left), with a note,
  and the rest are calibrated.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..errors import DegenerateGeometryError
from ..robust import TUNING, mad_std
from .calibrate import (
    _predict,
    _scatter_nodes,
    calibrate_matrix,
    n_parameters_of,
    refit,
    sender_matrix,
)
from .geometry import Planarity
from .leverage import event_leverage
from .solution import Calibration

__all__ = ["robust_calibrate", "Outlier", "RobustFit", "OUTLIER_ALPHA"]

Array = NDArray[np.float64]

OUTLIER_ALPHA = 0.01  # family-wise false-alarm probability of the outlier test over all detections


MAX_OUTLIER_ROUNDS = 12


@dataclass(frozen=True)
class Outlier:
    """A detection the robust fit excluded (or re-detected).

    Attributes
    ----------
    receiver, event, sender : int
        Indices (rows of the TOA matrix, events of setup.json, senders).
    residual : float
        Detected minus modelled TOA, s.
    z : float
        Residual over its standard deviation (noise model and leverage).
    redetected : bool
        A new detection near the predicted time replaced it.
    new_residual : float
        Residual of the replacement, s (NaN when not re-detected).
    """

    receiver: int
    event: int
    sender: int
    residual: float
    z: float
    redetected: bool = False
    new_residual: float = float("nan")

    def to_dict(self) -> dict[str, Any]:
        """JSON-safe dictionary."""
        return {"receiver": self.receiver, "event": self.event, "sender": self.sender, "residual": self.residual,
                "z": self.z, "redetected": self.redetected, "new_residual": self.new_residual}


@dataclass(frozen=True)
class RobustFit:
    """Outcome of :func:`robust_calibrate`.

    Attributes
    ----------
    solution : Calibration
        Full-size solution (dropped units' rows NaN).
    planarity : Planarity or None
    notes : list of str
    outliers : list of Outlier
    toa : (I, E) array
        The event TOA matrix after exclusions / re-detections, s.
    matrix, matrix_std : (I, J) arrays
        Per-sender TOA matrix and its std, s (dropped units NaN).
    dropped_receivers, dropped_senders : list of int
    threshold : float
        Bonferroni bound on |z| used.
    std : (I, E) array
        Detection stds after re-detections, s.
    n_params : int
        Free parameters of the kept model.
    leverage : (I, E) array or None
        Residual std factor ``sqrt(1 - h / n)`` of every detection in the final fit
        (:func:`selfcal.acoustics.leverage.event_leverage`), NaN where not used.
    """

    solution: Calibration
    planarity: Planarity | None
    notes: list[str]
    outliers: list[Outlier]
    toa: Array
    matrix: Array
    matrix_std: Array
    dropped_receivers: list[int]
    dropped_senders: list[int]
    threshold: float
    std: Array
    n_params: int
    leverage: Array | None = None


def _drop_units(T: Array, need: int) -> tuple[NDArray[np.bool_], NDArray[np.bool_]]:
    """Receivers / senders kept: at least ``need`` observations among the kept others (iterated)."""
    kr = np.ones(T.shape[0], bool)
    ks = np.ones(T.shape[1], bool)
    obs = np.isfinite(T)
    while True:
        sub = obs & kr[:, None] & ks[None, :]
        nr = kr & (sub.sum(axis=1) >= need)
        ns = ks & (sub.sum(axis=0) >= need)
        if (nr == kr).all() and (ns == ks).all():
            return kr, ks
        kr, ks = nr, ns


def robust_calibrate(
    toa: Array,
    std: Array,
    event_senders: NDArray[np.int64],
    n_senders: int,
    *,
    speed: float,
    dim: int | str = "auto",
    heights: tuple[Array, Array] | None = None,
    rng: int = 0,
    noise: float | None = None,
    redetect: Callable[[NDArray[np.intp], NDArray[np.intp], Array, Array], tuple[Array, Array]] | None = None,
    alpha: float = OUTLIER_ALPHA,
    names: tuple[tuple[str, ...], tuple[str, ...]] | None = None,
    units: NDArray[np.intp] | None = None,
) -> RobustFit:
    """Calibrate from the event TOA matrix with outlier exclusion and unit dropping (module docstring).

    Parameters
    ----------
    toa : (I, E) array
        Detected TOA of every event (arrival minus nominal time), s, NaN = missed.
    std : (I, E) array
        Noise-model std of every detection, s (:func:`selfcal.acoustics.noise.detection_std`).
    event_senders : (E,) int array
    n_senders : int
    speed : float
        m/s.
    dim, heights, rng :
        As :func:`calibrate_matrix`.
    noise : float, optional
        Timing-noise std of the residual test, s; when the cleaned fit fails that test the
        deep search of :func:`selfcal.toa.solve_toa` runs once on the cleaned matrix.
    redetect : callable, optional
        ``redetect(receivers, events, predicted_toa, half_width) -> (toa, std)`` (NaN =
        nothing acceptable): a new detection of an outlier near its predicted time.
    alpha : float
        Family-wise false-alarm probability of the outlier test.
    names : (receiver names, sender names), optional
        For the notes.
    units : (K, 2) int array, optional
        ``(receiver, sender)`` of the units (:func:`selfcal.acoustics.units.unit_pairs`):
        the start of the searches (:func:`calibrate_matrix`), restricted to the kept units.

    Returns
    -------
    RobustFit

    Raises
    ------
    DegenerateGeometryError
        Fewer than ``d + 2`` units left on one side (``kind="unobservable-node"``), or as
        :func:`calibrate_matrix`.
    """
    from scipy.stats import norm

    toa = np.array(toa, dtype=float)
    std = np.asarray(std, float)
    es = np.asarray(event_senders, dtype=np.int64)
    I, E = toa.shape
    J = int(n_senders)
    rn, sn = names if names is not None else (tuple(f"#{i}" for i in range(I)), tuple(f"#{j}" for j in range(J)))
    d_model = 2 if (dim == 2 or heights is not None) else 3
    need = d_model + 2
    notes: list[str] = []
    T = sender_matrix(toa, es, J)
    kr, ks = _drop_units(T, need)
    if kr.sum() < need or ks.sum() < need:
        raise DegenerateGeometryError(
            f"only {int(kr.sum())} receivers and {int(ks.sum())} senders have >= {need} detections each; "
            "too few to calibrate (check levels, cabling and the event times)", kind="unobservable-node")
    dropped_r = [int(i) for i in np.flatnonzero(~kr)]
    dropped_s = [int(j) for j in np.flatnonzero(~ks)]
    for i in dropped_r:
        notes.append(f"dropped microphone {rn[i]}: {int(np.isfinite(T[i]).sum())} of {J} senders detected "
                     f"(need {need}); dead, disconnected or silent input")
    for j in dropped_s:
        notes.append(f"dropped loudspeaker {sn[j]}: heard by {int(np.isfinite(T[:, j]).sum())} of {I} "
                     f"microphones (need {need}); silent, or its events are missing from the audio")
    hz = None if heights is None else (np.asarray(heights[0])[kr], np.asarray(heights[1])[ks])
    ev_keep = ks[es]
    sub_es = np.cumsum(ks)[es] - 1  # sender index within the kept senders
    t_ev = toa[np.ix_(kr, ev_keep)]
    s_ev = std[np.ix_(kr, ev_keep)]
    es_k = sub_es[ev_keep]
    Jk = int(ks.sum())
    Tk = sender_matrix(t_ev, es_k, Jk)
    from .noise import sender_std

    def wts() -> Array | None:
        """1 / std of the per-sender entries: the known-heights fit is weighted (the only one
        that takes weights, :func:`calibrate_matrix`)."""
        if hz is None:
            return None
        with np.errstate(divide="ignore", invalid="ignore"):
            return 1.0 / sender_std(s_ev, t_ev, es_k, Jk)

    units_k = None
    if units is not None and len(units):
        u = np.asarray(units, dtype=np.intp).reshape(-1, 2)
        u = u[kr[u[:, 0]] & ks[u[:, 1]]]
        units_k = np.column_stack([np.cumsum(kr)[u[:, 0]] - 1, np.cumsum(ks)[u[:, 1]] - 1])
    sol, plan, cnotes = calibrate_matrix(Tk, speed=speed, dim=dim, heights=hz, rng=rng, weights=wts(), units=units_k)
    notes.extend(cnotes)
    n_par = n_parameters_of(sol, len(Tk), Jk)
    ri_full = np.flatnonzero(kr)
    ev_full = np.flatnonzero(ev_keep)
    outliers: list[Outlier] = []
    m = int(np.isfinite(t_ev).sum())
    zc = float(norm.isf(alpha / (2.0 * max(m, 1))))
    searched = False
    robust_start = False
    needs_ls = False

    def exclude(ok: list[tuple[int, int]], pred: Array, res: Array, z: Array, scale: float, lev: Array) -> None:
        """Record the flagged (receiver, event) entries as outliers; re-detect each near its
        predicted time (kept when within the outlier bound of the prediction), else NaN."""
        if not ok:
            return
        fi = np.array([a for a, _ in ok])
        fe = np.array([b for _, b in ok])
        new_t = np.full(len(fi), np.nan)
        new_s = np.full(len(fi), np.nan)
        if redetect is not None:
            half = np.maximum(zc * s_ev[fi, fe] * scale, 0.0)
            new_t, new_s = redetect(ri_full[fi], ev_full[fe], pred[fi, es_k[fe]], half)
            new_t = np.asarray(new_t, float)
            new_s = np.asarray(new_s, float)
        for k, (a, b) in enumerate(ok):
            nt = new_t[k]
            good = np.isfinite(nt) and abs(nt - pred[a, es_k[b]]) <= zc * new_s[k] * scale * lev[a, b]
            outliers.append(Outlier(int(ri_full[a]), int(ev_full[b]), int(es[ev_full[b]]), float(res[a, b]),
                                    float(z[a, b]), bool(good),
                                    float(nt - pred[a, es_k[b]]) if good else float("nan")))
            t_ev[a, b] = nt if good else np.nan
            if good:
                s_ev[a, b] = new_s[k]

    def standardised(sol: Calibration) -> tuple[Array, Array, Array, float, Array]:
        """Predicted TOA (I, J), event residuals, their z (noise model, leverage, robust scale)."""
        pred = _predict(sol, speed)
        res = t_ev - pred[:, es_k]
        lev = event_leverage(sol, t_ev, es_k, Jk, speed, wts())
        z = res / (s_ev * lev)
        scale = max(1.0, mad_std(z, centre=False)) if np.isfinite(z).any() else 1.0
        return pred, res, z / scale, scale, lev

    # the entries the TOA package's robust fit rejected (solve_toa's outlier rule) are the
    # first outliers: excluded from the start, re-detected near the time that fit predicts
    flagged = np.zeros(Tk.shape, bool) if sol.toa_outliers is None else np.asarray(sol.toa_outliers, bool)
    if flagged.any():
        pred, res, z, scale, lev = standardised(sol)
        first_ok = [(int(a), int(b)) for a, b in zip(*np.nonzero(flagged[:, es_k] & np.isfinite(t_ev)), strict=True)]
        exclude(first_ok, pred, res, z, scale, lev)
        Tk = sender_matrix(t_ev, es_k, Jk)
        try:
            sol = refit(Tk, sol, speed, hz, weights=wts())
        except DegenerateGeometryError:
            pass
    from ..progress import note

    for k_round in range(MAX_OUTLIER_ROUNDS + 1):
        note(f"outlier round {k_round + 1}")  # on the running stage's progress line, if any
        pred, res, z, scale, lev = standardised(sol)
        az = np.where(np.isfinite(z), np.abs(z), 0.0)
        # the largest of its receiver and of its sender: one bad entry does not take its neighbours along
        sender_max = np.zeros((az.shape[0], Jk))
        for j in range(Jk):
            cols = es_k == j
            if cols.any():
                sender_max[:, j] = az[:, cols].max(axis=1)
        worst_in_sender = sender_max.max(axis=0)
        if not robust_start and (az > zc).any():
            # a wrong entry pulls a least-squares fit towards itself and spreads its error over
            # its receiver's and sender's other entries (masking): restart from a Cauchy fit
            # (scale 2.385 stds: 95 % efficiency under Gaussian noise), then rank the residuals
            robust_start = True
            try:
                f_sc = TUNING["cauchy"] * float(np.nanmedian(s_ev)) * scale
                sol = refit(Tk, sol, speed, hz, f_scale=f_sc, weights=wts())
                needs_ls = True
                continue
            except DegenerateGeometryError:
                pass
        flag = (az > zc) & (az >= az.max(axis=1, keepdims=True)) & (az >= worst_in_sender[es_k][None, :])
        # never below the identifiability bound
        cnt_r = np.isfinite(Tk).sum(axis=1)
        cnt_s = np.isfinite(Tk).sum(axis=0)
        fi, fe = np.nonzero(flag)
        ok = []
        for a, b in zip(fi, fe, strict=True):
            last = np.isfinite(t_ev[a, es_k == es_k[b]]).sum() == 1
            if last and (cnt_r[a] <= need or cnt_s[es_k[b]] <= need):
                continue
            ok.append((int(a), int(b)))
        if not ok:
            if searched or noise is None:
                break
            # outliers are out: one deep search if the cleaned fit still fails its residual check
            from .noise import residual_check

            Tk = sender_matrix(t_ev, es_k, Jk)
            test = residual_check(t_ev - _predict(sol, speed)[:, es_k], s_ev, es_k, n_par, cap=zc)
            searched = True
            if test.passed:
                break
            try:
                sol2, plan2, cn2 = calibrate_matrix(Tk, speed=speed, dim=dim, heights=hz, rng=rng, noise=noise,
                                                    weights=wts(), units=units_k)
            except DegenerateGeometryError:
                break
            if sol2.residual_rms < sol.residual_rms:
                sol, plan = sol2, plan2
                n_par = n_parameters_of(sol, len(Tk), Jk)
                notes[:] = [n for n in notes if n not in cnotes] + cn2
                cnotes = cn2
            continue
        exclude(ok, pred, res, z, scale, lev)
        Tk = sender_matrix(t_ev, es_k, Jk)
        try:
            sol = refit(Tk, sol, speed, hz, weights=wts())
            needs_ls = False
        except DegenerateGeometryError:
            break
    if needs_ls:  # the robust start found nothing to exclude: finish with least squares (covariances)
        sol = refit(sender_matrix(t_ev, es_k, Jk), sol, speed, hz, weights=wts())
    if outliers:
        redo = sum(o.redetected for o in outliers)
        worst = max(outliers, key=lambda o: abs(o.z))
        notes.append(f"{len(outliers)} outlier detection(s) (|z| > {zc:.2f}, Bonferroni at {alpha:g}) excluded, "
                     f"{redo} re-detected near the predicted time; worst: microphone {rn[worst.receiver]}, "
                     f"loudspeaker {sn[worst.sender]}, residual {worst.residual * 1e6:.3g} us")
    Tk = sender_matrix(t_ev, es_k, Jk)
    Sk = sender_std(s_ev, t_ev, es_k, Jk)
    toa_out = toa.copy()
    toa_out[np.ix_(kr, ev_keep)] = t_ev
    Tf = np.full((I, J), np.nan)
    Sf = np.full((I, J), np.nan)
    Tf[np.ix_(kr, ks)] = Tk
    Sf[np.ix_(kr, ks)] = Sk
    std_out = np.array(std, dtype=float)
    std_out[np.ix_(kr, ev_keep)] = s_ev
    full = _scatter_nodes(sol, kr, ks)
    lev_out = np.full(toa.shape, np.nan)
    lev_out[np.ix_(kr, ev_keep)] = event_leverage(sol, t_ev, es_k, Jk, speed, wts())
    return RobustFit(full, plan, notes, outliers, toa_out, Tf, Sf, dropped_r, dropped_s, zc, std_out, n_par, lev_out)
