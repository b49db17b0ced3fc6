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

import base64
import html
import io
import warnings
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

__all__ = ["write_html_report", "render_html", "ellipse_magnification"]

CHI2_2D_95 = 5.991  # chi-square quantile, 2 dof, 95 %: the ellipse radius in sigmas is its square root


def ellipse_magnification(std: NDArray[np.float64], extent: float) -> float:
    """Factor (1-2-5 steps) that makes the median 95 % ellipse about 4 % of the map's extent.

    Parameters
    ----------
    std : array
        Position stds, m.
    extent : float
        Map extent, m.

    Returns
    -------
    float
        1, 2, 5, 10, 20, ... (the largest at most the wanted factor; never below 1).
    """
    s = np.asarray(std, float)
    s = s[np.isfinite(s) & (s > 0)]
    if not s.size or extent <= 0:
        return 1.0
    want = 0.04 * extent / (np.sqrt(CHI2_2D_95) * float(np.median(s)))
    if want <= 1.0:
        return 1.0
    k = int(np.floor(np.log10(want)))
    return float(max(m * 10.0**k for m in (1, 2, 5) if m * 10.0**k <= want))


def _png(fig: Any) -> str:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110, bbox_inches="tight")
    import matplotlib.pyplot as plt

    plt.close(fig)
    return base64.b64encode(buf.getvalue()).decode("ascii")


def _map_png(result: Any) -> tuple[str, float]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Ellipse

    r, s = np.asarray(result.receivers, float), np.asarray(result.sources, float)
    rc, sc = np.asarray(result.receiver_cov, float), np.asarray(result.source_cov, float)
    pts = np.vstack([r, s])[:, :2]
    ok = np.isfinite(pts).all(axis=1)
    extent = float(np.ptp(pts[ok], axis=0).max()) if ok.any() else 1.0
    std = np.sqrt(np.concatenate([np.trace(rc[:, :2, :2], axis1=1, axis2=2), np.trace(sc[:, :2, :2], axis1=1, axis2=2)]))
    mag = ellipse_magnification(std, extent)
    fig, ax = plt.subplots(figsize=(8.0, 7.0))
    k95 = np.sqrt(CHI2_2D_95)
    for P, C, names, color, marker, label in ((r, rc, result.receiver_names, "C0", "o", "microphones"),
                                              (s, sc, result.sender_names, "C3", "s", "loudspeakers")):
        good = np.isfinite(P).all(axis=1)
        ax.scatter(P[good, 0], P[good, 1], c=color, marker=marker, s=8, label=label, zorder=2)
        for k in np.flatnonzero(good):
            c2 = C[k, :2, :2]
            if np.isfinite(c2).all():
                w, v = np.linalg.eigh(c2)
                w = np.maximum(w, 0.0)
                ang = float(np.degrees(np.arctan2(v[1, 1], v[0, 1])))
                ax.add_patch(Ellipse((P[k, 0], P[k, 1]), 2 * k95 * mag * np.sqrt(w[1]), 2 * k95 * mag * np.sqrt(w[0]),
                                     angle=ang, fill=False, color=color, lw=1.2, zorder=3))
            if marker == "o":
                ax.annotate(names[k], (P[k, 0], P[k, 1]), fontsize=6, xytext=(3, 3), textcoords="offset points")
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.grid(alpha=0.3)
    ax.legend(loc="best", fontsize=8)
    ax.set_title(f"units and 95 % ellipses (ellipses magnified x{mag:g})")
    return _png(fig), mag


def _residual_png(result: Any, z: NDArray[np.float64]) -> str:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7.5, 6.0))
    lim = max(3.0, float(np.nanmax(np.abs(z)))) if np.isfinite(z).any() else 3.0
    im = ax.imshow(z, cmap="RdBu_r", vmin=-min(lim, 10.0), vmax=min(lim, 10.0), aspect="auto", interpolation="nearest")
    fig.colorbar(im, ax=ax, label="residual / noise std (grey: missed or excluded)")
    ax.set_xlabel("loudspeaker (sender)")
    ax.set_ylabel("microphone (receiver)")
    ax.set_title("TOA residuals, detected minus modelled")
    ax.set_facecolor("0.8")
    return _png(fig)


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
    sol = {"receivers": result.receivers, "sources": result.sources, "receiver_offsets": result.receiver_offsets,
           "source_offsets": result.source_offsets}
    speed = float(result.speed_of_sound)
    T = np.asarray(result.toa_matrix, float)
    es = np.arange(T.shape[1])
    bars = result.error_bars
    I, J = len(result.receiver_names), len(result.sender_names)
    # residuals per receiver and sender (events of one sender averaged)
    pred = _predict(sol, speed)
    senders = getattr(result, "event_senders", None)
    if senders is None or len(senders) != T.shape[1]:
        senders = es % J
    R = np.full((I, J), np.nan)
    for j in range(J):
        cols = T[:, np.asarray(senders) == j]
        if cols.shape[1]:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)  # rows without a detection stay NaN
                R[:, j] = np.nanmean(cols, axis=1) - pred[:, j]
    noise = np.asarray(getattr(result, "matrix_std", None) if getattr(result, "matrix_std", None) is not None
                       else np.full((I, J), result.timing_noise), float)
    z = R / noise
    map_b64, mag = _map_png(result)
    res_b64 = _residual_png(result, z)
    v = result.verdict
    passed = v is not None and v.passed
    head = "PASS" if passed else "FAIL"
    reasons = "" if v is None or v.passed else "".join(f"<li>{e(x)}</li>" for x in v.reasons)
    rows = []
    d = result.receivers.shape[1]
    axes = "xyz"[:d]
    out_r = {o.receiver for o in result.outliers}
    out_s = {o.sender for o in result.outliers}
    for k in range(max(I, J)):
        cells = []
        for P, C, names, offs, ostd, dropped, outl in (
                (result.receivers, result.receiver_cov, result.receiver_names, result.receiver_offsets,
                 None if bars is None else bars.delay_std, result.dropped_receivers, out_r),
                (result.sources, result.source_cov, result.sender_names, result.source_offsets,
                 None if bars is None else bars.onset_std, result.dropped_senders, out_s)):
            if k >= len(names):
                cells.append("<td></td>" * (d + 3))
                continue
            name = names[k]
            status = "dropped" if name in dropped else ("outlier(s)" if k in outl else "")
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
{'met by the calibration&rsquo;s own error bars' if passed else 'not met'}</p>
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
