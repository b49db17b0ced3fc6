"""Antenna responses by wavefield modelling and manifold separation (paper 002, eqs. 5-9).

An M-port antenna's response to a plane wave from azimuth ``phi`` (radians, body frame) is
``a(phi) = G b(phi)`` (eq. 7) with the sampling matrix ``G`` (M, U) and the Fourier basis
``b_u(phi) = exp(j u phi) / sqrt(2 pi)``, ``u = floor(-(U-1)/2) .. floor((U-1)/2)`` (eq. 8).

Synthetic antennas
------------------
* :func:`dipole_response` -- single-port half-wave dipole, ``a = 10**(2.15/20)`` (after eq. 6).
* :func:`multimode_antenna` -- a 4-port multi-mode antenna (MMA) with four distinct port
  patterns in three versions that differ the way section II describes: ``"em"`` (nominal EM
  simulation), ``"chamber"`` (EM + manufacturing deviations, measured alone in a chamber) and
  ``"true"`` (chamber + the platform's scattering once installed on the rover, which adds
  higher-order spatial harmonics). They are deterministic (fixed internal seeds).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from .._checks import check_choice
from ..errors import InputError

__all__ = [
    "basis_orders",
    "fourier_basis",
    "sampling_matrix",
    "AntennaResponse",
    "dipole_response",
    "multimode_antenna",
    "DIPOLE_GAIN",
]

CArray = NDArray[np.complex128]
FArray = NDArray[np.float64]

#: Amplitude of a half-wave dipole's isotropic-in-azimuth response, 2.15 dBi (after eq. 6).
DIPOLE_GAIN = 10.0 ** (2.15 / 20.0)


def basis_orders(U: int) -> NDArray[np.int64]:
    """Integer orders ``u`` of the Fourier basis of eq. 8, shape (U,).

    ``u = floor(-(U-1)/2), ..., 0, ..., floor((U-1)/2)``; for odd U symmetric around 0.
    """
    if int(U) < 1:
        raise InputError(f"U (number of basis functions) must be >= 1, got {U}")
    lo = int(np.floor(-(U - 1) / 2))
    return np.arange(lo, lo + int(U), dtype=np.int64)


def fourier_basis(phi: float | FArray, U: int) -> CArray:
    """Fourier basis vectors ``b(phi)`` of eq. 8.

    Parameters
    ----------
    phi : float or (K,) array
        Azimuths in radians.
    U : int
        Number of basis functions.

    Returns
    -------
    (U,) or (K, U) complex array, ``exp(j u phi) / sqrt(2 pi)``.
    """
    u = basis_orders(U)
    ph = np.asarray(phi, dtype=float)
    return np.exp(1j * ph[..., None] * u) / np.sqrt(2.0 * np.pi)


def sampling_matrix(samples: CArray, phis: FArray, U: int) -> CArray:
    """Sampling matrix from spatial samples, ``G0 = E B^H (B B^H)^-1`` (eq. 9).

    Parameters
    ----------
    samples : (Q, M) complex
        Response of each of the M ports measured (or simulated) at the Q azimuths.
    phis : (Q,) float
        Sample azimuths in radians.
    U : int
        Basis order. Nyquist condition: ``Q >= U`` distinct azimuths.

    Returns
    -------
    (M, U) complex sampling matrix G0 (least-squares fit when Q > U).
    """
    E = np.asarray(samples, dtype=complex)
    ph = np.asarray(phis, dtype=float).ravel()
    if E.ndim == 1:
        E = E[:, None]
    if E.ndim != 2 or E.shape[0] != ph.size:
        raise InputError(f"samples must be (Q, M) with Q = len(phis) = {ph.size}; got {E.shape}")
    if not np.all(np.isfinite(E)) or not np.all(np.isfinite(ph)):
        raise InputError("samples and phis must be finite")
    nq = np.unique(np.round(np.mod(ph, 2 * np.pi), 12)).size
    if nq < U:
        raise InputError(
            f"{nq} distinct sample azimuths cannot determine U = {U} basis coefficients "
            "(Nyquist: sample at least U azimuths over the circle)"
        )
    B = fourier_basis(ph, U).T  # (U, Q)
    # E^T is (M, Q); solve (B B^H) X = B E for X = G0^T rather than invert explicitly.
    gram = B @ B.conj().T
    rhs = B.conj() @ E  # (U, M) = conj(B) E  -> G0 = (rhs^T) (B B^H)^-1 transposed appropriately
    G0 = np.linalg.solve(gram.T, rhs).T
    return np.asarray(G0, dtype=complex)


@dataclass(frozen=True)
class AntennaResponse:
    """An antenna described by its sampling matrix ``G`` (M, U) (eq. 7).

    Attributes
    ----------
    G : (M, U) complex
        Sampling matrix.
    name : str
        Free label ("dipole", "mma-true", ...).
    """

    G: CArray
    name: str = "antenna"

    @property
    def ports(self) -> int:
        return int(self.G.shape[0])

    @property
    def U(self) -> int:
        return int(self.G.shape[1])

    def response(self, phi: float | FArray) -> CArray:
        """``a(phi) = G b(phi)``: (M,) for scalar phi, (K, M) for (K,) phi."""
        return fourier_basis(phi, self.U) @ self.G.T

    def to_dict(self) -> dict[str, object]:
        return {"name": self.name, "G_real": self.G.real, "G_imag": self.G.imag}


def dipole_response(U: int = 13) -> AntennaResponse:
    """Single-port half-wave dipole, ``a(phi) = 10^(2.15/20)`` for every azimuth.

    Only the ``u = 0`` coefficient is non-zero: ``G[0, u=0] = sqrt(2 pi) * 10^(2.15/20)``.
    """
    G = np.zeros((1, U), dtype=complex)
    G[0, int(np.flatnonzero(basis_orders(U) == 0)[0])] = np.sqrt(2 * np.pi) * DIPOLE_GAIN
    return AntennaResponse(G, "dipole")


def _mma_nominal(U: int) -> CArray:
    """Nominal 4-port MMA: four characteristic modes with distinct low-order patterns."""
    u = basis_orders(U)
    G = np.zeros((4, U), dtype=complex)

    def put(m: int, order: int, value: complex) -> None:
        if order in u:
            G[m, int(np.flatnonzero(u == order)[0])] += value

    # mode 1 ~ cos(phi) (x-directed), mode 2 ~ sin(phi) (y-directed) with a small omni leak,
    # mode 3 ~ cos(2 phi) quadrupole-like, mode 4 ~ omni-directional monopole-like mode.
    put(0, 1, 1.0)
    put(0, -1, 1.0)
    put(0, 0, 0.25j)
    put(1, 1, -1j)
    put(1, -1, 1j)
    put(1, 0, 0.2)
    put(2, 2, 0.9 * np.exp(0.3j))
    put(2, -2, 0.9 * np.exp(0.3j))
    put(2, 0, 0.45)
    put(2, 1, 0.2j)
    put(3, 0, 1.2)
    put(3, 3, 0.25 * np.exp(1.0j))
    put(3, -3, 0.25 * np.exp(-0.4j))
    put(3, 1, 0.2)
    # Mild fixed phase-pattern structure so that ports are not trivially real-valued.
    rng = np.random.default_rng(2002)
    low = np.abs(u) <= 3
    G[:, low] += 0.06 * (rng.standard_normal((4, int(low.sum()))) + 1j * rng.standard_normal((4, int(low.sum()))))
    # Mean port gain 0 dBi: sum_u |G_mu|^2 = 2 pi.
    G *= np.sqrt(2 * np.pi / np.sum(np.abs(G) ** 2, axis=1, keepdims=True))
    return G


def multimode_antenna(
    version: str = "true",
    U: int = 13,
    *,
    manufacturing: float = 0.12,
    platform: float = 0.22,
) -> AntennaResponse:
    """Synthetic 4-port multi-mode antenna in one of three versions.

    Parameters
    ----------
    version : {"em", "chamber", "true"}
        ``"em"``: nominal EM simulation. ``"chamber"``: EM plus manufacturing deviations
        (relative size ``manufacturing``, orders ``|u| <= 3``). ``"true"``: chamber plus the
        platform's influence once mounted (relative size ``platform``, all orders up to
        ``|u| <= (U-1)/2`` with weight decaying in ``|u|``), i.e. what the rover really has.
    U : int
        Number of basis functions (13 in the paper).
    manufacturing, platform : float
        Relative RMS sizes of the two deviations (fractions of the port's RMS coefficient).

    Returns
    -------
    AntennaResponse with ``G`` of shape (4, U).
    """
    check_choice(version, "version", ("em", "chamber", "true"))
    G = _mma_nominal(U)
    u = basis_orders(U)
    rms = np.sqrt(np.mean(np.abs(G) ** 2, axis=1, keepdims=True) * U / 7.0)
    if version in ("chamber", "true"):
        rng = np.random.default_rng(77)
        w = (np.abs(u) <= 3).astype(float)
        dev = (rng.standard_normal(G.shape) + 1j * rng.standard_normal(G.shape)) / np.sqrt(2)
        G = G + manufacturing * rms * w * dev
    if version == "true":
        rng = np.random.default_rng(4242)
        w = 1.0 / (1.0 + 0.25 * np.abs(u))
        dev = (rng.standard_normal(G.shape) + 1j * rng.standard_normal(G.shape)) / np.sqrt(2)
        G = G + platform * rms * w * dev
    return AntennaResponse(np.asarray(G, dtype=complex), f"mma-{version}")
