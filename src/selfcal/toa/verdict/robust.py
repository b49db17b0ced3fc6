"""Measured data that are not clean: gross entries, outliers, nodes with too few ranges.

The rules here are statistical or counting arguments, never tuned on a data set:

- :func:`gross_entries`: entries so far from a robust two-way (median-polish) fit of the
  matrix that no initialiser should see them (Tukey's "far out" fence, 3 IQR beyond the
  quartiles). A 1e300 typo is one; they are excluded from the search and re-judged by
  :func:`outlier_mask` against the fitted model at the end.
- :func:`noise_scale`: normal-consistent MAD of residuals
  (:func:`scipy.stats.median_abs_deviation`).
- :func:`outlier_mask`: ``|t_ij| > k s`` for the studentized residuals
  ``t = r / sqrt(1 - h)`` (:func:`leverages`, :func:`studentized`), ``s`` the given noise
  or the MAD of t, ``k = Phi^-1(1 - alpha / (2 m))`` (Bonferroni over the m measurements:
  under Gaussian noise the probability that any inlier is flagged is at most ``alpha``).
- :func:`drop_unidentifiable`: nodes with fewer ranges than their unknowns + 1, removed
  iteratively (removing a source lowers its receivers' counts).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

__all__ = ["OUTLIER_ALPHA", "TUKEY_FAR", "drop_unidentifiable", "gross_entries", "elemental_subsets", "high_breakdown_start",
           "leverages",
           "lts_criterion", "noise_scale",
           "outlier_mask", "outlier_threshold", "required_ranges", "studentized"]

Array = NDArray[np.float64]
Mask = NDArray[np.bool_]

#: family-wise probability of flagging any inlier as an outlier (Gaussian noise)
OUTLIER_ALPHA = 0.01
#: Tukey's "far out" fence in interquartile ranges beyond the quartiles
TUKEY_FAR = 3.0


def _nanmedian_rows(R: Array) -> Array:
    """Row medians ignoring NaN, equal to ``np.nanmedian(R, axis=1)`` (NaN for an all-NaN row).

    One vectorised sort of the rows (NaN sort last) and the middle one or two finite
    entries of each: ``np.nanmedian`` loops over the rows in Python above 600 columns
    (``apply_along_axis``; 2.6 s of the 1000 x 1000 median polish, 20 calls).
    """
    S = np.sort(R, axis=1)
    n = R.shape[1] - np.isnan(R).sum(axis=1)
    lo = np.take_along_axis(S, np.maximum((n - 1) // 2, 0)[:, None], axis=1)[:, 0]
    hi = np.take_along_axis(S, (n // 2)[:, None], axis=1)[:, 0]  # n // 2 <= n - 1 when n >= 1
    with np.errstate(invalid="ignore"):
        med = (lo + hi) / 2
    med[n == 0] = np.nan
    return med


def _median_polish(Y: Array, iterations: int = 10) -> Array:
    """Residuals of Tukey's median polish ``y_ij ~ m + a_i + b_j`` over the observed entries.

    Stops early at a fixed point (every row and column median exactly 0: further sweeps
    would change nothing), so the result equals that of all ``iterations`` sweeps.
    """
    R = np.array(Y, dtype=float)
    if R.size == 0:
        return R
    with np.errstate(all="ignore"):
        for _ in range(iterations):
            a = _nanmedian_rows(R)
            a = np.where(np.isfinite(a), a, 0.0)
            R = R - a[:, None]
            b = _nanmedian_rows(R.T)
            b = np.where(np.isfinite(b), b, 0.0)
            R = R - b[None, :]
            if not a.any() and not b.any():
                break
    return R


def gross_entries(Y: Array) -> Mask:
    """Entries beyond Tukey's far-out fence of the median-polish residuals (I, J) bool.

    The additive part ``a_i + b_j`` absorbs offsets and the typical range of each node;
    what is left has the geometric spread of the network. An entry more than 3 IQR beyond
    the quartiles of those residuals (a typo, 1e300, a reflection many times longer than
    the room) is excluded before any initialiser runs. The spread used is the IQR of the
    residuals plus that of the entries (the residuals' quartiles collapse on small
    matrices, where median polish zeroes a large share of them; over 2000 clean draws of
    5-9 nodes the largest clean entry reached 2.5 of the 3 spreads). The rule is deliberately loose: the
    final :func:`outlier_mask` re-judges every entry against the fitted model.
    """
    obs = np.isfinite(Y)
    if obs.sum() < 4:
        return np.zeros(Y.shape, bool)
    # scale down first so that 1e300 entries cannot overflow in the medians' arithmetic
    big = float(np.nanmax(np.abs(Y)))
    Z = Y / big if big > 0 else Y
    R = _median_polish(Z)
    v = R[obs]
    q1, q3 = np.percentile(v, [25, 75])
    # median polish zeroes at least one residual per row and column, so on a small matrix
    # the quartiles of its residuals collapse (5 x 5: 9 exact zeros of 25) and clean
    # entries fell outside the fence (half of 2000 clean 5-9 node draws); the spread of the
    # entries themselves, which bounds what a geometry leaves in the residuals, is added
    z1, z3 = np.percentile(Z[obs], [25, 75])
    iqr = (q3 - q1) + (z3 - z1)
    if not iqr > 0:
        return np.zeros(Y.shape, bool)
    lo, hi = q1 - TUKEY_FAR * iqr, q3 + TUKEY_FAR * iqr
    return obs & ((R < lo) | (R > hi))


def noise_scale(residuals: Array, floor: float = 0.0) -> float:
    """Normal-consistent MAD of the finite residuals (``scipy.stats.median_abs_deviation``)."""
    from scipy.stats import median_abs_deviation

    f = np.asarray(residuals, float)
    f = f[np.isfinite(f)]
    if f.size == 0:
        return float("nan")
    return max(float(median_abs_deviation(f, scale="normal")), float(floor))


def outlier_threshold(m: int, alpha: float = OUTLIER_ALPHA, dof: int | None = None) -> float:
    """``k = Phi^-1(1 - alpha / (2 m))``: Bonferroni two-sided normal quantile for m measurements.

    With ``dof`` (the scale was estimated from residuals with that many degrees of freedom)
    Student's t quantile with ``dof`` degrees of freedom instead: a studentized residual over
    an estimated scale is t-distributed under Gaussian noise (the normal quantile for dof -> oo).
    """
    from scipy.stats import norm, t

    a = alpha / (2.0 * max(int(m), 1))
    return float(norm.isf(a) if dof is None else t.isf(a, max(int(dof), 1)))


def outlier_mask(residuals: Array, scale: float, alpha: float = OUTLIER_ALPHA, dof: int | None = None) -> Mask:
    """Entries with ``|r_ij| > k scale``, ``k`` from :func:`outlier_threshold` (NaN -> False)."""
    R = np.asarray(residuals, float)
    fin = np.isfinite(R)
    k = outlier_threshold(int(fin.sum()), alpha, dof)
    with np.errstate(invalid="ignore"):
        return fin & (np.abs(np.where(fin, R, 0.0)) > k * scale)


def required_ranges(dim: int, own_offset: bool) -> int:
    """Ranges a node needs: its ``dim (+1)`` unknowns plus one redundant range.

    With exactly ``dim`` ranges (``dim + 1`` with an offset) a node sits at one of the
    (generically two) intersections of its spheres: locally determined but with a mirror
    ambiguity and no redundancy to test it; one more range resolves both.
    """
    return int(dim) + int(own_offset) + 1


def drop_unidentifiable(observed: Mask, dim: int, offsets: str) -> tuple[Mask, Mask]:
    """Receivers and sources kept after iteratively removing nodes with too few ranges.

    Returns boolean keep-masks (I,), (J,). A node is removed while its count of observed
    ranges to kept partners is below :func:`required_ranges`.
    """
    has_r, has_s = offsets in ("receivers", "both"), offsets in ("sources", "both")
    need_r, need_s = required_ranges(dim, has_r), required_ranges(dim, has_s)
    keep_r = np.ones(observed.shape[0], bool)
    keep_s = np.ones(observed.shape[1], bool)
    while True:
        sub = observed & keep_r[:, None] & keep_s[None, :]
        bad_r = keep_r & (sub.sum(axis=1) < need_r)
        bad_s = keep_s & (sub.sum(axis=0) < need_s)
        if not bad_r.any() and not bad_s.any():
            return keep_r, keep_s
        keep_r &= ~bad_r
        keep_s &= ~bad_s


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


#: the bipartite inverse is used while a lower bound on the smallest eigenvalue of every
#: block it inverts (one over the largest absolute row sum of the inverse) stays this many
#: times above 1e-12 of ``trace(N)`` (an upper bound on N's largest eigenvalue): the cut of
#: the dense path (:func:`_normal_pinv`) with its margin; otherwise the dense path decides
_BLOCK_MARGIN = 1e3


class BipartiteInverse:
    """A generalised inverse ``G`` of ``N = J^T J`` from the bipartite structure of the TOA model.

    A range touches one receiver block ``[r_i, d_i]`` (row ``a_ij = [u_ij, 1]``) and one
    source block ``[s_j, o_j]`` (row ``b_ij = [-u_ij, 1]``), so ``N = [[A, B], [B^T, D]]``
    with ``A`` and ``D`` block diagonal (one ``p x p`` block per node). The side with more
    unknowns is eliminated (its blocks ``A_e = L_e L_e^T`` inverted one by one) and the
    Schur complement ``S = D - B^T A^-1 B = D - V^T V`` (``V = L^-1 B``) of the other side is
    formed; ``S`` is singular along the kept side's share of the gauge (Q's rows there,
    orthonormalised: ``Q_k``), so ``S^- = (S + c Q_k Q_k^T)^-1`` (``c`` S's largest diagonal
    entry) is a generalised inverse of it, and Rohde's formula ``G = [[A^-1 + A^-1 B S^- B^T
    A^-1, -A^-1 B S^-], [-S^- B^T A^-1, S^-]]`` one of N (Rohde 1965). Every quantity the
    checks take from ``(J^T J)^+`` is invariant to the choice of generalised inverse: the
    leverages ``j^T G j`` (the hat matrix ``J G J^T`` is the orthogonal projector onto the
    range of J for any of them; Searle, *Linear Models*, 1971, sec. 1.5) and the Fisher
    blocks after the S-transformation, which removes the gauge part in which two generalised
    inverses differ (:func:`selfcal.toa.verdict.determinacy.fisher_blocks`).

    Cost: ``O(m p^2 + n_e p^3)`` for the blocks, two products ``(n_k p)^2 (n_e p)`` and one
    Cholesky + inverse of ``n_k p`` (480 at 120 units) instead of the Cholesky + inverse of
    the whole ``n`` (960): 120 units, 36-54 ms against 116-137 ms for the dense lifted
    inverse in the same process (load 3). Tested against it (``tests/toa/test_postsolve_cost.py``).

    References
    ----------
    C. A. Rohde, "Generalized inverses of partitioned matrices", J. SIAM 13 (1965) 1033-1035.
    """

    swap: bool  # the sources' side eliminated (else the receivers')
    Linv: Array  # (nE, pe, pe) inverse Cholesky factors of the eliminated blocks
    Ainv: Array  # (nE, pe, pe) their inverses
    W: Array  # (nE pe, nK pk) L^-1 B S^-
    W4: Array  # the same, (nE, pe, nK, pk)
    V: Array  # (nE pe, nK pk) L^-1 B
    Sg: Array  # (nK pk, nK pk) S^-
    Ke: Array  # (nE, pe, pe) V_e S^- V_e^T
    Sd: Array  # (nK, pk, pk) diagonal blocks of S^-
    info_e: Array  # (nE, pe, pe) information blocks of the eliminated side
    info_k: Array  # (nK, pk, pk) of the kept side
    idx_e: NDArray[np.intp]  # (nE, pe) their places in the parameter vector
    idx_k: NDArray[np.intp]  # (nK, pk)
    rows_r: Array  # (I, J, pr) receiver parts of the Jacobian rows (zero where unobserved)
    rows_s: Array  # (I, J, ps) source parts
    nE: int
    nK: int
    pe: int
    pk: int

    def __init__(self, **parts: Any) -> None:
        for name in self.__annotations__:
            setattr(self, name, parts[name])

    @classmethod
    def build(cls, ne: NormalEquations) -> BipartiteInverse | None:
        """From a :class:`NormalEquations`; None when a block is singular or too ill-conditioned."""
        import scipy.linalg

        pat = ne.pattern
        I, J = pat.shape
        d = ne.dim
        has_r, has_s = ne.offsets in ("receivers", "both"), ne.offsets in ("sources", "both")
        r, s = ne.theta[:I * d].reshape(I, d), ne.theta[I * d:(I + J) * d].reshape(J, d)  # toa_jacobian's layout
        U = r[:, None, :] - s[None, :, :]
        nrm = np.linalg.norm(U, axis=2, keepdims=True)
        U = np.divide(U, nrm, out=np.zeros_like(U), where=nrm > 0) * pat[..., None]
        w = pat[..., None].astype(float)
        rows_r = np.concatenate([U, w], axis=2) if has_r else U  # (I, J, pr)
        rows_s = np.concatenate([-U, w], axis=2) if has_s else -U  # (I, J, ps)
        k = (I + J) * d
        idx_r = [np.arange(I)[:, None] * d + np.arange(d)]
        idx_s = [I * d + np.arange(J)[:, None] * d + np.arange(d)]
        if has_r:
            idx_r.append((k + np.arange(I))[:, None])
            k += I
        if has_s:
            idx_s.append((k + np.arange(J))[:, None])
        ir, js = np.concatenate(idx_r, axis=1), np.concatenate(idx_s, axis=1)
        swap = J * rows_s.shape[2] > I * rows_r.shape[2]  # keep the side with fewer unknowns
        if swap:  # eliminate the receivers' side: e = sources ... as written for e = receivers
            Ae, Bk = rows_s.transpose(1, 0, 2), rows_r.transpose(1, 0, 2)
            idx_e, idx_k = js, ir
        else:
            Ae, Bk = rows_r, rows_s
            idx_e, idx_k = ir, js
        nE, nK, pe = Ae.shape
        pk = Bk.shape[2]
        info_e = np.einsum("ekp,ekq->epq", Ae, Ae)  # the eliminated nodes' information blocks
        info_k = np.einsum("ekp,ekq->kpq", Bk, Bk)
        trace = float(np.einsum("epp->", info_e) + np.einsum("kpp->", info_k))
        if not trace > 0:
            return None
        floor = _BLOCK_MARGIN * 1e-12 * trace
        try:
            Linv = np.linalg.inv(np.linalg.cholesky(info_e))  # (nE, pe, pe)
        except np.linalg.LinAlgError:
            return None
        Ainv = np.matmul(Linv.transpose(0, 2, 1), Linv)
        if not np.all(np.isfinite(Ainv)) or 1.0 / np.max(np.abs(Ainv).sum(axis=2)) <= floor:
            return None
        Cc = np.einsum("epq,ekq->ekp", Linv, Ae)  # L_e^-1 a_ek
        V = np.einsum("ekm,ekq->emkq", Cc, Bk).reshape(nE * pe, nK * pk)
        S = -(V.T @ V)
        S4 = S.reshape(nK, pk, nK, pk)
        S4[np.arange(nK), :, np.arange(nK), :] += info_k
        U_q, sv, _ = np.linalg.svd(ne.Q[idx_k.ravel()], full_matrices=False)
        if sv.size < ne.Q.shape[1] or sv[-1] <= 1e-8 * sv[0]:
            return None  # part of the gauge does not reach the kept side: not this path
        c = float(np.max(np.diag(S)))
        if not c > 0:
            return None
        L, info = scipy.linalg.lapack.dpotrf(S + c * (U_q @ U_q.T), lower=1, clean=1)
        if info != 0:
            return None
        Sg, info = scipy.linalg.lapack.dpotri(L, lower=1)
        if info != 0:
            return None
        Sg = Sg + Sg.T - np.diag(np.diag(Sg))
        top = float(np.max(np.abs(Sg).sum(axis=1)))
        if not (np.isfinite(top) and top > 0 and 1.0 / top > floor):
            return None
        W = V @ Sg  # L^-1 B S^-, (nE pe, nK pk)
        W4 = W.reshape(nE, pe, nK, pk)
        Ke = np.einsum("emkq,enkq->emn", W4, V.reshape(nE, pe, nK, pk))  # V_e S^- V_e^T
        Sd = Sg.reshape(nK, pk, nK, pk)[np.arange(nK), :, np.arange(nK), :]
        return cls(swap=swap, Linv=Linv, Ainv=Ainv, W=W, W4=W4, V=V, Sg=Sg, Ke=Ke, Sd=Sd,
                   info_e=info_e, info_k=info_k, idx_e=idx_e, idx_k=idx_k, rows_r=rows_r, rows_s=rows_s,
                   nE=nE, nK=nK, pe=pe, pk=pk)

    def hat(self, ii: NDArray[np.intp], jj: NDArray[np.intp], a: Array, b: Array) -> Array:
        """``j^T G j`` for the Jacobian rows of entries (ii, jj): receiver part ``a`` (m, pr), source part ``b`` (m, ps)."""
        e, k, ae, bk = (jj, ii, b, a) if self.swap else (ii, jj, a, b)
        c = np.einsum("mpq,mq->mp", self.Linv[e], ae)
        return (np.einsum("mp,mp->m", c, c) + np.einsum("mp,mpq,mq->m", c, self.Ke[e], c)
                - 2.0 * np.einsum("mp,mpq,mq->m", c, self.W4[e, :, k, :], bk)
                + np.einsum("mp,mpq,mq->m", bk, self.Sd[k], bk))

    def pattern_hat(self, pattern: Mask) -> Array:
        """Leverages of the fitted entries, row-major order of ``pattern``."""
        ii, jj = np.nonzero(pattern)
        return self.hat(ii, jj, self.rows_r[ii, jj], self.rows_s[ii, jj])

    def diagonal_blocks(self) -> tuple[Array, Array, Array, Array]:
        """The nodes' diagonal blocks of G and of N: (G_receivers (I, pr, pr), G_sources (J, ps, ps),
        N_receivers, N_sources)."""
        Ge = self.Ainv + np.matmul(np.matmul(self.Linv.transpose(0, 2, 1), self.Ke), self.Linv)
        return (self.Sd, Ge, self.info_k, self.info_e) if self.swap else (Ge, self.Sd, self.info_e, self.info_k)

    def apply(self, X: Array) -> Array:
        """``G X`` for X (n, g) in the parameter order of :func:`selfcal.toa.engine.nls.toa_jacobian`."""
        nE, pe = self.nE, self.pe
        g = X.shape[1]
        xe = X[self.idx_e.ravel()]  # (nE pe, g), block order
        xk = X[self.idx_k.ravel()]
        ye = np.einsum("epq,eqg->epg", self.Linv, xe.reshape(nE, pe, g)).reshape(nE * pe, g)  # L^-1 x_e
        # G_ee x_e = A^-1 x_e + L^-T W V^T L^-1 x_e ; G_ek x_k = -L^-T W x_k
        # G_ke x_e = -W^T L^-1 x_e                 ; G_kk x_k = S^- x_k
        inner = (self.W @ (self.V.T @ ye) - self.W @ xk).reshape(nE, pe, g)
        out_e = (np.einsum("epq,eqg->epg", self.Ainv, xe.reshape(nE, pe, g))
                 + np.einsum("eqp,eqg->epg", self.Linv, inner)).reshape(nE * pe, g)
        out_k = self.Sg @ xk - self.W.T @ ye
        out = np.empty_like(X, dtype=float)
        out[self.idx_e.ravel()] = out_e
        out[self.idx_k.ravel()] = out_k
        return out


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


#: the elemental subsets per node of :func:`high_breakdown_start` give at least one free of gross
#: errors with this probability when 40 % of the node's ranges are gross
HB_CLEAN_SET = 0.99
HB_CONTAMINATION = 0.4
#: most alternating sweeps (all sources, then all receivers) of :func:`high_breakdown_start`
HB_SWEEPS = 20
#: the sweeps stop when one lowers the trimmed cost (:func:`lts_criterion`) by less than 1 %
HB_DECREASE = 0.99
#: above this many observed entries the outlier rule's start is not searched by
#: :func:`high_breakdown_start` (a cost bound, not a statistical one: its cost grows as
#: sweeps x subsets x entries, ~0.03 s at 12 x 40, ~0.4 s at 120 x 120 on a loaded core)
HB_MAX_ENTRIES = 6000
#: level of the F test by which the high-breakdown start must lower the trimmed cost to replace
#: the soft-L1 start of the outlier rule (:func:`selfcal.toa.fit.finish`)
HB_LEVEL = 0.01
#: inlier cut of the reweighting step, in robust standard deviations (Rousseeuw & Leroy 1987, p. 202)
HB_CUT = 2.5


def elemental_subsets(p: int, clean: float = HB_CLEAN_SET, contamination: float = HB_CONTAMINATION) -> int:
    """Random elemental sets of ``p`` ranges that contain one free of gross errors with probability ``clean``.

    ``K = ceil(log(1 - clean) / log(1 - (1 - contamination)^p))`` (Rousseeuw & Leroy 1987,
    eq. 5.1.11): 19, 34, 58 sets for p = 3, 4, 5 at 40 % contamination and 99 %.

    Examples
    --------
    >>> elemental_subsets(4)
    34
    """
    good = (1.0 - contamination) ** p
    return int(np.ceil(np.log(1.0 - clean) / np.log(1.0 - good)))


def _lmeds_side(A: Array, Y: Array, q: Array | None, own: bool, X0: Array, D0: Array | None, subsets: int,
                rng: np.random.Generator) -> tuple[Array, Array | None]:
    """Every node of one side re-placed from its ranges ``Y`` (N, M) to anchors ``A`` (M, d):
    LMedS over random elemental sets, then Gauss-Newton least squares on its inliers
    (:func:`high_breakdown_start`). ``q``: the anchors' offsets (subtracted from ``Y``);
    ``own``: each node has its own offset (``D0``). Nodes with at most ``2 p`` ranges (an
    elemental set could fit half of them), or no regular elemental set, keep ``X0``, ``D0``. Vectorised over the nodes (N x subsets x M)."""
    N, M = Y.shape
    d = A.shape[1]
    p = d + 1 + int(own)
    Yq = Y - q[None, :] if q is not None else Y
    obs = np.isfinite(Yq)
    n = obs.sum(axis=1)
    X = np.array(X0, float)
    D = None if D0 is None else np.array(D0, float)
    # the median of a node's residuals must not be fittable by one elemental set: n > 2 p
    # (with n <= 2 p ranges, p of them fitted exactly make the median 0 whatever the rest are)
    fit = n >= 2 * p + 1
    if not fit.any():
        return X, D
    idx = np.flatnonzero(fit)
    Yv, ob, nv = Yq[idx], obs[idx], n[idx]
    K = subsets if subsets else elemental_subsets(p)
    # p distinct observed anchors per set: the first p of a random order (unobserved sort last)
    keys = rng.random((idx.size, K, M))
    keys[np.broadcast_to(~ob[:, None, :], keys.shape)] = 2.0
    sub = np.argpartition(keys, p - 1, axis=2)[:, :, :p] if p < M else np.argsort(keys, axis=2)[:, :, :p]
    a = A[sub]  # (n, K, p, d)
    ys = np.take_along_axis(Yv, sub.reshape(idx.size, -1), axis=1).reshape(idx.size, K, p)
    # linearised trilateration: |x|^2 - 2 a.x + |a|^2 = (y - delta)^2, unknowns (x, |x|^2 - delta^2, delta)
    cols = [-2.0 * a, np.ones(sub.shape + (1,))] + ([2.0 * ys[..., None]] if own else [])
    Mx = np.concatenate(cols, axis=3)
    rhs = ys**2 - (a**2).sum(-1)
    with np.errstate(all="ignore"):
        # elemental sets whose anchors (nearly) share a line / plane are singular: skipped
        scale = np.abs(Mx).max(axis=(2, 3))
        regular = np.abs(np.linalg.det(Mx)) > 1e-9 * scale**p
        Mx[~regular] = np.eye(p)
        sol = np.linalg.solve(Mx, rhs[..., None])[..., 0]
        x = sol[..., :d]  # (n, K, d)
        dd = sol[..., d + 1] if own else np.zeros(sol.shape[:2])
        sq = (x**2).sum(-1)[..., None] - 2.0 * (x @ A.T) + (A**2).sum(-1)[None, None]
        r = np.sqrt(np.maximum(sq, 0.0)) + dd[..., None] - Yv[:, None, :]
        r = np.where(ob[:, None, :], np.abs(r), np.inf)  # unobserved sort last
        lo_k, hi_k = (nv - 1) // 2, nv // 2
        if np.all(nv == nv[0]):  # complete rows: one partition
            rs = np.partition(r, sorted({int(lo_k[0]), int(hi_k[0])}), axis=2)
        else:
            rs = np.sort(r, axis=2)
        lo = np.take_along_axis(rs, lo_k[:, None, None].repeat(K, 1), axis=2)[..., 0]
        hi = np.take_along_axis(rs, hi_k[:, None, None].repeat(K, 1), axis=2)[..., 0]
        med = (lo + hi) / 2  # the median of each set's residuals over the node's observed ranges
    med = np.where(regular & np.isfinite(med), med, np.inf)
    k = np.argmin(med, axis=1)
    best = med[np.arange(idx.size), k]
    ok = np.isfinite(best)
    # LMedS scale with its finite-sample factor (Rousseeuw & Leroy 1987, p. 202)
    s0 = 1.4826 * (1.0 + 5.0 / (nv - p)) * best
    xk = x[np.arange(idx.size), k]
    dk = dd[np.arange(idx.size), k]
    rk = r[np.arange(idx.size), k]  # (n, M) absolute residuals, NaN unobserved
    with np.errstate(invalid="ignore"):
        inl = ob & (rk <= HB_CUT * np.maximum(s0, 1e-12)[:, None])
    w = inl.astype(float)
    for _ in range(4):  # Gauss-Newton least squares on the inliers (the reweighting step)
        diff = xk[:, None, :] - A[None]
        dist = np.maximum(np.linalg.norm(diff, axis=2), 1e-12)
        res = np.where(ob, dist + dk[:, None] - np.nan_to_num(Yv), 0.0)
        Jm = diff / dist[..., None]
        if own:
            Jm = np.concatenate([Jm, np.ones(Jm.shape[:2] + (1,))], axis=2)
        Jw = Jm * w[..., None]
        JtJ = np.einsum("nmi,nmj->nij", Jw, Jm) + 1e-12 * np.eye(Jm.shape[2])
        Jtr = np.einsum("nmi,nm->ni", Jw, res)
        with np.errstate(all="ignore"):
            step = -np.linalg.solve(JtJ, Jtr[..., None])[..., 0]
        good = np.all(np.isfinite(step), axis=1) & (inl.sum(axis=1) >= Jm.shape[2])
        xk = xk + np.where(good[:, None], step[:, :d], 0.0)
        if own:
            dk = dk + np.where(good, step[:, d], 0.0)
    ok &= np.all(np.isfinite(xk), axis=1)
    X[idx[ok]] = xk[ok]
    if D is not None and own:
        D[idx[ok]] = dk[ok]
    return X, D


def high_breakdown_start(ranges: Array, receivers: Array, sources: Array, receiver_offsets: Array | None,
                         source_offsets: Array | None, offsets: str, sweeps: int = HB_SWEEPS,
                         subsets: int = 0, seed: int = 0) -> tuple[Array, Array, Array | None, Array | None]:
    """A start of high breakdown point: every node re-placed by least median of squares, alternating.

    Each sweep places every source, then every receiver, with the other side held at its
    current estimate: the position (and the node's own offset) minimising the median
    absolute residual of its ranges over random elemental sets (``dim + 1``
    ranges, ``+1`` with an offset; linearised trilateration), then least squares on the
    ranges within :data:`HB_CUT` of its finite-sample-corrected LMedS scale (Rousseeuw's
    reweighted LMedS). A node with at most ``2 p`` ranges keeps its place: one elemental set
    of ``p`` would fit half of them exactly and make their median 0. The sweeps stop when one lowers the trimmed cost
    (:func:`lts_criterion`) by less than 1 % (at most ``sweeps``); the best sweep is returned.
    Per node the breakdown point is that of LMedS, ``floor((n - p) / 2) / n``
    for ``n`` ranges and ``p`` unknowns, the most any regression-equivariant estimator can
    hold (:func:`selfcal.toa.fit._overflagged` drops the nodes beyond it). Started from a least-squares
    or soft-L1 fit that gross errors have pulled off, the sweeps move each node to the
    majority of its ranges: a start for the outlier rule that a smooth loss cannot give
    (soft-L1 and least squares break down together at ~30 % of ranges metres long).

    Parameters
    ----------
    ranges:
        (I, J) observed ranges (NaN missing), metres.
    receivers, sources:
        (I, d), (J, d) current estimate; ``receiver_offsets`` (I,), ``source_offsets`` (J,) or None.
    offsets:
        ``'none' | 'receivers' | 'sources' | 'both'``.
    sweeps, subsets:
        Most alternating sweeps; elemental subsets per node (0: :func:`elemental_subsets`).
    seed:
        Seed of the subsets' generator (the result is deterministic).

    Returns
    -------
    (receivers, sources, receiver_offsets, source_offsets) in the same layout.

    Notes
    -----
    The cost is ``O(sweeps * subsets * m)`` for ``m`` observed entries. It is a start, not an
    estimate: the outlier rule and the final least-squares fit judge it
    (:func:`selfcal.toa.fit.finish`).

    References
    ----------
    P. J. Rousseeuw and A. M. Leroy, *Robust Regression and Outlier Detection*, Wiley, 1987,
    ch. 5 (LMedS, its scale, reweighting).

    Examples
    --------
    >>> import numpy as np
    >>> from selfcal.toa import toa_model
    >>> g = np.random.default_rng(1)
    >>> r, s = g.uniform(0, 10, (8, 2)), g.uniform(0, 10, (12, 2))
    >>> Y = toa_model(r, s)
    >>> Y[0, :3] += 4.0  # three gross ranges
    >>> r2, s2, _, _ = high_breakdown_start(Y, r + 0.3, s - 0.3, None, None, "none")
    >>> bool(np.abs(toa_model(r2, s2) - toa_model(r, s)).max() < 1e-6)
    True
    """
    Y = np.asarray(ranges, float)
    rng = np.random.default_rng(seed)
    R, S = np.array(receivers, float), np.array(sources, float)
    own_r, own_s = offsets in ("receivers", "both"), offsets in ("sources", "both")
    D = None if receiver_offsets is None else np.array(receiver_offsets, float)
    O = None if source_offsets is None else np.array(source_offsets, float)
    n_par = (R.shape[0] + S.shape[0]) * R.shape[1] + (R.shape[0] if own_r else 0) + (S.shape[0] if own_s else 0)

    def trimmed() -> float:
        from ..engine.model import toa_model

        with np.errstate(all="ignore"):
            return lts_criterion(Y - toa_model(R, S, D, O), n_par)

    best = (trimmed(), R.copy(), S.copy(), None if D is None else D.copy(), None if O is None else O.copy())
    for _ in range(sweeps):
        S, O = _lmeds_side(R, Y.T, D, own_s, S, O, subsets, rng)
        R, D = _lmeds_side(S, Y, O, own_r, R, D, subsets, rng)
        now = trimmed()
        if not now < HB_DECREASE * best[0]:  # converged (or worse): keep the best sweep
            if now < best[0]:
                best = (now, R.copy(), S.copy(), None if D is None else D.copy(), None if O is None else O.copy())
            break
        best = (now, R.copy(), S.copy(), None if D is None else D.copy(), None if O is None else O.copy())
    return best[1], best[2], best[3], best[4]


def lts_criterion(residuals: Array, n_par: int) -> float:
    """Least-trimmed-squares objective: the sum of the ``h = floor((m + n_par + 1) / 2)`` smallest squared residuals.

    Its minimiser has breakdown point ``(m - h + 1) / m``, about one half (Rousseeuw 1984): a
    fit that holds the majority of the entries scores lower than one that gross errors pulled
    off, whatever they are. Used to choose the outlier rule's start among candidate fits.

    Parameters
    ----------
    residuals:
        Residuals of a fit (any shape, metres); NaN entries are ignored.
    n_par:
        Unknowns of the fit (sets ``h``).

    Returns
    -------
    float
        The trimmed sum of squares (m^2); ``inf`` without a finite residual.

    References
    ----------
    P. J. Rousseeuw, "Least median of squares regression", *J. Am. Stat. Assoc.* 79 (1984) 871-880.

    Examples
    --------
    >>> round(lts_criterion(np.array([0.1, -0.2, 0.1, 5.0, np.nan]), n_par=1), 9)  # h = 3 of 4 finite
    0.06
    """
    f = np.asarray(residuals, float)
    f = f[np.isfinite(f)]
    if f.size == 0:
        return float("inf")
    h = min(max((f.size + int(n_par) + 1) // 2, 1), f.size)
    return float(np.sort(f**2)[:h].sum())
