"""The far-field solve without the gross-error screen: the body of :func:`~selfcal.tdoa.solve_farfield`.

:func:`solve_unscreened` runs steps 2-4 of :mod:`selfcal.tdoa.farfield` (failure-mode
analysis, initialisation, refinement) after an optional screen given as a callable. It lives
below the screen because the screen's deletion test (:mod:`selfcal.tdoa.deletion`) re-solves
sub-matrices with it: :func:`~selfcal.tdoa.solve_farfield` passes
:func:`~selfcal.tdoa.screen.gross_error_screen` in, the deletion test passes nothing, and no
module imports one that imports it back.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable
from dataclasses import replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .._checks import as_matrix, as_rng, check_choice, check_positive, entry
from ..errors import ConvergenceWarning, DegenerateGeometryError, InputError
from ..robust import TUNING
from .covariance import DIRECTION_COV_MAX, direction_covariance
from .degeneracy import (
    DETERMINED,
    MESSAGES,
    RANK_ALPHA,
    analyse_degeneracy,
    partial_collinear_motion,
    partial_coplanar_directions,
    partial_parallel_directions,
    partial_planar_motion,
)
from .initialize import _canonical, initialize_farfield, reduce_matrix
from .lowdim import _effective_dim, _solve_low_dim
from .minimal import solve_minimal
from .orientation import check_orientation
from .refine import LOSSES, farfield_residuals, refine_alternating, refine_lm
from .result import FarfieldResult
from .semiblind import _solve_known_directions
from .structure import _robust_sigma, lowrank_fit, ransac_farfield

__all__ = ["METHODS", "COLLAPSE_RATIO", "dimension_rule", "solve_unscreened"]

Array = NDArray[np.float64]
METHODS = ("auto", "lm", "alternating", "init", "minimal")
#: Flag a refined solution whose directions are nearly coplanar (smallest / largest singular
#: value of the (k, 3) direction matrix below this). At high noise (sigma about a third of the array size) the
#: ML cost itself has such minima: the out-of-plane scale of the positions is then barely
#: determined and the array comes out stretched (see the audit note in :mod:`.refine`).
COLLAPSE_RATIO = 0.2


# ----------------------------------------------------------------------------- entry point
#: robust-loss scale in units of the noise standard deviation (95 % Gaussian efficiency)
_TUNING = TUNING


def _raise_or_return(
    kind: str, message: str, result: FarfieldResult, allow_degenerate: bool
) -> FarfieldResult:
    if allow_degenerate:
        return result
    raise DegenerateGeometryError(
        message + " Pass allow_degenerate=True (CLI: --allow-degenerate) for the partial reconstruction.",
        kind=kind,
        partial=result,
    )


@entry(matrix="array", f_scale="positive?", noise_std="positive?", max_iter="count?", tol="positive?",
       rng="rng", reject_k="positive", cone_tol="positive", allow_degenerate="bool",
       check_degeneracy="bool", ransac="bool")
def solve_unscreened(
    matrix: Any,
    *,
    method: str = "auto",
    loss: str = "linear",
    f_scale: float | None = None,
    noise_std: float | None = None,
    offsets: str = "auto",
    direction_solver: str = "global",
    allow_degenerate: bool = False,
    reject_k: float = 4.0,
    max_iter: int | None = None,
    tol: float | None = None,
    cone_tol: float = 3.0,
    init_reference: str = "mean",
    check_degeneracy: bool = True,
    ransac: bool = False,
    rng: np.random.Generator | int | None = None,
    dim: int | str = 3,
    directions: Any = None,
    gross_screen: Callable[[Array], Any] | None = None,
) -> FarfieldResult:
    """:func:`~selfcal.tdoa.solve_farfield` with the screen passed in (None: no screen).

    Parameters
    ----------
    matrix, method, loss, f_scale, noise_std, offsets, direction_solver, allow_degenerate,
    reject_k, max_iter, tol, cone_tol, init_reference, check_degeneracy, ransac, rng, dim,
    directions : as :func:`~selfcal.tdoa.solve_farfield`.
    gross_screen : ``D -> GrossScreen`` (:func:`~selfcal.tdoa.screen.gross_error_screen`), run
        on the validated matrix; None skips the screen (``screen=False``).

    Returns
    -------
    FarfieldResult
        As :func:`~selfcal.tdoa.solve_farfield`.

    Examples
    --------
    >>> import numpy as np
    >>> rng = np.random.default_rng(4)
    >>> Z, N = rng.normal(size=(8, 3)), rng.normal(size=(12, 3))
    >>> N /= np.linalg.norm(N, axis=1, keepdims=True)
    >>> res = solve_unscreened(Z @ N.T + rng.normal(size=12), method="lm", offsets="free")
    >>> res.success, res.screen_rule
    (True, 'none (screen=False)')
    """
    check_choice(method, "method", METHODS)
    if dim not in (1, 2, 3, "auto"):
        raise InputError(f"dim must be 1, 2, 3 or 'auto', got {dim!r}")
    if method == "minimal" and dim != 3:
        raise InputError("method='minimal' (Algorithm 1) is the 3-D 4 x 6 solver; use dim=3")
    check_choice(loss, "loss", LOSSES)
    check_choice(offsets, "offsets", ("auto", "reference", "free"))
    check_choice(direction_solver, "direction_solver", ("global", "local"))
    check_choice(init_reference, "init_reference", ("mean", "first"))
    check_positive(f_scale, "f_scale")
    if noise_std is not None and not (np.isfinite(noise_std) and noise_std >= 0):
        raise InputError(f"noise_std must be a finite non-negative number, got {noise_std!r}")
    gen = as_rng(rng)
    D = as_matrix(matrix, "matrix", allow_nan=True, min_shape=(1, 1), huge="entry")
    m, k = D.shape
    if m < 3:
        raise DegenerateGeometryError(
            f"{m} receiver positions: at least 4 are needed for 3-D far-field calibration (3 for a "
            "planar partial solution)", kind="too-few-receivers")
    if k < 3:
        raise DegenerateGeometryError(
            f"{k} transmitters: at least 6 are needed for 3-D far-field calibration (3 for a partial "
            "solution)", kind="too-few-sources")
    finite = np.isfinite(D)
    if (finite.sum(axis=0) < 2).any():
        j = int(np.flatnonzero(finite.sum(axis=0) < 2)[0])
        raise InputError(f"matrix: column {j} has fewer than 2 observed entries; it carries no information")
    if (finite.sum(axis=1) < 3).any():
        i = int(np.flatnonzero(finite.sum(axis=1) < 3)[0])
        raise InputError(f"matrix: row {i} has fewer than 3 observed entries; its position is undetermined")

    if method == "minimal" and ((m, k) != (4, 6) or not finite.all()):
        raise InputError(f"method='minimal' needs a complete 4 x 6 matrix, got {m} x {k}")
    check_orientation(D, noise_std=noise_std, rank=3)
    dim_rule = dimension_rule(dim)
    scr = gross_screen(D) if gross_screen is not None else None
    gross = scr.mask if scr is not None else np.zeros_like(finite)
    untestable = int(scr.untestable.sum()) if scr is not None else 0
    screen_note = (scr.message,) if scr is not None and scr.message else ()
    screen_rule = scr.rule if scr is not None else "none (screen=False)"
    if ransac:
        gross = gross | (finite & ~ransac_farfield(np.where(gross, np.nan, D), rng=gen))
    used = finite & ~gross
    complete = bool(used.all())
    if directions is not None:
        res0 = _solve_known_directions(D, used, gross, directions, loss=loss)
        return replace(res0, untestable=untestable, warnings=screen_note + res0.warnings, dim_rule=dim_rule,
                       screen_rule=screen_rule)
    if offsets == "auto":
        # always the maximum-likelihood offsets: the paper's reference offsets (C_j = D_1j) carry
        # row 1's noise into every row, so that estimator is less accurate, its residuals are
        # correlated and switching to it only when the screen flags nothing made the estimator (and
        # the covariance: positions 1.8x, directions 1.3x too small in variance) depend on the screen
        offsets = "free"
    if offsets == "reference" and not np.all(used[0]):
        raise InputError("offsets='reference' needs a complete first row; use offsets='free'")

    # ---- a complete, clean reduced matrix for analysis and initialisation
    sigma_entries = noise_std
    if complete and loss == "linear":
        Dfill = D
    else:
        fit_loss = "huber" if loss != "linear" else "linear"
        Dfill, sig = lowrank_fit(D, used.astype(float), rank=dim if isinstance(dim, int) else 3, loss=fit_loss)
        if sigma_entries is None:
            sigma_entries = sig
        if dim == "auto" or dim == 2:
            # a rank-r completion puts spurious components into the missing entries;
            # complete at rank 1, then 2, and keep the first whose next singular value is noise
            # (a real higher component stays visible in the observed entries); sigma from the
            # largest (rank-3) fit, unbiased whatever the true rank
            for rank_r in range(1, 3 if dim == "auto" else 2):
                Lr, _ = lowrank_fit(D, used.astype(float), rank=rank_r, loss=fit_loss)
                # the observed entries carry the rank (a robust fit's own rank-r matrix always passes
                # its rank-r test: with Lr here dim=2 and a robust loss refused every planar matrix)
                Fr = np.where(used, D, Lr)
                if analyse_degeneracy(Fr - Fr.mean(axis=0), noise_std=sigma_entries,
                                      cone_tol=cone_tol).rank <= rank_r:
                    Dfill = Lr
                    break
    if loss == "linear":
        Dfill = np.where(used, D, Dfill)  # only the gaps are filled
    if init_reference == "first":
        X = np.vstack([np.zeros((1, k)), reduce_matrix(Dfill)])  # the paper's K_j = D_1j
    else:
        X = Dfill - Dfill.mean(axis=0, keepdims=True)  # K_j = column mean (Lemma 1)
    C0 = D[0].copy() if offsets == "reference" else Dfill[0].copy()
    report = analyse_degeneracy(X, noise_std=sigma_entries, cone_tol=cone_tol)

    def _offsets(pos: Array, dirs: Array) -> Array:
        if offsets == "reference":
            return D[0].copy()
        return np.asarray(np.nanmean(np.where(used, D - pos @ dirs.T, np.nan), axis=0))

    def _result(pos: Array, dirs: Array, C: Array, *, kind: str | None, conv: bool, its: int,
                meth: str, rej: NDArray[np.bool_], pd: bool, hist: list[float],
                cov: Array | None = None) -> FarfieldResult:
        pos, dirs, R = _canonical(pos, dirs)
        if cov is not None:
            cov = np.einsum("ab,ibc,dc->iad", R, cov, R)
        r = farfield_residuals(np.where(used & ~rej, D, np.nan), pos, dirs, C)
        rms = float(np.sqrt(np.nanmean(r**2))) if np.isfinite(r).any() else float("nan")
        dcov = None
        if cov is not None and kind is None and dirs.shape[1] in (2, 3) and \
                dirs.shape[1] * (len(pos) - 1) <= DIRECTION_COV_MAX:
            Wd = (used & ~rej).astype(float)
            Cf = np.sum(Wd * np.where(Wd > 0, D - pos @ dirs.T, 0.0), axis=0) / np.maximum(Wd.sum(0), 1e-300)
            if offsets == "reference":  # the estimate with C_j = D_1j (sandwich for row 1's noise)
                dcov = direction_covariance(D, pos, dirs, D[0].copy(), Wd, free_offsets=False)
            else:
                dcov = direction_covariance(D, pos, dirs, Cf, Wd, free_offsets=True)
        return FarfieldResult(pos, dirs, C, kind, rms, conv, its, meth, loss, rej | gross, pd, report, hist,
                              cov, warnings=screen_note, untestable=untestable, dim_rule=dim_rule,
                              direction_cov=dcov, screen_rule=screen_rule)

    no_rej = np.zeros_like(finite)
    kind_found = report.kind if check_degeneracy else None
    dim_eff = _effective_dim(dim, report) if check_degeneracy or dim != 3 else 3
    if dim_eff in (1, 2):
        if dim_eff == 2 and (dim == 2 or report.kind == "coplanar-directions"):
            check_orientation(D, noise_std=noise_std, rank=2)
        low = _solve_low_dim(D, X, used, dim_eff, report, offsets=offsets, loss=loss, f_scale=f_scale,
                             method=method, max_iter=max_iter, tol=tol, cone_tol=cone_tol)
        res = _result(low["positions"], low["directions"], low["offsets"], kind=None, conv=low["converged"],
                      its=low["iterations"], meth=low["method"], rej=no_rej, pd=low["pd"], hist=low["history"],
                      cov=low["cov"])
        return replace(res, dim=dim_eff, case=low["case"], determined=low["determined"])
    if check_degeneracy and report.rank < 3:
        kind = report.kind or "collinear-motion"
        partial_fn = {
            "planar-motion": partial_planar_motion,
            "coplanar-directions": partial_coplanar_directions,
            "collinear-motion": partial_collinear_motion,
            "parallel-directions": partial_parallel_directions,
        }[kind]
        pos, dirs = partial_fn(X)
        pos = pos - pos[0]
        hint = {"planar-motion": "", "coplanar-directions": " (dim=2 / --dim 2 gives the in-plane geometry)",
                "collinear-motion": " (dim=1 / --dim 1 gives the positions along the line, up to scale)",
                "parallel-directions": " (dim=1 / --dim 1 gives the coordinate along the direction)"}[kind]
        part = _result(pos, dirs, _offsets(pos, dirs), kind=kind, conv=False, its=0, meth=f"partial-{kind}",
                       rej=no_rej, pd=False, hist=[])
        sv = ", ".join(f"{v:.3g}" for v in report.singular_values[:4])
        detail = (f" (numerical rank {report.rank}: singular values {sv} against the noise-aware "
                  f"threshold {report.rank_threshold:.3g})")
        part = replace(part, case=kind, dim=3, determined=DETERMINED[kind])
        return _raise_or_return(kind, MESSAGES[kind] + detail + hint, part, allow_degenerate)
    if m < 4:
        raise DegenerateGeometryError(
            f"{m} receiver positions span 3-D but at least 4 are needed (Theorem 1)", kind="too-few-receivers")
    if k < 6:
        raise DegenerateGeometryError(
            f"{k} transmitters: at least 6 are needed to determine B (Theorem 1)", kind="too-few-sources")

    if method == "auto":
        method = "minimal" if (m, k) == (4, 6) and complete and loss == "linear" else "lm"
    if method == "minimal":
        if (m, k) != (4, 6) or not complete:
            raise InputError(f"method='minimal' needs a complete 4 x 6 matrix, got {m} x {k}")
        sol = solve_minimal(D)
        if kind_found == "cone":
            part = _result(np.nan_to_num(sol.positions), np.nan_to_num(sol.directions), C0, kind="cone",
                           conv=False, its=0, meth="minimal", rej=no_rej, pd=bool(sol.valid), hist=[])
            return _raise_or_return("cone", MESSAGES["cone"], part, allow_degenerate)
        if sol.valid:
            return _result(sol.positions, sol.directions, C0, kind=None, conv=True, its=0,
                           meth="minimal", rej=no_rej, pd=True, hist=[])
        method = "init"  # B not positive definite: the nonlinear fit of A (section 2.3)

    if not np.isfinite(X).all():  # never hand LAPACK a non-finite matrix (its DLASCL noise on stderr)
        raise InputError("matrix: the completed matrix is not finite; check for huge or missing entries")
    init = initialize_farfield(X)
    if not (np.isfinite(init.positions).all() and np.isfinite(init.directions).all()):
        raise DegenerateGeometryError(
            "the initialisation gave non-finite positions (B and its nonlinear fit are singular): the "
            "geometry is numerically degenerate", kind="no-solution")
    Z, N = init.positions - init.positions[0], init.directions
    C = _offsets(Z, N)
    if kind_found == "cone":
        # B is not determined: refining one arbitrary member of the family is wasted work
        part = _result(Z, N, C, kind="cone", conv=False, its=0, meth="init", rej=no_rej,
                       pd=init.b_positive_definite, hist=[])
        return _raise_or_return("cone", MESSAGES["cone"] + f" (cone SNR {report.cone_snr:.3g} < "
                                f"{cone_tol:g})", part, allow_degenerate)
    hist: list[float] = []
    cov: Array | None = None
    its, conv = 0, True
    rej = no_rej
    if method in ("lm", "alternating"):
        rounds = 1 if loss == "linear" else 2
        for _ in range(rounds):
            delta = 1.0
            if loss != "linear":
                rob = _robust_sigma(D, Z, N, C, used)
                delta = f_scale if f_scale is not None else _TUNING[loss] * max(
                    rob, 1e-12 * (np.nanmax(np.abs(X)) + 1e-300))
            if method == "lm":
                out = refine_lm(D, Z, N, C, mask=used, free_offsets=offsets == "free", loss=loss, delta=delta,
                                max_iter=max_iter or 200, tol=tol or 1e-12)
            else:
                out = refine_alternating(D, Z, N, C, mask=used, free_offsets=offsets == "free", loss=loss,
                                         delta=delta, direction_solver=direction_solver,
                                         max_iter=max_iter or 2000, tol=tol or 1e-10)
            Z, N, C = out.positions, out.directions, out.offsets
            cov = out.position_cov
            hist += out.history
            its += out.iterations
            conv = out.converged
        if not conv and kind_found is None:
            warnings.warn(f"far-field {method} stopped after {its} iterations without converging",
                          ConvergenceWarning, stacklevel=2)
        if loss != "linear":
            r = farfield_residuals(np.where(used, D, np.nan), Z, N, C)
            rob = _robust_sigma(D, Z, N, C, used)
            with np.errstate(invalid="ignore"):
                rej = np.asarray(used & (np.abs(r) > reject_k * max(rob, 1e-300)))
    res = _result(Z, N, C, kind=kind_found, conv=conv, its=its, meth=method, rej=rej,
                  pd=init.b_positive_definite, hist=hist, cov=cov)
    res = replace(res, case="cone" if kind_found == "cone" else "spatial",
                  determined=DETERMINED["cone" if kind_found == "cone" else "spatial"])
    cautions = _collapse_warning(init.directions, res.directions)
    if method == "lm" and res.position_cov is None:
        cautions = cautions + ("position_cov not computed: both sides of the problem are large (the reduced "
                               "system exceeds selfcal.tdoa.refine.COV_DIRECT_MAX unknowns); call "
                               "refine.position_covariance for it",)
    if cautions:
        if cautions[0].startswith("directions-collapsed"):
            warnings.warn(cautions[0], ConvergenceWarning, stacklevel=2)
        res = replace(res, warnings=res.warnings + cautions)
    return res


def dimension_rule(dim: int | str) -> str:
    """How the dimension of a far-field solution is chosen, in words (``FarfieldResult.dim_rule``).

    Examples
    --------
    >>> dimension_rule(2)
    'given: dim=2 (no test)'
    """
    if dim != "auto":
        return f"given: dim={dim} (no test)"
    return (f"auto: nested rank tests of the column-centred matrix against the noise (rank r - 1 against r, "
            f"false-alarm rate {RANK_ALPHA:g} each, Tracy-Widom quantiles); rank 2 is solved as planar when "
            "its 2-D quadric is consistent, rank 1 as linear, else 3-D")


def _direction_spread(N: Array) -> float:
    sv = np.linalg.svd(np.asarray(N, dtype=float), compute_uv=False)
    return float(sv[-1] / max(sv[0], 1e-300))


def _collapse_warning(N_init: Array, N_final: Array) -> tuple[str, ...]:
    """``("directions-collapsed: ...",)`` when the refined directions are nearly coplanar
    (:data:`COLLAPSE_RATIO`), else ``()``; the initial ratio is quoted for context."""
    before, after = _direction_spread(N_init), _direction_spread(N_final)
    if after < COLLAPSE_RATIO:
        return (f"directions-collapsed: the refined directions are nearly coplanar (singular-value "
                f"ratio {after:.3g}, initialisation {before:.3g}); the out-of-plane scale of the "
                "positions is then poorly determined — typical of noise that is large against the "
                "array; treat the positions with caution or add transmitters",)
    return ()
