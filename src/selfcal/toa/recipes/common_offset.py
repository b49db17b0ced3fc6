"""One range offset common to every entry of a moving-tag recording: a block jackknife test.

UWB two-way ranging carries an antenna delay shared by the tag's ranges: the model
``y_ij = |r_i - s_j| + c + e_ij``. ``c`` is identified only through the spread of the
ranges (it trades against the scale of the geometry), and on a moving tag the residuals
are serially correlated and partly systematic (per-anchor biases, antenna patterns,
non-line-of-sight stretches): the measured LPS flights have lag-1 residual
autocorrelation ~0.8 and a nested F statistic of ~1e3, so any test that counts ranges
as independent accepts every extra parameter there.

The test here counts *time blocks* instead of ranges. The columns (tag positions, in
time order) are cut into ``B`` consecutive blocks long enough that residuals of
different blocks are practically uncorrelated, and the offset is re-estimated ``B``
times, each time leaving one block out (its tag positions with it; the anchors and the
other positions are refitted). The block jackknife standard error (Kuensch 1989)

``se^2 = (B - 1) / B * sum_b (c_(b) - mean(c_(.)))^2``

is valid under serial dependence and misspecification: it measures how much the
estimate moves when a stretch of the flight is replaced, whatever the cause of the
misfit. ``t = c / se`` is referred to Student's t with ``B - 1`` degrees of freedom and
the offset is kept when the two-sided p-value is below :data:`COMMON_OFFSET_ALPHA`.

The level, 5 %, is that of a model choice, not of a detection (the solver's detections,
outliers and residual tests, run at 1e-2 / 1e-3). On two-way UWB ranging "no common
offset" has no physical standing: the antenna delay is a hardware constant that the
firmware never compensates exactly, so the test guards only against fitting an offset
the flight does not determine (``c`` trades against the scale of the geometry: a tag
that stays far from every anchor leaves it undetermined, the jackknife error is then
large and ``c`` is not kept). Negative ranges near an anchor are direct evidence of a
negative ``c``. On simulated flights (``experiments/lps.py``) a wrongly kept offset
cost <= 2 cm of anchor RMSE, a missed one 5-19 cm; the three levels 1e-3 / 1e-2 / 5e-2
are compared there on every case.

Block length (:func:`residual_correlation_length`): the first lag at which the mean
autocorrelation of the rows' residuals along time (under the common-offset model) falls
inside the 95 % white-noise band ``1.96 / sqrt(J)`` (Bartlett): beyond it, residuals
are indistinguishable from uncorrelated ones. ``B = J // L`` capped at
:data:`MAX_BLOCKS` (more blocks only sharpen the t reference law, at one refit each);
below :data:`MIN_BLOCKS` the recording is too short for its correlation length and the
offset is not kept (the test is reported as not run).

References
----------
H. R. Kuensch, "The jackknife and the bootstrap for general stationary observations",
Ann. Statist. 17 (1989) 1217-1241.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..verdict.offset_fit import _with_common, residual_correlation_length

__all__ = ["COMMON_OFFSET_ALPHA", "MAX_BLOCKS", "MIN_BLOCKS", "block_edges", "residual_correlation_length",
           "choose_common_offset"]

Array = NDArray[np.float64]

#: level of the two-sided block t test (a model choice; see the module docstring)
COMMON_OFFSET_ALPHA = 0.05
#: fewest blocks the t test is run with (t_5 at 5 % two-sided is 2.57 against 1.96 for the normal)
MIN_BLOCKS = 6
#: most blocks (t_15 is within 9 % of the normal quantile at 5 %; each block is one refit)
MAX_BLOCKS = 16


def block_edges(n: int, length: int) -> NDArray[np.intp]:
    """Edges of ``min(n // length, MAX_BLOCKS)`` consecutive, near-equal blocks of ``range(n)``.

    Examples
    --------
    >>> block_edges(600, 48).tolist()
    [0, 50, 100, 150, 200, 250, 300, 350, 400, 450, 500, 550, 600]
    """
    B = min(n // max(int(length), 1), MAX_BLOCKS)
    return np.linspace(0, n, max(B, 1) + 1).round().astype(np.intp)


def choose_common_offset(base: Any, sub: Array, scale: float = 1.0, solver: str = "auto") -> tuple[Any, dict[str, Any]]:
    """Fit one range offset common to every entry and keep it if the block t test finds it.

    Parameters
    ----------
    base: the offsets-free :class:`selfcal.toa.solve.ToaResult` fitted on ``sub``.
    sub: (I, J) the matrix it was fitted on (columns = tag positions in time order),
        matrix units (metres, or seconds with ``scale`` = speed).
    scale: metres per matrix unit.
    solver: the engine of the constrained refits, as :func:`selfcal.toa.engine.nls.refine_toa`'s
        ``solver`` ("auto": the Schur-reduced engine of :mod:`selfcal.toa.engine.schur_affine` on
        flights above 120 unknowns; "trf": SciPy's trust region, the reference).

    Returns
    -------
    (result, info): ``base`` itself when the offset is not kept, else ``base`` with the
    common-offset fit written in (``offsets="common"``, ``receiver_offsets`` all equal to
    ``c``); ``info`` holds the test: ``value`` (c, matrix units), ``std`` (block jackknife),
    ``t_statistic``, ``dof`` (B - 1), ``p_value``, ``blocks``, ``block_length``,
    ``correlation_length``, ``replicates``, ``adopted``, ``n_negative_ranges`` (used
    entries below zero: direct evidence of a negative offset), and for comparison the iid nested
    F statistic (``f_statistic``, ``f_p_value``) that this test replaces.

    Notes
    -----
    Cost: one refit of the whole flight plus one per block (each started from the full
    fit). On the Schur engine a refit of a 6 x 600 flight takes 5-20 Newton-LM iterations,
    0.05-0.2 s; ``benchmarks/bench_lps.py`` measures the test against the trf reference.

    Examples
    --------
    >>> from selfcal.experiments.lps import simulate_uwb_flight
    >>> from selfcal.toa import solve_toa
    >>> sim = simulate_uwb_flight(1, 240, layout="lps", bias_std=0.0, spike_rate=0.0)
    >>> base = solve_toa(sim["ranges"], rng=0)
    >>> res, info = choose_common_offset(base, sim["ranges"])
    >>> res.offsets, info["adopted"], round(info["value"], 1)
    ('common', True, -0.2)
    """
    kr = np.isfinite(base.receivers).all(axis=1)
    ks = np.isfinite(base.sources).all(axis=1)
    used = np.isfinite(base.residuals) & ~np.asarray(base.outliers, bool)
    com, info = block_offset_test(base, sub, scale, solver)
    if not info["adopted"]:
        return base, info
    assert com is not None and com.receiver_offsets is not None
    return _with_common(base, com, sub, scale, kr, ks, used, np.asarray(com.receiver_offsets, float)), info


def block_offset_test(base: Any, sub: Array, scale: float = 1.0, solver: str = "auto") -> tuple[Any, dict[str, Any]]:
    """The fit and test of :func:`choose_common_offset` without writing the result.

    Returns ``(com, info)``: ``com`` the :class:`selfcal.toa.engine.nls.NlsSolution` of the
    common-offset model on the used rows / columns (None when it failed), ``info`` the
    test (``info["adopted"]`` its decision).
    """
    from scipy.stats import f as f_dist
    from scipy.stats import t as t_dist

    from ...errors import DegenerateGeometryError, InputError
    from ..engine.nls import refine_toa
    from ..result import n_parameters

    kr = np.isfinite(base.receivers).all(axis=1)
    ks = np.isfinite(base.sources).all(axis=1)
    used = np.isfinite(base.residuals) & ~np.asarray(base.outliers, bool)
    Z = np.where(used, sub * scale, np.nan)[np.ix_(kr, ks)]
    info: dict[str, Any] = {"test": "block-jackknife-t", "alpha": COMMON_OFFSET_ALPHA, "adopted": False,
                            # direct evidence of a negative offset (a distance is never negative)
                            "n_negative_ranges": int(np.sum(np.nan_to_num(Z, nan=0.0) < 0))}
    fails = (DegenerateGeometryError, InputError, np.linalg.LinAlgError, ValueError)
    try:
        com = refine_toa(Z, base.receivers[kr], base.sources[ks], offsets="receivers",
                         common_offsets="receivers", covariance=True, solver=solver)
    except fails as exc:
        info["error"] = str(exc)
        return None, info
    assert com.receiver_offsets is not None
    offs = np.asarray(com.receiver_offsets, float)
    c = float(np.mean(offs))
    # the iid nested F test, reported for comparison only
    e0 = (base.residuals[np.ix_(kr, ks)] * scale)[np.isfinite(Z)]
    rss0, rss1 = float(e0 @ e0), float(np.nansum(com.residuals**2))
    m = int(np.isfinite(Z).sum())
    dof_f = m - n_parameters(int(kr.sum()), int(ks.sum()), base.dim, "none") - 1
    F = (rss0 - rss1) / (rss1 / dof_f) if dof_f > 0 and rss1 > 0 else float("nan")
    info.update({"value": c / scale, "f_statistic": float(F),
                 "f_p_value": float(f_dist.sf(F, 1, dof_f)) if np.isfinite(F) else float("nan"),
                 "rss_none": rss0 / scale**2, "rss_common": rss1 / scale**2, "iterations": int(com.iterations)})
    J = Z.shape[1]
    L = residual_correlation_length(com.residuals)
    edges = block_edges(J, L)
    B = len(edges) - 1
    info.update({"correlation_length": int(L), "blocks": int(B),
                 "block_length": int(J // B) if B else 0, "dof": int(B - 1)})
    if B < MIN_BLOCKS:
        info["reason"] = (f"{J} tag positions hold only {B} blocks of the residual correlation length "
                          f"{L}: fewer than {MIN_BLOCKS}, no test")
        return com, info
    reps = []
    from ...progress import report

    for b in range(B):
        report(b, B)
        keep = np.ones(J, bool)
        keep[edges[b]:edges[b + 1]] = False
        try:
            sol = refine_toa(Z[:, keep], com.receivers, com.sources[keep], offsets="receivers",
                             common_offsets="receivers", receiver_offsets0=offs, covariance=False,
                             solver=solver)
        except fails as exc:
            info["error"] = f"block {b}: {exc}"
            return com, info
        assert sol.receiver_offsets is not None
        reps.append(float(np.mean(sol.receiver_offsets)))
    cb = np.array(reps)
    se = float(np.sqrt((B - 1) / B * np.sum((cb - cb.mean()) ** 2)))
    t = c / se if se > 0 else float("inf") * np.sign(c)
    p = float(2 * t_dist.sf(abs(t), B - 1))
    info.update({"std": se / scale, "t_statistic": float(t), "p_value": p,
                 "replicates": (cb / scale).tolist()})
    info["adopted"] = bool(p < COMMON_OFFSET_ALPHA and com.converged)
    return com, info
