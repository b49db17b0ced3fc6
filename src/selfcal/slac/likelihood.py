"""Concentrated log-likelihoods of received OFDM snapshots (paper 002, eqs. 18-19).

With ``e = vec(a(phi) s(tau)^T)`` the amplitude and phase of eq. 3 are eliminated in closed
form, leaving (up to a constant)

    multi-port  (eq. 18):  L = |e^H r|^2 / (sigma^2 e^H e) = |a^H y|^2 / (sigma^2 |a|^2 |s|^2)
    single-port (eq. 19):  L = |s(tau)^H r|^2 / (sigma^2 |s|^2)

with ``y(tau) = R s^*(tau)`` (M,). Eq. 19 is eq. 18 with a scalar ``a`` (which cancels). Delays
enter as round-trip ranges ``rho = c tau / 2`` so that ``y(rho) = sum_n X[:, n] e^{j k rho n}``,
``X = R * conj(s)`` and ``k`` from :func:`~selfcal.slac.signals.range_wavenumber`.

The batched core :func:`link_loglik` evaluates L and its analytic gradient with respect to
``rho``, ``phi`` and the sampling matrix ``G`` for L links at once (vectorised over links,
ports and subcarriers); :func:`fisher_blocks` gives the Fisher information of the same
parameters (used for the Laplace covariance and as the BFGS preconditioner). The definitions
straight from eqs. 18-19 (one snapshot, the dense Fisher matrix) are the tests' references
(``tests/slac/reference.py``).

Sampling-matrix parameters are packed as in eq. 16: ``g = [Re vec(G); Im vec(G)]`` with
``vec`` stacking columns, i.e. index ``u * M + m``.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from .antenna import basis_orders, fourier_basis
from .signals import phasors

__all__ = [
    "LinkTerms",
    "link_loglik",
    "FisherBlocks",
    "fisher_blocks",
    "pack_g",
    "DelayExpansion",
    "delay_expansion",
    "unpack_g",
]

CArray = NDArray[np.complex128]
FArray = NDArray[np.float64]


def pack_g(G: CArray) -> FArray:
    """``g = [Re vec(G); Im vec(G)]`` (eq. 16), shape (2 M U,)."""
    v = np.asarray(G).T.ravel()
    return np.concatenate([v.real, v.imag])


def unpack_g(g: FArray, M: int, U: int) -> CArray:
    """Inverse of :func:`pack_g`: (2 M U,) -> (M, U) complex; also works on (..., 2MU)."""
    g = np.asarray(g, dtype=float)
    n = M * U
    v = g[..., :n] + 1j * g[..., n:]
    return np.swapaxes(v.reshape(*g.shape[:-1], U, M), -1, -2)


@dataclass(frozen=True)
class LinkTerms:
    """Per-link values of the concentrated log-likelihood and its gradient.

    Attributes
    ----------
    value : (L,) log-likelihoods.
    d_rho : (L,) dL/drho (per metre of round-trip range).
    d_phi : (L,) dL/dphi (zero for single-port links).
    d_G : (L, M, U) complex ``dL/dRe G + j dL/dIm G`` (None for single-port links).
    c, y, a : (L,), (L, M), (L, M) intermediate ``a^H y``, ``y`` and ``a`` (for the Fisher).
    """

    value: FArray
    d_rho: FArray
    d_phi: FArray
    d_G: CArray | None
    c: CArray
    y: CArray
    a: CArray


def link_loglik(
    X: CArray,
    rho: FArray,
    noise_var: FArray,
    k: float,
    S: float,
    *,
    phi: FArray | None = None,
    G: CArray | None = None,
    want_grad: bool = True,
    expansion: DelayExpansion | None = None,
) -> LinkTerms:
    """Batched eq. 18 / 19 and analytic gradients for L links with M ports each.

    Parameters
    ----------
    X : (L, M, N) complex, ``R * conj(s)`` per link (precomputed once per snapshot).
    rho : (L,) round-trip ranges ``c tau / 2`` in metres.
    noise_var : (L,) noise variances.
    k : wavenumber from :func:`range_wavenumber`; S : ``|s|^2``.
    phi : (L,) DoAs in the body frame and G : (L, M, U) sampling matrices (multi-port), or
        both None (single-port, eq. 19).
    expansion : optional :class:`DelayExpansion` of the same X (fast path, same values).

    Returns
    -------
    LinkTerms
    """
    L_, M, N = X.shape
    n = np.arange(N)
    fast = expansion.evaluate(rho) if expansion is not None else None
    if fast is not None:
        y, yd_fast = fast
    else:
        E = np.exp(1j * k * np.asarray(rho, dtype=float)[:, None] * n)  # (L, N)
        y = np.einsum("lmn,ln->lm", X, E)
    sig = np.asarray(noise_var, dtype=float)
    if G is None:
        c = y[:, 0]
        A = np.ones(L_)
        a = np.ones((L_, 1), dtype=complex)
    else:
        U = G.shape[2]
        b = fourier_basis(np.asarray(phi, dtype=float), U)  # (L, U)
        a = np.einsum("lmu,lu->lm", G, b)
        c = np.einsum("lm,lm->l", a.conj(), y)
        A = np.sum(np.abs(a) ** 2, axis=1)
    c2 = np.abs(c) ** 2
    den = sig * A * S
    value = c2 / den
    d_phi = np.zeros(L_)
    d_G = None
    if want_grad:
        yd = yd_fast if fast is not None else np.einsum("lmn,ln->lm", X, E * (1j * k * n))
        cd = np.einsum("lm,lm->l", a.conj(), yd)
        d_rho = 2.0 * np.real(c.conj() * cd) / den
        if G is not None:
            bd = 1j * basis_orders(G.shape[2]) * b
            ad = np.einsum("lmu,lu->lm", G, bd)
            dc_phi = np.einsum("lm,lm->l", ad.conj(), y)
            dA_phi = 2.0 * np.real(np.einsum("lm,lm->l", a.conj(), ad))
            d_phi = (2.0 * np.real(c.conj() * dc_phi) * A - c2 * dA_phi) / (sig * A**2 * S)
            # complex gradient (Re + j Im) of |c|^2 is 2 c^* y b^H, of |a|^2 is 2 a b^H
            num = 2.0 * (c.conj()[:, None, None] * y[:, :, None]) * A[:, None, None]
            num = num - 2.0 * c2[:, None, None] * a[:, :, None]
            d_G = num * b.conj()[:, None, :] / (sig * A**2 * S)[:, None, None]
    else:
        d_rho = np.zeros(L_)
    return LinkTerms(value=value, d_rho=d_rho, d_phi=d_phi, d_G=d_G, c=c, y=y, a=a)


def _fisher_common(terms: LinkTerms, noise_var: FArray, k: float,
                   probe_power: FArray) -> tuple[float, complex, float, FArray, FArray]:
    """Probe moments ``S, S', S''``, ``A = |a|^2`` (L,) and ``2 |alpha|^2 / sigma^2`` (L,)."""
    sig = np.asarray(noise_var, dtype=float)
    p = np.asarray(probe_power, dtype=float)
    n = np.arange(p.size)
    S = float(p.sum())
    Sd = -1j * k * float(np.sum(p * n))
    Sdd = k * k * float(np.sum(p * n * n))
    A = np.sum(np.abs(terms.a) ** 2, axis=1)
    alpha2 = np.abs(terms.c) ** 2 / (A * S) ** 2
    return S, Sd, Sdd, A, 2.0 * alpha2 / sig


