"""Every solution of the three-beacon problem (perspective-three-point), batched.

Beyond paper 001: its equations (7) and (19) are the classical P3P system (Grunert 1841), which
has up to four real solutions; Newton (Solutions 1 and 2) finds one of them, depending on the
start. Here all of them are found in closed form: with ``r2 = u r1``, ``r3 = v r1`` the three
cosine-rule equations (eq. 20) become two quadratics in ``u`` whose coefficients are
polynomials in ``v``::

    P(u) = u^2 - 2 c12 u + K(v),                 K(v) = 1 - (d12^2/d13^2)(1 + v^2 - 2 c13 v)
    Q(u) = (d12^2 - d23^2) u^2 + 2 (d23^2 c12 - d12^2 c23 v) u + d12^2 v^2 - d23^2

and their Sylvester resultant in ``u`` is a quartic in ``v``. Its real positive roots give ``u``
(the root of P that also zeroes Q), ``r1 = d12 / sqrt(1 + u^2 - 2 c12 u)``, then a few Newton
steps of Solution 2 polish the ranges to machine precision. The pose of each candidate is the
rigid (Kabsch) fit of the back-projected points ``r_k ubar_k`` onto the beacons.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

Array = NDArray[Any]

__all__ = ["p3p_ranges", "p3p"]

MAX_SOLUTIONS = 4


def _pmul(a: Array, b: Array) -> Array:
    """Product of batched polynomials (coefficients lowest degree first, last axis)."""
    out = np.zeros(a.shape[:-1] + (a.shape[-1] + b.shape[-1] - 1,))
    for k in range(b.shape[-1]):
        out[..., k : k + a.shape[-1]] += a * b[..., k : k + 1]
    return out


def _padd(a: Array, b: Array) -> Array:
    n = max(a.shape[-1], b.shape[-1])
    pa = np.zeros(a.shape[:-1] + (n,))
    pb = np.zeros(b.shape[:-1] + (n,))
    pa[..., : a.shape[-1]] = a
    pb[..., : b.shape[-1]] = b
    return pa + pb


def _quartic_roots(c: Array) -> Array:
    """Complex roots (n, 4) of batched quartics ``c[:, 0] + ... + c[:, 4] v^4`` (Ferrari).

    Closed form: depress (``v = y - B/4``), factor ``y^4 + p y^2 + q y + r`` into two
    quadratics ``(y^2 + s y + t)(y^2 - s y + w)`` with ``s^2`` the largest-modulus root of the
    resolvent cubic ``S^3 + 2p S^2 + (p^2 - 4r) S - q^2`` (Cardano, in complex arithmetic).
    About three times faster than companion-matrix eigenvalues and as accurate; the Newton
    polish of the ranges removes what rounding remains. A vanishing leading coefficient
    (degree drop) is replaced by a tiny one, sending the spurious root to infinity where the
    positivity filter discards it.
    """
    c = np.array(c, float, copy=True)
    big = np.max(np.abs(c), axis=1)
    tiny = np.abs(c[:, 4]) < 1e-14 * big
    c[tiny, 4] = 1e-14 * big[tiny]
    a4 = c[:, 4]
    B, C, D, E = c[:, 3] / a4, c[:, 2] / a4, c[:, 1] / a4, c[:, 0] / a4
    p = C - 3 * B**2 / 8
    q = D - B * C / 2 + B**3 / 8
    r = E - B * D / 4 + B**2 * C / 16 - 3 * B**4 / 256
    a2, a1, a0 = 2 * p, p**2 - 4 * r, -(q**2)
    P = a1 - a2**2 / 3
    Q = 2 * a2**3 / 27 - a2 * a1 / 3 + a0
    sq = np.sqrt((Q**2 / 4 + P**3 / 27).astype(complex))
    u1, u2 = -Q / 2 + sq, -Q / 2 - sq
    cub = np.where(np.abs(u1) >= np.abs(u2), u1, u2) ** (1.0 / 3.0)
    omega = np.exp(2j * np.pi / 3)
    S = np.zeros((len(c), 3), complex)
    with np.errstate(all="ignore"):
        for k in range(3):
            ck = cub * omega**k
            S[:, k] = np.where(np.abs(ck) > 0, ck - P / (3 * ck), 0.0) - a2 / 3
    S1 = S[np.arange(len(c)), np.argmax(np.abs(S), axis=1)]
    s_ = np.sqrt(S1)
    with np.errstate(all="ignore"):
        qs = np.where(np.abs(s_) > 0, q / s_, 0.0)
    t = (p + S1 - qs) / 2
    w = (p + S1 + qs) / 2
    d1 = np.sqrt(s_**2 - 4 * t)
    d2 = np.sqrt(s_**2 - 4 * w)
    y = np.stack([(-s_ + d1) / 2, (-s_ - d1) / 2, (s_ + d2) / 2, (s_ - d2) / 2], axis=-1)
    return np.asarray(y - (B / 4)[:, None])


def _polish3(r: Array, cos_p: Array, d2: Array, iters: int = 4, extend: bool = True) -> tuple[Array, Array]:
    """Newton steps on the three-beacon cosine-rule system (eq. 19-20), batched, closed-form.

    ``r`` (n, 3), ``cos_p`` (n, 3) the cosines of the pairs (1,2), (2,3), (3,1), ``d2`` (3,).
    The 3 x 3 Jacobian has two non-zeros per row; it is inverted by Cramer's rule (far faster
    than a batched LAPACK solve on tiny systems). Returns the ranges and ``max|f| / max d^2``.
    """
    r = np.array(r, float, copy=True)
    c12, c23, c31 = cos_p[:, 0], cos_p[:, 1], cos_p[:, 2]
    for it in range(iters + 1):
        if it == iters:
            if not extend:
                break
            # near a double root (danger cylinder) Newton is only linear: keep going there
            slow = _cosine_residual(r, cos_p, d2) > 1e-13
            if not slow.any():
                break
            r[slow] = _polish3(r[slow], cos_p[slow], d2, iters=40, extend=False)[0]
            break
        r1, r2, r3 = r[:, 0], r[:, 1], r[:, 2]
        f = np.stack(
            [
                r1**2 + r2**2 - 2 * r1 * r2 * c12 - d2[0],
                r2**2 + r3**2 - 2 * r2 * r3 * c23 - d2[1],
                r3**2 + r1**2 - 2 * r3 * r1 * c31 - d2[2],
            ],
            axis=-1,
        )
        # J = [[a, b, 0], [0, c, d], [e, 0, g]]
        a, b = 2 * (r1 - r2 * c12), 2 * (r2 - r1 * c12)
        c, d = 2 * (r2 - r3 * c23), 2 * (r3 - r2 * c23)
        e, g = 2 * (r1 - r3 * c31), 2 * (r3 - r1 * c31)
        det = a * c * g + b * d * e
        with np.errstate(all="ignore"):
            inv = np.stack(
                [
                    np.stack([c * g, -b * g, b * d], -1),
                    np.stack([d * e, a * g, -a * d], -1),
                    np.stack([-c * e, b * e, a * c], -1),
                ],
                -2,
            ) / det[:, None, None]
            step = np.einsum("nij,nj->ni", inv, f)
        step = np.where(np.isfinite(step), step, 0.0)
        r -= step
    return r, _cosine_residual(r, cos_p, d2)


def _cosine_residual(r: Array, cos_p: Array, d2: Array) -> Array:
    """``max |f| / max d^2`` of the three-beacon cosine-rule system (eq. 20), (n,)."""
    r1, r2, r3 = r[:, 0], r[:, 1], r[:, 2]
    f = np.stack(
        [
            r1**2 + r2**2 - 2 * r1 * r2 * cos_p[:, 0] - d2[0],
            r2**2 + r3**2 - 2 * r2 * r3 * cos_p[:, 1] - d2[1],
            r3**2 + r1**2 - 2 * r3 * r1 * cos_p[:, 2] - d2[2],
        ],
        axis=-1,
    )
    return np.asarray(np.max(np.abs(f), axis=1) / float(np.max(d2)))


def p3p_ranges(beacons: Array, cosines: Array) -> tuple[Array, Array]:
    """All positive range triples consistent with three beacons and the bearing cosines.

    Parameters
    ----------
    beacons : (3, 3) beacon positions (m).
    cosines : (B, 3) ``[c12, c13, c23]`` with ``c_ij = ubar_i . ubar_j``.

    Returns
    -------
    ranges : (B, 4, 3) candidate ``(r1, r2, r3)``; rows past the valid ones are NaN.
    valid : (B, 4) bool.
    """
    b = np.asarray(beacons, float)
    c12, c13, c23 = (np.asarray(cosines, float)[:, k] for k in range(3))
    B = c12.shape[0]
    d12s = float(np.sum((b[1] - b[0]) ** 2))
    d13s = float(np.sum((b[2] - b[0]) ** 2))
    d23s = float(np.sum((b[2] - b[1]) ** 2))
    k = d12s / d13s
    one = np.ones(B)
    a1 = one[:, None]
    b1 = (-2 * c12)[:, None]
    c1 = np.stack([(1 - k) * one, 2 * k * c13, -k * one], axis=-1)
    a2 = ((d12s - d23s) * one)[:, None]
    b2 = np.stack([2 * d23s * c12, -2 * d12s * c23], axis=-1)
    c2 = np.stack([-d23s * one, 0 * one, d12s * one], axis=-1)
    t1 = _padd(_pmul(a1, c2), -_pmul(a2, c1))
    t2 = _padd(_pmul(a1, b2), -_pmul(a2, b1))
    t3 = _padd(_pmul(b1, c2), -_pmul(b2, c1))
    res = _padd(_pmul(t1, t1), -_pmul(t2, t3))[:, :5]
    roots = _quartic_roots(res)
    v = roots.real
    scale = 1.0 + np.abs(v)
    real = np.abs(roots.imag) <= 1e-5 * scale
    # u solves P(u) = 0; of its two roots keep the one that also solves Q(u) = 0
    K = (1 - k) + 2 * k * c13[:, None] * v - k * v**2
    disc = np.sqrt(np.maximum(c12[:, None] ** 2 - K, 0.0))
    ucand = np.stack([c12[:, None] + disc, c12[:, None] - disc], axis=-1)
    Qv = (
        (d12s - d23s) * ucand**2
        + 2 * (d23s * c12[:, None, None] - d12s * c23[:, None, None] * v[..., None]) * ucand
        + (d12s * v**2 - d23s)[..., None]
    )
    pick = np.argmin(np.abs(Qv), axis=-1)
    u = np.take_along_axis(ucand, pick[..., None], axis=-1)[..., 0]
    with np.errstate(all="ignore"):
        r1 = np.sqrt(d12s) / np.sqrt(1 + u**2 - 2 * u * c12[:, None])
    r = np.stack([r1, u * r1, v * r1], axis=-1)  # (B, 4, 3)
    valid = real & np.isfinite(r).all(axis=-1) & (r > 0).all(axis=-1)
    # polish with Solution 2's Newton (eq. 19-20) on the same cosines, valid slots only
    cos_p = np.stack([c12, c23, c13], axis=-1)
    bi, si = np.nonzero(valid)
    rv, resid = _polish3(r[bi, si], cos_p[bi], np.array([d12s, d23s, d13s]))
    rr = np.full((B, MAX_SOLUTIONS, 3), np.nan)
    rr[bi, si] = rv
    valid[bi, si] = (resid < 1e-6) & (rv > 0).all(axis=-1)
    # a double root shows up twice: keep the first copy
    for a in range(MAX_SOLUTIONS):
        for c in range(a + 1, MAX_SOLUTIONS):
            same = np.max(np.abs(rr[:, a] - rr[:, c]), axis=-1) <= 1e-7 * (1 + np.max(np.abs(rr[:, a]), axis=-1))
            valid[:, c] &= ~(same & valid[:, a])
    rr[~valid] = np.nan
    return rr, valid


def p3p(beacons: Array, bearings: Array) -> tuple[Array, Array, Array]:
    """All poses of a receiver seeing three beacons, batched.

    Parameters
    ----------
    beacons : (3, 3) beacon positions (m).
    bearings : (B, 3, 3) unit bearings in the receiver frame.

    Returns
    -------
    positions : (B, 4, 3), rotations : (B, 4, 3, 3) (``v_global = R v_receiver``),
    valid : (B, 4) bool. Invalid slots are NaN.
    """
    b = np.asarray(beacons, float)
    U = np.asarray(bearings, float)
    B = U.shape[0]
    cos = np.stack(
        [np.sum(U[:, 0] * U[:, 1], -1), np.sum(U[:, 0] * U[:, 2], -1), np.sum(U[:, 1] * U[:, 2], -1)],
        axis=-1,
    )
    r, valid = p3p_ranges(b, cos)
    bi, si = np.nonzero(valid)
    local = r[bi, si][..., None] * U[bi]  # (n, 3, 3) back-projected beacons, receiver frame
    Rv = _triad(b[None]) @ np.swapaxes(_triad(local), -1, -2)
    t = np.full((B, MAX_SOLUTIONS, 3), np.nan)
    R = np.full((B, MAX_SOLUTIONS, 3, 3), np.nan)
    R[bi, si] = Rv
    t[bi, si] = b[0] - np.einsum("nij,nj->ni", Rv, local[:, 0])
    return t, R, valid


def _triad(P: Array) -> Array:
    """Right-handed orthonormal frame (columns) of triangles (..., 3, 3): e1 along p2 - p1,
    e3 normal to the triangle. With congruent triangles (polished P3P ranges) the rotation
    between the two frames is exact and far cheaper than an SVD-based Kabsch fit."""
    e1 = P[..., 1, :] - P[..., 0, :]
    e1 = e1 / np.linalg.norm(e1, axis=-1, keepdims=True)
    e3 = np.cross(e1, P[..., 2, :] - P[..., 0, :])
    e3 = e3 / np.linalg.norm(e3, axis=-1, keepdims=True)
    return np.stack([e1, np.cross(e3, e1), e3], axis=-1)
