"""The dense joint LM of the 004 rank-d problem (offsets + missing entries as dense unknowns).

Used by :func:`selfcal.toa.init.rank3.rank3_lm` for small problems (up to
``_DENSE_JOINT_MAX`` unknowns, where one dense Gauss-Newton matrix and a full
eigendecomposition are cheaper) and by the tests as the reference of the scalable path.
"""

from __future__ import annotations

import time
from dataclasses import replace
from typing import Any

import numpy as np
from scipy.linalg import eigh
from scipy.linalg.lapack import dpotrf as potrf
from scipy.linalg.lapack import dpotrs as potrs

from ...optim.lm import levenberg_marquardt
from .mds_core import SUBSET_EIG_MIN
from .rank3_model import (
    Array,
    Rank3Model,
    Rank3Result,
    _centre,
    _feasible,
    _lm_extra,
    _lm_start,
    _result,
    _split,
    checked_rank_input,
    offset_matrix,
)

__all__: list[str] = []


def _rank1_factors(
    R: Array, p: Array, model: str, missing: tuple[Any, ...], centring: str = "reference"
) -> tuple[Array, Array]:
    """Columns of the Jacobian of the corrected matrix as rank-one pairs: dM/dx_k = U[:, k] V[:, k]^T.

    x = [p, missing t_ij]. Before centring, delta_k changes row k of D by ``-2 e_k.``, tau_l
    column l by ``-2 e_.l`` and a missing t_ij the single entry D_ij by ``2 e_ij``, with
    e = t - delta_i - tau_j (exact model, Gamma included) or e = t (linear model: the columns
    of W). Double centring maps a rank-one ``u v^T`` to ``(L u)(L v)^T``.
    """
    I, J = R.shape
    K = I + J - 1
    mi, mj = missing
    if model == "exact":
        delta, tau = _split(p, I)
        e = R - delta[:, None] - tau[None, :]
    else:
        e = R
    n = K + mi.size
    Uf = np.zeros((I, n))
    Vf = np.zeros((J, n))
    Uf[np.arange(I), np.arange(I)] = 1.0
    Vf[:, :I] = -2 * e.T
    Uf[:, I:K] = -2 * e[:, 1:]
    Vf[np.arange(1, J), np.arange(I, K)] = 1.0
    if mi.size:
        # d/dt_ij of t^2 - 2 t (delta + tau) (linear) and of (t - delta - tau)^2 (exact) agree
        delta, tau = _split(p, I)
        cols = np.arange(K, n)
        Uf[mi, cols] = 2 * (R[mi, mj] - delta[mi] - tau[mj])
        Vf[mj, cols] = 1.0
    return _centre(Uf, 0, centring), _centre(Vf, 0, centring)


def _tail(M: Array, dim: int) -> tuple[float, Array, Array, Array]:
    """Cost sum_{k>d} sigma_k^2, the leading singular vectors and the residual M - M_d.

    The leading left subspace comes from the eigendecomposition of the smaller Gram matrix
    (2-3x cheaper than an SVD); the residual is formed by projection, not from the tail
    eigenvalues, so the cost keeps its accuracy down to the rounding of M. From
    :data:`~selfcal.toa.init.mds_core.SUBSET_EIG_MIN` rows on only the top ``dim`` eigenpairs
    are computed (LAPACK ``syevr`` on a subset; 119 x 119, the 120-unit workload: 0.30 vs
    0.75 ms, measured single-threaded).
    """
    if M.shape[0] > M.shape[1]:
        c, Vd, Ud, r = _tail(M.T, dim)
        return c, Ud, Vd, r.T
    G = M @ M.T
    n = G.shape[0]
    if n >= SUBSET_EIG_MIN and dim < n and np.isfinite(G).all():
        Ud = eigh(G, subset_by_index=[n - dim, n - 1], driver="evr", check_finite=False)[1]
    else:
        Ud = np.linalg.eigh(G)[1][:, -dim:]
    B = Ud.T @ M
    resid = M - Ud @ B
    Vd, _ = np.linalg.qr(B.T)
    return float(np.sum(resid * resid)), Ud, Vd, resid


