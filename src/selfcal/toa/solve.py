"""``solve_toa``: anchor-free TOA / range self-calibration end to end (papers 003, 004).

Validation (the options then travel as one :class:`selfcal.toa.options.ToaOptions`) ->
seconds to metres (``speed``) -> ``"auto"`` model choices
(:mod:`selfcal.toa.verdict.select`) -> canonical order of rows and columns -> gross entries
screened, unidentifiable nodes dropped (:mod:`selfcal.toa.verdict.robust`) -> the search
(:mod:`selfcal.toa.search`: initialisers, plane moves, the one engine
:func:`selfcal.toa.engine.nls.refine_toa`) -> outlier rule and refit without the outliers ->
covariances, trust test (:mod:`selfcal.toa.result`) -> :class:`ToaResult`.
"""

from __future__ import annotations

import warnings
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .._checks import (
    MAX_ABS_ENTRY,
    as_matrix,
    as_points,
    as_rng,
    check_choice,
    check_dim,
    check_positive,
    check_toa_counts,
    check_toa_observable,
    entry,
)
from ..errors import ConvergenceWarning, DegenerateGeometryError, InputError, Status
from .engine.covariance import normalize_covariance
from .engine.nls import LOSSES, OFFSET_MODES, toa_model
from .fit import Start, finish, n_negative
from .options import ToaOptions
from .result import ResidualTest, ToaResult, n_parameters, residual_test

Array = NDArray[np.float64]

__all__ = ["ResidualTest", "ToaResult", "n_parameters", "residual_test", "solve_toa"]

METHODS = ("auto", "nls", "rank3")


@entry(matrix="array", speed="positive?", rng="rng", f_scale="positive?", max_nfev="count?", noise="positive?",
       budget="count?", sweep="bool")
