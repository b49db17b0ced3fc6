"""CMU Plaza range-only robot log (Djugash et al.; via gpslam): ``load_plaza(path)``.

``Plaza1.mat`` (MATLAB v5) holds ``TL`` beacons ``[id, x, y]``, ``TD`` ranges
``[time, -, beacon id, range m]``, ``GT`` ground truth ``[time, x, y, heading rad]`` and ``DR``
odometry ``[time, delta distance m, delta heading rad]``, where ``DR[k]`` is the increment
from ``GT[k]`` to ``GT[k+1]`` (so ``DR[k, 0] == GT[k+1, 0]``).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from ..errors import InputError

__all__ = ["PlazaData", "load_plaza"]

FArray = NDArray[np.float64]


@dataclass(frozen=True)
class PlazaData:
    """The Plaza log as arrays (times in seconds, metres, radians).

    Attributes
    ----------
    beacon_ids : (B,) int ids; beacons : (B, 2) positions.
    range_times : (K,); range_beacon : (K,) index into ``beacons``; ranges : (K,) metres.
    gt_times : (G,); gt : (G, 3) ``[x, y, heading]``.
    odo_times : (G-1,) end times of the odometry increments; odo : (G-1, 2) ``[dd, dpsi]``.
    """

    beacon_ids: NDArray[np.int64]
    beacons: FArray
    range_times: FArray
    range_beacon: NDArray[np.int64]
    ranges: FArray
    gt_times: FArray
    gt: FArray
    odo_times: FArray
    odo: FArray

    def gt_at(self, times: FArray) -> FArray:
        """Ground truth interpolated at ``times`` (K,) -> (K, 3); heading unwrapped then wrapped."""
        t = np.asarray(times, dtype=float)
        psi = np.unwrap(self.gt[:, 2])
        out = np.column_stack([np.interp(t, self.gt_times, self.gt[:, 0]), np.interp(t, self.gt_times, self.gt[:, 1]),
                               np.interp(t, self.gt_times, psi)])
        out[:, 2] = (out[:, 2] + np.pi) % (2 * np.pi) - np.pi
        return out


def load_plaza(path: str | os.PathLike[str]) -> PlazaData:
    """Load ``Plaza1.mat`` (or a compatible log) and validate it.

    Parameters
    ----------
    path : the user's copy of the .mat file.

    Raises
    ------
    InputError if the file is missing, unreadable or lacks / mangles TL, TD, GT or DR.
    """
    p = Path(path)
    if not p.is_file():
        raise InputError(f"{p}: file not found")
    try:
        from scipy.io import loadmat

        m = loadmat(p)
    except Exception as exc:  # scipy raises several types for non-MAT input
        raise InputError(f"{p}: not a readable MATLAB file ({exc})") from None
    for key, width in (("TL", 3), ("TD", 4), ("GT", 4), ("DR", 3)):
        if key not in m:
            raise InputError(f"{p}: missing variable {key!r} (expected TL, TD, GT, DR)")
        a = np.asarray(m[key])
        if a.ndim != 2 or a.shape[1] < width or a.shape[0] < 1 or not np.all(np.isfinite(a[:, :width])):
            raise InputError(f"{p}: {key} must be a finite (rows, {width}) array, got {a.shape}")
    TL = np.asarray(m["TL"], dtype=float)
    TD = np.asarray(m["TD"], dtype=float)
    GT = np.asarray(m["GT"], dtype=float)
    DR = np.asarray(m["DR"], dtype=float)
    ids = TL[:, 0].astype(int)
    lookup = {int(b): k for k, b in enumerate(ids)}
    unknown = sorted({int(b) for b in TD[:, 2]} - set(lookup))
    if unknown:
        raise InputError(f"{p}: TD refers to beacons {unknown} that TL does not list")
    if np.any(np.diff(GT[:, 0]) <= 0):
        raise InputError(f"{p}: GT times must increase")
    if DR.shape[0] != GT.shape[0] - 1:
        raise InputError(f"{p}: DR must have one row fewer than GT (increments between GT rows)")
    if np.any(TD[:, 3] < 0):
        raise InputError(f"{p}: negative ranges in TD")
    order = np.argsort(TD[:, 0], kind="stable")
    TD = TD[order]
    return PlazaData(
        beacon_ids=ids, beacons=TL[:, 1:3].copy(), range_times=TD[:, 0].copy(),
        range_beacon=np.array([lookup[int(b)] for b in TD[:, 2]]), ranges=TD[:, 3].copy(),
        gt_times=GT[:, 0].copy(), gt=GT[:, 1:4].copy(), odo_times=DR[:, 0].copy(), odo=DR[:, 1:3].copy(),
    )
