"""One TOA model fitted robustly and honestly: what :func:`selfcal.toa.solve_toa` runs per model.

Steps (every rule stated in :mod:`selfcal.toa.verdict.robust`):

1. sort rows and columns canonically (:func:`selfcal.toa.search.canonical_order`);
2. screen gross entries (:func:`~selfcal.toa.verdict.robust.gross_entries`) out of the search;
3. drop nodes with too few ranges (:func:`~selfcal.toa.verdict.robust.drop_unidentifiable`) and
   check that what is left is identifiable (:func:`selfcal._checks.check_toa_counts`);
4. the search (:func:`selfcal.toa.search.search`);
5. the outlier rule on every entry against the fitted model, with the noise given or its
   robust estimate, and the final refit without the outliers (and with covariances); its
   first candidates come from a soft-L1 refit or, where its trimmed cost is significantly
   lower, the high-breakdown start (:func:`~selfcal.toa.verdict.high_breakdown.high_breakdown_start`);
Steps 6-9 judge and package the final fit (:mod:`selfcal.toa.fit_result`, below this module):

6. the trust test (:func:`~selfcal.toa.result.residual_test` with a given noise,
   :func:`~selfcal.toa.result.geometry_test` without) -> ``status`` / ``message``;
7. the result in the caller's numbering, dropped nodes as NaN rows;
8. the determinacy test (:func:`~selfcal.toa.verdict.trust.determinacy_test`) on the result's own
   covariances: more than half of the nodes undetermined fails the result, fewer are named;
9. the uniqueness test (:func:`~selfcal.toa.verdict.uniqueness.judge_fit`): an alternative solution
   the data do not reject (a flip, another minimum of the search), or no spare measurement
   at all, fails the result and names the ambiguous nodes.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..errors import DegenerateGeometryError, InputError
from ..robust import rejection_factor
from .engine.nls import NlsSolution, refine_toa, toa_model, with_covariance
from .fit_result import _start, judge_final
from .init.rank3_model import rank_identifiable
from .options import ToaOptions
from .result import (
    ToaResult,
    n_parameters,
    residual_test,
)
from .search import search
from .verdict.leverage import kept_inverse, leverages, studentized
from .verdict.leverage import settled as settled_fit
from .verdict.robust import (
    _check_kept,
    drop_unidentifiable,
    noise_scale,
    outlier_mask,
    outlier_threshold,
    screened,
)

__all__ = ["finish", "n_negative"]

Array = NDArray[np.float64]
Start = tuple[Array, Array, "Array | None", "Array | None"]


def n_negative(M: Array) -> int:
    """How many observed entries of ``M`` are zero or negative (measurements, reported)."""
    return int(np.sum(M[np.isfinite(M)] <= 0))


def finish(M: Array, dim: int, offsets: str, opts: ToaOptions, *, init: Any) -> ToaResult:
    """Fit one model robustly (module docstring) and package the :class:`ToaResult`."""
    # the options by their names (ToaOptions documents each)
    speed, loss, method, rng, f_scale = opts.speed, opts.loss, opts.method, opts.rng, opts.f_scale
    max_nfev, covariance, noise, budget = opts.max_nfev, opts.covariance, opts.noise, opts.budget
    scale = speed if speed is not None else 1.0
    I, J = M.shape
    Y = M * scale
    sd = None if noise is None else noise * scale
    # method="nls" is one start and one refinement: no outlier rounds (outliers are flagged)
    robust = loss != "linear" and method != "nls"
    robust_loss = "soft_l1" if loss == "auto" else loss
    final_loss = "linear" if loss == "auto" else loss
    fs = None if f_scale is None else f_scale * scale

    # 1. canonical order, 2. gross entries, 3. identifiable nodes
    pr, pc, Yc, gross, used, keep_r, keep_s = screened(Y, dim, offsets)
    start0 = None
    if not isinstance(init, str):
        r0, s0, d0, o0 = init
        start0 = (r0[pr], s0[pc], None if d0 is None else d0[pr], None if o0 is None else o0[pc])
    obs = np.isfinite(Yc)
    n_par_of = lambda kr, ks: n_parameters(int(kr.sum()), int(ks.sum()), dim, offsets)  # noqa: E731

    def sub(mask: NDArray[np.bool_], kr: NDArray[np.bool_], ks: NDArray[np.bool_]) -> Array:
        return np.where(mask, Yc, np.nan)[np.ix_(kr, ks)]

    def stop_rule(kr: NDArray[np.bool_], ks: NDArray[np.bool_]) -> Any:
        if sd is None:
            return None
        n_par = n_par_of(kr, ks)
        return lambda res: residual_test(res, sd, n_par).passed

    one = method == "nls"
    given = None if start0 is None else ("given", _restrict(start0, keep_r, keep_s))
    iters = n_runs = 0
    label = ""
    outliers = np.zeros((I, J), bool)
    best: NlsSolution | None = None
    prev_keep = (keep_r.copy(), keep_s.copy())
    minima: Any = ([], prev_keep)
    degenerate = False  # the best fit collapsed to a line / point (data that fit no dim-D geometry)
    ever = gross.copy()  # every entry screened or flagged in some round (outliers if its node is dropped)
    cut_u: Array | None = None  # the rule's residuals over its cut, wherever its cut is in force
    memo: dict[str, Any] = {}  # the last leverages of the outlier rule (leverage.leverages)
    breakdown: list[str] = []  # why the outlier rule cannot be trusted here (reported, FAILED_TEST)
    overflagged: list[str] = []  # nodes dropped: more flagged ranges than their position can hold
    # 4. the search (ML cost on the entries in use), 5. the outlier rule; a changed set of
    # inliers runs the search again from the winner (at most twice: the rule converges fast)
    if given is None and not one:  # the nested fit's start, and the block start of structured gaps
        given = _nested_start(sub(used, keep_r, keep_s), dim, offsets, rng, loss, fs, max_nfev)
    for rnd in range(3):
        Ys = sub(used, keep_r, keep_s)
        first = given if best is None else ("previous", _restrict(_embed_start(best, prev_keep, keep_r, keep_s),
                                                                   keep_r, keep_s))
        # later rounds (a changed set of inliers) refine the previous winner only
        again = rnd > 0
        out = search(Ys, dim, offsets, rng=rng, loss="linear" if loss == "auto" else loss, f_scale=fs,
                     starts=[first] if (one or again) and first is not None else None,
                     first=None if one or again else first,
                     stop=stop_rule(keep_r, keep_s), budget=1 if one or again else budget, max_nfev=max_nfev,
                     use_moves=opts.sweep and not one and not again)
        best, prev_keep = out.solution, (keep_r.copy(), keep_s.copy())
        winner, winner_entries = best, np.isfinite(Ys)  # the search's answer and the entries it fitted
        if rnd == 0:  # the race's other minima, on these nodes (the uniqueness test's candidates)
            minima = (out.minima, prev_keep)
        iters += out.iterations
        n_runs += out.refinements
        if not label:
            label = f"{out.start}+nls" + (f"+{'+'.join(out.moves)}" if out.moves else "")
        if not robust:
            break
        sub_obs = obs[np.ix_(keep_r, keep_s)]
        Yr = sub(obs & ~gross, keep_r, keep_s)
        # candidates: the rule on a robust refit over every entry that is not absurd; the
        # linear fit without them is what the rule then judges every entry against. Not run
        # where no fit the robust refit can reach from the winner flags anything
        # (_refit_cannot_flag: the winner fits every entry to far below the rule's resolution)
        if rnd == 0 and not _refit_cannot_flag(Yc, best, keep_r, keep_s, offsets, np.isfinite(Yr), memo,
                                               robust_loss, fs):
            try:
                rob = _refine(Yr, _start(best), dim, offsets, robust_loss, fs, max_nfev, False)
            except DegenerateGeometryError:
                # the winner is (nearly) collinear: no outlier rule on a geometry of lower
                # dimension; the trust test judges it below
                degenerate = True
                break
            iters += rob.iterations
            n_runs += 1
            # the candidates' fit: soft-L1 or the high-breakdown start, the lower trimmed cost wins
            hb = _high_breakdown(Yr, rob, offsets, n_par_of(keep_r, keep_s))
            from_hb, rob = hb is not rob, hb
            # studentized by the leverages of the least-squares fit rob started from (a function of
            # the geometry alone, within the noise of rob's): computed once, and reused when that
            # fit is the one the rule then judges on the same entries (no candidate changed it);
            # with a given noise a candidate also stands out from rob's own spread (rob is no ML fit)
            cand = _flag(Yc, rob, keep_r, keep_s, offsets, None, np.isfinite(Yr), memo, at=best)
            if sd is not None:
                cand &= _flag(Yc, rob, keep_r, keep_s, offsets, sd, np.isfinite(Yr), memo, at=best)
            cand |= gross[np.ix_(keep_r, keep_s)]
            if not np.array_equal(cand, sub_obs & ~used[np.ix_(keep_r, keep_s)]):
                trial = np.where(cand, np.nan, Yc[np.ix_(keep_r, keep_s)])
                kr_t, ks_t = drop_unidentifiable(np.isfinite(trial), dim, offsets)
                if (kr_t.all() and ks_t.all()) or (from_hb and kr_t.sum() > dim and ks_t.sum() > dim):
                    try:
                        # from the high-breakdown start, nodes the candidates leave too few ranges
                        # keep its place (the rule judges them); soft-L1 candidates that leave a node
                        # too few are not refitted (as before: ~4x the cost on LPS data4, same result)
                        lin = _refine(trial[np.ix_(kr_t, ks_t)], _restrict(_start(rob), kr_t, ks_t), dim, offsets,
                                      "linear", None, max_nfev, False)
                        iters += lin.iterations
                        n_runs += 1
                        best = _merged(rob, lin, kr_t, ks_t)
                        used = obs.copy()
                        # the rule's leverages need every node determined: the candidates of the
                        # nodes left out of lin stay "fitted" (the rule judges them all again)
                        used[np.ix_(keep_r, keep_s)] &= ~(cand & kr_t[:, None] & ks_t[None, :])
                    except DegenerateGeometryError:
                        pass
        fitted = used[np.ix_(keep_r, keep_s)]
        flags, u = _rule(Yc, best, keep_r, keep_s, offsets, sd, fitted, memo)
        cut_u = np.full((I, J), np.nan)  # the rule's cut in force on the entries kept: the final refit's
        cut_u[np.ix_(keep_r, keep_s)] = u  # covariance accounts for it (selfcal.robust.rejection_factor)
        if flags.sum() > 0.5 * sub_obs.sum():
            # beyond the MAD's breakdown point the "outliers" are the model (a wrong basin, a wrong
            # noise level, data of no geometry): remove nothing and let the trust test say so
            breakdown.append(f"{int(flags.sum())} of {int(sub_obs.sum())} entries flagged, more than the half "
                             "the MAD noise scale can hold (none removed)")
            outliers = gross.copy()
            used = obs & ~gross
            cut_u = None  # nothing removed by the rule
            break
        new_out = np.zeros((I, J), bool)
        new_out[np.ix_(keep_r, keep_s)] = flags
        new_used = obs & ~new_out
        ever |= new_out
        br, bs = _overflagged(obs, flags, keep_r, keep_s, dim, offsets)
        kr2, ks2 = drop_unidentifiable(new_used & ~br[:, None] & ~bs[None, :], dim, offsets)
        kr2 &= keep_r & ~br
        ks2 &= keep_s & ~bs
        try:
            _check_kept(new_used, kr2, ks2, dim, offsets)
        except DegenerateGeometryError:
            breakdown.append(f"removing the {int(flags.sum())} flagged entries would leave the network "
                             "unidentifiable (none removed)")
            outliers = gross.copy()  # removing the flagged entries would leave too little: keep them
            used = obs & ~gross
            cut_u = None  # nothing removed by the rule
            break
        overflagged += [f"r{int(pr[i])}" for i in np.flatnonzero(br)] + [f"s{int(pc[j])}" for j in np.flatnonzero(bs)]
        changed = not (np.array_equal(new_used, used) and kr2.sum() == keep_r.sum() and ks2.sum() == keep_s.sum())
        outliers, used, keep_r, keep_s = new_out, new_used, kr2, ks2
        if not changed:
            break
    assert best is not None
    label += f"+search({n_runs})" if n_runs > 1 else ""
    Yf = sub(used, keep_r, keep_s)
    st = _restrict(_embed_start(best, prev_keep, keep_r, keep_s), keep_r, keep_s)
    final = best
    singular = False  # the covariance was refused: singular beyond the gauge at the estimate
    # the search's converged least-squares answer on exactly these entries, whose Gauss-Newton
    # step is below the step tolerance, is its own refit (nls.with_covariance, leverage.settled)
    settled = (best is winner and final_loss == "linear" and best.solver == "schur-lm" and bool(best.converged)
               and all(np.array_equal(a, b) for a, b in zip(prev_keep, (keep_r, keep_s), strict=True))
               and np.array_equal(np.isfinite(Yf), winner_entries)
               and settled_fit(np.isfinite(Yf), *_start(best), offsets, Yf - toa_model(*_start(best))))
    if not degenerate:
        try:
            # the covariance from the outlier rule's linearisation where the final fit is at it
            cov_spec, kept = _cov_spec(covariance, pr, pc, keep_r, keep_s), kept_inverse(offsets)
            final = (with_covariance(best, Yf, offsets=offsets, covariance=cov_spec, normal_inverse=kept) if settled
                     else _refine(Yf, st, dim, offsets, final_loss, fs, max_nfev, cov_spec, kept))
        except DegenerateGeometryError:
            try:
                final = _refine(Yf, st, dim, offsets, final_loss, fs, max_nfev, False)
                singular = covariance is not False
            except DegenerateGeometryError:
                degenerate = True  # the search's winner is (nearly) collinear: reported, not raised
        if cut_u is not None and final_loss == "linear" and final.receiver_cov is not None:
            # least squares on the entries the rule kept: its covariance ignores that the cut
            # depends on the data (the hard-rejection sandwich, selfcal.robust.rejection_factor)
            g = rejection_factor(cut_u[np.ix_(keep_r, keep_s)], n_par_of(keep_r, keep_s))
            final = replace(final, receiver_cov=final.receiver_cov * g, source_cov=final.source_cov * g,
                            receiver_offset_std=_times(final.receiver_offset_std, np.sqrt(g)),
                            source_offset_std=_times(final.source_offset_std, np.sqrt(g)))
        iters += final.iterations if final is not best else 0
        n_runs += 1 if final.iterations > 0 else 0
    if degenerate:
        final = _without_covariance(best)
        keep_r, keep_s = prev_keep  # the nodes the winner was fitted on
        Yf = sub(used, keep_r, keep_s)
    if not robust and not degenerate:  # flagged for the reader, not removed
        outliers = np.zeros((I, J), bool)
        outliers[np.ix_(keep_r, keep_s)] = _flag(Yc, final, keep_r, keep_s, offsets, sd, np.isfinite(Yf))
    # entries screened or flagged on nodes dropped since stay outliers (they had NaN residuals and a clean mask)
    outliers |= ever & obs & ~(keep_r[:, None] & keep_s[None, :])

    # 6.-9. the trust, determinacy and uniqueness verdicts, in the caller's numbering
    return judge_final(M, Yc, final, Yf, keep=(keep_r, keep_s), order=(pr, pc), outliers=outliers, speed=speed,
                       label=label, iters=iters, n_runs=n_runs, dim=dim, offsets=offsets, noise=noise, sd=sd,
                       scale=scale, covariance=covariance, degenerate=degenerate, singular=singular, minima=minima,
                       overflagged=overflagged, breakdown=breakdown, n_negative=n_negative(M))


def _overflagged(obs: NDArray[np.bool_], flags: NDArray[np.bool_], kr: NDArray[np.bool_], ks: NDArray[np.bool_],
                 dim: int, offsets: str) -> tuple[NDArray[np.bool_], NDArray[np.bool_]]:
    """Kept nodes with more flagged ranges than their position can hold, (I,), (J,) bool.

    A node with ``n`` observed ranges and ``p`` unknowns (the dimension, plus its offset)
    can hold at most ``floor((n - p) / 2)`` outliers: the maximal breakdown point of any
    regression-equivariant estimator of its position (Rousseeuw & Leroy, *Robust
    Regression and Outlier Detection*, 1987, sec. 3.4). Beyond it its remaining ranges no
    longer outvote the flagged ones (which set may be the wrong one cannot be told), so the
    node is dropped, as a node with too few ranges is (:func:`drop_unidentifiable`).
    ``flags`` is the rule's mask on the kept block (kept I x kept J).
    """
    sub_obs = obs[np.ix_(kr, ks)]
    out = []
    for axis, own, keep in ((1, offsets in ("receivers", "both"), kr), (0, offsets in ("sources", "both"), ks)):
        n, f = sub_obs.sum(axis=axis), flags.sum(axis=axis)
        bad = np.zeros(keep.size, bool)
        bad[np.flatnonzero(keep)[f > np.maximum((n - (dim + int(own))) // 2, 0)]] = True
        out.append(bad)
    return out[0], out[1]


def _nested_start(Y: Array, dim: int, offsets: str, rng: np.random.Generator, loss: str, fs: float | None,
                  max_nfev: int | None) -> tuple[str, Start] | None:
    """The offsets-free fit with zero offsets: a start of every model that nests it.

    Zero offsets make the nested model's solution a point of the larger model with the same
    cost, so the larger model's search, which only accepts lower costs, never ends above it
    (before, ``offsets="receivers"`` ended at RSS 28.1 vs 24.0 for the offsets-free fit on the
    LPS flight data4). The nested model is found by the search's starts without moves (on
    large networks its one start, :func:`selfcal.toa.search.default_budget`).

    Where the missing pattern leaves a pair of receivers with fewer than ``dim + 1`` common
    sources (:func:`selfcal.toa.block_start.needs_block_start`), the incremental
    :func:`~selfcal.toa.block_start.block_start` joins the offsets-free search's starts (first,
    raced against the registry's, the lower cost wins), and ``offsets="none"`` gets that
    search's winner (large networks, whose search refines one start) or the block start itself
    (small ones, whose search races it with the registry) as its start.
    """
    from .block_start import block_start, needs_block_start
    from .search import MOVES_MAX_NODES, RACE_RUNGS

    I, J = Y.shape
    block = None
    if needs_block_start(np.isfinite(Y), dim):
        try:
            st = block_start(Y, dim, rng=rng)
        except (DegenerateGeometryError, InputError, np.linalg.LinAlgError, ValueError):
            st = None
        block = None if st is None else ("block", st)
    large = I + J > MOVES_MAX_NODES
    if offsets == "none" and (block is None or not large):
        return block
    if offsets == "both" and block is None and rank_identifiable(Y.shape[0], Y.shape[1], dim):
        # the 004 rank-3 initialiser estimates both offset kinds consistently here, so its start
        # is already near the larger model's minimum; an offsets-free search would only cost
        # (500 units: 4 s of a 6 s solve, same final RSS). offsets="auto" still chains the
        # nested fits explicitly (select.choose_offsets)
        return None
    # a large network's search refines its first start only: with the block start, a race of
    # two (the block start and the registry's one), each its rungs
    budget = 2 * (1 + RACE_RUNGS) if block is not None and large else None
    try:
        out = search(Y, dim, "none", rng=rng, loss="linear" if loss == "auto" else loss, f_scale=fs,
                     max_nfev=max_nfev, use_moves=False, first=block,
                     budget=budget)
    except (DegenerateGeometryError, InputError):
        return block if offsets == "none" else None
    sol = out.solution
    if offsets == "none":
        return (out.start, (sol.receivers, sol.sources, None, None))
    has_r, has_s = offsets in ("receivers", "both"), offsets in ("sources", "both")
    return ("nested", (sol.receivers, sol.sources, np.zeros(I) if has_r else None, np.zeros(J) if has_s else None))


def _without_covariance(sol: NlsSolution) -> NlsSolution:
    """``sol`` with NaN covariances (a degenerate geometry has none)."""
    import dataclasses

    def nan(a: Array | None) -> Array | None:
        return None if a is None else np.full(np.shape(a), np.nan)

    return dataclasses.replace(sol, receiver_cov=np.full(np.shape(sol.receiver_cov), np.nan),
                               source_cov=np.full(np.shape(sol.source_cov), np.nan),
                               receiver_offset_std=nan(sol.receiver_offset_std),
                               source_offset_std=nan(sol.source_offset_std))


def _refine(Y: Array, start: Start, dim: int, offsets: str, loss: str, fs: float | None, max_nfev: int | None,
            covariance: Any, normal_inverse: Any = None) -> NlsSolution:
    r0, s0, d0, o0 = start
    return refine_toa(Y, r0, s0, offsets=offsets, receiver_offsets0=d0, source_offsets0=o0, loss=loss,
                      f_scale=fs if loss != "linear" else None, max_nfev=max_nfev, covariance=covariance,
                      normal_inverse=normal_inverse)


def _cov_spec(cov: Any, pr: NDArray[np.intp], pc: NDArray[np.intp], kr: NDArray[np.bool_],
              ks: NDArray[np.bool_]) -> Any:
    """A covariance request in the caller's numbering, in the kept canonical order (modes unchanged)."""
    if not isinstance(cov, tuple):
        return cov

    def remap(idx: Any, perm: NDArray[np.intp], keep: NDArray[np.bool_]) -> Any:
        if idx is None:
            return None
        inv = np.argsort(perm)  # caller index -> canonical position
        pos = np.cumsum(keep) - 1  # canonical position -> kept position
        c = inv[np.asarray(idx, dtype=np.intp)]
        return np.sort(pos[c[keep[c]]])

    return remap(cov[0], pr, kr), remap(cov[1], pc, ks)


