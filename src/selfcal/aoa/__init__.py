"""selfcal.aoa: receiver location and orientation from angles of arrival (paper 001).

The package exports the entry points: :func:`solve_aoa` with its result classes and method
names, the residual test, and the conversions of measurements into bearings
(:mod:`~selfcal.aoa.bearings`: two orthogonal TDOA pairs, angles, azimuth / elevation). The
paper's solutions stay importable from their modules (:mod:`~selfcal.aoa.solution1`,
:mod:`~selfcal.aoa.solution2`, :mod:`~selfcal.aoa.p3p`, :mod:`~selfcal.aoa.planar2d`,
:mod:`~selfcal.aoa.ml`, :mod:`~selfcal.aoa.orientation`); ``solve_aoa(method=...)`` selects
them.

>>> import numpy as np
>>> from selfcal.aoa import solve_aoa
>>> beacons = np.array([[0.0, 0, 0], [5, 0, 0], [0, 5, 0], [5, 5, 0]])
>>> m = np.array([1.0, 2.0, -3.0])
>>> u = (beacons - m) / np.linalg.norm(beacons - m, axis=1, keepdims=True)
>>> res = solve_aoa(beacons, u)          # receiver axes = global axes here
>>> bool(np.allclose(res.position, m))
True
"""

from __future__ import annotations

from .bearings import (
    Bearings,
    angles_to_bearings,
    azel_to_bearings,
    bearings_to_angles,
    bearings_to_azel,
    tdoa_to_bearings,
)
from .checks import residual_test
from .pose import METHODS_2D, METHODS_3D, solve_aoa
from .result import AoaCandidate, AoaResult

__all__ = [
    "AoaCandidate",
    "AoaResult",
    "Bearings",
    "METHODS_2D",
    "METHODS_3D",
    "angles_to_bearings",
    "azel_to_bearings",
    "bearings_to_angles",
    "bearings_to_azel",
    "residual_test",
    "solve_aoa",
    "tdoa_to_bearings",
]


def __dir__() -> list[str]:
    return sorted(__all__)
