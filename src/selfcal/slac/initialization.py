"""Snapshot-based initial poses for the SLAC filter (paper 002, section IV, "s = 0").

The paper initialises the filter with "a snapshot-based position and orientation estimation
algorithm": no prior track, only the signals of one snapshot. Here, from the snapshots of all
links at one instant:

1. ML round-trip delay of every link (antenna-agnostic, :func:`batch_delay_search`) -> range
   ``rho_l = c tau_l / 2`` (eq. 1 with the biases at their initial value 0) and its
   Cramér-Rao standard deviation;
2. agent positions by linear multilateration from the anchor links, then a joint weighted
   nonlinear least-squares fit over all anchor and cooperative links; the range variance of
   a link adds the prior variance of the two unknown biases (``2 bias_std^2``), so the
   position covariance is honest about the uncalibrated biases;
3. the heading of every multi-port agent from its links' ML DoAs with the prior sampling
   matrix (eq. 2: ``psi = atan2(p_tx - p_rx) - phi``), combined by a circular mean; its
   standard deviation is the circular spread of the per-link values (not divided by the
   number of links: errors of the antenna prior are systematic, not independent).

A single-port (dipole) agent has an omnidirectional response: its heading is not observable
from one snapshot, so it must come from the caller (``headings`` / ``heading_std``).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import least_squares

from ..errors import DegenerateGeometryError, InputError
from ..toa.init.mds import multilaterate
from .doa import estimate_doa_from_y
from .motion import motion_step, process_noise, wrap_angle
from .signals import SPEED_OF_LIGHT, batch_delay_search

FArray = NDArray[np.float64]
CArray = NDArray[np.complex128]

#: Smallest heading standard deviation reported (rad): the DoA grid refinement and the
#: antenna prior are never better than about a degree on real hardware.
MIN_HEADING_STD = float(np.deg2rad(1.0))


@dataclass(frozen=True)
class InitialPoses:
    """Snapshot-based initial state.

    Attributes
    ----------
    poses : (n, 3) ``[x, y, psi]`` in metres / radians.
    cov : (n, 3, 3) their covariances (positions joint with each other only per agent).
    ranges : (L,) ML ranges of the links (m, biases not removed).
    range_std : (L,) their Cramér-Rao standard deviations (m, without the bias term).
    heading_observed : (n,) True where the heading came from the snapshot (multi-port agents).
    """

    poses: FArray
    cov: FArray
    ranges: FArray
    range_std: FArray
    heading_observed: NDArray[np.bool_]


def range_crlb_std(ys: Sequence[CArray], noise_var: FArray, probe: CArray, bandwidth: float) -> FArray:
    """Cramér-Rao standard deviation (m) of the RTT range of each link.

    ``var(tau) = sigma^2 / (2 |alpha|^2 sum_n (w_n - w_bar)^2 |s_n|^2)`` summed over ports, with
    ``w_n = 2 pi B n / N`` and ``|alpha_m|^2 = |y_m|^2 / S^2`` the ML amplitude of port m
    (the phase of each port is a nuisance, hence the centred frequencies); the range is
    ``c tau / 2``.

    Parameters
    ----------
    ys : L port vectors ``R s^*(tau)`` (M_l,) from :func:`batch_delay_search`.
    noise_var : (L,) noise variance per bin and port.
    probe : (N,) known spectrum; bandwidth : Hz.
    """
    p = np.abs(np.asarray(probe, dtype=complex)) ** 2
    N = p.size
    S = float(p.sum())
    w = 2 * np.pi * float(bandwidth) * np.arange(N) / N
    wbar = float(np.sum(w * p) / S)
    spread = float(np.sum((w - wbar) ** 2 * p))
    amp2 = np.array([float(np.sum(np.abs(y) ** 2)) for y in ys]) / S**2
    var_tau = np.asarray(noise_var, dtype=float) / (2 * np.maximum(amp2, 1e-300) * spread)
    return np.asarray(SPEED_OF_LIGHT * np.sqrt(var_tau) / 2)


def snapshot_initial_poses(
    anchors: FArray,
    ports: Sequence[int] | NDArray[np.int64],
    G_prior: Sequence[CArray | None],
    rx: NDArray[np.int64],
    tx: NDArray[np.int64],
    snapshots: Sequence[CArray],
    probe: CArray,
    bandwidth: float,
    *,
    headings: FArray | None = None,
    heading_std: FArray | None = None,
    bias_std: float = 0.5,
) -> InitialPoses:
    """Poses of all agents from the snapshots of one instant (paper 002, section IV).

    Parameters
    ----------
    anchors : (A, 2) known anchor positions (m).
    ports : (n,) number of antenna ports of each agent.
    G_prior : n prior sampling matrices (M_i, U), None for single-port agents.
    rx, tx : (L,) link node indices (agents 0..n-1, then anchors n..n+A-1); rx is an agent.
    snapshots : L arrays (M_rx, N), the received signals (eq. 3).
    probe : (N,) known OFDM spectrum; bandwidth : Hz.
    headings, heading_std : (n,) headings (rad) and their standard deviations used for agents
        whose heading the snapshot cannot give (single-port agents); NaN / None elsewhere.
    bias_std : prior standard deviation of every ranging bias (m), as in ``SlacConfig``.

    Returns
    -------
    InitialPoses.

    Raises
    ------
    InputError : a single-port agent without a given heading, or inconsistent inputs.
    DegenerateGeometryError(kind="unobservable-agent") : an agent whose position the links
        do not determine.
    """
    P = np.asarray(anchors, dtype=float)
    ports_a = np.asarray(ports, dtype=int)
    n, A = ports_a.size, P.shape[0]
    rx = np.asarray(rx, dtype=int)
    tx = np.asarray(tx, dtype=int)
    if rx.shape != tx.shape or len(snapshots) != rx.size or np.any(rx >= n) or np.any(tx >= n + A):
        raise InputError("rx, tx and snapshots must describe the same L links (rx an agent)")
    tau, ys, var = batch_delay_search(list(snapshots), probe, bandwidth)
    rng_ml = SPEED_OF_LIGHT * tau / 2
    sd_crlb = range_crlb_std(ys, var, probe, bandwidth)
    sd_r = np.sqrt(sd_crlb**2 + 2 * bias_std**2)

    # linear multilateration of each agent from its anchor links (mean over repeated links)
    R = np.full((n, A), np.nan)
    for i in range(n):
        for a in range(A):
            sel = (rx == i) & (tx == n + a)
            if np.any(sel):
                R[i, a] = float(np.mean(rng_ml[sel]))
    x0 = np.where(np.sum(~np.isnan(R), axis=1, keepdims=True) >= 3, multilaterate(P, R), P.mean(axis=0))

    def resid(z: FArray) -> FArray:
        pos = np.vstack([z.reshape(n, 2), P])
        return (np.linalg.norm(pos[tx] - pos[rx], axis=1) - rng_ml) / sd_r

    sol = least_squares(resid, x0.ravel(), method="lm" if rx.size >= 2 * n else "trf")
    J = sol.jac
    info = J.T @ J
    ev = np.linalg.eigvalsh(info)
    if ev[0] <= 1e-9 * max(ev[-1], 1e-300):
        raise DegenerateGeometryError(
            "the links of this snapshot do not determine every agent's position (each agent needs "
            "ranges to >= 3 non-collinear known or located nodes in 2-D)", kind="unobservable-agent")
    cov_p = np.linalg.inv(info)
    pos = sol.x.reshape(n, 2)

    psi = np.full(n, np.nan)
    psi_sd = np.full(n, np.nan)
    observed = np.zeros(n, dtype=bool)
    allpos = np.vstack([pos, P])
    for i in range(n):
        G = G_prior[i]
        links = np.flatnonzero(rx == i)
        if ports_a[i] > 1 and G is not None and links.size:
            d = allpos[tx[links]] - allpos[i]
            cand = np.array([np.arctan2(d[k, 1], d[k, 0]) - estimate_doa_from_y(ys[l], G)
                             for k, l in enumerate(links)])
            m = complex(np.mean(np.exp(1j * cand)))
            psi[i] = float(np.angle(m))
            # circular standard deviation; a single link gives no spread: assume 10 degrees
            spread = np.sqrt(-2 * np.log(min(abs(m), 1.0) + 1e-300)) if links.size > 1 else np.deg2rad(10.0)
            psi_sd[i] = max(float(spread), MIN_HEADING_STD)
            observed[i] = True
        else:
            if headings is None or heading_std is None or not np.isfinite(headings[i]) \
                    or not np.isfinite(heading_std[i]):
                raise InputError(f"agent {i} has a single-port antenna: its heading is not observable from "
                                 "one snapshot; give it (headings / heading_std)")
            psi[i], psi_sd[i] = float(headings[i]), float(heading_std[i])
    cov = np.zeros((n, 3, 3))
    for i in range(n):
        cov[i, :2, :2] = cov_p[2 * i : 2 * i + 2, 2 * i : 2 * i + 2]
        cov[i, 2, 2] = psi_sd[i] ** 2
    poses = np.column_stack([pos, wrap_angle(psi)])
    return InitialPoses(poses=poses, cov=cov, ranges=rng_ml, range_std=sd_crlb, heading_observed=observed)


def back_propagate(poses: FArray, cov: FArray, controls: FArray, T: float, sigma_v: float,
                   sigma_omega: float) -> tuple[FArray, FArray]:
    """Move poses estimated at state index 1 back to index 0 through the motion model (eq. 14).

    Driving an arc backwards with ``(-v, -omega)`` retraces it exactly, so ``x_0 = f(x_1, -u_0)``;
    the covariance grows by one step of process noise (eq. 21), the price of not having the
    signals of state 0.

    Parameters
    ----------
    poses, cov : (n, 3), (n, 3, 3) at state index 1. controls : (n, 2) ``u_0 = [v, omega]``.
    T : step (s); sigma_v, sigma_omega : control-noise densities.
    """
    x0 = motion_step(poses, -np.asarray(controls, dtype=float), T)
    Q = process_noise(poses, controls, T, sigma_v, sigma_omega)
    return np.asarray(x0), np.asarray(cov + Q)
