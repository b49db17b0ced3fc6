"""Coherent maximum-likelihood DoA estimation with a given antenna response (paper 002, sec. V).

For a snapshot ``R`` (M, N) and the delay-compensated port vector ``y = R s^*(tau)`` the
coherent ML DoA maximises the concentrated likelihood of eq. 18 over ``phi`` alone:
``phi_hat = argmax |a(phi)^H y|^2 / |a(phi)|^2`` with ``a = G b(phi)``. The delay is the
antenna-agnostic ML delay (FFT grid) unless given. Grid search, then Newton refinement on
the analytic derivative.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from ..errors import InputError
from ..geometry import wrap_angle
from .antenna import basis_orders, fourier_basis
from .signals import delay_grid_search

__all__ = ["doa_spectrum", "estimate_doa", "estimate_doa_from_y"]

CArray = NDArray[np.complex128]


def doa_spectrum(y: CArray, G: CArray, phis: NDArray[np.float64]) -> NDArray[np.float64]:
    """Normalised coherent ML spectrum ``|a^H y|^2 / (|a|^2 |y|^2)`` in [0, 1] on ``phis`` (K,)."""
    a = fourier_basis(phis, G.shape[1]) @ G.T  # (K, M)
    num = np.abs(a.conj() @ y) ** 2
    return num / (np.sum(np.abs(a) ** 2, axis=1) * np.vdot(y, y).real)


def estimate_doa_from_y(y: CArray, G: CArray, *, grid: int = 720, newton_steps: int = 4) -> float:
    """ML DoA (radians, in [-pi, pi)) from a delay-compensated port vector ``y`` (M,)."""
    y = np.asarray(y, dtype=complex).ravel()
    G = np.asarray(G, dtype=complex)
    if G.ndim != 2 or G.shape[0] != y.size or y.size < 2:
        raise InputError(f"DoA needs a multi-port G (M, U) with M = len(y) >= 2; got G {G.shape}, y {y.shape}")
    phis = -np.pi + 2 * np.pi * np.arange(grid) / grid
    spec = doa_spectrum(y, G, phis)
    phi = float(phis[int(np.argmax(spec))])
    U = G.shape[1]
    u = basis_orders(U)
    h = 2 * np.pi / grid
    for _ in range(newton_steps):
        # f(phi) = log spectrum; Newton on numerically stable central differences of the
        # analytic first derivative keeps this tiny routine independent of the filter code.
        def d1(p: float) -> float:
            b = fourier_basis(p, U)
            a = G @ b
            ad = G @ (1j * u * b)
            c = np.vdot(a, y)
            A = np.vdot(a, a).real
            return float(2 * np.real(np.conj(c) * np.vdot(ad, y)) / abs(c) ** 2 - 2 * np.real(np.vdot(a, ad)) / A)

        g0 = d1(phi)
        eps = h / 20
        g2 = (d1(phi + eps) - d1(phi - eps)) / (2 * eps)
        if g2 >= 0:
            break
        step = float(np.clip(-g0 / g2, -h, h))
        phi += step
        if abs(step) < 1e-9:
            break
    return float(wrap_angle(phi))


def estimate_doa(
    R: CArray, probe: CArray, bandwidth: float, G: CArray, *, tau: float | None = None, grid: int = 720
) -> float:
    """Coherent ML DoA of one snapshot ``R`` (M, N) for the antenna with sampling matrix ``G``.

    Parameters
    ----------
    R : (M, N) snapshot, probe : (N,) known spectrum, bandwidth : Hz.
    G : (M, U) assumed sampling matrix (EM prior, chamber prior or SLAC estimate).
    tau : delay in seconds; default: the antenna-agnostic FFT-grid ML delay.

    Returns
    -------
    DoA in the body frame, radians in [-pi, pi).
    """
    R2 = np.atleast_2d(np.asarray(R, dtype=complex))
    if tau is None:
        _, y = delay_grid_search(R2, probe, bandwidth)
    else:
        n = np.arange(R2.shape[1])
        y = (R2 * np.conj(probe)) @ np.exp(2j * np.pi * tau * bandwidth * n / R2.shape[1])
    return estimate_doa_from_y(y, G, grid=grid)
