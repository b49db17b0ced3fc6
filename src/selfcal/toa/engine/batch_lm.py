"""Levenberg-Marquardt on many starts of one small range problem at once: the search's race.

The race of :func:`selfcal.toa.search.search` refines a few dozen starts of the same small
problem (12 receivers x 6 sources with both offsets: 72 ranges, 72 parameters) in rungs of
a few iterations each. One start at a time, an iteration costs Python overhead, not
arithmetic (:mod:`selfcal.toa.engine.dense_lm`: ~0.2 ms, most of it in forming the gauge
projector, the evaluation and the LAPACK call). Here every start advances in lockstep and
each numpy call serves all of them, and the normal equations use the bipartite structure
of the model instead of a dense (n, n) product:

- a range ``y_ij = |r_i - s_j| + d_i + o_j`` touches one *receiver block* ``[r_i, d_i]``
  (``d + 1`` parameters, ``d`` without receiver offsets) and one *source block*
  ``[s_j, o_j]``: its Jacobian row is ``a_ij = [u_ij, 1]`` on the first and
  ``b_ij = [-u_ij, 1]`` on the second (``u_ij`` the unit vector from ``s_j`` to ``r_i``);
- so ``J^T W J`` is made of per-receiver blocks ``sum_j w a a^T``, per-source blocks
  ``sum_i w b b^T`` and one coupling block ``w a b^T`` per range, O(m (d + 1)^2) flops
  instead of O(m n^2);
- the damped system is solved by eliminating the larger node set (its blocks are inverted
  independently: a Schur complement, as in bundle adjustment, Triggs et al. 2000, sec. 6.1),
  leaving a ``J (d + 1)`` square system per start (24 x 24 at 12 x 6) for one stacked
  ``numpy.linalg.solve``.

The iteration of every start is that of :func:`selfcal.toa.engine.dense_lm.full_lm` (the same
Marquardt damping ``diag(H) (1 + lam)`` starting at ``lam = 1e-4``, the step projected off
the gauge, a trial accepted when the cost does not rise, Nielsen's gain-ratio update
:func:`selfcal.optim.lm.damping_after_success` from the decrease predicted for the
projected step, the same stopping rules), each start with its own damping and its own
iteration count: batching changes the cost, not the iterates (to round-off: the Schur
solve and the dense Cholesky differ in the last digits).

Measured (``benchmarks/bench_toa_minimal.py``'s scene, see its docstring): per start and
iteration the stacked form costs a fraction of the one-start dense step, so the race can
afford three times the starts for the time it spent on 8.

References
----------
B. Triggs, P. McLauchlan, R. Hartley, A. Fitzgibbon, "Bundle adjustment -- a modern
synthesis", Vision Algorithms: Theory and Practice, LNCS 1883, 2000.
K. Madsen, H. B. Nielsen, O. Tingleff, "Methods for non-linear least squares problems", 2004.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from ...optim.lm import FTOL, TRIALS, BatchModel, levenberg_marquardt_batch
from ...robust import loss_rho
from .model import _flags, _node_indices

__all__ = ["solve_batch_lm"]

Array = NDArray[np.float64]

#: relative singular-value floor of the rotation generators (as model.GaugeProjector:
#: a rotation dependent on the others, points on a line, adds no gauge direction)
_ROT_RCOND = 1e-10


class _Problem(BatchModel):
    """The stacked model of one range matrix: evaluation, normal blocks, damped solve, gauge."""

    def __init__(self, Y: Array, d: int, offsets: str, loss: str, f_scale: float, cholesky: bool = False) -> None:
        I0, J0 = Y.shape[-2:]
        self.cholesky = cholesky  # the reduced systems by Cholesky (else LU; :func:`_solve`)
        has_r, has_s = _flags(offsets)
        r_idx, s_idx, _ = _node_indices(I0, J0, d, offsets)
        # the rows are the eliminated (larger) node set, the columns the kept one
        swap = J0 * (d + has_s) > I0 * (d + has_r)
        if swap:
            Y, has_r, has_s, r_idx, s_idx = np.swapaxes(Y, -1, -2), has_s, has_r, s_idx, r_idx
        self.I, self.J = Y.shape[-2:]
        self.I0 = I0  # receivers: the sign of the common-offset gauge direction
        self.d, self.has_r, self.has_s = d, has_r, has_s
        self.obs = np.isfinite(Y if Y.ndim == 2 else Y[0])  # (S, I, J): one matrix per start, one pattern
        self.Y = np.where(self.obs, Y, 0.0)
        self.obsf = self.obs.astype(float)
        self.loss, self.fs = loss, float(f_scale)
        self.idx_r, self.idx_s = r_idx, s_idx  # (I, pr), (J, ps): a row / column node's places in theta
        self.pr, self.ps = pr, ps = self.idx_r.shape[1], self.idx_s.shape[1]
        self.eye_r, self.eye_s = np.eye(pr, dtype=bool), np.eye(ps, dtype=bool)

    def evaluate(self, Th: Array, rows: object = None) -> tuple[Array, tuple[Array, Array, Array]]:
        """(cost (a,), (residuals (a, I, J), weights (a, I, J), unit vectors (a, I, J, d))); zero
        residual and weight where unobserved (``rows``: the driver's start indices, whose matrix
        is used when there is one per start)."""
        d = self.d
        u = Th[:, self.idx_r[:, :d]][:, :, None, :] - Th[:, self.idx_s[:, :d]][:, None, :, :]
        dist = np.sqrt(np.einsum("aijp,aijp->aij", u, u))
        f = dist - (self.Y if self.Y.ndim == 2 else self.Y[np.asarray(rows, dtype=np.intp)])
        if self.has_r:
            f += Th[:, self.idx_r[:, -1]][:, :, None]
        if self.has_s:
            f += Th[:, self.idx_s[:, -1]][:, None, :]
        f *= self.obsf  # 0 where unobserved (the entries of Y there are 0, never NaN)
        u *= np.divide(1.0, dist, out=np.zeros_like(dist), where=dist > 0)[..., None]  # 0 where points coincide
        if self.loss == "linear":
            return 0.5 * np.einsum("aij,aij->a", f, f), (f, np.broadcast_to(self.obsf, f.shape), u)
        rho, w = loss_rho((f / self.fs) ** 2, self.loss)
        cost = 0.5 * self.fs**2 * np.where(self.obs, rho, 0.0).sum(axis=(1, 2))
        return cost, (f, np.where(self.obs, w, 0.0), u)

    def linearize(self, Th: Array, state: tuple[Array, Array, Array]) -> _BatchStep:
        return _BatchStep(self, Th, state)

    def rows(self, u: Array) -> tuple[Array, Array]:
        """The Jacobian rows' receiver and source parts, (a, I, J, pr) and (a, I, J, ps)."""
        one = np.ones(u.shape[:-1] + (1,))
        A = np.concatenate([u, one], axis=-1) if self.has_r else u
        B = np.concatenate([-u, one], axis=-1) if self.has_s else -u
        return A, B

    def rotations(self, Th: Array) -> Array:
        """Orthonormal rotation gauge directions at each start, (a, k, (I + J) d)."""
        N, d = self.I + self.J, self.d
        P = Th[:, :N * d].reshape(-1, N, d)
        P = P - P.mean(axis=1, keepdims=True)
        pairs = [(0, 1)] if d == 2 else [(0, 1), (0, 2), (1, 2)]
        V = np.zeros((P.shape[0], len(pairs), N, d))
        for k, (p, q) in enumerate(pairs):
            V[:, k, :, p] = -P[:, :, q]
            V[:, k, :, q] = P[:, :, p]
        V = V.reshape(P.shape[0], len(pairs), N * d)
        lam, E = np.linalg.eigh(np.matmul(V, V.transpose(0, 2, 1)))  # the Gram matrix, ascending
        keep = lam > _ROT_RCOND**2 * lam[:, -1:]
        scale = np.divide(1.0, np.sqrt(np.where(keep, lam, 1.0)), out=np.zeros_like(lam), where=keep)
        return np.matmul(E.transpose(0, 2, 1), V) * scale[..., None]  # orthonormal; dependent ones zeroed

    def project(self, dx: Array, Q: Array) -> Array:
        """``dx`` off the gauge (translations, rotations ``Q``, the common offset shift), in place."""
        N, d, I = self.I + self.J, self.d, self.I0
        X = dx[:, :N * d].reshape(-1, N, d)
        X -= X.mean(axis=1, keepdims=True)
        flat = dx[:, :N * d]
        flat -= np.matmul(np.matmul(Q, flat[..., None]).transpose(0, 2, 1), Q)[:, 0]
        if self.has_r and self.has_s:
            off = dx[:, N * d:]
            shift = (off[:, :I].sum(axis=1) - off[:, I:].sum(axis=1)) / off.shape[1]
            off[:, :I] -= shift[:, None]
            off[:, I:] += shift[:, None]
        return dx


