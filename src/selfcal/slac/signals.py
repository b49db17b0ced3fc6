"""OFDM probe, delayed spectrum and received snapshots (paper 002, eqs. 3-4).

Conventions: a received snapshot is an (M, N) complex array ``R`` (ports x DFT bins),
``R[:, n] = a(phi) s(n, tau) alpha e^{j varphi} + w(n)`` (eq. 3) with
``s(n, tau) = s(n) exp(-j 2 pi tau B n / N)`` for the zero-based bin index ``n`` (eq. 4 with
``n - 1``). Delays are handled as *ranges* ``rho = c tau / 2`` (metres, round trip) by the
filter so that every state is in metres or radians.
"""

from __future__ import annotations

import threading
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .._checks import as_rng, check_positive
from ..errors import InputError

__all__ = [
    "SPEED_OF_LIGHT",
    "ofdm_probe",
    "delayed_spectrum",
    "range_wavenumber",
    "snapshot",
    "delay_grid_search",
    "estimate_noise_variance",
    "batch_delay_search",
    "phasors",
    "DelaySearchWorkspace",
]

SPEED_OF_LIGHT = 299_792_458.0
CArray = NDArray[np.complex128]


def ofdm_probe(n_subcarriers: int, rng: np.random.Generator | int | None = 0) -> CArray:
    """Unit-modulus QPSK OFDM probe spectrum ``s(n)``, shape (N,).

    Parameters
    ----------
    n_subcarriers : int
        N, the FFT length (1024 in the paper).
    rng : Generator | int | None
        Seed of the pseudo-random QPSK symbols (known to every receiver).
    """
    N = int(n_subcarriers)
    if N < 2:
        raise InputError(f"n_subcarriers must be >= 2, got {n_subcarriers}")
    g = as_rng(rng)
    return np.exp(1j * (np.pi / 4 + np.pi / 2 * g.integers(0, 4, N)))


def range_wavenumber(bandwidth: float, n_subcarriers: int) -> float:
    """``k`` such that ``s(n, tau) = s(n) exp(-j k rho n)`` with the round-trip range ``rho = c tau / 2``.

    ``k = 2 pi (2 / c) B / N`` in rad per metre per bin (from eq. 4 with ``tau = 2 rho / c``).
    """
    return 2.0 * np.pi * 2.0 / SPEED_OF_LIGHT * float(bandwidth) / int(n_subcarriers)


def delayed_spectrum(probe: CArray, tau: float | NDArray[np.float64], bandwidth: float) -> CArray:
    """Delayed probe spectrum of eq. 4, ``s(n) exp(-j 2 pi tau B n / N)``.

    Parameters
    ----------
    probe : (N,) complex
    tau : float or (L,) array, seconds
    bandwidth : float, Hz (the sample rate B)

    Returns
    -------
    (N,) or (L, N) complex.
    """
    s = np.asarray(probe, dtype=complex)
    N = s.size
    n = np.arange(N)
    t = np.asarray(tau, dtype=float)
    return s * np.exp(-2j * np.pi * t[..., None] * float(bandwidth) * n / N)


def snapshot(
    response: CArray,
    probe: CArray,
    tau: float,
    bandwidth: float,
    *,
    amplitude: float,
    phase: float,
    noise_var: float,
    rng: np.random.Generator | int | None = None,
) -> CArray:
    """One received snapshot ``R`` (M, N) of eq. 3.

    ``response`` is ``a(phi)`` (M,), the amplitude ``alpha`` and phase ``varphi`` are the
    complex path gain, ``noise_var`` the per-bin, per-port variance of the circular Gaussian
    noise. The per-bin SNR is ``alpha^2 |a_m|^2 / noise_var``.
    """
    a = np.atleast_1d(np.asarray(response, dtype=complex))
    g = as_rng(rng)
    s_tau = delayed_spectrum(probe, tau, bandwidth)
    M, N = a.size, s_tau.size
    sd = np.sqrt(float(noise_var) / 2.0)
    w = sd * (g.standard_normal((M, N)) + 1j * g.standard_normal((M, N)))
    return np.outer(a, s_tau) * (amplitude * np.exp(1j * phase)) + w


