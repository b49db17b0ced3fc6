"""The installer's figure of a UWB anchor set: named anchors with 95 % ellipses, the tag path,
the room box, in three views (plan x-y, elevations x-z and y-z).
"""

from __future__ import annotations

import os
from collections.abc import Sequence

import numpy as np
from matplotlib.figure import Figure
from numpy.typing import NDArray

from ._common import finish
from .elements import AXIS_NAMES, plot_positions

__all__ = ["plot_anchors", "room_box"]

Path = str | os.PathLike[str]
Array = NDArray[np.float64]

_VIEWS = (((0, 1), "plan (x-y)"), ((0, 2), "elevation (x-z)"), ((1, 2), "elevation (y-z)"))


def room_box(values: Sequence[float]) -> Array:
    """A room box ``(2, 3)`` (min corner, max corner) from ``W,D,H`` or ``x0,y0,z0,x1,y1,z1`` (m).

    Examples
    --------
    >>> room_box([5, 4, 3]).tolist()
    [[0.0, 0.0, 0.0], [5.0, 4.0, 3.0]]
    """
    from ..errors import InputError

    v = np.asarray(values, float).ravel()
    if v.size == 3:
        v = np.concatenate([np.zeros(3), v])
    if v.size != 6 or not np.isfinite(v).all():
        raise InputError(f"room: give W,D,H or x0,y0,z0,x1,y1,z1 in metres (finite), got {len(values)} values")
    box = v.reshape(2, 3)
    if np.any(box[1] <= box[0]):
        raise InputError(f"room: the far corner {box[1].tolist()} must exceed the near one {box[0].tolist()}")
    return box


def plot_anchors(
    anchors: Array,
    names: Sequence[str],
    path: Path | None = None,
    *,
    cov: Array | None = None,
    tag: Array | None = None,
    room: Array | None = None,
    title: str = "",
) -> Figure:
    """Named anchors with 95 % ellipses, the tag path and the room box, in three views (3-D).

    Parameters
    ----------
    anchors : (k, d) array
        Anchor positions in the room frame, m (z up).
    names : sequence of str
        One name per anchor, written next to it in every view.
    path : path, optional
        Output file (format from the suffix); None only builds the figure.
    cov : (k, d, d) array, optional
        Anchor covariances, m^2 (95 % ellipses; NaN ones skipped).
    tag : (t, d) array, optional
        Tag positions in time order, drawn as a line (NaN rows break it).
    room : (2, 3) array, optional
        Room box (min corner, max corner), m: its outline in every view.
    title : str

    Returns
    -------
    Figure
        One panel (x-y) in 2-D; three (plan x-y, elevations x-z and y-z) in 3-D.
    """
    from scipy.stats import chi2

    from .elements import confidence_ellipse

    A = np.asarray(anchors, float)
    d = A.shape[1]
    views = _VIEWS if d == 3 else _VIEWS[:1]
    # ellipses of millimetres are invisible on a room: magnified to ~3 % of the extent, stated
    mag = 1.0
    if cov is not None:
        C = np.asarray(cov, float)
        ok = np.isfinite(C).all(axis=(1, 2))
        semi = float(np.sqrt(chi2.ppf(0.95, 2) * np.max(np.linalg.eigvalsh(C[ok]), initial=0.0))) if ok.any() else 0.0
        extent = float(np.nanmax(np.ptp(A, axis=0))) if A.shape[0] > 1 else 1.0
        if semi > 0 and semi < 0.03 * extent:
            want = 0.03 * extent / semi
            base = 10 ** np.floor(np.log10(want))
            mag = float(max(m * base for m in (1, 2, 5) if m * base <= want))
    ell = "95 % ellipses" + (f" x{mag:g}" if mag > 1 else "")
    fig = Figure(figsize=(5.5 * len(views), 5.0))
    for k, ((a, b), label) in enumerate(views):
        ax = fig.add_subplot(1, len(views), k + 1)
        if room is not None:
            (x0, y0), (x1, y1) = room[0, [a, b]], room[1, [a, b]]
            ax.plot([x0, x1, x1, x0, x0], [y0, y0, y1, y1, y0], color="0.5", lw=1.0, label="room")
        if tag is not None and len(tag):
            T = np.asarray(tag, float)
            ax.plot(T[:, a], T[:, b], color="C1", lw=0.7, alpha=0.7, label="tag path")
        plot_positions(ax, A, label=f"anchors ({ell})" if cov is not None else "anchors", color="C0", marker="^",
                       dims=(a, b))
        if cov is not None:
            for p, c in zip(A, np.asarray(cov, float), strict=False):
                c2 = c[np.ix_([a, b], [a, b])]
                if np.isfinite(c2).all() and np.isfinite(p[[a, b]]).all():
                    ax.add_patch(confidence_ellipse(p[[a, b]], c2, scale=mag, edgecolor="C0", lw=0.8))
        for p, name in zip(A, names, strict=False):
            if np.isfinite(p[[a, b]]).all():
                ax.annotate(str(name), (p[a], p[b]), textcoords="offset points", xytext=(4, 4), fontsize=8)
        ax.set_xlabel(f"{AXIS_NAMES[a]} [m]")
        ax.set_ylabel(f"{AXIS_NAMES[b]} [m]")
        ax.set_title(label, fontsize=10)
        if k == 0:
            ax.legend(loc="best", fontsize=7)
    if title:
        fig.suptitle(title)
    return finish(fig, path)

