"""The installer's calibration report: one self-contained HTML file (``selfcal pipeline --report x.html``).

Contents: the verdict against paper 004's requirements (from the result's own error bars,
:mod:`selfcal.acoustics.verdict`), a map of the units with their labels and 95 % error
ellipses magnified to a visible scale (the factor is printed on the map), the per-unit
table of position, internal delay and onset with their standard deviations, the residual
matrix as a heat map (residual over its noise std, per receiver and sender), the outliers
and dropped units, and the notes (including the two limits no residual can show: the scale
set by the speed of sound and a timing bias common to every detection). Figures are
embedded as base64 PNG; the page loads nothing and runs no script.
"""

from __future__ import annotations

import html
import warnings
from pathlib import Path
from typing import Any

import numpy as np

from ..plotting import png_base64
from ..plotting.conference import ellipse_magnification, plot_report_map, plot_residuals

__all__ = ["write_html_report", "render_html", "ellipse_magnification"]

def _fmt(x: float, scale: float, digits: int = 3) -> str:
    return "&ndash;" if not np.isfinite(x) else f"{x * scale:.{digits}g}"


def render_html(result: Any, errors: dict[str, Any] | None = None, *, summary: list[str] | None = None) -> str:
    """The report as one HTML string (module docstring).

    Parameters
    ----------
    result : PipelineResult
    errors : dict, optional
        :func:`selfcal.acoustics.scoring.truth_errors` when a truth is known (shown as a
        separate "truth check", not as the verdict).
    summary : list of str, optional
        The CLI summary lines (shown verbatim).

    Returns
    -------
    str
    """
    from .calibrate import _predict

    e = html.escape
    speed = float(result.speed_of_sound)
    T = np.asarray(result.toa_matrix, float)
    es = np.arange(T.shape[1])
    bars = result.error_bars
    I, J = len(result.receiver_names), len(result.sender_names)
    # residuals per receiver and sender (events of one sender averaged)
    pred = _predict(result, speed)
    senders = result.event_senders
    if senders is None or len(senders) != T.shape[1]:
        senders = es % J
    R = np.full((I, J), np.nan)
    for j in range(J):
        cols = T[:, np.asarray(senders) == j]
        if cols.shape[1]:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)  # rows without a detection stay NaN
                R[:, j] = np.nanmean(cols, axis=1) - pred[:, j]
    noise = np.asarray(result.matrix_std if result.matrix_std is not None
                       else np.full((I, J), result.timing_noise), float)
    z = R / noise
    map_fig, mag = plot_report_map(result)
    map_b64, res_b64 = png_base64(map_fig), png_base64(plot_residuals(z))
    v = result.verdict
    missed = errors is not None and not errors["passed"]  # never a PASS under a truth check that says MISSED
    passed = v is not None and v.passed and not missed
    head = "PASS" if passed else "FAIL"
    reasons = "" if v is None or v.passed else "".join(f"<li>{e(x)}</li>" for x in v.reasons)
    if missed:
        reasons += "<li>the truth check (truth.json) says the 004 requirements were MISSED</li>"
    rows = []
    d = result.receivers.shape[1]
    axes = "xyz"[:d]
    out_r = {o.receiver for o in result.outliers}
    out_s = {o.sender for o in result.outliers}
    for k in range(max(I, J)):
        cells = []
        for P, C, names, offs, ostd, dropped, flagged in (
                (result.receivers, result.receiver_cov, result.receiver_names, result.receiver_offsets,
                 None if bars is None else bars.delay_std, result.dropped_receivers, out_r),
                (result.sources, result.source_cov, result.sender_names, result.source_offsets,
                 None if bars is None else bars.onset_std, result.dropped_senders, out_s)):
            if k >= len(names):
                cells.append("<td></td>" * (d + 3))
                continue
            name = names[k]
            status = "dropped" if name in dropped else ("outlier(s)" if k in flagged else "")
            pos = "".join(f"<td>{_fmt(float(P[k, a]), 1.0, 5)}</td>" for a in range(d))
            pstd = float(np.sqrt(np.trace(C[k]))) if np.isfinite(C[k]).all() else float("nan")
            os_ = float(ostd[k]) if ostd is not None else float("nan")
            cells.append(f"<td>{e(name)}{(' <em>' + status + '</em>') if status else ''}</td>{pos}"
                         f"<td>{_fmt(pstd, 100.0)}</td><td>{_fmt(float(offs[k]), 1e3, 6)} &plusmn; {_fmt(os_, 1e6)} us</td>")
        rows.append("<tr>" + "".join(cells) + "</tr>")
    hdr_pos = "".join(f"<th>{a} [m]</th>" for a in axes)
    table = (f'<table id="units"><thead><tr><th>microphone</th>{hdr_pos}<th>std [cm]</th><th>internal delay [ms]</th>'
             f'<th>loudspeaker</th>{hdr_pos}<th>std [cm]</th><th>onset [ms]</th></tr></thead>'
             f'<tbody>{"".join(rows)}</tbody></table>')
    outl_rows = "".join(
        f"<tr><td>{e(result.receiver_names[o.receiver])}</td><td>{e(result.sender_names[o.sender])}</td>"
        f"<td>{o.event}</td><td>{o.residual * 1e6:.4g}</td><td>{o.z:.3g}</td>"
        f"<td>{'re-detected (' + format(o.new_residual * 1e6, '.3g') + ' us)' if o.redetected else 'excluded'}</td></tr>"
        for o in result.outliers)
    outl = (f'<table id="outliers"><thead><tr><th>microphone</th><th>loudspeaker</th><th>event</th>'
            f'<th>residual [us]</th><th>z</th><th>action</th></tr></thead><tbody>{outl_rows}</tbody></table>'
            if result.outliers else "<p>none</p>")
    dropped = ", ".join([f"microphone {e(n)}" for n in result.dropped_receivers]
                        + [f"loudspeaker {e(n)}" for n in result.dropped_senders]) or "none"
    notes = "".join(f"<li>{e(n)}</li>" for n in result.notes)
    truth = ""
    if errors is not None:
        truth = (f"<h2>Truth check (simulation)</h2><p>Against truth.json: position max "
                 f"{errors['position_max'] * 100:.3g} cm, timing max {errors['timing_max'] * 1e6:.3g} us: 004 "
                 f"requirements {'met' if errors['passed'] else 'MISSED'}.</p>")
    summ = "" if not summary else "<h2>Summary</h2><pre>" + e("\n".join(summary)) + "</pre>"
    pstd_max = "&ndash;" if v is None else _fmt(v.position_std_max, 100.0)
    tstd_max = "&ndash;" if v is None else _fmt(v.timing_std_max, 1e6)
    return f"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><title>selfcal calibration report</title>
