"""Far-field TDOA self-calibration (paper 000): the solver entry point.

``D_ij = z_i . n_j + C_j`` (rows = receiver positions, columns = far transmitters,
``|n_j| = 1``, C_j unknown per column). :func:`solve_farfield` recovers the positions (first
at the origin), the unit directions and the offsets:

1. gross-error screen (optional) and, when entries are missing or a robust loss is asked
   for, a weighted / robust fit of the structure ``D = P Q^T + 1 c^T`` (rank 3 plus
   offsets, :func:`lowrank_fit`) that fills (and, robustly, cleans) the matrix for the
   factorisation steps;
2. failure-mode analysis of ``Dbar`` (:mod:`selfcal.tdoa.degeneracy`);
3. overdetermined initialisation (section 2.3 (i)-(iii), :func:`initialize_farfield`),
   with the nonlinear fit of A when the least-squares B is not positive definite;
4. refinement: Levenberg-Marquardt on the spheres (Algorithm 3) or alternating
   optimisation (Algorithm 2), with an optional robust loss.

Robustness (beyond the paper, its future work): with ``loss != "linear"`` the structured fit
and the refinement are iteratively re-weighted; entries whose final residual exceeds
``reject_k`` robust standard deviations are reported in ``rejected``. :func:`ransac_farfield`
additionally offers RANSAC over the minimal solver.

The pieces live one job per module: :mod:`.screen` (gross errors, robust structure fits,
RANSAC), :mod:`.orientation` (the transposed check), :mod:`.degeneracy` (failure modes),
:mod:`.initialize` (section 2.3), :mod:`.lm` / :mod:`.alternating` (Algorithms 3 / 2),
:mod:`.lowdim` (planar and linear arrays), :mod:`.semiblind` (known directions) and
:mod:`.result`; their public names are re-exported here as before.
"""

from __future__ import annotations

import warnings
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
from .initialize import _canonical, fit_A_nonlinear, initialize_farfield, reduce_matrix
from .lowdim import _effective_dim, _solve_low_dim
from .minimal import solve_minimal
from .orientation import check_orientation
from .refine import LOSSES, farfield_residuals, refine_alternating, refine_lm
from .result import FarfieldInit, FarfieldResult
from .screen import (
    _robust_sigma,
    gross_error_screen,
    lowrank_fit,
    ransac_farfield,
    screen_gross_errors,
)
from .semiblind import _solve_known_directions

__all__ = [
    "FarfieldResult",
    "FarfieldInit",
    "solve_farfield",
    "initialize_farfield",
    "fit_A_nonlinear",
    "reduce_matrix",
    "screen_gross_errors",
    "check_orientation",
    "lowrank_fit",
    "ransac_farfield",
    "METHODS",
    "dimension_rule",
]

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
       rng="rng", reject_k="positive", cone_tol="positive", allow_degenerate="bool", screen="bool",
       check_degeneracy="bool", ransac="bool")
