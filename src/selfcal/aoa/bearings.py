"""Bearings: unit lines of sight in the receiver frame, from two orthogonal TDOA pairs or angles (paper 001, eq. 2-4).

The receiver carries two orthogonal sensor pairs whose baselines define its local x and y
axes (paper Fig. 1). Under the far-field assumption the TDOA of a pair gives the cosine of the
angle between the line of sight and the pair's baseline (eq. 3); the third direction cosine
follows from the unit norm (eq. 4) **taking the positive root**: the beacons are assumed to be
in front of the sensor panel (local z >= 0, paper Fig. 2). Noise can push ``|cos| > 1`` or
``cos^2 a + cos^2 b > 1``; those values are clipped and flagged rather than turned into NaN.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .._checks import check_positive
from ..errors import InputError

Array = NDArray[np.float64]

__all__ = ["Bearings", "tdoa_to_bearings", "angles_to_bearings", "bearings_to_angles"]


@dataclass(frozen=True)
class Bearings:
    """Unit line-of-sight vectors in the receiver frame with the clipping flags of eq. 3-4.

    Attributes
    ----------
    vectors : (..., 3) unit vectors ``[cos a, cos b, cos g]`` (eq. 2).
    clipped : (...,) bool, True where ``|cos a| > 1``, ``|cos b| > 1`` or
        ``cos^2 a + cos^2 b > 1`` had to be clipped (noise, or a beacon behind the panel).
    """

    vectors: Array
    clipped: NDArray[np.bool_]

    def to_dict(self) -> dict[str, object]:
        """JSON-safe form."""
        return {"vectors": self.vectors.tolist(), "clipped": self.clipped.tolist()}


def _paired(x: ArrayLike, y: ArrayLike, names: tuple[str, str], not_finite: str) -> tuple[Array, Array]:
    """Two measurements of one beacon set as float arrays: the same shape, finite."""
    a, b = np.asarray(x, float), np.asarray(y, float)
    if a.shape != b.shape:
        raise InputError(f"{names[0]} {a.shape} and {names[1]} {b.shape} must have the same shape")
    if not (np.isfinite(a).all() and np.isfinite(b).all()):
        raise InputError(not_finite)
    return a, b


def _from_cosines(ca: Array, cb: Array) -> Bearings:
    clipped = (np.abs(ca) > 1.0) | (np.abs(cb) > 1.0)
    ca = np.clip(ca, -1.0, 1.0)
    cb = np.clip(cb, -1.0, 1.0)
    g2 = 1.0 - ca**2 - cb**2
    clipped = clipped | (g2 < 0.0)
    # eq. 4, positive root: the beacon is in front of the panel (gamma <= pi/2)
    cg = np.sqrt(np.maximum(g2, 0.0))
    v = np.stack([ca, cb, cg], axis=-1)
    v /= np.linalg.norm(v, axis=-1, keepdims=True)  # re-normalise after clipping
    return Bearings(vectors=v, clipped=np.asarray(clipped, bool))


def tdoa_to_bearings(
    tdoa_12: ArrayLike,
    tdoa_34: ArrayLike,
    *,
    baseline_12: float,
    baseline_34: float,
    speed: float,
) -> Bearings:
    """Bearings from the TDOAs of two orthogonal sensor pairs (paper 001 eq. 2-4).

    ``cos a_k = c d12_k / |s2 - s1|`` and ``cos b_k = c d34_k / |s4 - s3|`` (eq. 3),
    ``cos g_k = +sqrt(1 - cos^2 a_k - cos^2 b_k)`` (eq. 4, front hemisphere).

    Parameters
    ----------
    tdoa_12, tdoa_34 : (...,) seconds
        TDOA of each beacon's signal across the x pair (sensors 1, 2) and the y pair (3, 4),
        ``t_1 - t_2`` so that a beacon along +x has a positive TDOA.
    baseline_12, baseline_34 : float, metres
        Sensor separations ``|s2 - s1|`` and ``|s4 - s3|``.
    speed : float, m/s
        Propagation speed ``c``.

    Returns
    -------
    Bearings
        (..., 3) unit vectors in the receiver frame and the clipping flags.
    """
    b12 = check_positive(baseline_12, "baseline_12", allow_none=False)
    b34 = check_positive(baseline_34, "baseline_34", allow_none=False)
    c = check_positive(speed, "speed", allow_none=False)
    t12, t34 = _paired(tdoa_12, tdoa_34, ("tdoa_12", "tdoa_34"),
                       "TDOAs must be finite (drop the beacons that were not received)")
    assert b12 is not None and b34 is not None and c is not None
    return _from_cosines(c * t12 / b12, c * t34 / b34)


def angles_to_bearings(alpha: ArrayLike, beta: ArrayLike) -> Bearings:
    """Bearings from the angles ``alpha``, ``beta`` (rad) with the local x and y axes (eq. 2, 4).

    This is how the paper's simulation perturbs the measurements: noise on ``alpha`` and
    ``beta``, then eq. 4 for the third cosine.
    """
    a, b = _paired(alpha, beta, ("alpha", "beta"), "alpha and beta must be finite")
    return _from_cosines(np.cos(a), np.cos(b))


def bearings_to_angles(vectors: ArrayLike) -> tuple[Array, Array]:
    """Inverse of :func:`angles_to_bearings`: (..., 3) unit vectors -> (alpha, beta) in rad."""
    v = np.asarray(vectors, float)
    v = v / np.linalg.norm(v, axis=-1, keepdims=True)
    return np.arccos(np.clip(v[..., 0], -1, 1)), np.arccos(np.clip(v[..., 1], -1, 1))


def azel_to_bearings(azimuth: ArrayLike, elevation: ArrayLike | None = None) -> Array:
    """Unit bearings from azimuth / elevation (rad) in the receiver frame: (..., 3) or (..., 2).

    Convention (that of DoA estimators such as ``pyroomacoustics.doa``): azimuth in the
    receiver's xy plane from +x towards +y, elevation from that plane towards +z, so
    ``(cos el cos az, cos el sin az, sin el)``. Unlike the angles to the x and y axes
    (:func:`angles_to_bearings`, paper 001 eq. 2) they keep the side of the xy plane. With
    ``elevation=None`` the 2-D bearings ``(cos az, sin az)``.

    Examples
    --------
    >>> azel_to_bearings(0.0, 0.5 * 3.141592653589793).round(12).tolist()
    [0.0, 0.0, 1.0]
    """
    az = np.asarray(azimuth, float)
    if not np.isfinite(az).all():
        raise InputError("azimuth must be finite")
    if elevation is None:
        return np.stack([np.cos(az), np.sin(az)], axis=-1)
    el = np.asarray(elevation, float)
    if az.shape != el.shape:
        raise InputError(f"azimuth {az.shape} and elevation {el.shape} must have the same shape")
    if not np.isfinite(el).all():
        raise InputError("elevation must be finite")
    return np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], axis=-1)


def bearings_to_azel(vectors: ArrayLike) -> tuple[Array, Array]:
    """Inverse of :func:`azel_to_bearings` for (..., 3) vectors: (azimuth, elevation) in rad."""
    v = np.asarray(vectors, float)
    v = v / np.linalg.norm(v, axis=-1, keepdims=True)
    return np.arctan2(v[..., 1], v[..., 0]), np.arcsin(np.clip(v[..., 2], -1.0, 1.0))
