"""Documented preprocessing recipes for measured range data, in front of :func:`solve_toa`.

A recipe states an assumption about how the data were taken that the bare range model
does not use, and exploits it before the fit. Each is an option of ``calibrate toa``
(``--recipe NAME``) and a function here.

``"none"``
    The matrix as given (the solver's own robust fit and checks).

``"auto"`` (the ``calibrate toa`` default)
    ``"moving-tag"`` when the columns are detectably a time series, else ``"none"``.
    The test (:func:`detect_time_order`) is a permutation test of the column order: the
    total variation of the rows along the given order against that of random orders.
    Independent sources are exchangeable (any order is as rough as a random one); samples
    of a moving device are far smoother in their recording order. Applied when the
    p-value is below 1e-3 (999 permutations), so a matrix of independent sources
    triggers the recipe with probability 1e-3.

``"moving-tag"``
    The sources (columns) are successive positions of *one* moving device, in time order
    (a UWB tag on a drone, a loudspeaker carried around). Each row is then a smooth
    function of time, and multipath / non-line-of-sight returns are isolated spikes in
    it. They are removed before the fit by a leave-one-out robust local quadratic in time
    per row (a Hampel identifier, :func:`selfcal.toa.recipes.preprocess.reject_range_outliers`).
    Only entries *above* the local prediction are tested (``one_sided=True``): a
    reflected or obstructed path is longer than the direct one, never shorter. The
    threshold (``threshold="bonferroni"``, :func:`spike_threshold`) is the normal quantile
    ``Phi^-1(1 - alpha / m)`` over the ``m`` observed entries, alpha = 1 %: on Gaussian
    noise no entry of the whole recording is rejected with probability 99 %, the same
    false-alarm rule as the solver's own outlier test (about 4.5 robust sigmas for a
    6 x 600 flight).
    Tag positions left with fewer than ``dim + 1`` ranges cannot be located (``dim``
    ranges fix a point only up to a mirror image) and are dropped and reported; the
    result has NaN rows for them.

    Then, with ``offsets="none"`` (the default), one range offset common to every entry
    (the tag's antenna delay) is fitted and kept when a block jackknife t test over time
    blocks finds it (``common_offset="test"``, :mod:`selfcal.toa.recipes.common_offset`): the
    blocks are as long as the residuals' correlation length, so the test holds under the
    serial correlation and the systematic misfit of a moving tag, where a test counting
    ranges as independent accepts any parameter (nested F = 953 / 1305 on data4 / data5).
    A kept offset makes the result ``offsets="common"`` (``receiver_offsets`` all equal),
    and the ``--known`` / ``--frame`` refits fit that same model.

    Then per-anchor offsets (UWB ranging biases, tens of cm; ``offsets="receivers"``) are
    refitted from that fit and kept when they predict held-out tag positions better
    (:func:`selfcal.toa.verdict.crossval.choose_receiver_offsets`: K-fold over time blocks of tag
    positions, held-out positions located with the training fit's anchors and biases,
    leave-one-range-out prediction errors, one-standard-error rule), not by an in-sample
    test, which any extra parameter passes on real ranges, and whose anchors' mean squared
    error, estimated from the same folds' refits, is lower than the simpler model's (held-out
    prediction alone preferred per-anchor offsets on LPS data4 that placed the anchors worse,
    0.309 vs 0.166 m). The evidence is in ``details["offsets_choice"]``. A common offset is not chosen that way: it trades
    against the geometry's scale, so held-out ranges are predicted as well without it
    (simulated rooms: the same prediction error, anchor RMSE 0.21 m without against 0.04 m
    with); its block t test judges the value itself. ``offsets="auto"`` runs the same
    chain (a per-position offset, the other kinds of ``solve_toa``'s "auto", is a free
    clock per sample of one tag).

Choice of the defaults. Spike rejection: by principle (it uses only the stated
assumption, a smooth trajectory, and no parameter fitted to a data set). A variant that
chose the common offset by a robust residual profile scored best on the two shared LPS
flights, but issue 12 reports it worse than the data set authors' estimate on 6 of 6
flights of the same system outside ``shared/``; it stays an explicit opt-in
(``common_offset="profile"``). The common offset: by physics (two-way UWB ranging
carries an antenna delay common to the tag's ranges; negative ranges near an anchor are
direct evidence of it) and a test valid for dependent, misspecified residuals; its 5 %
level was compared with 1e-3 and 1e-2 on 24 simulated flights with the real faults
(:func:`selfcal.experiments.lps.simulate_uwb_flight`: per-anchor bias, common bias, no
bias, AR(1) noise, NLOS stretches, multipath spikes; LPS and room geometries), never on
the shared flights (kept there at every level: t = -7.7 / -10.8, anchor RMSE 0.236 ->
0.185 and 0.176 -> 0.155 m against the authors' 0.235 / 0.170). The one-sided Bonferroni
spike rule replaced a two-sided 3.5-sigma rule by principle (the physics of NLOS, a
stated false-alarm rate); every variant is scored by
``benchmarks/lps_variants.py`` (docs/results.md, "Results on real data").
"""

