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

from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..optim.lm import BatchModel, levenberg_marquardt_batch
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


class _PoseModel(BatchModel):
    """The pose model for :func:`selfcal.optim.levenberg_marquardt_batch`: a point is
    ``[m (d), R (d d)]`` per start (2-D: R holds theta), a step ``(m, w)`` or ``(m, theta)``."""

    def __init__(self, evaluate: Any, update: Any, q: int, d: int, rshape: tuple[int, ...]) -> None:
        self._evaluate, self._update, self.q, self.d, self.rshape = evaluate, update, q, d, rshape

    def split(self, X: Array) -> tuple[Array, Array]:
        return X[:, :self.d], X[:, self.d:].reshape(X.shape[0], *self.rshape)

    def evaluate(self, X: Array, rows: NDArray[np.intp]) -> tuple[Array, tuple[Array, Array]]:
        e, J = self._evaluate(*self.split(X), True, rows)
        return np.sum(e**2, axis=1), (e, J)

    def retract(self, X: Array, dX: Array) -> Array:
        m_, R_ = self._update(*self.split(X), dX)
        return np.concatenate([m_, R_.reshape(X.shape[0], -1)], axis=1)

    def small_step(self, X: Array, dX: Array, xtol: float) -> NDArray[np.bool_]:
        out: NDArray[np.bool_] = np.linalg.norm(dX, axis=1) <= xtol * (1 + np.linalg.norm(X[:, :self.d], axis=1))
        return out

    def linearize(self, X: Array, state: tuple[Array, Array]) -> Any:
        e, J = state
        JtJ = np.swapaxes(J, 1, 2) @ J
        g = np.einsum("bra,br->ba", J, e)
        dg = np.maximum(np.diagonal(JtJ, axis1=1, axis2=2), 1e-12)
        return _PoseStep(JtJ, g, dg, np.eye(self.q))


class _PoseStep:
    """The stacked damped normal equations of the poses (``q`` x ``q`` each)."""

    def __init__(self, JtJ: Array, g: Array, dg: Array, eye: Array) -> None:
        self.JtJ, self.g, self.dg, self.eye = JtJ, g, dg, eye
        # cost = sum e^2: the driver's test |g| <= 1e-6 max(1, sqrt(2 cost)) on J^T e
        self.gnorm = np.linalg.norm(g, axis=1)

    def step(self, lam: Array, t: NDArray[np.intp]) -> Array:
        Hm = self.JtJ[t] + lam[:, None, None] * (self.eye * self.dg[t][:, None, :])
        with np.errstate(all="ignore"):
            return np.asarray(-np.linalg.solve(Hm, self.g[t][..., None])[..., 0])

    def predicted(self, dx: Array, t: NDArray[np.intp]) -> Array:
        # decrease of |e + J dx|^2: -(2 g.dx + dx.JtJ.dx)
        return np.asarray(-(2 * np.einsum("ba,ba->b", self.g[t], dx)
                            + np.einsum("ba,bac,bc->b", dx, self.JtJ[t], dx)))


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

        def evaluate(m_: Array, R_: Array, jac: bool, rows: Any = slice(None)) -> tuple[Array, Array | None]:
            return residuals_3d(b, U[rows], m_, R_, noise=noise, jacobian=jac)

        def update(m_: Array, R_: Array, s: Array) -> tuple[Array, Array]:
            return m_ + s[:, :3], R_ @ rotvec_to_matrix(s[:, 3:])
    else:
        q = 3
        theta0 = np.arctan2(R[:, 1, 0], R[:, 0, 0])
        R = theta0[:, None, None] * np.ones((1, 1, 1))  # 2-D: carry theta in a (B,1,1) array

        def evaluate(m_: Array, R_: Array, jac: bool, rows: Any = slice(None)) -> tuple[Array, Array | None]:
            return residuals_2d(b, U[rows], m_, R_[:, 0, 0], jacobian=jac)

        def update(m_: Array, R_: Array, s: Array) -> tuple[Array, Array]:
            return m_ + s[:, :2], R_ + s[:, 2][:, None, None]

    model = _PoseModel(evaluate, update, q, m.shape[1], R.shape[1:])
    out = levenberg_marquardt_batch(model, np.concatenate([m, R.reshape(B, -1)], axis=1), max_iter=max_iter,
                                    xtol=tol, ftol=tol, lam0=1e-6)
    m, R = model.split(out.x)
    e, J = evaluate(m, R, True)
    assert J is not None
    cost, iters = np.sum(e**2, axis=1), out.iterations
    JtJ = np.swapaxes(J, 1, 2) @ J
    # a rejected step at a stationary point (e.g. zero residual) is convergence, not failure
    grad = np.linalg.norm(np.einsum("bra,br->ba", J, e), axis=1)
    stationary = grad <= 1e-10 * np.sqrt(np.trace(JtJ, axis1=1, axis2=2))
    converged = out.converged | stationary
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