def solve_batch_lm(
    Theta0: Array, Y: Array, d: int, offsets: str, loss: str, f_scale: float, max_nfev: int | None,
    xtol: float, max_it: int = 100, cholesky: bool = False,
) -> tuple[Array, NDArray[np.bool_], NDArray[np.intp], NDArray[np.bool_]]:
    """Levenberg-Marquardt from every row of ``Theta0`` at once (module docstring).

    Parameters
    ----------
    Theta0 : (S, n) starts, receiver-major ``[r (I d), s (J d), d_i (I)?, o_j (J)?]`` (metres),
        the layout of :mod:`selfcal.toa.engine.nls`.
    Y : (I, J) ranges, metres, NaN = missing (every node needs at least one range); or (S, I, J),
        one matrix per start, all with the missing pattern of the first (the permutation
        test's copies, :func:`selfcal.toa.verdict.trust.permutation_test`).
    d, offsets : the model (``"none"``, ``"receivers"``, ``"sources"``, ``"both"``).
    loss, f_scale : robust loss (:func:`selfcal.robust.loss_rho`) and its scale (metres).
    max_nfev : iteration cap per start (default ``max_it``); xtol : relative step tolerance.
    max_it : iteration cap when ``max_nfev`` is None.
    cholesky : solve the reduced (positive definite) systems by Cholesky, about half the time
        of the default stacked LU at 20 x (64 x 64); the iterates agree to round-off, not bit for
        bit (the permutation test's statistic uses it; the search's race keeps LU, whose
        iterates its tests and benchmarks pin).

    Returns
    -------
    Theta : (S, n) the iterates reached.
    converged : (S,) bool, each start's stopping rule met (as :func:`selfcal.toa.engine.dense_lm.full_lm`).
    iterations : (S,) int.
    finite : (S,) bool, False for a start whose iterate or cost stopped being finite (its row
        of ``Theta`` is then its last finite iterate).

    Notes
    -----
    Flops per iteration and start O(I J (d + 1)^2 (J + 1)) for the normal blocks and the Schur
    complement plus O((J (d + 1))^3) for the reduced solve, with the smaller node set kept
    (the sources are the eliminated rows when they are the larger set).

    Examples
    --------
    Three starts of one 2-D network with receiver delays, refined together to the exact fit:

    >>> import numpy as np
    >>> from selfcal.toa.engine import nls
    >>> rx, tx = np.random.default_rng(1).uniform(-2, 2, (8, 2)), np.random.default_rng(2).uniform(-3, 3, (5, 2))
    >>> delays = np.linspace(0.1, 0.8, 8)
    >>> Y = nls.toa_model(rx, tx, delays)
    >>> starts = np.stack([nls._pack(rx + e, tx - e, delays, None) for e in (0.02, -0.01, 0.05)])
    >>> Th, ok, nit, fin = solve_batch_lm(starts, Y, 2, "receivers", "linear", 1.0, None, 1e-12)
    >>> res = [float(np.abs(nls.toa_residuals(t, Y, 2, "receivers")).max()) for t in Th]
    >>> bool(ok.all()) and max(res) < 1e-6
    True
    """
    pb = _Problem(np.asarray(Y, float), d, offsets, loss, f_scale, cholesky)
    out = levenberg_marquardt_batch(pb, np.array(Theta0, dtype=float, ndmin=2), max_iter=int(max_nfev or max_it),
                                    xtol=xtol, ftol=FTOL, trials=TRIALS)
    return out.x, out.converged, out.iterations, out.finite


