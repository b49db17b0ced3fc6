"""Trajectory export of a :class:`~selfcal.slac.ranging.RangeSlacResult`: CSV and TUM.

* CSV: header ``time,x,y,heading,x_std,y_std,heading_std`` (s, m, m, rad, m, m, rad).
* TUM (the TUM RGB-D benchmark's trajectory format, read by evo and most SLAM tools): one
  line per pose ``timestamp tx ty tz qx qy qz qw``, space separated, with ``tz = 0`` and the
  planar heading as the unit quaternion about z, ``(0, 0, sin(psi/2), cos(psi/2))``.

Both are written atomically (a temporary file, then a rename).
"""

from __future__ import annotations

import io as _io
import os
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..io import atomic_write_bytes

__all__ = ["trajectory_csv", "trajectory_tum", "write_trajectory_csv", "write_trajectory_tum"]


def _arrays(result: Any) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    return np.asarray(result.times, dtype=float), np.asarray(result.poses, dtype=float), np.asarray(result.pose_std, dtype=float)


def trajectory_csv(result: Any) -> str:
    """CSV text of ``result.times`` (P,), ``poses`` (P, 3) and ``pose_std`` (P, 3).

    Examples
    --------
    >>> from types import SimpleNamespace
    >>> import numpy as np
    >>> r = SimpleNamespace(times=np.array([0.0]), poses=np.array([[1.0, 2.0, 0.5]]), pose_std=np.full((1, 3), 0.1))
    >>> print(trajectory_csv(r).splitlines()[1])
    0.000000,1.000000,2.000000,0.500000,0.100000,0.100000,0.100000
    """
    t, p, s = _arrays(result)
    buf = _io.StringIO()
    np.savetxt(buf, np.column_stack([t, p, s]), delimiter=",", fmt="%.6f",
               header="time,x,y,heading,x_std,y_std,heading_std", comments="")
    return buf.getvalue()


def trajectory_tum(result: Any) -> str:
    """TUM text ``timestamp tx ty tz qx qy qz qw`` of ``result.times`` and ``poses``.

    Examples
    --------
    >>> from types import SimpleNamespace
    >>> import numpy as np
    >>> r = SimpleNamespace(times=np.array([0.0]), poses=np.array([[1.0, 2.0, np.pi]]), pose_std=np.zeros((1, 3)))
    >>> trajectory_tum(r).split()[-2:]
    ['1.000000000', '0.000000000']
    """
    t, p, _ = _arrays(result)
    half = 0.5 * p[:, 2]
    z = np.zeros_like(t)
    buf = _io.StringIO()
    np.savetxt(buf, np.column_stack([t, p[:, 0], p[:, 1], z, z, z, np.sin(half), np.cos(half)]), fmt="%.9f")
    return buf.getvalue()


def write_trajectory_csv(path: str | os.PathLike[str], result: Any) -> None:
    """Write :func:`trajectory_csv` to ``path`` atomically."""
    atomic_write_bytes(path, trajectory_csv(result).encode())


def write_trajectory_tum(path: str | os.PathLike[str], result: Any) -> None:
    """Write :func:`trajectory_tum` to ``path`` atomically."""
    atomic_write_bytes(path, trajectory_tum(result).encode())
