"""Replica of paper 002's rover experiment (section V): 3 anchors, 4 rovers, raw OFDM snapshots.

Rovers (agents, in this order): ``Dias`` (4-port multi-mode antenna, drives all the time),
``Drake`` and ``Vespucci`` (dipoles, start driving at 48 % of the run = 6 of 12.5 min) and
``Magellan`` (dipole, static). Every agent receives every other node's response at each
step (T = 0.1 s). The controls are the true turn rate and velocity plus Gaussian noise of
variance ``sigma^2 T`` (gyroscope / commanded velocity); every node has an unknown ranging
bias; the MMA's installed response differs from its EM and chamber priors
(:func:`selfcal.slac.antenna.multimode_antenna`).

SNR: ``snr_db`` is the *post-integration* SNR (all N bins) at 10 m, decaying as free space,
so a run behaves alike for any number of subcarriers N.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from .._checks import as_rng, check_positive
from ..errors import InputError
from ..geometry import wrap_angle
from ..slac.antenna import dipole_response, fourier_basis, multimode_antenna
from ..slac.motion import motion_step
from ..slac.signals import SPEED_OF_LIGHT, ofdm_probe, snapshot

__all__ = ["AGENT_NAMES", "RoverScenario", "make_rover_scenario"]

AGENT_NAMES = ("Dias", "Drake", "Vespucci", "Magellan")
FArray = NDArray[np.float64]
CArray = NDArray[np.complex128]


@dataclass(frozen=True)
class RoverScenario:
    """A simulated run: geometry, truth, controls and the signal model to draw snapshots.

    Attributes
    ----------
    anchors : (A, 2) positions; names : agent names; ports : (n,) antenna ports.
    G_true, G_em, G_chamber : per agent (M_i, U) sampling matrices (dipoles: same in all three).
    T : step (s); states : (S+1, n, 3) true poses; controls_true / controls : (S, n, 2) true and
    measured ``[v, omega]``; biases : (n + A,) true ranging biases (eq. 1 convention:
    measured range = distance - delta_i - delta_j).
    probe : (N,) OFDM spectrum; bandwidth, carrier : Hz; snr_db : SNR at 10 m after integration.
    rx, tx : (L,) the links observed at every step (node numbering: agents, then anchors).
    """

    anchors: FArray
    names: tuple[str, ...]
    ports: NDArray[np.int64]
    G_true: list[CArray]
    G_em: list[CArray]
    G_chamber: list[CArray]
    T: float
    states: FArray
    controls_true: FArray
    controls: FArray
    biases: FArray
    probe: CArray
    bandwidth: float
    carrier: float
    snr_db: float
    sigma_v: float
    sigma_omega: float
    rx: NDArray[np.int64] = field(repr=False)
    tx: NDArray[np.int64] = field(repr=False)

    @property
    def n_steps(self) -> int:
        return int(self.controls.shape[0])

    @property
    def n_agents(self) -> int:
        return int(self.ports.size)

    def node_positions(self, step: int) -> FArray:
        """(n + A, 2) true positions of all nodes after ``step`` controls (state index)."""
        return np.vstack([self.states[step, :, :2], self.anchors])

    def true_ranges(self, step: int) -> FArray:
        """(L,) true distances of the links at state index ``step``."""
        p = self.node_positions(step)
        return np.linalg.norm(p[self.tx] - p[self.rx], axis=1)

    def true_doas(self, step: int) -> FArray:
        """(L,) true DoA in the receiver's body frame (eq. 2), radians in [-pi, pi)."""
        p = self.node_positions(step)
        dlt = p[self.tx] - p[self.rx]
        phi = np.arctan2(dlt[:, 1], dlt[:, 0]) - self.states[step, self.rx, 2]
        return wrap_angle(phi)

    def snapshots(self, step: int, rng: np.random.Generator | int | None) -> list[CArray]:
        """Received snapshots (eq. 3) of every link at state index ``step`` (1..S), unit noise."""
        g = as_rng(rng)
        d = self.true_ranges(step)
        phi = self.true_doas(step)
        rho = d - self.biases[self.rx] - self.biases[self.tx]
        tau = 2.0 * rho / SPEED_OF_LIGHT
        N = self.probe.size
        amp = 10 ** (self.snr_db / 20) * (10.0 / np.maximum(d, 1.0)) / np.sqrt(N)
        out = []
        for l in range(self.rx.size):
            G = self.G_true[int(self.rx[l])]
            a = G @ fourier_basis(float(phi[l]), G.shape[1])
            out.append(snapshot(a, self.probe, float(tau[l]), self.bandwidth, amplitude=float(amp[l]),
                                phase=float(g.uniform(0, 2 * np.pi)), noise_var=1.0, rng=g))
        return out