<style>
body {{ font-family: sans-serif; margin: 2em; color: #222; }}
.verdict {{ font-size: 1.4em; font-weight: bold; padding: 0.4em; }}
.pass {{ background: #d8f5d8; }} .fail {{ background: #f8d8d8; }}
table {{ border-collapse: collapse; font-size: 0.85em; }} td, th {{ border: 1px solid #bbb; padding: 2px 6px; text-align: right; }}
img {{ max-width: 100%; }}
</style></head><body>
<h1>Calibration report</h1>
<p class="verdict {'pass' if passed else 'fail'}" id="verdict">{head}: paper 004 requirements (10 cm, 58 us at 2 sigma)
{'met by the calibration&rsquo;s own error bars' if passed else 'not met' + (' against the truth' if missed else '')}</p>
<ul>{reasons}</ul>
<p>Method {e(result.method)}; {I} microphones, {J} loudspeakers, {result.rounds} round(s) per loudspeaker;
speed of sound {speed:.2f} m/s; position std max {pstd_max} cm, delay+onset std max {tstd_max} us (1 sigma).</p>
<h2>Map</h2><img alt="map of the units" src="data:image/png;base64,{map_b64}">
<p>Ellipses: 95 % confidence, magnified x{mag:g} so that they are visible.</p>
<h2>Units</h2>{table}
<h2>Residuals</h2><img alt="residual heat map" src="data:image/png;base64,{res_b64}">
<h2>Outliers</h2>{outl}
<h2>Dropped units</h2><p id="dropped">{dropped}</p>
<h2>Notes</h2><ul>{notes}</ul>
<p>Two things no residual can show: the scale of the whole geometry comes from the speed of sound (a 1 %
error in c scales every distance by 1 %), and a timing bias common to every detection (a probe that differs
from the declared one, a loudspeaker&rsquo;s group delay) lands in the onsets.</p>
{truth}{summ}
</body></html>
"""


def write_html_report(result: Any, path: str | Path, errors: dict[str, Any] | None = None, *,
                      summary: list[str] | None = None) -> None:
    """Write :func:`render_html` to ``path`` atomically (a non-regular file there is refused).

    Parameters
    ----------
    result : PipelineResult
    path : path
        The ``.html`` file.
    errors : dict, optional
    summary : list of str, optional
    """
    from ..io import atomic_write_bytes

    atomic_write_bytes(path, render_html(result, errors, summary=summary).encode("utf-8"))
