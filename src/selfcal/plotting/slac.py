"""SLAC figures (paper 002): agent tracks, the CMU Plaza range-only tracks, and the section V replica.

:func:`plot_trajectories` is ``selfcal slac run --plot``, :func:`plot_plaza` is
``selfcal slac plaza --plot``; :func:`plot_doa_cdf`, :func:`plot_ranging_rmse` and
:func:`plot_position_rmse` are Fig. 3, Fig. 4 and Table I of ``selfcal reproduce slac``.
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
from matplotlib.figure import Figure
from numpy.typing import NDArray

from ._common import finish, new_figure
from .elements import plot_cdf

__all__ = ["plot_trajectories", "plot_plaza", "plot_doa_cdf", "plot_ranging_rmse", "plot_position_rmse"]

Path = str | os.PathLike[str]


def plot_trajectories(poses: NDArray[np.float64], anchors: NDArray[np.float64], path: Path | None = None, *,
                      names: Sequence[str] | None = None, truth: NDArray[np.float64] | None = None) -> Figure:
    """Estimated agent tracks in the plane, with the anchors and (dotted) the true tracks.

    Parameters
    ----------
    poses : (T, n, >= 2) array
        Per step and agent, x and y in metres (further columns such as the heading are ignored).
    anchors : (m, >= 2) array
        Anchor positions, m.
    path : path, optional
    names : sequence of str, optional
        Agent names for the legend.
    truth : (T', n, >= 2) array, optional
        True states; the first T steps are drawn.

    Returns
    -------
    Figure
    """
    fig, ax = new_figure(size=(6, 6))
    P = np.asarray(poses, float)
    for i in range(P.shape[1]):
        ax.plot(P[:, i, 0], P[:, i, 1], label=(names[i] if names else f"agent {i}"))
        if truth is not None:
            ax.plot(truth[: P.shape[0], i, 0], truth[: P.shape[0], i, 1], "k:", lw=0.8)
    ax.plot(anchors[:, 0], anchors[:, 1], "k^", label="anchors")
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.legend()
    return finish(fig, path)


def plot_plaza(data: Any, results: Mapping[str, Any], path: Path | None = None, *,
               rmse: Mapping[str, float] | None = None) -> Figure:
    """Range-only tracks against ground truth; the beacons labelled with their scale / offset.

    Parameters
    ----------
    data : PlazaData
        ``gt`` (T, >= 2) ground truth, ``beacons`` (m, 2), ``beacon_ids``, ``dead_reckoning()``.
    results : mapping of name to RangeSlacResult
        ``poses`` (T, >= 2), ``scale`` / ``scale_std`` (m,) and ``offset`` / ``offset_std`` (m,) in
        metres; the last one's beacon calibration labels the beacons.
    path : path, optional
    rmse : mapping of name to float, optional
        Position RMSE against ground truth (m) shown in the legend
        (:func:`selfcal.experiments.slac.score_plaza`).

    Returns
    -------
    Figure
    """
    fig, ax = new_figure(size=(7, 7))
    ax.plot(data.gt[:, 0], data.gt[:, 1], "k-", lw=0.8, label="ground truth")
    dr = data.dead_reckoning()
    ax.plot(dr[:, 0], dr[:, 1], ":", color="0.5", lw=0.8, label="dead reckoning (DR)")
    ref = None
    for name, r in results.items():
        tag = f" ({rmse[name]:.2f} m RMSE)" if rmse is not None and name in rmse else ""
        ax.plot(r.poses[:, 0], r.poses[:, 1], lw=0.9, label=f"{name}{tag}")
        ref = r
    ax.plot(data.beacons[:, 0], data.beacons[:, 1], "r^", ms=9, label="beacons")
    for k, (bx, by) in enumerate(data.beacons):
        txt = f"id {int(data.beacon_ids[k])}"
        if ref is not None:
            txt += (f"\nscale {ref.scale[k]:.3f}\u00b1{ref.scale_std[k]:.3f}\noffset {ref.offset[k]:+.2f}"
                    f"\u00b1{ref.offset_std[k]:.2f} m")
        ax.annotate(txt, (bx, by), textcoords="offset points", xytext=(6, 6), fontsize=7)
    ax.set_aspect("equal")
    ax.margins(0.15)  # room for the beacon labels
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    which = f" ({ref.method} calibration)" if ref is not None else ""
    ax.set_title(f"Range-only SLAC with per-beacon scale + offset{which}")
    ax.legend(fontsize=7, loc="best")
    return finish(fig, path)


def plot_doa_cdf(errors_deg: Mapping[str, NDArray[np.float64]], path: Path | None = None, *,
                 title: str = "Fig. 3 replica: DoA error at Dias (MMA)") -> Figure:
    """Empirical CDFs of absolute DoA errors, one curve per antenna model (paper 002 Fig. 3).

    Parameters
    ----------
    errors_deg : mapping of label to array
        Absolute DoA errors, degrees.
    path : path, optional
    title : str

    Returns
    -------
    Figure
    """
    fig, ax = new_figure(size=(6, 4.5))
    for label, errs in errors_deg.items():
        plot_cdf(ax, errs, label=label)
    ax.set_xlabel("absolute DoA error (deg)")
    ax.set_title(title)
    ax.legend()
    return finish(fig, path)


def plot_ranging_rmse(t_min: NDArray[np.float64], curves: Mapping[str, NDArray[np.float64]],
                      path: Path | None = None, *, window: int = 50) -> Figure:
    """Ranging RMSE over time, moving-averaged over ``window`` steps (paper 002 Fig. 4).

    Parameters
    ----------
    t_min : (T,) array
        Time, minutes.
    curves : mapping of label to (T,) array
        Ranging RMSE per step, m.
    path : path, optional
    window : int
        Moving-average length in steps (50 steps of 0.1 s = 5 s).

    Returns
    -------
    Figure
    """
    fig, ax = new_figure(size=(7, 4))
    kernel = np.ones(window) / window
    for label, v in curves.items():
        ax.plot(t_min, np.convolve(np.asarray(v, float), kernel, mode="same"), label=label)
    ax.set_xlabel("time (min)")
    ax.set_ylabel("ranging RMSE (m), moving average")
    ax.set_title("Fig. 4 replica")
    ax.legend()
    return finish(fig, path)


def plot_position_rmse(agents: Sequence[str], bars: Mapping[str, Sequence[float]], path: Path | None = None) -> Figure:
    """Grouped bars of the position RMSE per agent, one bar per mode (paper 002 Table I).

    Parameters
    ----------
    agents : sequence of str
    bars : mapping of label to sequence of float
        Position RMSE per agent, m.
    path : path, optional

    Returns
    -------
    Figure
    """
    fig, ax = new_figure(size=(7, 4))
    xs = np.arange(len(agents))
    width = 0.8 / max(len(bars), 1)
    for k, (label, v) in enumerate(bars.items()):
        ax.bar(xs + (k - (len(bars) - 1) / 2) * width, list(v), width, label=label)
    ax.set_xticks(xs, list(agents))
    ax.set_xlabel("agent (-)")
    ax.set_ylabel("position RMSE (m)")
    ax.set_title("Table I replica")
    ax.legend()
    return finish(fig, path)