@dataclass(frozen=True)
class FisherBlocks:
    """Per-link Fisher information of ``(rho, phi, g)`` in factored blocks (see :func:`fisher_blocks`).

    The dense per-link Fisher matrix (order ``[rho, phi, g]``, ``g`` packed as in
    eq. 16 with P_g = 2 M U entries) has the structure

        F_rr = rho_rho,   F_rp = F_rg = 0,   F_pp = phi_phi,   F_pg = phi_g,
        F_gg = g_weight (Kron(bb) - h h^T),  Kron(bb) = [[Re bb (x) I_M, -Im bb (x) I_M],
                                                         [Im bb (x) I_M,  Re bb (x) I_M]]

    so that sums over the links of one receiver cost O(L (U^2 + P_g)) plus one (P_g, 2L) x
    (2L, P_g) product instead of L dense (P_g, P_g) blocks.

    Attributes
    ----------
    rho_rho : (L,) information of the round-trip range, 1/m^2.
    phi_phi : (L,) information of the DoA, 1/rad^2 (zeros for single-port links).
    phi_g : (L, P_g) DoA / sampling-matrix cross information, or None (single-port).
    g_weight : (L,) ``2 |alpha|^2 |s|^2 / sigma^2``, or None.
    g_bb : (L, U, U) complex ``conj(b) b^T`` with ``b = b(phi)`` the Fourier basis, or None.
    g_h : (L, P_g, 2) real low-rank factor ``[Re, Im]`` of ``B^H a / |a|`` in packed order, or None.
    M : ports per link (1 for single-port links).
    """

    rho_rho: FArray
    phi_phi: FArray
    phi_g: FArray | None
    g_weight: FArray | None
    g_bb: CArray | None
    g_h: FArray | None
    M: int

    def gg_sum(self, links: NDArray[np.int64] | slice | None = None) -> FArray:
        """Sum of the (P_g, P_g) sampling-matrix blocks ``F_gg`` over ``links`` (default: all)."""
        assert self.g_weight is not None and self.g_bb is not None and self.g_h is not None
        sel = slice(None) if links is None else links
        w = self.g_weight[sel]
        bb = np.einsum("l,luv->uv", w, self.g_bb[sel])
        eye = np.eye(self.M)
        Kr = np.kron(bb.real, eye)
        Ki = np.kron(bb.imag, eye)
        out = np.block([[Kr, -Ki], [Ki, Kr]])
        h = self.g_h[sel] * np.sqrt(w)[:, None, None]  # (L, P_g, 2)
        hf = np.swapaxes(h, 0, 1).reshape(h.shape[1], -1)
        out -= hf @ hf.T
        return out

    def dense(self) -> FArray:
        """The dense per-link matrices: (L, 1, 1) or (L, P_g + 2, P_g + 2)."""
        L_ = self.rho_rho.size
        if self.phi_g is None:
            return self.rho_rho[:, None, None].copy()
        Pg = self.phi_g.shape[1]
        F = np.zeros((L_, Pg + 2, Pg + 2))
        F[:, 0, 0] = self.rho_rho
        F[:, 1, 1] = self.phi_phi
        F[:, 1, 2:] = F[:, 2:, 1] = self.phi_g
        for l in range(L_):
            F[l, 2:, 2:] = self.gg_sum(np.array([l]))
        return F