def delay_grid_search(
    R: CArray, probe: CArray, bandwidth: float, *, oversample: int = 8
) -> tuple[float, CArray]:
    """Antenna-agnostic ML delay on a zero-padded FFT grid, refined by parabolic interpolation.

    Maximises ``sum_m |y_m(tau)|^2`` with ``y(tau) = R s^*(tau)`` (the unstructured-response
    likelihood), evaluated for every grid delay with one inverse FFT per port.

    Returns
    -------
    tau : float, seconds, in ``[-N / (2B), N / (2B))``
    y : (M,) complex, ``R s^*(tau)`` at the refined delay.
    """
    R2 = np.atleast_2d(np.asarray(R, dtype=complex))
    s = np.asarray(probe, dtype=complex)
    N = s.size
    P = int(oversample) * N
    X = R2 * s.conj()
    # y(tau_k) = sum_n X_n exp(+j 2 pi k n / P) with tau_k = k N / (B P)
    Y = np.fft.ifft(X, n=P, axis=1) * P
    power = np.sum(np.abs(Y) ** 2, axis=0)
    k = int(np.argmax(power))
    pm, p0, pp = power[(k - 1) % P], power[k], power[(k + 1) % P]
    den = pm - 2 * p0 + pp
    frac = 0.5 * (pm - pp) / den if den < 0 else 0.0
    tau = ((k + frac) % P) * N / (float(bandwidth) * P)
    period = N / float(bandwidth)
    tau = (tau + period / 2) % period - period / 2  # symmetric: small negative delays stay small
    n = np.arange(N)
    y = X @ np.exp(2j * np.pi * tau * float(bandwidth) * n / N)
    return float(tau), y


def estimate_noise_variance(R: CArray, probe: CArray, bandwidth: float) -> float:
    """Noise variance per bin and port estimated from the known transmitted signal.

    Fits ``R ~ c s(tau)^T`` with a free complex vector ``c`` (M,) and the ML delay
    (:func:`delay_grid_search`), and divides the residual power by its ``M (N - 1)`` degrees of
    freedom. Independent of any antenna model, so it is the same for every filter mode.
    """
    R2 = np.atleast_2d(np.asarray(R, dtype=complex))
    check_positive(bandwidth, "bandwidth", allow_none=False)
    M, N = R2.shape
    _, y = delay_grid_search(R2, probe, bandwidth)
    S = float(np.sum(np.abs(probe) ** 2))
    resid = float(np.sum(np.abs(R2) ** 2) - np.sum(np.abs(y) ** 2) / S)
    return max(resid, 1e-300) / (M * (N - 1))