def _embed_start(sol: NlsSolution, keep: tuple[NDArray[np.bool_], NDArray[np.bool_]],
                 kr: NDArray[np.bool_], ks: NDArray[np.bool_]) -> Start:
    """A solution on the nodes ``keep`` as a full-size start (nodes outside ``keep`` at their centroid)."""
    pkr, pks = keep

    def grow(a: Array | None, k: NDArray[np.bool_], tail: tuple[int, ...]) -> Array | None:
        if a is None:
            return None
        out = np.empty((k.size,) + tail)
        out[:] = np.mean(a, axis=0)
        out[k] = a
        return out

    d = sol.receivers.shape[1]
    return (grow(sol.receivers, pkr, (d,)), grow(sol.sources, pks, (d,)),  # type: ignore[return-value]
            grow(sol.receiver_offsets, pkr, ()), grow(sol.source_offsets, pks, ()))


def _restrict(start: Start, kr: NDArray[np.bool_], ks: NDArray[np.bool_]) -> Start:
    r, s, d, o = start
    return r[kr], s[ks], None if d is None else d[kr], None if o is None else o[ks]


def _times(a: Array | None, g: float) -> Array | None:
    return None if a is None else a * g


def _residuals(Yc: Array, sol: NlsSolution, kr: NDArray[np.bool_], ks: NDArray[np.bool_]) -> Array:
    """Measured minus modelled on every observed entry of the kept nodes (outliers included)."""
    Ysub = Yc[np.ix_(kr, ks)]
    with np.errstate(all="ignore"):
        return np.where(np.isfinite(Ysub), Ysub - toa_model(*_start(sol)), np.nan)