from __future__ import annotations

import dataclasses
import warnings
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..._checks import as_matrix, check_choice, check_toa_observable
from ..._result import WrappedResult
from ...errors import InputError
from ...robust import mad_std

__all__ = ["RECIPES", "RecipeResult", "TimeOrderTest", "apply_recipe", "detect_time_order", "moving_tag",
           "spike_threshold"]

Array = NDArray[np.float64]

RECIPES = ("auto", "none", "moving-tag")

# the time-order test: significance level and permutations (the smallest attainable
# p-value is 1 / (n + 1), so n = 999 resolves the 1e-3 level)
TIME_ORDER_ALPHA = 1e-3
TIME_ORDER_PERMUTATIONS = 999
# random orders at least as smooth as the given one after which the test stops (its
# decision is then certain: not a time series); sets the precision of the reported p-value
TIME_ORDER_HITS = 10
# the spike detector's local quadratic needs a window of samples on each side
_MIN_SAMPLES = 20


@dataclass(frozen=True)
class TimeOrderTest:
    """Result of :func:`detect_time_order`.

    Attributes
    ----------
    detected: the columns are a time series at level ``alpha``.
    p_value: permutation p-value of the observed total variation.
    ratio: observed total variation over the median of the permuted ones (about 1 for
        exchangeable columns, << 1 for a densely sampled trajectory).
    alpha, permutations: the test's level and number of random orders drawn (fewer than
        asked when the test stopped early with its decision certain, see
        :func:`detect_time_order`).
    """

    detected: bool
    p_value: float
    ratio: float
    alpha: float
    permutations: int

    def to_dict(self) -> dict[str, Any]:
        """JSON-safe dictionary."""
        return dataclasses.asdict(self)


def _total_variation(Y: Array, order: NDArray[np.intp]) -> float:
    Z = Y[:, order]
    dz = np.abs(np.diff(Z, axis=1))
    return float(np.nansum(dz))


def detect_time_order(matrix: Any, *, alpha: float = TIME_ORDER_ALPHA,
                      permutations: int = TIME_ORDER_PERMUTATIONS, rng: Any = 0) -> TimeOrderTest:
    """Permutation test: are the columns of ``matrix`` samples of one device in time order?

    Statistic: the total variation ``sum_i sum_j |y_i,j+1 - y_i,j|`` over consecutive
    observed pairs. Under the null hypothesis (exchangeable columns: independent sources)
    every column order has the same distribution, so the p-value is the rank of the
    observed statistic among ``permutations`` random orders, ``(1 + #{TV_perm <= TV}) /
    (permutations + 1)``. Rows are standardised by their robust scale first so that no
    receiver dominates. The orders are drawn until :data:`TIME_ORDER_HITS` of them are as
    smooth as the given one (then the full test cannot reject: the same decision, the
    sequential p-value ``hits / drawn`` of Besag & Clifford 1991) or all are drawn.

    Parameters
    ----------
    matrix: (I, J) ranges or times, NaN = missing.
    alpha: significance level.
    permutations: number of random column orders.
    rng: seed / Generator of the permutations.

    Returns
    -------
    :class:`TimeOrderTest` (never detected with fewer than 20 columns).
    """
    from ..._checks import as_rng

    Y = as_matrix(matrix, "matrix")
    # rows with fewer than two entries add no consecutive pair to any order's statistic:
    # dropping them changes nothing but the cost (3000 rows of which 6 observed: 500x)
    Y = Y[np.isfinite(Y).sum(axis=1) >= 2]
    I, J = Y.shape
    if J < _MIN_SAMPLES or I == 0:
        return TimeOrderTest(False, 1.0, 1.0, float(alpha), 0)
    with np.errstate(all="ignore"):
        med = np.nanmedian(Y, axis=1, keepdims=True)
        sc = mad_std(Y, axis=1, keepdims=True)
    sc = np.where(np.isfinite(sc) & (sc > 0), sc, 1.0)
    Z = (Y - med) / sc
    gen = as_rng(rng)
    tv = _total_variation(Z, np.arange(J))
    n = int(permutations)
    # sequential stop (Besag & Clifford 1991): once ``stop`` random orders are as smooth as
    # the given one, the full test's p-value exceeds alpha whatever the rest would give, so
    # the decision is that of all n orders; the p-value reported is then the sequential
    # one, stop / (orders drawn), itself valid. Independent sources stop after ~2 stop orders
    # (1000 x 1000: 20 orders, 0.3 s, instead of 999, 15 s)
    stop = max(TIME_ORDER_HITS, int(np.floor(alpha * (n + 1))))
    perm: list[float] = []
    hits = 0
    for _ in range(n):
        perm.append(_total_variation(Z, gen.permutation(J)))
        hits += perm[-1] <= tv
        if hits >= stop:
            break
    p = float(hits / len(perm)) if hits >= stop and len(perm) < n else float((1 + hits) / (n + 1))
    mid = float(np.median(perm)) if perm else 0.0
    ratio = float(tv / mid) if mid > 0 else 1.0
    return TimeOrderTest(bool(p <= alpha), p, ratio, float(alpha), len(perm))