def fisher_blocks(
    terms: LinkTerms,
    noise_var: FArray,
    k: float,
    probe_power: FArray,
    *,
    phi: FArray | None = None,
    G: CArray | None = None,
) -> FisherBlocks:
    """Factored per-link Fisher information of ``(rho, phi, g)``.

    Fisher information of the concentrated model of eqs. 18-19 (the Laplace covariance of
    eq. 22 and the whitening of the MAP update), ``F = (2 |alpha|^2 / sigma^2) Re(D^H P^perp D)``
    with ``D = d e / d theta``, returned as the blocks of :class:`FisherBlocks` instead of
    L dense (P, P) matrices.

    Parameters
    ----------
    terms : :func:`link_loglik` output at the point (L links).
    noise_var : (L,) noise variance per bin and port; k : rad / m / bin
        (:func:`range_wavenumber`); probe_power : (N,) ``|s(n)|^2``.
    phi : (L,) DoAs (rad) and G : (L, M, U) sampling matrices for multi-port links, or None.

    Returns
    -------
    FisherBlocks (units: 1/m^2 for rho, 1/rad^2 for phi, 1/(entry of G)^2 for g).
    """
    S, Sd, Sdd, A, scale = _fisher_common(terms, noise_var, k, probe_power)
    a = terms.a
    rr = scale * A * (Sdd - abs(Sd) ** 2 / S)
    if G is None:
        return FisherBlocks(rr, np.zeros(rr.size), None, None, None, None, 1)
    L_, M, U = G.shape
    MU = M * U
    b = fourier_basis(np.asarray(phi, dtype=float), U)  # (L, U)
    ad = np.einsum("lmu,lu->lm", G, 1j * basis_orders(U) * b)
    e0 = (b[:, :, None] * ad.conj()[:, None, :]).reshape(L_, MU)  # a'^H B
    ha = (b.conj()[:, :, None] * a[:, None, :]).reshape(L_, MU)  # B^H a
    h0 = np.einsum("lm,lm->l", ad.conj(), a)
    w = scale * S
    sA = np.sqrt(A)
    hg = np.empty((L_, 2 * MU, 2))
    hg[:, :MU, 0] = ha.real
    hg[:, MU:, 0] = ha.imag
    hg[:, :MU, 1] = ha.imag
    hg[:, MU:, 1] = -ha.real
    hg /= sA[:, None, None]
    h0r = h0.real / sA
    h0i = h0.imag / sA
    pp = w * (np.sum(np.abs(ad) ** 2, axis=1) - (h0r * h0r + h0i * h0i))
    pg = np.concatenate([e0.real, -e0.imag], axis=1) - (h0r[:, None] * hg[:, :, 0] + h0i[:, None] * hg[:, :, 1])
    pg *= w[:, None]
    bb = b.conj()[:, :, None] * b[:, None, :]
    return FisherBlocks(rr, pp, pg, w, bb, hg, int(M))


