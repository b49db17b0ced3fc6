"""AOA figures (paper 001): a located receiver with its axes, and the error surfaces of Fig. 3-6.

:func:`plot_pose` is ``selfcal locate aoa --plot``; :func:`plot_error_surfaces` draws
``selfcal reproduce aoa``'s heat maps.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from typing import Any

import numpy as np
from matplotlib.figure import Figure
from numpy.typing import NDArray

from ._common import finish, new_figure
from .elements import plot_heatmap, tidy_3d_ticks

__all__ = ["plot_pose", "plot_error_surfaces"]

Path = str | os.PathLike[str]


def plot_pose(beacons: NDArray[np.float64], bearings: NDArray[np.float64], res: Any,
              path: Path | None = None, *, names: Sequence[str] | None = None) -> Figure:
    """Beacons, the receiver position, its axes (columns of R) and the measured bearing rays.

    A 3-D problem is drawn on 3-D axes; a 2-D one in the plane.

    Parameters
    ----------
    beacons : (N, d) array
        Beacon positions, m.
    bearings : (N, d) array
        Measured bearings in the receiver frame (unit vectors; NaN rows are skipped).
    res : AoaResult
        ``position`` (d,), m; ``rotation`` (d, d), columns = receiver axes in the global frame.
    path : path, optional
    names : sequence of str, optional
        Beacon names (the beacons file's row names; default ``beacon 0``, ``beacon 1``, ...).

    Returns
    -------
    Figure
    """
    B = np.asarray(beacons, float)
    U = np.asarray(bearings, float)
    m = np.asarray(res.position, float)
    R = np.asarray(res.rotation, float)
    d = B.shape[1]
    span = float(np.max(np.ptp(np.vstack([B, m[None]]), axis=0))) or 1.0
    L = 0.15 * span
    fig = Figure(figsize=(7.0, 6.0))
    ax: Any = fig.add_subplot(1, 1, 1, projection="3d" if d == 3 else None)  # Axes3D in 3-D
    P = B if d == 3 else np.column_stack([B, np.zeros(len(B))])
    mm = m if d == 3 else np.append(m, 0.0)
    RR = R if d == 3 else np.block([[R, np.zeros((2, 1))], [np.zeros((1, 2)), np.ones((1, 1))]])
    UU = U if d == 3 else np.column_stack([U, np.zeros(len(U))])

    def coords(v: NDArray[np.float64]) -> tuple[NDArray[np.float64], ...]:
        return (v[..., 0], v[..., 1], v[..., 2]) if d == 3 else (v[..., 0], v[..., 1])

    ax.scatter(*coords(P), c="C3", marker="s", s=40, label="beacons")
    labels = list(names) if names else [f"beacon {k}" for k in range(len(P))]
    for k, name in enumerate(labels[: len(P)]):
        if np.isfinite(P[k]).all():
            ax.text(*coords(P[k]), f" {name}", fontsize=7, color="C3")
    ax.scatter(*coords(mm[None]), c="k", s=50, label="receiver")
    for a, (col, name) in enumerate(zip(("r", "g", "b"), "xyz", strict=True)):
        if d == 2 and a == 2:
            break
        tip = mm + L * RR[:, a]
        ax.plot(*coords(np.vstack([mm, tip])), color=col, lw=2.5, label=f"receiver {name} axis")
    for k in range(len(P)):
        if not np.isfinite(UU[k]).all():
            continue
        ray = RR @ (UU[k] / np.linalg.norm(UU[k]))
        dist = float(np.linalg.norm(P[k] - mm))
        ax.plot(*coords(np.vstack([mm, mm + dist * ray])), color="0.5", lw=0.8, ls="--")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    if d == 3:
        ax.set_zlabel("z [m]")
        tidy_3d_ticks(ax)
    else:
        ax.set_aspect("equal")
    ok = res.status.name.lower()
    ax.set_title(f"AOA pose ({res.method}, residual {np.degrees(res.residual_rms):.2g} deg, {ok}); "
                 "dashed: measured bearings", fontsize=9)
    ax.legend(loc="best", fontsize=7)
    return finish(fig, path)


def plot_error_surfaces(panels: Sequence[tuple[str, NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]],
                        path: Path | None = None, *, label: str, cmap: str = "viridis") -> Figure:
    """One heat map per panel of a mean error over the receiver's grid (paper 001 Fig. 3-6).

    Parameters
    ----------
    panels : sequence of (title, x, y, z)
        ``x`` (nx,), ``y`` (ny,) grid coordinates in metres and ``z`` (ny, nx) the mean error.
    path : path, optional
    label : str
        Colour bar label with its unit (``"mean location error [m]"``).
    cmap : str

    Returns
    -------
    Figure
    """
    fig, axes = new_figure(1, len(panels), size=(4.2 * len(panels), 3.6))
    for ax, (title, x, y, z) in zip(np.atleast_1d(axes), panels, strict=True):
        plot_heatmap(ax, x, y, z, label=label, cmap=cmap)
        ax.set_title(title)
    return finish(fig, path)
