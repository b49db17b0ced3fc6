"""Model selection for TOA calibration: which offsets (``offsets="auto"``) and which dimension (``dim="auto"``).

- :func:`choose_offsets`: none / receivers / sources / both by held-out prediction
  (K-fold cross-validation over the sources with the one-standard-error rule,
  :mod:`selfcal.toa.verdict.crossval`) on the same entries for every candidate. It replaced the
  BIC, an in-sample criterion that on measured ranges (serially correlated, partly
  systematic residuals) accepts every extra parameter.
- :func:`dimension_test`: the one planarity decision (:mod:`selfcal.toa.verdict.planarity`:
  the F test of a 2-D against a 3-D fit and the chi-square of the out-of-plane coordinates
  against their covariances, both at ``PLANAR_ALPHA``) on a 3-D fit (its 2-D fit refined from it); used by
  :func:`choose_dim` and the acoustic pipeline.
- :func:`choose_dim`: 3-D unless :func:`dimension_test` finds z undetermined; then 2-D, so a
  flat layout does not report a confident spurious z.
"""

from __future__ import annotations

import dataclasses
import math
import warnings
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from ...errors import ConvergenceWarning, DegenerateGeometryError
from ..options import scores_only
from .planarity import (
    BOOT_REPLICATES,
    PLANAR_ALPHA,
    Planarity,
    bartlett_corrected,
    compare_fits,
    in_bootstrap_band,
    planarity,
)

if TYPE_CHECKING:  # the result type sits one layer above the verdicts (docs/design.md)
    from ..options import ToaOptions
    from ..result import ToaResult

__all__ = ["choose", "choose_dim", "choose_offsets", "dimension_test"]

Array = NDArray[np.float64]

OFFSET_CANDIDATES = ("none", "receivers", "sources", "both")
LIFTS = 4  # lifted 2-D starts of the observed 3-D model in the bootstrap band (one lands in the right basin 2 in 3 times on gen-3d-6x8 seed 43)


# ------------------------------------------------------------------ choices on solve_toa results

Solver = Callable[..., "ToaResult"]


def _quiet(solve: Solver, M: Array, dim: int, offsets: str, opts: ToaOptions,
           init: Any = "auto") -> ToaResult | None:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ConvergenceWarning)
        try:
            return solve(M, dim, offsets, opts, init=init)
        except DegenerateGeometryError:
            return None


def _n_off(mode: str, I: int, J: int) -> int:
    return {"none": 0, "receivers": I, "sources": J, "both": I + J - 1}[mode]


def _rss(res: ToaResult) -> float:
    assert res.residuals is not None
    e = res.residuals[np.isfinite(res.residuals) & ~np.asarray(res.outliers, bool)]
    return float(e @ e)


def _nested_init(res: ToaResult, mode: str, speed: float | None) -> tuple[Any, ...]:
    """A fit as a start of ``mode`` (dropped nodes at the centroid, missing offsets 0).

    In metres, offsets too (the fit reports them in the matrix's units: times ``speed``):
    the form of the ``init`` of the solver the choice runs (:func:`selfcal.toa.solve._solve_fixed`,
    the search's internal units). A solver in :func:`selfcal.toa.solve_toa`'s form (offsets in
    the matrix's units) converts back (:func:`selfcal.acoustics.calibrate._toa_solver`).
    """
    k = 1.0 if speed is None else float(speed)

    def fill(P: Array) -> Array:
        P = np.array(P, dtype=float)
        bad = ~np.isfinite(P).all(axis=1)
        P[bad] = np.nanmean(P[~bad], axis=0) if (~bad).any() else 0.0
        return P

    def off(a: Array | None, n: int) -> Array:
        return np.zeros(n) if a is None else np.nan_to_num(np.asarray(a, float) * k)

    r, s = fill(res.receivers), fill(res.sources)
    d = off(res.receiver_offsets, len(r)) if mode in ("receivers", "both") else None
    o = off(res.source_offsets, len(s)) if mode in ("sources", "both") else None
    return r, s, d, o


def _misfit(res: ToaResult) -> bool:
    """True when the fit's own residual test (chi-square at a given noise, else the geometry
    test) rejects it: the model does not explain the data (not merely undetermined)."""
    tests = (res.fit, res.geometry)
    return any(t is not None and not bool(t.passed) for t in tests)


def _projected_init(res: ToaResult, mode: str, speed: float | None) -> tuple[Any, ...]:
    """A 3-D fit projected onto its best-fitting plane: a 2-D start (metres, in-plane axes)."""
    r, s, d, o = _nested_init(res, mode, speed)
    P = np.vstack([r, s])
    c = P.mean(axis=0)
    _, _, vt = np.linalg.svd(P - c, full_matrices=False)
    return (r - c) @ vt[:2].T, (s - c) @ vt[:2].T, d, o


def _lsq(res: ToaResult) -> float:
    """Sum of squares over every entry the fit used (outliers included): the objective a
    refinement (``method="nls"``) minimises, comparable between two refinements of one model."""
    assert res.residuals is not None
    e = res.residuals[np.isfinite(res.residuals)]
    return float(e @ e)


