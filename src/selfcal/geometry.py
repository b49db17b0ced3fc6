"""Rigid / similarity alignment, rotations, the sphere exponential map and gauge fixing.

Self-calibration recovers geometry only up to a rigid motion (and a reflection);
everything that compares an estimate with ground truth aligns first with
:func:`align` (Kabsch 1976; Umeyama 1991 for the similarity case).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from .errors import InputError

__all__ = [
    "Alignment",
    "align",
    "apply_alignment",
    "rotation_2d",
    "rotation_from_rotvec",
    "rotvec_from_rotation",
    "skew",
    "sphere_exp",
    "sphere_tangent_basis",
    "canonical_gauge",
    "pairwise_distances",
]

Array = NDArray[np.float64]


@dataclass(frozen=True)
class Alignment:
    """A transform ``y = scale * R @ x + t`` mapping estimate coordinates to reference ones.

    ``rotation`` is (d, d) orthogonal (det -1 when a reflection was allowed and chosen).
    """

    rotation: Array
    translation: Array
    scale: float = 1.0

    def apply(self, points: Array) -> Array:
        """Map (n, d) points with this transform."""
        return self.scale * np.asarray(points) @ self.rotation.T + self.translation


def align(
    estimate: Array,
    reference: Array,
    *,
    reflection: bool = True,
    scale: bool = False,
    weights: Array | None = None,
) -> Alignment:
    """Least-squares alignment of ``estimate`` onto ``reference`` (Kabsch / Umeyama).

    Minimises ``sum_i w_i |reference_i - (s R estimate_i + t)|^2`` over rotations R
    (orthogonal matrices, det = -1 allowed if ``reflection``), translations t and,
    if ``scale``, a scale s > 0 (Umeyama 1991, eq. 40-42).

    Parameters
    ----------
    estimate, reference: (n, d) arrays of corresponding points; rows with NaN are ignored.
    reflection: allow an improper orthogonal transform (the mirror ambiguity of
        self-calibration).
    scale: also fit a similarity scale.
    weights: optional (n,) non-negative weights.
    """
    X = np.asarray(estimate, dtype=float)
    Y = np.asarray(reference, dtype=float)
    if X.shape != Y.shape or X.ndim != 2:
        raise InputError(f"align: estimate {X.shape} and reference {Y.shape} must be equal (n, d) arrays")
    ok = np.isfinite(X).all(axis=1) & np.isfinite(Y).all(axis=1)
    w = np.ones(len(X)) if weights is None else np.asarray(weights, dtype=float)
    w = np.where(ok, w, 0.0)
    if w.sum() <= 0:
        raise InputError("align: no finite corresponding points")
    w = w / w.sum()
    mx = w @ np.where(ok[:, None], X, 0.0)
    my = w @ np.where(ok[:, None], Y, 0.0)
    Xc = np.where(ok[:, None], X - mx, 0.0)
    Yc = np.where(ok[:, None], Y - my, 0.0)
    C = (Yc * w[:, None]).T @ Xc
    U, S, Vt = np.linalg.svd(C)
    d = X.shape[1]
    D = np.ones(d)
    if not reflection and np.linalg.det(U @ Vt) < 0:
        D[-1] = -1.0
    R = (U * D) @ Vt
    s = 1.0
    if scale:
        var_x = float((w * (Xc**2).sum(axis=1)).sum())
        s = float((S * D).sum() / var_x) if var_x > 0 else 1.0
    t = my - s * R @ mx
    return Alignment(rotation=R, translation=t, scale=s)


def apply_alignment(points: Array, alignment: Alignment) -> Array:
    """Map (n, d) ``points`` with ``alignment`` (convenience for :meth:`Alignment.apply`)."""
    return alignment.apply(points)


def rotation_2d(theta: float | Array) -> Array:
    """2-D rotation matrix/matrices for angle(s) ``theta`` (rad): shape (2, 2) or (..., 2, 2)."""
    th = np.asarray(theta, dtype=float)
    c, s = np.cos(th), np.sin(th)
    return np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)


def skew(v: Array) -> Array:
    """Cross-product matrix [v]_x of (..., 3) vectors, shape (..., 3, 3)."""
    v = np.asarray(v, dtype=float)
    z = np.zeros(v.shape[:-1])
    return np.stack(
        [
            np.stack([z, -v[..., 2], v[..., 1]], -1),
            np.stack([v[..., 2], z, -v[..., 0]], -1),
            np.stack([-v[..., 1], v[..., 0], z], -1),
        ],
        -2,
    )


def rotation_from_rotvec(rotvec: Array) -> Array:
    """Rodrigues' formula: (..., 3) rotation vectors (axis * angle, rad) -> (..., 3, 3) matrices."""
    v = np.asarray(rotvec, dtype=float)
    th = np.linalg.norm(v, axis=-1)[..., None, None]
    K = skew(v)
    small = th < 1e-8
    th_safe = np.where(small, 1.0, th)
    a = np.where(small, 1.0 - th**2 / 6.0, np.sin(th_safe) / th_safe)
    b = np.where(small, 0.5 - th**2 / 24.0, (1.0 - np.cos(th_safe)) / th_safe**2)
    eye = np.broadcast_to(np.eye(3), K.shape)
    return eye + a * K + b * (K @ K)