@dataclass(frozen=True, repr=False)
class RecipeResult(WrappedResult):
    """A :class:`selfcal.toa.solve.ToaResult` plus what the recipe did to the data.

    Every attribute of the wrapped result is available directly; ``to_dict()`` adds the
    key ``"recipe"``; status, summary and dict follow the :class:`~selfcal._result.Result`
    convention (:class:`~selfcal._result.WrappedResult`).

    Attributes
    ----------
    result: the calibration (rows / columns of the full input; dropped nodes are NaN).
    recipe: the recipe name.
    rejected: (I, J) bool, entries removed as spikes before the fit.
    dropped_sources, dropped_receivers: indices removed for having too few ranges left.
    details: recipe-specific numbers (e.g. the profiled common offset).
    """

    recipe: str
    rejected: NDArray[np.bool_]
    dropped_sources: tuple[int, ...] = ()
    dropped_receivers: tuple[int, ...] = ()
    details: dict[str, Any] = field(default_factory=dict)

    @property
    def n_rejected(self) -> int:
        """Number of entries removed as spikes."""
        return int(self.rejected.sum())

    def to_dict(self) -> dict[str, Any]:
        """The wrapped result's dictionary with ``"recipe"`` added."""
        out = dict(self.result.to_dict())
        out["recipe"] = self.recipe_dict()
        return out

    def recipe_dict(self) -> dict[str, Any]:
        """What the recipe did (the ``"recipe"`` entry of :meth:`to_dict`), without the result."""
        return {
            "name": self.recipe,
            "n_rejected": self.n_rejected,
            "rejected_fraction": float(self.rejected.sum() / max(self.rejected.size, 1)),
            "dropped_sources": list(self.dropped_sources),
            "dropped_receivers": list(self.dropped_receivers),
            **{k: v for k, v in self.details.items()},
        }


def _embed_columns(result: Any, keep: NDArray[np.bool_], J: int, M: Array) -> Any:
    """Write a result fitted on the kept columns back into the full column count (NaN)."""
    names = {f.name for f in dataclasses.fields(result)}

    def put(val: Any, shape: tuple[int, ...]) -> Any:
        if val is None:
            return None
        out = np.full((J,) + shape, np.nan)
        out[keep] = np.asarray(val)
        return out

    d = np.asarray(result.receivers).shape[1]
    kw: dict[str, Any] = {
        "sources": put(result.sources, (d,)),
        "source_cov": put(result.source_cov, (d, d)),
        "source_offsets": put(result.source_offsets, ()),
        "source_offset_std": put(result.source_offset_std, ()),
    }
    if result.residuals is not None:
        res = np.full((M.shape[0], J), np.nan)
        res[:, keep] = result.residuals
        kw["residuals"] = res
    if result.outliers is not None:
        out = np.zeros((M.shape[0], J), bool)
        out[:, keep] = result.outliers
        kw["outliers"] = out
    if "dropped_sources" in names:
        # the solver's drops are in the kept columns' numbering; every NaN row is reported
        cols = np.nonzero(keep)[0]
        solver = {int(cols[j]) for j in result.dropped_sources}
        kw["dropped_sources"] = tuple(sorted(solver | {int(j) for j in np.nonzero(~keep)[0]}))
    if "n_missing" in names:
        kw["n_missing"] = int((~np.isfinite(M)).sum())
    det = result.determinacy
    if det is not None and "determinacy" in names:  # the undetermined nodes in the caller's numbering
        kw["determinacy"] = det.embedded(None, keep)
        if det.n_undetermined:
            kw["verdict_message"] = result.verdict_message.replace(det.names(), kw["determinacy"].names())
    return dataclasses.replace(result, **{k: v for k, v in kw.items() if k in names})


