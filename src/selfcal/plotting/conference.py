"""Conference-pipeline figures (paper 004): the unit map, the timing panel and the report's figures.

:func:`plot_map` and :func:`plot_timing` are ``selfcal pipeline --plot / --report DIR`` and
``selfcal demo``; :func:`plot_report_map` and :func:`plot_residuals` are the two figures of the
HTML report (:mod:`selfcal.acoustics.report`). A 3-D calibration's map has three views.
"""

from __future__ import annotations

import os
from typing import Any

import numpy as np
from matplotlib.figure import Figure
from numpy.typing import NDArray

from ..requirements import TIMING_REQUIREMENT
from ._common import finish, new_figure
from .elements import (
    confidence_ellipse,
    draw_room,
    integer_ticks,
    note_small_ellipses,
    plot_positions,
    position_views,
)

__all__ = ["plot_map", "plot_timing", "plot_report_map", "plot_residuals", "ellipse_magnification"]

Path = str | os.PathLike[str]

CHI2_2D_95 = 5.991  # chi-square quantile, 2 dof, 95 %: the ellipse radius in sigmas is its square root


def plot_map(result: Any, path: Path | None = None, errors: dict[str, Any] | None = None, title: str = "",
             *, room: Any = None) -> Figure:
    """Estimated (and, when known, true) microphones and loudspeakers with 95 % ellipses and names.

    With ``errors`` the estimate is drawn aligned on the truth, its covariances rotated alike.
    One x-y panel in 2-D (or with known heights, ``known_heights``, where z is given), three views
    in 3-D.

    Parameters
    ----------
    result : PipelineResult
        ``receivers`` / ``sources`` (m), ``receiver_cov`` / ``source_cov`` (m^2) and
        ``known_heights`` (the ``2d+heights`` model).
    path : path, optional
    errors : dict, optional
        :func:`selfcal.acoustics.scoring.truth_errors` (``aligned_*`` and ``true_*`` arrays).
    title : str
    room : (L, W, H), optional
        The room's outline (m), drawn in the frame of the positions (the truth's, or the
        room's own frame after ``--known`` / ``--frame``).

    Returns
    -------
    Figure
    """
    from ..geometry import align, rotate_covariances

    er, es = result.receivers, result.sources
    rc, sc = result.receiver_cov, result.source_cov
    tr = ts = None
    planar = er.shape[1] == 2 or result.known_heights  # z given: the x-y map is the answer
    if errors is not None:
        er, es = errors["aligned_receivers"], errors["aligned_sources"]
        tr, ts = np.asarray(errors["true_receivers"]), np.asarray(errors["true_senders"])
        k = 2 if planar else 3
        al = align(np.vstack([result.receivers, result.sources])[:, :k], np.vstack([tr, ts])[:, :k])
        rc, sc = rotate_covariances(rc, al.rotation), rotate_covariances(sc, al.rotation)
    views = 2 if planar else er.shape[1]
    fig = Figure(figsize=(8.5, 6.5) if views < 3 else (17.0, 5.5))
    for n, (ax, dims) in enumerate(position_views(fig, views)):
        if room is not None:
            draw_room(ax, room, dims)
        plot_positions(ax, er, truth=tr, cov=rc, label="microphones", color="C0", marker="o", dims=dims,
                       names=result.receiver_names)
        plot_positions(ax, es, truth=ts, cov=sc, label="loudspeakers", color="C3", marker="s", dims=dims)
        note_small_ellipses(ax, [rc, sc], np.vstack([er, es]), dims)
        if n == 0:  # the legend beside the map, never over a unit; a long method name wraps
            ax.legend(loc="upper left", bbox_to_anchor=(1.02, 1.0), fontsize=8, borderaxespad=0.0)
            ax.set_title(title or f"positions (95 % ellipses)\n{result.method}", fontsize=9)
    return finish(fig, path)