def _own_starts(M: Array, dim: int, mode: str, opts: ToaOptions) -> list[tuple[Any, ...]]:
    """The model's own start, from the solver's registry initialiser for offsets: the rank-d
    iteration (both offset kinds at once, :mod:`selfcal.toa.init.offsets_init`) on the matrix
    the search would see (:func:`selfcal.toa.verdict.robust.screened`), collapsed to ``mode``; of its
    candidates the one of least sum of squares (metres, original order; none where the
    initialiser does not apply). Inside :func:`choose_offsets` the initialiser runs once per
    matrix (:func:`selfcal.toa.init.starts.shared_rank3`): every candidate and the final search
    reuse it."""
    from ..engine.nls import toa_model
    from ..init.starts import _rank3
    from .robust import screened

    Y = np.asarray(M, float) * (1.0 if opts.speed is None else float(opts.speed))
    I, J = Y.shape
    try:
        pr, pc, Yc, _, used, kr, ks = screened(Y, dim, mode)
        found = _rank3(np.where(used, Yc, np.nan)[np.ix_(kr, ks)], dim, mode, opts.rng)
    except (DegenerateGeometryError, ValueError, np.linalg.LinAlgError, FloatingPointError):
        return []
    rows, cols = pr[kr], pc[ks]

    def back(r: Array, s: Array, d: Array | None, o: Array | None) -> tuple[Any, ...]:
        R, S = np.full((I, dim), np.nan), np.full((J, dim), np.nan)
        R[rows], S[cols] = r, s
        D = None if d is None else np.zeros(I)
        O = None if o is None else np.zeros(J)
        if D is not None:
            D[rows] = d
        if O is not None:
            O[cols] = o
        return R, S, D, O

    def cost(st: tuple[Any, ...]) -> float:
        with np.errstate(all="ignore"):
            e = Y - toa_model(*st)
        e = e[np.isfinite(e)]
        return float(e @ e) if e.size else math.inf

    out = [back(*st) for st in found]
    return [min(out, key=cost)] if out else []


def choose_offsets(M: Array, dim: int, solve: Solver, opts: ToaOptions) -> tuple[ToaResult, dict[str, Any]]:
    """Fit every offsets mode and keep the one chosen by held-out prediction; (result, statistics).

    The offsets-free mode is fitted by ``solve``'s search; each larger mode by a cheap search:
    one refinement (``method="nls"``) started from the best fit of the modes it nests, its new
    offsets at zero (so it never ends above them; a full search per mode cost 4x the blind
    solve), and a refinement from the model's own start (the rank-d offsets initialiser of
    the solver's registry, computed once for all modes, its best start by sum of squares)
    where the first is certainly not the model's fit: it fails its own residual test
    (:func:`_misfit`; with a given noise the chi-square test), or the mode is the widest
    ("both"), which no narrower fit certifies (a nested chain of wrong models led it to a
    wrong basin, held-out RMS 0.3 m against 1 cm noise, where its own start finds the truth).
    The lower sum of squares over the same entries wins (:func:`_lsq`): a fit stuck in a wrong
    basin is a search failure, not evidence against its model.
    :func:`selfcal.toa.verdict.crossval.cross_validate` then refits each on K - 1 blocks of
    the sources, locates the held-out sources with the fitted receivers (and offsets) and
    scores their leave-one-range-out prediction residuals; the one-standard-error rule
    keeps the simplest mode within one paired standard error of the best. Every mode is
    judged on the same entries: those kept by the candidate that removed the fewest as
    outliers (a model that cannot fit good entries must not hide its misfit by removing
    them), of the nodes every candidate kept. An in-sample criterion (BIC, F) is not used:
    on measured ranges (serially correlated, partly systematic residuals) it accepts any
    extra parameter. The chosen mode, if not the offsets-free one, is finally searched
    from its refinement (the search accepts only lower costs).
    ``statistics`` is :meth:`selfcal.toa.verdict.crossval.CvChoice.to_dict` plus ``observations``,
    each mode's in-sample ``rss`` and ``own_start`` (the modes whose own start was tried).
    """
    from ..init.starts import shared_rank3

    with shared_rank3():  # the rank-d initialiser runs once for every candidate and the final search
        return _choose_offsets(M, dim, solve, opts)


