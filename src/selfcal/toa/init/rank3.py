"""The fast solver of the 004 rank-d problem: variable-projection LM, its default use, acceptance.

:func:`rank3_lm` (LM on the distance of the offset-corrected matrix to rank d, scalable:
subspace iteration, CG for missing entries), :func:`fast_offsets` (linear then exact model),
:func:`estimate_offsets` (the thesis's acceptance test and restarts). The model and its
notation are in :mod:`.rank3_model`.

Why this file is at ~600 lines: the LM on the rank-d distance and its two step structures
(the complete-data Gauss-Newton matrix kept as blocks, :class:`_Structure`, and the scalable
CG step) are one algorithm's pieces that share private arrays; the model and the joint
variant already live in their own files.
"""

from __future__ import annotations

import time
import warnings
from dataclasses import replace
from typing import Any

import numpy as np
import scipy.linalg
from scipy.linalg import cho_factor, cho_solve

from ..._checks import as_rng, check_choice
from ...errors import ConvergenceWarning, InputError
from ...optim.lm import levenberg_marquardt
from .rank3_joint import _rank3_lm_joint
from .rank3_model import (
    THESIS_ACCEPT,
    THESIS_TOL,
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
)
from .rank3_thesis import rank3_iteration

__all__ = ["estimate_offsets", "fast_offsets", "rank3_lm"]

_DENSE_JOINT_MAX = 256


def _centre_adj(Y: Array, axis: int, centring: str) -> Array:
    """Adjoint of :func:`_centre` along ``axis`` (mean centring is its own adjoint)."""
    if centring == "mean":
        return Y - Y.mean(axis=axis, keepdims=True)
    return np.concatenate([-Y.sum(axis=axis, keepdims=True), Y], axis=axis)


def _centre_gram(n: int, centring: str) -> tuple[Array, Array]:
    """``C^T C = I + F S F^T`` of the centring operator C on vectors of length n: (F, S)."""
    if centring == "mean":
        return np.full((n, 1), 1.0 / np.sqrt(n)), -np.eye(1)
    F = np.zeros((n, 2))
    F[0, 0] = 1.0
    F[1:, 1] = 1.0
    return F, np.array([[n - 2.0, -1.0], [-1.0, 0.0]])


def _tail_sub(M: Array, dim: int, Q: Array | None = None) -> tuple[float, Array, Array, Array, Array]:
    """:func:`_tail` by warm-started subspace iteration: no full eigendecomposition.

    Block power iteration on ``M M^T`` with ``k = d + 4`` vectors and a Rayleigh-Ritz step,
    started from the basis ``Q`` of the previous call (the corrected matrix changes little
    between LM trials), until the leading d-subspace moves by less than 1e-13 (sine of the
    largest principal angle), at most 60 sweeps. Each sweep costs three (I x J) x k products.
    Returns (cost, Ud, Vd, residual, basis for the next call).
    """
    m, n = M.shape
    k = min(dim + 4, m, n)
    if Q is None or Q.shape != (m, k):
        Q = np.linalg.qr(M @ np.random.default_rng(0).standard_normal((n, k)))[0]
    Ud_prev: Array | None = None
    Ud = Q[:, :dim]
    for _ in range(60):
        Q = np.linalg.qr(M @ (M.T @ Q))[0]
        Ub = np.linalg.svd(Q.T @ M, full_matrices=False)[0]
        Ud = Q @ Ub[:, :dim]
        if Ud_prev is not None and np.linalg.norm(Ud - Ud_prev @ (Ud_prev.T @ Ud), 2) < 1e-13:
            break
        Ud_prev = Ud
    B = Ud.T @ M
    resid = M - Ud @ B
    Vd = np.linalg.qr(B.T)[0]
    return float(np.sum(resid * resid)), Ud, Vd, resid, Q


