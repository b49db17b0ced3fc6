"""Rigid / similarity alignment, rotations, the sphere exponential map and gauge fixing.

Self-calibration recovers geometry only up to a rigid motion (and a reflection);
everything that compares an estimate with ground truth aligns first with
:func:`align` (Kabsch 1976; Umeyama 1991 for the similarity case).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from ._checks import (  # the counts live with the check that uses them
    entry,
    gauge_freedoms,
    n_parameters,
)
from .errors import InputError

__all__ = [
    "Alignment",
    "align",
    "rotate_covariances",
    "rotation_2d",
    "rotation_from_rotvec",
    "rotvec_from_rotation",
    "skew",
    "PlaneFit",
    "fit_plane",
    "wrap_angle",
    "sphere_exp",
    "sphere_tangent_basis",
    "canonical_gauge",
    "pairwise_distances",
    "gauge_freedoms",
    "n_parameters",
]

Array = NDArray[np.float64]


@dataclass(frozen=True)
class Alignment:
    """A transform ``y = scale * R @ x + t`` mapping estimate coordinates to reference ones.

    ``rotation`` is (d, d) orthogonal (det -1 when a reflection was allowed and chosen);
    for a batch (from (B, n, d) inputs) ``rotation`` is (B, d, d), ``translation`` (B, d)
    and ``scale`` a (B,) array.
    """

    rotation: Array
    translation: Array
    scale: float | Array = 1.0

    def apply(self, points: Array) -> Array:
        """Map (n, d) points (or (B, n, d) for a batched alignment) with this transform."""
        P = np.asarray(points, dtype=float)
        s = np.asarray(self.scale, dtype=float)[..., None, None]
        out = s * (P @ np.swapaxes(self.rotation, -1, -2)) + self.translation[..., None, :]
        return out[0] if P.ndim == 2 and self.rotation.ndim == 3 else out


@entry(estimate="array", reference="array", reflection="bool", scale="bool", weights="array")
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
    if ``scale``, a scale s > 0 (Umeyama 1991, eq. 40-42). The one home of orthogonal
    Procrustes in selfcal: the batched initialisers (003 Algorithm 2, eq. 14; the Kabsch
    step of the AOA solutions) call it with a leading batch axis.

    Parameters
    ----------
    estimate, reference : (n, d) or (B, n, d) arrays
        Corresponding points; rows with NaN are ignored.
    reflection : bool
        Allow an improper orthogonal transform (the mirror ambiguity of self-calibration).
    scale : bool
        Also fit a similarity scale.
    weights : (n,) or (B, n) array, optional
        Non-negative weights.

    Returns
    -------
    Alignment
        ``rotation`` (d, d), ``translation`` (d,), ``scale``; batched: (B, d, d), (B, d), (B,).

    Examples
    --------
    >>> import numpy as np
    >>> from selfcal.geometry import align, rotation_2d
    >>> X = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 2.0]])
    >>> Y = X @ rotation_2d(0.3).T + [5.0, -1.0]
    >>> a = align(X, Y, reflection=False)
    >>> bool(np.allclose(a.apply(X), Y)), bool(np.allclose(a.rotation, rotation_2d(0.3)))
    (True, True)
    """
    X = np.asarray(estimate, dtype=float)
    Y = np.asarray(reference, dtype=float)
    if X.shape != Y.shape or X.ndim not in (2, 3):
        raise InputError(f"align: estimate {X.shape} and reference {Y.shape} must be equal (n, d) arrays")
    batched = X.ndim == 3
    if not batched:
        X, Y = X[None], Y[None]
    ok = np.isfinite(X).all(axis=-1) & np.isfinite(Y).all(axis=-1)
    w = np.ones(ok.shape) if weights is None else np.broadcast_to(np.asarray(weights, dtype=float), ok.shape)
    w = np.where(ok, w, 0.0)
    total = w.sum(axis=-1, keepdims=True)
    if np.any(total <= 0):
        raise InputError("align: no finite corresponding points")
    w = w / total
    every = bool(ok.all())  # no row to mask (the same values without the masking copies)
    X0, Y0 = (X, Y) if every else (np.where(ok[..., None], X, 0.0), np.where(ok[..., None], Y, 0.0))
    mx = np.einsum("bn,bnd->bd", w, X0)
    my = np.einsum("bn,bnd->bd", w, Y0)
    Xc = X - mx[:, None] if every else np.where(ok[..., None], X - mx[:, None], 0.0)
    Yc = Y - my[:, None] if every else np.where(ok[..., None], Y - my[:, None], 0.0)
    C = np.einsum("bn,bni,bnj->bij", w, Yc, Xc)
    U, S, Vt = np.linalg.svd(C)
    D = np.ones(S.shape)
    if not reflection:
        D[:, -1] = np.where(np.linalg.det(U @ Vt) < 0, -1.0, 1.0)
    R = (U * D[:, None, :]) @ Vt
    s = np.ones(len(X))
    if scale:
        var_x = np.einsum("bn,bn->b", w, (Xc**2).sum(axis=-1))
        s = np.where(var_x > 0, (S * D).sum(axis=-1) / np.where(var_x > 0, var_x, 1.0), 1.0)
    t = my - s[:, None] * np.einsum("bij,bj->bi", R, mx)
    if batched:
        return Alignment(rotation=R, translation=t, scale=s)
    return Alignment(rotation=R[0], translation=t[0], scale=float(s[0]))


