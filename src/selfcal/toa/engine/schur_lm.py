"""The one range model of the TOA engines (:class:`RangeModel`) and its Schur step solver.

:class:`RangeModel` evaluates ``y = |x_k - x_e| + o_k + o_e`` for every unconstrained engine,
on the full grid (:class:`Grid`) or the observed pairs (:class:`Pairs`), and hands the driver
a step solver: the dense normal matrix (:class:`selfcal.optim.steps.DenseStep`) or the Schur
complement below, formed or by CG (:func:`selfcal.optim.structure.lm_step` chooses).

The residual of entry (k, e) of the range matrix, oriented with the *kept* node set K
(the smaller one, :class:`selfcal.toa.engine.model._Layout`) in the rows, is::

    f_ke = |x_k - x_e| + o_k + o_e - y_ke          (003 eq. 2; 004 sec. 3 offsets)

so its Jacobian row is ``a_ke = [U_ke, 1?]`` on node k and ``b_ke = [-U_ke, 1?]`` on
node e, with the unit vector ``U_ke = (x_k - x_e) / |x_k - x_e|``. Everything the solver
needs is a sum over the observed pairs of products of the d component arrays ``U_p``
(each nK x nE, the size of the data) with the weights ``w`` and the residuals ``f``:

- the diagonal blocks ``A_k = sum_e w a a^T`` and ``D_e = sum_k w b b^T`` (both from the
  same products ``w U_p U_q``, summed over the other axis);
- the Schur-Jacobi preconditioner, the exact d x d diagonal blocks of
  ``S = A - B D^-1 B^T``: ``S_k = A_k - sum_e c_ke a a^T`` with ``c = w^2 b^T D_e^-1 b``;
- the products ``B^T x`` and ``B y`` of one CG step: ``(m_K + m_E)`` multiply-adds of
  nK x nE arrays each.

Component-major storage (d arrays of nK x nE, never an (nK, nE, d) tensor and its
transposed copies) keeps the working set at ~(d + 4) times the data and lets every
product run as plain contiguous array arithmetic. Cost per CG product O(nK nE (m_K + m_E)),
per Levenberg-Marquardt iteration O(nK nE d^2) for the blocks; nothing of size
(nK d) x (nE d) is formed (Agarwal et al., "Bundle adjustment in the large", 2010, for the
inexact-Newton Schur scheme).

Why this file is above 600 lines (~630): the range model and its Schur step solver share the
component-major products (directions, diagonal blocks, the reduced system); split, each half
would import the other's private arrays and layout.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ...errors import DegenerateGeometryError
from ...optim.lm import Model, levenberg_marquardt
from ...optim.steps import DenseStep, cholesky_solve
from ...optim.structure import DENSE_MAX_UNKNOWNS, DIRECT_MAX_UNKNOWNS, lm_step
from ...robust import loss_rho
from .model import GaugeProjector

Array = NDArray[np.float64]

__all__ = ["DENSE_MAX_UNKNOWNS", "DIRECT_MAX_UNKNOWNS", "solve_schur_lm"]

#: default iteration cap per step kind (the same for all: a larger cap for the cheap dense
#: step was tried, 400, and made the robust stages of solve_toa at 12 x 6 crawl along flat
#: valleys towards far-field minima without converging, for no gain in the basin rate)
DEFAULT_MAX_IT = {"dense": 100, "reduced": 100, "cg": 100}
#: forcing-term range of the inexact (CG) steps: relative residual of each CG solve
CG_RTOL = (1e-8, 1e-3)


#: condition number (2-norm) above which a node's block counts as singular
COND_MAX = 1e12


def _inv_blocks(blocks: Array, first: int = 0) -> Array:
    """Inverse of each small symmetric block (node ``first`` onwards of its set); an unobservable
    node (a block of 2-norm condition number :data:`COND_MAX` or more) raises DegenerateGeometryError.

    The condition test by SVD costs five times the inverse, so it runs only on the blocks the
    Frobenius bound does not clear: ``cond_2(B) <= ||B||_F ||B^-1||_F``, from the inverse that
    is needed anyway, a factor of at most the block size above ``cond_2``; a block whose bound
    is under ``COND_MAX / 10`` (a margin for the inverse's own error, relative ``cond eps``)
    passes the test without its SVD. Same decisions and the same inverse as the SVD of every block.
    """
    with np.errstate(all="ignore"):
        try:
            Binv = np.asarray(np.linalg.inv(blocks), dtype=np.float64)
            bound = np.sqrt(np.einsum("kpq,kpq->k", blocks, blocks) * np.einsum("kpq,kpq->k", Binv, Binv))
            inv: Array | None = Binv
            suspect = ~(bound < COND_MAX / 10)  # NaN / inf bounds included
        except np.linalg.LinAlgError:  # an exactly singular block: the SVD test names it
            inv, suspect = None, np.ones(blocks.shape[0], bool)
    cond_ok = np.ones(blocks.shape[0], bool)
    if suspect.any():
        cond_ok[suspect] = np.linalg.cond(blocks[suspect]) < COND_MAX
    if not cond_ok.all():
        bad = first + int(np.nonzero(~cond_ok)[0][0])
        raise DegenerateGeometryError(
            f"node {bad} of the eliminated set is not determined by its observed ranges "
            "(too few or collinear observations); it needs at least d+1 (+1 per offset) "
            "ranges to non-collinear partners",
            kind="unobservable-node",
        )
    return inv if inv is not None else np.asarray(np.linalg.inv(blocks), dtype=np.float64)


class Grid:
    """All nK x nE pairs as 2-D arrays (dense data; missing entries carry weight 0)."""

    def __init__(self, nK: int, nE: int) -> None:
        self.nK, self.nE = nK, nE

    def pairs(self, a: Array, b: Array) -> Array:
        """``a_k - b_e`` for every pair."""
        return np.subtract.outer(a, b)

    def kx(self, v: Array) -> Array:
        """A per-K-node value on every pair."""
        return v[:, None]

    def ex(self, v: Array) -> Array:
        """A per-E-node value on every pair."""
        return v[None, :]

    def ksum(self, a: Array, b: Array | None = None) -> Array:
        """``sum_e a b`` per K node."""
        return a.sum(1) if b is None else np.einsum("ke,ke->k", a, b)

    def esum(self, a: Array, b: Array | None = None) -> Array:
        """``sum_k a b`` per E node."""
        return a.sum(0) if b is None else np.einsum("ke,ke->e", a, b)


class Pairs(Grid):
    """Only the observed pairs ``(k[m], e[m])`` as 1-D arrays (sparse data)."""

    def __init__(self, k: NDArray[np.intp], e: NDArray[np.intp], nK: int, nE: int) -> None:
        super().__init__(nK, nE)
        self.k, self.e = k, e

    def pairs(self, a: Array, b: Array) -> Array:
        return a[self.k] - b[self.e]

    def kx(self, v: Array) -> Array:
        return v[self.k]

    def ex(self, v: Array) -> Array:
        return v[self.e]

    def ksum(self, a: Array, b: Array | None = None) -> Array:
        return np.bincount(self.k, a if b is None else a * b, minlength=self.nK).astype(np.float64, copy=False)

    def esum(self, a: Array, b: Array | None = None) -> Array:
        return np.bincount(self.e, a if b is None else a * b, minlength=self.nE).astype(np.float64, copy=False)


class _Oriented:
    """The parameter vector split into the two sides' positions and offsets (views), from any
    ``lay`` with ``k_idx``, ``e_idx`` (:class:`selfcal.toa.engine.model._Layout`) and ``d``."""

    def __init__(self, lay: Any) -> None:
        self.k_idx, self.e_idx, self.d = lay.k_idx, lay.e_idx, lay.d
        self.hasK, self.hasE = self.k_idx.shape[1] > self.d, self.e_idx.shape[1] > self.d

    def split(self, theta: Array) -> tuple[Array, Array, Array | None, Array | None]:
        """Positions of the two sides and their offsets (None without)."""
        d = self.d
        K, E = theta[self.k_idx], theta[self.e_idx]
        return K[:, :d], E[:, :d], (K[:, d] if self.hasK else None), (E[:, d] if self.hasE else None)


def directions(xK: Array, xE: Array, pat: Grid) -> tuple[list[Array], Array]:
    """Unit-vector components ``U_p`` (d arrays, one value per pair) and the distances.

    ``U = (x_k - x_e) / |x_k - x_e|``, zero where two points coincide (the range is not
    differentiable there).
    """
    U = [pat.pairs(xK[:, p], xE[:, p]) for p in range(xK.shape[1])]
    dist = U[0] * U[0]
    for Up in U[1:]:
        dist += Up * Up
    np.sqrt(dist, out=dist)
    inv = np.divide(1.0, dist, out=np.zeros_like(dist), where=dist > 0)
    for Up in U:
        Up *= inv
    return U, dist


def diagonal_blocks(U: list[Array], w: Array, hasK: bool, hasE: bool, pat: Grid) -> tuple[Array, Array]:
    """The node blocks of the weighted normal matrix: ``A_k = sum_e w a a^T``, ``D_e = sum_k w b b^T``.

    ``a = [U, 1?]``, ``b = [-U, 1?]`` (the offset entry when that side has offsets). Both come
    from the same products ``w U_p U_q``, summed over the other axis. Returns (nK, mK, mK),
    (nE, mE, mE).
    """
    d = len(U)
    mK, mE = d + hasK, d + hasE
    A = np.zeros((pat.nK, mK, mK))
    D = np.zeros((pat.nE, mE, mE))
    for p in range(d):
        wUp = w * U[p]  # one temporary at a time: the working set stays ~(d + 4) x the data
        for q in range(p, d):
            A[:, p, q] = pat.ksum(wUp, U[q])
            D[:, p, q] = pat.esum(wUp, U[q])
        if hasK:
            A[:, p, d] = pat.ksum(wUp)
        if hasE:
            D[:, p, d] = -pat.esum(wUp)
        del wUp
    if hasK:
        A[:, d, d] = pat.ksum(w)
    if hasE:
        D[:, d, d] = pat.esum(w)
    for B, m in ((A, mK), (D, mE)):  # the lower triangles: copies of the upper ones
        for p in range(m):
            for q in range(p + 1, m):
                B[:, q, p] = B[:, p, q]
    return A, D


class _Reduced:
    """Matrix-free damped Schur complement ``S = A - B D^-1 B^T`` on the kept nodes.

    No coordinate is pinned: the Marquardt damping makes S positive definite and the caller
    projects the gauge out of the step (pinning would create soft modes of relative stiffness
    ~1/n that slow conjugate gradients down ~3x). The preconditioner is the inverse of the exact
    diagonal blocks of S (Schur-Jacobi).
    """

    def __init__(self, U: list[Array], w: Array, hasK: bool, hasE: bool, damping: float, pat: Grid,
                 precondition: bool = True, blocks: tuple[Array, Array] | None = None) -> None:
        d = len(U)
        self.U, self.w, self.hasK, self.hasE, self.d, self.pat = U, w, hasK, hasE, d, pat
        self.mK, self.mE = d + hasK, d + hasE
        # the undamped blocks depend on the linearisation only: a caller trying several
        # dampings at one point passes them (``blocks``) instead of summing them again
        A, D = blocks if blocks is not None else diagonal_blocks(U, w, hasK, hasE, pat)
        if damping > 0:
            A = A + damping * np.einsum("kpp->kp", A)[:, :, None] * np.eye(self.mK)
            D = D + damping * np.einsum("epp->ep", D)[:, :, None] * np.eye(self.mE)
        self.A = A
        self.Dinv = Dinv = _inv_blocks(D)
        if not precondition:  # the direct step needs no preconditioner
            return
        # c = w^2 b^T D_e^-1 b with b = [-U, 1?]
        c = np.zeros_like(w)
        for p in range(d):
            for q in range(p, d):
                c += U[p] * U[q] * pat.ex((1.0 if p == q else 2.0) * Dinv[:, p, q])
            if hasE:
                c -= U[p] * pat.ex(2.0 * Dinv[:, p, d])
        if hasE:
            c += pat.ex(Dinv[:, d, d])
        c *= w
        c *= w
        Sb = A.copy()
        for p in range(d):
            cUp = c * U[p]
            for q in range(p, d):
                v = pat.ksum(cUp, U[q])
                Sb[:, p, q] -= v
                if q != p:
                    Sb[:, q, p] -= v
            if hasK:
                v = pat.ksum(cUp)
                Sb[:, p, d] -= v
                Sb[:, d, p] -= v
            del cUp
        if hasK:
            Sb[:, d, d] -= pat.ksum(c)
        self.Pinv = _inv_blocks(Sb)

    def bt(self, x: Array) -> Array:
        """``B^T x``: K vector (nK mK,) to E vector (nE mE,)."""
        d, pat = self.d, self.pat
        X = x.reshape(-1, self.mK)
        t = self.U[0] * pat.kx(X[:, 0])
        for p in range(1, d):
            t += self.U[p] * pat.kx(X[:, p])
        if self.hasK:
            t += pat.kx(X[:, d])
        t *= self.w
        out = np.empty((pat.nE, self.mE))
        for q in range(d):
            out[:, q] = -pat.esum(t, self.U[q])
        if self.hasE:
            out[:, d] = pat.esum(t)
        return out.ravel()

    def b(self, y: Array) -> Array:
        """``B y``: E vector (nE mE,) to K vector (nK mK,)."""
        d, pat = self.d, self.pat
        Yv = y.reshape(-1, self.mE)
        t = self.U[0] * pat.ex(-Yv[:, 0])
        for q in range(1, d):
            t -= self.U[q] * pat.ex(Yv[:, q])
        if self.hasE:
            t += pat.ex(Yv[:, d])
        t *= self.w
        out = np.empty((pat.nK, self.mK))
        for p in range(d):
            out[:, p] = pat.ksum(t, self.U[p])
        if self.hasK:
            out[:, d] = pat.ksum(t)
        return out.ravel()

    def dinv(self, y: Array) -> Array:
        return np.einsum("epq,eq->ep", self.Dinv, y.reshape(-1, self.mE)).ravel()

    def smul(self, x: Array) -> Array:
        return np.einsum("kpq,kq->kp", self.A, x.reshape(-1, self.mK)).ravel() - self.b(self.dinv(self.bt(x)))

    def prec(self, x: Array) -> Array:
        return np.einsum("kpq,kq->kp", self.Pinv, x.reshape(-1, self.mK)).ravel()

    def dense(self) -> Array:
        """The reduced matrix ``S = A - B D^-1 B^T`` itself, (nK mK, nK mK).

        With ``D_e^-1 = L_e L_e^T`` (Cholesky) the pair block of ``B D^-1/2`` is
        ``W_ke = w_ke a_ke (L_e^T b_ke)^T``, so ``S = A - W W^T`` with ``W`` a dense
        (nK mK, nE mE) array (zero where a pair is not observed): O(nK nE mK mE) memory,
        O((nK mK)^2 nE mE) time, the price of a direct step (:data:`DIRECT_MAX_UNKNOWNS`).
        """
        pat, mK, mE = self.pat, self.mK, self.mE
        nK, nE = pat.nK, pat.nE
        L: Array = np.asarray(np.linalg.cholesky(self.Dinv), float)  # (nE, mE, mE); Dinv is positive definite (damped)
        # the Jacobian entries of each pair per parameter; None = the offset's constant 1
        a: list[Array | None] = [*self.U, *([None] if self.hasK else [])]
        b: list[Array | None] = [*(-Up for Up in self.U), *([None] if self.hasE else [])]
        W = np.zeros((nK, mK, nE, mE))
        for r in range(mE):
            G: Array | None = None  # (L_e^T b_ke)_r = sum_q b_q L_e[q, r], one value per pair
            for q in range(r, mE):
                Lq = pat.ex(L[:, q, r])
                bq = b[q]
                t = Lq if bq is None else bq * Lq
                G = t if G is None else G + t
            assert G is not None
            G = G * self.w
            for p in range(mK):
                ap = a[p]
                v = G if ap is None else G * ap
                if isinstance(pat, Pairs):
                    W[pat.k, p, pat.e, r] = v
                else:
                    W[:, p, :, r] = v
        W2 = W.reshape(nK * mK, nE * mE)
        S = -(W2 @ W2.T)
        idx = np.arange(nK)
        for p in range(mK):
            S[(idx * mK + p)[:, None], (idx * mK)[:, None] + np.arange(mK)] += self.A[:, p, :]
        return 0.5 * (S + S.T)


def solve_schur_lm(
    theta0: Array, Y: Array, lay: object, loss: str, f_scale: float, max_nfev: int | None, xtol: float,
    gauge: Callable[[Array], Array] | None = None,
    pairs: tuple[NDArray[np.intp], NDArray[np.intp]] | None = None, step: str = "auto",
) -> tuple[Array, bool, int]:
    """Levenberg-Marquardt (Marquardt diagonal damping) on the range model, dense or Schur-reduced.

    Parameters
    ----------
    theta0 : (n,) start, receiver-major parameter vector (:mod:`selfcal.toa.engine.nls`).
    Y : (I, J) ranges, NaN = missing; or, with ``pairs``, the (m,) observed ranges.
    pairs : None (dense Y) or ``(i, j)``, the receiver and source index of each entry of Y:
        the observed-pairs path (:class:`Pairs`), O(m) memory and time per product.
    lay : the :class:`selfcal.toa.engine.model._Layout` (kept / eliminated sides).
    loss, f_scale : robust loss and its scale (metres).
    max_nfev : iteration cap (default :data:`DEFAULT_MAX_IT` of the step kind); xtol : relative step tolerance.
    gauge : ``theta -> Q`` orthonormal gauge basis (n, g) to project each step off; default
        None, the same projector formed analytically
        (:class:`selfcal.toa.engine.model.GaugeProjector`).
    step : the step solver (:class:`RangeModel`): "dense", "reduced", "cg" or "auto"
        (default): :func:`selfcal.optim.structure.lm_step`, the one rule (dense up to 120
        unknowns, else the formed reduced system while forming it is cheap, else CG).

    Returns
    -------
    (theta, converged, iterations).

    Notes
    -----
    Each Schur step solves the reduced system on the smaller node set by Schur-Jacobi
    preconditioned CG (inexact Newton, Eisenstat-Walker forcing term), then back-substitutes
    the eliminated nodes; small reduced systems are formed and solved by Cholesky instead
    (:data:`DIRECT_MAX_UNKNOWNS`). The dense, reduced and CG (exact inner solve) steps give the
    same iterates (tested). Robust losses run iteratively reweighted normal equations (weights
    rho'(z)), whose fixed points are the stationary points of the robust cost.
    """
    k_is_r = lay.k_is_receivers  # type: ignore[attr-defined]
    k_idx, e_idx = lay.k_idx, lay.e_idx  # type: ignore[attr-defined]
    n = lay.n  # type: ignore[attr-defined]
    if step not in ("auto", "dense", "reduced", "cg"):
        raise ValueError(f"step must be 'auto', 'dense', 'reduced' or 'cg', got {step!r}")
    mode = lm_step(n, k_idx.size, e_idx.size) if step == "auto" else step
    if pairs is None and mode == "dense":  # the dense step works on the observed entries
        ii, jj = np.nonzero(np.isfinite(Y))
        Y, pairs = np.asarray(Y, float)[ii, jj], (ii, jj)
    pat: Grid
    if pairs is None:
        YK = np.ascontiguousarray(Y if k_is_r else Y.T)
        pat = Grid(k_idx.shape[0], e_idx.shape[0])
    else:
        ki, ei = (pairs[0], pairs[1]) if k_is_r else (pairs[1], pairs[0])
        YK = np.asarray(Y, float)
        pat = Pairs(np.asarray(ki, np.intp), np.asarray(ei, np.intp), k_idx.shape[0], e_idx.shape[0])
    model = RangeModel(k_idx, e_idx, pat, YK, lay.d, lay.I, loss, f_scale, mode, gauge=gauge)  # type: ignore[attr-defined]
    out = levenberg_marquardt(model, theta0, max_iter=max_nfev or DEFAULT_MAX_IT[mode], xtol=xtol)
    return out.x, out.converged, out.iterations


class _BasisProjector:
    """``dx - Q Q^T dx`` in place (a given orthonormal gauge basis Q)."""

    def __init__(self, Q: Array) -> None:
        self.Q = Q

    def apply(self, dx: Array) -> Array:
        dx -= self.Q @ (self.Q.T @ dx)
        return dx


class RangeModel(Model, _Oriented):
    """The range model ``y = |x_k - x_e| + o_k + o_e`` on the driver, with its plug-ins.

    One evaluation (residuals, IRLS weights, unit vectors on the data's :class:`Grid` or
    :class:`Pairs` pattern) for every step solver:

    - ``"dense"`` (:class:`selfcal.optim.steps.DenseStep`): the Jacobian written into a
      preallocated (m, n) array (only its unit-vector entries change), ``J^T W J`` formed
      and Cholesky-factorised per trial; needs the :class:`Pairs` pattern;
    - ``"reduced"`` / ``"cg"`` (:class:`_SchurStep`): the damped system reduced onto the
      kept nodes, formed and factorised, or solved matrix-free by preconditioned CG.

    The parametrisation: all free with the gauge projected off each step
    (:class:`selfcal.toa.engine.model.GaugeProjector`, or a given basis ``gauge``), or (dense
    step only) the ``free`` parameters fitted, the others held and no gauge projected.

    Parameters
    ----------
    k_idx, e_idx : (nK, d + hasK), (nE, d + hasE) parameter indices of each node of the two
        sides (its d coordinates, then its offset when that side has offsets).
    pat : the pattern; y : the data in its shape ((nK, nE) with NaN = missing, or (m,)).
    d : dimension; I : number of receivers (the sign of the common-offset gauge direction).
    loss, f_scale : robust loss and its scale (metres); mode : the step solver.
    gauge : ``theta -> Q`` or None (see :func:`solve_schur_lm`); free : (n,) bool or None.
    """

    def __init__(self, k_idx: NDArray[np.intp], e_idx: NDArray[np.intp], pat: Grid, y: Array, d: int, I: int,
                 loss: str, f_scale: float, mode: str, gauge: Callable[[Array], Array] | None = None,
                 free: NDArray[np.bool_] | None = None) -> None:
        self.k_idx, self.e_idx, self.d, self.pat, self.mode, self.I, self.gauge = k_idx, e_idx, d, pat, mode, I, gauge
        self.loss, self.f_scale, self.linear = loss, f_scale, loss == "linear"
        self.hasK, self.hasE = k_idx.shape[1] > d, e_idx.shape[1] > d
        self.n = int(k_idx.size + e_idx.size)
        self.N = k_idx.shape[0] + e_idx.shape[0]
        self.fidx = None if free is None or bool(np.all(free)) else np.nonzero(free)[0]
        self.g0, self.it = 1.0, 0  # first gradient norm (the CG forcing term's reference), linearisations
        if isinstance(pat, Pairs):
            self.y, self.obs, self.w1 = y, None, np.ones(y.size)
            # each pair's places in theta: its two positions (m, d) and offsets (m,) gathered directly
            kc, ec = k_idx[pat.k], e_idx[pat.e]
            self.pk, self.pe = kc[:, 0] // d, ec[:, 0] // d  # node rows of the (N, d) position block
            self.ok, self.oe = (kc[:, d] if self.hasK else None), (ec[:, d] if self.hasE else None)
        else:
            self.obs = np.isfinite(y)
            self.y, self.w1 = np.where(self.obs, y, 0.0), self.obs.astype(float)
        if mode == "dense":
            if not isinstance(pat, Pairs):
                raise ValueError("the dense step needs the Pairs pattern")
            self._dense_setup()
        elif self.fidx is not None:
            raise ValueError("a free mask needs the dense step")

    def _dense_setup(self) -> None:
        """The preallocated Jacobian (its constant offset entries written) and the flat places
        of its unit-vector entries and of the normal matrix's diagonal."""
        pat, d, n = self.pat, self.d, self.n
        assert isinstance(pat, Pairs)
        m = pat.k.size
        ar = np.arange(m)
        self.Jf = np.zeros((m, n))
        kc, ec = self.k_idx[pat.k], self.e_idx[pat.e]
        if self.hasK:
            self.Jf[ar, kc[:, d]] = 1.0
        if self.hasE:
            self.Jf[ar, ec[:, d]] = 1.0
        self.Jflat = self.Jf.reshape(-1)
        self.posK = (ar[:, None] * n + kc[:, :d]).ravel()  # flat places of the unit-vector entries
        self.posE = (ar[:, None] * n + ec[:, :d]).ravel()
        nf = n if self.fidx is None else self.fidx.size
        self.dstep = np.arange(nf) * (nf + 1)

    def geometry(self, theta: Array) -> tuple[Any, Array]:
        """Unit-vector components ``U`` (d rows, one value per pair) and distances at ``theta``.

        On :class:`Pairs` the (m, d) differences are gathered from theta in one step and ``U``
        is their transpose (a (d, m) view for the dense step, which writes it back row-major;
        contiguous for the Schur steps); on :class:`Grid`, :func:`directions`."""
        if self.obs is not None:
            xK, xE, _, _ = self.split(theta)
            return directions(xK, xE, self.pat)
        P = theta[: self.N * self.d].reshape(self.N, self.d)
        Dm = P[self.pk] - P[self.pe]
        dist = np.sqrt(np.einsum("mp,mp->m", Dm, Dm))
        Dm *= np.divide(1.0, dist, out=np.zeros_like(dist), where=dist > 0)[:, None]  # 0 where points coincide
        return (Dm.T if self.mode == "dense" else np.ascontiguousarray(Dm.T)), dist

    def evaluate(self, theta: Array) -> tuple[float, tuple[Array, Array, Any]]:
        pat = self.pat
        U, f = self.geometry(theta)
        if self.obs is None:
            if self.ok is not None:
                f += theta[self.ok]
            if self.oe is not None:
                f += theta[self.oe]
        else:
            _, _, oK, oE = self.split(theta)
            if oK is not None:
                f += pat.kx(oK)
            if oE is not None:
                f += pat.ex(oE)
        f -= self.y
        if self.obs is not None:
            f[~self.obs] = 0.0
        if self.linear:
            return 0.5 * float(np.vdot(f, f) if self.obs is not None else f @ f), (f, self.w1, U)
        rho, w = loss_rho((f / self.f_scale) ** 2, self.loss)
        w = np.asarray(w, float) if self.obs is None else np.where(self.obs, w, 0.0)
        rsum = float(rho.sum()) if self.obs is None else float(rho[self.obs].sum())
        return 0.5 * self.f_scale**2 * rsum, (f, w, U)

    def projector(self, theta: Array) -> Any:
        """The gauge projector at ``theta`` (None for a partial refit)."""
        if self.fidx is not None:
            return None
        if self.gauge is not None:
            return _BasisProjector(self.gauge(theta))
        return GaugeProjector(theta, self.N, self.d, self.I, self.hasK and self.hasE)

    def jacobian(self, U: Array) -> Array:
        """The dense Jacobian at the unit vectors ``U`` (its unit-vector entries rewritten)."""
        u = U.T.ravel()  # (m, d) row-major: a view of geometry()'s array
        self.Jflat[self.posK] = u
        self.Jflat[self.posE] = -u
        return self.Jf if self.fidx is None else self.Jf[:, self.fidx]

    def linearize(self, theta: Array, state: tuple[Array, Array, Any]) -> Any:
        f, w, U = state
        proj = self.projector(theta)
        if self.mode == "dense":
            Jm = self.jacobian(U)
            if self.linear:
                H, g = np.dot(Jm.T, Jm), np.dot(Jm.T, f)
            else:
                Jw = Jm * w[:, None]
                H, g = np.dot(Jm.T, Jw), np.dot(Jw.T, f)
            return DenseStep(H, g, self.dstep, proj, self.fidx, self.n)
        self.it += 1
        step = _SchurStep(U, w, f, self, proj)
        self.g0 = step.gnorm if self.it == 1 else self.g0
        # inexact Newton forcing term (Eisenstat-Walker style): loose CG solves far from
        # the minimum, tight ones once the gradient has dropped (keeps the fast local rate)
        step.cg_rtol = float(np.clip(step.gnorm / max(self.g0, 1e-300), *CG_RTOL))
        return step


class _SchurStep:
    """The Schur step solver of :class:`RangeModel`: the damped system reduced to the kept
    nodes, solved directly (``mode="reduced"``) or by Schur-Jacobi preconditioned CG, the
    eliminated nodes back-substituted and the step projected off the gauge."""

    cg_rtol = CG_RTOL[1]

    def __init__(self, U: list[Array], w: Array, f: Array, rm: RangeModel, proj: Any) -> None:
        self.U, self.w, self.rm, self.pat, self.proj = U, w, rm, rm.pat, proj
        self.k_flat, self.e_flat, self.n, self.mode = rm.k_idx.ravel(), rm.e_idx.ravel(), rm.n, rm.mode
        self.blocks: tuple[Array, Array] | None = None  # the undamped diagonal blocks (first step)
        pat = rm.pat
        d = len(U)
        wf = w * f
        gK = np.empty((pat.nK, d + rm.hasK))
        gE = np.empty((pat.nE, d + rm.hasE))
        for p in range(d):
            gK[:, p] = pat.ksum(wf, U[p])
            gE[:, p] = -pat.esum(wf, U[p])
        if rm.hasK:
            gK[:, d] = pat.ksum(wf)
        if rm.hasE:
            gE[:, d] = pat.esum(wf)
        del wf
        self.gK, self.gE = gK.ravel(), gE.ravel()
        self.gnorm = float(np.sqrt(self.gK @ self.gK + self.gE @ self.gE))

    def step(self, lam: float) -> Array | None:
        from scipy.sparse.linalg import LinearOperator, cg

        if self.blocks is None:  # once per linearisation, whatever the number of damping trials
            self.blocks = diagonal_blocks(self.U, self.w, self.rm.hasK, self.rm.hasE, self.pat)
        try:
            red = _Reduced(self.U, self.w, self.rm.hasK, self.rm.hasE, lam, self.pat,
                           precondition=self.mode == "cg", blocks=self.blocks)
        except DegenerateGeometryError:
            return None
        gK, gE = self.gK, self.gE
        rhs = -gK + red.b(red.dinv(gE))
        nk = self.k_flat.size
        if self.mode == "reduced":
            xr = cholesky_solve(red.dense(), rhs)
            if xr is None:
                return None
            x = xr
        else:
            op = LinearOperator((nk, nk), matvec=red.smul, dtype=float)
            pc = LinearOperator((nk, nk), matvec=red.prec, dtype=float)
            x, _ = cg(op, rhs, rtol=self.cg_rtol, maxiter=500, M=pc)
        y = red.dinv(-gE - red.bt(x))
        del red
        dx = np.zeros(self.n)
        dx[self.k_flat] = x
        dx[self.e_flat] = y
        if self.proj is not None:
            self.proj.apply(dx)  # no rigid drift (and no common offset shift)
        return dx

    def predicted(self, dx: Array) -> float:
        """``-(g^T dx + |J dx|_W^2 / 2)``: the cost decrease the Gauss-Newton model predicts."""
        U, pat = self.U, self.pat
        xK, xE, oK, oE = self.rm.split(dx)
        t = U[0] * (pat.kx(xK[:, 0]) - pat.ex(xE[:, 0]))
        for p in range(1, xK.shape[1]):
            t += U[p] * (pat.kx(xK[:, p]) - pat.ex(xE[:, p]))
        if oK is not None:
            t += pat.kx(oK)
        if oE is not None:
            t += pat.ex(oE)
        gd = float(self.gK @ dx[self.k_flat] + self.gE @ dx[self.e_flat])
        return -(gd + 0.5 * float(np.sum(self.w * t * t)))