def _choose_offsets(M: Array, dim: int, solve: Solver, opts: ToaOptions) -> tuple[ToaResult, dict[str, Any]]:
    fits: dict[str, ToaResult] = {}
    own: list[str] = []
    # the candidates' refinements are starts and scores only: no covariances and no verdicts
    # beyond the trust test _misfit reads (the chosen one is searched, or refitted with both)
    nls = dataclasses.replace(opts, method="nls", covariance=False)

    def candidate(mode: str, init: Any) -> ToaResult | None:
        with scores_only():
            return _quiet(solve, M, dim, mode, nls, init=init)

    for mode in OFFSET_CANDIDATES:
        # every model is also started from the best fit of the models it nests (offsets of the
        # other kinds at zero): a refinement only lowers the cost, so it never ends above them
        nested = [fits[k] for k in fits if k == "none" or mode == "both"]
        base = min(nested, key=_rss) if nested else None
        res = candidate(mode, _nested_init(base, mode, opts.speed)) if base else None
        if base is None or res is None:
            res = _quiet(solve, M, dim, mode, opts)
        elif mode == "both" or _misfit(res):
            own.append(mode)
            for st in _own_starts(M, dim, mode, opts):
                try:  # a start the engine cannot refine (singular normal equations) is skipped
                    alt = candidate(mode, st)
                except (np.linalg.LinAlgError, ValueError):
                    alt = None
                if alt is not None and _lsq(alt) < _lsq(res):
                    res = alt
        if res is not None:
            fits[mode] = res
    if not fits:
        raise DegenerateGeometryError("no offsets model could be fitted to this matrix", kind="too-few-measurements")
    from .crossval import cross_validate

    # every candidate judged on the same entries: those kept by the candidate that removed the
    # fewest as outliers (a gross error is removed by every model that fits the rest; a model
    # that cannot fit good entries removes them too, and must not hide its misfit that way)
    k = 1.0 if opts.speed is None else float(opts.speed)
    fewest = min(fits.values(), key=lambda r: (int(np.asarray(r.outliers).sum()), _rss(r)))
    kept = np.isfinite(M) & ~np.asarray(fewest.outliers, bool)
    kr = np.logical_and.reduce([np.isfinite(r.receivers).all(axis=1) for r in fits.values()])
    ks = np.logical_and.reduce([np.isfinite(r.sources).all(axis=1) for r in fits.values()])
    Z = np.where(kept, M * k, np.nan)[np.ix_(kr, ks)]

    def start(res: ToaResult) -> tuple[Any, ...]:
        d = None if res.receiver_offsets is None else np.nan_to_num(np.asarray(res.receiver_offsets)[kr] * k)
        o = None if res.source_offsets is None else np.nan_to_num(np.asarray(res.source_offsets)[ks] * k)
        return res.receivers[kr], res.sources[ks], d, o

    choice = cross_validate(Z, {mode: start(res) for mode, res in fits.items()})
    stats = {**choice.to_dict(), "observations": int(np.isfinite(Z).sum()),
             "rss": {mode: _rss(res) for mode, res in fits.items()}, "own_start": own}
    chosen = choice.chosen
    if chosen != "none":
        # the chosen model (only it) gets the full search, started from its refinement: the
        # refinement alone can stop in a worse basin (room 7 x 220: anchor RMSE 0.146 vs 0.071 m)
        full = _quiet(solve, M, dim, chosen, opts, init=_nested_init(fits[chosen], chosen, opts.speed))
        if full is not None:
            fits[chosen] = full
            stats["searched"] = chosen
        else:  # the candidates' refinements skip the covariances: the chosen one's, refitted in place
            fits[chosen] = _quiet(solve, M, dim, chosen, dataclasses.replace(opts, method="nls"),
                                  init=_nested_init(fits[chosen], chosen, opts.speed)) or fits[chosen]
    return fits[chosen], stats


def _thickness_cov(fit3: ToaResult, speed: float | None) -> Array:
    """The 3-D fit's covariances (receivers then sources) for the thickness chi-square:
    four times the linearised ones for the nodes whose partners are coplanar within their
    error bars (:func:`.flips.coplanar_partner_nodes`, level :data:`PLANAR_ALPHA`).

    Such a node's height ``h`` above its partners' plane enters its ranges at second order,
    ``rho_j + h^2 / (2 rho_j)``: its misfit is the double well ``A (h^2 - h0^2)^2``. The
    linearised variance at the fitted ``h0`` is ``sigma^2 = 1 / (4 A h0^2)``, so the
    parabola says the plane (``h = 0``) costs ``(h0 / sigma)^2`` while the likelihood ratio
    is ``A h0^4 = (h0 / (2 sigma))^2``: four times less. Scaling these nodes' covariances by
    4 makes their term of the thickness chi-square the profile-likelihood one (exact for a
    node over exactly coplanar, fixed partners).
    """
    from scipy.stats import chi2

    from .flips import coplanar_partner_nodes

    R, S = np.asarray(fit3.receivers, float), np.asarray(fit3.sources, float)
    Cr, Cs = np.array(fit3.receiver_cov, float), np.array(fit3.source_cov, float)
    res = np.asarray(fit3.residuals, float)
    fr, fs = np.isfinite(R).all(axis=1), np.isfinite(S).all(axis=1)  # nodes the fit dropped: NaN rows
    obs = (np.isfinite(res) & ~np.asarray(fit3.outliers, bool))[np.ix_(fr, fs)]
    if obs.any():
        noise2 = float(np.mean(res[np.ix_(fr, fs)][obs] ** 2)) * (1.0 if speed is None else float(speed)) ** 2
        q = float(chi2.ppf(1.0 - PLANAR_ALPHA, 1))

        def std(C: Array) -> Array:
            return np.sqrt(np.abs(np.trace(C, axis1=1, axis2=2)))

        with np.errstate(invalid="ignore"):
            sr = coplanar_partner_nodes(R[fr], S[fs], obs, noise2=noise2, partner_var=Cs[fs],
                                        point_std=std(Cr[fr]), quantile=q)
            ss = coplanar_partner_nodes(S[fs], R[fr], obs.T, noise2=noise2, partner_var=Cr[fr],
                                        point_std=std(Cs[fs]), quantile=q)
        Cr[np.flatnonzero(fr)[sr]] *= 4.0
        Cs[np.flatnonzero(fs)[ss]] *= 4.0
    return np.concatenate([Cr, Cs])


