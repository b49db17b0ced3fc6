"""TOA figures: a calibrated network (``calibrate toa --plot``), paper 003's Fig. 5-7, an LPS flight.

A 3-D network is drawn as three views (x-y, x-z, y-z) so that no coordinate is hidden.
"""

from __future__ import annotations

import os
from typing import Any

import numpy as np
from matplotlib.figure import Figure
from numpy.typing import NDArray

from ._common import finish, new_figure
from .elements import note_small_ellipses, plot_positions, position_views

__all__ = ["plot_network", "plot_toa", "plot_rmse_curves", "plot_lps_flight"]

Path = str | os.PathLike[str]


def plot_network(
    receivers: NDArray[np.float64],
    sources: NDArray[np.float64],
    path: Path | None = None,
    *,
    receiver_cov: NDArray[np.float64] | None = None,
    source_cov: NDArray[np.float64] | None = None,
    true_receivers: NDArray[np.float64] | None = None,
    true_sources: NDArray[np.float64] | None = None,
    labels: tuple[str, str] = ("receivers", "sources"),
    markers: tuple[str, str] = ("x", "s"),
    title: str = "",
    names: tuple[Any, Any] | None = None,
) -> Figure:
    """Receivers and sources with 95 % ellipses; one panel in 2-D, three views in 3-D.

    Parameters
    ----------
    receivers : (I, d) array
        Positions, m.
    sources : (J, d) array
        Positions, m.
    path : path, optional
        Where to save (format from the suffix); None only builds the figure.
    receiver_cov, source_cov : (I, d, d) / (J, d, d) arrays, optional
        Position covariances, m^2.
    true_receivers, true_sources : arrays, optional
        Truth in the same frame (open markers).
    labels, markers : (str, str)
        Legend labels and markers of the two kinds.
    title : str
    names : (receiver names, source names), optional
        Drawn beside each point (default ``r0, r1, ...`` / ``s0, s1, ...``, the names of
        ``--known`` / ``--frame``).

    Returns
    -------
    Figure
    """
    r = np.asarray(receivers, float)
    S = np.asarray(sources, float)
    rn, sn = names if names is not None else (None, None)
    rn = list(rn) if rn else [f"r{i}" for i in range(len(r))]
    sn = list(sn) if sn else [f"s{j}" for j in range(len(S))]
    d = r.shape[1]
    fig = Figure(figsize=(6.0, 5.0) if d < 3 else (15.0, 5.0))
    for k, (ax, dims) in enumerate(position_views(fig, d)):
        plot_positions(ax, r, truth=true_receivers, cov=receiver_cov, label=labels[0], color="C0",
                       marker=markers[0], dims=dims, names=rn)
        plot_positions(ax, S, truth=true_sources, cov=source_cov, label=labels[1], color="C3",
                       marker=markers[1], dims=dims, names=sn)
        note_small_ellipses(ax, [c for c in (receiver_cov, source_cov) if c is not None], np.vstack([r, S]), dims)
        if k == 0:
            ax.legend(loc="best", fontsize=8)
            ax.set_title(title)
    return finish(fig, path)


def plot_toa(result: Any, path: Path | None = None, *, user_frame: bool = False,
             names: tuple[Any, Any] | None = None) -> Figure:
    """The figure of ``selfcal calibrate toa --plot``: a :class:`~selfcal.toa.ToaResult`'s network.

    Parameters
    ----------
    result : ToaResult
        ``receivers``, ``sources`` and their ``*_cov``, m.
    path : path, optional
        Output file (``.png``, ``.pdf``, ``.svg``, ...).
    user_frame : bool
        Whether the result is in the user's frame (else the canonical gauge); shown in the title.
    names : (receiver names, source names), optional
        The matrix's row / column names (default ``r<i>`` / ``s<j>``).

    Returns
    -------
    Figure
    """
    gauge = "user frame" if user_frame else "canonical gauge"
    return plot_network(result.receivers, result.sources, path, receiver_cov=result.receiver_cov,
                        source_cov=result.source_cov, title=f"TOA self-calibration (95% ellipses, {gauge})",
                        names=names)


def plot_rmse_curves(summary: list[dict[str, Any]], key: str, xlabel: str, title: str,
                     path: Path | None = None, *, logx: bool = False) -> Figure:
    """Paper 003 Fig. 6 / 7: sensor RMSE (eq. 18a) of MDS, NLS and sqrt(CRLB) against ``key``.

    Parameters
    ----------
    summary : list of dict
        One dict per setting with ``key`` and ``mds_rmse`` / ``nls_rmse`` / ``crlb_rmse`` (m, or None).
    key : str
        The swept quantity.
    xlabel : str
        Its axis label, with its unit.
    title : str
    path : path, optional
    logx : bool
        Log-log axes.

    Returns
    -------
    Figure
    """
    fig, ax = new_figure(size=(6.0, 4.5))
    x = np.array([e[key] for e in summary], float)
    for name, label, style in (("mds_rmse", "MDS (Alg. 2)", "s-"), ("nls_rmse", "NLS", "o-"),
                               ("crlb_rmse", "sqrt(CRLB)", "k--")):
        y = np.array([np.nan if e[name] is None else e[name] for e in summary], float)
        ax.plot(x, y, style, label=label)
    if logx:
        ax.set_xscale("log")
        ax.set_yscale("log")
    ax.set_xlabel(xlabel)
    ax.set_ylabel("sensor RMSE (m), eq. 18a")
    ax.set_title(title)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend()
    return finish(fig, path)


def plot_lps_flight(anchors: NDArray[np.float64], tag: NDArray[np.float64], true_anchors: NDArray[np.float64],
                    path: Path | None = None, *, title: str = "") -> Figure:
    """A blind LPS calibration aligned on the surveyed anchors: anchors against truth, the tag track.

    Parameters
    ----------
    anchors : (I, 3) array
        Estimated anchors after alignment, m.
    tag : (J, 3) array
        Estimated tag positions after the same alignment, m.
    true_anchors : (I, 3) array
        Surveyed anchors, m.
    path : path, optional
    title : str

    Returns
    -------
    Figure
    """
    tg = np.asarray(tag, float)
    d = tg.shape[1]
    fig = Figure(figsize=(6.0, 5.5) if d < 3 else (15.0, 5.0))
    for k, (ax, (a, b)) in enumerate(position_views(fig, d)):
        ax.plot(tg[:, a], tg[:, b], ".", ms=2, color="C1", alpha=0.4, label="tag (blind)")
        plot_positions(ax, anchors, truth=true_anchors, label="anchors (blind)", color="C0", marker="^",
                       dims=(a, b))
        if k == 0:
            ax.set_title(title)
            ax.legend(fontsize=8)
    return finish(fig, path)
