"""Steps 6-9 of :func:`selfcal.toa.fit.finish`: the final fit judged and packaged as a :class:`ToaResult`.

6. the trust test (:func:`~selfcal.toa.result.residual_test` with a given noise,
   :func:`~selfcal.toa.result.geometry_test` without) -> ``status`` / ``message``;
7. the result in the caller's numbering, dropped nodes as NaN rows;
8. the determinacy test (:func:`~selfcal.toa.verdict.trust.determinacy_test`) on the result's own
   covariances: more than half of the nodes undetermined fails the result, fewer are named;
9. the uniqueness test (:func:`~selfcal.toa.verdict.uniqueness.judge_fit`), then the notes of
   the outlier rule (nodes dropped, breakdown, no power).

Split from :mod:`selfcal.toa.fit` (steps 1-5: order, screen, search, outlier rounds, final
refit), which it sits below: everything here reads the final fit and never refits.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..errors import Status
from .engine.nls import NlsSolution, toa_model
from .options import verdicts_enabled
from .result import (
    MESSAGES,
    ToaResult,
    determinacy_test,
    geometry_test,
    n_parameters,
    residual_test,
)
from .verdict.determinacy import DENSE_MAX_UNKNOWNS, fisher_blocks
from .verdict.high_breakdown import majority_scale_check
from .verdict.leverage import leverages, outlier_rule_has_power
from .verdict.robust import noise_scale
from .verdict.uniqueness import judge_fit

__all__ = ["judge_final"]

Array = NDArray[np.float64]
Start = tuple[Array, Array, "Array | None", "Array | None"]


def judge_final(M: Array, Yc: Array, final: NlsSolution, Yf: Array, *, keep: tuple[NDArray[np.bool_], NDArray[np.bool_]],
                order: tuple[NDArray[np.intp], NDArray[np.intp]], outliers: NDArray[np.bool_], speed: float | None,
                label: str, iters: int, n_runs: int, dim: int, offsets: str, noise: float | None, sd: float | None,
                scale: float, covariance: Any, degenerate: bool, singular: bool, minima: Any,
                overflagged: list[str], breakdown: list[str], n_negative: int) -> ToaResult:
    """The :class:`ToaResult` of the final fit with its verdicts (module docstring).

    Parameters
    ----------
    M : (I, J) the caller's matrix (its units); Yc : (I, J) metres, in canonical order.
    final : the final refit on the kept nodes; Yf : its (kept) data, outliers as NaN.
    keep : (I,), (J,) bool kept receivers / sources (canonical order); order : the canonical
        permutations ``(pr, pc)``.
    outliers : (I, J) bool (canonical order); speed : the caller's speed, or None.
    label, iters, n_runs : method label, iterations and refinements so far.
    dim, offsets : the model; noise : the given noise (caller's units) or None; sd : it in
        metres; scale : metres per caller unit.
    covariance : the caller's covariance option; degenerate : the winner collapsed (no
        refit, FAILED_TEST); singular : the final covariance was refused.
    minima : (the search's other minima, the keep masks they were fitted on).
    overflagged, breakdown : the outlier rule's notes (nodes dropped, why it was not trusted).
    n_negative : negative entries of the input.

    Returns
    -------
    ToaResult
    """
    keep_r, keep_s = keep
    pr, pc = order
    # 6. trust
    n_par = n_parameters(int(keep_r.sum()), int(keep_s.sum()), dim, offsets)
    R_fit = final.residuals
    m = int(np.isfinite(R_fit).sum())
    dof = m - n_par
    noise_est = _noise_estimate(R_fit, dof)
    fit = geo = None
    passed: bool | None = None
    if sd is not None:
        fit = residual_test(R_fit / scale, sd / scale, n_par)
        passed = fit.passed
    elif not degenerate:
        geo = geometry_test(Yf, R_fit, leverages(Yf, *_start(final), offsets), dim, offsets)
        passed = geo.passed
    status, key = _verdict(passed, dof, final.converged, sd is not None)
    if degenerate:
        status, key = Status.FAILED_TEST, "degenerate"
    message = MESSAGES[key]
    if key == "chi2-failed" and fit is not None:
        message += f" (chi2 = {fit.chi2:.4g} for {fit.dof} dof, p = {fit.p_value:.3g})"
    if key == "cv-failed" and geo is not None:
        pt = geo.permutation
        perm = "" if pt is None else (f"; RSS ratio {pt.statistic:.3g} vs {pt.null_min:.3g} at least in "
                                      f"{pt.copies} permuted copies, p = {pt.p_value:.2g}")
        message += f" (median PRESS {geo.press:.3g} vs {geo.press_null:.3g} without geometry{perm})"

    # 7. back to the caller's numbering, 8. is the geometry determined?
    res = _package(M, Yc, final, keep_r, keep_s, pr, pc, outliers, speed, label, iters, n_runs, fit, geo,
                   status, message, noise, noise_est, dim, offsets, n_negative)
    if not verdicts_enabled():  # inside options.scores_only(): a model choice's candidate, steps 6-7 only
        return res
    blocks = None
    sig = sd if sd is not None else float(final.sigma)
    if covariance is not False and not degenerate and np.isfinite(sig) and sig > 0:
        # small networks: the blocks in the gauge of the well-placed nodes (trust.fisher_blocks);
        # larger ones (None) are judged on the fit's own blocks
        sb = fisher_blocks(Yf, *_start(final), offsets, sig)
        if sb is not None:  # in the caller's numbering, as _package embeds the result's blocks
            inv_r, inv_c = np.argsort(pr), np.argsort(pc)
            blocks = tuple(_embed_rows(B, k, inv, dim) for B, k, inv in ((sb[0], keep_r, inv_r),
                                                                          (sb[1], keep_s, inv_c)))
    res = _judge_determinacy(res, sd, float(final.sigma), covariance, key, singular, blocks)
    if not degenerate:  # 9. is it the only solution the data allow? (selfcal.toa.verdict.uniqueness)
        same = all(np.array_equal(a, b) for a, b in zip(minima[1], (keep_r, keep_s), strict=True))
        res = judge_fit(res, Yf, final, offsets, sd, n_par, (keep_r, keep_s), (pr, pc),
                        minima[0] if same else ())
    if overflagged:  # dropped: their position rests on fewer inliers than its flagged ranges
        res = dataclasses.replace(res, verdict_message=(
            f"{res.verdict_message}; {len(overflagged)} nodes dropped, more ranges flagged than a position can "
            f"hold (floor((n - unknowns) / 2)): {', '.join(overflagged[:8])}{' ...' if len(overflagged) > 8 else ''}"))
    if sd is None and not degenerate and not breakdown and res.verdict == int(Status.SUCCESS):
        # with the noise estimated, a fit of the majority at a far smaller scale means this one broke down
        maj = majority_scale_check(Yf, *_start(final), offsets, n_par)
        breakdown = breakdown + ([maj] if maj else [])
    if breakdown:
        text = "outlier breakdown: " + "; ".join(breakdown)
        failed = res.verdict == int(Status.FAILED_TEST)
        res = dataclasses.replace(res, outlier_breakdown=text, verdict=int(Status.FAILED_TEST),
                                  verdict_message=f"{res.verdict_message}; {text}" if failed else text)
    if sd is None and not degenerate and dof > 0 and not outlier_rule_has_power(Yf, *_start(final), offsets, dof):
        # the estimated-scale cut cannot flag a gross error of any size here: say so, not "0 outliers"
        res = dataclasses.replace(res, verdict_message=(
            f"{res.verdict_message}; outlier detection has no power at {dof} residual dof (a gross error on any "
            "one entry inflates the noise scale it is judged against; give the noise, or more measurements)"))
    return res


def _start(sol: NlsSolution) -> Start:
    return sol.receivers, sol.sources, sol.receiver_offsets, sol.source_offsets


def _verdict(test_passed: bool | None, dof: int, converged: bool, noise_given: bool) -> tuple[Status, str]:
    """Status and message key of the trust test (failed test first, then convergence)."""
    if dof <= 0:
        return Status.SUCCESS, "untestable"
    if test_passed is False:
        return Status.FAILED_TEST, "chi2-failed" if noise_given else "cv-failed"
    if not converged:
        return Status.NOT_CONVERGED, "not-converged"
    return Status.SUCCESS, "chi2-passed" if noise_given else "cv-passed"


def _embed_rows(B: Array, keep: NDArray[np.bool_], inv: NDArray[np.intp], dim: int) -> Array:
    """(kept, d, d) blocks in canonical order -> the caller's numbering, NaN for dropped nodes."""
    out = np.full((keep.size, dim, dim), np.nan)
    out[keep] = B
    return out[inv]


def _judge_determinacy(res: ToaResult, sd: float | None, sigma_fit: float, covariance: Any, key: str,
                       singular: bool = False, blocks: Any = None) -> ToaResult:
    """Attach the determinacy test (:func:`~selfcal.toa.verdict.trust.determinacy_test`) and apply its rule.

    The covariances of the final fit are ``sigma_fit^2 (J^T J)^+``; with a given noise ``sd``
    (metres) they are rescaled to it (the estimate has only ``m - n`` degrees of freedom,
    7 at 12 x 6 with both offsets). More than half of the tested nodes undetermined, or a
    determined core that its own ranges cannot identify, turns a success or a non-converged
    fit into FAILED_TEST ("undetermined"); fewer are named in the
    message of a result that keeps its status. An already failed or untestable result keeps
    its verdict (the test is still attached).
    """
    skipped = "covariance=False: no covariance to test" if covariance is False else None
    if sd is not None and sigma_fit > 0 and np.isfinite(sigma_fit):
        scale, noise, src = (sd / sigma_fit) ** 2, sd, "given"
    else:
        scale, noise, src = 1.0, sigma_fit, "estimated"
    Cr, Cs = res.receiver_cov, res.source_cov
    if blocks is not None:
        Cr, Cs, scale = blocks[0], blocks[1], 1.0  # fisher_blocks are at the noise already
    elif singular:
        skipped = (f"the normal equations are singular beyond the gauge and the network has more than "
                   f"{DENSE_MAX_UNKNOWNS} unknowns: the undetermined nodes are not named")
    used = None
    if res.residuals is not None:
        used = np.isfinite(res.residuals) & (~res.outliers if res.outliers is not None else True)
    det = determinacy_test(res.receivers, res.sources, Cr, Cs, noise=noise, cov_scale=scale,
                           noise_source=src, skipped=skipped, observed=used, offsets=res.offsets)
    if singular and blocks is None:
        det = dataclasses.replace(det, failed=True)
    status, message = Status(res.verdict), res.verdict_message
    n, m = det.n_undetermined, det.tested
    if singular and blocks is None and status != Status.FAILED_TEST and key != "untestable":
        status, message = Status.FAILED_TEST, MESSAGES["singular"]
    elif det.failed and status != Status.FAILED_TEST and key != "untestable":
        status = Status.FAILED_TEST
        message = MESSAGES["undetermined"].format(n=n, m=m, names=det.names())
        if det.core is not None:
            message += f"; {det.core}"
    elif n and status != Status.FAILED_TEST:
        message += MESSAGES["some-undetermined"].format(n=n, m=m, names=det.names())
    return dataclasses.replace(res, determinacy=det, verdict=int(status), verdict_message=message)


def _scaled(a: Array | None, k: float) -> Array | None:
    return None if a is None else a * k


def _noise_estimate(R: Array, dof: int) -> float:
    """Robust noise std of the final residuals: MAD times sqrt(m / dof) (fitted residuals shrink)."""
    f = R[np.isfinite(R)]
    if dof <= 0 or f.size == 0:
        return float("nan")
    return noise_scale(f) * float(np.sqrt(f.size / dof))


def _package(M: Array, Yc: Array, sol: NlsSolution, kr: NDArray[np.bool_], ks: NDArray[np.bool_],
             pr: NDArray[np.intp], pc: NDArray[np.intp], outliers: NDArray[np.bool_], speed: float | None,
             label: str, iters: int, n_runs: int, fit: Any, geo: Any, status: Status, message: str,
             noise: float | None, noise_est: float, dim: int, offsets: str, n_negative: int) -> ToaResult:
    I, J = M.shape
    k = 1.0 / speed if speed is not None else 1.0
    inv_r, inv_c = np.argsort(pr), np.argsort(pc)

    def embed(a: Array | None, keep: NDArray[np.bool_], inv: NDArray[np.intp], tail: tuple[int, ...] = ()) -> Array | None:
        if a is None:
            return None
        out = np.full((keep.size,) + tail, np.nan)
        out[keep] = a
        return out[inv]

    R = np.full((I, J), np.nan)
    R[np.ix_(kr, ks)] = np.where(np.isfinite(Yc[np.ix_(kr, ks)]), Yc[np.ix_(kr, ks)] - toa_model(*_start(sol)), np.nan)
    R = R[np.ix_(inv_r, inv_c)]
    d = embed(sol.receiver_offsets, kr, inv_r)
    o = embed(sol.source_offsets, ks, inv_c)
    if offsets == "both" and d is not None and o is not None:
        j0 = int(np.nonzero(np.isfinite(o))[0][0])  # the first kept source in the caller's numbering
        shift = o[j0]
        d, o = d + shift, o - shift
    mask = outliers[np.ix_(inv_r, inv_c)]
    resid_used = R[~mask & np.isfinite(R)]
    rms = float(np.sqrt(np.mean(resid_used**2))) if resid_used.size else float("nan")
    return ToaResult(
        receivers=embed(sol.receivers, kr, inv_r, (dim,)),  # type: ignore[arg-type]
        sources=embed(sol.sources, ks, inv_c, (dim,)),  # type: ignore[arg-type]
        receiver_offsets=None if d is None else d * k,
        source_offsets=None if o is None else o * k,
        receiver_cov=embed(sol.receiver_cov, kr, inv_r, (dim, dim)),  # type: ignore[arg-type]
        source_cov=embed(sol.source_cov, ks, inv_c, (dim, dim)),  # type: ignore[arg-type]
        residual_rms=rms * k,
        sigma=noise_est * k,
        converged=sol.converged,
        iterations=iters,
        method=label,
        n_missing=int((~np.isfinite(M)).sum()),
        n_starts=n_runs,
        receiver_offset_std=_scaled(embed(sol.receiver_offset_std, kr, inv_r), k),
        source_offset_std=_scaled(embed(sol.source_offset_std, ks, inv_c), k),
        speed=speed,
        residuals=R * k,
        fit=fit,
        verdict=int(status),
        verdict_message=message,
        outliers=mask,
        dropped_receivers=tuple(int(i) for i in np.sort(pr[~kr])),
        dropped_sources=tuple(int(j) for j in np.sort(pc[~ks])),
        noise=noise,
        noise_estimate=noise_est * k,
        geometry=geo,
        dim=dim,
        offsets=offsets,
        n_negative=n_negative,
    )
