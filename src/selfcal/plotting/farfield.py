"""Far-field TDOA figures (paper 000): positions, and the directions on the unit sphere with a colour bar.

:func:`plot_farfield` is ``selfcal calibrate tdoa-farfield --plot``; :func:`plot_minimal_solver`,
:func:`plot_initialisation`, :func:`plot_convergence` and :func:`plot_noise` are Fig. 1-4 of
``selfcal reproduce farfield``.
"""

from __future__ import annotations

import os
from typing import Any

import numpy as np
from matplotlib.figure import Figure

from ._common import finish
from .elements import plot_positions, tidy_3d_ticks

__all__ = ["plot_farfield", "plot_minimal_solver", "plot_initialisation", "plot_convergence", "plot_noise"]

Path = str | os.PathLike[str]


def plot_farfield(res: Any, path: Path | None = None, *, speed: float | None = None,
                  names: Any = None) -> Figure:
    """Positions and transmitter directions of a :class:`~selfcal.tdoa.FarfieldResult`.

    Left: the receiver positions (95 % ellipses in 2-D; in 3-D the x-y view coloured by z).
    Right: the directions n_j on the unit sphere (3-D), circle (2-D) or line (1-D), coloured by
    each transmitter's offset C_j.

    Parameters
    ----------
    res : FarfieldResult
        ``positions`` (m, d) in metres, ``directions`` (k, d) unit vectors, ``offsets`` (k,) in
        metres, ``dim``, ``case``, ``degeneracy``, ``position_cov``.
    path : path, optional
        Output file; the format comes from the suffix.
    speed : float, optional
        m/s when the matrix held times: the offsets are then drawn in seconds (as the JSON
        reports them), else in metres.
    names : sequence of str, optional
        Receiver names beside the positions (default ``0, 1, ...``, the JSON's order).

    Returns
    -------
    Figure
    """
    fig = Figure(figsize=(12.0, 5.2))
    offsets, off_unit = (np.asarray(res.offsets, float), "m") if speed is None else (
        np.asarray(res.offsets, float) / float(speed), "s")
    if names is None or len(names) != len(res.positions):
        names = [str(i) for i in range(len(res.positions))]
    P, n, d = res.positions, res.directions, res.dim
    ax0 = fig.add_subplot(1, 2, 1)
    if d == 1:
        ax0.scatter(P[:, 0], np.zeros(len(P)), s=25)
        ax0.set_xlabel("position along the line [m] (up to scale)")
        ax0.set_ylabel("(none) [m]")
        ax0.set_yticks([])
    else:
        plot_positions(ax0, P, cov=res.position_cov if d == 2 else None, label="positions", names=names)
        if d == 3:
            sc = ax0.scatter(P[:, 0], P[:, 1], c=P[:, 2], cmap="viridis", s=25, zorder=4)
            fig.colorbar(sc, ax=ax0, label="z [m]")
        ax0.legend(loc="best", fontsize=8)
    ax0.set_title(f"receiver positions ({res.case}, first at the origin)")
    ax1: Any = fig.add_subplot(1, 2, 2, projection="3d" if d == 3 else None)  # Axes3D in 3-D
    if d == 3:
        u, v = np.mgrid[0 : 2 * np.pi : 37j, 0 : np.pi : 19j]
        ax1.plot_wireframe(np.cos(u) * np.sin(v), np.sin(u) * np.sin(v), np.cos(v), color="0.85", lw=0.4)
        sc = ax1.scatter(n[:, 0], n[:, 1], n[:, 2], c=offsets, cmap="plasma", s=14, depthshade=False)
        ax1.set_xlabel("n_x [unit]")
        ax1.set_ylabel("n_y [unit]")
        ax1.set_zlabel("n_z [unit]")
        ax1.set_box_aspect((1, 1, 1))
        tidy_3d_ticks(ax1)
    elif d == 2:
        t = np.linspace(0, 2 * np.pi, 200)
        ax1.plot(np.cos(t), np.sin(t), color="0.8", lw=0.8)
        sc = ax1.scatter(n[:, 0], n[:, 1], c=offsets, cmap="plasma", s=18)
        ax1.set_aspect("equal")
        ax1.set_xlabel("n_x [unit]")
        ax1.set_ylabel("n_y [unit]")
    else:
        sc = ax1.scatter(n[:, 0], np.arange(len(n)), c=offsets, cmap="plasma", s=14)
        ax1.set_xlabel("projection of the direction on the line [unit] (cos of the angle)")
        ax1.set_ylabel("transmitter index [-]")
    fig.colorbar(sc, ax=ax1, label=f"offset C_j [{off_unit}]", shrink=0.8)
    ax1.set_title("transmitter directions" + (f" [{res.degeneracy}]" if res.degeneracy else ""))
    return finish(fig, path)


