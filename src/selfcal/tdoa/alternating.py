"""Alternating optimisation, paper 000 Algorithm 2, and its per-direction sphere solvers."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from .._checks import check_choice
from ..geometry import sphere_exp, sphere_tangent_basis
from ..robust import LOSSES
from .model import (
    RefineResult,
    _cost,
    _positions_given_directions,
    _start,
    _weights,
    farfield_residuals,
)

Array = NDArray[np.float64]


# ----------------------------------------------------------------------------- directions
def sphere_lstsq_global(H: Array, g: Array, *, iterations: int = 200) -> Array:
    """Global minimiser of ``n^T H n - 2 g^T n`` on the unit sphere, batched.

    This is the per-direction problem of Algorithm 2, step 3 (``H = sum_i w_i z_i z_i^T``,
    ``g = sum_i w_i (D_ij - C_j) z_i``). Stationary points satisfy ``(H + mu I) n = g``,
    ``|n| = 1`` -- the tangency of an ellipsoidal level set with the sphere that paper 000
    solves as polynomial equations (multiplying out gives a degree-6 polynomial in mu).
    The global minimum is the stationary point with the largest multiplier
    ``mu >= -lambda_min(H)`` (Gander 1981), found here as the root of the monotone secular
    equation ``sum_a c_a^2 / (lambda_a + mu)^2 = 1`` by bisection on
    ``(-lambda_min, -lambda_min + |g|]`` (safeguarded Newton); the "hard case" (``c_min = 0``) is completed
    along the eigenvector of ``lambda_min``.

    Parameters
    ----------
    H : (..., 3, 3) symmetric positive semi-definite.
    g : (..., 3).

    Returns
    -------
    (..., 3) unit vectors.
    """
    lam, Q = np.linalg.eigh(H)
    c = np.einsum("...ab,...a->...b", Q, g)
    gn = np.linalg.norm(g, axis=-1)
    lo = -lam[..., 0]
    hi = lo + np.maximum(gn, 1e-300)
    mu = hi.copy()
    # safeguarded Newton on psi(mu) = 1/|y(mu)| - 1 (increasing, nearly linear in mu:
    # Moré-Sorensen), falling back to bisection whenever Newton leaves the bracket
    for _ in range(iterations):
        den = np.maximum(lam + mu[..., None], 1e-300)
        s2 = np.sum(c**2 / den**2, axis=-1)
        s3 = np.sum(c**2 / den**3, axis=-1)
        ny = np.sqrt(s2)
        psi = 1.0 / np.maximum(ny, 1e-300) - 1.0
        lo = np.where(psi < 0, mu, lo)
        hi = np.where(psi >= 0, mu, hi)
        dpsi = s3 / np.maximum(ny, 1e-300) ** 3
        new = mu - psi / np.maximum(dpsi, 1e-300)
        bad = ~((new > lo) & (new < hi)) | ~np.isfinite(new)
        new = np.where(bad, 0.5 * (lo + hi), new)
        done = np.abs(new - mu) <= 1e-15 * (np.abs(mu) + np.abs(lam[..., -1]) + 1e-300)
        mu = new
        if np.all(done):
            break
    den = lam + mu[..., None]
    y = c / np.maximum(den, 1e-300)
    ny = np.linalg.norm(y, axis=-1)
    # hard case: the multiplier sits at -lambda_min and |y| < 1; fill up along q_min
    hard = ny < 1.0 - 1e-9
    y0 = np.where(hard, 0.0, y[..., 0])
    rest = np.sqrt(np.maximum(1.0 - y[..., 1] ** 2 - y[..., 2] ** 2, 0.0))
    y0 = np.where(hard, np.where(c[..., 0] < 0, -rest, rest), y0)
    y = np.concatenate([y0[..., None], y[..., 1:]], axis=-1)
    n = np.einsum("...ab,...b->...a", Q, y)
    return n / np.linalg.norm(n, axis=-1, keepdims=True)


def sphere_lstsq_local(H: Array, g: Array, n0: Array, *, iterations: int = 20) -> Array:
    """Local minimiser of ``n^T H n - 2 g^T n`` on the unit sphere from ``n0``, batched.

    Riemannian Newton with the exponential map and a Levenberg safeguard: the local
    constrained solver of Algorithm 2 (the paper used an interior-point method; any
    descent method that stays on the sphere converges to the same local minimum).

    Parameters
    ----------
    H : (..., 3, 3), g : (..., 3), n0 : (..., 3) unit start.
    """
    n = n0 / np.linalg.norm(n0, axis=-1, keepdims=True)
    for _ in range(iterations):
        T = sphere_tangent_basis(n)  # (..., 3, 2)
        Hn = np.einsum("...ab,...b->...a", H, n)
        grad_e = Hn - g  # half Euclidean gradient
        mu = np.einsum("...a,...a->...", n, grad_e)  # Lagrange multiplier estimate
        gt = np.einsum("...ab,...a->...b", T, grad_e)
        Ht = np.einsum("...ab,...bc,...cd->...ad", np.swapaxes(T, -1, -2), H, T)
        Ht = Ht - mu[..., None, None] * np.eye(2)  # Riemannian Hessian on the sphere
        # keep the step a descent step where the Hessian is indefinite
        shift = np.maximum(0.0, 1e-9 - np.linalg.eigvalsh(Ht)[..., 0])
        Ht = Ht + (shift[..., None, None] + 1e-12) * np.eye(2)
        v = -np.linalg.solve(Ht, gt[..., None])[..., 0]
        step = np.einsum("...ab,...b->...a", T, v)
        nrm = np.linalg.norm(step, axis=-1, keepdims=True)
        step = np.where(nrm > 0.5, step * 0.5 / np.maximum(nrm, 1e-300), step)
        n = sphere_exp(n, step)
    return n


def refine_alternating(
    D: Array,
    positions: Array,
    directions: Array,
    offsets: Array,
    *,
    mask: NDArray[np.bool_] | None = None,
    free_offsets: bool = False,
    direction_solver: str = "global",
    loss: str = "linear",
    delta: float = 1.0,
    max_iter: int = 500,
    tol: float = 1e-10,
    record_positions: bool = False,
) -> RefineResult:
    """Alternating (block coordinate descent) optimisation, paper 000 Algorithm 2.

    Parameters
    ----------
    D : (m, k) relative distances (NaN = missing), metres.
    positions : (m, 3) initial z_i (row 0 is forced to 0), directions (k, 3) unit,
        offsets (k,) initial C_j (with ``free_offsets=False`` they stay fixed: use
        ``C_j = D_1j`` for the paper's reduced cost).
    mask : optional (m, k) bool of entries to use (False = rejected / missing).
    direction_solver : "global" (secular equation) or "local" (Newton on the sphere).
    loss, delta : robust loss (see :data:`LOSSES`) and its scale in metres (IRLS).
    max_iter, tol : stop after ``max_iter`` sweeps, when the relative decrease of the cost
        in one sweep is below ``tol``, when the cost reaches the rounding floor, or when no
        position moves by more than 1e-13 of the array size.
    record_positions : keep the positions after every sweep (for convergence plots).
    """
    check_choice(direction_solver, "direction_solver", ("global", "local"))
    check_choice(loss, "loss", LOSSES)
    D0, obs, Z, N, C = _start(D, mask, positions, directions, offsets)
    cost = _cost(farfield_residuals(D0, Z, N, C), obs, loss, delta)
    hist, phist = [cost], ([Z.copy()] if record_positions else [])
    # rounding floor: below this the data are fitted to machine precision
    atol = obs.sum() * (1e-14 * (np.sqrt(np.mean(D0[obs] ** 2)) + 1e-300)) ** 2
    zscale = float(np.max(np.abs(Z))) + 1e-300
    Z_prev = Z.copy()
    converged = False
    it = 0
    for it in range(1, max_iter + 1):
        W = _weights(D0, Z, N, C, obs, loss, delta)
        Z = _positions_given_directions(D0, N, C, W)
        if free_offsets:
            W = _weights(D0, Z, N, C, obs, loss, delta)
            num = np.sum(W * (D0 - Z @ N.T), axis=0)
            C = np.where(W.sum(0) > 0, num / np.maximum(W.sum(0), 1e-300), C)
        W = _weights(D0, Z, N, C, obs, loss, delta)
        H = np.einsum("ij,ia,ib->jab", W, Z, Z)
        g = np.einsum("ij,ij,ia->ja", W, D0 - C[None, :], Z)
        N = sphere_lstsq_global(H, g) if direction_solver == "global" else sphere_lstsq_local(H, g, N)
        new = _cost(farfield_residuals(D0, Z, N, C), obs, loss, delta)
        hist.append(new)
        if record_positions:
            phist.append(Z.copy())
        moved = float(np.max(np.abs(Z - Z_prev))) if it > 1 else np.inf
        Z_prev = Z.copy()
        if abs(cost - new) <= tol * max(cost, 1e-300) or new <= atol or moved <= 1e-13 * zscale:
            converged = True
            cost = new
            break
        cost = new
    return RefineResult(Z, N, C, cost, it, converged, hist, phist)