def _null_replicates(M: Array, fit2: ToaResult, fit3: ToaResult, common: NDArray[np.bool_], offsets: str,
                     opts: ToaOptions, n: int = BOOT_REPLICATES) -> tuple[Array, Array]:
    """F statistics of ``n`` data sets simulated from the 2-D fit: the F test's null at a planar
    truth; with the 3-D estimator's mean-square error there, per node.

    Each replicate is the 2-D fit's model on the entries both fits used (``common``) plus
    Gaussian noise of the 2-D fit's variance estimate (``RSS_2 / (m - p_2)``), refitted by
    least squares (:func:`selfcal.toa.engine.nls.refine_toa`, the Gaussian likelihood the F
    test assumes; no outlier rule, no covariances): the 2-D model from the 2-D fit (the
    replicate's truth), the 3-D model from the observed 3-D fit and from the replicate's 2-D
    fit lifted by random heights of the bending scale ``sqrt(noise x extent)`` (a planar
    start is a saddle of the 3-D cost), the lower sum of squares kept. Replicates whose
    refinements fail are skipped. The random numbers come from a child of the solver's
    generator (``opts.rng.spawn``): deterministic for a seeded solve, the solver's own
    stream not advanced (a generator that cannot spawn seeds a new one from one draw).

    The same refits give the 3-D estimator's error at that planar truth: each replicate's
    3-D fit (the one of lower RSS) aligned onto the 2-D fit embedded in 3-D (rigid motion,
    reflection allowed: the frame the gauge-free covariances and the truth checks use,
    :func:`selfcal.geometry.align`), itself aligned onto ``fit3``; ``mse`` is the mean of
    ``e e^T`` over the replicates, (I + J, 3, 3) in ``fit3``'s frame (receivers then
    sources; NaN for nodes either fit dropped, all NaN with fewer than 2 replicates).
    """
    from ...geometry import align
    from ..engine.model import toa_model
    from ..engine.nls import refine_toa

    k = 1.0 if opts.speed is None else float(opts.speed)
    I, J = M.shape
    n_off = _n_off(offsets, I, J)
    assert fit2.residuals is not None
    m = int(common.sum())
    p2 = 2 * (I + J) - 3 + n_off  # the 2-D model's free parameters
    sigma = k * float(np.sqrt(np.sum(fit2.residuals[common] ** 2) / max(m - p2, 1)))  # metres
    st2, st3 = _nested_init(fit2, offsets, opts.speed), _nested_init(fit3, offsets, opts.speed)
    mu = toa_model(*st2)
    extent = float(np.ptp(np.vstack([st2[0], st2[1]]), axis=0).max())
    bend = math.sqrt(sigma * extent)
    try:
        g = opts.rng.spawn(1)[0]
    except (TypeError, ValueError, AttributeError):  # a generator without a seed sequence
        g = np.random.default_rng(int(opts.rng.integers(2**63)))

    def rss(Y: Array, st: tuple[Any, ...]) -> tuple[float, tuple[Any, ...]]:
        try:
            with warnings.catch_warnings(), np.errstate(all="ignore"):
                warnings.simplefilter("ignore")
                sol = refine_toa(Y, st[0], st[1], offsets=offsets, receiver_offsets0=st[2], source_offsets0=st[3],
                                 covariance=False)
        except (np.linalg.LinAlgError, ValueError, FloatingPointError, DegenerateGeometryError):
            return math.inf, st
        e = sol.residuals[np.isfinite(sol.residuals)]
        return float(e @ e), (sol.receivers, sol.sources, sol.receiver_offsets, sol.source_offsets)

    # the replicates' planar truth in fit3's frame (the frame of its covariances)
    ok = (np.isfinite(np.vstack([fit3.receivers, fit3.sources])).all(axis=1)
          & np.isfinite(np.vstack([fit2.receivers, fit2.sources])).all(axis=1))
    P3 = np.vstack([st3[0], st3[1]])
    T0 = np.c_[np.vstack([st2[0], st2[1]]), np.zeros(I + J)]
    T0 = align(T0[ok], P3[ok], reflection=True).apply(T0)
    sq = np.zeros((I + J, 3, 3))
    out = []
    for _ in range(n):
        Y = np.where(common, mu + g.normal(0.0, sigma, M.shape), np.nan)
        z = g.normal(0.0, bend, I + J)
        rss2, f2 = rss(Y, st2)
        lifted = (np.c_[f2[0], z[:I]], np.c_[f2[1], z[I:]], f2[2], f2[3])
        rss3, f3 = min(rss(Y, st3), rss(Y, lifted), key=lambda t: t[0])
        if math.isfinite(rss2) and math.isfinite(rss3):
            out.append(compare_fits(math.sqrt(rss2 / m), math.sqrt(min(rss3, rss2) / m), m, I + J,
                                    n_offsets=n_off).f_statistic)
            X = np.vstack([f3[0], f3[1]])[ok]
            e = align(X, T0[ok], reflection=True).apply(X) - T0[ok]
            sq[ok] += np.einsum("ki,kj->kij", e, e)
    mse = np.full((I + J, 3, 3), np.nan)
    if len(out) >= 2:
        mse[ok] = sq[ok] / len(out)
    return np.asarray(out, float), mse


