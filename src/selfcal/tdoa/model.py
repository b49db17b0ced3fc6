"""Far-field model pieces shared by the refinements: result type, losses, residuals, Jacobian,
weights and the blocks of the normal equations (paper 000, eq. 1)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .._result import Result
from ..geometry import sphere_tangent_basis
from ..robust import loss_rho as _loss_table

Array = NDArray[np.float64]


@dataclass(frozen=True, repr=False)
class RefineResult(Result):
    """Output of :func:`refine_lm` / :func:`refine_alternating`.

    positions (m, 3) with row 0 = 0, directions (k, 3) unit, offsets (k,), cost (final
    value of F), iterations, converged, and ``history``: the cost after every iteration
    (``history[0]`` is the initial cost) and, if requested, the positions after every
    iteration (``position_history``). :func:`refine_lm` also gives ``position_cov``
    (m, 3, 3), the Gauss-Newton covariance of each position (see :func:`position_covariance`).
    """

    positions: Array
    directions: Array
    offsets: Array
    cost: float
    iterations: int
    converged: bool
    history: list[float] = field(default_factory=list)
    position_history: list[Array] = field(default_factory=list)
    position_cov: Array | None = None


# ----------------------------------------------------------------------------- losses
def loss_rho(s: Array, loss: str) -> Array:
    """Loss ``rho(s)`` of squared, scaled residuals ``s = r^2 / delta^2`` (scipy convention)."""
    return _loss_table(s, loss)[0]


def loss_weight(s: Array, loss: str) -> Array:
    """IRLS weight ``rho'(s)`` for squared, scaled residuals ``s`` (1 for the linear loss)."""
    return _loss_table(s, loss)[1]


def _cost(r: Array, mask: NDArray[np.bool_], loss: str, delta: float) -> float:
    s = np.where(mask, r, 0.0) ** 2 / delta**2
    return float(delta**2 * np.sum(np.where(mask, loss_rho(s, loss), 0.0)))


# ----------------------------------------------------------------------------- model
def farfield_residuals(D: Array, Z: Array, N: Array, C: Array) -> Array:
    """Residuals ``r_ij = D_ij - z_i . n_j - C_j`` (paper 000, Problem 1): (m, k).

    Z is (m, 3) with rows z_i, N is (k, 3) with rows n_j, C is (k,). NaN stays NaN.
    """
    return D - Z @ N.T - C[None, :]


def farfield_jacobian(Z: Array, N: Array, *, free_offsets: bool = True) -> Array:
    """Dense Jacobian of the model ``z_i . exp_{n_j}(T_j v_j) + C_j`` at ``v = 0``.

    Parameter order: ``z_2..z_m`` (3 each), then per column ``v_j`` (2, tangent coordinates
    in :func:`selfcal.geometry.sphere_tangent_basis`) and, with ``free_offsets``, ``C_j``.
    Rows: entries (i, j) in row-major order. This is the J of paper 000, Algorithm 3 step 1
    (of the model, i.e. minus the Jacobian of the residuals); it is meant for tests and
    small problems: :func:`refine_lm` never forms it.

    Returns
    -------
    (m*k, 3(m-1) + (3 or 2) k) array.
    """
    m, k = Z.shape[0], N.shape[0]
    T = sphere_tangent_basis(N)  # (k, 3, 2)
    p = 3 if free_offsets else 2
    J = np.zeros((m, k, 3 * (m - 1) + p * k))
    for i in range(1, m):
        J[i, :, 3 * (i - 1) : 3 * i] = N
    zt = np.einsum("ia,jab->ijb", Z, T)  # d(z_i . n_j)/dv_j
    base = 3 * (m - 1)
    for j in range(k):
        J[:, j, base + p * j : base + p * j + 2] = zt[:, j]
        if free_offsets:
            J[:, j, base + p * j + 2] = 1.0
    return J.reshape(m * k, -1)


# ----------------------------------------------------------------------------- helpers
def _weights(
    D: Array, Z: Array, N: Array, C: Array, mask: NDArray[np.bool_], loss: str, delta: float
) -> Array:
    r = np.where(mask, farfield_residuals(D, Z, N, C), 0.0)
    return np.where(mask, loss_weight(r**2 / delta**2, loss), 0.0)


