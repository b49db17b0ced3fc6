"""Scoring a calibration against a simulation's ``truth.json`` (paper 004's requirements).

This is a *comparison with the truth*, distinct from the calibration's own verdict
(:mod:`selfcal.acoustics.verdict`), which judges the result from its error bars without
knowing the truth.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from ..requirements import POSITION_REQUIREMENT, TIMING_REQUIREMENT

__all__ = ["truth_errors"]


def truth_errors(result: Any, truth: dict[str, Any]) -> dict[str, Any]:
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
    if d == 2 or result.known_heights:
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