def phasors(theta: NDArray[np.float64], N: int, *, out: CArray | None = None) -> CArray:
    """``exp(1j * theta[:, None] * n)`` for ``n = 0 .. N-1``, shape (L, N).

    Split ``n = B h + l`` with ``B ~ sqrt(N)``: two (L, ~sqrt N) exponentials and one product
    replace L N complex exponentials (the dominant per-step cost of the delay searches); the
    result equals the direct one to a few ulp. Used for the delay phase ``e^{j k rho n}`` of
    eq. 4 (``theta = k rho``, radians per bin).

    Parameters
    ----------
    theta : (L,) phase increments per bin, radians.
    N : number of bins.
    out : optional C-contiguous (L, N) complex array that receives the result (no allocation
        of the (L, N) product; same values).
    """
    th = np.asarray(theta, dtype=float).reshape(-1)
    B = max(1, int(np.ceil(np.sqrt(N))))
    H = -(-N // B)
    lo = np.exp(1j * th[:, None] * np.arange(B))
    hi = np.exp(1j * th[:, None] * (B * np.arange(H)))
    if out is not None and H * B == N and out.shape == (th.size, N) and out.flags.c_contiguous:
        np.multiply(hi[:, :, None], lo[:, None, :], out=out.reshape(th.size, H, B))
        return out
    res = (hi[:, :, None] * lo[:, None, :]).reshape(th.size, H * B)[:, :N]
    if out is not None:
        out[...] = res
        return out
    return res


class DelaySearchWorkspace:
    """Work arrays of :func:`batch_delay_search`, reused across calls with the same layout.

    The search touches a few (rows, 2N) arrays per call (about 1.4 MB each for the paper-002
    replica); allocating them afresh costs page faults that exceed the FFT itself. One
    workspace holds them for a fixed ``(ports per link, N, oversample, bandwidth)`` layout and
    is rebuilt when the layout changes. Not thread-safe: use one workspace per thread (the
    default workspaces of :func:`batch_delay_search` are thread-local).

    Attributes (rows = total number of ports ``sum_l M_l``, P = oversample N)
    ----------
    R, X : (rows, N) complex stacked snapshots and ``R * conj(s)``.
    Y : (rows, P) complex zero-padded FFT buffer; pw, tmp : (rows, P) float; power : (L, P).
    ph : (rows, N) complex phasors / products; absR : (rows, N) float.
    W3 : (N, 3) complex ``[1, w, w^2]`` with ``w = j 2 pi B n / N`` (d/dtau per bin).
    """

    def __init__(self, sizes: NDArray[np.int64], N: int, oversample: int, bandwidth: float) -> None:
        self.sizes = np.asarray(sizes, dtype=np.int64).copy()
        self.key = (tuple(int(m) for m in self.sizes), int(N), int(oversample), float(bandwidth))
        rows = int(self.sizes.sum())
        P = int(oversample) * int(N)
        self.starts = np.concatenate([[0], np.cumsum(self.sizes)[:-1]]).astype(np.int64)
        self.R = np.empty((rows, N), dtype=complex)
        self.X = np.empty((rows, N), dtype=complex)
        self.Y = np.zeros((rows, P), dtype=complex)
        self.pw = np.empty((rows, P))
        self.tmp = np.empty((rows, P))
        self.power = np.empty((self.sizes.size, P))
        self.ph = np.empty((rows, N), dtype=complex)
        self.absR = np.empty((rows, N))
        n = np.arange(N)
        w = 2j * np.pi * float(bandwidth) * n / N
        self.W3 = np.stack([np.ones(N), w, w * w], axis=1)
        for a in (self.R, self.X, self.Y, self.pw, self.tmp, self.power, self.ph, self.absR):
            a.fill(0)  # touch every page once, here


_WORK = threading.local()


def _workspace(sizes: NDArray[np.int64], N: int, oversample: int, bandwidth: float) -> DelaySearchWorkspace:
    """Thread-local :class:`DelaySearchWorkspace` for this layout (the last few are kept)."""
    key = (tuple(int(m) for m in sizes), int(N), int(oversample), float(bandwidth))
    cache: dict[tuple[Any, ...], DelaySearchWorkspace] | None = getattr(_WORK, "cache", None)
    if cache is None:
        cache = _WORK.cache = {}
    ws = cache.get(key)
    if ws is None:
        if len(cache) >= 4:
            cache.pop(next(iter(cache)))
        ws = cache[key] = DelaySearchWorkspace(sizes, N, oversample, bandwidth)
    return ws


def batch_delay_search(
    snapshots: list[CArray], probe: CArray, bandwidth: float, *, oversample: int = 2, newton: int = 1,
    workspace: DelaySearchWorkspace | None = None,
) -> tuple[NDArray[np.float64], list[CArray], NDArray[np.float64]]:
    """:func:`delay_grid_search` and :func:`estimate_noise_variance` for many links at once.

    The antenna-agnostic ML delay of each link maximises ``sum_m |y_m(tau)|^2`` with
    ``y(tau) = R s^*(tau)`` (eqs. 3-4, the concentrated likelihood of eq. 18 with an
    unstructured response). All ports of all links share one batched zero-padded FFT
    (``oversample`` x N points); the grid maximum is refined by parabolic interpolation and
    ``newton`` exact Newton steps. Work arrays come from ``workspace`` (default: a
    thread-local one per layout, reused across calls; the values do not depend on it).

    Parameters
    ----------
    snapshots : L arrays (M_l, N) complex.
    probe : (N,) complex known spectrum s(n); bandwidth : Hz.
    workspace : optional :class:`DelaySearchWorkspace` for this layout (rebuilt if it does not
        match the snapshots).

    Returns
    -------
    tau : (L,) antenna-agnostic ML delays (s); y : L arrays ``R s^*(tau)`` (M_l,);
    noise_var : (L,) residual noise variance per bin and port.
    """
    s = np.asarray(probe, dtype=complex)
    N = s.size
    P = int(oversample) * N
    rows = [np.atleast_2d(r) for r in snapshots]
    sizes = np.array([r.shape[0] for r in rows], dtype=np.int64)
    ws = workspace
    if ws is None or ws.key != (tuple(int(m) for m in sizes), N, int(oversample), float(bandwidth)):
        ws = _workspace(sizes, N, int(oversample), float(bandwidth))
    starts = ws.starts
    Rall = ws.R
    if len(rows) > 1:
        np.concatenate(rows, axis=0, out=Rall)
    else:
        Rall[...] = rows[0]
    X = np.multiply(Rall, s.conj(), out=ws.X)
    Yb = ws.Y
    Yb[:, :N] = X
    Yb[:, N:] = 0.0
    # unscaled inverse FFT in place: y(tau_k) = sum_n X_n exp(+j 2 pi k n / P)
    Y = np.fft.ifft(Yb, axis=1, norm="forward", out=Yb)
    pw = np.multiply(Y.real, Y.real, out=ws.pw)
    pw = np.add(pw, np.multiply(Y.imag, Y.imag, out=ws.tmp), out=pw)
    power = np.add.reduceat(pw, starts, axis=0, out=ws.power)  # (L, P)
    k = np.argmax(power, axis=1)
    Lr = np.arange(power.shape[0])
    pm, p0, pp = power[Lr, (k - 1) % P], power[Lr, k], power[Lr, (k + 1) % P]
    den = pm - 2 * p0 + pp
    frac = np.where(den < 0, 0.5 * (pm - pp) / np.where(den < 0, den, -1.0), 0.0)
    tau = ((k + frac) % P) * N / (float(bandwidth) * P)
    wb = 2 * np.pi * float(bandwidth) / N
    W3 = ws.W3  # y, dy/dtau, d2y/dtau2 in one product
    for _ in range(newton):
        # Newton on P(tau) = sum_m |y_m|^2 with exact first and second derivatives
        ph = phasors(np.repeat(tau * wb, sizes), N, out=ws.ph)
        Y3 = np.multiply(X, ph, out=ph) @ W3
        y0, y1, y2 = Y3[:, 0], Y3[:, 1], Y3[:, 2]
        d1 = np.add.reduceat(2 * np.real(y0.conj() * y1), starts)
        d2 = np.add.reduceat(2 * (np.abs(y1) ** 2 + np.real(y0.conj() * y2)), starts)
        step = np.where(d2 < 0, -d1 / np.where(d2 < 0, d2, -1.0), 0.0)
        tau = tau + np.clip(step, -N / (float(bandwidth) * P), N / (float(bandwidth) * P))
    # delays are N/B-periodic: report them in [-N/(2B), N/(2B)) so that a round trip shorter
    # than the biases (nodes passing each other) gives a small negative range, not ~c N / (2B)
    period = N / float(bandwidth)
    tau = (tau + period / 2) % period - period / 2
    yrows = np.einsum("rn,rn->r", X, phasors(np.repeat(tau * wb, sizes), N, out=ws.ph))
    Sp = float(np.sum(np.abs(s) ** 2))
    aR = np.abs(Rall, out=ws.absR)
    tot = np.add.reduceat(np.sum(np.multiply(aR, aR, out=aR), axis=1), starts)
    fit = np.add.reduceat(np.abs(yrows) ** 2, starts) / Sp
    var = np.maximum(tot - fit, 1e-300) / (sizes * (N - 1))
    ys = [yrows[a : a + m] for a, m in zip(starts, sizes, strict=True)]
    return tau, ys, var