def _flag(Yc: Array, sol: NlsSolution, kr: NDArray[np.bool_], ks: NDArray[np.bool_], offsets: str,
          sd: float | None, fitted: NDArray[np.bool_], memo: dict[str, Any] | None = None,
          at: NlsSolution | None = None) -> NDArray[np.bool_]:
    """The outlier rule's mask (:func:`_rule`)."""
    return _rule(Yc, sol, kr, ks, offsets, sd, fitted, memo, at)[0]


def _rule(Yc: Array, sol: NlsSolution, kr: NDArray[np.bool_], ks: NDArray[np.bool_], offsets: str,
          sd: float | None, fitted: NDArray[np.bool_], memo: dict[str, Any] | None = None,
          at: NlsSolution | None = None) -> tuple[NDArray[np.bool_], Array]:
    """The outlier rule (:mod:`selfcal.toa.verdict.robust`) on every observed entry of the kept nodes.

    ``fitted`` (kept I x kept J) marks the entries the fit ``sol`` used; their residuals are
    studentized by ``sqrt(1 - h)``, the others' (held out: suspected outliers, gross
    entries) by ``sqrt(1 + h)`` (prediction error). The scale is the given noise, else the
    MAD of the fitted entries' studentized residuals, floored at sqrt(machine eps) times the
    median range (the solver's precision). The leverages are those of the geometry ``at``
    (default ``sol``); ``memo`` keeps the last ones (same geometry object, same entries).
    Returns the mask and ``u``, each entry's studentized residual over the rule's cut (flagged
    where ``|u| > 1``, NaN where missing; kept I x kept J).
    """
    Ysub = Yc[np.ix_(kr, ks)]
    obs = np.isfinite(Ysub)
    held = obs & ~fitted
    R_all = _residuals(Yc, sol, kr, ks)
    H = _leverages(Ysub, sol if at is None else at, offsets, fitted, memo)
    T = studentized(R_all, H, held)
    dof = None
    if sd is not None:
        s_noise = sd
    else:
        s_noise = noise_scale(T[fitted], _scale_floor(Ysub))
        dof = int(fitted.sum()) - n_parameters(int(kr.sum()), int(ks.sum()), sol.receivers.shape[1], offsets)
    k = outlier_threshold(int(np.isfinite(T).sum()), dof=dof)
    with np.errstate(invalid="ignore"):
        return outlier_mask(T, s_noise, dof=dof) & obs, np.where(obs, T / (k * s_noise), np.nan)


