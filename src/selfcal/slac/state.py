"""The SLAC state vector: its layout (paper 002, eqs. 10-16) and its prediction (eqs. 20-21).

State, in this order::

    [x_1, y_1, psi_1, ..., x_n, y_n, psi_n]          location states of the n agents (eq. 12)
    [delta_1 .. delta_n, (delta_anchor_1 ..)]         ranging biases (SLAC mode; eq. 15)
    [g_i for every multi-port agent i]                 [Re vec G_i; Im vec G_i] (eq. 16)

:func:`state_layout` builds the :class:`StateLayout` (where each node's bias and each agent's
sampling matrix sit) with the prior mean and covariance; :func:`predict_locations` is the
prediction, in which only the pose block moves.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import scipy.linalg as sla
from numpy.typing import NDArray

from .antenna import basis_orders
from .likelihood import pack_g
from .motion import motion_jacobian, motion_step, process_noise

__all__ = ["StateLayout", "state_layout", "predict_locations", "propagate_pose_block", "pose_means", "pose_blocks"]

FArray = NDArray[np.float64]
CArray = NDArray[np.complex128]


@dataclass(frozen=True)
class StateLayout:
    """Where each quantity sits in the state vector (module docstring).

    Attributes
    ----------
    n : int
        Number of agents (the first ``3 n`` entries are their poses).
    D : int
        Length of the state.
    bias_index : (n + A,) int array
        Index of each node's ranging bias (agents then anchors; -1 where not estimated).
    g_index : dict of int to int array
        Indices of agent i's packed sampling matrix (multi-port agents, SLAC mode only).
    g_prior_packed : dict of int to float array
        Agent i's prior sampling matrix, packed (:func:`~selfcal.slac.likelihood.pack_g`).
    """

    n: int
    D: int
    bias_index: NDArray[np.int64]
    g_index: dict[int, NDArray[np.int64]]
    g_prior_packed: dict[int, FArray]


def state_layout(
    ports: NDArray[np.int64], G_prior: Sequence[CArray | None], x0: FArray, P0: FArray, n_anchors: int, *,
    estimate_calibration: bool, anchor_biases: bool, bias_std: float, g_rel_std: float, g_order_decay: float,
) -> tuple[StateLayout, FArray, FArray]:
    """The state layout and the prior mean (D,) and covariance (D, D) (paper 002, section IV).

    Parameters
    ----------
    ports : (n,) int array
        Antenna ports M_i of each agent.
    G_prior : sequence of n (M_i, U) complex arrays or None
        Prior sampling matrices (None for single-port agents).
    x0 : (n, 3) array
        Initial poses ``[x, y, psi]`` (m, rad).
    P0 : (n, 3, 3) array
        Their covariances.
    n_anchors : int
    estimate_calibration : bool
        SLAC mode (biases and sampling matrices are states); False = localization only.
    anchor_biases : bool
        The anchors' biases are states too.
    bias_std : float
        Prior std of every bias, m (prior mean 0).
    g_rel_std, g_order_decay : float
        Prior std of each sampling-matrix entry relative to the RMS magnitude of the prior's
        entries, scaled by ``1 / (1 + decay |u|)`` for order u.

    Returns
    -------
    (StateLayout, (D,) array, (D, D) array)
    """
    n = len(ports)
    n_nodes = n + n_anchors
    blocks: list[FArray] = [x0.ravel()]
    cov_blocks: list[FArray] = list(P0)
    bias_index = np.full(n_nodes, -1)
    g_index: dict[int, NDArray[np.int64]] = {}
    D = 3 * n
    if estimate_calibration:
        nb = n_nodes if anchor_biases else n
        bias_index[:nb] = D + np.arange(nb)
        blocks.append(np.zeros(nb))
        cov_blocks.append(np.eye(nb) * bias_std**2)
        D += nb
        for i in range(n):
            if ports[i] > 1:
                G = G_prior[i]
                assert G is not None
                g = pack_g(G)
                g_index[i] = D + np.arange(g.size)
                blocks.append(g)
                rms = float(np.sqrt(np.mean(np.abs(G) ** 2)))
                orders = np.abs(basis_orders(G.shape[1]))
                per = g_rel_std * rms / (1.0 + g_order_decay * orders)
                sd = np.tile(np.repeat(per, G.shape[0]), 2)  # matches pack_g's u * M + m layout
                cov_blocks.append(np.diag(sd**2))
                D += g.size
    x = np.concatenate(blocks)
    P = sla.block_diag(*cov_blocks)
    packed = {i: pack_g(G_prior[i]) for i in g_index}  # type: ignore[arg-type]
    return StateLayout(n=n, D=D, bias_index=bias_index, g_index=g_index, g_prior_packed=packed), x, P


def predict_locations(
    x: FArray, P: FArray, controls: FArray, T: float, sigma_v: float, sigma_omega: float
) -> tuple[FArray, FArray]:
    """Prediction of eqs. 20-21 for a state whose first ``3 n`` entries are agent poses.

    The calibration states (biases, g) have identity motion and zero process noise, so only
    the pose rows and columns of the covariance change: with the block-diagonal pose Jacobian
    F_p (eq. 14) and process noise Q_p, ``P_pp <- F_p P_pp F_p^T + Q_p``,
    ``P_pc <- F_p P_pc`` and ``P_cc`` is untouched (the same as ``F P F^T + Q`` with the full
    F = diag(F_p, I), at O(n D) instead of O(D^3) cost).

    Parameters
    ----------
    x, P : (D,), (D, D) state (m, rad) and covariance; calibration states follow the poses.
    controls : (n, 2) ``[v, omega]`` per agent (m/s, rad/s); T : s; sigma_v : m/s^1.5;
        sigma_omega : rad/s^1.5.

    Returns
    -------
    x_bar (D,), P_bar (D, D) (symmetric).
    """
    u = np.asarray(controls, dtype=float)
    n = u.shape[0]
    p = 3 * n
    poses = x[:p].reshape(n, 3)
    Fl = motion_jacobian(poses, u, T)
    Ql = process_noise(poses, u, T, sigma_v, sigma_omega)
    x_new = x.copy()
    x_new[:p] = motion_step(poses, u, T).ravel()
    Fp = sla.block_diag(*Fl)
    Qp = sla.block_diag(*Ql) + 1e-12 * np.eye(p)  # keeps P_bar positive definite for a static rover
    return x_new, propagate_pose_block(P, Fp, Qp)


def propagate_pose_block(P: FArray, Fp: FArray, Qp: FArray) -> FArray:
    """Covariance prediction (eq. 21) when only the first ``p`` states (the poses) move.

    ``P`` (D, D), pose Jacobian ``Fp`` (p, p), pose process noise ``Qp`` (p, p):
    ``P_pp <- Fp P_pp Fp^T + Qp`` (symmetrised), ``P_pc <- Fp P_pc``, ``P_cc`` unchanged.
    Returns a new (D, D) array.
    """
    p = Fp.shape[0]
    P_new = P.copy()
    rows = Fp @ P[:p]  # (p, D): [F_p P_pp, F_p P_pc]
    Ppp = rows[:, :p] @ Fp.T + Qp
    P_new[:p, :p] = 0.5 * (Ppp + Ppp.T)
    P_new[:p, p:] = rows[:, p:]
    P_new[p:, :p] = rows[:, p:].T
    return P_new


def pose_means(x: FArray, n: int) -> FArray:
    """The n agents' poses (n, 3) ``[x, y, psi]`` from a state whose first ``3 n`` entries are poses (a copy)."""
    return x[: 3 * n].reshape(n, 3).copy()


def pose_blocks(P: FArray, n: int) -> FArray:
    """The n agents' pose covariances (n, 3, 3): the diagonal 3 x 3 blocks of the state covariance."""
    return np.stack([P[3 * i : 3 * i + 3, 3 * i : 3 * i + 3] for i in range(n)])
