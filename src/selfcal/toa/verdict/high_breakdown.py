"""The high-breakdown start of the outlier rule: nodewise least median of squares.

:func:`high_breakdown_start` re-places every node by LMedS over elemental subsets of its own
ranges (:func:`elemental_subsets`), then least squares on its inliers; :func:`lts_criterion`
(the trimmed cost, breakdown point about 1/2) decides whether it replaces the soft-L1 start
(:func:`selfcal.toa.fit.finish`). After the final fit, :func:`majority_scale_test` looks for a
fit of the majority of the ranges by graduated non-convexity and reports an outlier
breakdown when its residual scale is smaller than the final fit's by more than the outlier
rule's own cut (:func:`selfcal.toa.fit_result.judge_final`).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

__all__ = ["elemental_subsets", "high_breakdown_start", "lts_criterion", "lts_scale", "majority_scale_check", "majority_scale_test"]

Array = NDArray[np.float64]

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
#: the scale of the graduated trimmed refits of :func:`majority_scale_test` (least squares on the
#: entries within :data:`HB_CUT` of it, the reweighting cut of reweighted LMedS) shrinks by this
#: factor per round (Tukey-biweight-weighted refits instead reached the majority no more often, at
#: ~15x the cost: every refit weighted)
GNC_SHRINK = 0.7
#: ... and the refits stop after two rounds that do not lower the trimmed cost below this fraction
#: of its best: refits that only overfit the noise lower it ~1.15x per round (clean 12 x 40),
#: refits reaching a majority ~1.8x per round on average (to 1/1000 in about 12)
GNC_DECREASE = 0.8
#: most rounds of :func:`majority_scale_test`
GNC_ROUNDS = 12
#: Levenberg-Marquardt steps per round of :func:`majority_scale_test` (the weights change each round:
#: iteratively reweighted, not converged per round)
GNC_STEPS = 4
#: :func:`majority_scale_test` needs this many entries per unknown: the majority's fit keeps about
#: (m + n_par) / 2 of them, and below 2 its scale is biased low by the choice of which (clean 8 x 10
#: networks in 3-D, m / n_par = 1.67, with Laplace noise: 4 false breakdowns in 40 draws)
GNC_REDUNDANCY = 2


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


def majority_scale_test(ranges: Array, receivers: Array, sources: Array, receiver_offsets: Array | None,
                        source_offsets: Array | None, offsets: str, n_par: int, alpha: float | None = None,
                        rounds: int = GNC_ROUNDS) -> tuple[float, float, float] | None:
    """Is there a fit of the majority of the ranges at a scale the final fit's residuals are outliers of?

    From the final fit, graduated non-convexity (Black & Rangarajan 1996; Yang et al. 2020) with
    the truncated quadratic: least-squares refits (:func:`selfcal.toa.engine.nls.refine_toa`,
    :data:`GNC_STEPS` Levenberg-Marquardt steps per round: not converged per round) on the entries
    within :data:`HB_CUT` of a scale that starts at the normal-consistent MAD of the final
    residuals and shrinks by :data:`GNC_SHRINK` per round (never above the current fit's MAD),
    keeping the refit of lowest trimmed cost (:func:`lts_criterion`, breakdown point ~1/2). The refits
    follow the majority of the entries where one exists at a much smaller scale: a fit that
    gross errors spread over every node (the noise estimate inflated 100x, the residuals as
    Gaussian-looking as noise) is pulled towards it.

    The majority fit's scale ``s_m`` is estimated as the final fit's ``s_f`` is: least squares on
    its inliers, the entries within ``k`` of its scale (first its trimmed scale, :func:`lts_scale`,
    then the refit's), at most three C-steps, continued only while the scale falls; each scale is
    the normal-consistent MAD of the fitted entries times ``sqrt(m / (m - n_par))``
    (``fit_result._noise_estimate``). The trimmed
    refits alone overfit the noise (a weighted version's MAD was up to 14x below it on clean
    8 x 10 networks); least squares on every entry within ``k`` of a scale does not.

    The test: the final fit has broken down when ``s_f > k s_m``, ``k`` the outlier rule's own
    cut (:func:`~selfcal.toa.verdict.robust.outlier_threshold`: Bonferroni normal quantile over
    the ``m`` entries at family-wise level :data:`~selfcal.toa.verdict.robust.OUTLIER_ALPHA`;
    4.3 at 480 entries, 3.8 at 80): judged at the majority's scale, the final fit's typical
    residual is itself an outlier, so more than half of its entries would be flagged, the
    breakdown the rule reports when the noise is given. On a consistent fit both scales
    estimate the same noise and the ratio is ~1 (``benchmarks/outlier_sweep.py --families``
    and ``tests/toa/test_majority_scale.py`` for the measured spread). Being a search, the test
    can miss a majority it does not reach; it then reports nothing.

    Parameters
    ----------
    ranges:
        (I, J) the final fit's entries (NaN elsewhere: missing or removed), metres.
    receivers, sources, receiver_offsets, source_offsets:
        The final fit; ``offsets``: ``'none' | 'receivers' | 'sources' | 'both'``.
    n_par:
        Unknowns of the final fit (sets the trimmed cost's ``h``).
    alpha:
        Family-wise level of the cut (default the outlier rule's).
    rounds:
        Most refits.

    Returns
    -------
    ``(s_f, s_m, k)`` (metres, metres, the cut; the fit has broken down when ``s_f > k s_m``),
    or None when no scale could be formed or the entries are fewer than
    :data:`GNC_REDUNDANCY` times the unknowns (no test).

    Notes
    -----
    Cost: up to :data:`GNC_ROUNDS` least-squares refits of :data:`GNC_STEPS` steps and three
    C-steps, without covariance, on the sparse solver (a weighted refit only where a node keeps too
    few entries); on clean 12 x 40 networks 0.05 of the solve (``benchmarks/bench_postsolve.py``).

    References
    ----------
    M. J. Black and A. Rangarajan, "On the unification of line processes, outlier rejection,
    and robust statistics", *Int. J. Comput. Vision* 19 (1996) 57-91. H. Yang, P. Antonante,
    V. Tzoumas and L. Carlone, "Graduated non-convexity for robust spatial perception",
    *IEEE Robot. Autom. Lett.* 5 (2020) 1127-1134.

    Examples
    --------
    >>> import numpy as np
    >>> from selfcal.toa import toa_model
    >>> g = np.random.default_rng(0)
    >>> r, s = g.uniform(0, 10, (8, 2)), g.uniform(0, 10, (20, 2))
    >>> Y = toa_model(r, s) + g.normal(0, 0.01, (8, 20))
    >>> s_f, s_m, k = majority_scale_test(Y, r, s, None, None, "none", n_par=53)
    >>> bool(s_f < k * s_m)  # clean: the final fit holds
    True
    """
    from ...errors import DegenerateGeometryError, InputError
    from ...robust import mad_std
    from ..engine.model import toa_model
    from ..engine.nls import refine_toa
    from .robust import OUTLIER_ALPHA, outlier_threshold

    Y = np.asarray(ranges, float)
    obs = np.isfinite(Y)
    m = int(obs.sum())
    if m < GNC_REDUNDANCY * n_par:
        return None

    def resid(R: Array, S: Array, D: Array | None, O: Array | None) -> Array:
        with np.errstate(all="ignore"):
            return np.where(obs, Y - toa_model(R, S, D, O), np.nan)

    def mad(res: Array) -> float:  # residuals of a fit: already centred
        return float(mad_std(res, centre=False))

    def scale_of(res: Array, used: NDArray[np.bool_]) -> float:
        # the final fit's noise estimate (fit_result._noise_estimate): MAD times sqrt(m / dof)
        n_used = int(used.sum())
        return mad(np.where(used, res, np.nan)) * float(np.sqrt(n_used / max(n_used - n_par, 1)))

    def refit(R: Array, S: Array, D: Array | None, O: Array | None, W: Array, steps: int | None = None) -> Any:
        try:
            if np.all((W == 0.0) | (W == 1.0)):
                try:  # least squares on a subset: the sparse Schur solver, where every node keeps enough ranges
                    return refine_toa(np.where(W > 0, Y, np.nan), R, S, offsets=offsets, receiver_offsets0=D,
                                      source_offsets0=O, covariance=False, max_nfev=steps)
                except DegenerateGeometryError:
                    pass
            return refine_toa(Y, R, S, offsets=offsets, receiver_offsets0=D, source_offsets0=O,
                              weights=np.sqrt(W), covariance=False, max_nfev=steps, solver="lm")
        except (DegenerateGeometryError, InputError, np.linalg.LinAlgError, ValueError):
            return None  # the weights left a node undetermined: the search ends here

    R, S, D, O = receivers, sources, receiver_offsets, source_offsets
    res0 = resid(R, S, D, O)
    s_f = scale_of(res0, obs)
    if not (np.isfinite(s_f) and s_f > 0):
        return None
    def gnc(R: Array, S: Array, D: Array | None, O: Array | None) -> tuple[float, tuple]:
        res = resid(R, S, D, O)
        best, best_fit, scale, stall = lts_criterion(res, n_par), (R, S, D, O), mad(res), 0
        for _ in range(rounds):  # graduated non-convexity: trimmed refits at a shrinking scale
            if not scale > 0:
                break
            # least squares on the entries within the cut of the current scale
            sol = refit(R, S, D, O, (obs & (np.abs(np.nan_to_num(res)) < HB_CUT * scale)).astype(float), GNC_STEPS)
            if sol is None:
                break
            R, S, D, O = sol.receivers, sol.sources, sol.receiver_offsets, sol.source_offsets
            res = resid(R, S, D, O)
            now = lts_criterion(res, n_par)
            if now < GNC_DECREASE * best:
                best, best_fit, stall = now, (R, S, D, O), 0
            else:
                stall += 1
                if stall >= 2:
                    break
            scale = min(GNC_SHRINK * scale, mad(res))
        return best, best_fit

    k = outlier_threshold(m, OUTLIER_ALPHA if alpha is None else alpha)
    best, best_fit = gnc(R, S, D, O)
    # the majority fit's scale as the final fit's is estimated: least squares on its inliers (within
    # the cut k of its scale: first the trimmed one, lts_scale, then the refit's MAD times
    # sqrt(inliers / dof); C-steps): the trimmed refits overfit the noise (their raw MAD was up to
    # 14x below it on clean 8 x 10 networks), least squares on all entries within k of a scale does not
    fit = best_fit
    res = resid(*fit)
    s_m = lts_scale(res, n_par)
    if not s_f > k * s_m:
        # the trimmed scale is the lower one (it overfits): it already rules the breakdown out
        return s_f, s_m, k
    for _ in range(3):
        inl = obs & (np.abs(np.nan_to_num(res)) <= k * s_m)
        if int(inl.sum()) <= n_par:
            return None
        sol = refit(fit[0], fit[1], fit[2], fit[3], inl.astype(float))
        if sol is None:
            break
        fit = (sol.receivers, sol.sources, sol.receiver_offsets, sol.source_offsets)
        res = resid(*fit)
        now = scale_of(res, inl)
        done = now >= 0.99 * s_m  # C-steps only while the scale keeps falling (the larger one is kept)
        s_m = now
        if done:
            break
    return (s_f, s_m, k) if s_m > 0 else None


def majority_scale_check(ranges: Array, receivers: Array, sources: Array, receiver_offsets: Array | None,
                         source_offsets: Array | None, offsets: str, n_par: int) -> str | None:
    """:func:`majority_scale_test` on a final fit as the outlier-breakdown note (None: it holds).

    Not run above :data:`HB_MAX_ENTRIES` observed entries (the cost bound of the high-breakdown start).

    Parameters
    ----------
    ranges, receivers, sources, receiver_offsets, source_offsets, offsets, n_par:
        As :func:`majority_scale_test` (metres).

    Returns
    -------
    str or None
        The note (without the ``"outlier breakdown: "`` prefix) when the final fit's scale exceeds
        the majority fit's by more than the outlier cut, else None.

    Examples
    --------
    >>> import numpy as np
    >>> from selfcal.toa import toa_model
    >>> g = np.random.default_rng(0)
    >>> r, s = g.uniform(0, 10, (8, 2)), g.uniform(0, 10, (20, 2))
    >>> majority_scale_check(toa_model(r, s) + g.normal(0, 0.01, (8, 20)), r, s, None, None, "none", 53) is None
    True
    """
    if int(np.isfinite(np.asarray(ranges, float)).sum()) > HB_MAX_ENTRIES:
        return None
    out = majority_scale_test(ranges, receivers, sources, receiver_offsets, source_offsets, offsets, n_par)
    if out is None:
        return None
    s_f, s_m, k = out
    if not s_f > k * s_m:
        return None
    return (f"a fit of the majority of the ranges has residual scale {s_m:.3g} m against this fit's {s_f:.3g} m "
            f"({s_f / s_m:.3g}x, more than the outlier cut {k:.3g}): at its scale most of this fit's residuals are "
            "outliers (gross errors spread over the nodes, the noise estimate inflated; give the noise, or remove "
            "the faulty ranges)")


def lts_scale(residuals: Array, n_par: int) -> float:
    """Normal-consistent scale of the trimmed cost: ``sqrt(LTS / ((h - n_par) c_h))`` (metres).

    ``LTS`` is :func:`lts_criterion` (the ``h`` smallest squared residuals of ``m``), ``h - n_par``
    its degrees of freedom, ``c_h = 1 - 2 q phi(q) / (2 Phi(q) - 1)`` with
    ``q = Phi^-1((1 + h / m) / 2)`` the variance of a standard normal truncated to its central
    fraction ``h / m`` (Rousseeuw & Leroy 1987, p. 17; Croux & Rousseeuw 1992).

    Examples
    --------
    >>> r = np.random.default_rng(0).normal(0, 2.0, 20000)
    >>> bool(abs(lts_scale(r, 0) - 2.0) < 0.1)
    True
    """
    from scipy.stats import norm

    f = np.asarray(residuals, float)
    m = int(np.isfinite(f).sum())
    if m == 0:
        return float("nan")
    h = min(max((m + int(n_par) + 1) // 2, 1), m)
    q = float(norm.ppf((1.0 + h / m) / 2.0))
    c = 1.0 - 2.0 * q * float(norm.pdf(q)) / (2.0 * float(norm.cdf(q)) - 1.0) if h < m else 1.0
    return float(np.sqrt(lts_criterion(f, n_par) / (max(h - int(n_par), 1) * c)))
