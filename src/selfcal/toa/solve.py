"""``solve_toa``: anchor-free TOA / range self-calibration end to end (papers 003, 004).

Validation -> unit conversion (seconds -> metres with ``speed``) -> initialisation
(003 Alg. 1/2 family for plain TOA, the 004 rank-3 iteration with offsets) ->
sparse NLS refinement with covariances (:func:`selfcal.toa.nls.refine_toa`) ->
multi-start when the fit is implausible -> :class:`ToaResult` in the canonical gauge.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .._checks import (
    as_matrix,
    as_points,
    as_rng,
    check_choice,
    check_dim,
    check_positive,
    check_toa_counts,
    entry,
)
from .._result import Result
from ..errors import DegenerateGeometryError, InputError
from .covariance import normalize_covariance
from .nls import LOSSES, OFFSET_MODES, NlsSolution, refine_toa, toa_model

__all__ = ["ResidualTest", "ToaResult", "n_parameters", "residual_test", "solve_toa"]

Array = NDArray[np.float64]

METHODS = ("auto", "nls", "rank3")
#: significance level of the residual test: a fit whose chi-square has p below this is rejected
RESIDUAL_ALPHA = 1e-3
#: rank-3 candidate starts compared by the full model's fit (I + J <= SWEEP_MAX_NODES)
RANK_CANDIDATES = 4
#: iteration cap of the short refinements that rank the initial candidates
RANK_NFEV = 30
#: rank-3 starts and kept candidates of the deep search (:func:`_deep_search`)
DEEP_STARTS = 40
DEEP_CANDIDATES = 12


@dataclass(frozen=True)
class ResidualTest:
    """Chi-square test of a fit's residuals against a known timing-noise level.

    Attributes
    ----------
    chi2: weighted residual sum of squares ``sum_ij (e_ij / noise)^2`` over the observed
        entries (dimensionless; ``e_ij`` measured minus modelled, matrix units).
    dof: degrees of freedom ``m - n`` (m observations, n free parameters, gauge removed,
        :func:`n_parameters`).
    p_value: ``P(chi2_dof >= chi2)``; NaN when ``dof <= 0`` (nothing to test).
    noise: the timing / range noise std the residuals were weighted with (matrix units).
    alpha: significance level; ``passed`` is ``not p_value < alpha``.
    passed: False when the residuals are too large for the noise: a wrong basin, wrong
        geometry or model, or a noise level set too low.
    """

    chi2: float
    dof: int
    p_value: float
    noise: float
    alpha: float
    passed: bool

    def to_dict(self) -> dict[str, Any]:
        """JSON-safe dict (chi2, dof, p_value, noise, alpha, passed)."""
        return {"chi2": float(self.chi2), "dof": int(self.dof), "p_value": float(self.p_value),
                "noise": float(self.noise), "alpha": float(self.alpha), "passed": bool(self.passed)}


def n_parameters(n_receivers: int, n_sources: int, dim: int, offsets: str) -> int:
    """Free parameters of the TOA model up to the gauge (003 eq. 2, 004 eq. 3.1).

    ``dim (I + J)`` coordinates minus the ``dim (dim + 1) / 2`` of a rigid motion, plus
    ``I + J - 1`` offsets for ``offsets="both"`` (a common shift between delays and onsets
    is not observable), ``I`` for "receivers", ``J`` for "sources", 0 for "none".
    """
    check_choice(offsets, "offsets", OFFSET_MODES)
    I, J = int(n_receivers), int(n_sources)
    n_off = {"none": 0, "receivers": I, "sources": J, "both": I + J - 1}[offsets]
    return dim * (I + J) - dim * (dim + 1) // 2 + n_off


def residual_test(residuals: Any, noise: float, n_params: int, *, alpha: float = RESIDUAL_ALPHA) -> ResidualTest:
    """Chi-square goodness-of-fit test of TOA residuals (ML fit under Gaussian noise, 003 eq. 2).

    At the global minimum with i.i.d. Gaussian timing noise of std ``noise`` the weighted
    residual sum of squares ``chi2 = sum_ij (e_ij / noise)^2`` follows (to first order) a
    chi-square law with ``dof = m - n_params`` degrees of freedom (m observed entries). A
    wrong basin leaves systematic misfit and a much larger chi2; the fit is rejected when
    ``P(chi2_dof >= chi2) < alpha``.

    Parameters
    ----------
    residuals: (I, J) measured minus modelled, in the units of ``noise`` (e.g. seconds); NaN = missing.
    noise: timing-noise standard deviation (> 0), same units.
    n_params: free parameters of the model (:func:`n_parameters`).
    alpha: significance level (default 1e-3).

    Returns
    -------
    ResidualTest
    """
    from scipy.stats import chi2 as chi2_dist

    sd = check_positive(noise, "noise")
    assert sd is not None
    e = np.asarray(residuals, dtype=float)
    e = e[np.isfinite(e)]
    chi2 = float(np.sum((e / sd) ** 2))
    dof = int(e.size - int(n_params))
    p = float(chi2_dist.sf(chi2, dof)) if dof > 0 else float("nan")
    return ResidualTest(chi2, dof, p, float(sd), float(alpha), passed=not p < alpha)


@dataclass(frozen=True, repr=False)
class ToaResult(Result):
    """Result of :func:`solve_toa`.

    Attributes
    ----------
    receivers, sources: (I, d), (J, d) positions in metres, canonical gauge
        (receiver centroid at 0, receiver principal axes along x, y(, z)).
    receiver_offsets, source_offsets: (I,), (J,) or None; seconds when ``speed`` was
        given, metres otherwise. With both kinds, ``source_offsets[0] == 0``.
    receiver_cov, source_cov: (I, d, d), (J, d, d) gauge-free covariances (m^2,
        003 eq. 17); NaN when not available (``method="rank3"``).
    residual_rms, sigma: RMS of the observed residuals and the estimated noise std,
        in the matrix's units (seconds with ``speed``).
    converged, iterations: solver status (iterations summed over starts).
    method: what ran, e.g. ``"mds+nls"``, ``"rank3+nls"``, ``"given+nls"``, ``"rank3"``;
        ``"+multistart(k)"`` when k extra starts were tried.
    n_missing: number of missing (NaN) entries.
    n_starts: number of refinements run (1 unless the multi-start triggered).
    receiver_offset_std, source_offset_std: offset standard deviations (minimum-norm gauge).
    speed: propagation speed used (m/s) or None.
    residuals: (I, J) measured minus modelled, matrix units, NaN where missing.
    fit: chi-square residual test (:func:`residual_test`) when ``noise`` was given, else None.
    """

    receivers: Array
    sources: Array
    receiver_offsets: Array | None
    source_offsets: Array | None
    receiver_cov: Array
    source_cov: Array
    residual_rms: float
    sigma: float
    converged: bool
    iterations: int
    method: str
    n_missing: int
    n_starts: int = 1
    receiver_offset_std: Array | None = None
    source_offset_std: Array | None = None
    speed: float | None = None
    residuals: Array | None = None
    fit: ResidualTest | None = None

    @property
    def noise_estimate(self) -> float:
        """The estimated noise std (alias of ``sigma``), matrix units."""
        return self.sigma

    @property
    def noise(self) -> float | None:
        """The given noise std the residual test used (``fit.noise``), or None."""
        return None if self.fit is None else self.fit.noise

    def to_dict(self) -> dict[str, Any]:
        """JSON-safe dict with exactly the DESIGN.md toa keys plus extras (units, sigma, ...)."""

        def tl(a: Array | None) -> Any:
            return None if a is None else np.asarray(a, dtype=float).tolist()

        unit = "s" if self.speed is not None else "m"
        return {
            "receivers": tl(self.receivers),
            "sources": tl(self.sources),
            "receiver_offsets": tl(self.receiver_offsets),
            "source_offsets": tl(self.source_offsets),
            "receiver_cov": tl(self.receiver_cov),
            "source_cov": tl(self.source_cov),
            "residual_rms": float(self.residual_rms),
            "converged": bool(self.converged),
            "iterations": int(self.iterations),
            "method": self.method,
            # extras
            "sigma": float(self.sigma),
            "n_missing": int(self.n_missing),
            "n_starts": int(self.n_starts),
            "receiver_offset_std": tl(self.receiver_offset_std),
            "source_offset_std": tl(self.source_offset_std),
            "speed": self.speed,
            "fit": None if self.fit is None else self.fit.to_dict(),
            "units": {"positions": "m", "covariances": "m^2", "offsets": unit, "residual_rms": unit},
        }


# ---------------------------------------------------------------------------
# initialisation
# ---------------------------------------------------------------------------

_Init = tuple[Array, Array, Array | None, Array | None]


def _init_plain(ranges: Array, dim: int, rng: np.random.Generator) -> list[tuple[str, _Init]]:
    """Candidate starts for offsets="none": the 003 initialisers (``selfcal.toa.mds``)."""
    from . import mds

    r, s = mds.initialize_toa(ranges, dim, rng=rng)
    return [("mds", (np.asarray(r, float), np.asarray(s, float), None, None))]


def _sane(start: _Init, ranges: Array) -> bool:
    """A start is usable when it is finite and within 100x the scale of the data."""
    lim = 100.0 * (float(np.nanmax(np.abs(ranges))) + 1.0)
    for part in start:
        if part is not None and not (np.isfinite(part).all() and np.abs(part).max() <= lim):
            return False
    return True


def _kept_offsets(r: Array, s: Array, d0: Array, o0: Array, offsets: str) -> _Init:
    """A rank-3 start (both kinds of offsets) collapsed to the kinds ``offsets`` keeps.

    The true other kind is zero, so its estimate is (up to noise) the common shift c, which
    moves into the kept kind (``d_i + c`` or ``o_j + c``).
    """
    r, s = np.asarray(r, float), np.asarray(s, float)
    d0, o0 = np.asarray(d0, float), np.asarray(o0, float)
    if offsets == "receivers":
        return r, s, d0 + np.mean(o0), None
    if offsets == "sources":
        return r, s, None, o0 + np.mean(d0)
    return r, s, d0, o0


def _init_offsets(ranges: Array, dim: int, offsets: str, rng: np.random.Generator, *,
                  n_starts: int = 8, max_candidates: int = 4) -> list[tuple[str, _Init]]:
    """Starts for offsets in {receivers, sources, both}: the 004 rank-3 initialiser, then MDS.

    The rank-3 initialiser contributes up to ``max_candidates`` distinct starts
    (:func:`selfcal.toa.offsets.initialize_offsets_candidates`, smallest Frobenius norm
    first); :func:`solve_toa` ranks them by the fit of the full model (:func:`_rank_starts`).

    For a single kind of offset the rank-3 estimate of both kinds is collapsed: the
    true other kind is zero, so its estimate is (up to noise) the common shift c,
    which moves into the kept kind (``d_i + c`` or ``o_j + c``). The fallback (used
    when the rank-3 initialiser cannot run or returns a non-finite / absurd start) is
    MDS on the ranges shifted to be non-negative, with the offsets started at zero:
    good when the offsets are small compared with the ranges.
    """
    from . import mds
    from . import offsets as off

    I, J = ranges.shape
    out: list[tuple[str, _Init]] = []
    inputs = [ranges]
    if np.isnan(ranges).any():
        inputs.append(_fill_additive(ranges))
    for Z in inputs:
        try:
            found = off.initialize_offsets_candidates(Z, dim, rng=rng, n_starts=n_starts,
                                                      max_candidates=max_candidates)
        except (DegenerateGeometryError, InputError):
            continue
        for r, s, d0, o0 in found:
            cand = _kept_offsets(r, s, d0, o0, offsets)
            if _sane(cand, ranges):
                out.append(("rank3", cand))
        if out:
            break
    shift = min(0.0, float(np.nanmin(ranges)))
    r, s = mds.initialize_toa(ranges - shift, dim, rng=rng)
    has_r, has_s = offsets in ("receivers", "both"), offsets in ("sources", "both")
    out.append(("mds", (np.asarray(r, float), np.asarray(s, float),
                        np.zeros(I) if has_r else None, np.zeros(J) if has_s else None)))
    return out


def _fill_additive(ranges: Array, iterations: int = 50) -> Array:
    """Fill missing entries from a two-way additive fit ``y_ij ~ a_i + b_j`` (start only).

    With offsets the matrix is dominated by ``d_i + o_j`` plus ranges that vary
    less; the additive fit (alternating row / column means over the observed
    entries) gives the rank-3 initialiser a complete matrix. The NLS afterwards
    uses only the observed entries.
    """
    obs = np.isfinite(ranges)
    Y = np.where(obs, ranges, 0.0)
    n_r = np.maximum(obs.sum(axis=1), 1)
    n_c = np.maximum(obs.sum(axis=0), 1)
    a = np.zeros(ranges.shape[0])
    b = np.zeros(ranges.shape[1])
    for _ in range(iterations):
        a = ((Y - b[None, :]) * obs).sum(axis=1) / n_r
        b = ((Y - a[:, None]) * obs).sum(axis=0) / n_c
    return np.where(obs, ranges, a[:, None] + b[None, :])


def _given_init(init: Any, I: int, J: int, dim: int, offsets: str, scale: float) -> _Init:
    """Validate an explicit ``init=(receivers, sources[, receiver_offsets, source_offsets])``."""
    if not isinstance(init, (tuple, list)) or len(init) not in (2, 4):
        raise InputError("init must be 'auto' or a tuple (receivers, sources[, receiver_offsets, source_offsets])")
    r = as_points(init[0], "init receivers", dim=dim)
    s = as_points(init[1], "init sources", dim=dim)
    if r.shape[0] != I or s.shape[0] != J:
        raise InputError(f"init has {r.shape[0]} receivers and {s.shape[0]} sources; the matrix is {I} x {J}")
    d0 = o0 = None
    if len(init) == 4:
        d0 = None if init[2] is None else np.asarray(init[2], float).ravel() * scale
        o0 = None if init[3] is None else np.asarray(init[3], float).ravel() * scale
    if offsets in ("receivers", "both") and d0 is None:
        d0 = np.zeros(I)
    if offsets in ("sources", "both") and o0 is None:
        o0 = np.zeros(J)
    return r, s, (d0 if offsets in ("receivers", "both") else None), (o0 if offsets in ("sources", "both") else None)


def _implausible(sol: NlsSolution, robust: bool = False) -> bool:
    """Heuristic test for a local minimum from the residuals alone (the noise level is unknown).

    At the ML solution with i.i.d. Gaussian noise (i) every receiver's and source's
    residual RMS is close to the median one, (ii) the RMS is close to the MAD-based
    std and (iii) the largest residual is a few MAD-stds. A wrong basin (e.g. sources
    mirrored across the receivers) concentrates misfit on a few nodes and entries.
    Criteria (ii)-(iii) are skipped for robust losses, where outliers are expected.
    """
    R = sol.residuals
    if not sol.converged:
        return True
    f = R[np.isfinite(R)]
    if not np.isfinite(sol.residual_rms) or sol.residual_rms <= 1e-9 * (1 + np.abs(f).max()):
        return False
    if robust:  # outliers inflate node RMS: use each node's median absolute residual
        node = np.concatenate([np.nanmedian(np.abs(R), axis=1), np.nanmedian(np.abs(R), axis=0)])
    else:
        node = np.concatenate([np.sqrt(np.nanmean(R**2, axis=1)), np.sqrt(np.nanmean(R**2, axis=0))])
    node = node[np.isfinite(node)]
    if node.max() > 3.0 * np.median(node):
        return True
    if robust:
        return False
    mad_std = 1.4826 * float(np.median(np.abs(f)))
    if mad_std <= 0:
        return False
    extreme = max(6.0, float(np.sqrt(2 * np.log(f.size))) + 2.0)
    return bool(sol.residual_rms > 1.5 * mad_std or np.abs(f).max() > extreme * mad_std)


# ---------------------------------------------------------------------------
# entry point
# ---------------------------------------------------------------------------


@entry(matrix="array", dim="count", speed="positive?", rng="rng", f_scale="positive?", max_nfev="count?",
       noise="positive?")
def solve_toa(
    matrix: Any,
    *,
    dim: int = 3,
    offsets: str = "none",
    speed: float | None = None,
    loss: str = "linear",
    init: Any = "auto",
    method: str = "auto",
    rng: np.random.Generator | int | None = None,
    f_scale: float | None = None,
    max_nfev: int | None = None,
    covariance: Any = True,
    sweep: bool = True,
    noise: float | None = None,
) -> ToaResult:
    """Anchor-free self-calibration of receivers and sources from TOA / range measurements.

    Solves 003 eq. 2 (ML under Gaussian noise) for the model of entry (i, j)
    ``|r_i - s_j| + d_i + o_j`` (offsets per ``offsets``; 004 sec. 3), initialised by
    the 003 MDS family (``offsets="none"``) or the 004 rank-3 iteration (with
    offsets), refined by the sparse NLS of :func:`selfcal.toa.nls.refine_toa`.

    Parameters
    ----------
    matrix: (I, J) ranges in metres, or times in seconds when ``speed`` is given;
        rows = receivers, columns = sources, NaN = missing. Must be >= 0 when
        ``offsets="none"``.
    dim: 2 or 3.
    offsets: "none" | "receivers" | "sources" | "both".
    speed: propagation speed (m/s) converting seconds to metres; offsets, residual
        RMS and sigma are then reported in seconds.
    loss: "linear" | "huber" | "soft_l1" | "cauchy" (robust losses for outliers).
    init: "auto" or an explicit start ``(receivers, sources[, receiver_offsets,
        source_offsets])`` (positions in metres, offsets in the matrix's units).
    method: "auto" (initialise, refine, multi-start when the fit is implausible),
        "nls" (initialise and refine once) or "rank3" (the 004 initialiser only,
        offsets != "none").
    rng: seed / Generator for the randomised parts (initialisers, restarts).
    f_scale: robust-loss scale in the matrix's units (default: from a MAD estimate).
    max_nfev: iteration cap for the refinement.
    sweep: with ``method="auto"``, the linear loss and at most ``SWEEP_MAX_NODES`` nodes,
        re-place each node with the others fixed (its reflection through the plane of the
        others, its closed-form position) and refine again while that lowers the cost
        (:func:`_node_sweep`); escapes local minima the residual tests cannot detect.
    covariance: which per-point covariance blocks to compute: True / "all", "receivers",
        "sources", False / "none", or indices ``{"receivers": idx, "sources": idx}``
        (:func:`selfcal.toa.covariance.normalize_covariance`); the others are NaN-filled
        (skipping them saves most of the time on networks of a thousand nodes per side).
    noise: optional std of the measurement noise in the matrix's units (seconds with
        ``speed``). The result then carries ``fit``, the chi-square test of its weighted
        residual sum of squares against its degrees of freedom (:func:`residual_test`,
        rejected at p < 1e-3); with ``method="auto"`` a fit that fails the test starts a
        deep search over more rank-3 / MDS starts (:func:`_deep_search`), so fits that
        pass cost nothing extra.

    Returns
    -------
    ToaResult

    Raises
    ------
    InputError: malformed matrix (shape, inf, negative ranges without offsets), bad options.
    DegenerateGeometryError: too few receivers / sources / observations for ``dim``.
    """
    check_choice(offsets, "offsets", OFFSET_MODES)
    check_choice(loss, "loss", LOSSES)
    check_choice(method, "method", METHODS)
    covariance = normalize_covariance(covariance)  # False when no block is asked for
    dim = check_dim(dim)
    spd = check_positive(speed, "speed")
    M = as_matrix(matrix, "matrix", nonnegative=(offsets == "none"))
    I, J = M.shape
    obs = np.isfinite(M)
    check_toa_counts((I, J), int(obs.sum()), dim, offsets)
    if method == "rank3" and offsets == "none":
        raise InputError("method='rank3' estimates offsets: use offsets='both' (or 'receivers'/'sources'), or method='nls'")
    gen = as_rng(rng)
    scale = spd if spd is not None else 1.0
    ranges = M * scale
    fs = None if f_scale is None else float(check_positive(f_scale, "f_scale") or 1.0) * scale
    sd = check_positive(noise, "noise")
    n_par = n_parameters(I, J, dim, offsets)

    def test(sol: NlsSolution) -> ResidualTest | None:
        return None if sd is None else residual_test(sol.residuals / scale, sd, n_par)

    if isinstance(init, str):
        if init != "auto":
            raise InputError(f"init must be 'auto' or a tuple of arrays, got {init!r}")
        if offsets == "none":
            cands = _init_plain(ranges, dim, gen)
        else:
            k = RANK_CANDIDATES if method != "rank3" and I + J <= SWEEP_MAX_NODES else 1
            cands = _init_offsets(ranges, dim, offsets, gen, max_candidates=k)
    else:
        cands = [("given", _given_init(init, I, J, dim, offsets, scale))]

    if method == "rank3":
        name, (r0, s0, d0, o0) = cands[0]
        return _unrefined(M, ranges, r0, s0, d0, o0, offsets, spd, name)

    def refine(start: _Init, cov: bool = covariance, nfev: int | None = None) -> NlsSolution:
        r0, s0, d0, o0 = start
        return refine_toa(ranges, r0, s0, offsets=offsets, receiver_offsets0=d0, source_offsets0=o0,
                          loss=loss, f_scale=fs, max_nfev=nfev or max_nfev, covariance=cov)

    extra = 0
    if sum(n == "rank3" for n, _ in cands) > 1:
        cands, extra = _rank_starts(cands, refine)
    # first candidate that refines to a non-degenerate solution; the others are restarts
    best: NlsSolution | None = None
    err: DegenerateGeometryError | None = None
    rest = list(cands)
    name, start = rest[0]
    iters = starts = 0
    while rest and best is None:
        name, start = rest.pop(0)
        starts += 1
        try:
            best = refine(start)
        except DegenerateGeometryError as exc:  # diverged to a degenerate configuration
            err = exc
            if exc.kind == "unobservable-node" and method == "auto":
                best = _off_saddle(refine, ranges, start)
    if best is None:
        assert err is not None
        tried = ", ".join(n for n, _ in cands)
        raise DegenerateGeometryError(
            f"{err.args[0]} (reached from every start tried: {tried}; if the geometry is fine, "
            "the initialisation failed: pass init=(receivers, sources[, offsets]) or add measurements)",
            kind=err.kind,
        )
    iters = best.iterations
    robust = loss != "linear"
    if method == "auto" and _implausible(best, robust):
        more = [c for _, c in rest] + _restarts(ranges, dim, offsets, best, gen, start)
        first = best
        for start2 in more:
            starts += 1
            try:
                sol = refine(start2, cov=False)  # covariances only for the winner, below
            except DegenerateGeometryError:  # e.g. a degenerate random start
                continue
            iters += sol.iterations
            if sol.cost < best.cost:
                best = sol
            if not _implausible(best, robust):
                break
        if best is not first and covariance:
            best = refine((best.receivers, best.sources, best.receiver_offsets, best.source_offsets))
            iters += best.iterations
    exact = best.residual_rms <= 1e-9 * (1.0 + float(np.nanmax(np.abs(ranges))))
    if method == "auto" and not robust and sweep and not exact and I + J <= SWEEP_MAX_NODES:
        # cheap escapes from the local minima the residual tests above cannot see at the noise
        # level (nodes, or microphone-loudspeaker pairs, on the wrong side of a near-plane)
        first = best
        for _ in range(SWEEP_ROUNDS):
            moves = [m for m in (_node_sweep(ranges, best), _pair_flip(best, 1.0), _pair_flip(best, 0.5))
                     if m is not None]
            round_best = best
            for start3 in moves:
                starts += 1
                try:  # a short refinement ranks the moves; only the winner is finished below
                    sol = refine(start3, cov=False, nfev=SWEEP_NFEV)
                except DegenerateGeometryError:
                    continue
                iters += sol.iterations
                if sol.cost < round_best.cost:
                    round_best = sol
            if not round_best.cost < best.cost * (1 - 1e-6):
                break
            best = round_best
            if not best.converged:
                try:
                    best = refine((best.receivers, best.sources, best.receiver_offsets, best.source_offsets),
                                  cov=False)
                    iters += best.iterations
                except DegenerateGeometryError:
                    best = first
                    break
        if best is not first and dim == 3:
            # the landscape had a wrong basin; a (near-)planar network is the case where a 3-D
            # fit keeps finding better wrong basins while the truth is the plane
            planar = _planar_check(ranges, offsets, best, refine, gen)
            if planar is not None:
                best = planar
        if best is not first and covariance:
            best = refine((best.receivers, best.sources, best.receiver_offsets, best.source_offsets))
            iters += best.iterations
    label = f"{name}+nls" + (f"+multistart({starts - 1})" if starts > 1 else "")
    fit = test(best)
    if fit is not None and not fit.passed and method == "auto":
        found, n_deep = _deep_search(ranges, dim, offsets, best, refine, gen, test)
        starts += n_deep
        label += f"+deep({n_deep})"
        if found is not None:
            best = found
            if covariance:
                best = refine((best.receivers, best.sources, best.receiver_offsets, best.source_offsets))
            iters += best.iterations
            fit = test(best)
    return _to_result(M, best, spd, label, iters, starts + extra, fit)


def _rank_starts(cands: list[tuple[str, _Init]], refine: Any) -> tuple[list[tuple[str, _Init]], int]:
    """Order the rank-3 candidate starts by the fit of the full model after a short refinement.

    The rank-3 initialiser's own criterion, the Frobenius norm F (004 eq. 3.17), measures how
    close the offset-corrected matrix is to rank 3, not how well ``|r_i - s_j| + delta_i +
    tau_j`` fits; with few units a wrong basin can have the smallest F. Each candidate is
    refined for at most ``RANK_NFEV`` iterations without covariances and the candidates are
    sorted by the resulting cost (their refined states become the starts); candidates whose
    refinement fails keep their place after the others. Returns (ordered, refinements run).
    """
    scored: list[tuple[float, int, tuple[str, _Init]]] = []
    runs = 0
    for k, (name, start) in enumerate(cands):
        if name != "rank3":
            scored.append((float("inf"), k, (name, start)))
            continue
        runs += 1
        try:
            sol = refine(start, cov=False, nfev=RANK_NFEV)
        except DegenerateGeometryError:
            scored.append((float("inf"), k, (name, start)))
            continue
        cost = float(sol.cost) if np.isfinite(sol.cost) else float("inf")
        scored.append((cost, k, (name, (sol.receivers, sol.sources, sol.receiver_offsets, sol.source_offsets))))
    scored.sort(key=lambda c: (c[0], c[1]))
    return [c[2] for c in scored], max(runs - 1, 0)


def _deep_search(ranges: Array, dim: int, offsets: str, best: NlsSolution, refine: Any,
                 rng: np.random.Generator, test: Any) -> tuple[NlsSolution | None, int]:
    """More starts after a fit that failed the residual test; the best better fit or None.

    Starts: up to ``DEEP_CANDIDATES`` distinct rank-3 candidates from ``DEEP_STARTS`` random
    initialisations (offsets) or the 003 initialisers (no offsets), plus MDS on the shifted
    ranges with fresh random draws. Each is refined without covariances and then given the
    node sweeps (:func:`_node_sweep`); the search stops at the first fit that passes the
    residual test. Returns (solution with a lower cost than ``best`` or None, starts tried).
    """
    from . import mds
    from . import offsets as off

    I, J = ranges.shape
    starts: list[_Init] = []
    if offsets != "none":
        try:
            for r, s, d0, o0 in off.initialize_offsets_candidates(ranges, dim, rng=rng, n_starts=DEEP_STARTS,
                                                                  max_candidates=DEEP_CANDIDATES):
                starts.append(_kept_offsets(r, s, d0, o0, offsets))
        except (DegenerateGeometryError, InputError):
            pass
    shift = min(0.0, float(np.nanmin(ranges)))
    has_r, has_s = offsets in ("receivers", "both"), offsets in ("sources", "both")
    for m in ("auto", "rank", "mds-multilat", "alg2"):
        try:
            r, s = mds.initialize_toa(ranges - shift, dim, method=m, rng=rng)
        except Exception:  # an initialiser that does not apply at this size is simply skipped
            continue
        starts.append((np.asarray(r, float), np.asarray(s, float),
                       np.zeros(I) if has_r else None, np.zeros(J) if has_s else None))
    found: NlsSolution | None = None
    tried = 0
    for start in starts:
        if not _sane(start, ranges):
            continue
        tried += 1
        try:
            sol = refine(start, cov=False)
            moved = _node_sweep(ranges, sol) if I + J <= SWEEP_MAX_NODES else None
            if moved is not None:
                sol2 = refine(moved, cov=False)
                sol = sol2 if sol2.cost < sol.cost else sol
        except DegenerateGeometryError:
            continue
        if sol.cost < (best if found is None else found).cost * (1 - 1e-9):
            found = sol
            fit = test(found)
            if fit is not None and fit.passed:
                break
    return found, tried


def _restarts(ranges: Array, dim: int, offsets: str, sol: NlsSolution, rng: np.random.Generator,
              first: _Init) -> list[_Init]:
    """Further starts: the other 003 initialisers (plain TOA), then the worst nodes re-drawn.

    The re-drawn start keeps the refined solution but moves the nodes with the
    largest residuals to their mirror image across the centroid of the others (the
    typical wrong basin of range-only calibration) or to a random spot in the scene.
    """
    out: list[_Init] = []
    if offsets == "none":
        from . import mds

        for m in ("rank", "mds-multilat", "alg2"):
            try:
                r, s = mds.initialize_toa(ranges, dim, method=m, rng=rng)
            except Exception:  # an initialiser that does not apply at this size is simply skipped
                continue
            out.append((np.asarray(r, float), np.asarray(s, float), None, None))
    R = sol.residuals
    r, s = sol.receivers.copy(), sol.sources.copy()
    span = float(np.ptp(np.vstack([r, s]), axis=0).max()) or 1.0
    node_r = np.sqrt(np.nanmean(R**2, axis=1))
    node_s = np.sqrt(np.nanmean(R**2, axis=0))
    for attempt in range(2):
        r2, s2 = r.copy(), s.copy()
        for pts, score in ((r2, node_r), (s2, node_s)):
            bad = score > 3.0 * np.median(np.concatenate([node_r, node_s]))
            c = pts[~bad].mean(axis=0) if (~bad).any() else pts.mean(axis=0)
            if attempt == 0:
                pts[bad] = 2 * c - pts[bad]
            else:
                pts[bad] = c + rng.uniform(-0.5, 0.5, (int(bad.sum()), dim)) * span
        out.append((r2, s2, sol.receiver_offsets, sol.source_offsets))
    return out


#: node sweeps (see :func:`_node_sweep`) run by default up to this many receivers + sources
SWEEP_MAX_NODES = 300
#: rounds of node sweeps + collective pair flips (each round refines up to 3 starts)
SWEEP_ROUNDS = 1
#: iteration cap of the short refinements that rank the sweep moves
SWEEP_NFEV = 25


def _fit_node(anchors: Array, y: Array, x: Array, b: float | None, iterations: int = 8) -> tuple[Array, float | None, float]:
    """One node against fixed others: Gauss-Newton on ``y_k = |x - a_k| (+ b)``, returns (x, b, SSR).

    ``anchors`` (n, d) the other kind's positions, ``y`` (n,) the ranges with the anchors'
    offsets removed, ``b`` the node's own offset (None: the node has none). A handful of
    undamped steps with step halving: the problem has d(+1) unknowns.
    """
    def ssr(xv: Array, bv: float | None) -> float:
        e = y - np.linalg.norm(xv - anchors, axis=1) - (bv or 0.0)
        return float(e @ e)

    cost = ssr(x, b)
    for _ in range(iterations):
        diff = x - anchors
        dist = np.maximum(np.linalg.norm(diff, axis=1), 1e-12)
        e = y - dist - (b or 0.0)
        Jm = diff / dist[:, None]
        if b is not None:
            Jm = np.column_stack([Jm, np.ones(len(y))])
        JtJ = Jm.T @ Jm
        try:  # normal equations of a 3-4 unknown problem, a tiny ridge against a flat direction
            step = np.linalg.solve(JtJ + 1e-12 * np.trace(JtJ) * np.eye(JtJ.shape[0]), Jm.T @ e)
        except np.linalg.LinAlgError:
            break
        t = 1.0
        while t > 1e-4:
            x2 = x + t * step[: x.size]
            b2 = None if b is None else b + t * float(step[-1])
            c2 = ssr(x2, b2)
            if c2 < cost:
                break
            t *= 0.5
        else:
            break
        done = cost - c2 <= 1e-12 * (cost + 1e-30)
        x, b, cost = x2, b2, c2
        if done:
            break
    return x, b, cost


def _node_sweep(ranges: Array, sol: NlsSolution) -> _Init | None:
    """Re-place every node with the others fixed; the start for a refinement when a node moved.

    A local minimum of range-only calibration typically has a node (or a microphone and
    its nearby loudspeaker) on the wrong side of the plane the other nodes nearly span:
    the reflection changes most ranges little, so the full NLS does not cross back.
    With the others fixed, a single node has only d(+1) unknowns; we try its reflection
    through the least-squares plane of all the other nodes, and (with an offset) the
    closed-form position of :func:`selfcal.toa.offsets._locate_with_offset`, polish each by
    Gauss-Newton (:func:`_fit_node`) and move the node when its own residual sum of
    squares drops by more than 1 %. Returns the moved start or None if nothing moved.
    """
    from .offsets import _locate_with_offset

    obs = np.isfinite(ranges)
    r, s = sol.receivers.copy(), sol.sources.copy()
    d = None if sol.receiver_offsets is None else sol.receiver_offsets.copy()
    o = None if sol.source_offsets is None else sol.source_offsets.copy()
    moved = False
    for side in (0, 1):
        pts, other = (r, s) if side == 0 else (s, r)
        own, oth = (d, o) if side == 0 else (o, d)
        Y = ranges if side == 0 else ranges.T
        ob = obs if side == 0 else obs.T
        allpts = np.vstack([r, s])
        for k in range(pts.shape[0]):
            use = ob[k]
            if use.sum() < pts.shape[1] + 2:
                continue
            anchors = other[use]
            y = Y[k, use] - (0.0 if oth is None else oth[use])
            b0 = None if own is None else float(own[k])
            _, _, c0 = _fit_node(anchors, y, pts[k], b0, iterations=0)
            rest = np.delete(allpts, k + (0 if side == 0 else r.shape[0]), axis=0)
            c = rest.mean(axis=0)
            normal = np.linalg.svd(rest - c, full_matrices=False)[2][-1]
            cands = [pts[k] - 2 * ((pts[k] - c) @ normal) * normal]
            # a node in the plane of coplanar partners sits on a saddle (its out-of-plane
            # gradient vanishes by symmetry, its Fisher block is singular): push it off the
            # plane by a tenth of its typical range; the side is the mirror ambiguity
            ca = anchors.mean(axis=0)
            sv, vt = np.linalg.svd(anchors - ca, full_matrices=False)[1:]
            if sv[-1] <= 1e-6 * sv[0] and abs((pts[k] - ca) @ vt[-1]) <= 1e-6 * sv[0]:
                push = 0.1 * float(np.median(np.linalg.norm(anchors - pts[k], axis=1)))
                cands += [pts[k] + push * vt[-1], pts[k] - push * vt[-1]]
            if b0 is not None:
                got = _locate_with_offset(anchors, y)
                if got is not None:
                    cands.append(got[0])
            best = (c0, pts[k], b0)
            for x0 in cands:
                bx = None if b0 is None else float(np.mean(y - np.linalg.norm(x0 - anchors, axis=1)))
                x1, b1, c1 = _fit_node(anchors, y, x0, bx)
                if c1 < best[0]:
                    best = (c1, x1, b1)
            if best[0] < 0.99 * c0:
                pts[k] = best[1]
                if own is not None and best[2] is not None:
                    own[k] = best[2]
                moved = True
    moved = _pair_sweep(ranges, r, s, d, o) or moved
    return (r, s, d, o) if moved else None


def _pair_sweep(ranges: Array, r: Array, s: Array, d: Array | None, o: Array | None) -> bool:
    """Flip close receiver-source pairs through their local plane (in place); True if any moved.

    The local minimum of 004-type units on tiered rows: a microphone and its loudspeaker a
    few cm apart swap sides of the row plane together (the microphone below, the
    loudspeaker above), which no single-node move undoes. For each receiver and its nearest
    source we reflect both through the plane through their midpoint whose normal is that of
    the nearest other nodes, polish the two alternately with the others fixed and keep the
    move when the pair's residual sum of squares drops by more than 1 %.
    """
    obs = np.isfinite(ranges)
    dim = r.shape[1]
    I, J = ranges.shape
    moved = False

    def pair_cost(i: int, j: int, ri: Array, sj: Array, di: float | None, oj: float | None) -> float:
        rr, ss = r.copy(), s.copy()
        rr[i], ss[j] = ri, sj
        dd = None if d is None else d.copy()
        oo = None if o is None else o.copy()
        if dd is not None and di is not None:
            dd[i] = di
        if oo is not None and oj is not None:
            oo[j] = oj
        row = ranges[i] - np.linalg.norm(ss - ri, axis=1) - (0.0 if dd is None else dd[i]) - (0.0 if oo is None else oo)
        col = ranges[:, j] - np.linalg.norm(rr - sj, axis=1) - (0.0 if dd is None else dd) - (0.0 if oo is None else oo[j])
        row, col = row[obs[i]], col[obs[:, j]]
        return float(row @ row + col @ col)

    for i in range(I):
        j = int(np.argmin(np.linalg.norm(s - r[i], axis=1)))
        if obs[i].sum() < dim + 2 or obs[:, j].sum() < dim + 2:
            continue
        di = None if d is None else float(d[i])
        oj = None if o is None else float(o[j])
        c0 = pair_cost(i, j, r[i], s[j], di, oj)
        allpts = np.vstack([np.delete(r, i, axis=0), np.delete(s, j, axis=0)])
        mid = 0.5 * (r[i] + s[j])
        near = allpts[np.argsort(np.linalg.norm(allpts - mid, axis=1))[: 2 * dim + 2]]
        normal = np.linalg.svd(near - near.mean(axis=0), full_matrices=False)[2][-1]
        ri = r[i] - 2 * ((r[i] - mid) @ normal) * normal
        sj = s[j] - 2 * ((s[j] - mid) @ normal) * normal
        for _ in range(2):
            u = obs[i]
            y = ranges[i, u] - (0.0 if o is None else o[u])
            ss = s.copy()
            ss[j] = sj
            if o is not None and oj is not None:
                y = ranges[i, u] - np.where(np.arange(J)[u] == j, oj, o[u])
            ri, di, _ = _fit_node(ss[u], y, ri, di)
            u = obs[:, j]
            rr = r.copy()
            rr[i] = ri
            dd = None if d is None else d.copy()
            if dd is not None and di is not None:
                dd[i] = di
            y = ranges[u, j] - (0.0 if dd is None else dd[u])
            sj, oj, _ = _fit_node(rr[u], y, sj, oj)
        c1 = pair_cost(i, j, ri, sj, di, oj)
        if c1 < 0.99 * c0:
            r[i], s[j] = ri, sj
            if d is not None and di is not None:
                d[i] = di
            if o is not None and oj is not None:
                o[j] = oj
            moved = True
    return moved


def _off_saddle(refine: Any, ranges: Array, start: _Init) -> NlsSolution | None:
    """Second chance after an ``unobservable-node`` verdict of the covariance step.

    The verdict is correct for the point reached (scale-free: the node's Fisher block has
    a relative condition number above 1e12, i.e. a direction 1e6 times less determined than
    the best one), but that point can be a saddle rather than the solution: a microphone
    that ends exactly in the plane of coplanar loudspeakers has a zero out-of-plane
    gradient, so the iteration cannot leave the plane. Refine without covariances, move
    such nodes off their partners' plane (:func:`_node_sweep`) and refine again; None
    when that does not help (the caller then reports the original verdict).
    """
    try:
        sol = refine(start, cov=False)
        moved = _node_sweep(ranges, sol)
        if moved is None:
            return None
        out: NlsSolution = refine(moved)
        return out
    except DegenerateGeometryError:
        return None


def _planar_check(ranges: Array, offsets: str, sol: NlsSolution, refine: Any,
                  rng: np.random.Generator) -> NlsSolution | None:
    """Compare a 3-D solution with the best planar one; raise if the data say "planar".

    The 3-D model contains every planar network, so a 2-D fit with a lower cost proves the
    3-D solution is a local minimum. Refined in 3-D from the planar embedding (z = 0), the
    result either leaves the plane (returned: a better 3-D solution) or the covariance
    step finds the out-of-plane coordinates unobservable: the data are those of a planar
    layout, and the honest answer is that verdict, not a confident wrong z (issue 7).
    """
    try:
        flat = solve_toa(ranges, dim=2, offsets=offsets, rng=rng, covariance=False, method="nls")
    except DegenerateGeometryError:
        return None
    if not flat.residual_rms < sol.residual_rms:
        return None

    def lift(a: Array) -> Array:
        return np.column_stack([a, np.zeros(a.shape[0])])

    start = (lift(flat.receivers), lift(flat.sources), flat.receiver_offsets, flat.source_offsets)
    try:
        out: NlsSolution = refine(start)
    except DegenerateGeometryError as exc:
        raise DegenerateGeometryError(
            f"a planar network fits the data better (residual {flat.residual_rms:.3g} vs "
            f"{sol.residual_rms:.3g} in 3-D, matrix units x speed) and its out-of-plane "
            f"coordinates are not determined ({exc.args[0]}): the layout is (near-)planar; "
            "use dim=2 or give known heights",
            kind=exc.kind,
        ) from None
    return out if out.cost < sol.cost else None


def _pair_flip(sol: NlsSolution, fraction: float) -> _Init | None:
    """Every receiver and its nearest source reflected together through their local plane.

    The collective version of :func:`_pair_sweep`: on tiered conference rows many units'
    microphone-loudspeaker vectors end up mirrored at once (microphones low, loudspeakers
    high, a few cm each). ``fraction`` 1 reflects, 0.5 moves both onto the plane (a neutral
    start between the two basins). The local plane's normal is that of the 2d+2 nearest
    other nodes. None when there are fewer receivers than 2 d + 4 (no local plane).
    """
    r, s = sol.receivers.copy(), sol.sources.copy()
    dim = r.shape[1]
    if r.shape[0] + s.shape[0] < 2 * dim + 4:
        return None
    allpts = np.vstack([r, s])
    I = r.shape[0]
    for i in range(I):
        j = int(np.argmin(np.linalg.norm(sol.sources - sol.receivers[i], axis=1)))
        mid = 0.5 * (sol.receivers[i] + sol.sources[j])
        others = np.delete(allpts, [i, I + j], axis=0)
        near = others[np.argsort(np.linalg.norm(others - mid, axis=1))[: 2 * dim + 2]]
        n = np.linalg.svd(near - near.mean(axis=0), full_matrices=False)[2][-1]
        r[i] = sol.receivers[i] - 2 * fraction * ((sol.receivers[i] - mid) @ n) * n
        s[j] = sol.sources[j] - 2 * fraction * ((sol.sources[j] - mid) @ n) * n
    return r, s, sol.receiver_offsets, sol.source_offsets


def _to_result(M: Array, sol: NlsSolution, speed: float | None, method: str, iters: int, starts: int,
               fit: ResidualTest | None = None) -> ToaResult:
    k = 1.0 / speed if speed is not None else 1.0

    def sc(a: Array | None) -> Array | None:
        return None if a is None else np.asarray(a) * k

    return ToaResult(
        receivers=sol.receivers,
        sources=sol.sources,
        receiver_offsets=sc(sol.receiver_offsets),
        source_offsets=sc(sol.source_offsets),
        receiver_cov=sol.receiver_cov,
        source_cov=sol.source_cov,
        residual_rms=sol.residual_rms * k,
        sigma=sol.sigma * k,
        converged=sol.converged,
        iterations=iters,
        method=method,
        n_missing=int((~np.isfinite(M)).sum()),
        n_starts=starts,
        receiver_offset_std=sc(sol.receiver_offset_std),
        source_offset_std=sc(sol.source_offset_std),
        speed=speed,
        residuals=sol.residuals * k,
        fit=fit,
    )


def _unrefined(M: Array, ranges: Array, r: Array, s: Array, d: Array | None, o: Array | None,
               offsets: str, speed: float | None, method: str) -> ToaResult:
    """Package an initialiser's estimate (no NLS): canonical gauge, residuals, NaN covariances."""
    from ..geometry import canonical_gauge

    r = np.asarray(r, float)
    s = np.asarray(s, float)
    res = np.where(np.isfinite(ranges), ranges - toa_model(r, s, d, o), np.nan)
    f = res[np.isfinite(res)]
    rc, scn, _ = canonical_gauge(r, s)
    assert scn is not None
    I, dim = r.shape
    k = 1.0 / speed if speed is not None else 1.0
    if offsets == "both" and d is not None and o is not None:
        d, o = d + o[0], o - o[0]
    return ToaResult(
        receivers=rc,
        sources=scn,
        receiver_offsets=None if d is None else np.asarray(d) * k,
        source_offsets=None if o is None else np.asarray(o) * k,
        receiver_cov=np.full((I, dim, dim), np.nan),
        source_cov=np.full((s.shape[0], dim, dim), np.nan),
        residual_rms=float(np.sqrt(np.mean(f**2))) * k,
        sigma=float("nan"),
        converged=True,
        iterations=0,
        method=method,
        n_missing=int((~np.isfinite(M)).sum()),
        speed=speed,
        residuals=res * k,
    )