def _lifted_fit3(M: Array, fit2: ToaResult, fit3: ToaResult, common: NDArray[np.bool_], offsets: str,
                 solve: Solver, opts: ToaOptions) -> ToaResult | None:
    """The observed data's 3-D model refined from the replicates' second start too: the 2-D
    fit lifted by random heights of the bending scale; the better fit where its sum of squares
    is lower.

    :func:`_null_replicates` fits every replicate's 3-D model from two starts, the observed
    3-D fit and the replicate's 2-D fit lifted by heights ``N(0, sqrt(noise x extent))`` (a
    planar start is a saddle of the 3-D cost), and keeps the lower sum of squares. The
    observed F is computed from the 3-D fit of the search alone, which a wrong basin can leave
    far above the 3-D model's minimum: F then falls into the bootstrap band (its noise
    estimate, from that fit, inflates the bending scale) and the 2-D fit is accepted
    (issue 27, ``benchmarks/cli_audit.py`` ``gen-3d-6x8`` seed 43: the search's 3-D fit at
    0.18 m RMS, flagged, F = 8.3; from the lifted 2-D fit 3.7 mm, F = 2.2e4). Here the same
    lift is tried on the observed data, :data:`LIFTS` times (a lifted start lands in the right
    basin about 2 in 3 times there; the replicates take one each, so the observed F is at
    most slightly larger than theirs at a planar truth: measured by
    ``benchmarks/planarity_rates.py``).

    Each lift is refined by least squares (:func:`selfcal.toa.engine.nls.refine_toa`, as the
    replicates, ``noise`` the 2-D fit's variance estimate); only where the best one's sum of
    squares over ``common`` is below the observed 3-D fit's by more than one noise variance
    (its RSS over the residual dof: a different minimum, not the same one refitted) is the
    model refitted by ``solve`` from it (``method="nls"``: the result with its own tests and covariances).
    Returns that fit when it removes no more entries than ``fit3`` and its sum of squares is
    lower, else None. The heights come from a stream keyed off the solver's seed sequence
    that does not advance it (the replicates' child, and so every decision the lift does not
    change, stay as they were; a generator without a seed sequence: seed 0).
    """
    from ..engine.nls import refine_toa

    k = 1.0 if opts.speed is None else float(opts.speed)
    I, J = M.shape
    m = int(common.sum())
    assert fit2.residuals is not None and fit3.residuals is not None
    p2 = 2 * (I + J) - 3 + _n_off(offsets, I, J)
    sigma = k * float(np.sqrt(np.sum(fit2.residuals[common] ** 2) / max(m - p2, 1)))  # metres
    st2 = _nested_init(fit2, offsets, opts.speed)
    extent = float(np.ptp(np.vstack([st2[0], st2[1]]), axis=0).max())
    # a stream of its own, keyed off the solver's seed sequence without advancing it: the
    # replicates' child (opts.rng.spawn) and so every decision the lift does not change stay as they were
    ss = getattr(getattr(opts.rng, "bit_generator", None), "seed_seq", None)
    key = (*ss.spawn_key, 2**31 - 1) if isinstance(ss, np.random.SeedSequence) else None
    g = np.random.default_rng(np.random.SeedSequence(ss.entropy, spawn_key=key) if key is not None and ss is not None
                              else 0)
    Y = np.where(common, k * M, np.nan)
    st3 = _nested_init(fit3, offsets, opts.speed)

    def lsq(start: tuple[Any, ...]) -> Any:
        try:
            with warnings.catch_warnings(), np.errstate(all="ignore"):
                warnings.simplefilter("ignore")
                return refine_toa(Y, start[0], start[1], offsets=offsets, receiver_offsets0=start[2],
                                  source_offsets0=start[3], covariance=False)
        except (np.linalg.LinAlgError, ValueError, FloatingPointError, DegenerateGeometryError):
            return None

    # the baseline on the same objective: the search's fit refined on the same entries (it was
    # fitted on entries outside ``common`` too, so its own RSS there is not the minimum there)
    base = lsq(st3)
    e3 = (k * fit3.residuals[common]) if base is None else base.residuals[np.isfinite(base.residuals)]
    best, init = float(e3 @ e3), None
    # a different minimum, not the same one refitted: lower by more than one noise variance
    # (a log-likelihood gain of 1/2; round-off between two refinements of one minimum must not
    # replace the search's fit, whose statistics and decision then stay as they were)
    p3 = 3 * (I + J) - 6 + _n_off(offsets, I, J)
    best -= best / max(m - p3, 1)
    for _ in range(LIFTS):
        z = g.normal(0.0, math.sqrt(sigma * extent), I + J)
        sol = lsq((np.c_[st2[0], z[:I]], np.c_[st2[1], z[I:]], st2[2], st2[3]))
        if sol is None:
            continue
        e = sol.residuals[np.isfinite(sol.residuals)]
        if float(e @ e) < best:
            best, init = float(e @ e), (sol.receivers, sol.sources, sol.receiver_offsets, sol.source_offsets)
    if init is None:
        return None
    new = _quiet(solve, M, 3, offsets, dataclasses.replace(opts, method="nls"), init=init)
    if new is None or new.outliers is None or np.asarray(new.outliers).sum() > np.asarray(fit3.outliers).sum():
        return None
    # the same rule on the solver's fits (kept entries): the refit is a different minimum, lower
    # by more than one noise variance, or the search's fit stands (a near-flat bend lets two
    # refinements of one minimum stop apart by round-off)
    kept = int((np.isfinite(fit3.residuals) & ~np.asarray(fit3.outliers, bool)).sum())
    rss3 = _rss(fit3)
    return new if _rss(new) < rss3 - rss3 / max(kept - p3, 1) else None