def _scale_floor(Ysub: Array) -> float:
    """The outlier rule's floor on the estimated noise scale: sqrt(machine eps) x the median range."""
    return float(np.sqrt(np.finfo(float).eps) * float(np.nanmedian(np.abs(Ysub))))


def _leverages(Ysub: Array, geo: NlsSolution, offsets: str, fitted: NDArray[np.bool_],
               memo: dict[str, Any] | None) -> Array:
    """Leverages of the kept block's entries at the geometry ``geo`` fitted on ``fitted`` (the
    others observed are held out); ``memo`` keeps the last ones (same geometry object, same entries)."""
    held = np.isfinite(Ysub) & ~fitted
    key = (id(geo), fitted.tobytes(), held.tobytes(), fitted.shape)
    if memo is not None and memo.get("key") == key and memo.get("geo") is geo:
        return memo["H"]  # type: ignore[no-any-return]
    H = leverages(np.where(fitted, Ysub, np.nan), *_start(geo), offsets, held_out=held)
    if memo is not None:
        memo.update(key=key, geo=geo, H=H)
    return H


def _refit_cannot_flag(Yc: Array, best: NlsSolution, kr: NDArray[np.bool_], ks: NDArray[np.bool_], offsets: str,
                       fitted: NDArray[np.bool_], memo: dict[str, Any], loss: str, fs: float | None) -> bool:
    """Would the outlier rule's candidates from the robust refit of ``best`` be none, whatever it returns?

    The candidates are the entries the rule flags on the robust refit (:func:`refine_toa` with
    ``loss`` from ``best`` on the entries ``fitted``), studentized by ``best``'s leverages over
    an estimated scale of at least :func:`_scale_floor`. The refit only accepts steps that do
    not raise its cost ``sum_k f^2 rho(r_k^2 / f^2)``, which is at most ``sum_k r_k^2`` and grows
    with the scale ``f`` (:func:`selfcal.robust.loss_rho_inverse`): from ``best``'s residual sum
    of squares ``S`` every residual of its first fit is at most ``b1 = f sqrt(rho^-1(S / f^2))``,
    ``f`` the smallest scale it may use (``f_scale``, else
    :data:`~selfcal.toa.engine.nls.ROBUST_SCALE_FLOOR`), and of the second fit at the
    re-estimated scale (none when ``f_scale`` is given) at most ``f sqrt(rho^-1(m b1^2 / f^2))``.
    When no entry with that residual would be flagged, the refit cannot propose a candidate:
    the winner fits every entry to far below the rule's resolution (noise-free data, a fit
    exact to round-off), which is also the minimum of every robust loss, so there is no gross
    error it masks. True then, and the refit is not run (its result could not change the
    answer); False in every other case, including networks where the high-breakdown start
    competes with it (:func:`_high_breakdown`, no such bound) and a winner the refit would refuse
    as (nearly) collinear (the degenerate path decides those, as before).
    """
    from ..robust import loss_rho_inverse
    from .engine.model import _make_layout
    from .engine.nls import ROBUST_SCALE_FLOOR
    from .verdict.high_breakdown import HB_MAX_ENTRIES

    m = int(fitted.sum())
    if m <= HB_MAX_ENTRIES:
        return False
    R = _residuals(Yc, best, kr, ks)
    r = R[fitted]
    if not np.isfinite(r).all():
        return False
    f = ROBUST_SCALE_FLOOR if fs is None else float(fs)
    with np.errstate(all="ignore"):
        b = f * float(np.sqrt(loss_rho_inverse(float(r @ r) / f**2, loss)))
        if fs is None:  # the refit at the scale re-estimated from the first one
            b = f * float(np.sqrt(loss_rho_inverse(m * b * b / f**2, loss)))
    Ysub = Yc[np.ix_(kr, ks)]
    b += 64 * np.finfo(float).eps * float(np.nanmax(np.abs(Ysub)))  # the gauge fix's round-off
    if not np.isfinite(b):
        return False
    H = _leverages(Ysub, best, offsets, fitted, memo)
    # the largest studentized residual any such refit can have, on the entries the rule judges
    # (held-out entries are the gross ones, candidates anyway)
    bound = np.where(fitted, b, 0.0)
    T = studentized(np.where(np.isfinite(Ysub), bound, np.nan), H, np.isfinite(Ysub) & ~fitted)
    dof = m - n_parameters(int(kr.sum()), int(ks.sum()), best.receivers.shape[1], offsets)
    if outlier_mask(T, _scale_floor(Ysub), dof=dof).any():
        return False
    try:  # the refit's own refusal of a (nearly) collinear winner
        _make_layout(best.receivers, best.sources, offsets)
    except DegenerateGeometryError:
        return False
    return True


