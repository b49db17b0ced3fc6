"""Refinement of a far-field TDOA reconstruction (paper 000, section 2.3).

Cost (paper 000, eq. 1, Problem 3), generalised with weights, missing entries and a robust
loss::

    F(Z, N, C) = sum_ij  delta^2 rho( (D_ij - z_i . n_j - C_j)^2 / delta^2 ),  |n_j| = 1,

over the observed entries, with ``z_1 = 0`` fixed (the gauge of Lemma 1). With
``free_offsets=False`` the offsets are pinned to ``C_j = D_1j`` and the cost is exactly the
paper's ``||Dbar - Z N||_F^2`` on the reduced matrix; with ``free_offsets=True`` the ``C_j``
are estimated too (the maximum-likelihood cost under i.i.d. noise on D, and the one that
keeps a corrupted first row from spoiling whole columns).

* :func:`refine_alternating` -- Algorithm 2: exact least squares for Z given N, then each
  ``n_j`` on the unit sphere, either globally (:func:`sphere_lstsq_global`, the secular
  equation) or locally (:func:`sphere_lstsq_local`, Gauss-Newton on the sphere).
* :func:`refine_lm` -- Algorithm 3: Levenberg-Marquardt with the exponential-map
  re-parametrisation ``n_j <- exp_{n_j}(T_j v_j)`` (T_j a tangent basis), Marquardt scaling
  ``J^T J + lambda diag(J^T J)``. The block structure (z_i couple to every column, each
  column's unknowns only to themselves) is used through a Schur complement, so one step
  costs O(m k + m^3) rather than a dense solve in 3m + 3k unknowns.

Robust losses are handled by iteratively re-weighted least squares (weights ``rho'``).

:func:`farfield_crlb` gives the Cramer-Rao bound of the positions (rigid gauge removed).
Audit (issue 4): with ``free_offsets=True`` LM reaches the same minimum as an independent
``scipy.optimize.least_squares`` and meets the bound at low noise; that it barely lowers
the error of the initialisation there is because the initialisation is already within
1.0-1.4x of the bound in MSE. At high noise relative to the array (sigma = 0.1, unit cube,
m = k = 10) the ML estimate is biased outwards (each column's direction and offset are fitted
from only m entries, so a larger array absorbs more noise) and can be worse than the
initialisation; in about a quarter of such draws the ML minimum itself (reached by LM
even when started at the true geometry) has nearly coplanar directions and a stretched
array. See ``selfcal.experiments.farfield.FINDING``. :func:`selfcal.tdoa.solve_farfield`
flags such solutions (``warnings``: ``directions-collapsed``, threshold
``selfcal.tdoa.farfield.COLLAPSE_RATIO``).

Length (822 lines, above the ~600 guideline): alternating and LM refinement, the Schur / CG
steps and the covariance share the sphere parametrisation.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .._checks import check_choice
from ..geometry import sphere_exp, sphere_tangent_basis
from ..robust import LOSSES
from ..robust import loss_rho as _loss_table

__all__ = [
    "LOSSES",
    "RefineResult",
    "loss_rho",
    "loss_weight",
    "farfield_residuals",
    "farfield_jacobian",
    "sphere_lstsq_global",
    "sphere_lstsq_local",
    "refine_alternating",
    "refine_lm",
    "position_covariance",
    "farfield_crlb",
]

Array = NDArray[np.float64]


@dataclass(frozen=True)
class RefineResult:
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


# ----------------------------------------------------------------------------- Algorithm 3
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


def _lm_step(
    Hzz: Array, Hzn: Array, Hnn: Array, gz: Array, gn: Array, lam: float, *, side: str = "auto"
) -> tuple[Array, Array]:
    """Solve (H + lam diag H) dx = g by a Schur complement over the smaller side.

    Both the position blocks (d x d) and the per-column blocks (p x p) are block diagonal;
    only their coupling is dense. ``side="directions"`` eliminates the columns (reduced
    system of size d(m-1)), ``"positions"`` eliminates the positions (size p k); ``"auto"``
    takes the smaller, so one step costs O(m k min(dm, pk)) and memory O(m k).
    """
    if isinstance(Hzn, tuple):
        mz, k, d, p = Hzn[0].shape[0], Hzn[1].shape[0], Hzn[1].shape[1], Hnn.shape[1]
    else:
        mz, k, d, p = Hzn.shape
    eye_p, eye_d = np.eye(p), np.eye(d)
    Hnn_d = Hnn + lam * np.einsum("jaa->ja", Hnn)[:, :, None] * eye_p + 1e-12 * eye_p
    Hzz_d = Hzz + lam * np.einsum("iaa->ia", Hzz)[:, :, None] * eye_d + 1e-12 * eye_d
    if side == "auto":
        side = "positions" if _eliminate_positions(mz, d, k, p) else "directions"
        if min(d * mz, p * k) > DIRECT_MAX:
            side = "cg"
    if isinstance(Hzn, tuple):
        return _lm_step_cg_factored(Hzz_d, Hzn, Hnn_d, gz, gn)
    if side == "cg":
        return _lm_step_cg(Hzz_d, Hzn, Hnn_d, gz, gn)
    Hr = _flat(Hzn)
    if side == "directions":
        Hnn_inv = np.linalg.inv(Hnn_d)  # (k, p, p)
        Xf = _flat(np.matmul(Hzn, Hnn_inv[None]))  # Hzn Hnn^-1
        S = -(Xf @ Hr.T)
        S4 = S.reshape(mz, d, mz, d)
        idx = np.arange(mz)
        S4[idx, :, idx, :] += Hzz_d
        rhs = gz - (Xf @ gn.reshape(-1)).reshape(mz, d)
        dz = np.linalg.solve(S, rhs.reshape(-1)).reshape(mz, d)
        dn = np.einsum("jab,jb->ja", Hnn_inv, gn - (dz.reshape(-1) @ Hr).reshape(k, p))
        return dz, dn
    Hzz_inv = np.linalg.inv(Hzz_d)  # (mz, d, d)
    Yr = _flat(np.matmul(Hzz_inv[:, None], Hzn))  # Hzz^-1 Hzn as (mz d, k p)
    S = -(Hr.T @ Yr)  # (k p, k p)
    S4 = S.reshape(k, p, k, p)
    idx = np.arange(k)
    S4[idx, :, idx, :] += Hnn_d
    rhs = gn.reshape(-1) - Yr.T @ gz.reshape(-1)
    dn = np.linalg.solve(S, rhs)
    dz = np.einsum("iab,ib->ia", Hzz_inv, gz) - (Yr @ dn).reshape(mz, d)
    return dz, dn.reshape(k, p)


#: largest reduced (Schur) system solved directly; above it (both sides large, e.g. 2000 x 2000)
#: the reduced system would cost O(m k n) to form and O(n^3) to factor, and the LM step
#: uses preconditioned conjugate gradients with O(m k) matrix-vector products instead
DIRECT_MAX = 1500
#: largest reduced system for which :func:`refine_lm` computes the covariance by default
#: (n = 2000: 32 MB and a few seconds of one core for the O(n^3) inverse)
COV_DIRECT_MAX = 2000


def _block_jacobi_cg(matvec: Any, diag: Array, rhs: Array, *, rtol: float, max_iter: int) -> Array:
    """Solve ``S x = rhs`` by CG preconditioned with the exact (k, p, p) diagonal blocks of S.

    ``matvec`` applies S to a flat (k p,) vector; the result is flat too.
    """
    from scipy.sparse.linalg import LinearOperator, cg

    k, p, _ = diag.shape
    Pinv = np.linalg.inv(diag)

    def precond(x: Array) -> Array:
        return np.einsum("jab,jb->ja", Pinv, np.asarray(x).reshape(k, p)).reshape(-1)

    n = k * p
    A = LinearOperator((n, n), matvec=matvec, dtype=float)
    M = LinearOperator((n, n), matvec=precond, dtype=float)
    x, _ = cg(A, rhs, rtol=rtol, atol=0.0, maxiter=max_iter, M=M)
    return np.asarray(x)


def _lm_step_cg(Hzz_d: Array, Hzn: Array, Hnn_d: Array, gz: Array, gn: Array, *,
                rtol: float = 1e-10, max_iter: int = 500) -> tuple[Array, Array]:
    """The damped Gauss-Newton step by block-Jacobi preconditioned CG on the directions' Schur
    complement ``S_n = Hnn - H_nz Hzz^-1 H_zn``, never formed: each product costs O(m k d p)."""
    mz, k, d, p = Hzn.shape
    Hzz_inv = np.linalg.inv(Hzz_d)
    Hf = Hzn.transpose(0, 2, 1, 3).reshape(mz * d, k * p)  # one copy, reused by every product
    HzzB = Hzz_inv

    def zsolve(v: Array) -> Array:
        return np.einsum("iab,ib->ia", HzzB, v.reshape(mz, d)).reshape(-1)

    def matvec(x: Array) -> Array:
        x = np.asarray(x).reshape(-1)
        y = np.einsum("jab,jb->ja", Hnn_d, x.reshape(k, p)).reshape(-1)
        return y - Hf.T @ zsolve(Hf @ x)

    # block-Jacobi preconditioner: the exact diagonal blocks of S_n
    Y = np.matmul(Hzz_inv[:, None], Hzn)  # (mz, k, d, p)
    At = Hzn.transpose(1, 0, 2, 3).reshape(k, mz * d, p)
    diag = Hnn_d - np.matmul(At.transpose(0, 2, 1), Y.transpose(1, 0, 2, 3).reshape(k, mz * d, p))
    del At
    del Y
    rhs = gn.reshape(-1) - Hf.T @ zsolve(gz.reshape(-1))
    dn = _block_jacobi_cg(matvec, diag, rhs, rtol=rtol, max_iter=max_iter)
    dz = (zsolve(gz.reshape(-1)) - zsolve(Hf @ dn)).reshape(mz, d)
    return dz, dn.reshape(k, p)


def _lm_step_cg_factored(Hzz_d: Array, factors: tuple[Array, Array, Array], Hnn_d: Array, gz: Array,
                         gn: Array, *, rtol: float = 1e-10, max_iter: int = 500) -> tuple[Array, Array]:
    """:func:`_lm_step_cg` with the coupling blocks ``W_ij n_j b_ij^T`` kept factored.

    Products with H_zn / H_nz cost O(m k (d + p)) and need no (m, k, d, p) array: the
    memory stays a few copies of the data.
    """
    W, N, bc = factors  # (mz, k), (k, d), (mz, k, p)
    mz, k, p = bc.shape
    Hzz_inv = np.linalg.inv(Hzz_d)

    def hzn(x: Array) -> Array:  # (k, p) -> (mz, d): sum_j W_ij n_j (b_ij . x_j)
        t = np.einsum("ijp,jp->ij", bc, x)
        return (W * t) @ N

    def hnz(v: Array) -> Array:  # (mz, d) -> (k, p): sum_i W_ij b_ij (n_j . v_i)
        s_ = W * (v @ N.T)
        return np.einsum("ij,ijp->jp", s_, bc)

    def zsolve(v: Array) -> Array:
        return np.einsum("iab,ib->ia", Hzz_inv, v)

    def matvec(x: Array) -> Array:
        x = np.asarray(x).reshape(k, p)
        return (np.einsum("jab,jb->ja", Hnn_d, x) - hnz(zsolve(hzn(x)))).reshape(-1)

    qn = np.einsum("ja,iab,jb->ij", N, Hzz_inv, N)  # n_j^T Hzz_i^-1 n_j
    wq = (W**2 * qn)[:, :, None] * bc
    diag = Hnn_d - np.matmul(wq.transpose(1, 2, 0), bc.transpose(1, 0, 2))
    del wq
    rhs = (gn - hnz(zsolve(gz))).reshape(-1)
    dn = _block_jacobi_cg(matvec, diag, rhs, rtol=rtol, max_iter=max_iter).reshape(k, p)
    dz = zsolve(gz - hzn(dn))
    return dz, dn


def _rotation_generators(Z: Array) -> Array:
    """Orthonormal basis (d(m-1), g) of the infinitesimal rotations of z_2..z_m about z_1 = 0."""
    Zr = Z[1:]
    d = Z.shape[1]
    if d == 3:
        G = np.stack([np.cross(np.eye(3)[a], Zr).ravel() for a in range(3)], axis=1)
    else:
        G = np.stack([-Zr[:, 1], Zr[:, 0]], axis=1).ravel()[:, None]
    Q, R = np.linalg.qr(G)
    keep = np.abs(np.diag(R)) > 1e-12 * (np.abs(R).max() + 1e-300)
    return np.asarray(Q[:, keep])


def position_covariance(
    D: Array, Z: Array, N: Array, C: Array, W: Array, *, free_offsets: bool, dof_extra: int = 0,
    method: str = "auto",
) -> Array:
    """Gauss-Newton covariance of the positions at a least-squares solution: (m, d, d).

    ``sigma^2 [S^+]_ii`` with S the Schur complement of the direction/offset blocks in
    ``J^T W J`` (the positions' information with the directions and offsets profiled out)
    and ``sigma^2 = cost / (observations - parameters + rotations)``. The pseudo-inverse puts
    the unobservable rotations (3 in space, 1 in a plane) in the minimum-norm gauge
    (z_1 = 0 fixes translation), so the covariances describe errors after the best rotation
    about the first position.

    Parameters
    ----------
    D, Z, N, C, W : data (m, k), positions (m, d), unit directions (k, d), offsets (k,),
        weights (m, k) (0 = unused entry).
    free_offsets : whether the C_j are estimated (adds one parameter per column).
    dof_extra : further parameters to subtract from the residual degrees of freedom.
    method : ``"dense"`` -- pseudo-inverse of the d(m-1) x d(m-1) Schur complement (SVD;
        the reference, O(m^3)); ``"schur"`` -- the same blocks without a pseudo-inverse,
        ``S^+ = (S + Q Q^T)^-1 - Q Q^T`` with Q the orthonormal rotation generators (the
        exact null space of S), the inverse's diagonal blocks from whichever side is
        smaller: a Cholesky inverse of ``S + QQ^T`` (d(m-1) <= p k) or, eliminating the
        positions, Woodbury's identity with the (p k + g) core
        ``[[-S_n, H_nz A^-1 Q], [Q^T A^-1 H_zn, I + Q^T A^-1 Q]]`` (A = the block-diagonal
        position information, S_n the directions' Schur complement), so the cost is
        O(m k min(dm, pk)) and memory O(m k); ``"auto"`` = ``"schur"``.

    Returns
    -------
    (m, d, d) covariance blocks (metres^2), the first one zero (the gauge origin).

    Notes
    -----
    ``"schur"`` and ``"dense"`` agree to rounding where S's numerical null space is exactly
    the rotations (every position seen by d independent directions); the tests check 1e-9.
    """
    check_choice(method, "method", ("auto", "dense", "schur"))
    D0 = np.where(W > 0, D, 0.0)
    Hzz, Hzn, Hnn, _, _, _, r = _normal_equations(D0, Z, N, C, W, free_offsets)
    mz, k, d, p = Hzn.shape
    Q = _rotation_generators(Z)
    g = Q.shape[1]
    n_obs = int((W > 0).sum())
    n_par = d * mz + p * k - g - dof_extra
    sigma2 = float(np.sum(W * r**2)) / max(n_obs - n_par, 1)
    idx = np.arange(mz)
    Hr = _flat(Hzn)
    if method == "dense" or (method in ("auto", "schur") and not _eliminate_positions(mz, d, k, p)):
        Hnn_inv = np.linalg.pinv(Hnn)  # (k, p, p) blocks: cheap either way
        X = np.matmul(Hzn, Hnn_inv[None])
        S = -(_flat(X) @ Hr.T)
        S4 = S.reshape(mz, d, mz, d)
        S4[idx, :, idx, :] += Hzz
        if method == "dense":
            cov = np.linalg.pinv(S, rcond=1e-10, hermitian=True)
        else:
            cov = _spd_inverse(S + Q @ Q.T)
            cov = np.linalg.pinv(S, rcond=1e-10, hermitian=True) if cov is None else cov - Q @ Q.T
        blocks = cov.reshape(mz, d, mz, d)[idx, :, idx, :]
    else:
        if np.min(np.linalg.eigvalsh(Hzz)[:, 0] / np.maximum(np.trace(Hzz, axis1=1, axis2=2), 1e-300)) < 1e-10:
            return position_covariance(D, Z, N, C, W, free_offsets=free_offsets, dof_extra=dof_extra,
                                       method="dense")  # a position is not seen by d directions
        A_inv = np.linalg.inv(Hzz)  # (mz, d, d): each position seen by >= d directions
        Qb = Q.reshape(mz, d, g)
        U = np.concatenate([Hr, Q], axis=1)  # (mz d, k p + g)
        Ub = U.reshape(mz, d, -1)
        Y = np.matmul(A_inv, Ub)  # A^-1 U, per position block: (mz, d, k p + g)
        Yf = Y.reshape(mz * d, -1)
        K = U.T @ Yf
        K[: k * p, : k * p] -= _block_diag(Hnn)
        K[k * p:, k * p:] += np.eye(g)
        YK = (Yf @ np.linalg.inv(K)).reshape(mz, d, -1)  # one (kp+g)^3 inverse, then BLAS
        blocks = A_inv - np.matmul(YK, Y.transpose(0, 2, 1)) - np.matmul(Qb, Qb.transpose(0, 2, 1))
    blocks = sigma2 * 0.5 * (blocks + blocks.transpose(0, 2, 1))
    return np.concatenate([np.zeros((1, d, d)), blocks], axis=0)


def _block_diag(H: Array) -> Array:
    """(k, p, p) blocks as the (k p, k p) block-diagonal matrix."""
    k, p, _ = H.shape
    out = np.zeros((k * p, k * p))
    idx = np.arange(k)
    out.reshape(k, p, k, p)[idx, :, idx, :] = H
    return out


def _spd_inverse(S: Array) -> Array | None:
    """Inverse of a symmetric positive definite matrix by Cholesky (LAPACK potrf / potri);
    None when S is not numerically positive definite (the caller falls back to a pseudo-inverse)."""
    import scipy.linalg as sla

    if not np.isfinite(S).all():
        return None
    try:
        c, _ = sla.cho_factor(S, lower=True, check_finite=False)
    except np.linalg.LinAlgError:
        return None
    inv, info = sla.lapack.dpotri(c, lower=1)
    if info != 0:
        return None
    inv = np.tril(inv) + np.tril(inv, -1).T
    d = np.diag(S)
    # a factor this close to singular means extra null directions beyond the rotations
    if np.max(np.abs(np.diag(inv)) * d) > 1e10:
        return None
    return np.asarray(inv)


def refine_lm(
    D: Array,
    positions: Array,
    directions: Array,
    offsets: Array,
    *,
    mask: NDArray[np.bool_] | None = None,
    free_offsets: bool = False,
    loss: str = "linear",
    delta: float = 1.0,
    lam: float = 1.0,
    adaptive: bool = True,
    max_iter: int = 200,
    tol: float = 1e-12,
    record_positions: bool = False,
    covariance: bool | None = None,
    linear_solver: str = "auto",
    covariance_method: str = "auto",
) -> RefineResult:
    """Levenberg-Marquardt on the product of spheres, paper 000 Algorithm 3.

    Each iteration linearises ``z_i . exp_{n_j}(T_j v_j) + C_j`` at ``v = 0`` (the exponential
    map keeps every ``n_j`` unit without constraints), solves
    ``(J^T W J + lambda diag(J^T W J)) dy = J^T W r`` (step 2; W = IRLS weights of the loss)
    and retracts ``n_j <- exp_{n_j}(T_j dv_j)``.

    Lambda schedule: starts at ``lam`` (the paper uses a constant 1). With ``adaptive`` a step
    that lowers the cost is accepted and lambda divided by 10; one that does not is rejected
    and lambda multiplied by 10 (so the cost never increases). Without it, lambda stays
    constant and every step is taken, as in the paper.

    Convergence: the relative cost decrease of an accepted step is below ``tol``, or the
    step is below ``tol`` relative to the parameters, or lambda exceeds 1e12.

    Parameters are as in :func:`refine_alternating`; ``lam`` > 0. Positions (m, d) and
    directions (k, d) may be 3-D (spheres) or 2-D (circles, the planar far-field problem).
    ``covariance``: also compute ``position_cov`` (:func:`position_covariance`); None =
    when its reduced system has at most :data:`COV_DIRECT_MAX` unknowns (above, it costs
    O(n^3) time and O(n^2) memory with n = min(d(m-1), p k)).
    ``linear_solver``: how each step's normal equations are solved -- ``"auto"`` (the
    smaller Schur side, CG above :data:`DIRECT_MAX`), ``"directions"`` (eliminate the
    directions: a d(m-1) system, the pre-0.2 behaviour and the benchmarks' dense
    baseline), ``"positions"`` or ``"cg"``. ``covariance_method``: see
    :func:`position_covariance`.
    Each step eliminates the smaller block-diagonal side (Schur complement, see
    :func:`_lm_step`): O(m k min(dm, pk)) time and O(m k) memory.
    """
    check_choice(loss, "loss", LOSSES)
    check_choice(linear_solver, "linear_solver", ("auto", "directions", "positions", "cg"))
    check_choice(covariance_method, "covariance_method", ("auto", "dense", "schur"))
    D0, obs, Z, N, C = _start(D, mask, positions, directions, offsets)
    cost = _cost(farfield_residuals(D0, Z, N, C), obs, loss, delta)
    hist, phist = [cost], ([Z.copy()] if record_positions else [])
    converged = False
    it = 0
    side = linear_solver
    if side == "auto":
        d_, p_ = Z.shape[1], Z.shape[1] - 1 + int(free_offsets)
        if min(d_ * (Z.shape[0] - 1), p_ * N.shape[0]) > DIRECT_MAX:
            side = "cg-factored"
    for it in range(1, max_iter + 1):  # noqa: B007 (it is reported after the loop)
        W = _weights(D0, Z, N, C, obs, loss, delta)
        Hzz, Hzn, Hnn, gz, gn, T, _ = _normal_equations(D0, Z, N, C, W, free_offsets,
                                                        coupling=side != "cg-factored")
        q = T.shape[2]
        while True:
            dz, dn = _lm_step(Hzz, Hzn, Hnn, gz, gn, lam, side="cg" if side == "cg-factored" else side)
            Zc = Z.copy()
            Zc[1:] += dz
            Nc = sphere_exp(N, np.einsum("jab,jb->ja", T, dn[:, :q]))
            Cc = C + dn[:, q] if free_offsets else C
            new = _cost(farfield_residuals(D0, Zc, Nc, Cc), obs, loss, delta)
            if not adaptive or new <= cost:
                break
            lam *= 10.0
            if lam > 1e12:
                break
        if adaptive and new > cost:
            converged = True  # no descent direction left at machine precision
            break
        small_step = np.sqrt(np.sum(dz**2) + np.sum(dn**2)) <= tol * (1.0 + np.sqrt(np.sum(Z**2)))
        rel = (cost - new) / max(cost, 1e-300)
        Z, N, C = Zc, Nc, Cc
        if adaptive:
            lam = max(lam / 10.0, 1e-12)
        hist.append(new)
        if record_positions:
            phist.append(Z.copy())
        done = abs(rel) <= tol or small_step or new == 0.0
        cost = new
        if done:
            converged = True
            break
    W = _weights(D0, Z, N, C, obs, loss, delta)
    if covariance is None:
        d_, p_ = Z.shape[1], Z.shape[1] - 1 + int(free_offsets)
        covariance = min(d_ * (Z.shape[0] - 1), p_ * N.shape[0]) <= COV_DIRECT_MAX
    cov = (position_covariance(D0, Z, N, C, W, free_offsets=free_offsets, method=covariance_method)
           if covariance else None)
    return RefineResult(Z, N, C, cost, it, converged, hist, phist, cov)


def farfield_crlb(positions: Array, directions: Array, sigma: float, *, free_offsets: bool = True) -> Array:
    """Cramer-Rao bound of the far-field model for the positions, gauge removed: (m, d, d).

    Fisher information ``J^T J / sigma^2`` of ``D_ij = z_i . n_j + C_j + e_ij`` with i.i.d.
    ``e_ij ~ N(0, sigma^2)`` (paper 000, section 3.3 noise model) in all unknowns: every
    ``z_i`` (d each, z_1 included), each ``n_j`` in d-1 tangent coordinates of the unit
    sphere (d = 3) or circle (d = 2) and, with ``free_offsets``, each ``C_j``. For d = 1
    (a linear array) ``directions`` are the projections ``u_j`` in [-1, 1], each a free
    scalar. The information is singular along the gauge (translations trade against
    ``C_j``, rotations of Z against those of N, and for d = 1 the scale ``x -> a x``,
    ``u -> u / a``); its pseudo-inverse is projected onto the complement of the gauge
    motions of the positions, which is the error that remains after aligning an estimate to
    the truth by such a motion (rigid; rigid + scale for d = 1). ``trace(sum_i cov_i) / m``
    bounds the expected aligned mean squared position error (to first order).

    Parameters
    ----------
    positions : (m, d) true z_i, metres; directions : (k, d) true unit n_j ((k, 1)
        projections for d = 1); sigma : noise standard deviation of D (metres);
    free_offsets : C_j unknown (True).

    Returns
    -------
    (m, d, d) covariance blocks of the aligned positions, metres^2.
    """
    Z = np.asarray(positions, dtype=float)
    N = np.asarray(directions, dtype=float)
    if Z.ndim == 1:
        Z = Z[:, None]
    if N.ndim == 1:
        N = N[:, None]
    m, d = Z.shape
    k = N.shape[0]
    if d == 1:
        T = np.ones((k, 1, 1))
    else:
        N = N / np.linalg.norm(N, axis=1, keepdims=True)
        T = _tangent(N)
    q = T.shape[2]
    n_par = d * m + q * k + (k if free_offsets else 0)
    J = np.zeros((m, k, n_par))
    for i in range(m):
        J[i, :, d * i : d * i + d] = N
    zt = np.einsum("ia,jab->ijb", Z, T)
    for j in range(k):
        J[:, j, d * m + q * j : d * m + q * j + q] = zt[:, j]
        if free_offsets:
            J[:, j, d * m + q * k + j] = 1.0
    J = J.reshape(m * k, n_par)
    cov = np.linalg.pinv(J.T @ J, rcond=1e-10, hermitian=True)[: d * m, : d * m] * sigma**2
    gens = [np.tile(np.eye(d)[a], (m, 1)).ravel() for a in range(d)]
    if d == 3:
        gens += [np.cross(np.eye(3)[a], Z).ravel() for a in range(3)]
    elif d == 2:
        gens += [np.column_stack([-Z[:, 1], Z[:, 0]]).ravel()]
    else:
        gens += [Z.ravel()]  # the scale of a linear array
    G = np.array(gens).T
    proj = np.eye(d * m) - G @ np.linalg.pinv(G)
    full = proj @ cov @ proj
    idx = np.arange(m)
    return np.asarray(full.reshape(m, d, m, d)[idx, :, idx, :])