def plot_minimal_solver(fig1: list[dict[str, Any]], path: Path | None = None) -> Figure:
    """Paper 000 Fig. 1: the minimal solver's failure rate and mean error against the relative distance R.

    Parameters
    ----------
    fig1 : list of dict
        Per setting: ``model`` (``"3d"`` or ``"far-field"``), ``distance`` (R, dimensionless),
        ``failure_rate`` and ``mean_error`` (position error, in the units of the positions).
    path : path, optional

    Returns
    -------
    Figure
    """
    exact = next((x for x in fig1 if x["model"] == "far-field"), None)
    d3 = [x for x in fig1 if x["model"] == "3d"]
    fig = Figure(figsize=(7, 4.5))
    ax = fig.add_subplot(1, 1, 1)
    xs = np.arange(len(d3))
    ax.bar(xs, [x["failure_rate"] for x in d3], color="0.7", label="failure rate (B not PD)")
    ax.set_ylabel("failure rate (-)")
    ax.set_xticks(xs, [f"{x['distance']:g}" for x in d3], rotation=45)
    ax.set_xlabel("relative distance R (-)")
    ax2 = ax.twinx()
    ax2.semilogy(xs, [x["mean_error"] for x in d3], "o-", color="C0", label="mean position error")
    ax2.set_ylabel("mean position error (m)")
    tail = f" (exact far field: {exact['mean_error']:.1e})" if exact is not None else ""
    ax.set_title(f"Fig. 1: minimal solver{tail}")
    return finish(fig, path)


def plot_initialisation(fig2: list[dict[str, Any]], path: Path | None = None) -> Figure:
    """Paper 000 Fig. 2: the overdetermined initialisation's mean error and failure rate against R.

    Parameters
    ----------
    fig2 : list of dict
        Per (size, distance): ``size`` (``"r4-s6"``: receivers and senders), ``distance``,
        ``mean_error`` (m), ``failure_rate``.
    path : path, optional

    Returns
    -------
    Figure
    """
    fig = Figure(figsize=(11, 4.5))
    axes = fig.subplots(1, 2)
    for size in dict.fromkeys(x["size"] for x in fig2):
        sel = [x for x in fig2 if x["size"] == size]
        axes[0].loglog([x["distance"] for x in sel], [x["mean_error"] for x in sel], "o-", label=size)
        axes[1].semilogx([x["distance"] for x in sel], [x["failure_rate"] for x in sel], "o-", label=size)
    axes[0].set_xlabel("relative distance R (-)")
    axes[0].set_ylabel("mean position error (m)")
    axes[1].set_xlabel("relative distance R (-)")
    axes[1].set_ylabel("failure rate (B not PD) (-)")
    axes[0].legend()
    axes[0].set_title("Fig. 2: overdetermined initialisation")
    return finish(fig, path)


def plot_convergence(curves: dict[str, Any], path: Path | None = None, *,
                     title: str = "Fig. 3: convergence, m = k = 10, sigma = 0.1") -> Figure:
    """Paper 000 Fig. 3: the median position error against the iteration, one curve per method.

    Parameters
    ----------
    curves : dict of label to (n_iter,) array
        Median (over draws) mean position error per iteration, m.
    path : path, optional
    title : str

    Returns
    -------
    Figure
    """
    fig = Figure(figsize=(7, 4.5))
    ax = fig.add_subplot(1, 1, 1)
    for k, (label, c) in enumerate(curves.items()):
        c = np.asarray(c, float)
        ax.plot(np.arange(len(c)), c, "--" if k == 2 else "-", label=label)
    ax.set_xscale("symlog")
    ax.set_xlabel("iteration (-)")
    ax.set_ylabel("median (over draws) of the mean position error (m)")
    ax.set_title(title)
    ax.legend()
    return finish(fig, path)


def plot_noise(fig4: list[dict[str, Any]], path: Path | None = None) -> Figure:
    """Paper 000 Fig. 4: position error of the initialisation, LM and ML against the noise, with the CRLB.

    One panel per relative distance R.

    Parameters
    ----------
    fig4 : list of dict
        Per (distance, sigma): ``sigma`` (m), ``init_error`` / ``lm_error`` (means),
        ``*_median``, ``ml_error_median``, ``rmse["crlb"]`` (m), ``failure_rate``.
    path : path, optional

    Returns
    -------
    Figure
    """
    distances = list(dict.fromkeys(x["distance"] for x in fig4))
    fig = Figure(figsize=(11, 4.5))
    axes = np.atleast_1d(fig.subplots(1, len(distances)))
    for ax, d in zip(axes, distances, strict=True):
        sel = [x for x in fig4 if x["distance"] == d]
        sx = [max(x["sigma"], 1e-5) for x in sel]
        ax.loglog(sx, [x["init_error"] for x in sel], "o-", label="initialisation (mean)")
        ax.loglog(sx, [x["lm_error"] for x in sel], "s-", label="LM (mean)")
        ax.loglog(sx, [x["init_error_median"] for x in sel], "o:", label="initialisation (median)")
        ax.loglog(sx, [x["lm_error_median"] for x in sel], "s:", label="LM (median)")
        ax.loglog(sx, [x["ml_error_median"] for x in sel], "^:", label="ML, C_j free (median)")
        ax.loglog(sx, [x["rmse"]["crlb"] for x in sel], "k--", label="CRLB (aligned RMSE)")
        ax.set_xlabel("noise std (m; 0 plotted at 1e-5)")
        ax.set_ylabel("mean position error (m)")
        ax.set_title(f"Fig. 4: m=5, k=10, R={d:g}; failure rate " +
                     ", ".join(f"{x['failure_rate']:.2f}" for x in sel))
        ax.legend()
    return finish(fig, path)
