"""Leverages of the fitted range model and the one linearisation the checks after a fit share.

:func:`leverages` gives ``h_ij``, the diagonal of the hat matrix ``J (J^T J)^+ J^T`` at a
fitted geometry (gauge directions removed), for the studentized residuals of the outlier rule
(:func:`studentized`, :func:`selfcal.toa.verdict.robust.outlier_mask`);
:func:`outlier_rule_has_power` says whether that rule can see a gross error at all.
:func:`normal_equations` keeps ``J^T J`` and its generalised inverse
(:class:`selfcal.toa.verdict.bipartite.BipartiteInverse`, a Schur complement on the smaller node set, else
:func:`lifted_inverse`) for the final fit's leverages and the determinacy test's Fisher
blocks, reused while the geometry stays within the solver's step tolerance.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from .bipartite import BipartiteInverse
from .robust import OUTLIER_ALPHA, noise_scale, outlier_threshold

__all__ = ["NormalEquations", "kept_inverse", "leverages", "lifted_inverse", "normal_equations", "settled",
           "outlier_rule_has_power", "studentized"]

Array = NDArray[np.float64]
Mask = NDArray[np.bool_]

#: above this many unknowns the leverages are approximated by their mean n / m
LEVERAGE_MAX_UNKNOWNS = 2000


def leverages(ranges: Array, receivers: Array, sources: Array, receiver_offsets: Array | None,
              source_offsets: Array | None, offsets: str, held_out: NDArray[np.bool_] | None = None) -> Array:
    """Leverages of the observed entries at a fitted geometry, (I, J), NaN elsewhere.

    For an entry the fit used, ``h = j (J^T J)^+ j^T`` with J the Jacobian of the range
    model over the fitted entries (003 eq. 16, :func:`selfcal.toa.engine.nls.toa_jacobian`) and j
    its row: its residual has variance ``sigma^2 (1 - h)``. For an entry ``held_out`` of the
    fit (a suspected outlier) the same formula gives the prediction variance
    ``sigma^2 (1 + h)``. With few redundant ranges the leverages vary widely, so the outlier
    rule studentizes the residuals by them (:func:`studentized`). Problems with more than
    :data:`LEVERAGE_MAX_UNKNOWNS` unknowns use the mean leverage ``n / m`` everywhere.
    """
    from ..engine.nls import _pack, toa_jacobian

    Y = np.asarray(ranges, float)
    obs = np.isfinite(Y)
    out_mask = np.zeros(Y.shape, bool) if held_out is None else (np.asarray(held_out, bool) & ~obs)
    dim = receivers.shape[1]
    theta = _pack(receivers, sources, receiver_offsets, source_offsets)
    H = np.full(Y.shape, np.nan)
    m = int(obs.sum())
    gauge = dim * (dim + 1) // 2 + (1 if offsets == "both" else 0)
    n_free = theta.size - gauge
    if theta.size > LEVERAGE_MAX_UNKNOWNS:
        H[obs | out_mask] = min(n_free / max(m, 1), 1.0)
        return H
    ne = normal_equations(obs, receivers, sources, receiver_offsets, source_offsets, offsets)
    blk = ne.block()  # the bipartite generalised inverse, else the dense lifted one
    if ne.hat is None:
        ne.hat = blk.pattern_hat(obs) if blk is not None else _hat_rows(ne.J, ne.pinv())
    H[obs] = ne.hat
    if out_mask.any():
        if blk is not None:
            ii, jj = np.nonzero(out_mask)
            u = receivers[ii] - sources[jj]
            nrm = np.linalg.norm(u, axis=1, keepdims=True)
            u = np.divide(u, nrm, out=np.zeros_like(u), where=nrm > 0)
            one = np.ones((ii.size, 1))
            a = np.hstack([u, one]) if offsets in ("receivers", "both") else u
            b = np.hstack([-u, one]) if offsets in ("sources", "both") else -u
            H[out_mask] = blk.hat(ii, jj, a, b)
        else:
            Z = np.where(out_mask, 1.0, np.nan)
            H[out_mask] = _hat_rows(toa_jacobian(theta, Z, dim, offsets).tocsr(), ne.pinv())
    return H


#: Largest number of fitted entries for which :func:`outlier_rule_has_power` forms the
#: (m, m) residual projector; beyond it the rule is taken to have power (dof is then large).
POWER_MAX_ENTRIES = 3000


def outlier_rule_has_power(ranges: Array, receivers: Array, sources: Array, receiver_offsets: Array | None,
                           source_offsets: Array | None, offsets: str, dof: int,
                           alpha: float = OUTLIER_ALPHA) -> bool:
    """Can the estimated-scale outlier rule flag a single gross error of any size on any entry?

    A gross error ``g`` on fitted entry ``i`` leaves (to first order) the residuals
    ``g P e_i``, ``P = I - J (J^T J)^+ J^T`` the residual projector of the fit (rank
    ``dof``). Studentized (:func:`studentized`) and divided by their MAD
    (:func:`noise_scale`), entry ``i`` stands at a ratio that does not depend on ``g``: the
    error inflates the scale it is judged against. The rule (:func:`outlier_mask` with
    Student's t at ``dof``) can flag it only when that ratio exceeds
    :func:`outlier_threshold`. Returns False when no entry can be flagged: at 1-3 residual
    dof the t quantile is 8.9-300 while the ratio is of order ``sqrt(dof)``.

    Parameters
    ----------
    ranges:
        (I, J) fitted entries (NaN elsewhere), metres.
    receivers, sources:
        (I, d), (J, d) fitted positions; ``receiver_offsets``, ``source_offsets`` as fitted.
    offsets:
        ``'none' | 'receivers' | 'sources' | 'both'``.
    dof:
        Residual degrees of freedom of the fit (fitted entries minus parameters).
    alpha:
        Family-wise false-alarm probability of the rule.

    Returns
    -------
    bool
        True when some entry could be flagged (or the problem is too large to check).

    Notes
    -----
    Internally studentized residuals over the RMS scale obey ``|t_i| <= sqrt(dof)`` (Cook and
    Weisberg, *Residuals and Influence in Regression*, 1982, sec. 2.2.1); the MAD scale is
    not bounded that way, so the ratio is computed from the projector itself.
    """
    from ..engine.nls import _pack

    if dof <= 0:
        return False
    Y = np.asarray(ranges, float)
    obs = np.isfinite(Y)
    m = int(obs.sum())
    theta = _pack(receivers, sources, receiver_offsets, source_offsets)
    if theta.size > LEVERAGE_MAX_UNKNOWNS or m > POWER_MAX_ENTRIES:
        return True
    ne = normal_equations(obs, receivers, sources, receiver_offsets, source_offsets, offsets)
    J, Pinv = ne.J, ne.pinv()
    if ne.hat is None:
        ne.hat = _hat_rows(J, Pinv)
    d = 1.0 - ne.hat  # diagonal of P (the leverages' complement)
    ok = np.flatnonzero(d > 1e-8)
    if not ok.size:
        return False
    Jd = np.asarray(J.todense())
    root_d = np.sqrt(d[ok])
    k = outlier_threshold(m, alpha, dof)
    for c, i in enumerate(ok):  # column i of P formed on demand: the first entry with power ends the check
        col = -(Jd @ (Pinv @ Jd[i]))
        col[i] += 1.0
        t = col[ok] / root_d  # studentized residuals of an error on entry i
        s = noise_scale(t)
        if not s > 0 or abs(t[c]) > k * s:
            return True
    return False


#: the lifted normal matrix is inverted by Cholesky while its smallest eigenvalue stays this
#: many times above the eigenvalue cut of the fallback (1e-12 of the largest), both bounded
#: by the matrices' largest absolute row sums (>= their largest eigenvalues)
_LIFT_MARGIN = 1e3


#: a linearisation is reused for a geometry within the refinement's step tolerance of the one
#: it was formed at (the driver's small-step test ``|dx| <= xtol (xtol + |x|)`` with
#: ``refine_toa``'s default xtol): to the solver's precision the same estimate
REUSE_XTOL = 1e-10


class NormalEquations:
    """The linearisation of a TOA fit on its fitted entries, and what is derived from it once.

    Attributes
    ----------
    pattern: (I, J) bool, the fitted entries; offsets: the offsets mode.
    theta: (n,) packed parameters it was formed at (:func:`selfcal.toa.engine.nls.toa_jacobian`'s layout).
    J: (m, n) sparse Jacobian (CSR) over the fitted entries, row-major order of ``pattern``
        (formed on first use: the bipartite path does not need it).
    Q: (n, g) orthonormal gauge basis (:func:`selfcal.toa.engine.nls.gauge_basis`).
    N: (n, n) normal matrix ``J^T J`` (dense, formed on first use).
    hat: (m,) leverages of the fitted entries, once computed (:func:`leverages`).
    """

    def __init__(self, pattern: Mask, offsets: str, theta: Array, Q: Array, dim: int) -> None:
        self.pattern, self.offsets, self.theta, self.Q, self.dim = pattern, offsets, theta, Q, dim
        self.hat: Array | None = None
        self._J: Any = None
        self._N: Array | None = None
        self._lifted: tuple[Array | None, Array | None, float] | None = None
        self._pinv: Array | None = None
        self._block: BipartiteInverse | None | bool = False  # False: not tried yet

    @property
    def J(self) -> Any:
        """The sparse Jacobian (CSR), formed on first use (:func:`selfcal.toa.engine.nls.toa_jacobian`)."""
        if self._J is None:
            from ..engine.nls import toa_jacobian

            Z = np.where(self.pattern, 1.0, np.nan)
            self._J = toa_jacobian(self.theta, Z, self.dim, self.offsets).tocsr()
        return self._J

    @property
    def N(self) -> Array:
        """``J^T J`` (n, n), dense (formed on first use)."""
        if self._N is None:
            self._N = np.asarray((self.J.T @ self.J).todense())
        return self._N

    def block(self) -> BipartiteInverse | None:
        """:class:`BipartiteInverse` of ``N`` (computed once), None where it does not apply."""
        if self._block is False:
            self._block = BipartiteInverse.build(self)
        return self._block  # type: ignore[return-value]

    def lifted(self) -> tuple[Array | None, Array | None, float]:
        """:func:`lifted_inverse` of ``N`` with the gauge ``Q`` (computed once)."""
        if self._lifted is None:
            self._lifted = lifted_inverse(self.N, self.Q)
        return self._lifted

    def pinv(self) -> Array:
        """``N^+`` (:func:`_normal_pinv`, computed once)."""
        if self._pinv is None:
            self._pinv = _normal_pinv(self.N, self.Q, self.lifted())
        return self._pinv

    def same(self, pattern: Mask, offsets: str, theta: Array) -> bool:
        """Is this the linearisation at ``theta`` (within :data:`REUSE_XTOL`) on the same entries?"""
        return (offsets == self.offsets and theta.shape == self.theta.shape and pattern.shape == self.pattern.shape
                and bool(np.array_equal(pattern, self.pattern))
                and float(np.linalg.norm(theta - self.theta)) <= REUSE_XTOL * (REUSE_XTOL + float(np.linalg.norm(self.theta))))


_LAST: list[NormalEquations] = []  # the last linearisation (the flagging's, reused by the final checks)


def normal_equations(pattern: Mask, receivers: Array, sources: Array, receiver_offsets: Array | None,
                     source_offsets: Array | None, offsets: str) -> NormalEquations:
    """The linearisation (:class:`NormalEquations`) of a fit on the entries ``pattern``, reused when possible.

    The outlier rule's last leverages (the search's winner), the trust test's (the final fit)
    and the determinacy test's Fisher blocks all need ``J^T J`` of nearly one geometry: the
    final fit is refined from the winner on the same entries and, with nothing flagged,
    moves less than the refinement's step tolerance (120 units noise-free: 2.5e-13 m; 1 mm
    noise: 3e-10 m). The last linearisation is kept and reused while the entries are the same
    and the geometry is within :data:`REUSE_XTOL` of it: the solver cannot tell the two
    estimates apart, and the hat matrix and the Fisher blocks are smooth functions of it
    (their change is of the order of the displacement over the shortest range). One
    inversion (:class:`BipartiteInverse`, else the lifted matrix's ``potrf`` + ``potri``)
    instead of two (or three).

    Parameters
    ----------
    pattern: (I, J) bool, the fitted entries.
    receivers, sources, receiver_offsets, source_offsets: the fit (metres; offsets or None).
    offsets: the offsets mode.

    Returns
    -------
    NormalEquations
    """
    from ..engine.nls import _pack, gauge_basis

    pattern = np.asarray(pattern, bool)
    theta = _pack(receivers, sources, receiver_offsets, source_offsets)
    if _LAST and _LAST[0].same(pattern, offsets, theta):
        return _LAST[0]
    ne = NormalEquations(pattern.copy(), offsets, theta, gauge_basis(receivers, sources, offsets),
                         np.shape(receivers)[1])
    _LAST[:] = [ne]
    return ne


def kept_inverse(offsets: str) -> Any:
    """``(theta, pattern) -> BipartiteInverse | None``: the generalised inverse of the kept
    linearisation (:func:`normal_equations`) when it is at ``theta`` (within :data:`REUSE_XTOL`)
    on the entries ``pattern``, else None: what :func:`selfcal.toa.engine.nls.refine_toa`
    takes as ``normal_inverse`` for the final fit's covariance blocks
    (:func:`selfcal.toa.engine.covariance.blocks_from_inverse`)."""

    def at(theta: Array, pattern: Mask) -> BipartiteInverse | None:
        if _LAST and _LAST[0].same(np.asarray(pattern, bool), offsets, np.asarray(theta, float)):
            return _LAST[0].block()
        return None

    return at


def settled(pattern: Mask, receivers: Array, sources: Array, receiver_offsets: Array | None,
            source_offsets: Array | None, offsets: str, residuals: Array) -> bool:
    """Is the kept linearisation (:func:`normal_equations`) at this fit, and its Gauss-Newton step
    ``N^+ J^T f`` below the refinement's step tolerance (:data:`REUSE_XTOL`)?

    Then a least-squares refinement from the fit (whose damped steps are no longer than the
    Gauss-Newton step in the damping's metric) stops after one such step: the fit is its own
    refinement to the solver's precision (:func:`selfcal.toa.engine.nls.with_covariance`).
    False when no kept bipartite inverse is at the fit.
    """
    from ..engine.nls import _pack

    theta = _pack(receivers, sources, receiver_offsets, source_offsets)
    pattern = np.asarray(pattern, bool)
    if not (_LAST and _LAST[0].same(pattern, offsets, theta)):
        return False
    blk = _LAST[0].block()
    if blk is None:
        return False
    dx = blk.newton_step(np.asarray(residuals, float), _LAST[0].Q)
    tol = REUSE_XTOL * (REUSE_XTOL + float(np.linalg.norm(theta)))
    return bool(np.all(np.isfinite(dx)) and float(np.linalg.norm(dx)) <= tol)


def lifted_inverse(N: Array, gauge: Array) -> tuple[Array | None, Array | None, float]:
    """``M^-1`` of the gauge-lifted normal matrix ``M = N + c Q Q^T``, ``c`` N's largest diagonal entry.

    Parameters
    ----------
    N: (n, n) normal (Fisher) matrix ``J^T J`` of a TOA fit.
    gauge: (n, g) orthonormal gauge basis Q (:func:`selfcal.toa.engine.nls.gauge_basis`).

    Returns
    -------
    (C, diag_L, c): the symmetric inverse (n, n) and the diagonal of M's Cholesky factor, or
    ``(None, diag_L or None, c)`` when M is not numerically positive definite (the callers'
    own tests on ``C`` / ``diag_L`` decide whether to use it).

    Notes
    -----
    One LAPACK ``potrf`` + ``potri``. The leverages of the final fit (:func:`leverages`, the
    cross-validation) and the determinacy test's Fisher blocks
    (:func:`selfcal.toa.verdict.determinacy.fisher_blocks`) invert the same matrix once,
    through :func:`normal_equations`.
    """
    import scipy.linalg

    c = float(np.max(np.diag(N))) if N.size else 0.0
    C_out: Array | None = None
    dl: Array | None = None
    if c > 0:
        L, info = scipy.linalg.lapack.dpotrf(N + c * (gauge @ gauge.T), lower=1, clean=1)
        if info == 0:
            dl = np.abs(np.diag(L))
            C, info = scipy.linalg.lapack.dpotri(L, lower=1)  # lower triangle of M^-1, upper zero
            if info == 0:
                C_out = C + C.T - np.diag(np.diag(C))
    return C_out, dl, c


def _normal_pinv(N: Array, gauge: Array | None = None,
                 lifted: tuple[Array | None, Array | None, float] | None = None) -> Array:
    """``N^+`` of a normal matrix ``N = J^T J`` (n, n), eigenvalues below ``1e-12`` of the largest cut.

    With the gauge basis ``Q`` (:func:`selfcal.toa.engine.nls.gauge_basis`, orthonormal, the null
    space of ``N`` for a determined network) the lifted matrix ``M = N + c Q Q^T``
    (``c`` the largest diagonal entry of N) is positive definite and ``N^+ = M^-1 - Q Q^T / c``
    exactly: one Cholesky factorization and its inverse (LAPACK ``potrf`` + ``potri``, ~n^3
    flops; ``lifted``: that inverse already computed, :func:`lifted_inverse`), ~5x cheaper
    than the eigendecomposition. Where M is singular or its smallest
    eigenvalue may be within :data:`_LIFT_MARGIN` of the cut (directions the data do not
    determine beyond the gauge; bounded by row sums, a conservative test), and without
    ``gauge``, the eigendecomposition of N with the
    relative cut, as a singular-value cut of 1e-6 on J would (O(nnz n + n^3) instead of the
    O(m n^2) SVD of the dense (m, n) Jacobian: 4.7 s at 14,400 x 960, 0.2 s this way, 0.04 s
    by the lifted Cholesky).
    """
    if gauge is not None and N.size and gauge.shape[0] == N.shape[0]:
        C, _, c = lifted if lifted is not None else lifted_inverse(N, gauge)
        if C is not None:
            # lambda_min(M) >= 1 / max row sum |C|, lambda_max(N) <= max row sum |N|
            top = float(np.max(np.abs(C).sum(axis=1)))
            if np.isfinite(top) and top > 0 and 1.0 / top > _LIFT_MARGIN * 1e-12 * float(np.max(np.abs(N).sum(axis=1))):
                return C - (gauge / c) @ gauge.T
    lam, V = np.linalg.eigh(N)
    if lam.size == 0 or lam[-1] <= 0:
        return np.zeros_like(N)
    keep = lam > lam[-1] * 1e-12
    return (V[:, keep] / lam[keep]) @ V[:, keep].T


def _hat_rows(J: Any, Pinv: Array, block: int = 65536) -> Array:
    """``diag(J P J^T)`` for a sparse (m, n) J, in row blocks.

    The TOA Jacobian has the same number ``k`` of stored entries on every row (2d + offsets,
    :func:`selfcal.toa.engine.nls.toa_jacobian`): each diagonal entry is then the quadratic form of
    the row's ``k`` values with the ``k x k`` sub-block of P it touches, O(m k^2) (gathered
    in blocks, memory ``block x k^2``) instead of the (m, n) product ``J P`` (O(nnz n)).
    Other patterns take that product in row blocks of 4096.
    """
    J = J.tocsr()
    m = J.shape[0]
    out = np.empty(m)
    if m == 0:
        return out
    per = int(J.indptr[1] - J.indptr[0])
    if per > 0 and J.indptr[-1] == m * per and np.all(np.diff(J.indptr) == per):
        cols = J.indices.reshape(m, per)
        vals = J.data.reshape(m, per)
        for a in range(0, m, block):
            c, v = cols[a:a + block], vals[a:a + block]
            out[a:a + block] = np.einsum("ka,kab,kb->k", v, Pinv[c[:, :, None], c[:, None, :]], v)
        return out
    for a in range(0, m, 4096):
        Jb = J[a:a + 4096]
        out[a:a + 4096] = np.asarray(Jb.multiply(Jb @ Pinv).sum(axis=1)).ravel()
    return out


def studentized(residuals: Array, lev: Array, held_out: NDArray[np.bool_] | None = None) -> Array:
    """``r / sqrt(1 - h)`` for fitted entries, ``r / sqrt(1 + h)`` for ``held_out`` ones.

    NaN where ``1 - h`` is below 1e-8 (an entry the fit interpolates: its residual is 0
    whatever it measured, so it cannot be judged).
    """
    h = np.asarray(lev, float)
    ho = np.zeros(h.shape, bool) if held_out is None else np.asarray(held_out, bool)
    one = np.where(ho, 1.0 + h, 1.0 - h)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(one > 1e-8, np.asarray(residuals, float) / np.sqrt(np.maximum(one, 1e-300)), np.nan)