def moving_tag(
    matrix: Any,
    *,
    times: Any = None,
    dim: int | str = 3,
    threshold: float | str = "bonferroni",
    half_window: int = 7,
    degree: int = 2,
    one_sided: bool = True,
    common_offset: str = "test",
    speed: float | None = None,
    **solve_kw: Any,
) -> RecipeResult:
    """Calibrate a moving-tag recording: spike rejection in time, then :func:`solve_toa`.

    Parameters
    ----------
    matrix: (I, J) ranges in metres (seconds with ``speed``); rows = fixed anchors,
        columns = tag positions **in time order**; NaN = missing.
    times: (J,) increasing sample times (any unit); default equally spaced.
    dim: 2, 3 or "auto" (chosen by :func:`selfcal.toa.verdict.select.choose_dim`).
    threshold, half_window, degree, one_sided: of the spike detector
        (:func:`selfcal.toa.recipes.preprocess.reject_range_outliers`). ``threshold`` in robust
        standard deviations, or ``"bonferroni"``: the normal quantile that flags any
        Gaussian entry of the matrix with probability at most
        :data:`selfcal.toa.verdict.robust.OUTLIER_ALPHA` (:func:`spike_threshold`), the same
        false-alarm rule as the solver's own outlier test.
    common_offset: "test" (default: with offsets "none" or "auto", one range offset common
        to every entry, a UWB antenna delay, kept when the block jackknife t test over time
        blocks finds it at p < 0.05, :func:`selfcal.toa.recipes.common_offset.choose_common_offset`;
        the result then has ``offsets="common"`` and the test is in
        ``details["common_offset_test"]``; then per-anchor offsets (ranging biases), kept
        when they predict held-out tag positions better and their anchors' estimated MSE
        is lower,
        :func:`selfcal.toa.verdict.crossval.choose_receiver_offsets`: ``offsets="receivers"``, the
        evidence in ``details["offsets_choice"]``), "free" (the fit as ``solve_toa`` does it with
        the ``offsets`` given in ``solve_kw``, no common offset) or "profile" (opt-in:
        per-anchor offsets whose common part minimises the trimmed residual scale,
        :func:`selfcal.toa.recipes.preprocess.fit_offsets_profile_common`; ``offsets`` must be
        "none" or "receivers").
    speed: propagation speed (m/s) when the matrix holds seconds.
    **solve_kw: passed to :func:`selfcal.toa.solve_toa` (``offsets``, ``loss``, ``rng``,
        ``noise``, ...).

    Returns
    -------
    :class:`RecipeResult` (dropped tag positions are NaN rows of ``sources``).

    Raises
    ------
    InputError: bad matrix or options, too few samples for the local polynomial.
    DegenerateGeometryError: what remains after the cleaning does not determine the
        geometry.

    Examples
    --------
    >>> import numpy as np
    >>> from selfcal.toa.engine.nls import toa_model
    >>> rng = np.random.default_rng(0)
    >>> anchors = rng.uniform(0, 5, (6, 3))
    >>> t = np.linspace(0, 20, 300)
    >>> tag = np.c_[2.5 + 2 * np.cos(t / 3), 2.5 + 2 * np.sin(t / 2), 1.5 + np.sin(t / 5)]
    >>> Y = toa_model(anchors, tag) + 0.02 * rng.standard_normal((6, 300))
    >>> Y[2, 100] += 1.5  # a multipath spike
    >>> res = moving_tag(Y, rng=0)
    >>> bool(res.rejected[2, 100])
    True
    """
    from ..solve import solve_toa
    from .preprocess import fit_offsets_profile_common, reject_range_outliers

    check_choice(common_offset, "common_offset", ("free", "profile", "test"))
    M = as_matrix(matrix, "matrix")
    I, J = M.shape
    scale = 1.0 if speed is None else float(speed)
    if isinstance(threshold, str):
        check_choice(threshold, "threshold", ("bonferroni",))
        k = spike_threshold(M, one_sided)
    else:
        k = float(threshold)
    rej = reject_range_outliers(M * scale, times, half_window=half_window, degree=degree,
                                threshold=k, one_sided=one_sided)
    cleaned = rej.ranges / scale
    # dim="auto": a tag position is kept when it can be located in the largest dimension the
    # anchors can span (3-D needs 4 anchors off a plane); the solver then chooses the dimension
    d_keep = (3 if M.shape[0] >= 4 else 2) if dim == "auto" else int(dim)
    keep = np.isfinite(cleaned).sum(axis=0) >= d_keep + 1
    dropped = tuple(int(j) for j in np.nonzero(~keep)[0])
    if keep.sum() < d_keep + 1:
        raise InputError(f"after spike rejection only {int(keep.sum())} tag positions keep {d_keep + 1} "
                         "ranges; the recording is too short or too sparse for this recipe")
    sub = cleaned[:, keep]
    details: dict[str, Any] = {"threshold": float(k), "half_window": int(half_window),
                               "degree": int(degree), "one_sided": bool(one_sided),
                               "common_offset": common_offset}
    if common_offset == "profile":
        offs = solve_kw.pop("offsets", "receivers")
        if offs not in ("none", "receivers"):
            raise InputError("common_offset='profile' estimates per-anchor offsets: use offsets='receivers'")
        base = solve_toa(sub, dim=dim, speed=speed, offsets="none", **_plain(solve_kw))
        prof = fit_offsets_profile_common(sub * scale, base.receivers, base.sources)
        res = _profile_result(base, prof, sub, scale)
        details["common_offset_value"] = float(prof.common / scale)
        details["profile"] = {"grid": (prof.grid / scale).tolist(), "scale": prof.profile.tolist()}
    else:
        # the solver's warnings name nodes in the kept columns' numbering: held, then re-issued
        # in the caller's numbering once the result is embedded (as its message is)
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            if common_offset == "test" and solve_kw.get("offsets") == "auto":
                # a moving tag's offset models are those of the anchors (a per-position offset is
                # a free clock per sample): "auto" is the choice below, from the offsets-free fit
                solve_kw = {**solve_kw, "offsets": "none"}
            res = solve_toa(sub, dim=dim, speed=speed, **solve_kw)
            if common_offset == "test" and res.offsets == "none":
                from ...progress import stage
                from ..verdict.crossval import choose_receiver_offsets
                from .common_offset import choose_common_offset

                with stage("common range offset: block jackknife", unit="refits"):
                    res, test = choose_common_offset(res, sub, scale)
                details["common_offset_test"] = test
                details["common_offset_value"] = test.get("value") if test["adopted"] else 0.0
                # per-anchor ranging biases: kept when they predict held-out tag positions better
                with stage("per-anchor biases: held-out prediction", unit="refits") as progress:
                    res, cv = choose_receiver_offsets(res, sub, scale, progress=progress)
                if cv is not None:
                    details["offsets_choice"] = cv.to_dict()
                details["offsets"] = res.offsets
                # error bars that hold on a flight's serially correlated, position-dependent errors
                from ..verdict.jackknife import jackknife_blind_fit

                with stage("anchor error bars: block jackknife", unit="refits"):
                    res, js = jackknife_blind_fit(res, sub, scale)
                if js is not None:
                    details["error_scale"] = js.to_dict()
        inner = res.determinacy
        res = _embed_columns(res, keep, J, M)
        _reissue(caught, inner, res.determinacy)
        return RecipeResult(res, "moving-tag", rej.outliers, dropped, (), details)
    res = _embed_columns(res, keep, J, M)
    return RecipeResult(res, "moving-tag", rej.outliers, dropped, (), details)