def _damped_pcg(jtj: Any, chol: Any, hz: Array, damp: Array, g: Array, K: int, rtol: float = 1e-10) -> Array:
    """Solve ``(J^T J + diag(damp)) dx = -g`` by conjugate gradients (offsets + missing times).

    Preconditioner: the exact damped offset block (its Cholesky factor ``chol``) and the
    damped diagonal ``hz`` of the missing-time block. Relative tolerance ``rtol``, at most 500
    iterations; the LM gain test guards the rest. (A loose, gradient-scaled tolerance far from
    the minimum was measured to cost iterations: 83 instead of 12 at 300 units.)
    """
    from scipy.sparse.linalg import LinearOperator, cg

    n = g.size

    def mat(v: Array) -> Array:
        return np.asarray(jtj(v) + damp * v)

    def prec(v: Array) -> Array:
        return np.concatenate([cho_solve(chol, v[:K], check_finite=False), v[K:] / hz])

    op = LinearOperator((n, n), matvec=mat, dtype=float)
    pc = LinearOperator((n, n), matvec=prec, dtype=float)
    x0 = prec(-g)
    dx, _ = cg(op, -g, x0=x0, rtol=rtol, maxiter=500, M=pc)
    return np.asarray(dx)


def rank3_lm(
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
    """Levenberg-Marquardt with variable projection on (*): the fast solver for the 004 fixed point.

    Residual: ``N(M(p)) = M(p) - [M(p)]_d`` (the part of the corrected matrix outside its best
    rank-d approximation), with ``M = T + A(p) (+ Gamma(p))``. Jacobian (Kaufman's variable
    projection approximation, exact at zero residual): ``N(dM/dp_k) = (P u_k)(Q v_k)^T`` with
    P, Q the projectors off the leading singular subspaces, so
    ``J^T J = (U~^T U~) o (V~^T V~)`` (Hadamard) and ``J^T r = diag(U^T N(M) V)`` is the exact
    gradient of (*)/2. Marquardt damping with the usual gain-ratio update; steps that leave
    ``|p| <= 2 max t`` are refused (see :func:`_feasible`).

    Scaling. The (K x K) Gauss-Newton matrix, K = I+J-1, is formed from its block structure
    (the columns of the delays are unit vectors): two rank-I/J Gram products, ``O(I J (I+J))``,
    instead of ``O(I J K)`` per factor. The rank-d subspace comes from warm-started subspace
    iteration (:func:`_tail_sub`, ``O(I J d)`` per sweep), not from a full eigendecomposition.

    Missing entries (NaN) are extra unknowns (their times), each with its own rank-one
    Jacobian column (matrix completion inside the same projection), but no dense matrix has
    a row per missing entry: the damped Gauss-Newton system in (p, missing times) is solved by
    conjugate gradients, preconditioned by the exact (Cholesky-factored) p-block and the
    diagonal of the missing-time block; its products cost ``O(I J d)`` from the low-rank form
    of the projectors (``C^T (I - U U^T) C = I + F S F^T``). Memory ``O(I J + K^2)``. Their
    count adds to the I+J-1 unknowns of the identifiability condition. Up to
    ``_DENSE_JOINT_MAX`` unknowns in all, the dense joint step of :func:`_rank3_lm_joint`
    runs instead (cheaper there; the same iteration).

    Parameters
    ----------
    ranges : (I, J) metres; NaN = missing.
    dim : rank d (3 or 2).
    model : ``"exact"`` (keeps Gamma: distinct internal delays) or ``"linear"`` (thesis, Gamma = 0).
    p0 : initial p (metres); default the thesis random initialisation from ``rng``.
    max_iter : maximum LM iterations.
    xtol : stop when ``||dx|| <= xtol (||x|| + xtol)`` or F <= xtol ||M||_F.
    centring : ``"mean"`` (default, no special node) or ``"reference"`` (thesis (3.4)).
    rng : seed or Generator for the initialisation.
    abort_above : the early abort the thesis proposes (sec. 6.2), for restarts: once an
        iteration lowers (*) by less than 1 % while its square root (``extra["objective"]``)
        is still more than 0.1 % above this value (the best run so far), the run heads for a worse local
        minimum and stops (``converged=False``, ``extra["aborted"]=True``). None: never.
    frobenius : compute the result's ``frobenius`` (one more rank-d tail); False (NaN there)
        for a caller that uses only ``p`` (:func:`fast_offsets`' first stage).

    Returns
    -------
    Rank3Result with ``method="fast"``; ``frobenius`` is sqrt of (*) with reference centring,
    the quantity F (3.17) converges to; with missing entries ``extra["completed"]`` is the
    completed (I, J) matrix.
    """
    t0 = time.perf_counter()
    dim, R0, mask, I, J, K, n_miss = checked_rank_input(ranges, model, centring, dim)
    if K + n_miss <= _DENSE_JOINT_MAX:
        # small: one dense joint Gauss-Newton matrix and a full eigendecomposition are cheaper
        # than the iterative pieces below (measured crossover ~300 unknowns)
        return _rank3_lm_joint(R0, dim=dim, model=model, p0=p0, max_iter=max_iter, xtol=xtol,
                               centring=centring, rng=rng, abort_above=abort_above, frobenius=frobenius)
    missing, R, bound, p = _lm_start(R0, mask, K, p0, rng)
    Fr, Sr = _centre_gram(I, centring)
    Fc, Sc = _centre_gram(J, centring)

    def centred(X: Array) -> Array:
        return _centre(_centre(X, 0, centring), 1, centring)

    def adjoint(Y: Array) -> Array:
        return _centre_adj(_centre_adj(Y, 0, centring), 1, centring)

    def squared(pv: Array, Rt: Array) -> tuple[Array, Array, Array]:
        """D(p) of the (completed) times Rt, the p-factor e (dD/d(offset sum) = -2 e), dD/dt / 2."""
        delta, tau = _split(pv, I)
        c = delta[:, None] + tau[None, :]
        if model == "exact":
            e = Rt - c
            return e * e, e, e
        return Rt * Rt - 2 * Rt * c, Rt, Rt - c

    def times(xv: Array) -> Array:
        Rt = R.copy()
        if n_miss:
            Rt[missing] = xv[K:]
        return Rt

    def evaluate(xv: Array, Q: Array | None) -> tuple[float, Array, Array, Array, Array, Array]:
        M = centred(squared(xv[:K], times(xv))[0])
        cost, Ud, Vd, resid, Q = _tail_sub(M, dim, Q)
        return cost, Ud, Vd, resid, Q, M

    def metric(Ud: Array, Vd: Array) -> tuple[Array, Array, Array, Array]:
        """``C^T (I - Ud Ud^T) C = I + FA SA FA^T`` on rows, likewise on columns."""
        FA = np.hstack([Fr, _centre_adj(Ud, 0, centring)])
        SA = scipy.linalg.block_diag(Sr, -np.eye(dim))
        FB = np.hstack([Fc, _centre_adj(Vd, 0, centring)])
        SB = scipy.linalg.block_diag(Sc, -np.eye(dim))
        return FA, SA, FB, SB

    def gauss_newton(xv: Array, Ud: Array, Vd: Array, resid: Array) -> tuple[Any, Array, Any]:
        """p-block of J^T J from its structure, the gradient J^T r and the J^T J product.

        Complete data, mean centring: the matrix is returned as its :class:`_Structure`
        (the receiver blocks and the source-offset block's diagonal minus low rank), never
        formed (its (K, K) products cost most of an iteration for a long flight)."""
        _, e, ez = squared(xv[:K], times(xv))
        FA, SA, FB, SB = metric(Ud, Vd)
        W = -2.0 * e[:, 1:]  # tau columns of the receiver factors, (I, J-1)
        Vm = -2.0 * e.T  # delta columns of the source factors, (J, I)
        FW = FA.T @ W
        FV = FB.T @ Vm
        G = adjoint(resid)
        if not n_miss and centring == "mean":
            st = _Structure(I, W, FA, SA, FB, SB)
            if st.ok:
                BV1 = Vm[1:] + FB[1:] @ (SB @ FV)  # rows 1.. of BV below
                st.blocks(st.PA * (Vm.T @ Vm + FV.T @ SB @ FV), (W + FA @ (SA @ FW)) * BV1.T)
                return st, jt_complete(e, G), st
        Hu = np.empty((K, K))
        Hu[:I, :I] = np.eye(I) + FA @ SA @ FA.T
        Hu[:I, I:] = W + FA @ (SA @ FW)
        Hu[I:, :I] = Hu[:I, I:].T
        Hu[I:, I:] = W.T @ W + FW.T @ SA @ FW
        BV = Vm + FB @ (SB @ FV)
        Bm = np.eye(J) + FB @ SB @ FB.T
        Hv = np.empty((K, K))
        Hv[:I, :I] = Vm.T @ Vm + FV.T @ SB @ FV
        Hv[:I, I:] = BV[1:, :].T
        Hv[I:, :I] = BV[1:, :]
        Hv[I:, I:] = Bm[1:, 1:]
        Hu *= Hv

        def jt(Gm: Array) -> Array:
            parts = [jt_complete(e, Gm)]
            if n_miss:
                parts.append(2.0 * ez[missing] * Gm[missing])
            return np.concatenate(parts)

        def jtj(v: Array) -> Array:
            tau = np.concatenate([[0.0], v[I:K]])
            X = -2.0 * e * (v[:I, None] + tau[None, :])
            if n_miss:
                X[missing] += 2.0 * ez[missing] * v[K:]
            Gm = X + FA @ (SA @ (FA.T @ X))
            Gm += (Gm @ FB) @ SB @ FB.T
            return jt(Gm)

        g = jt(G)
        if not n_miss:
            return Hu, g, None  # reference centring, or a metric that is not a projector
        # diagonal of the missing-time block: (2 e_ij)^2 A_ii B_jj
        Ad = 1.0 + np.einsum("ia,ab,ib->i", FA, SA, FA)
        Bd = 1.0 + np.einsum("ja,ab,jb->j", FB, SB, FB)
        hz = 4.0 * ez[missing] ** 2 * Ad[missing[0]] * Bd[missing[1]]
        return Hu, g, (jtj, hz)

    def jt_complete(e: Array, Gm: Array) -> Array:
        """``J^T`` of the offsets (delta, tau without the first) applied to an (I, J) matrix."""
        eg = e * Gm
        return np.concatenate([-2.0 * eg.sum(axis=1), -2.0 * eg.sum(axis=0)[1:]])

    class Scalable(Rank3Model):
        Q: Array | None = None  # the subspace basis of the accepted point (warm start)

        def evaluate(self, xv: Array) -> tuple[float, tuple[Array, Array, Array, Array]]:
            cost, Ud, Vd, resid, Q, _ = evaluate(xv, self.Q)
            return cost, (Ud, Vd, resid, Q)

        def linearize(self, xv: Array, state: tuple[Array, Array, Array, Array]) -> _ScalableStep:
            Ud, Vd, resid, self.Q = state
            H, g, extra = gauss_newton(xv, Ud, Vd, resid)
            if isinstance(extra, _Structure):
                return _ScalableStep(xv, H, g, None, K, self.bound, structure=extra)
            return _ScalableStep(xv, H, g, extra, K, self.bound)

    x = np.concatenate([p, R[missing]])
    cost, _, _, _, Q, M = evaluate(x, None)
    rm = Scalable(bound, float(np.linalg.norm(M)), abort_above)
    rm.Q = Q
    rm.hist.append(float(np.sqrt(cost)))
    out = levenberg_marquardt(rm, x, max_iter=int(max_iter), xtol=xtol, ftol=0.0, lam0=rm.first_damping)
    x, it, converged, cost = out.x, out.iterations, out.converged, out.cost
    hist, steps, aborted = rm.hist, rm.steps, rm.aborted
    p = x[:K]
    Rx = times(x)
    # report the thesis's quantity: the distance to rank d of the reference-centred matrix, the
    # value F (3.17) converges to, so that the acceptance threshold means the same for both methods
    Dx = squared(p, Rx)[0]
    Mref = _centre(_centre(Dx, 0, "reference"), 1, "reference")
    F_ref = np.sqrt(_tail_sub(Mref, dim)[0]) if frobenius else np.nan
    res = _result(Rx, p, F_ref, hist, steps, it, converged, "fast", model, 0.0)
    return replace(res, seconds=time.perf_counter() - t0, extra=_lm_extra(Rx, n_miss, cost, aborted))


class _Structure:
    """What the complete-data Gauss-Newton matrix of :func:`rank3_lm` (mean centring) is made of.

    ``H = Hu o Hv`` with ``Hu = [I, W]^T P_A [I, W]``, ``Hv = [V, E]^T P_B [V, E]`` and the
    projectors ``P_A = I - F_A F_A^T`` (rank ``I - 1 - d``) and ``P_B = I - F_B F_B^T``. Its
    source-offset block is therefore diagonal minus low rank:
    ``H_tt = sum_a mu_a diag(u_a) (I - L L^T) diag(u_a) = diag(s) - Z Z^T`` with
    ``P_A = sum_a mu_a q_a q_a^T``, ``u_a = W^T q_a``, ``L = F_B[1:]`` and ``Z = [sqrt(mu_a) u_a o L]``
    (``(I - 1 - d)(1 + d)`` columns: 8 for 6 anchors in 3-D), which :meth:`solve` eliminates by
    the Woodbury identity in ``O(J r^2)`` instead of the ``O(K^3)`` Cholesky factor of the
    whole matrix (``K = I + J - 1``: 600+ for a UWB flight of 6 anchors). With the receiver
    blocks set (:meth:`blocks`) the object stands for H itself and :func:`rank3_lm` never forms
    it: products, diagonal, Frobenius norm and (for the Cholesky fallback) the dense matrix come
    from the blocks.
    """

    def __init__(self, I: int, W: Array, FA: Array, SA: Array, FB: Array, SB: Array) -> None:
        self.PA = PA = np.eye(I) + FA @ SA @ FA.T
        mu, q = np.linalg.eigh(0.5 * (PA + PA.T))
        keep = mu > 0.5  # a projector: eigenvalues 0 and 1 (to round-off)
        self.ok = bool(np.all(np.abs(mu[~keep]) < 1e-8) and np.all(np.abs(mu[keep] - 1.0) < 1e-8)
                       and np.allclose(SB, -np.eye(SB.shape[0])))
        self.I = I
        if self.ok:
            U = (W.T @ q[:, keep]) * np.sqrt(mu[keep])  # (J-1, r)
            L = FB[1:]
            self.s = np.sum(U * U, axis=1)
            self.Z = (U[:, :, None] * L[:, None, :]).reshape(U.shape[0], -1)

    def blocks(self, H11: Array, H12: Array) -> None:
        """The receiver-offset blocks ``H[:I, :I]``, ``H[:I, I:]``: with them this object is the
        whole matrix (``H[I:, I:] = diag(s) - Z Z^T``), used without forming it."""
        self.H11, self.H12 = H11, H12
        self.n = H11.shape[0] + H12.shape[1]

    def diagonal(self) -> Array:
        """``diag(H)`` (the Marquardt scaling)."""
        return np.concatenate([np.diag(self.H11), self.s - np.einsum("jr,jr->j", self.Z, self.Z)])

    def __matmul__(self, x: Array) -> Array:
        """``H x`` from the blocks, ``O(J r)``."""
        I = self.I
        x1, x2 = x[:I], x[I:]
        return np.concatenate([self.H11 @ x1 + self.H12 @ x2,
                               self.H12.T @ x1 + self.s * x2 - self.Z @ (self.Z.T @ x2)])

    def frobenius(self) -> float:
        """``|H|_F`` from the blocks: ``|diag(s) - Z Z^T|_F^2 = |s|^2 - 2 s.|Z_j|^2 + |Z^T Z|_F^2``."""
        z2 = np.einsum("jr,jr->j", self.Z, self.Z)
        ZtZ = self.Z.T @ self.Z
        tt = float(self.s @ self.s - 2.0 * self.s @ z2 + np.sum(ZtZ * ZtZ))
        return float(np.sqrt(max(float(np.sum(self.H11 ** 2)) + 2.0 * float(np.sum(self.H12 ** 2)) + tt, 0.0)))

    def dense(self) -> Array:
        """The formed matrix (the Cholesky fallback's)."""
        I = self.I
        H = np.empty((self.n, self.n))
        H[:I, :I], H[:I, I:], H[I:, :I] = self.H11, self.H12, self.H12.T
        H[I:, I:] = -(self.Z @ self.Z.T)
        H[I:, I:][np.diag_indices(self.n - I)] += self.s
        return H

    def solve(self, H: Any, damp: Array, b: Array) -> Array | None:
        """``(H + diag(damp)) x = b`` through the block structure; None where the damped matrix is
        not positive definite (the test the Cholesky factor made) or a factor fails. ``H`` is
        the formed matrix or this object (its blocks set)."""
        I = self.I
        Dd = self.s + damp[I:]
        if not np.all(Dd > 0):
            return None
        Zs = self.Z / Dd[:, None]
        try:
            cap = scipy.linalg.cho_factor(np.eye(self.Z.shape[1]) - self.Z.T @ Zs, check_finite=False)

            def cinv(v: Array) -> Array:  # (Dd - Z Z^T)^-1 v (Woodbury)
                v = v / Dd[:, None] if v.ndim == 2 else v / Dd
                return v + Zs @ scipy.linalg.cho_solve(cap, self.Z.T @ v, check_finite=False)

            H11, H12 = (H.H11, H.H12) if isinstance(H, _Structure) else (H[:I, :I], H[:I, I:])
            Y21 = cinv(H12.T)
            y2 = cinv(b[I:])
            Sm = H11 + np.diag(damp[:I]) - H12 @ Y21
            x1 = scipy.linalg.cho_solve(scipy.linalg.cho_factor(Sm, check_finite=False), b[:I] - H12 @ y2,
                                        check_finite=False)
        except np.linalg.LinAlgError:
            return None
        return np.concatenate([x1, y2 - Y21 @ x1])


#: relative residual ``|(H + lam D) x - b| / (|H + lam D|_F |x| + |b|)`` a structured solve
#: (:class:`_Structure`) must reach; above it the step falls back to the Cholesky factor
STRUCTURED_RTOL = 1e-12


class _ScalableStep:
    """The damped step of :func:`rank3_lm`: the p-block by Cholesky (or, complete data, through
    its structure, :class:`_Structure`), with missing times by preconditioned CG
    (:func:`_damped_pcg`); a step leaving the feasible box is refused."""

    def __init__(self, x: Array, H: Any, g: Array, coupled: Any, K: int, bound: float,
                 structure: _Structure | None = None) -> None:
        # H: the formed (K, K) matrix, or the _Structure itself (complete data, never formed)
        self.x, self.H, self.g, self.coupled, self.K, self.bound = x, H, g, coupled, K, bound
        dg = H.diagonal() if isinstance(H, _Structure) else np.diag(H).copy()
        if coupled is not None:
            dg = np.concatenate([dg, coupled[1]])
        dg[dg <= 0] = 1.0
        self.dg = dg
        self.last = np.zeros_like(x)
        self.gnorm = float(np.linalg.norm(g))
        self.structure = structure if structure is not None and structure.ok else None
        if self.structure is None:
            self.hnorm = 0.0
        else:
            self.hnorm = H.frobenius() if isinstance(H, _Structure) else float(np.linalg.norm(H))

    def _structured(self, lam: float) -> Array | None:
        """The damped step through :class:`_Structure`, or None (then the Cholesky factor decides)."""
        assert self.structure is not None
        damp = lam * self.dg[:self.K]
        dx = self.structure.solve(self.H, damp, -self.g)
        if dx is None or not np.isfinite(dx).all():
            return None
        r = self.H @ dx + damp * dx + self.g
        scale = (self.hnorm + float(np.max(damp))) * float(np.linalg.norm(dx)) + float(np.linalg.norm(self.g))
        return dx if float(np.linalg.norm(r)) <= STRUCTURED_RTOL * scale else None

    def step(self, lam: float) -> Array | None:
        K, dg = self.K, self.dg
        dx = self._structured(lam) if self.structure is not None else None
        if dx is not None:
            if not _feasible(self.x + dx, self.bound):
                return None
            self.last = dx
            return np.asarray(dx)
        Hm = self.H.dense() if isinstance(self.H, _Structure) else self.H.copy()
        Hm[np.diag_indices(K)] += lam * dg[:K]
        try:
            cf = cho_factor(Hm, check_finite=False)
        except np.linalg.LinAlgError:
            return None
        if self.coupled is None:
            dx = -cho_solve(cf, self.g, check_finite=False)
        else:
            dx = _damped_pcg(self.coupled[0], cf, dg[K:] * (1.0 + lam), dg * lam, self.g, K)
        if not _feasible(self.x + dx, self.bound):
            return None
        self.last = dx
        return np.asarray(dx)

    def predicted(self, dx: Array) -> float:
        Hdx = self.H @ dx[:self.K] if self.coupled is None else self.coupled[0](dx)
        # (*) is a sum of squares: twice the decrease of the model of its half
        return float(2 * (-(self.g @ dx) - 0.5 * dx @ Hdx))


def fast_offsets(
    ranges: Any,
    *,
    dim: int = 3,
    model: str = "exact",
    p0: Any = None,
    max_iter: int = 100,
    rng: np.random.Generator | int | None = None,
    abort_above: float | None = None,
) -> Rank3Result:
    """One start of the default fast method: LM on the linear (Gamma = 0) model, then on ``model``.

    The linear model's objective is the distance of an affine family to the rank-d matrices,
    and from a random start it lands in the basin of the true p more often than the exact
    (quadratic) model; we measured on 12 x 12 x 2 m setups with 12 units 48/72 vs 40/72
    starts with equal delays, 64/72 vs 39/72 with distinct delays. The second stage removes
    the Gamma bias (distinct delays) and polishes to machine precision. Both stages use mean
    centring. ``iterations`` counts both stages. With missing entries only the second stage runs.
    ``abort_above`` (the early abort of :func:`rank3_lm`) applies to the last stage only (the
    linear stage's objective is biased by Gamma and not comparable).
    """
    if np.isnan(np.asarray(ranges, dtype=float)).any():
        # with missing entries the biased linear stage lets the free entries absorb Gamma and
        # leaves the exact stage in a wrong basin: exact model only
        return rank3_lm(ranges, dim=dim, model=model, p0=p0, max_iter=max_iter, rng=rng, abort_above=abort_above)
    first = rank3_lm(ranges, dim=dim, model="linear", p0=p0, max_iter=max_iter, rng=rng,
                     abort_above=abort_above if model == "linear" else None, frobenius=model == "linear")
    if model == "linear":
        return first
    second = rank3_lm(ranges, dim=dim, model=model, p0=first.p, max_iter=max_iter, abort_above=abort_above)
    return replace(
        second,
        iterations=first.iterations + second.iterations,
        total_iterations=first.iterations + second.iterations,
        seconds=first.seconds + second.seconds,
        history=np.concatenate([first.history, second.history]),
        steps=np.concatenate([first.steps, second.steps]),
    )


# ----------------------------------------------------------------------------- with acceptance


def estimate_offsets(
    ranges: Any,
    *,
    dim: int = 3,
    method: str = "fast",
    model: str | None = None,
    accept: float | None = THESIS_ACCEPT,
    max_restarts: int | None = None,
    early_abort: bool = True,
    lam: float = 0.0,
    max_iter: int | None = None,
    tol: float = THESIS_TOL,
    rng: np.random.Generator | int | None = None,
) -> Rank3Result:
    """Onset times and internal delays with the thesis's acceptance test and restarts (004 sec. 4.3, 6.2).

    Runs :func:`fast_offsets` (``method="fast"``, first from p = 0, then from thesis random
    starts) or :func:`rank3_iteration` (``"faithful"``, thesis random starts). A run whose final
    Frobenius norm F (3.17) exceeds ``accept`` has converged to a local minimum and is
    restarted from a new random initialisation (the thesis's future-work proposal, sec. 6.2;
    with ``early_abort`` a faithful run is stopped as soon as it is almost converged above
    ``accept``), at most ``max_restarts`` times. If no run is accepted, the one with the
    smallest F is returned with ``accepted=False`` and a :class:`ConvergenceWarning`.
    ``accept=None`` (noisy data, where no absolute threshold fits) runs all
    ``max_restarts + 1`` starts and returns the smallest F.

    Parameters
    ----------
    ranges : (I, J) times times the speed c, metres (rows = receivers); NaN = missing is
        supported by the fast method only.
    dim : 3 (thesis) or 2.
    method : ``"fast"`` or ``"faithful"``.
    model : ``"exact"`` / ``"linear"``; default ``"exact"`` for fast, ``"linear"`` for faithful
        (the faithful iteration implements only the thesis's Gamma = 0 model).
    accept : acceptance threshold on F, m^2; default 8e-7 s^2 x (343 m/s)^2 = 0.094 m^2 (thesis,
        noise-free; with timing noise F grows with the noise and the threshold must follow).
    max_restarts : restarts after rejected runs (default 30 fast, 10 faithful; 5 with accept=None).
    early_abort : the faithful iteration's early restart (``abort_above=accept``).
    lam, tol : passed to the faithful iteration.
    max_iter : iteration cap per run (default 1e6 faithful, 100 per stage fast).
    rng : seed or Generator.

    Returns
    -------
    Rank3Result; ``restarts`` says how many restarts were needed, ``total_iterations`` counts all runs.
    """
    t0 = time.perf_counter()
    check_choice(method, "method", ("fast", "faithful"))
    model = model or ("exact" if method == "fast" else "linear")
    check_choice(model, "model", ("exact", "linear"))
    if method == "faithful" and model != "linear":
        raise InputError("the faithful thesis iteration implements only model='linear' (Gamma = 0)")
    if max_restarts is None:
        max_restarts = 5 if accept is None else (30 if method == "fast" else 10)
    if max_restarts < 0:
        raise InputError(f"max_restarts must be >= 0, got {max_restarts}")
    shape = np.shape(ranges)
    gen = as_rng(rng)
    best: Rank3Result | None = None
    total = 0
    for attempt in range(int(max_restarts) + 1):
        if method == "fast":
            # p = 0 first: a deterministic start that lands in the right basin at least as often
            # as a random one; the restarts use the thesis random initialisation
            p0 = np.zeros(shape[0] + shape[1] - 1) if attempt == 0 else None
            res = fast_offsets(ranges, dim=dim, model=model, max_iter=max_iter or 100, rng=gen, p0=p0)
        else:
            res = rank3_iteration(
                ranges, dim=dim, lam=lam, tol=tol, max_iter=max_iter or 1_000_000, rng=gen,
                abort_above=accept if early_abort else None,
            )
        total += res.iterations
        ok = None if accept is None else bool(np.isfinite(res.frobenius) and res.frobenius <= accept)
        res = replace(res, accepted=ok, restarts=attempt, total_iterations=total)
        if best is None or res.frobenius < best.frobenius:
            best = res
        if ok:
            return replace(res, seconds=time.perf_counter() - t0)
    assert best is not None
    if accept is not None:
        warnings.warn(
            f"no run of the rank-{dim} offset estimation reached F <= {accept:g} m^2 in {max_restarts + 1} "
            f"runs (best F = {best.frobenius:.3g} m^2); noisy data need a larger 'accept' or accept=None",
            ConvergenceWarning,
            stacklevel=2,
        )
    return replace(best, total_iterations=total, seconds=time.perf_counter() - t0)

