"""Creating and saving figures: the one place that knows matplotlib's backend and file formats.

Figures are plain :class:`matplotlib.figure.Figure` objects (no pyplot state, so they are
thread-safe and never shown); :func:`save_figure` writes them atomically in the format named by
the path's suffix (``.pdf`` writes a PDF, ``.svg`` an SVG, no suffix a PNG), and
:func:`png_base64` gives the PNG bytes for an HTML page.
"""

from __future__ import annotations

import base64
import io
import os
from typing import Any

import matplotlib

matplotlib.use("Agg")
from matplotlib.figure import Figure  # noqa: E402

from ..io import atomic_write_bytes  # noqa: E402

__all__ = ["new_figure", "save_figure", "figure_bytes", "png_base64", "finish"]


def new_figure(nrows: int = 1, ncols: int = 1, *, size: tuple[float, float] = (6.0, 5.0),
               **subplot_kw: Any) -> tuple[Figure, Any]:
    """A figure with a grid of axes.

    Parameters
    ----------
    nrows, ncols : int
        Grid of axes.
    size : (float, float)
        Figure size, inches.
    **subplot_kw
        Passed to each axes (``projection="3d"`` for a 3-D plot).

    Returns
    -------
    (Figure, Axes or ndarray of Axes)
        One Axes for a 1 x 1 grid, else an array shaped like the grid (squeezed).
    """
    fig = Figure(figsize=size)
    axes = fig.subplots(nrows, ncols, squeeze=True, subplot_kw=subplot_kw or None)
    return fig, axes


def _format(path: str | os.PathLike[str] | None, fig: Figure) -> str:
    if path is None:
        return "png"
    suffix = os.path.splitext(os.fspath(path))[1].lower().lstrip(".")
    if not suffix:
        return "png"
    if suffix not in fig.canvas.get_supported_filetypes():
        from ..errors import InputError

        raise InputError(f"{os.fspath(path)}: unknown figure format '.{suffix}' (use one of png, pdf, svg, ...)")
    return suffix


def figure_bytes(fig: Figure, fmt: str = "png", *, dpi: int = 120) -> bytes:
    """The figure encoded as ``fmt`` (``"png"``, ``"pdf"``, ``"svg"``, ...).

    Parameters
    ----------
    fig : Figure
    fmt : str
        A format matplotlib writes.
    dpi : int
        Resolution of raster formats.

    Returns
    -------
    bytes
    """
    buf = io.BytesIO()
    fig.tight_layout()
    fig.savefig(buf, format=fmt, dpi=dpi)
    return buf.getvalue()


def save_figure(fig: Figure, path: str | os.PathLike[str], *, dpi: int = 120) -> None:
    """Write ``fig`` atomically; the format comes from the suffix (``.pdf`` is a PDF; none = PNG).

    Parameters
    ----------
    fig : Figure
    path : path
        Output file; a non-regular file there is refused (:func:`selfcal.io.atomic_write_bytes`).
    dpi : int
        Resolution of raster formats.

    Raises
    ------
    InputError
        For a suffix matplotlib cannot write.
    """
    atomic_write_bytes(path, figure_bytes(fig, _format(path, fig), dpi=dpi))


def png_base64(fig: Figure, *, dpi: int = 110) -> str:
    """The figure as a base64 PNG (for an ``<img src="data:image/png;base64,...">``)."""
    return base64.b64encode(figure_bytes(fig, "png", dpi=dpi)).decode("ascii")


def finish(fig: Figure, path: str | os.PathLike[str] | None) -> Figure:
    """Save ``fig`` to ``path`` when one is given; return the figure (every ``plot_*`` ends here)."""
    if path is not None:
        save_figure(fig, path)
    return fig
