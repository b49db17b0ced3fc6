"""selfcal.aoa: receiver location and orientation from angles of arrival (paper 001).

>>> import numpy as np
>>> from selfcal.aoa import solve_aoa
>>> beacons = np.array([[0.0, 0, 0], [5, 0, 0], [0, 5, 0], [5, 5, 0]])
>>> m = np.array([1.0, 2.0, -3.0])
>>> u = (beacons - m) / np.linalg.norm(beacons - m, axis=1, keepdims=True)
>>> res = solve_aoa(beacons, u)          # receiver axes = global axes here
>>> bool(np.allclose(res.position, m))
True
"""

from .ml import refine_ml, residuals_2d, residuals_3d
from .orientation import kabsch, nearest_rotation, orientation_from_vectors
from .p3p import p3p, p3p_ranges
from .planar2d import linear_pose_2d
from .pose import METHODS_2D, METHODS_3D, AoaCandidate, AoaResult, residual_test, solve_aoa
from .solution1 import newton_location, solution1, torus_jacobian, torus_residuals
from .solution2 import newton_ranges, solution2
from .tdoa import (
    Bearings,
    angles_to_bearings,
    azel_to_bearings,
    bearings_to_angles,
    bearings_to_azel,
    tdoa_to_bearings,
)

__all__ = [
    "AoaCandidate",
    "AoaResult",
    "Bearings",
    "METHODS_2D",
    "METHODS_3D",
    "angles_to_bearings",
    "azel_to_bearings",
    "bearings_to_azel",
    "bearings_to_angles",
    "kabsch",
    "linear_pose_2d",
    "nearest_rotation",
    "newton_location",
    "newton_ranges",
    "orientation_from_vectors",
    "p3p",
    "p3p_ranges",
    "refine_ml",
    "residual_test",
    "residuals_2d",
    "residuals_3d",
    "solution1",
    "solution2",
    "solve_aoa",
    "tdoa_to_bearings",
    "torus_jacobian",
    "torus_residuals",
]
