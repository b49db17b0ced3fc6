"""Figures of ``selfcal reproduce delays`` (the 004 thesis's Fig. 4.1-4.5 and the noise efficiency).

The numbers come from :mod:`selfcal.experiments.delays`; the thesis's constants (acceptance
threshold, run times) are passed in, so this module knows no experiment.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from typing import Any

import numpy as np
from matplotlib.figure import Figure

from ._common import finish, new_figure

__all__ = ["plot_accuracy", "plot_timing", "plot_lambda", "plot_noise"]

Path = str | os.PathLike[str]


def plot_accuracy(summary: list[dict[str, Any]], path: Path | None = None, *, accept_s2: float) -> Figure:
    """Fig. 4.1-4.3: final Frobenius norm and offset error against the number of units, per room.

    Parameters
    ----------
    summary : list of dict
        Per (room, method, units): ``frobenius_s2`` / ``p_error_s`` (and ``*_filtered``) statistics
        ``{"n", "mean", "min", "max"}`` in s^2 and s.
    path : path, optional
    accept_s2 : float
        Acceptance threshold of the Frobenius norm, s^2 (drawn dotted).

    Returns
    -------
    Figure
    """
    fig, axes = new_figure(2, 2, size=(11.0, 8.0))
    for row, room in enumerate(("large", "small")):
        for col, (key, label) in enumerate((("frobenius_s2", "final Frobenius norm F (s$^2$)"),
                                            ("p_error_s", r"$\|\hat p - p\|$ (s)"))):
            ax = axes[row, col]
            for method, colour in (("faithful", "C0"), ("fast", "C1")):
                for suffix, style, tag in (("", "--", "unfiltered"), ("_filtered", "-", "filtered")):
                    items = [s for s in summary if s["room"] == room and s["method"] == method
                             and s[key + suffix].get("n", 0) > 0]
                    if not items:
                        continue
                    x = np.array([s["units"] for s in items], float) + (0.4 if method == "fast" else -0.4)
                    x = x + (0.15 if suffix else -0.15)
                    mean = np.array([s[key + suffix]["mean"] for s in items])
                    lo = np.array([s[key + suffix]["min"] for s in items])
                    hi = np.array([s[key + suffix]["max"] for s in items])
                    ax.errorbar(x, mean, yerr=[mean - lo, hi - mean], fmt="o" + style, color=colour,
                                alpha=1.0 if suffix else 0.5, capsize=3, label=f"{method}, {tag}")
            if key == "frobenius_s2":
                ax.axhline(accept_s2, color="k", lw=0.8, ls=":", label=f"acceptance {accept_s2:g} s$^2$")
            else:
                ax.axhline(1e-6, color="k", lw=0.8, ls=":", label="1 us")
            ax.set_yscale("log")
            ax.set_xlabel("units (-)")
            ax.set_ylabel(label)
            ax.set_title(f"{'30 x 30 x 12' if room == 'large' else '12 x 12 x 2'} m$^3$")
            ax.legend(fontsize=7)
    return finish(fig, path)


def plot_timing(rows: list[dict[str, Any]], path: Path | None = None, *,
                thesis_means: Mapping[int, float] | None = None) -> Figure:
    """Fig. 4.4: run time per number of units and method (box plots, log scale).

    Parameters
    ----------
    rows : list of dict
        One per run: ``units``, ``method`` (``"faithful"`` / ``"fast"``), ``seconds`` and
        ``extrapolated_seconds`` (faithful runs capped before convergence), s.
    path : path, optional
    thesis_means : mapping of units to seconds, optional
        The thesis's mean run times (MATLAB), drawn dotted.

    Returns
    -------
    Figure
    """
    fig, ax = new_figure(size=(7.0, 5.0))
    groups = []
    labels = []
    for units in sorted({r["units"] for r in rows}):
        for method in ("faithful", "fast"):
            sel = [r for r in rows if r["units"] == units and r["method"] == method]
            if sel:
                key = "extrapolated_seconds" if method == "faithful" else "seconds"
                groups.append([r[key] for r in sel])
                labels.append(f"{units} units\n{method}")
    ax.boxplot(groups, tick_labels=labels)
    ax.set_yscale("log")
    ax.set_xlabel("network size and method (-)")
    ax.set_ylabel("run time (s); faithful: to convergence, extrapolated when capped")
    for k, (units, sec) in enumerate((thesis_means or {}).items()):
        ax.axhline(sec, color=f"C{k + 2}", ls=":", label=f"thesis mean, {units} units (MATLAB)")
    if thesis_means:
        ax.legend(fontsize=8)
    return finish(fig, path)


def plot_lambda(rows: list[dict[str, Any]], path: Path | None = None) -> Figure:
    """Fig. 4.5: the objective (3.17) against the iteration for each regularisation lambda.

    Parameters
    ----------
    rows : list of dict
        ``lam_s`` (s), ``history_iteration`` and ``history_frobenius_s2`` (s^2).
    path : path, optional

    Returns
    -------
    Figure
    """
    fig, ax = new_figure(size=(7.0, 5.0))
    for r in rows:
        ax.loglog(r["history_iteration"], r["history_frobenius_s2"], label=f"lambda = {r['lam_s']:g}")
    ax.set_xlabel("iteration (-)")
    ax.set_ylabel("F (3.17) (s$^2$)")
    ax.legend(fontsize=8)
    return finish(fig, path)


def plot_noise(summary: list[dict[str, Any]], path: Path | None = None) -> Figure:
    """Offset RMSE of NLS and of the rank-3 iteration alone against the timing noise, with sqrt(CRLB).

    Parameters
    ----------
    summary : list of dict
        Per (room, sigma): ``sigma`` (s), ``offset_rmse_nls_s``, ``offset_rmse_rank3_s``,
        ``offset_crlb_s`` (s).
    path : path, optional

    Returns
    -------
    Figure
    """
    fig, ax = new_figure(size=(7.0, 5.0))
    for room, marker in (("large", "o"), ("small", "s")):
        items = [s for s in summary if s["room"] == room]
        if not items:
            continue
        sig = np.array([s["sigma"] for s in items]) * 1e6
        ax.loglog(sig, [s["offset_rmse_nls_s"] for s in items], marker + "-", label=f"{room}: NLS")
        ax.loglog(sig, [s["offset_rmse_rank3_s"] for s in items], marker + "--", label=f"{room}: rank-3 only")
        ax.loglog(sig, [s["offset_crlb_s"] for s in items], marker + ":", color="k", label=f"{room}: sqrt CRLB")
    ax.set_xlabel("timing noise sigma (us)")
    ax.set_ylabel("offset RMSE (s), minimum-norm gauge")
    ax.legend(fontsize=8)
    return finish(fig, path)
