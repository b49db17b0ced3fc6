"""Turn-rate / velocity motion model of a ground rover (paper 002, eq. 14).

State ``[x, y, psi]`` (metres, radians), controls ``[v, omega]`` (m/s, rad/s), period ``T``:

    x' = x - v/omega sin(psi) + v/omega sin(psi + omega T)
    y' = y + v/omega cos(psi) - v/omega cos(psi + omega T)
    psi' = psi + omega T

Written with ``h = omega T / 2`` as ``x' = x + v T cos(psi + h) sinc(h)`` (and ``sin`` for y),
which is the same function and stays exact in the straight-line limit ``omega -> 0``.
Process noise: the controls carry Gaussian noise of variances ``sigma_v^2 T`` and
``sigma_omega^2 T`` (``sigma_v`` in m/s^1.5, ``sigma_omega`` in rad/s^1.5, as in the paper),
mapped to the state by the control Jacobian: ``Q = B diag(.) B^T`` (Thrun et al. [9]).
All functions are vectorised over a leading batch axis.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from ..geometry import wrap_angle  # the one angle wrap, [-pi, pi) (re-exported here)

__all__ = ["motion_step", "motion_jacobian", "control_jacobian", "process_noise", "wrap_angle"]

FArray = NDArray[np.float64]


def _sinc_terms(h: FArray) -> tuple[FArray, FArray]:
    """``s(h) = sin(h)/h`` and ``s'(h) = (cos h - s(h)) / h`` with series near 0."""
    s = np.sinc(h / np.pi)
    small = np.abs(h) < 1e-4
    hs = np.where(small, 1.0, h)
    ds = np.where(small, -h / 3.0 + h**3 / 30.0, (np.cos(h) - s) / hs)
    return s, ds


def _unpack(state: FArray, controls: FArray, T: float) -> tuple[FArray, FArray, FArray, FArray, FArray]:
    """``(x, u, v, omega, h = omega T / 2)`` as float arrays: the common start of eq. 14 and its Jacobians."""
    x = np.asarray(state, dtype=float)
    u = np.asarray(controls, dtype=float)
    return x, u, u[..., 0], u[..., 1], u[..., 1] * T / 2.0


def motion_step(state: FArray, controls: FArray, T: float) -> FArray:
    """Predicted state ``f(x, u)`` of eq. 14.

    Parameters
    ----------
    state : (..., 3) ``[x, y, psi]``.
    controls : (..., 2) ``[v, omega]``.
    T : float, step in seconds.

    Returns
    -------
    (..., 3) next state (heading not wrapped, so that it stays continuous).
    """
    x, u, v, w, h = _unpack(state, controls, T)
    s, _ = _sinc_terms(h)
    th = x[..., 2] + h
    out = np.empty(np.broadcast(x, np.empty(u.shape[:-1] + (3,))).shape)
    out[..., 0] = x[..., 0] + v * T * np.cos(th) * s
    out[..., 1] = x[..., 1] + v * T * np.sin(th) * s
    out[..., 2] = x[..., 2] + w * T
    return out


def motion_jacobian(state: FArray, controls: FArray, T: float) -> FArray:
    """Jacobian ``d f / d x`` (..., 3, 3) of :func:`motion_step` with respect to the state."""
    x, u, v, w, h = _unpack(state, controls, T)
    s, _ = _sinc_terms(h)
    th = x[..., 2] + h
    F = np.zeros(np.broadcast_shapes(x.shape[:-1], u.shape[:-1]) + (3, 3))
    F[..., 0, 0] = 1.0
    F[..., 1, 1] = 1.0
    F[..., 2, 2] = 1.0
    F[..., 0, 2] = -v * T * np.sin(th) * s
    F[..., 1, 2] = v * T * np.cos(th) * s
    return F


def control_jacobian(state: FArray, controls: FArray, T: float) -> FArray:
    """Jacobian ``d f / d [v, omega]`` (..., 3, 2) of :func:`motion_step`."""
    x, u, v, w, h = _unpack(state, controls, T)
    s, ds = _sinc_terms(h)
    th = x[..., 2] + h
    c, sn = np.cos(th), np.sin(th)
    Bm = np.zeros(np.broadcast_shapes(x.shape[:-1], u.shape[:-1]) + (3, 2))
    Bm[..., 0, 0] = T * c * s
    Bm[..., 1, 0] = T * sn * s
    Bm[..., 0, 1] = v * T * (T / 2.0) * (-sn * s + c * ds)
    Bm[..., 1, 1] = v * T * (T / 2.0) * (c * s + sn * ds)
    Bm[..., 2, 1] = T
    return Bm


def process_noise(state: FArray, controls: FArray, T: float, sigma_v: float, sigma_omega: float) -> FArray:
    """Location process-noise covariance ``B diag(sigma_v^2 T, sigma_omega^2 T) B^T`` (..., 3, 3)."""
    Bm = control_jacobian(state, controls, T)
    Mc = np.array([sigma_v**2 * T, sigma_omega**2 * T])
    return np.einsum("...ik,k,...jk->...ij", Bm, Mc, Bm)