def solve_toa(
    matrix: Any,
    *,
    dim: int | str = 3,
    offsets: str = "none",
    speed: float | None = None,
    loss: str = "auto",
    init: Any = "auto",
    method: str = "auto",
    rng: np.random.Generator | int | None = None,
    f_scale: float | None = None,
    max_nfev: int | None = None,
    covariance: Any = True,
    sweep: bool = True,
    noise: float | None = None,
    budget: int | None = None,
) -> ToaResult:
    """Anchor-free self-calibration of receivers and sources from TOA / range measurements.

    Solves 003 eq. 2 (ML under Gaussian noise) for the model of entry (i, j)
    ``|r_i - s_j| + d_i + o_j`` (offsets per ``offsets``; 004 sec. 3) by the search of
    :func:`selfcal.toa.search.search`, robust to gross outliers by default.

    Parameters
    ----------
    matrix: (I, J) ranges in metres, or times in seconds when ``speed`` is given; rows =
        receivers, columns = sources, NaN = missing. Negative and zero entries are
        measurements (bias + noise near zero range): accepted, with a warning giving their count.
    dim: 2, 3 or "auto" (3-D unless a 2-D fit explains the data as well: F test and
        planarity, :func:`selfcal.toa.verdict.select.choose_dim`).
    offsets: "none" | "receivers" | "sources" | "both" | "auto" (choice by BIC,
        :func:`selfcal.toa.verdict.select.choose_offsets`).
    speed: propagation speed (m/s) converting seconds to metres; offsets, residuals and
        noise are then reported in seconds.
    loss: "auto" (default: the search uses the soft-L1 loss with its scale estimated from
        the data, outliers are flagged by the Bonferroni rule of
        :func:`selfcal.toa.verdict.robust.outlier_mask` and the final fit is the linear one without
        them), "linear" (plain ML on every entry; outliers flagged, not removed) or a robust
        loss "huber" | "soft_l1" | "cauchy" used throughout (outliers removed before the last fit).
    init: "auto" or an explicit start ``(receivers, sources[, receiver_offsets,
        source_offsets])`` (positions in metres, offsets in the matrix's units); with
        ``method="auto"`` it is the first start of the search.
    method: "auto" (the search), "nls" (one start, one refinement) or "rank3" (the 004
        initialiser only, offsets != "none").
    rng: seed / Generator for the randomised initialisers.
    f_scale: robust-loss scale in the matrix's units (default: estimated from the data).
    max_nfev: iteration cap of each full refinement.
    covariance: which per-point covariance blocks of the final fit to compute: True / "all",
        "receivers", "sources", False / "none", or indices ``{"receivers": idx, "sources": idx}``
        in the caller's numbering (:func:`selfcal.toa.engine.covariance.normalize_covariance`); the
        others are NaN.
    sweep: run the plane moves of the search (:mod:`selfcal.toa.moves`).
    noise: optional std of the measurement noise in the matrix's units. The result then
        carries ``fit``, the chi-square test of its residuals (rejected at p < 1e-3), which
        is also the search's stopping rule; without it, the geometry test
        (:func:`selfcal.toa.verdict.trust.geometry_test`: a permutation test against offsets alone
        plus a median leave-one-out check, ``geometry``) says whether the data fit a
        geometry at all.
    budget: maximal refinements of the search (default :func:`selfcal.toa.search.default_budget`).

    Returns
    -------
    ToaResult; ``success`` False (and a :class:`~selfcal.errors.ConvergenceWarning`) when
    the result fails its own test.

    Raises
    ------
    InputError: malformed matrix (shape, inf), bad options.
    DegenerateGeometryError: what is left after dropping nodes with too few ranges cannot
        determine the geometry.

    Notes
    -----
    The answer does not depend on how receivers and sources are numbered (the search runs
    on the matrix sorted by :func:`selfcal.toa.search.canonical_order`), on a rigid motion
    of the network, or on the units (seconds with ``speed`` give the metres' answer).

    Examples
    --------
    >>> import numpy as np
    >>> from selfcal.toa import solve_toa, toa_model
    >>> g = np.random.default_rng(0)
    >>> r, s = g.uniform(-5, 5, (8, 3)), g.uniform(-5, 5, (10, 3))
    >>> res = solve_toa(toa_model(r, s) + g.normal(0, 0.01, (8, 10)), rng=0)
    >>> res.success, res.receivers.shape
    (True, (8, 3))
    """
    check_choice(offsets, "offsets", OFFSET_MODES + ("auto",))
    check_choice(loss, "loss", LOSSES + ("auto",))
    check_choice(method, "method", METHODS)
    covariance = normalize_covariance(covariance)  # False when no block is asked for
    if dim != "auto":
        dim = check_dim(dim)  # type: ignore[arg-type]
    spd = check_positive(speed, "speed")
    sd = check_positive(noise, "noise")
    if sd is not None and sd > MAX_ABS_ENTRY:  # its square overflows every chi-square sum
        raise InputError(f"noise: {sd:.3g} is beyond {MAX_ABS_ENTRY:.2g}; give the noise std in the matrix's units")
    fs = check_positive(f_scale, "f_scale")
    M = as_matrix(matrix, "matrix")
    # the pattern alone, for the least demanding model tried: linear in the entries, before any work
    check_toa_observable(M, 2 if dim == "auto" else int(dim), "none" if offsets == "auto" else offsets)
    gen = as_rng(rng)
    if method == "rank3" and offsets == "none":
        raise InputError("method='rank3' estimates offsets: use offsets='both' (or 'receivers'/'sources'), "
                         "or method='nls'")
    n_neg = n_negative(M)
    if n_neg:
        warnings.warn(f"{n_neg} of the entries are zero or negative; they are kept as measurements "
                      "(bias + noise near zero range)", UserWarning, stacklevel=2)
    if not isinstance(init, str):
        if dim == "auto" or offsets == "auto":
            raise InputError("an explicit init needs an explicit dim and offsets")
        I, J = M.shape
        init = given_start(init, I, J, int(dim), offsets, spd or 1.0, as_points)
    elif init != "auto":
        raise InputError(f"init must be 'auto' or a tuple of arrays, got {init!r}")
    opts = ToaOptions(speed=spd, loss=loss, method=method, rng=gen, f_scale=fs, max_nfev=max_nfev,
                      covariance=covariance, sweep=sweep, noise=sd, budget=budget)
    if dim == "auto" or offsets == "auto":
        from .verdict.select import choose

        res = choose(M, dim, offsets, opts, solve=_solve_fixed)
    else:
        res = _solve_fixed(M, int(dim), offsets, opts, init=init)  # type: ignore[arg-type]
    if not res.success or res.undetermined_receivers.any() or res.undetermined_sources.any():
        # a success with undetermined nodes warns too: its message names them
        warnings.warn(f"solve_toa: {res.message}", ConvergenceWarning, stacklevel=2)
    return res