def _reissue(caught: list[warnings.WarningMessage], inner: Any, outer: Any) -> None:
    """Re-issue held warnings, the undetermined nodes' names mapped to the caller's numbering."""
    old = inner.names() if inner is not None and inner.n_undetermined else ""
    new = outer.names() if outer is not None and old else ""
    for w in caught:
        text = str(w.message)
        if old and old in text:
            text = text.replace(old, new)
        warnings.warn_explicit(text, w.category, w.filename, w.lineno)


def spike_threshold(matrix: Any, one_sided: bool = False, alpha: float | None = None) -> float:
    """Spike threshold (robust sigmas) with family-wise false-alarm rate ``alpha`` over the matrix.

    ``k = Phi^-1(1 - alpha / m)`` one-sided (only positive spikes tested), ``Phi^-1(1 - alpha /
    (2 m))`` two-sided, ``m`` the observed entries (Bonferroni): under Gaussian noise the
    probability that any clean entry is rejected is at most ``alpha`` (default
    :data:`selfcal.toa.verdict.robust.OUTLIER_ALPHA`, 1 %), whatever the recording's length.

    Examples
    --------
    >>> round(spike_threshold(np.ones((6, 600)), one_sided=True), 2)
    4.54
    """
    from ..verdict.robust import OUTLIER_ALPHA, outlier_threshold

    a = OUTLIER_ALPHA if alpha is None else float(alpha)
    m = int(np.isfinite(np.asarray(matrix, float)).sum())
    # outlier_threshold is the two-sided quantile Phi^-1(1 - a / (2 m)); one-sided = twice a
    return outlier_threshold(m, 2 * a if one_sided else a)


