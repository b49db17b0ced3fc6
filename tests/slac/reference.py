"""Reference computations of the SLAC likelihood, straight from paper 002's definitions.

The library evaluates them batched and factored (:func:`selfcal.slac.likelihood.link_loglik`,
:func:`selfcal.slac.likelihood.fisher_blocks`); the tests compare those against these.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from selfcal.slac.antenna import basis_orders, fourier_basis
from selfcal.slac.likelihood import LinkTerms, _fisher_common
from selfcal.slac.signals import delayed_spectrum

CArray = NDArray[np.complex128]
FArray = NDArray[np.float64]


def concentrated_loglik(
    R: CArray,
    probe: CArray,
    bandwidth: float,
    noise_var: float,
    *,
    tau: float,
    phi: float | None = None,
    G: CArray | None = None,
) -> float:
    """Concentrated log-likelihood of one snapshot, eq. 18 (``G`` given) or eq. 19.

    Straight from the definition with ``e = vec(a s^T)``; reference implementation
    (the filter uses the batched :func:`selfcal.slac.likelihood.link_loglik`).

    Parameters
    ----------
    R : (M, N) complex snapshot, probe : (N,) complex, bandwidth : Hz, noise_var : per bin/port.
    tau : delay in seconds; phi : DoA in the body frame (radians), needed with ``G``.
    G : (M, U) sampling matrix, or None for a single-port receiver (eq. 19).
    """
    R2 = np.atleast_2d(np.asarray(R, dtype=complex))
    s_tau = delayed_spectrum(probe, tau, bandwidth)
    if G is None:
        r = R2.ravel()
        return float(np.abs(np.vdot(s_tau, r)) ** 2 / (noise_var * np.vdot(s_tau, s_tau).real))
    a = np.asarray(G) @ fourier_basis(float(phi if phi is not None else 0.0), np.asarray(G).shape[1])
    e = np.outer(a, s_tau).ravel(order="F")
    r = R2.ravel(order="F")
    return float(np.abs(np.vdot(e, r)) ** 2 / (noise_var * np.vdot(e, e).real))


def link_fisher(
    terms: LinkTerms,
    noise_var: FArray,
    k: float,
    probe_power: FArray,
    *,
    phi: FArray | None = None,
    G: CArray | None = None,
) -> FArray:
    """Fisher information of (rho, phi, g) per link for the concentrated model.

    ``F = (2 |alpha|^2 / sigma^2) Re(D^H P_e^perp D)`` with ``D = d e / d theta`` and the
    amplitude eliminated (the standard nuisance-parameter result); ``|alpha|^2`` is its ML
    estimate ``|c|^2 / (|a|^2 |s|^2)^2``. Inner products factor as
    ``<u (x) s1, v (x) s2> = (u^H v)(s1^H s2)`` so the cost is independent of N.

    Parameters
    ----------
    terms : output of :func:`link_loglik` at the point of interest.
    probe_power : (N,) ``|s(n)|^2``.

    Returns
    -------
    (L, 1, 1) for single-port links (rho only) or (L, P, P) with ``P = 2 + 2 M U`` in the order
    ``[rho, phi, g]`` for multi-port links.
    """
    S, Sd, Sdd, A, scale = _fisher_common(terms, noise_var, k, probe_power)
    a = terms.a
    if G is None:
        f = A * (Sdd - abs(Sd) ** 2 / S)
        return (scale * f)[:, None, None]
    L_, M, U = G.shape
    b = fourier_basis(np.asarray(phi, dtype=float), U)  # (L, U)
    ad = np.einsum("lmu,lu->lm", G, 1j * basis_orders(U) * b)
    # V = [d a/d phi, d a/d Re vec G, d a/d Im vec G] = [a', B, jB] with B[m, u M + m'] = b_u
    # delta_mm'. The Gram blocks are written out in real arithmetic instead of forming the
    # (L, M, P) Jacobian (the dominant cost of the update). Since Sd is imaginary, the rho row
    # of F = Re(DD - De De^H / (A S)) vanishes off the diagonal, leaving
    #   F_rr = A (Sdd - |Sd|^2 / S),   F_vv = S (Re V^H V - Re(h h^H) / A),  h = V^H a.
    MU = M * U
    bb = b.conj()[:, :, None] * b[:, None, :]  # (L, U, U): B^H B = bb kron I_M
    Kr5 = np.zeros((L_, U, M, U, M))
    Ki5 = np.zeros((L_, U, M, U, M))
    for m in range(M):
        Kr5[:, :, m, :, m] = bb.real
        Ki5[:, :, m, :, m] = bb.imag
    Kr = Kr5.reshape(L_, MU, MU)
    Ki = Ki5.reshape(L_, MU, MU)
    e0 = (b[:, :, None] * ad.conj()[:, None, :]).reshape(L_, MU)  # a'^H B
    ha = (b.conj()[:, :, None] * a[:, None, :]).reshape(L_, MU)  # B^H a
    h0 = np.einsum("lm,lm->l", ad.conj(), a)
    P = 1 + 2 * MU
    G_ = np.empty((L_, P, P))  # Re V^H V
    G_[:, 0, 0] = np.sum(np.abs(ad) ** 2, axis=1)
    G_[:, 0, 1 : 1 + MU] = G_[:, 1 : 1 + MU, 0] = e0.real
    G_[:, 0, 1 + MU :] = G_[:, 1 + MU :, 0] = -e0.imag
    G_[:, 1 : 1 + MU, 1 : 1 + MU] = Kr
    G_[:, 1 + MU :, 1 + MU :] = Kr
    G_[:, 1 : 1 + MU, 1 + MU :] = -Ki
    G_[:, 1 + MU :, 1 : 1 + MU] = Ki
    hr = np.concatenate([h0.real[:, None], ha.real, ha.imag], axis=1)
    hi = np.concatenate([h0.imag[:, None], ha.imag, -ha.real], axis=1)
    W = np.stack([hr, hi], axis=2) / np.sqrt(A)[:, None, None]  # (L, P, 2)
    G_ -= W @ np.swapaxes(W, 1, 2)
    G_ *= (scale * S)[:, None, None]
    F = np.zeros((L_, P + 1, P + 1))
    F[:, 0, 0] = scale * A * (Sdd - abs(Sd) ** 2 / S)
    F[:, 1:, 1:] = G_
    return F
