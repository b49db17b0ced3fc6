"""Drawing elements shared by the figures: positions with 95 % ellipses, three views, CDFs, heat maps.

Every element draws on a given Axes and labels the axes it owns with their units.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
from matplotlib.axes import Axes
from matplotlib.figure import Figure
from matplotlib.patches import Ellipse
from numpy.typing import NDArray

__all__ = ["confidence_ellipse", "plot_positions", "position_views", "plot_cdf", "plot_heatmap", "AXIS_NAMES",
           "draw_room", "note_small_ellipses", "integer_ticks", "tidy_3d_ticks"]

AXIS_NAMES = "xyz"


def confidence_ellipse(mean: NDArray[np.float64], cov: NDArray[np.float64], *, level: float = 0.95,
                       scale: float = 1.0, **kwargs: Any) -> Ellipse:
    """Ellipse patch of the ``level`` confidence region of a 2-D Gaussian.

    Parameters
    ----------
    mean : (2,) array
        Centre, m.
    cov : (2, 2) array
        Covariance, m^2 (only the leading 2 x 2 block is used).
    level : float
        Confidence level; the radius in standard deviations is sqrt(chi2.ppf(level, 2)).
    scale : float
        Magnification of the ellipse (a report draws tiny ellipses magnified).
    **kwargs
        Patch properties (``edgecolor``, ``lw``, ...); ``fill`` defaults to False.

    Returns
    -------
    matplotlib.patches.Ellipse
    """
    from scipy.stats import chi2

    k = chi2.ppf(level, 2)
    vals, vecs = np.linalg.eigh(np.asarray(cov, float)[:2, :2])
    vals = np.maximum(vals, 0.0)
    angle = np.degrees(np.arctan2(vecs[1, 1], vecs[0, 1]))
    w, h = 2.0 * scale * np.sqrt(k * vals[1]), 2.0 * scale * np.sqrt(k * vals[0])
    kwargs.setdefault("fill", False)
    return Ellipse(xy=tuple(np.asarray(mean)[:2]), width=w, height=h, angle=angle, **kwargs)


def plot_positions(
    ax: Axes,
    estimate: NDArray[np.float64],
    *,
    truth: NDArray[np.float64] | None = None,
    cov: NDArray[np.float64] | None = None,
    label: str = "estimate",
    color: str = "C0",
    marker: str = "o",
    dims: tuple[int, int] = (0, 1),
    names: Sequence[str] | None = None,
) -> None:
    """Scatter (n, d) points in the plane of coordinates ``dims``, with truth, 95 % ellipses and names.

    Parameters
    ----------
    ax : Axes
    estimate : (n, d) array
        Positions, m.
    truth : (n, d) array, optional
        Drawn as open markers.
    cov : (n, d, d) array, optional
        Position covariances, m^2; the ``dims`` block gives each ellipse (non-finite ones are skipped).
    label, color, marker : str
        Legend label and style.
    dims : (int, int)
        The two coordinates drawn (``(0, 2)`` is the x-z view).
    names : sequence of str, optional
        A name beside each point (the names of the JSON / CSV / ``--known``).
    """
    a, b = dims
    est = np.asarray(estimate, float)
    ax.scatter(est[:, a], est[:, b], s=22, c=color, marker=marker, label=label, zorder=3)
    if truth is not None:
        tr = np.asarray(truth, float)
        from matplotlib.markers import MarkerStyle

        style: dict[str, Any] = ({"facecolors": "none", "edgecolors": "k"} if MarkerStyle(marker).is_filled()
                                 else {"c": "k"})
        ax.scatter(tr[:, a], tr[:, b], s=40, marker=marker, label=f"{label} (truth)", zorder=2, **style)
    if cov is not None:
        idx = np.ix_([a, b], [a, b])
        for m, c in zip(est, np.asarray(cov, float), strict=False):
            c2 = c[idx]
            if np.all(np.isfinite(c2)) and np.all(np.isfinite(m[[a, b]])):
                ax.add_patch(confidence_ellipse(m[[a, b]], c2, edgecolor=color, lw=0.8, alpha=0.8))
    if names is not None:
        for m, name in zip(est, names, strict=False):
            if np.all(np.isfinite(m[[a, b]])):
                ax.annotate(str(name), (m[a], m[b]), fontsize=6, color=color, xytext=(3, 3),
                            textcoords="offset points", zorder=4)
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel(f"{AXIS_NAMES[a]} [m]")
    ax.set_ylabel(f"{AXIS_NAMES[b]} [m]")


#: A 95 % ellipse whose largest semi-axis is below this fraction of the panel's extent is hidden
#: under a marker (a 22 pt^2 marker is ~2.5 pt across a ~350 pt panel, i.e. ~0.7 %).
HIDDEN_ELLIPSE_FRACTION = 0.01


def draw_room(ax: Axes, room: Sequence[float], dims: tuple[int, int] = (0, 1)) -> None:
    """The room's outline ``[0, L] x [0, W] (x [0, H])`` in the plane of ``dims`` (grey rectangle).

    Parameters
    ----------
    ax : Axes
    room : (L, W[, H]) in metres, the frame of the positions drawn (a simulation's truth).
    dims : (int, int)
        The coordinates of the panel.
    """
    from matplotlib.patches import Rectangle

    a, b = dims
    try:
        L = np.asarray(room, dtype=float).ravel()
    except (TypeError, ValueError):
        return  # not a room (a malformed truth.json): no outline
    if max(a, b) >= L.size or not (np.isfinite(L).all() and (L > 0).all()):
        return
    ax.add_patch(Rectangle((0.0, 0.0), float(L[a]), float(L[b]), fill=False, edgecolor="0.5", lw=1.0,
                           ls="-", label="room", zorder=1))
    ax.update_datalim([(0.0, 0.0), (float(L[a]), float(L[b]))])
    ax.autoscale_view()


def note_small_ellipses(ax: Axes, covs: Sequence[NDArray[np.float64]], points: NDArray[np.float64],
                        dims: tuple[int, int] = (0, 1)) -> str | None:
    """Say on the panel when every 95 % ellipse is smaller than the markers (so none is visible).

    Parameters
    ----------
    ax : Axes
    covs : sequence of (n, d, d) arrays
        The covariances drawn, m^2.
    points : (n, d) array
        Every point drawn (for the panel's extent), m.
    dims : (int, int)

    Returns
    -------
    str or None
        The note written, or None when the ellipses are visible (or there are none).
    """
    from scipy.stats import chi2

    semi = []
    for C in covs:
        C = np.asarray(C, float)
        if C.ndim != 3 or C.shape[0] == 0:
            continue
        blk = C[:, list(dims)][:, :, list(dims)]
        ok = np.isfinite(blk).all(axis=(1, 2))
        if ok.any():
            semi.append(np.sqrt(chi2.ppf(0.95, 2) * np.linalg.eigvalsh(blk[ok])[:, -1].clip(min=0)))
    P = np.asarray(points, float)[:, list(dims)]
    P = P[np.isfinite(P).all(axis=1)]
    if not semi or len(P) < 2:
        return None
    largest = float(np.max(np.concatenate(semi)))
    extent = float(np.ptp(P, axis=0).max())
    if not extent > 0 or largest >= HIDDEN_ELLIPSE_FRACTION * extent:
        return None
    size = f"{largest * 1000:.2g} mm" if largest < 0.01 else f"{largest * 100:.2g} cm"
    note = f"95 % ellipses (largest semi-axis {size}) are smaller than the markers"
    ax.text(0.01, 0.01, note, transform=ax.transAxes, fontsize=7, color="0.3", va="bottom", ha="left")
    return note


def tidy_3d_ticks(ax: Any, n: int = 4) -> None:
    """At most ``n`` ticks per axis of a 3-D Axes, in a smaller font (dense 3-D tick labels overlap)."""
    from matplotlib.ticker import MaxNLocator

    for axis in (ax.xaxis, ax.yaxis, ax.zaxis):
        axis.set_major_locator(MaxNLocator(n))
    ax.tick_params(labelsize=7)


def integer_ticks(axis: Any) -> None:
    """Ticks at integers only (unit / receiver indices), e.g. ``integer_ticks(ax.xaxis)``."""
    from matplotlib.ticker import MaxNLocator

    axis.set_major_locator(MaxNLocator(integer=True))


def position_views(fig: Figure, dim: int) -> list[tuple[Axes, tuple[int, int]]]:
    """Axes for a position plot: one x-y panel in 2-D, three views (x-y, x-z, y-z) in 3-D.

    Parameters
    ----------
    fig : Figure
        An empty figure.
    dim : int
        2 or 3.

    Returns
    -------
    list of (Axes, (int, int))
        Each panel with the coordinates it shows (pass them as ``dims`` to :func:`plot_positions`).
    """
    if dim < 3:
        return [(fig.add_subplot(1, 1, 1), (0, 1))]
    views = ((0, 1), (0, 2), (1, 2))
    return [(fig.add_subplot(1, 3, k + 1), v) for k, v in enumerate(views)]


def plot_cdf(ax: Axes, values: NDArray[np.float64], *, label: str | None = None, **kwargs: Any) -> None:
    """Empirical CDF of the finite ``values`` (the caller labels the x axis with its unit)."""
    v = np.sort(np.asarray(values, float).ravel())
    v = v[np.isfinite(v)]
    if v.size:
        ax.step(v, np.arange(1, v.size + 1) / v.size, where="post", label=label, **kwargs)
    ax.set_ylim(0, 1)
    ax.set_ylabel("empirical CDF [-]")


def plot_heatmap(
    ax: Axes,
    x: NDArray[np.float64],
    y: NDArray[np.float64],
    z: NDArray[np.float64],
    *,
    label: str = "",
    cmap: str = "viridis",
    xlabel: str = "x [m]",
    ylabel: str = "y [m]",
) -> None:
    """Heat map of ``z`` (len(y), len(x)) over the grid ``x`` (columns) by ``y`` (rows), with a colour bar.

    Parameters
    ----------
    ax : Axes
    x, y : 1-D arrays
        Grid coordinates (metres unless the labels say otherwise).
    z : (len(y), len(x)) array
    label : str
        Colour bar label, with its unit.
    cmap : str
    xlabel, ylabel : str
        Axis labels with units.
    """
    im = ax.pcolormesh(np.asarray(x), np.asarray(y), np.asarray(z), shading="auto", cmap=cmap)
    ax.figure.colorbar(im, ax=ax, label=label)
    ax.set_aspect("equal", adjustable="box")
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