def rotvec_from_rotation(R: Array) -> Array:
    """Inverse of :func:`rotation_from_rotvec` for (..., 3, 3) rotation matrices (angle in [0, pi])."""
    from scipy.spatial.transform import Rotation

    R = np.asarray(R, dtype=float)
    flat = R.reshape(-1, 3, 3)
    out = Rotation.from_matrix(flat).as_rotvec()
    return out.reshape(R.shape[:-2] + (3,))


def sphere_tangent_basis(n: Array) -> Array:
    """Orthonormal basis of the tangent plane of the unit sphere at (..., 3) unit vectors ``n``.

    Returns (..., 3, 2): two columns orthogonal to ``n`` and to each other.
    """
    n = np.asarray(n, dtype=float)
    # pick the coordinate axis least aligned with n to avoid a degenerate cross product
    idx = np.argmin(np.abs(n), axis=-1)
    e = np.zeros_like(n)
    np.put_along_axis(e, idx[..., None], 1.0, axis=-1)
    t1 = np.cross(n, e)
    t1 /= np.linalg.norm(t1, axis=-1, keepdims=True)
    t2 = np.cross(n, t1)
    return np.stack([t1, t2], axis=-1)


def sphere_exp(n: Array, v: Array) -> Array:
    """Exponential map of the unit sphere: move (..., 3) unit ``n`` along tangent (..., 3) ``v``.

    ``exp_n(v) = cos|v| n + sin|v| v/|v|`` (the re-parametrisation of paper 000, Alg. 3).
    """
    n = np.asarray(n, dtype=float)
    v = np.asarray(v, dtype=float)
    a = np.linalg.norm(v, axis=-1, keepdims=True)
    small = a < 1e-12
    a_safe = np.where(small, 1.0, a)
    out = np.cos(a) * n + np.where(small, 1.0, np.sin(a_safe) / a_safe) * v
    return out / np.linalg.norm(out, axis=-1, keepdims=True)


def canonical_gauge(receivers: Array, sources: Array | None = None) -> tuple[Array, Array | None, Alignment]:
    """Put an anchor-free reconstruction in selfcal's canonical gauge.

    Canonical gauge: receiver centroid at the origin, receiver principal axes along
    the coordinate axes (largest spread first), each axis oriented so that the
    third moment of the receiver coordinates along it is non-negative. This fixes
    translation and rotation; the mirror ambiguity is fixed by making the transform
    proper (det +1). Returns the transformed receivers, sources and the transform.
    """
    R = np.asarray(receivers, dtype=float)
    c = np.nanmean(R, axis=0)
    X = R - c
    Xf = X[np.isfinite(X).all(axis=1)]
    _, _, Vt = np.linalg.svd(Xf, full_matrices=False)
    d = R.shape[1]
    basis = Vt[:d]
    proj = Xf @ basis.T
    signs = np.sign((proj**3).sum(axis=0))
    signs[signs == 0] = 1.0
    basis = basis * signs[:, None]
    if np.linalg.det(basis) < 0:
        basis[-1] *= -1.0
    al = Alignment(rotation=basis, translation=-basis @ c, scale=1.0)
    S = None if sources is None else al.apply(sources)
    return al.apply(R), S, al


def pairwise_distances(a: Array, b: Array) -> Array:
    """Euclidean distances between rows: (n, d), (m, d) -> (n, m)."""
    a = np.asarray(a, dtype=float)
    b = np.asarray(b, dtype=float)
    return np.sqrt(np.maximum(((a[:, None, :] - b[None, :, :]) ** 2).sum(-1), 0.0))