def _solve_fixed(M: np.ndarray, dim: int, offsets: str, opts: ToaOptions, *, init: Any = "auto") -> ToaResult:
    """One model (dim, offsets): counts, the rank-3 shortcut, else the robust search (:mod:`.fit`)."""
    I, J = M.shape
    check_toa_counts((I, J), int(np.isfinite(M).sum()), dim, offsets)
    if opts.method == "rank3":
        return unrefined(M, dim, offsets, opts.speed, opts.rng)
    from ..progress import stage

    with stage(f"solve {I}x{J} ({dim}-D, offsets {offsets}): search", unit="refinements"):
        return finish(M, dim, offsets, opts, init=init)


def given_start(init: Any, I: int, J: int, dim: int, offsets: str, scale: float, as_points: Any) -> Start:
    """Validate an explicit ``init=(receivers, sources[, receiver_offsets, source_offsets])`` (metres)."""
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
    has_r, has_s = offsets in ("receivers", "both"), offsets in ("sources", "both")
    if has_r and d0 is None:
        d0 = np.zeros(I)
    if has_s and o0 is None:
        o0 = np.zeros(J)
    return r, s, (d0 if has_r else None), (o0 if has_s else None)


def unrefined(M: Array, dim: int, offsets: str, speed: float | None, rng: np.random.Generator) -> ToaResult:
    """``method="rank3"``: the 004 initialiser's estimate without refinement (NaN covariances)."""
    from ..geometry import canonical_gauge
    from .search import INITIALISERS

    scale = speed if speed is not None else 1.0
    Y = M * scale
    starts = INITIALISERS["rank3"](Y, dim, offsets, rng)
    if not starts:
        raise DegenerateGeometryError("the rank-3 initialiser does not apply to this matrix "
                                      "(too few units for the rank-d conditions, 004 sec. 3)", kind="too-few-units")
    r, s, d, o = starts[0]
    res = np.where(np.isfinite(Y), Y - toa_model(r, s, d, o), np.nan)
    f = res[np.isfinite(res)]
    rc, scn, _ = canonical_gauge(r, s)
    assert scn is not None
    I, J = Y.shape
    k = 1.0 / scale
    if offsets == "both" and d is not None and o is not None:
        d, o = d + o[0], o - o[0]
    return ToaResult(
        receivers=rc, sources=scn,
        receiver_offsets=None if d is None else np.asarray(d) * k,
        source_offsets=None if o is None else np.asarray(o) * k,
        receiver_cov=np.full((I, dim, dim), np.nan), source_cov=np.full((J, dim, dim), np.nan),
        residual_rms=float(np.sqrt(np.mean(f**2))) * k, sigma=float("nan"), converged=True, iterations=0,
        method="rank3", n_missing=int((~np.isfinite(M)).sum()), speed=speed, residuals=res * k,
        verdict=int(Status.SUCCESS), verdict_message="the 004 initialiser alone (method='rank3'): not refined, not tested",
        outliers=np.zeros((I, J), bool), dim=dim, offsets=offsets,
        n_negative=n_negative(M))