def dimension_test(M: Array, fit3: ToaResult, offsets: str, solve: Solver, opts: ToaOptions, *,
                   lift: bool = True) -> tuple[bool, Planarity, ToaResult | None, dict[str, Any], ToaResult]:
    """Is the 3-D fit ``fit3`` of ``M`` determined in z, or is the layout (near-)planar?

    The 2-D model is fitted by one refinement from ``fit3`` projected onto its best plane
    (a full 2-D search only when that refinement fails): the 2-D model is nested in the 3-D
    one, so on planar data that start is usually the 2-D solution up to the noise, and on
    data with a resolved thickness no 2-D start approaches the 3-D residual. When that
    refinement fails its own residual test or removes more entries than the 3-D fit (a
    wrong 2-D basin, reached from a 3-D fit bent off a planar truth: it inflated F to 1e4-1e6
    on planar 8 x 10 draws), the 2-D model is also searched and the better fit kept. The decision is
    :func:`planarity` with the F test of the two fits over the entries both fitted
    (:func:`compare_fits`) and the 3-D fit's covariances, both at :data:`PLANAR_ALPHA`:
    z is kept when the F test rejects the plane and the 3-D layout resolves its thickness.
    Two exceptions keep z: no residual degree of freedom for the F test (the fits kept
    different entries: no evidence for dropping z), and an F test that rejects the plane
    while the 2-D fit fails its own residual test (the data reject the plane; the 3-D
    answer is then judged by its own determinacy test, never replaced by a failed 2-D fit).

    Where the F test rejects the plane but the layout is within ``BOOT_BAND`` bending
    scales ``sqrt(noise x extent)`` of flat (:func:`.planarity.in_bootstrap_band`; noise from
    the 3-D fit, extent the layout's largest), F(k, dof) is not the statistic's law: the
    heights enter the ranges at second order and the 3-D model is not regular at a planar
    truth (4 % of planar 8 x 10 draws called 3-D at a nominal 1e-3). There
    :data:`BOOT_REPLICATES` data sets are simulated from the 2-D fit and refitted
    (:func:`_null_replicates`) and the F test is corrected by their Bartlett factor
    (:func:`.planarity.bartlett_corrected`). Elsewhere (generic 3-D networks: F far beyond
    any null) nothing more runs. Where the bootstrap ran and the answer stays 3-D, the 3-D
    fit's covariances are widened by the 3-D estimator's mean-square error over the same
    replicates (:func:`_widened`: the linearised bars do not describe a fit in that band).
    Before the bootstrap, the 3-D model is also refitted from the 2-D fit lifted off its
    plane, the replicates' second start (:func:`_lifted_fit3`): a 3-D search stuck in a wrong
    basin otherwise puts a generic 3-D network in the band and hands it the 2-D fit.

    Parameters
    ----------
    M : (I, J) array
        The matrix both fits are of (NaN = missing).
    fit3 : ToaResult
        Its 3-D fit.
    offsets : str
        The offsets model of both fits.
    solve : callable
        ``solve(M, dim, offsets, opts, init=...)`` (:func:`selfcal.toa.solve._solve_fixed`'s form).
    opts : ToaOptions
        Passed to ``solve`` (the 2-D refinement with ``method="nls"``).
    lift : bool
        Where the bootstrap is to run, first refit the 3-D model from the 2-D fit lifted off
        its plane (:func:`_lifted_fit3`, the replicates' second start) and, where that fit
        is better, redo the test on it (``fit3_lifted`` True in the statistics). False: the
        test on ``fit3`` as given (the redone test).

    Returns
    -------
    keep3 : bool
        True: z is determined (report the 3-D fit).
    planarity : Planarity
        With the comparison; ``near_planar`` is the test's verdict (``not keep3`` except
        in the two exceptions above).
    fit2 : ToaResult or None
        The 2-D fit (None when none could be fitted: then ``keep3`` is True).
    statistics : dict
        ``criterion``, ``chosen``, ``f_statistic``, ``p_value``, ``residual_2d``,
        ``residual_3d``, ``dof_3d``, ``near_planar``, ``thickness``, ``normal_std``,
        ``thickness_chi2``, ``thickness_p``, ``alpha``, ``p_asymptotic``, ``bartlett``,
        ``bartlett_se``, ``replicates`` (0 and factor 1 where the bootstrap did not run),
        ``plane_rejected`` (the asymptotic F test rejects the plane outside the bootstrap
        band: :func:`choose_dim` then reports no 2-D answer when the 3-D fit fails its own tests),
        ``bars_widened``; where True also ``bar_widening_median`` / ``bar_widening_max``
        (per node, the RMS-radius std after over before), ``bootstrap_rms_error`` (m) and
        ``bars_note`` (the sentence that says why).
    fit3 : ToaResult
        The 3-D fit to report when ``keep3``: ``fit3``, its covariances widened where
        ``bars_widened``.
    """
    r3 = fit3
    r2 = _quiet(solve, M, 2, offsets, dataclasses.replace(opts, method="nls"), init=_projected_init(r3, offsets, opts.speed))
    if r2 is None or _misfit(r2) or (r2.outliers is not None and np.asarray(r2.outliers).sum() >
                                     np.asarray(r3.outliers).sum()):
        # at a planar truth the 3-D fit bends off the plane by ~sqrt(noise x extent); the
        # refinement from its projection can then stop in a wrong 2-D basin (removing good
        # entries as outliers), which would inflate F: the 2-D model is searched as well and
        # the better fit (fewer entries removed, then lower RSS) is the 2-D model's
        searched = _quiet(solve, M, 2, offsets, opts)
        cands = [f for f in (r2, searched) if f is not None]
        r2 = min(cands, key=lambda f: (int(np.asarray(f.outliers).sum()), _rss(f))) if cands else None
    pts = np.vstack([r3.receivers, r3.sources])
    cov = _thickness_cov(r3, opts.speed)
    if r2 is None:
        plan = planarity(pts, cov)
        return True, plan, None, {"criterion": "F", "chosen": 3, "reason": "only the 3-D fit exists",
                                  "alpha": PLANAR_ALPHA}, r3
    assert r2.residuals is not None and r3.residuals is not None and r2.outliers is not None
    assert r3.outliers is not None
    common = np.isfinite(r2.residuals) & np.isfinite(r3.residuals) & ~r2.outliers & ~r3.outliers
    m = int(common.sum())
    I, J = M.shape
    rms2 = float(np.sqrt(np.mean(r2.residuals[common] ** 2))) if m else float("nan")
    rms3 = float(np.sqrt(np.mean(r3.residuals[common] ** 2))) if m else float("nan")
    floor = float(np.sqrt(np.finfo(float).eps) * np.nanmedian(np.abs(M)))  # the solver's precision
    cmp = compare_fits(rms2, rms3, m, I + J, noise_floor=floor, n_offsets=_n_off(offsets, I, J))
    plan = planarity(pts, cov, comparison=cmp)
    k = 1.0 if opts.speed is None else float(opts.speed)
    noise = k * rms3 * math.sqrt(m / cmp.dof_3d) if cmp.dof_3d > 0 else 0.0  # range noise, m
    fin = np.isfinite(pts).all(axis=1)
    extent = float(np.ptp(pts[fin], axis=0).max()) if fin.any() else 0.0
    # the plane rejected where F(k, dof) is the statistic's law or F is beyond every Bartlett
    # factor measured at planar truths (outside the bootstrap band): no bend of a planar truth
    # explains it (choose_dim then reports no 2-D model when the 3-D fit fails its own tests)
    rejected = cmp.significant and not in_bootstrap_band(cmp, float(plan.extents[-1]), noise, extent)
    mse = None
    if in_bootstrap_band(cmp, float(plan.extents[-1]), noise, extent) and (not plan.near_planar or _misfit(r2)):
        if lift:
            # the observed 3-D model from the replicates' second start too (_lifted_fit3): the
            # test is then redone on the better 3-D fit (out of the band where F is far beyond it)
            better = _lifted_fit3(M, r2, r3, common, offsets, solve, opts)
            if better is not None:
                keep3, plan, r2, stats, r3 = dimension_test(M, better, offsets, solve, opts, lift=False)
                return keep3, plan, r2, {**stats, "fit3_lifted": True}, r3
        # only where the bootstrap can overturn a "3-D" verdict (F decides it)
        F, mse = _null_replicates(M, r2, r3, common, offsets, opts)
        cmp = bartlett_corrected(cmp, F)
        plan = planarity(pts, cov, comparison=cmp)
    untestable = cmp.dof_3d <= 0
    keep3 = untestable or not plan.near_planar or (cmp.significant and _misfit(r2))
    stats = {"criterion": "F", "chosen": 3 if keep3 else 2, "f_statistic": cmp.f_statistic,
             "p_value": cmp.p_value, "residual_2d": rms2, "residual_3d": rms3, "dof_3d": cmp.dof_3d,
             "near_planar": plan.near_planar, "thickness": float(plan.extents[-1]),
             "normal_std": plan.normal_std, "thickness_chi2": plan.thickness_chi2,
             "thickness_p": plan.thickness_p, "alpha": PLANAR_ALPHA, "p_asymptotic": cmp.p_asymptotic,
             "bartlett": cmp.bartlett, "bartlett_se": cmp.bartlett_se, "replicates": cmp.replicates,
             "plane_rejected": bool(rejected), "bars_widened": False}
    if keep3 and mse is not None and np.isfinite(mse).any():
        r3, widening = _widened(r3, mse)
        stats.update(widening)
    return keep3, plan, r2, stats, r3