def _positions_given_directions(D: Array, N: Array, C: Array, W: Array) -> Array:
    """Weighted least squares for z_2..z_m given the directions (Algorithm 2, step 2)."""
    Y = np.where(W > 0, D - C[None, :], 0.0)
    H = np.einsum("ij,ja,jb->iab", W, N, N)
    g = np.einsum("ij,ij,ja->ia", W, Y, N)
    H = H + 1e-12 * np.trace(H, axis1=1, axis2=2)[:, None, None] * np.eye(3)
    Z = np.linalg.solve(H, g[..., None])[..., 0]
    Z[0] = 0.0
    return Z


def _prepare(D: Array, mask: NDArray[np.bool_] | None) -> tuple[Array, NDArray[np.bool_]]:
    D = np.asarray(D, dtype=float)
    obs = np.isfinite(D) if mask is None else (np.asarray(mask, bool) & np.isfinite(D))
    return np.where(obs, D, 0.0), obs


# ----------------------------------------------------------------------------- Algorithm 2
def _start(
    D: Array, mask: NDArray[np.bool_] | None, positions: Array, directions: Array, offsets: Array
) -> tuple[Array, NDArray[np.bool_], Array, Array, Array]:
    """Working copies of the data and of the initial estimate in the paper's gauge
    (first position at the origin, unit directions), shared by both refinements."""
    D0, obs = _prepare(D, mask)
    Z = np.array(positions, dtype=float)
    Z[0] = 0.0
    N = np.array(directions, dtype=float)
    N /= np.linalg.norm(N, axis=1, keepdims=True)
    return D0, obs, Z, N, np.array(offsets, dtype=float)


def _tangent(N: Array) -> Array:
    """Tangent basis of the unit sphere (d = 3: (k, 3, 2)) or circle (d = 2: (k, 2, 1))."""
    if N.shape[1] == 3:
        return sphere_tangent_basis(N)
    return np.stack([-N[:, 1], N[:, 0]], axis=1)[:, :, None]


def _normal_equations(
    D0: Array, Z: Array, N: Array, C: Array, W: Array, free_offsets: bool, *, coupling: bool = True
) -> tuple[Any, ...]:
    """Blocks of J^T W J and J^T W r for the parametrisation of :func:`farfield_jacobian`.

    Works in d = 2 or 3 dimensions (Z (m, d), N (k, d)): Hzz (m-1, d, d), Hzn
    (m-1, k, d, p), Hnn (k, p, p) with p = d - 1 tangent coordinates (+1 offset).
    Each coupling block is the outer product ``W_ij n_j b_ij^T``; with ``coupling=False``
    Hzn is returned in that factored form ``(W[1:], N, b[1:])`` (O(m k p) memory instead
    of O(m k d p)) for the matrix-free CG step.
    """
    T = _tangent(N)  # (k, d, d-1)
    r = np.where(W > 0, farfield_residuals(D0, Z, N, C), 0.0)
    zt = np.einsum("ia,jab->ijb", Z, T)  # (m, k, d-1)
    if free_offsets:
        bcol = np.concatenate([zt, np.ones(zt.shape[:2] + (1,))], axis=-1)  # (m, k, p)
    else:
        bcol = zt
    m, k, d = Z.shape[0], N.shape[0], N.shape[1]
    NN = (N[:, :, None] * N[:, None, :]).reshape(k, d * d)
    Hzz = (W[1:] @ NN).reshape(m - 1, d, d)  # BLAS products and broadcasting, not einsum loops
    Wb = W[:, :, None] * bcol  # (m, k, p)
    Hzn = Wb[1:, :, None, :] * N[None, :, :, None] if coupling else (W[1:], N, bcol[1:])
    Hnn = np.matmul(Wb.transpose(1, 2, 0), bcol.transpose(1, 0, 2))
    Wr = W * r
    gz = (Wr @ N)[1:]
    gn = np.einsum("ij,ija->ja", Wr, bcol)
    return Hzz, Hzn, Hnn, gz, gn, T, r


def _flat(Hzn: Array) -> Array:
    """(mz, k, d, p) coupling blocks as the (mz d, k p) matrix H_zn."""
    mz, k, d, p = Hzn.shape
    return Hzn.transpose(0, 2, 1, 3).reshape(mz * d, k * p)


def _eliminate_positions(mz: int, d: int, k: int, p: int) -> bool:
    """Schur side: eliminate the (block-diagonal) positions when the directions' system is smaller."""
    return d * mz > p * k
