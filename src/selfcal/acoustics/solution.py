"""The solution the acoustic pipeline carries from its model fit to its verdict.

:class:`Calibration` is built by :mod:`selfcal.acoustics.calibrate` from the TOA solver's
result (2-D / 3-D) or the known-heights fit, refitted by the robust loop
(:mod:`selfcal.acoustics.robust_fit`) and read by the pipeline, the leverages, the residual
test and the scale from known distances.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from .._result import Result

if TYPE_CHECKING:
    from ..toa.verdict.uniqueness import UniquenessTest

__all__ = ["Calibration"]

Array = NDArray[np.float64]


@dataclass(frozen=True, repr=False)
class Calibration(Result):
    """One model fit of the per-sender TOA matrix: the solution the pipeline carries.

    Built from the :class:`selfcal.toa.ToaResult` of :func:`selfcal.toa.solve_toa` (2-D /
    3-D models) or returned by :func:`selfcal.acoustics.geometry.refine_known_heights` (known
    heights); a :class:`selfcal._result.Result` (``status`` from ``converged``); the robust loop (:mod:`selfcal.acoustics.robust_fit`) refits it with
    :func:`selfcal.acoustics.calibrate.refit` and the pipeline changes it with ``dataclasses.replace``.

    Attributes
    ----------
    receivers, sources : (I, d), (J, d) arrays
        Positions, m (NaN rows: nodes the fit did not locate); d = 3 with known heights.
    receiver_offsets, source_offsets : (I,), (J,) arrays
        Delays / onsets, s, shifted so that the first located onset is 0 (004 sec. 3.3).
    receiver_cov, source_cov : arrays
        (I, d, d), (J, d, d) position covariances, m^2 (NaN when the fit computed none).
    residual_rms : float
        s.
    converged : bool
    iterations : int
    method : str
        The label reported: the model (``"2d"``, ``"3d"``, ``"2d+heights"``) and the solver's method.
    dim : int
        Free coordinates per node: 2 for the 2-D model and for known heights, 3 for the 3-D model.
    known_heights : bool
        Every z given (:func:`selfcal.acoustics.geometry.refine_known_heights`).
    toa_outliers : (I, J) bool array or None
        Entries the TOA solver's outlier rule excluded (None: no such rule ran).
    uniqueness : UniquenessTest or None
        The TOA solver's flip test (:mod:`selfcal.toa.verdict.uniqueness`).
    outlier_breakdown : str or None
        Why the solver's outlier answer cannot be trusted, when it cannot.
    one_side : {"receivers", "sources"} or None
        The side put on one side of its partners' plane by the stated rule (:func:`calibrate_matrix`).
    extra_cov : ((I, d, d), (J, d, d)) arrays or None
        Covariance added to the linearised one and kept through refits: the 3-D estimator's
        bootstrap mean-square error where the planarity test's bootstrap ran and the answer
        stayed 3-D (:func:`selfcal.toa.verdict.select.dimension_test`); None elsewhere.
    """

    receivers: Array
    sources: Array
    receiver_offsets: Array
    source_offsets: Array
    receiver_cov: Array
    source_cov: Array
    residual_rms: float
    converged: bool
    iterations: int
    method: str
    dim: int
    known_heights: bool = False
    toa_outliers: NDArray[np.bool_] | None = None
    uniqueness: UniquenessTest | None = None
    outlier_breakdown: str | None = None
    one_side: str | None = None
    extra_cov: tuple[Array, Array] | None = None
