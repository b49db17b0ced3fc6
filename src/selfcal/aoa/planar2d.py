"""2-D variant: position and heading from bearings in the plane (beyond paper 001).

With ``R = rot(theta)`` the bearing of beacon k is parallel to ``b_k - m``:
``(b_k - m) x R ubar_k = 0``. Expanding with ``c = cos theta``, ``s = sin theta`` and
``t = R^T m`` gives one *linear homogeneous* equation per beacon in ``x = (c, s, t1, t2)``::

    c (b_x u_y - b_y u_x) + s (b_x u_x + b_y u_y) - u_y t1 + u_x t2 = 0

so three beacons fix ``x`` up to scale (``c^2 + s^2 = 1``) and sign (beacons in front,
``(b_k - m) . R ubar_k > 0``). A two-dimensional null space means the receiver lies on the circle
through the beacons (inscribed-angle theorem: every point of that arc sees the same angles),
reported as the ``danger-circle`` degeneracy.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]

__all__ = ["DANGER_TOL", "linear_pose_2d"]

#: relative second-smallest singular value below which the null space is two-dimensional
DANGER_TOL = 1e-9


def linear_pose_2d(beacons: Array, bearings: Array) -> tuple[Array, Array, Array]:
    """Closed-form (algebraic least-squares) 2-D pose, batched.

    Parameters
    ----------
    beacons : (N, 2) metres, N >= 3; bearings : (B, N, 2) unit vectors in the receiver frame.

    Returns
    -------
    position : (B, 2), rotation : (B, 2, 2), conditioning : (B,) ``s_{3} / s_{1}`` of the
    (normalised) linear system; below :data:`DANGER_TOL` the pose is not determined.
    """
    b = np.asarray(beacons, float)
    U = np.asarray(bearings, float)
    c0 = b.mean(axis=0)
    scale = float(np.sqrt(np.mean(np.sum((b - c0) ** 2, axis=1))))
    bn = (b - c0) / scale  # metres and unit vectors in one matrix: normalise the lever arm
    ux, uy = U[..., 0], U[..., 1]
    M = np.stack(
        [bn[:, 0] * uy - bn[:, 1] * ux, bn[:, 0] * ux + bn[:, 1] * uy, -uy, ux], axis=-1
    )  # (B, N, 4)
    _, s, Vt = np.linalg.svd(M, full_matrices=True)
    x = Vt[:, -1, :]
    x = x / np.linalg.norm(x[:, :2], axis=1, keepdims=True)
    c, sn = x[:, 0], x[:, 1]
    R = np.stack([np.stack([c, -sn], -1), np.stack([sn, c], -1)], -2)
    m = np.einsum("bij,bj->bi", R, x[:, 2:])
    # sign: the beacons must lie in front along their bearings
    front = np.einsum("bkj,bkj->b", bn[None] - m[:, None], np.einsum("bij,bkj->bki", R, U))
    # x -> -x turns R into -R (heading + pi) and leaves m = R t unchanged
    R[front < 0] *= -1.0
    cond = s[:, 2] / s[:, 0] if s.shape[1] > 2 else np.zeros(len(s))
    return c0 + scale * m, R, cond