def _rank3_lm_joint(
    ranges: Any,
    *,
    dim: int = 3,
    model: str = "exact",
    p0: Any = None,
    max_iter: int = 100,
    xtol: float = 1e-12,
    centring: str = "mean",
    rng: np.random.Generator | int | None = None,
    abort_above: float | None = None,
    frobenius: bool = True,
) -> Rank3Result:
    """:func:`~selfcal.toa.init.rank3.rank3_lm` (same problem, parameters and result) with a dense joint step.

    The missing entries are dense unknowns beside the I+J-1 offsets: one
    (I+J-1+missing)^2 Gauss-Newton matrix (Hadamard form, ``_JointStep``) and a full
    eigendecomposition per trial, cheaper than the scalable path's iterative pieces up to
    ``_DENSE_JOINT_MAX`` unknowns, where :func:`~selfcal.toa.init.rank3.rank3_lm` calls it;
    the tests also use it as the reference of the scalable path on small cases.
    """
    t0 = time.perf_counter()
    dim, R0, mask, I, J, K, n_miss = checked_rank_input(ranges, model, centring, dim)
    missing, R, bound, p = _lm_start(R0, mask, K, p0, rng)
    x = np.concatenate([p, R[missing]])

    def unpack(xv: Array) -> tuple[Array, Array]:
        if not n_miss:
            return R, xv
        Rx = R.copy()
        Rx[missing] = xv[K:]
        return Rx, xv[:K]

    class Joint(Rank3Model):
        def evaluate(self, xv: Array) -> tuple[float, tuple[Array, Array, Array, Array, Array]]:
            if np.array_equal(xv, x):  # the start: evaluated once, below
                return first
            Rt, pt = unpack(xv)
            cost, Ud, Vd, resid = _tail(offset_matrix(Rt, pt, model=model, centring=centring), dim)
            return cost, (Rt, pt, Ud, Vd, resid)

        def linearize(self, xv: Array, state: tuple[Array, Array, Array, Array, Array]) -> _JointStep:
            return _JointStep(xv, state, model, missing, centring, self.bound, factors)

    Rx, p = unpack(x)
    # the linear model without missing entries: the Jacobian's rank-one factors do not depend
    # on p (e = t), formed once for the run (the same arrays each iteration would form)
    factors = _rank1_factors(Rx, p, model, missing, centring) if model != "exact" and not n_miss else None
    M = offset_matrix(Rx, p, model=model, centring=centring)
    rm = Joint(bound, float(np.linalg.norm(M)), abort_above)
    c0, U0, V0, r0 = _tail(M, dim)
    first = (c0, (Rx, p, U0, V0, r0))  # the driver's first evaluation (at x) and the history's first F
    rm.hist.append(float(np.sqrt(c0)))
    out = levenberg_marquardt(rm, x, max_iter=int(max_iter), xtol=xtol, ftol=0.0, lam0=rm.first_damping)
    Rx, p = out.state[0], out.state[1]
    it, converged, cost = out.iterations, out.converged, out.cost
    hist, steps, aborted = rm.hist, rm.steps, rm.aborted
    # report the thesis's quantity: the distance to rank d of the reference-centred matrix, the
    # value F (3.17) converges to, so that the acceptance threshold means the same for both methods
    F_ref = (np.sqrt(_tail(offset_matrix(Rx, p, model=model, centring="reference"), dim)[0]) if frobenius
             else np.nan)
    res = _result(Rx, p, F_ref, hist, steps, it, converged, "fast", model, 0.0)
    return replace(res, seconds=time.perf_counter() - t0, extra=_lm_extra(Rx, n_miss, cost, aborted))


class _JointStep:
    """The dense joint Gauss-Newton matrix of offsets and missing times (Hadamard form)."""

    def __init__(self, x: Array, state: tuple[Array, Array, Array, Array, Array], model: str,
                 missing: tuple[Any, ...], centring: str, bound: float,
                 factors: tuple[Array, Array] | None = None) -> None:
        Rx, p, Ud, Vd, resid = state
        Uf, Vf = _rank1_factors(Rx, p, model, missing, centring) if factors is None else factors
        Pu = Uf - Ud @ (Ud.T @ Uf)
        Pv = Vf - Vd @ (Vd.T @ Vf)
        self.H = (Pu.T @ Pu) * (Pv.T @ Pv)
        self.g = np.einsum("ik,ik->k", Uf, resid @ Vf)
        self.dg = np.diag(self.H).copy()
        self.dg[self.dg <= 0] = 1.0
        self.x, self.bound = x, bound
        self.last = np.zeros_like(x)
        self.gnorm = float(np.linalg.norm(self.g))

    def step(self, lam: float) -> Array | None:
        # cho_factor / cho_solve's LAPACK calls (potrf, potrs) on H + lam diag(dg), without their wrappers' copies
        Hm = self.H.copy()
        Hm[np.diag_indices_from(Hm)] += lam * self.dg
        if not (np.isfinite(Hm).all() and np.isfinite(self.g).all()):
            raise ValueError("array must not contain infs or NaNs")  # as cho_factor's / cho_solve's check
        c, info = potrf(Hm, lower=0, overwrite_a=1, clean=0)
        if info != 0:  # not positive definite (cho_factor: LinAlgError)
            return None
        sol, info = potrs(c, self.g, lower=0)
        dx = -sol
        if not _feasible(self.x + dx, self.bound):
            return None
        self.last = dx
        return np.asarray(dx)

    def predicted(self, dx: Array) -> float:
        # (*) is a sum of squares: twice the decrease of the model of its half
        return float(2 * (-(self.g @ dx) - 0.5 * dx @ (self.H @ dx)))