class _BatchStep:
    """The linearisation of the running starts: normal blocks and the stacked Schur step."""

    def __init__(self, pb: _Problem, Theta: Array, state: tuple[Array, Array, Array]) -> None:
        f, w, u = state
        I, J, pr, ps = pb.I, pb.J, pb.pr, pb.ps
        self.pb, self.K, self.w = pb, J * ps, w
        self.eye_r, self.eye_s = pb.eye_r, pb.eye_s
        A, B = pb.rows(u)
        self.A, self.B = A, B
        wa = w[..., None]
        wA, wB = wa * A, wa * B
        self.Hrr = np.matmul(wA.transpose(0, 1, 3, 2), A)  # (a, I, pr, pr): sum over sources
        self.Hss = np.matmul(wB.transpose(0, 2, 3, 1), B.transpose(0, 2, 1, 3))  # (a, J, ps, ps)
        na = Theta.shape[0]
        C = np.empty((na, I, pr, J, ps))  # the coupling blocks w a b^T, written in place
        np.multiply(wA.transpose(0, 1, 3, 2)[..., None], B[:, :, None, :, :], out=C)
        self.C = C.reshape(na, I, pr, J * ps)
        fa = f[..., None]
        self.gr = (wA * fa).sum(axis=2)  # (a, I, pr)
        self.gs = (wB * fa).sum(axis=1)  # (a, J, ps)
        self.drr = self.Hrr[:, :, self.eye_r]  # (a, I, pr) diagonals
        self.dss = self.Hss[:, :, self.eye_s]
        self.Q = pb.rotations(Theta)
        self.n = Theta.shape[1]
        gr, gs = self.gr, self.gs
        self.gnorm = np.sqrt(np.einsum("aip,aip->a", gr, gr) + np.einsum("ajp,ajp->a", gs, gs))

    def step(self, lam: Array, t: NDArray[np.intp]) -> Array:
        pb, K = self.pb, self.K
        I, J, pr, ps = pb.I, pb.J, pb.pr, pb.ps
        lt = lam[:, None, None]
        Hr = self.Hrr[t]  # a gathered copy
        np.einsum("aipp->aip", Hr)[...] += lt * self.drr[t]  # the diagonals, a writable view
        Hs = self.Hss[t]
        np.einsum("ajpp->ajp", Hs)[...] += lt * self.dss[t]
        nt = t.size
        Hr_inv = _inv(Hr)
        Ct = self.C[t]
        X = np.matmul(Hr_inv, Ct)  # Hrr^-1 Hrs, (t, I, pr, J ps)
        zr = np.matmul(Hr_inv, self.gr[t][..., None])  # (t, I, pr, 1)
        CtT = Ct.reshape(nt, I * pr, K).transpose(0, 2, 1)
        Sred = -np.matmul(CtT, X.reshape(nt, I * pr, K))
        np.einsum("ajpjq->ajpq", Sred.reshape(nt, J, ps, J, ps))[...] += Hs  # its diagonal blocks, a view
        rhs = np.matmul(CtT, zr.reshape(nt, I * pr, 1)) - self.gs[t].reshape(nt, K, 1)
        xs = (_solve_cholesky if pb.cholesky else _solve)(Sred, rhs)  # (t, K, 1)
        xr = -(zr + np.matmul(X, xs[:, None]))[..., 0]
        xs = xs.reshape(nt, J, ps)
        dx = np.zeros((nt, self.n))
        dx[:, pb.idx_r] = xr
        dx[:, pb.idx_s] = xs
        ok = np.isfinite(dx).all(axis=1)
        dx[~ok] = 0.0
        pb.project(dx, self.Q[t])
        dx[~ok] = np.nan  # the driver refuses the trial
        return dx

    def predicted(self, dx: Array, t: NDArray[np.intp]) -> Array:
        pb = self.pb
        xr, xs = dx[:, pb.idx_r], dx[:, pb.idx_s]
        Jx = (np.matmul(self.A[t], xr[..., None])[..., 0]
              + np.matmul(self.B[t].transpose(0, 2, 1, 3), xs[..., None])[..., 0].transpose(0, 2, 1))
        return np.asarray(-(np.einsum("aip,aip->a", self.gr[t], xr) + np.einsum("ajp,ajp->a", self.gs[t], xs)
                            + 0.5 * np.einsum("aij,aij->a", self.w[t] * Jx, Jx)))