def _drive(x0: FArray, steps: int, T: float, start: int, speed: float, rng: np.random.Generator,
           center: FArray, radius: float) -> tuple[FArray, FArray]:
    """Smooth random drive inside a disc: returns (steps+1, 3) states and (steps, 2) controls."""
    states = np.empty((steps + 1, 3))
    ctrl = np.zeros((steps, 2))
    states[0] = x0
    freqs = rng.uniform(0.01, 0.05, 3)
    phases = rng.uniform(0, 2 * np.pi, 3)
    for s in range(steps):
        x = states[s]
        if s >= start:
            t = s * T
            w = 0.12 * np.sum(np.sin(2 * np.pi * freqs * t + phases)) / 1.5
            to_c = center - x[:2]
            dist = np.linalg.norm(to_c)
            if dist > radius:
                err = wrap_angle(np.arctan2(to_c[1], to_c[0]) - x[2])
                w += 0.3 * np.clip(err, -1, 1)
            ctrl[s] = [speed, np.clip(w, -0.4, 0.4)]
        states[s + 1] = motion_step(x, ctrl[s], T)
    return states, ctrl


def make_rover_scenario(
    minutes: float = 12.5,
    *,
    T: float = 0.1,
    n_subcarriers: int = 1024,
    U: int = 13,
    bandwidth: float = 28.2e6,
    carrier: float = 1.68e9,
    snr_db: float = 30.0,
    bias_std: float = 0.3,
    sigma_v: float = 0.015,
    sigma_omega: float = float(np.deg2rad(0.3)),
    rng: np.random.Generator | int | None = 0,
) -> RoverScenario:
    """Build the replica of section V (see module doc).

    Parameters
    ----------
    minutes : run length (12.5 in the paper); the two dipole rovers start at 48 % of it.
    n_subcarriers : N (1024 in the paper; smaller for fast tests).
    U : basis order (13). snr_db : post-integration SNR at 10 m.
    bias_std : standard deviation of the true per-node ranging biases (m).
    sigma_v, sigma_omega : control-noise densities (m/s^1.5, rad/s^1.5).
    rng : seed of trajectories, biases, control noise and probe.

    Returns
    -------
    RoverScenario
    """
    check_positive(minutes, "minutes", allow_none=False)
    if U % 2 != 1:
        raise InputError(f"U must be odd for the symmetric Fourier basis, got {U}")
    g = as_rng(rng)
    S = max(2, int(round(minutes * 60 / T)))
    anchors = np.array([[0.0, 0.0], [45.0, 5.0], [20.0, 40.0]])
    center = np.array([22.0, 15.0])
    start2 = int(0.48 * S)
    x0 = np.array([[15.0, 12.0, 0.3], [28.0, 8.0, 1.8], [12.0, 24.0, -0.8], [32.0, 24.0, 3.0]])
    dias_s, dias_c = _drive(x0[0], S, T, 0, 0.5, g, center, 14.0)
    drake_s, drake_c = _drive(x0[1], S, T, start2, 0.5, g, center + [4, -3], 12.0)
    vesp_s, vesp_c = _drive(x0[2], S, T, start2, 0.45, g, center + [-4, 5], 12.0)
    mag_s = np.repeat(x0[3][None], S + 1, axis=0)
    mag_c = np.zeros((S, 2))
    states = np.stack([dias_s, drake_s, vesp_s, mag_s], axis=1)
    ctrl = np.stack([dias_c, drake_c, vesp_c, mag_c], axis=1)
    noise = g.standard_normal(ctrl.shape) * np.array([sigma_v, sigma_omega]) * np.sqrt(T)
    meas = ctrl + noise
    # the controls drove the truth; the filter sees the noisy ones: re-integrate truth from
    # the true controls so that the measured controls are noisy by exactly the stated model
    n = 4
    ports = np.array([4, 1, 1, 1])
    mma = [multimode_antenna(v, U).G for v in ("true", "em", "chamber")]
    dip = dipole_response(U).G
    G_true = [mma[0]] + [dip] * 3
    G_em = [mma[1]] + [dip] * 3
    G_ch = [mma[2]] + [dip] * 3
    biases = g.normal(0.0, bias_std, n + anchors.shape[0])
    rx, tx = [], []
    for i in range(n):
        for j in range(n + anchors.shape[0]):
            if j != i:
                rx.append(i)
                tx.append(j)
    probe = ofdm_probe(n_subcarriers, g)
    return RoverScenario(
        anchors=anchors, names=AGENT_NAMES, ports=ports, G_true=G_true, G_em=G_em, G_chamber=G_ch,
        T=T, states=states, controls_true=ctrl, controls=meas, biases=biases, probe=probe,
        bandwidth=bandwidth, carrier=carrier, snr_db=snr_db, sigma_v=sigma_v, sigma_omega=sigma_omega,
        rx=np.array(rx), tx=np.array(tx),
    )
