"""Every figure selfcal draws, one module per kind (matplotlib, Agg backend, never shown).

Modules
-------
_common
    :func:`new_figure`, :func:`save_figure` (format from the suffix: ``FILE.pdf`` is a PDF,
    ``.svg`` an SVG, no suffix a PNG), :func:`png_base64` for HTML pages.
elements
    Drawing elements: positions with 95 % ellipses (any pair of coordinates), the three views of
    a 3-D network, empirical CDFs, heat maps.
toa
    ``calibrate toa --plot`` (three views in 3-D), paper 003 Fig. 5-7, an LPS flight.
farfield
    ``calibrate tdoa-farfield --plot``: positions, directions on the unit sphere with a colour bar.
aoa
    ``locate aoa --plot`` (the receiver's axes on 3-D axes) and paper 001's error surfaces.
slac
    ``slac run/plaza --plot`` tracks and paper 002's Fig. 3, Fig. 4 and Table I.
conference
    ``pipeline --plot / --report`` and ``demo``: the unit map, timing, the HTML report's figures.
delays
    ``reproduce delays``: the thesis's accuracy, run time, lambda and noise figures.

Every ``plot_*`` function builds a :class:`~matplotlib.figure.Figure`, writes it when given a
path and returns it; every axis is labelled with its unit. Callers import this package lazily
(inside the command), so ``selfcal --help`` does not load matplotlib.
"""

from __future__ import annotations

from ._common import figure_bytes, new_figure, png_base64, save_figure
from .elements import confidence_ellipse, plot_cdf, plot_heatmap, plot_positions, position_views

__all__ = [
    "new_figure",
    "save_figure",
    "figure_bytes",
    "png_base64",
    "confidence_ellipse",
    "plot_positions",
    "position_views",
    "plot_cdf",
    "plot_heatmap",
]