def rotate_covariances(cov: Array, R: Array) -> Array:
    """Covariances of rotated points: ``R C R^T`` for each (d, d) block (a fresh array).

    Parameters
    ----------
    cov : (n, d, d) array
        Covariances, m^2.
    R : (k, k) array
        Rotation with k <= d; it acts on the first k coordinates (a planar alignment of 3-D
        points rotates x and y and leaves z as it was).

    Returns
    -------
    (n, d, d) array

    Examples
    --------
    >>> C = np.array([np.diag([4.0, 1.0])])
    >>> np.round(rotate_covariances(C, rotation_2d(np.pi / 2))[0], 12)
    array([[1., 0.],
           [0., 4.]])
    """
    C = np.array(cov, dtype=float)
    k = np.asarray(R).shape[0]
    C[:, :k, :k] = np.einsum("ab,nbc,dc->nad", R, C[:, :k, :k], R)
    return C


def rotation_2d(theta: float | Array) -> Array:
    """2-D rotation matrix/matrices for angle(s) ``theta`` (rad): shape (2, 2) or (..., 2, 2)."""
    th = np.asarray(theta, dtype=float)
    c, s = np.cos(th), np.sin(th)
    return np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)


def wrap_angle(angle: float | Array) -> Array:
    """Wrap angles (rad) to ``[-pi, pi)``: the one angle wrap of selfcal.

    Examples
    --------
    >>> import numpy as np
    >>> from selfcal.geometry import wrap_angle
    >>> wrap_angle(np.array([np.pi, 3 * np.pi / 2, -0.5])).round(4).tolist()
    [-3.1416, -1.5708, -0.5]
    """
    return (np.asarray(angle, dtype=float) + np.pi) % (2 * np.pi) - np.pi


class PlaneFit(NamedTuple):
    """Total-least-squares plane (hyperplane) through points: see :func:`fit_plane`."""

    centroid: Array
    normal: Array
    singular_values: Array


def fit_plane(points: Array) -> PlaneFit:
    """Total-least-squares plane through (n, d) ``points``: the one plane fit of selfcal.

    The plane passes through the centroid; its unit ``normal`` is the right singular vector
    of the centred points with the smallest singular value (the direction of least extent).
    ``singular_values`` (largest first) say how flat the points are: the RMS distance to
    the plane is ``singular_values[-1] / sqrt(n)``.

    Examples
    --------
    >>> import numpy as np
    >>> from selfcal.geometry import fit_plane
    >>> pts = np.array([[0.0, 0, 1], [1, 0, 1], [0, 1, 1], [1, 1, 1]])
    >>> fit = fit_plane(pts)
    >>> fit.centroid.tolist(), abs(fit.normal).round(12).tolist()
    ([0.5, 0.5, 1.0], [0.0, 0.0, 1.0])
    """
    P = np.asarray(points, dtype=float)
    c = P.mean(axis=0)
    _, s, vt = np.linalg.svd(P - c, full_matrices=P.shape[0] < P.shape[1])  # vt[-1]: least extent
    return PlaneFit(c, vt[-1], s)


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
    """Rodrigues' formula: (..., 3) rotation vectors (axis * angle, rad) -> (..., 3, 3) matrices.

    The SO(3) exponential map, through :class:`scipy.spatial.transform.Rotation`.
    """
    from scipy.spatial.transform import Rotation

    v = np.asarray(rotvec, dtype=float)
    out = Rotation.from_rotvec(v.reshape(-1, 3)).as_matrix()
    return out.reshape(v.shape[:-1] + (3, 3))


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


def canonical_gauge(receivers: Array, sources: Array | None = None, *,
                    proper: bool = True) -> tuple[Array, Array | None, Alignment]:
    """Put an anchor-free reconstruction in selfcal's canonical gauge.

    Canonical gauge: receiver centroid at the origin, receiver principal axes along
    the coordinate axes (largest spread first), each axis oriented so that the third
    moment of the receiver coordinates along it is non-negative.

    Parameters
    ----------
    receivers : (I, d) array
        Positions that define the gauge (NaN rows ignored).
    sources : (J, d) array, optional
        Moved with the same transform.
    proper : bool
        True (default): the transform is a rotation (det +1): when the third-moment signs
        would make it a reflection, the last axis is flipped back, so a mirror image of the
        input stays a mirror image of the output (the handedness the solver found is kept).
        False: every axis follows the third-moment rule and the transform may be a
        reflection, so a configuration and its mirror image give the same output -- the
        deterministic choice for problems whose data cannot tell the mirrors apart (anchor-free
        TOA, far-field TDOA); never for a frame the user gave.

    Returns
    -------
    receivers, sources, alignment
        The transformed points and the :class:`Alignment` (``rotation`` orthogonal, det +1
        when ``proper``).

    Notes
    -----
    The rule is undecided where a third moment vanishes (a configuration symmetric about a
    principal plane) or two principal spreads are equal; the sign then follows rounding.

    Examples
    --------
    >>> import numpy as np
    >>> X = np.random.default_rng(0).normal(size=(8, 3))
    >>> A, _, _ = canonical_gauge(X, proper=False)
    >>> B, _, _ = canonical_gauge(X * np.array([1.0, 1.0, -1.0]), proper=False)  # the mirror image
    >>> bool(np.allclose(A, B))
    True
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
    if proper and np.linalg.det(basis) < 0:
        basis[-1] *= -1.0
    al = Alignment(rotation=basis, translation=-basis @ c, scale=1.0)
    S = None if sources is None else al.apply(sources)
    return al.apply(R), S, al


def pairwise_distances(a: Array, b: Array) -> Array:
    """Euclidean distances between rows: (n, d), (m, d) -> (n, m)."""
    a = np.asarray(a, dtype=float)
    b = np.asarray(b, dtype=float)
    return np.sqrt(np.maximum(((a[:, None, :] - b[None, :, :]) ** 2).sum(-1), 0.0))