def _high_breakdown(Y: Array, rob: NlsSolution, offsets: str, n_par: int) -> NlsSolution:
    """``rob``, or the high-breakdown start from it where its trimmed cost is lower.

    :func:`~selfcal.toa.verdict.high_breakdown.high_breakdown_start` re-places every node by LMedS;
    :func:`~selfcal.toa.verdict.high_breakdown.lts_criterion` (breakdown point ~1/2) picks the fit that
    holds the majority of the entries ``Y`` (the kept block without gross entries). The start
    replaces ``rob`` only when its trimmed cost is lower by more than the ``1 - HB_LEVEL``
    quantile of F(k, k), ``k = h - n_par`` the trimmed sums' degrees of freedom: a different
    basin, not the noise refitted (on clean 8 x 10 networks the sweeps lower the trimmed cost
    by up to 1.4x, and candidates from that overfit flagged clean entries). Only the positions
    of the returned solution are meaningful to the outlier rule.
    """
    import dataclasses

    from .verdict.high_breakdown import (
        HB_LEVEL,
        HB_MAX_ENTRIES,
        high_breakdown_start,
        lts_criterion,
    )

    if int(np.isfinite(Y).sum()) > HB_MAX_ENTRIES:
        return rob
    r, s, d, o = high_breakdown_start(Y, *_start(rob), offsets)
    if not (np.all(np.isfinite(r)) and np.all(np.isfinite(s))):
        return rob
    from scipy.stats import f as fisher

    with np.errstate(all="ignore"):
        hb = Y - toa_model(r, s, d, o)
        mine = Y - toa_model(*_start(rob))
    m = int(np.isfinite(Y).sum())
    k = max((m + n_par + 1) // 2 - n_par, 1)  # the trimmed sums' residual degrees of freedom
    # a different basin, not the noise refitted: lower by more than F(k, k) at level HB_LEVEL
    if lts_criterion(hb, n_par) * float(fisher.isf(HB_LEVEL, k, k)) < lts_criterion(mine, n_par):
        return dataclasses.replace(rob, receivers=r, sources=s, receiver_offsets=d, source_offsets=o)
    return rob


def _merged(outer: NlsSolution, inner: NlsSolution, kr: NDArray[np.bool_], ks: NDArray[np.bool_]) -> NlsSolution:
    """``inner`` (fitted on the nodes ``kr``, ``ks``) with ``outer``'s positions for the others."""
    import dataclasses

    if kr.all() and ks.all():
        return inner

    def put(a: Array | None, b: Array | None, k: NDArray[np.bool_]) -> Array | None:
        if a is None or b is None:
            return b if a is None else a
        out = np.array(a, float)
        out[k] = b
        return out

    receivers, sources = np.array(outer.receivers, float), np.array(outer.sources, float)
    receivers[kr], sources[ks] = inner.receivers, inner.sources
    return dataclasses.replace(inner, receivers=receivers, sources=sources,
                               receiver_offsets=put(outer.receiver_offsets, inner.receiver_offsets, kr),
                               source_offsets=put(outer.source_offsets, inner.source_offsets, ks))