def _widened(fit3: ToaResult, mse: Array) -> tuple[ToaResult, dict[str, Any]]:
    """``fit3`` with each node's bootstrap mean-square error at the 2-D fit added to its
    covariance (:func:`_null_replicates`); the statistics that say so.

    Where the bootstrap runs (the second-order band, :func:`.planarity.in_bootstrap_band`)
    and the answer stays 3-D, the band is the regime where the heights enter the ranges at
    second order: the 3-D fit bends along directions its linearised covariance (the CRLB at
    the bent fit) does not describe, and the planar layout of the 2-D fit is one the data
    cannot tell from it to first order. The covariance reported is then the larger error
    law of the two hypotheses the band holds: the linearised covariance plus the 3-D
    estimator's mean-square error (bias and scatter) at the planar truth, ``C + MSE``
    (conservative: at least either). No refit is added: the F test's replicates are reused.
    """
    I = len(fit3.receivers)
    ok: NDArray[np.bool_] = np.asarray(np.isfinite(mse).all(axis=(1, 2)), bool)
    add = np.where(ok[:, None, None], mse, 0.0)
    rc, sc = np.asarray(fit3.receiver_cov, float), np.asarray(fit3.source_cov, float)
    before = np.concatenate([rc, sc])
    after = before + add
    with np.errstate(invalid="ignore", divide="ignore"):
        f = np.sqrt(np.trace(after, axis1=1, axis2=2) / np.trace(before, axis1=1, axis2=2))[ok]
    f = f[np.isfinite(f)]
    med, mx = (float(np.median(f)), float(f.max())) if f.size else (float("nan"), float("nan"))
    rms = float(np.sqrt(np.mean(np.trace(add[ok], axis1=1, axis2=2)))) if ok.any() else float("nan")
    note = (f"error bars widened by the 3-D estimator's bootstrap mean-square error at the 2-D fit (the layout is in "
            f"the second-order band, where the linearised covariance does not describe a bent 3-D fit): "
            f"RMS position error {rms * 1e3:.3g} mm added; bars x{med:.3g} median, x{mx:.3g} max")
    out = dataclasses.replace(fit3, receiver_cov=after[:I], source_cov=after[I:])
    return out, {"bars_widened": True, "bar_widening_median": med, "bar_widening_max": mx,
                 "bootstrap_rms_error": rms, "bars_note": note}