def _inv(H: Array) -> Array:
    """Stacked inverses of small damped blocks; NaN for a singular one (its start's trial fails)."""
    try:
        return np.asarray(np.linalg.inv(H), float)
    except np.linalg.LinAlgError:
        out = np.full_like(H, np.nan)
        for k in range(H.shape[0]):
            try:
                out[k] = np.linalg.inv(H[k])
            except np.linalg.LinAlgError:
                pass
        return out


def _solve_cholesky(Sred: Array, rhs: Array) -> Array:
    """:func:`_solve` by Cholesky (LAPACK ``potrf`` + ``potrs`` on the upper triangle) matrix by
    matrix: the reduced system of a damped positive definite normal matrix is positive
    definite; LU (:func:`_solve`) for a matrix whose factorisation fails."""
    from scipy.linalg.lapack import dpotrf, dpotrs

    out = np.empty_like(rhs)
    with np.errstate(all="ignore"):
        for k in range(Sred.shape[0]):
            c, info = dpotrf(Sred[k], lower=0, clean=0)
            if info == 0:
                out[k], info = dpotrs(c, rhs[k], lower=0)
            if info != 0:
                out[k] = _solve(Sred[k:k + 1], rhs[k:k + 1])[0]
    return out


def _solve(Sred: Array, rhs: Array) -> Array:
    """Stacked solves ``Sred x = rhs`` of the reduced systems, (t, K, 1); NaN for a singular one."""
    try:
        return np.asarray(np.linalg.solve(Sred, rhs), float)
    except np.linalg.LinAlgError:
        out = np.full_like(rhs, np.nan)
        for k in range(Sred.shape[0]):
            try:
                out[k] = np.linalg.solve(Sred[k], rhs[k])
            except (np.linalg.LinAlgError, ValueError):
                pass
        return out
