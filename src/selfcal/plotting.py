"""Matplotlib figures shared by every method: positions with 95% ellipses, CDFs, heat maps.

All functions draw on a given Axes (or create a figure) and never call ``plt.show``;
:func:`save_figure` writes PNGs atomically. The Agg backend is forced so that plots work
on headless machines.
"""

from __future__ import annotations

import io
import os
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.axes import Axes  # noqa: E402
from matplotlib.figure import Figure  # noqa: E402
from matplotlib.patches import Ellipse  # noqa: E402
from numpy.typing import NDArray  # noqa: E402

from .io import atomic_write_bytes  # noqa: E402

__all__ = ["confidence_ellipse", "plot_positions", "plot_cdf", "plot_heatmap", "save_figure", "new_figure"]

CHI2_95 = {1: 3.841458820694124, 2: 5.991464547107979, 3: 7.814727903251178}


def new_figure(nrows: int = 1, ncols: int = 1, *, size: tuple[float, float] = (6.0, 5.0)) -> tuple[Figure, Any]:
    """Create a figure with a grid of axes (a thin wrapper so callers need no pyplot import)."""
    fig, axes = plt.subplots(nrows, ncols, figsize=size, squeeze=True)
    return fig, axes


def confidence_ellipse(mean: NDArray[np.float64], cov: NDArray[np.float64], *, level: float = 0.95, **kwargs: Any) -> Ellipse:
    """Ellipse patch of the ``level`` confidence region of a 2-D Gaussian (mean (2,), cov (2, 2))."""
    from scipy.stats import chi2

    k = chi2.ppf(level, 2)
    vals, vecs = np.linalg.eigh(np.asarray(cov, float)[:2, :2])
    vals = np.maximum(vals, 0.0)
    angle = np.degrees(np.arctan2(vecs[1, 1], vecs[0, 1]))
    w, h = 2.0 * np.sqrt(k * vals[1]), 2.0 * np.sqrt(k * vals[0])
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
) -> None:
    """Scatter estimated (n, d) points (first two coordinates) with optional truth and 95% ellipses.

    ``cov`` is (n, d, d); its leading 2 x 2 block gives the ellipse in the x-y plane.
    """
    est = np.asarray(estimate, float)
    ax.scatter(est[:, 0], est[:, 1], s=22, c=color, marker=marker, label=label, zorder=3)
    if truth is not None:
        tr = np.asarray(truth, float)
        ax.scatter(tr[:, 0], tr[:, 1], s=40, facecolors="none", edgecolors="k", marker=marker, label=f"{label} (truth)", zorder=2)
    if cov is not None:
        for m, c in zip(est, np.asarray(cov, float), strict=False):
            if np.all(np.isfinite(c)):
                ax.add_patch(confidence_ellipse(m, c, edgecolor=color, lw=0.8, alpha=0.8))
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")


def plot_cdf(ax: Axes, values: NDArray[np.float64], *, label: str | None = None, **kwargs: Any) -> None:
    """Empirical CDF of finite ``values``."""
    v = np.sort(np.asarray(values, float).ravel())
    v = v[np.isfinite(v)]
    if v.size:
        ax.step(v, np.arange(1, v.size + 1) / v.size, where="post", label=label, **kwargs)
    ax.set_ylim(0, 1)
    ax.set_ylabel("CDF")


def plot_heatmap(
    ax: Axes,
    x: NDArray[np.float64],
    y: NDArray[np.float64],
    z: NDArray[np.float64],
    *,
    label: str = "",
    cmap: str = "viridis",
) -> None:
    """Heat map of ``z`` (len(y), len(x)) over the grid ``x`` (columns) by ``y`` (rows)."""
    im = ax.pcolormesh(np.asarray(x), np.asarray(y), np.asarray(z), shading="auto", cmap=cmap)
    ax.figure.colorbar(im, ax=ax, label=label)
    ax.set_aspect("equal", adjustable="box")


def save_figure(fig: Figure, path: str | os.PathLike[str], *, dpi: int = 120) -> None:
    """Save ``fig`` atomically (format from the suffix: .pdf, .svg, ...; none = PNG) and close it."""
    buf = io.BytesIO()
    fig.tight_layout()
    suffix = os.path.splitext(os.fspath(path))[1].lower().lstrip(".")
    fmt = suffix if suffix in fig.canvas.get_supported_filetypes() else "png"
    fig.savefig(buf, format=fmt, dpi=dpi)
    plt.close(fig)
    atomic_write_bytes(path, buf.getvalue())