def choose_dim(M: Array, offsets: str, solve: Solver, opts: ToaOptions, *,
               fit3: ToaResult | None = None) -> tuple[ToaResult, dict[str, Any]]:
    """3-D unless z is not determined by the data (:func:`dimension_test`); (result, statistics).

    ``fit3``: the 3-D fit of this model when the caller already searched it
    (:func:`choose` after :func:`choose_offsets`); it is not searched again. Without a 3-D
    fit (the solver breaks down in 3-D) the 2-D model is searched.

    Where the test drops z although the data reject the plane (``plane_rejected``: F
    significant outside the bootstrap band, so no bend of a planar truth explains it; z is
    dropped because the 3-D layout's thickness is not resolved) and the 3-D fit fails its own
    tests (ambiguous or undetermined nodes), neither model gives a trustworthy answer: the
    failing 3-D fit is returned (``chosen`` 3, ``reason``), its ambiguous nodes named, rather
    than a 2-D fit the data reject that passes as a success (issue 27: a tag walked at one
    height under anchors on two levels; ``benchmarks/cli_audit.py``).
    """
    r3 = fit3 if fit3 is not None else _quiet(solve, M, 3, offsets, opts)
    if r3 is None:
        r2 = _quiet(solve, M, 2, offsets, opts)
        if r2 is None:
            raise DegenerateGeometryError("neither a 2-D nor a 3-D geometry could be fitted to this matrix",
                                          kind="degenerate-geometry")
        return r2, {"criterion": "F", "chosen": 2, "reason": "only the 2-D fit exists"}
    keep3, _, r2, stats, r3 = dimension_test(M, r3, offsets, solve, opts)
    if not keep3 and stats.get("plane_rejected") and not r3.success:
        # the data reject the plane beyond any bend of a planar truth, and the 3-D fit fails its
        # own tests (ambiguous, undetermined): neither answer is trustworthy. The failing 3-D fit
        # is reported (its ambiguous nodes named), not a 2-D model the data reject (a tag walked
        # at one height under anchors on two levels: 2-D anchors 1.6 m off at 7 error bars, exit 0)
        return r3, {**stats, "chosen": 3, "reason": "the data reject the plane and the 3-D fit fails its own tests"}
    return (r3 if keep3 or r2 is None else r2), stats


def choose(M: Array, dim: int | str, offsets: str, opts: ToaOptions, *, solve: Solver) -> ToaResult:
    """``solve_toa`` with ``dim`` and / or ``offsets`` set to "auto": the chosen fit with its statistics."""
    sel: dict[str, Any] = {}
    fit3 = None
    if offsets == "auto":
        d0 = 3 if dim == "auto" else int(dim)
        res, sel["offsets"] = choose_offsets(M, d0, solve, opts)
        offsets = res.offsets
        # the chosen model's 3-D fit, searched (its refinement alone is searched again)
        searched = res.offsets == "none" or "searched" in sel["offsets"]
        fit3 = res if d0 == 3 and searched else None
    if dim == "auto":
        res, sel["dim"] = choose_dim(M, offsets, solve, opts, fit3=fit3)
    return dataclasses.replace(res, selection=sel)
