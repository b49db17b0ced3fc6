"""Schur-reduced Levenberg-Marquardt for a constrained (affinely parametrised) range model.

The constrained fits of :mod:`selfcal.toa.engine.constrained` write the parameters of the range
model ``y_ij = |r_i - s_j| + d_i + o_j`` as ``theta = base + T x``: fixed coordinates drop
columns of the identity, a common offset is one column of ones, a general linear offset
constraint is any basis ``B`` (``offsets = d_0 + B x``). This module solves that problem
at the speed of the unconstrained engine (:mod:`selfcal.toa.engine.schur_lm`), for any ``T``.

Partition. Every column of the reduced Jacobian ``J T`` is either *local* to one node of
the eliminated set E (the larger node set: its free coordinates and an offset of its own)
or *global*: the kept set K's coordinates and offsets, and every offset parameter that
spans several nodes (a common offset, a basis column). Each residual row (one range, or one
prior row ``(sigma / std)(x_k - mu_k)``) touches at most one E node, so the normal matrix
is

    [ R   C^T ]      R = N_gg (global, dense, small)
    [ C   D   ]      D = blockdiag(D_e) (one small block per E node)

and each damped system is solved on the global unknowns only, ``S = R - C^T D^-1 C``
(dense, Cholesky by LAPACK posv, least squares when not positive definite), then
back-substituted node by node. A moving UWB tag (6 anchors x 600 positions, a common range
offset) has 1800 local unknowns in 600 blocks of 3 and 19 global ones; an iteration costs
O(m n_g^2), not the O(n^3) of a dense trust region (Agarwal et al., "Bundle adjustment in
the large", 2010, for the Schur scheme; Triggs et al., "Bundle adjustment - a modern
synthesis", 2000, sec. 6 for the elimination order).

:class:`RangeSchurModel` is the range model on this engine (the Jacobian's fixed sparsity
through ``T``, the residuals' curvature rows), used by :mod:`selfcal.toa.engine.constrained`.

The residual gauge the constraints leave is pinned by the caller (the pinned coordinates
are not in ``x``), so the system is non-singular beyond the Marquardt damping. The LM loop
is the engine's: Marquardt diagonal damping, Nielsen's gain-ratio update
(:func:`selfcal.optim.lm.damping_after_success`), robust losses as iteratively
reweighted normal equations with weights rho'(z) over every residual row (the prior rows
included, as ``scipy.optimize.least_squares`` applies its loss to them), whose fixed points
are the stationary points of the robust cost.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
import scipy.sparse
from numpy.typing import NDArray

from ...errors import DegenerateGeometryError
from ...optim.lm import Model, irls, levenberg_marquardt
from ...optim.steps import (
    cholesky_solve as _direct_solve,  # Cholesky (posv), least squares if not PD
)
from .model import _unpack

Array = NDArray[np.float64]
IntArray = NDArray[np.intp]
BoolArray = NDArray[np.bool_]

__all__ = ["MAX_GLOBAL", "FTOL", "RangeSchurModel", "RowPattern", "SchurInverse", "local_blocks", "solve_affine_lm"]

#: most global unknowns of the dense reduced system (a (n_g, n_g) Cholesky per damping trial)
MAX_GLOBAL = 1200
#: relative cost decrease that stops the iteration; tighter than the unconstrained engine's
#: 1e-8 because the constrained fits are refits from near the optimum whose parameters (a
#: common offset, its jackknife replicates) are compared at a fraction of their error
FTOL = 1e-12
#: damping trials per iteration before giving up (as schur_lm)
TRIALS = 12
#: relative cost decrease of a Gauss-Newton step below which the curvature rows are switched on
SWITCH = 1e-5


def local_blocks(T: scipy.sparse.spmatrix, node_of_theta: IntArray) -> tuple[IntArray, IntArray]:
    """Split the columns of ``T`` into node-local blocks and global columns.

    Parameters
    ----------
    T : (n, p) sparse map from the reduced vector x to theta.
    node_of_theta : (n,) the E node each entry of theta belongs to, -1 for entries of
        the kept side or of no node.

    Returns
    -------
    blocks : (nE, mE) column indices of x local to each E node, -1 padded (mE >= 1).
    glob : (n_g,) the other columns, in increasing order.

    Examples
    --------
    >>> T = scipy.sparse.eye(4, format="csc")
    >>> b, g = local_blocks(T, np.array([-1, 0, 0, 1]))
    >>> b.tolist(), g.tolist()
    ([[1, 2], [3, -1]], [0])
    """
    C = scipy.sparse.csc_matrix(T)
    p = C.shape[1]
    nE = int(node_of_theta.max()) + 1 if node_of_theta.size else 0
    owner = np.full(p, -1, np.intp)
    nz = np.diff(C.indptr) > 0
    if C.indices.size:
        nodes = node_of_theta[C.indices]
        starts = C.indptr[:-1][nz]
        lo = np.minimum.reduceat(nodes, starts)
        hi = np.maximum.reduceat(nodes, starts)
        owner[nz] = np.where((lo == hi) & (lo >= 0), lo, -1)
    loc = np.nonzero(owner >= 0)[0]
    counts = np.bincount(owner[loc], minlength=nE) if nE else np.zeros(0, np.intp)
    mE = max(int(counts.max()) if counts.size else 0, 1)
    blocks = np.full((nE, mE), -1, np.intp)
    order = loc[np.argsort(owner[loc], kind="stable")]
    start = np.concatenate([[0], np.cumsum(counts)[:-1]]) if nE else np.zeros(0, np.intp)
    slot = np.arange(order.size) - np.repeat(start, counts)
    blocks[owner[order], slot] = order
    return blocks, np.nonzero(owner < 0)[0]


class RowPattern:
    """The fixed sparsity of a Jacobian and its split into node-local and global entries.

    Parameters
    ----------
    rows, cols : (nnz,) row and column (x index) of every structural non-zero; no pair
        repeated. Rows ``0 .. n_res - 1`` are the residual rows, rows ``n_res .. n_rows - 1``
        curvature rows (see :func:`solve_affine_lm`).
    n_rows, n_res : number of rows in all, of residual rows.
    blocks, glob : the partition of :func:`local_blocks`.

    Raises
    ------
    ValueError : a row touches two E nodes (the partition does not separate the nodes).
    """

    def __init__(self, rows: IntArray, cols: IntArray, n_rows: int, n_res: int,
                 blocks: IntArray, glob: IntArray) -> None:
        p = int(blocks[blocks >= 0].size + glob.size)
        nE, mE = blocks.shape
        valid = blocks >= 0
        slot_of = -np.ones(p, np.intp)
        slot_of[blocks[valid]] = np.nonzero(valid.ravel())[0]
        ng = glob.size
        glob_pos = -np.ones(p, np.intp)
        glob_pos[glob] = np.arange(ng)
        loc = slot_of[cols] >= 0
        sl = slot_of[cols[loc]]
        own = -np.ones(n_rows, np.intp)
        own[rows[loc]] = sl // mE
        if (own[rows[loc]] != sl // mE).any():
            raise ValueError("a Jacobian row touches two eliminated nodes")
        self.rows, self.cols, self.n_rows, self.n_res = rows, cols, n_rows, n_res
        self.slot_of, self.glob_pos = slot_of, glob_pos
        self.blocks, self.glob, self.valid, self.p, self.nE, self.mE, self.ng = blocks, glob, valid, p, nE, mE, ng
        self.loc = np.nonzero(loc)[0]
        self.je_at = rows[loc] * mE + sl % mE  # flat index into JE (n_rows, mE)
        # JG: the global entries as a CSR matrix of fixed structure (rows sorted)
        gi = np.nonzero(~loc)[0]
        gi = gi[np.argsort(rows[gi], kind="stable")]
        self.g_ent = gi
        self.g_indices = glob_pos[cols[gi]]
        self.g_indptr = np.concatenate([[0], np.cumsum(np.bincount(rows[gi], minlength=n_rows))])
        # Cs: row (e * mE + a) holds w JE[row, a] on the rows of node e, so that
        # Cs @ JG = C, Cs @ JE = D and Cs @ f = g_E (fixed structure)
        has = np.nonzero(own >= 0)[0]
        hs = has[np.argsort(own[has], kind="stable")]
        cnt = np.bincount(own[has], minlength=nE)
        start = np.concatenate([[0], np.cumsum(cnt)[:-1]])
        seg = np.repeat(cnt, mE)
        self.c_indptr = np.concatenate([[0], np.cumsum(seg)])
        e_of = np.repeat(np.repeat(np.arange(nE), mE), seg)
        self.c_a = np.repeat(np.tile(np.arange(mE), nE), seg)
        j = np.arange(e_of.size) - np.repeat(self.c_indptr[:-1], seg)
        self.c_indices = hs[start[e_of] + j]

    def systems(self, vals: Array, w: Array, f: Array) -> tuple[Array, Array, Array, Array, Array]:
        """Normal-equation pieces: D (nE, mE, mE), C (nE, mE, n_g), R (n_g, n_g), g_E (nE, mE), g_G (n_g,).

        ``w`` (n_rows,) row weights, ``f`` (n_rows,) residuals (0 on curvature rows).
        """
        nE, mE, ng, n = self.nE, self.mE, self.ng, self.n_rows
        JE = np.zeros(n * mE)
        JE[self.je_at] = vals[self.loc]
        JE = JE.reshape(n, mE)
        JG = scipy.sparse.csr_matrix((vals[self.g_ent], self.g_indices, self.g_indptr), shape=(n, ng))
        wJG = scipy.sparse.csr_matrix((vals[self.g_ent] * np.repeat(w, np.diff(self.g_indptr)),
                                       self.g_indices, self.g_indptr), shape=(n, ng))
        gG = np.asarray(JG.T @ (w * f)).ravel()
        R = np.asarray((JG.T @ wJG).toarray())
        ci = self.c_indices
        Cs = scipy.sparse.csr_matrix((JE[ci, self.c_a] * w[ci], ci, self.c_indptr), shape=(nE * mE, n))
        C = np.asarray((Cs @ JG).toarray()).reshape(nE, mE, ng)
        D = np.asarray(Cs @ JE).reshape(nE, mE, mE)
        D = 0.5 * (D + np.swapaxes(D, 1, 2))
        gE = np.asarray(Cs @ f).reshape(nE, mE)
        return D, C, R, gE, gG

    def matvec(self, vals: Array, dx: Array) -> Array:
        """``J dx`` over every row (n_rows,)."""
        return np.asarray(np.bincount(self.rows, vals * dx[self.cols], minlength=self.n_rows), float)


class SchurInverse:
    """The inverse of the (undamped) normal matrix ``[[R, C^T], [C, D]]`` through its Schur complement.

    With ``K_e = D_e^-1 C_e`` and ``S = R - sum_e C_e^T K_e``, the inverse is
    ``Delta + L S^-1 L^T``: ``Delta`` the block diagonal of the ``D_e^-1`` on the local
    columns, ``L`` the identity on the global ones and ``-K`` on the local ones. Any block
    of it costs O(k^2 n_g) for k columns; no sparse factorisation of the whole matrix.

    Raises
    ------
    numpy.linalg.LinAlgError : a node block or S is singular to working precision
        (condition number above 1e12).
    """

    def __init__(self, pattern: RowPattern, vals: Array, w: Array) -> None:
        pat = pattern
        D, C, R, _, _ = pat.systems(vals, w, np.zeros(pat.n_rows))
        idx = np.arange(pat.mE)
        D[:, idx, idx] = np.where(pat.valid, D[:, idx, idx], 1.0)
        if D.size and not (np.linalg.cond(D) < 1e12).all():
            raise np.linalg.LinAlgError("a node block is singular")
        self.Dinv = np.linalg.inv(D)
        self.K = np.einsum("eab,ebk->eak", self.Dinv, C)
        S = R - np.einsum("eak,eal->kl", C, self.K)
        S = 0.5 * (S + S.T)
        if S.size and not np.linalg.cond(S) < 1e12:
            raise np.linalg.LinAlgError("the reduced matrix is singular")
        self.Sinv = np.linalg.inv(S) if S.size else S
        self.pat = pat

    def _L(self, cols: IntArray) -> tuple[Array, IntArray, IntArray]:
        pat = self.pat
        L = np.zeros((cols.size, pat.ng))
        g = pat.glob_pos[cols]
        isg = g >= 0
        L[np.nonzero(isg)[0], g[isg]] = 1.0
        sl = pat.slot_of[cols]
        e, a = np.where(isg, -1, sl // pat.mE), np.where(isg, 0, sl % pat.mE)
        loc = ~isg
        L[loc] = -self.K[e[loc], a[loc]]
        return L, e, a

    def block(self, cols: IntArray) -> Array:
        """``N^-1[cols][:, cols]``."""
        L, e, a = self._L(np.asarray(cols, np.intp))
        same = (e[:, None] == e[None, :]) & (e[:, None] >= 0)
        ee = np.maximum(e, 0)
        Delta = np.where(same, self.Dinv[ee[:, None], a[:, None], a[None, :]], 0.0)
        return Delta + L @ self.Sinv @ L.T

    def solve(self, B: Array) -> Array:
        """``N^-1 B`` for a dense (p, k) B."""
        pat = self.pat
        B = np.asarray(B, float).reshape(pat.p, -1)
        BE = np.zeros((pat.nE, pat.mE, B.shape[1]))
        BE[pat.valid] = B[pat.blocks[pat.valid]]
        yG = self.Sinv @ (B[pat.glob] - np.einsum("eak,eaj->kj", self.K, BE))
        yE = np.einsum("eab,ebj->eaj", self.Dinv, BE) - np.einsum("eak,kj->eaj", self.K, yG)
        out = np.zeros_like(B)
        out[pat.glob] = yG
        out[pat.blocks[pat.valid]] = yE[pat.valid]
        return out


def _damped(D: Array, dD: Array, lam: float, valid: NDArray[np.bool_]) -> Array | None:
    """Inverses of the Marquardt-damped node blocks ``D_e + lam diag(D_e)`` (padding: identity)."""
    idx = np.arange(D.shape[1])
    Dd = D.copy()
    Dd[:, idx, idx] = np.where(valid, D[:, idx, idx] + lam * dD, 1.0)
    try:
        inv = np.linalg.inv(Dd)
    except np.linalg.LinAlgError:
        return None
    return np.asarray(inv, float) if np.isfinite(inv).all() else None


def _floor(v: Array) -> Array:
    """Diagonal entries floored at 1e-12 of the largest (Marquardt scaling of a zero column)."""
    return np.maximum(v, 1e-12 * max(float(v.max(initial=0.0)), 1.0))


def solve_affine_lm(
    x0: Array, fun: Callable[[Array], Array],
    values: Callable[[Array, Array, Array], tuple[Array, Array]], pattern: RowPattern,
    loss: str, f_scale: float, xtol: float, max_it: int = 200, ftol: float = FTOL,
) -> tuple[Array, bool, int]:
    """Levenberg-Marquardt with the node-local unknowns eliminated by a Schur complement.

    Parameters
    ----------
    x0 : (p,) start of the reduced vector.
    fun : ``x -> f`` (n_res,) residuals (model - data, then any prior rows).
    values : ``(x, f, w) -> (vals, wc)``: the Jacobian of ``fun`` on the residual rows of
        ``pattern`` and the curvature rows' vectors (``vals`` (nnz,)), and the curvature
        rows' weights ``wc`` (n_rows - n_res,), so that ``sum_c wc_c j_c j_c^T`` is the
        second-order part ``sum_i w_i f_i d^2 f_i`` of the Hessian (none: no curvature rows).
    pattern : the fixed sparsity (:class:`RowPattern`).
    loss, f_scale : robust loss (:func:`selfcal.robust.loss_rho`) and its scale.
    xtol : relative step tolerance; ftol : relative cost decrease that stops.
    max_it : iteration cap.

    Returns
    -------
    (x, converged, iterations).

    Notes
    -----
    Each damped step solves ``(H + lam diag|H|) dx = -g`` with ``H = J^T W J + sum wc j j^T``:
    the Gauss-Newton matrix plus the residuals' curvature, i.e. Newton's method with
    Marquardt damping. The curvature matters on range data: a tag position 0.2 m from an
    anchor with a 0.1 m residual has a second-order term half the size of its Gauss-Newton
    block, the Gauss-Newton model is then wrong for it and, through its coupling, for the
    global unknowns (measured on the LPS flights: 50 Gauss-Newton iterations for a
    common-offset refit, linear convergence at the end; 20 with the curvature, quadratic).
    The damping is relative to ``|diag H|``, a trial that does not lower the cost is refused
    and the damping raised, so an indefinite ``H`` far from the minimum costs trials, not
    descent. Per iteration O(nnz (mE + c^2)) for the pieces (c the global entries per row),
    a batched inverse of the node blocks and one dense (n_g, n_g) solve per trial.
    """
    model = _AffineModel(fun, values, pattern, loss, f_scale)
    out = levenberg_marquardt(model, np.array(x0, float), max_iter=max_it, xtol=xtol, ftol=ftol, trials=TRIALS)
    return out.x, out.converged, out.iterations


class _AffineModel(Model):
    """:func:`solve_affine_lm`'s model: the Gauss-Newton matrix, plus the residuals' curvature
    once the Gauss-Newton model fails (``newton``), and the node-block Schur step solver."""

    def __init__(self, fun: Callable[[Array], Array], values: Callable[[Array, Array, Array], tuple[Array, Array]],
                 pattern: RowPattern, loss: str, f_scale: float) -> None:
        self.fun, self.values, self.pat, self.loss, self.f_scale = fun, values, pattern, loss, f_scale
        self.newton = False
        self.zeros_c = np.zeros(pattern.n_rows - pattern.n_res)

    def evaluate(self, x: Array) -> tuple[float, tuple[Array, Array]]:
        f = self.fun(x)
        cost, w = irls(f, self.loss, self.f_scale)
        return cost, (f, w)

    def linearize(self, x: Array, state: tuple[Array, Array]) -> _AffineStep:
        f, w = state
        vals, wc = self.values(x, f, w)
        if not self.newton:
            wc = np.zeros_like(wc)
        wall = np.concatenate([w, np.asarray(wc, float)])
        fall = np.concatenate([f, self.zeros_c])
        return _AffineStep(self.pat, vals, wall, fall)

    def accepted(self, lin: Any, cost: float, new: float, predicted: float) -> None:
        # Gauss-Newton while its model holds; the residuals' curvature once it fails
        # (gain ratio below 1/4) or its progress has become the linear tail
        if not self.newton and ((cost - new) <= SWITCH * cost or (cost - new) < 0.25 * predicted):
            self.newton = True


class _AffineStep:
    """The damped step ``(H + lam diag|H|) dx = -g`` with the node blocks eliminated (Schur
    complement on the global unknowns, dense Cholesky)."""

    def __init__(self, pat: RowPattern, vals: Array, wall: Array, fall: Array) -> None:
        self.pat, self.vals, self.wall = pat, vals, wall
        self.wf = wall * fall
        self.D, self.C, self.R, self.gE, self.gG = pat.systems(vals, wall, fall)
        self.dD = _floor(np.abs(np.einsum("eaa->ea", self.D)))
        self.dR = _floor(np.abs(np.diag(self.R)).copy())
        self.gnorm = float(np.sqrt(self.gG @ self.gG + np.sum(self.gE * self.gE)))

    def step(self, lam: float) -> Array | None:
        pat, C = self.pat, self.C
        Dinv = _damped(self.D, self.dD, lam, pat.valid)
        if Dinv is None:
            return None
        DiC = np.einsum("eab,ebk->eak", Dinv, C)
        S = self.R + np.diag(lam * self.dR) - np.einsum("eak,eal->kl", C, DiC)
        DigE = np.einsum("eab,eb->ea", Dinv, self.gE)
        rhs = -self.gG + np.einsum("eak,ea->k", C, DigE)
        xg = _direct_solve(0.5 * (S + S.T), rhs) if pat.ng else np.zeros(0)
        if xg is None:
            return None
        xe = -DigE - np.einsum("eak,k->ea", DiC, xg)
        dx = np.zeros(pat.p)
        dx[pat.glob] = xg
        dx[pat.blocks[pat.valid]] = xe[pat.valid]
        return dx if np.isfinite(dx).all() else None

    def predicted(self, dx: Array) -> float:
        Jd = self.pat.matvec(self.vals, dx)
        return -(float(self.wf @ Jd) + 0.5 * float(np.sum(self.wall * Jd * Jd)))


class RangeSchurModel:
    """The constrained range model on the fixed sparsity of :mod:`selfcal.toa.engine.schur_affine`.

    Rows: the m observed ranges (row-major, as :func:`selfcal.toa.engine.nls.toa_residuals`), the
    prior rows, then ``(d - 1) m`` curvature rows: the second-order part of the Hessian of a
    range residual ``f = |r_i - s_j| + ...`` is ``f (I - u u^T) / |r_i - s_j|`` on
    ``(r_i, -s_j)``, written as one row per direction ``v`` normal to ``u`` (entries ``v``
    at ``r_i``, ``-v`` at ``s_j``) with weight ``w f / |r_i - s_j|``. Every theta-space
    entry is mapped through ``T`` once; per iteration only the values change.
    """

    def __init__(self, obs: BoolArray, I: int, J: int, d: int, offsets: str, TF: scipy.sparse.csc_matrix,
                 prior_pos: NDArray[np.intp], blocks: NDArray[np.intp], glob: NDArray[np.intp]) -> None:
        ii, jj = np.nonzero(obs)
        m = ii.size
        npri = prior_pos.size
        self.ii, self.jj, self.I, self.J, self.d, self.offsets, self.m = ii, jj, I, J, d, offsets, m
        self.has_r, self.has_s = offsets in ("receivers", "both"), offsets in ("sources", "both")
        ar = np.arange(m)
        rc = (ii[:, None] * d + np.arange(d)).ravel()
        sc = (I * d + jj[:, None] * d + np.arange(d)).ravel()
        rows_t = [np.repeat(ar, d), np.repeat(ar, d)]
        cols_t = [rc, sc]
        k = (I + J) * d
        if self.has_r:
            rows_t.append(ar)
            cols_t.append(k + ii)
            k += I
        if self.has_s:
            rows_t.append(ar)
            cols_t.append(k + jj)
        for q in range(d - 1):
            rq = np.repeat(m + npri + q * m + ar, d)
            rows_t += [rq, rq]
            cols_t += [rc, sc]
        rt, ct = np.concatenate(rows_t), np.concatenate(cols_t)
        # through T: theta entry (row, t) -> x entries (row, c) with coefficient T[t, c]
        Tr = scipy.sparse.csr_matrix(TF)
        lens = np.diff(Tr.indptr)[ct]
        src = np.repeat(np.arange(ct.size), lens)
        first = np.repeat(Tr.indptr[ct] - np.concatenate([[0], np.cumsum(lens)[:-1]]), lens)
        at = first + np.arange(src.size)
        xr, xc, coef = rt[src], Tr.indices[at], Tr.data[at]
        nV = ct.size
        # prior rows live in x directly; their values follow the theta entries in V
        xr = np.concatenate([xr, m + np.arange(npri)])
        xc = np.concatenate([xc, prior_pos])
        coef = np.concatenate([coef, np.ones(npri)])
        src = np.concatenate([src, nV + np.arange(npri)])
        p = TF.shape[1]
        uniq, inv = np.unique(xr * p + xc, return_inverse=True)
        self.inv, self.coef, self.src, self.nnz = inv.ravel(), coef, src, uniq.size
        self.pattern = RowPattern(uniq // p, uniq % p, m + npri + (d - 1) * m, m + npri, blocks, glob)

    def values(self, theta: Array, f: Array, w: Array, wprior: Array) -> tuple[Array, Array]:
        """Jacobian values on the pattern, curvature weights (see the class docstring)."""
        d, m = self.d, self.m
        r, s, _, _ = _unpack(theta, self.I, self.J, d, self.offsets)
        diff = r[self.ii] - s[self.jj]
        dist = np.linalg.norm(diff, axis=1)
        pos = dist > 0
        u = np.where(pos[:, None], diff / np.where(pos, dist, 1.0)[:, None], 0.0)
        parts = [u.ravel(), -u.ravel()] + [np.ones(m)] * (int(self.has_r) + int(self.has_s))
        if d == 2:
            normals = [np.c_[-u[:, 1], u[:, 0]]]
        else:
            a = np.where((np.abs(u[:, 0]) < 0.9)[:, None], np.eye(3)[0], np.eye(3)[1])
            v1 = np.cross(u, a)
            n1 = np.linalg.norm(v1, axis=1)
            v1 = np.where((n1 > 0)[:, None], v1 / np.where(n1 > 0, n1, 1.0)[:, None], 0.0)
            normals = [v1, np.cross(u, v1)]
        curv: list[Array] = []
        for v in normals:
            curv += [v.ravel(), -v.ravel()]
        V = np.concatenate(parts + curv + [np.asarray(wprior, float).ravel()])
        vals = np.asarray(np.bincount(self.inv, self.coef * V[self.src], minlength=self.nnz), float)
        wc = np.where(pos, w[:m] * f[:m] / np.where(pos, dist, 1.0), 0.0)
        return vals, np.tile(wc, d - 1)

    def inverse(self, theta: Array, drho: Array, wprior: Array) -> Any:
        """The pinned inverse of the Gauss-Newton normal matrix at ``theta`` (weights rho')."""
        f0 = np.zeros(self.pattern.n_res)
        vals, _ = self.values(theta, f0, f0, wprior)
        w = np.concatenate([np.asarray(drho, float), np.zeros(self.pattern.n_rows - self.pattern.n_res)])
        try:
            return SchurInverse(self.pattern, vals, w)
        except np.linalg.LinAlgError:
            raise DegenerateGeometryError(
                "the normal equations are numerically singular beyond the gauge: the constrained "
                "geometry is degenerate", kind="degenerate-geometry") from None

    def solve(self, x0: Array, fun: Any, theta_of: Any, wprior: Array, loss: str, fs: float, xtol: float,
              max_it: int) -> tuple[Array, bool, int]:
        return solve_affine_lm(x0, fun, lambda x, f, w: self.values(theta_of(x), f, w, wprior),
                               self.pattern, loss, fs, xtol, max_it=max_it)
