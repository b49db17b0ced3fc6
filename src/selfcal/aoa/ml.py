"""Maximum-likelihood refinement of position and rotation from bearings (beyond paper 001).

Model: the measured bearing of beacon k in the receiver frame is the true one
``p_k = R^T (b_k - m) / |b_k - m|`` plus independent angular noise. Two noise models:

``"sphere"``  isotropic angular noise: residual ``T_k^T p_k`` with ``T_k`` (3 x 2) an orthonormal
              basis of the tangent plane at the measured bearing (= the two small angles).
``"angles"``  the paper's simulation model: Gaussian noise on ``alpha_k = acos(p_k,x)`` and
              ``beta_k = acos(p_k,y)`` (eq. 2); residuals are those two angle differences.

Levenberg-Marquardt over ``(m, w)`` with ``R <- R exp([w]x)`` (rotation kept on SO(3), right
perturbation, so ``w`` is in the receiver frame), analytic Jacobians, batched. Covariance of
``(m, w)``: ``sigma^2 (J^T J)^-1`` at the optimum. In 2-D the unknowns are ``(m, theta)`` with
``R = rot(theta)`` and the residual is the wrapped bearing angle difference.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from .orientation import rotvec_to_matrix, tangent_basis

Array = NDArray[np.float64]

__all__ = ["residuals_3d", "residuals_2d", "refine_ml"]


def _skew(v: Array) -> Array:
    K = np.zeros(v.shape[:-1] + (3, 3))
    K[..., 0, 1], K[..., 0, 2] = -v[..., 2], v[..., 1]
    K[..., 1, 0], K[..., 1, 2] = v[..., 2], -v[..., 0]
    K[..., 2, 0], K[..., 2, 1] = -v[..., 1], v[..., 0]
    return K


def residuals_3d(
    beacons: Array, bearings: Array, m: Array, R: Array, *, noise: str = "sphere", jacobian: bool = False
) -> tuple[Array, Array | None]:
    """Angular residuals (rad) of a 3-D pose and, optionally, their Jacobian.

    Parameters
    ----------
    beacons : (N, 3); bearings : (B, N, 3) measured unit bearings (receiver frame);
    m : (B, 3); R : (B, 3, 3).

    Returns
    -------
    e : (B, 2N) residuals; J : (B, 2N, 6) derivatives w.r.t. ``(m, w)`` or None.
    """
    g = beacons[None] - m[:, None]  # (B, N, 3)
    rho = np.linalg.norm(g, axis=-1)[..., None]
    h = g / rho
    p = np.einsum("bji,bkj->bki", R, h)  # R^T h
    B, N, _ = p.shape
    if noise == "sphere":
        T = tangent_basis(bearings)  # (B, N, 3, 2)
        e = np.einsum("bkia,bki->bka", T, p).reshape(B, 2 * N)
        if not jacobian:
            return e, None
        # dp/dm = -R^T (I - h h^T)/rho ; dp/dw = [p]x
        Pm = -(np.eye(3) - h[..., :, None] * h[..., None, :]) / rho[..., None]
        dp_dm = np.einsum("bji,bkjl->bkil", R, Pm)
        dp_dw = _skew(p)
        dp = np.concatenate([dp_dm, dp_dw], axis=-1)  # (B, N, 3, 6)
        J = np.einsum("bkia,bkil->bkal", T, dp).reshape(B, 2 * N, 6)
        return e, J
    # "angles": alpha = acos(p_x), beta = acos(p_y)
    obs = np.arccos(np.clip(bearings[..., :2], -1.0, 1.0))
    pc = np.clip(p[..., :2], -1.0, 1.0)
    e = (np.arccos(pc) - obs).reshape(B, 2 * N)
    if not jacobian:
        return e, None
    Pm = -(np.eye(3) - h[..., :, None] * h[..., None, :]) / rho[..., None]
    dp_dm = np.einsum("bji,bkjl->bkil", R, Pm)
    dp = np.concatenate([dp_dm, _skew(p)], axis=-1)[..., :2, :]  # rows p_x, p_y
    dacos = -1.0 / np.sqrt(np.maximum(1.0 - pc**2, 1e-12))
    J = (dacos[..., None] * dp).reshape(B, 2 * N, 6)
    return e, J


def residuals_2d(
    beacons: Array, bearings: Array, m: Array, theta: Array, *, jacobian: bool = False
) -> tuple[Array, Array | None]:
    """Wrapped bearing-angle residuals (rad) of a 2-D pose ``(m, theta)``.

    ``e_k = wrap(atan2(b_k - m) - theta - phi_k)`` with ``phi_k`` the measured bearing angle in
    the receiver frame. Returns e (B, N) and J (B, N, 3) w.r.t. ``(m_x, m_y, theta)``.
    """
    g = beacons[None] - m[:, None]
    psi = np.arctan2(g[..., 1], g[..., 0])
    phi = np.arctan2(bearings[..., 1], bearings[..., 0])
    e = np.angle(np.exp(1j * (psi - theta[:, None] - phi)))
    if not jacobian:
        return e, None
    r2 = np.sum(g**2, axis=-1)
    J = np.stack([g[..., 1] / r2, -g[..., 0] / r2, -np.ones_like(r2)], axis=-1)
    return e, J


def refine_ml(
    beacons: Array,
    bearings: Array,
    position: Array,
    rotation: Array,
    *,
    noise: str = "sphere",
    sigma: float | None = None,
    max_iter: int = 50,
    tol: float = 1e-12,
) -> dict[str, Array]:
    """Levenberg-Marquardt maximum-likelihood pose, batched (3-D or 2-D from the shapes).

    Parameters
    ----------
    beacons : (N, d); bearings : (B, N, d) unit vectors in the receiver frame;
    position : (B, d) and rotation : (B, d, d) initial pose (``v_global = R v_receiver``).
    noise : ``"sphere"`` or ``"angles"`` (3-D only, see the module notes).
    sigma : angular noise standard deviation (rad) for the covariance; None estimates it from
        the residuals when there are more residuals than unknowns (else the covariance is NaN).

    Returns
    -------
    dict with ``position`` (B, d), ``rotation`` (B, d, d), ``covariance`` (B, q, q) over
    ``(m, w)`` (q = 6) or ``(m, theta)`` (q = 3), ``residual_rms`` (B,) rad, ``iterations`` (B,),
    ``converged`` (B,).
    """
    b = np.asarray(beacons, float)
    U = np.asarray(bearings, float)
    m = np.array(position, float, copy=True)
    R = np.array(rotation, float, copy=True)
    B, N, d = U.shape
    if d == 3:
        q = 6

        def evaluate(m_: Array, R_: Array, jac: bool) -> tuple[Array, Array | None]:
            return residuals_3d(b, U, m_, R_, noise=noise, jacobian=jac)

        def update(m_: Array, R_: Array, s: Array) -> tuple[Array, Array]:
            return m_ + s[:, :3], R_ @ rotvec_to_matrix(s[:, 3:])
    else:
        q = 3
        theta0 = np.arctan2(R[:, 1, 0], R[:, 0, 0])
        R = theta0[:, None, None] * np.ones((1, 1, 1))  # 2-D: carry theta in a (B,1,1) array

        def evaluate(m_: Array, R_: Array, jac: bool) -> tuple[Array, Array | None]:
            return residuals_2d(b, U, m_, R_[:, 0, 0], jacobian=jac)

        def update(m_: Array, R_: Array, s: Array) -> tuple[Array, Array]:
            return m_ + s[:, :2], R_ + s[:, 2][:, None, None]

    lam = np.full(B, 1e-6)
    e, J = evaluate(m, R, True)
    assert J is not None
    cost = np.sum(e**2, axis=1)
    iters = np.zeros(B, int)
    done = np.zeros(B, bool)
    eye = np.eye(q)
    for _ in range(max_iter):
        act = ~done
        if not act.any():
            break
        JtJ = np.swapaxes(J, 1, 2) @ J
        g = np.einsum("bra,br->ba", J, e)
        Hm = JtJ + lam[:, None, None] * (eye * np.maximum(np.diagonal(JtJ, axis1=1, axis2=2), 1e-12)[:, None, :])
        with np.errstate(all="ignore"):
            step = -np.linalg.solve(Hm, g[..., None])[..., 0]
        step[~act | ~np.isfinite(step).all(axis=1)] = 0.0
        m_new, R_new = update(m, R, step)
        e_new, J_new = evaluate(m_new, R_new, True)
        assert J_new is not None
        cost_new = np.sum(e_new**2, axis=1)
        better = act & np.isfinite(cost_new) & (cost_new <= cost)
        m[better], R[better], e[better], J[better] = m_new[better], R_new[better], e_new[better], J_new[better]
        gain = cost - cost_new
        cost = np.where(better, cost_new, cost)
        iters[act] += 1
        lam = np.where(better, np.maximum(lam / 10, 1e-12), lam * 10)
        small = np.linalg.norm(step, axis=1) <= tol * (1 + np.linalg.norm(m, axis=1))
        done |= act & ((better & (small | (gain <= tol * (cost + 1e-30)))) | (lam > 1e8))
    JtJ = np.swapaxes(J, 1, 2) @ J
    # a rejected step at a stationary point (e.g. zero residual) is convergence, not failure
    grad = np.linalg.norm(np.einsum("bra,br->ba", J, e), axis=1)
    stationary = grad <= 1e-10 * np.sqrt(np.trace(JtJ, axis1=1, axis2=2))
    converged = done & ((lam <= 1e8) | stationary)
    dof = e.shape[1] - q
    if sigma is not None:
        s2 = np.full(B, float(sigma) ** 2)
    elif dof > 0:
        s2 = cost / dof
    else:
        s2 = np.full(B, np.nan)
    with np.errstate(all="ignore"):
        cov = np.linalg.pinv(JtJ) * s2[:, None, None]
    if d == 2:
        th = R[:, 0, 0]
        c, s = np.cos(th), np.sin(th)
        R = np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)
    return {
        "position": m,
        "rotation": R,
        "covariance": cov,
        "residual_rms": np.sqrt(cost / e.shape[1]),
        "iterations": iters,
        "converged": converged,
    }