def _plain(kw: dict[str, Any]) -> dict[str, Any]:
    return {k: v for k, v in kw.items() if k != "offsets"}


def _profile_result(base: Any, prof: Any, sub: Array, scale: float) -> Any:
    """The base ToaResult with the profiled receivers / sources / offsets written in."""
    from ...geometry import canonical_gauge
    from ..engine.nls import toa_model

    names = {f.name for f in dataclasses.fields(base)}
    r, s_, _ = canonical_gauge(prof.receivers, prof.sources)
    assert s_ is not None
    s = s_
    model = toa_model(prof.receivers, prof.sources, prof.receiver_offsets)
    res = np.where(np.isfinite(sub), sub - model / scale, np.nan)
    I, d = r.shape
    kw = {
        "receivers": r, "sources": s, "receiver_offsets": prof.receiver_offsets / scale,
        "source_offsets": None, "receiver_cov": np.full((I, d, d), np.nan),
        "source_cov": np.full((s.shape[0], d, d), np.nan), "residual_rms": prof.residual_rms / scale,
        "converged": prof.converged, "iterations": int(base.iterations) + int(prof.iterations),
        "method": f"{base.method}+profile-common-offset", "residuals": res,
        "receiver_offset_std": None, "source_offset_std": None,
    }
    return dataclasses.replace(base, **{k: v for k, v in kw.items() if k in names})


def apply_recipe(name: str, matrix: Any, *, common_offset: str = "test", **kw: Any) -> Any:
    """Run recipe ``name`` (one of :data:`RECIPES`) on ``matrix``; ``"none"`` is solve_toa.

    ``"auto"`` runs ``"moving-tag"`` when :func:`detect_time_order` detects that the
    columns are a time series, else ``"none"``; the test is in ``details["auto"]``.
    ``common_offset`` is the moving-tag option (:func:`moving_tag`), unused by "none".
    Returns a :class:`RecipeResult` for every recipe (``rejected`` all False for "none").
    """
    from ..solve import solve_toa

    check_choice(name, "recipe", RECIPES)
    if name == "auto":
        M = as_matrix(matrix, "matrix")
        # a matrix neither recipe can solve (too few rows / columns / entries even for the
        # least demanding model: the smallest dimension, no offsets) is refused before the
        # time-order test, whose cost grows with the columns (1 x 200000: 12 s for nothing)
        dim = kw.get("dim", 3)
        check_toa_observable(M, 2 if dim == "auto" else int(dim), "none")
        test = detect_time_order(M)
        if test.detected:
            out = moving_tag(M, common_offset=common_offset, **kw)
            return dataclasses.replace(out, details={**out.details, "auto": test.to_dict()})
        res = solve_toa(M, **kw)
        return RecipeResult(res, "none", np.zeros(M.shape, bool), details={"auto": test.to_dict()})
    if name == "none":
        M = as_matrix(matrix, "matrix")
        res = solve_toa(M, **kw)
        return RecipeResult(res, "none", np.zeros(M.shape, bool))
    if name == "moving-tag":
        return moving_tag(matrix, common_offset=common_offset, **kw)
    raise InputError(f"unknown recipe {name!r}")  # pragma: no cover - check_choice above
