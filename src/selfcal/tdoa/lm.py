"""Levenberg-Marquardt on the product of spheres, paper 000 Algorithm 3 (Schur / CG steps)."""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from .._checks import check_choice
from ..geometry import sphere_exp
from ..optim.lm import Model, levenberg_marquardt
from ..optim.structure import FARFIELD_COV_MAX, FARFIELD_DIRECT_MAX
from ..robust import LOSSES
from .covariance import position_covariance
from .model import (
    RefineResult,
    _cost,
    _eliminate_positions,
    _flat,
    _normal_equations,
    _start,
    _weights,
    farfield_residuals,
)

Array = NDArray[np.float64]


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
    # Marquardt damping lam diag(H) plus a ridge of 1e-12 times the largest diagonal entry of
    # each kind of unknown (position axes, direction tangents, offsets): both scale with the
    # unit of the data, so the step does not depend on it (an absolute ridge would)
    dnn, dzz = np.einsum("jaa->ja", Hnn), np.einsum("iaa->ia", Hzz)
    ridge_n = 1e-12 * np.maximum(dnn.max(axis=0), np.finfo(float).tiny)
    ridge_z = 1e-12 * np.maximum(dzz.max(axis=0), np.finfo(float).tiny)
    Hnn_d = Hnn + (lam * dnn + ridge_n)[:, :, None] * eye_p
    Hzz_d = Hzz + (lam * dzz + ridge_z)[:, :, None] * eye_d
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
        dz = np.asarray(np.linalg.solve(S, rhs.reshape(-1)), dtype=np.float64).reshape(mz, d)
        dn = np.einsum("jab,jb->ja", Hnn_inv, gn - (dz.reshape(-1) @ Hr).reshape(k, p))
        return dz, dn
    Hzz_inv = np.linalg.inv(Hzz_d)  # (mz, d, d)
    Yr = _flat(np.matmul(Hzz_inv[:, None], Hzn))  # Hzz^-1 Hzn as (mz d, k p)
    S = -(Hr.T @ Yr)  # (k p, k p)
    S4 = S.reshape(k, p, k, p)
    idx = np.arange(k)
    S4[idx, :, idx, :] += Hnn_d
    rhs = gn.reshape(-1) - Yr.T @ gz.reshape(-1)
    dn = np.asarray(np.linalg.solve(S, rhs), dtype=np.float64)
    dz = np.einsum("iab,ib->ia", Hzz_inv, gz) - (Yr @ dn).reshape(mz, d)
    return dz, dn.reshape(k, p)


#: the far-field step's thresholds (reduced system solved directly / covariance by default):
#: :mod:`selfcal.optim.structure`, with the measurements behind them
DIRECT_MAX = FARFIELD_DIRECT_MAX
COV_DIRECT_MAX = FARFIELD_COV_MAX


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


def _small_step(dz: Array, dn: Array, Z: Array, C: Array, q: int, tol: float) -> bool:
    """Scale-free step test: each kind of unknown against its own size.

    Positions and offsets are lengths (the matrix's unit): their step is compared with
    ``L = sqrt(|Z|^2 + |C|^2)`` (``Z_0 = 0``, so ``|Z|`` is the array's extent); the direction
    steps are angles (radians) compared with ``|N| = sqrt(k)``. Rescaling the data (m -> mm)
    scales ``dz``, the offset steps and ``L`` alike and leaves the angles, so the test, like
    the Marquardt-damped step and the relative cost test, does not depend on the unit.
    """
    k = dn.shape[0]
    length = float(np.sqrt(np.sum(Z**2) + np.sum(C**2)))
    moved = float(np.sqrt(np.sum(dz**2) + np.sum(dn[:, q:] ** 2)))
    turned = float(np.sqrt(np.sum(dn[:, :q] ** 2)))
    return moved <= tol * length and turned <= tol * np.sqrt(k)


#: damping trials per iteration: the Marquardt factor grows by 2, 4, 8, ... per refused trial,
#: so 24 trials span a factor 2^300 (the former x10 rule stopped past 1e12)
_TRIALS = 24


class _FarfieldModel(Model):
    """The far-field model for :func:`selfcal.optim.levenberg_marquardt`.

    The point is ``[Z (m d), N (k d), C (k)]`` flat; a step is ``[dz ((m-1) d), dn (k p)]``
    (``Z_0 = 0`` fixed, tangent coordinates of the directions, offsets last when free),
    retracted by the exponential map.
    """

    def __init__(self, D0: Array, obs: Any, zshape: tuple[int, ...], nshape: tuple[int, ...], loss: str,
                 delta: float, free_offsets: bool, side: str) -> None:
        self.D0, self.obs, self.loss, self.delta = D0, obs, loss, delta
        self.free, self.side = free_offsets, side
        (self.m, self.d), self.k = zshape, nshape[0]

    def pack(self, Z: Array, N: Array, C: Array) -> Array:
        return np.concatenate([Z.ravel(), N.ravel(), C])

    def unpack(self, x: Array) -> tuple[Array, Array, Array]:
        md, kd = self.m * self.d, self.k * self.d
        return x[:md].reshape(self.m, self.d), x[md:md + kd].reshape(self.k, self.d), x[md + kd:]

    def evaluate(self, x: Array) -> tuple[float, None]:
        Z, N, C = self.unpack(x)
        return _cost(farfield_residuals(self.D0, Z, N, C), self.obs, self.loss, self.delta), None

    def linearize(self, x: Array, state: None) -> Any:
        Z, N, C = self.unpack(x)
        W = _weights(self.D0, Z, N, C, self.obs, self.loss, self.delta)
        Hzz, Hzn, Hnn, gz, gn, T, _ = _normal_equations(self.D0, Z, N, C, W, self.free,
                                                        coupling=self.side != "cg-factored")
        self._T = T
        return _FarfieldStep(self, Hzz, Hzn, Hnn, gz, gn, "cg" if self.side == "cg-factored" else self.side)

    def split(self, dx: Array) -> tuple[Array, Array]:
        n = (self.m - 1) * self.d
        return dx[:n].reshape(self.m - 1, self.d), dx[n:].reshape(self.k, -1)

    def retract(self, x: Array, dx: Array) -> Array:
        Z, N, C = self.unpack(x)
        dz, dn = self.split(dx)
        q = self._T.shape[2]
        Zc = Z.copy()
        Zc[1:] += dz
        Nc = sphere_exp(N, np.einsum("jab,jb->ja", self._T, dn[:, :q]))
        Cc = C + dn[:, q] if self.free else C
        return self.pack(Zc, Nc, Cc)

    def small_step(self, x: Array, dx: Array, xtol: float) -> bool:
        Z, _, C = self.unpack(x)
        dz, dn = self.split(dx)
        return _small_step(dz, dn, Z, C, self._T.shape[2], xtol)

    def stationary(self, lin: Any, cost: float) -> bool:
        return True