@dataclass(frozen=True)
class DelayExpansion:
    """Exact-to-rounding series of ``y(rho) = sum_n X[:, n] e^{j k rho n}`` around ``rho0``.

    With ``c = (N-1)/2``, ``t_n = (n - c) / (N/2)`` and ``x = k (rho - rho0) N / 2``:
    ``y(rho) = e^{j k (rho-rho0) c} sum_q (j x)^q / q! m_q``, ``m_q = sum_n X_n e^{j k rho0 n} t_n^q``.
    The moments cost one (L M, N) x (N, Q) product per snapshot; every later likelihood
    evaluation then costs O(L M Q) instead of O(L M N). Valid (error < 1e-12 relative) for
    ``|x| <= radius``; outside, :func:`link_loglik` falls back to the direct sum.
    """

    rho0: FArray
    moments: CArray  # (L, M, Q + 2)
    k: float
    N: int
    radius: float = 2.0

    def evaluate(self, rho: FArray) -> tuple[CArray, CArray] | None:
        """``(y, dy/drho)`` (L, M) each, or None when some ``rho`` is outside the radius."""
        c = (self.N - 1) / 2.0
        half = self.N / 2.0
        dr = np.asarray(rho, dtype=float) - self.rho0
        x = self.k * dr * half
        if np.any(np.abs(x) > self.radius):
            return None
        Q = self.moments.shape[2] - 1
        q = np.arange(Q)
        coef = (1j * x[:, None]) ** q / _FACT[:Q]  # (L, Q)
        rot = np.exp(1j * self.k * dr * c)[:, None]
        y = rot * np.einsum("lmq,lq->lm", self.moments[:, :, :Q], coef)
        # d/drho e^{j k rho n} = j k n e^{...} and n = c + half * t_n
        y1 = rot * np.einsum("lmq,lq->lm", self.moments[:, :, 1 : Q + 1], coef)
        yd = 1j * self.k * (c * y + half * y1)
        return y, yd


_FACT = np.array([float(np.prod(np.arange(1, i + 1))) for i in range(40)])


@functools.lru_cache(maxsize=8)
def _powers(N: int, Q: int) -> CArray:
    """(N, Q) matrix ``t_n^q`` of :class:`DelayExpansion` (same for every snapshot)."""
    t = (np.arange(N) - (N - 1) / 2.0) / (N / 2.0)
    # complex so that the moment product is one zgemm without casting a copy per snapshot
    P = np.asarray(t[:, None] ** np.arange(Q)[None, :], dtype=complex)
    P.flags.writeable = False
    return P


def delay_expansion(
    X: CArray, rho0: FArray, k: float, *, order: int = 24, work: tuple[CArray, CArray] | None = None
) -> DelayExpansion:
    """Moments of :class:`DelayExpansion` for X (L, M, N) around ``rho0`` (L,).

    Parameters
    ----------
    X : (L, M, N) complex ``R * conj(s)``; rho0 : (L,) expansion points, metres (round trip);
    k : rad / m / bin (eq. 4 as a range); order : series order Q.
    work : optional C-contiguous work arrays ``(phasors (L, N), rotated X (L, M, N))``, complex,
        reused across calls (same values).
    """
    L_, M, N = X.shape
    PT = _powers(N, order + 2)  # (N, Q+2)
    th = k * np.asarray(rho0, dtype=float)
    if work is not None and work[0].shape == (L_, N) and work[1].shape == X.shape:
        ph = phasors(th, N, out=work[0])
        Xr = np.multiply(X, ph[:, None, :], out=work[1])
    else:
        Xr = X * phasors(th, N)[:, None, :]
    mom = (Xr.reshape(L_ * M, N) @ PT).reshape(L_, M, order + 2)
    return DelayExpansion(np.asarray(rho0, dtype=float).copy(), mom, float(k), int(N))