def plot_timing(result: Any, path: Path | None = None, errors: dict[str, Any] | None = None, *,
                requirement: float | None = None) -> Figure:
    """Delay / onset estimates (errors against truth when known) and the run time per stage.

    Parameters
    ----------
    result : PipelineResult
        ``receiver_offsets`` / ``source_offsets`` (s) and ``timings`` (stage -> seconds).
    path : path, optional
    errors : dict, optional
        With ``delay_errors`` / ``onset_errors`` (s): those are drawn, in microseconds.
    requirement : float, optional
        Timing requirement drawn as +- lines, s (default: paper 004's 58 us,
        :data:`selfcal.requirements.TIMING_REQUIREMENT`).

    Returns
    -------
    Figure
    """
    if requirement is None:
        requirement = TIMING_REQUIREMENT
    fig, (ax1, ax2) = new_figure(1, 2, size=(11.0, 4.2))
    if errors is not None:
        ax1.plot(np.asarray(errors["delay_errors"]) * 1e6, "o", label="internal delay error")
        ax1.plot(np.asarray(errors["onset_errors"]) * 1e6, "s", label="onset time error")
        for s in (-1, 1):
            ax1.axhline(s * requirement * 1e6, color="r", ls="--", lw=0.8)
        ax1.set_ylabel(f"error [us], common shift removed (red: {requirement * 1e6:g} us)")
    else:
        ax1.plot(result.receiver_offsets * 1e3, "o", label="internal delay")
        ax1.plot(result.source_offsets * 1e3, "s", label="onset time (first = 0)")
        ax1.set_ylabel("estimate [ms]")
    ax1.set_xlabel("unit [index]")
    integer_ticks(ax1.xaxis)
    ax1.legend(fontsize=8)
    names = list(result.timings)
    ax2.bar(names, [result.timings[n] for n in names], color="C2")
    ax2.set_xlabel("stage [-]")
    ax2.set_ylabel("run time [s]")
    ax2.set_title("time per stage")
    return finish(fig, path)


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

    Examples
    --------
    >>> ellipse_magnification([0.001], 10.0)
    100.0
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


def plot_report_map(result: Any, path: Path | None = None) -> tuple[Figure, float]:
    """The report's plan view: units with their names and magnified 95 % ellipses.

    Parameters
    ----------
    result : PipelineResult
        Positions (m), covariances (m^2), ``receiver_names`` / ``sender_names``.
    path : path, optional

    Returns
    -------
    (Figure, float)
        The figure and the ellipse magnification (:func:`ellipse_magnification`), printed on the map.
    """
    r, s = np.asarray(result.receivers, float), np.asarray(result.sources, float)
    rc, sc = np.asarray(result.receiver_cov, float), np.asarray(result.source_cov, float)
    pts = np.vstack([r, s])[:, :2]
    ok = np.isfinite(pts).all(axis=1)
    extent = float(np.ptp(pts[ok], axis=0).max()) if ok.any() else 1.0
    std = np.sqrt(np.concatenate([np.trace(rc[:, :2, :2], axis1=1, axis2=2),
                                  np.trace(sc[:, :2, :2], axis1=1, axis2=2)]))
    mag = ellipse_magnification(std, extent)
    fig, ax = new_figure(size=(8.0, 7.0))
    for P, C, names, color, marker, label in ((r, rc, result.receiver_names, "C0", "o", "microphones"),
                                              (s, sc, result.sender_names, "C3", "s", "loudspeakers")):
        good = np.isfinite(P).all(axis=1)
        ax.scatter(P[good, 0], P[good, 1], c=color, marker=marker, s=8, label=label, zorder=2)
        for k in np.flatnonzero(good):
            if np.isfinite(C[k, :2, :2]).all():
                ax.add_patch(confidence_ellipse(P[k, :2], C[k, :2, :2], scale=mag, color=color, lw=1.2, zorder=3))
            if marker == "o":
                ax.annotate(names[k], (P[k, 0], P[k, 1]), fontsize=6, xytext=(3, 3), textcoords="offset points")
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.grid(alpha=0.3)
    ax.legend(loc="best", fontsize=8)
    ax.set_title(f"units and 95 % ellipses (ellipses magnified x{mag:g})")
    return finish(fig, path), mag


def plot_residuals(z: NDArray[np.float64], path: Path | None = None) -> Figure:
    """Heat map of the TOA residuals over their noise std, per receiver (rows) and sender (columns).

    Parameters
    ----------
    z : (I, J) array
        Residual / noise std (dimensionless); NaN (missed or excluded) is grey.
    path : path, optional

    Returns
    -------
    Figure
    """
    fig, ax = new_figure(size=(7.5, 6.0))
    lim = max(3.0, float(np.nanmax(np.abs(z)))) if np.isfinite(z).any() else 3.0
    im = ax.imshow(z, cmap="RdBu_r", vmin=-min(lim, 10.0), vmax=min(lim, 10.0), aspect="auto",
                   interpolation="nearest")
    fig.colorbar(im, ax=ax, label="residual / noise std [-] (grey: missed or excluded)")
    ax.set_xlabel("loudspeaker (sender) [index]")
    ax.set_ylabel("microphone (receiver) [index]")
    integer_ticks(ax.xaxis)
    integer_ticks(ax.yaxis)
    ax.set_title("TOA residuals, detected minus modelled")
    ax.set_facecolor("0.8")
    return finish(fig, path)