def solve_farfield(
    matrix: Any,
    *,
    method: str = "auto",
    loss: str = "linear",
    f_scale: float | None = None,
    noise_std: float | None = None,
    offsets: str = "auto",
    direction_solver: str = "global",
    allow_degenerate: bool = False,
    screen: bool = True,
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
) -> FarfieldResult:
    """Far-field TDOA self-calibration: positions, directions and offsets from D (paper 000).

    Parameters
    ----------
    matrix : (m, k) relative distances ``D_ij = z_i . n_j + C_j`` in metres (or any length
        unit; results come in the same unit). Rows = receiver positions (an antenna moved
        to m places, or m microphones), columns = k far transmitters. NaN = missing.
        Needs m >= 4 and k >= 6 for a full 3-D solution (Theorem 1).
    method : "lm" (Algorithm 3), "alternating" (Algorithm 2), "init" (section 2.3 only),
        "minimal" (Algorithm 1, 4 x 6 only) or "auto" ("minimal" for a complete 4 x 6
        matrix with the linear loss, else "lm").
    loss : "linear" (the paper's least squares) or a robust loss "huber", "soft_l1",
        "cauchy" (IRLS; then outliers are reported in ``rejected``).
    f_scale : robust loss scale (metres); default 1.345 (Huber, soft_l1) or 2.385 (Cauchy)
        x the robust noise estimate (1.4826 MAD of the residuals, dof-corrected).
    noise_std : known noise standard deviation of the entries (metres); used by the
        degeneracy thresholds (else estimated from the data).
    offsets : "reference" (C_j = D_1j, the paper's reduced cost), "free" (C_j estimated)
        or "auto" ("reference" for complete data with the linear loss, else "free").
    direction_solver : for "alternating": "global" or "local" (see :mod:`.refine`).
    allow_degenerate : return the partial reconstruction of a degenerate configuration
        (with ``degeneracy`` set) instead of raising.
    screen : treat gross errors (:func:`screen_gross_errors`: a residual test at family-wise
        false-alarm rate 1 % against the Student-t tail fitted to the residuals, so the rate
        holds for heavy-tailed noise too) as missing.
    reject_k : with a robust loss, entries with ``|residual| > reject_k`` robust std are rejected.
    max_iter, tol : refinement limits (defaults 200 / 1e-12 for LM, 2000 / 1e-10 for
        alternating).
    cone_tol : threshold of the cone test (see :mod:`.degeneracy`).
    init_reference : per-column constant removed before the factorisation (Lemma 1):
        "mean" (column means; noise spread evenly, our default) or "first" (``D_1j``, the
        paper's Algorithm 1 step 1).
    check_degeneracy : run the failure-mode analysis and act on it (raise / partial result).
        With False the full 3-D pipeline runs regardless, as in the paper's experiments; the
        analysis is still reported in ``diagnostics`` but ``degeneracy`` stays None.
    ransac : screen outliers first with :func:`ransac_farfield` (RANSAC over the minimal
        solver); entries outside its inlier set are treated as missing and reported in
        ``rejected``. Combine with a robust loss for the best results.
    rng : random generator / seed (used by ``ransac``).
    dim : 3 (space, the paper), 2 (planar: positions and directions in one plane, e.g. a
        circular / rectangular board with sources around it in its plane; or any array with
        coplanar directions, whose positions are then seen projected onto that plane),
        1 (linear: positions on a line, or all directions parallel), or ``"auto"``: the
        numerical rank of the column-centred matrix against the noise (nested tests of rank
        r - 1 against r at false-alarm rate 1e-3, Tracy-Widom quantiles, in
        :func:`~selfcal.tdoa.analyse_degeneracy`) and, at rank 2, the
        consistency of the 2-D quadric (chi-square per dof of ``ntilde^T B2 ntilde = 1``)
        decide. What is determined (paper 000, section 2.2) is in ``result.determined``:
        planar -- the in-plane geometry up to a rotation / reflection of the plane (needs
        k >= 3 directions not all on two lines); linear -- the positions along the line up
        to one scale factor (reported with the largest ``|projection|`` of a direction = 1:
        the smallest array consistent with the data, exact when a source is at endfire);
        parallel directions -- the coordinate along the direction, scale included.
        Positions with the directions off their plane (``planar-motion``) are not determined
        (a 2 x 2 family) and raise in every mode.
    directions : optional (k, d) known unit directions n_j (d = 3 or 2; e.g. from a
        turntable's angles). Then the problem is linear (semi-blind calibration): positions
        and offsets by least squares, ``case = "known-directions"``, in the frame of the given
        directions (no rotation is left free). The only way to calibrate data whose blind
        problem is degenerate (a ``cone``: all sources at one elevation), provided the
        directions are right.

    Raises
    ------
    InputError
        Malformed matrix or options.
    DegenerateGeometryError
        ``kind`` = "too-few-receivers" / "too-few-sources", or one of the failure modes
        (with ``partial`` = the partial FarfieldResult) unless ``allow_degenerate``.

    Examples
    --------
    Eight receiver positions, twelve far-away transmitters, 0.1 mm noise:

    >>> import numpy as np
    >>> import selfcal
    >>> rng = np.random.default_rng(4)
    >>> Z = rng.normal(size=(8, 3))
    >>> N = rng.normal(size=(12, 3))
    >>> N /= np.linalg.norm(N, axis=1, keepdims=True)
    >>> D = Z @ N.T + rng.normal(size=12) + 1e-4 * rng.standard_normal((8, 12))
    >>> res = selfcal.solve_farfield(D)
    >>> res.success, res.degeneracy, res.positions.shape
    (True, None, (8, 3))
    >>> bool(res.residual_rms < 2e-4)
    True
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
    scr = gross_error_screen(D) if screen else None
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
        offsets = "reference" if (complete and loss == "linear") else "free"
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
                Fr = np.where(used, D, Lr) if loss == "linear" else Lr
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