class _FarfieldStep:
    """The far-field step solver (:func:`_lm_step`, Schur over the smaller side or CG) at one
    linearisation; ``gnorm`` 0: a refused step at any damping is convergence (no descent left)."""

    gnorm = 0.0

    def __init__(self, model: _FarfieldModel, Hzz: Array, Hzn: Any, Hnn: Array, gz: Array, gn: Array,
                 side: str) -> None:
        self.model, self.Hzz, self.Hzn, self.Hnn, self.gz, self.gn, self.side = model, Hzz, Hzn, Hnn, gz, gn, side
        self.dzz, self.dnn = np.einsum("iaa->ia", Hzz), np.einsum("jaa->ja", Hnn)
        self.ridge_z = 1e-12 * np.maximum(self.dzz.max(axis=0), np.finfo(float).tiny)
        self.ridge_n = 1e-12 * np.maximum(self.dnn.max(axis=0), np.finfo(float).tiny)
        self.lam = 0.0

    def step(self, lam: float) -> Array:
        self.lam = lam
        dz, dn = _lm_step(self.Hzz, self.Hzn, self.Hnn, self.gz, self.gn, lam, side=self.side)
        return np.concatenate([dz.ravel(), dn.ravel()])

    def predicted(self, dx: Array) -> float:
        # cost = sum rho ~ |r - J dx|_W^2: decrease 2 g.dx - dx.H dx, where
        # (H + damping) dx = g gives dx.H dx = g.dx - dx.damping.dx
        dz, dn = self.model.split(dx)
        damp = (np.sum((self.lam * self.dzz + self.ridge_z) * dz**2)
                + np.sum((self.lam * self.dnn + self.ridge_n) * dn**2))
        return float(np.sum(self.gz * dz) + np.sum(self.gn * dn) + damp)


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
    lam: float | None = None,
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

    Lambda schedule: with ``adaptive`` the driver's (:mod:`selfcal.optim.lm`: a step that
    does not lower the cost is refused and lambda raised, Nielsen's gain-ratio update after an
    accepted one), starting at ``lam`` (default 1e-4, as every model of the driver; from the
    paper's 1 the gain-ratio rule, at most /3 per step, took 7 -> 10 iterations on a 20 x 40
    network). Without ``adaptive``, lambda stays ``lam`` (default 1, the paper's constant)
    and every step is taken, as in the paper.

    Convergence: the relative cost decrease of an accepted step is below ``tol``, or the
    step is below ``tol`` relative to the parameters (lengths against the array's extent,
    direction angles against ``sqrt(k)``: the test is unit-free), or no damped trial lowers
    the cost.

    Parameters are as in :func:`refine_alternating`; ``lam`` > 0 or None. Positions (m, d) and
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
    side = linear_solver
    if side == "auto":
        d_, p_ = Z.shape[1], Z.shape[1] - 1 + int(free_offsets)
        if min(d_ * (Z.shape[0] - 1), p_ * N.shape[0]) > DIRECT_MAX:
            side = "cg-factored"
    model = _FarfieldModel(D0, obs, Z.shape, N.shape, loss, delta, free_offsets, side)
    out = levenberg_marquardt(model, model.pack(Z, N, C), max_iter=max_iter, xtol=tol, ftol=tol,
                              lam0=lam if lam is not None else (1e-4 if adaptive else 1.0), trials=_TRIALS,
                              adaptive=adaptive, history=True)
    Z, N, C = model.unpack(out.x)
    cost, hist = out.cost, list(out.history)
    phist = [model.unpack(x)[0].copy() for x in out.path] if record_positions else []
    converged, it = out.converged, out.iterations
    W = _weights(D0, Z, N, C, obs, loss, delta)
    if covariance is None:
        d_, p_ = Z.shape[1], Z.shape[1] - 1 + int(free_offsets)
        covariance = min(d_ * (Z.shape[0] - 1), p_ * N.shape[0]) <= COV_DIRECT_MAX
    # a robust fit's covariance: the Gauss-Newton information of the entries used and the
    # M-estimator's variance factor (not the IRLS weights, which shrink the cut residuals)
    cov = (position_covariance(D0, Z, N, C, W if loss == "linear" else obs.astype(float),
                               free_offsets=free_offsets, method=covariance_method, loss=loss, delta=delta)
           if covariance else None)
    return RefineResult(Z, N, C, cost, it, converged, hist, phist, cov)
