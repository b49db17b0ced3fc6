"""Sparse nonlinear least squares for the bipartite range model (paper 003 sec. IV).

Model of entry (i, j) of an I x J range matrix (metres, NaN = missing)::

    y_ij = |r_i - s_j| + d_i + o_j + e_ij,      e_ij ~ N(0, sigma^2)

with optional per-receiver offsets ``d_i`` and per-source offsets ``o_j``
(``offsets`` in {"none", "receivers", "sources", "both"}; 004 sec. 3 writes the
same model in seconds). :func:`refine_toa` minimises 003 eq. 2 (or a robust
version of it) from an initial geometry and returns the 003 eq. 17 covariance of
every point with the gauge removed.

Gauge. The cost is invariant under the d(d+1)/2 rigid motions of all points (and,
with both kinds of offsets, under ``d_i + c, o_j - c``), so ``J^T J`` is singular.
The default solver keeps every coordinate free: the Marquardt damping makes each
step's system positive definite and the step is projected onto the orthogonal
complement of the gauge directions (:class:`selfcal.toa.engine.model.GaugeProjector`, the
projector off :func:`gauge_basis` formed analytically), so the network never drifts. ``solver="trf"`` and the covariance instead *pin* g coordinates, chosen by
a column-pivoted QR of the gauge basis restricted to the smaller node set so that
no gauge motion leaves every pinned coordinate fixed (the reduced normal matrix is
then non-singular). The minimum of the cost does not depend on either choice. The
covariance is reported gauge-free: the Moore-Penrose inverse ``sigma^2 (J^T J)^+``
(003 eq. 17 with the null space of the gauge removed), obtained from the pinned
inverse ``C`` as ``P C P`` with ``P`` the orthogonal projector onto the complement
of the gauge directions (any gauge-fixed inverse differs from ``(J^T J)^+`` only
along the gauge directions). Results are returned in the canonical gauge of
:func:`selfcal.geometry.canonical_gauge` (covariance blocks rotated with it).

Sparse structure. Every residual touches one receiver and one source, so the
Jacobian has 2d (+1, +2) non-zeros per row and ``J^T J`` is d x d block-diagonal
within each node set, coupled only through the receiver-source blocks. The default solver (``solver="schur"``) is Levenberg-Marquardt whose
normal equations are reduced by a Schur complement onto the smaller node set and
solved matrix-free by preconditioned conjugate gradients (Schur-Jacobi blocks):
O(I J d) per product, nothing of size (I d)^2 stored; the working set is the d unit-vector
components and a few residual / weight arrays, each the size of the data
(:mod:`selfcal.toa.engine.schur_lm`; 3000 x 3000 peaks at 1.1 GB). The covariance (:mod:`selfcal.toa.engine.covariance`)
needs the exact inverse: it forms the reduced matrix once, factorises it once and
computes only the requested d x d diagonal blocks by selected inversion,
O(min(I,J)^2 max(I,J) d^3) time for all of them.
``scipy.optimize.least_squares(method="trf", x_scale="jac")`` with the analytic
sparse Jacobian is the alternative solver (``solver="trf"``, the reference): it runs as the
constrained path's trf engine (:mod:`selfcal.toa.engine.constrained`) with the identity
parametrisation, the gauge pinned there.

Files: the model, its residuals, Jacobian, gauge and the kept / eliminated layout shared by
every engine live in :mod:`selfcal.toa.engine.model` (re-exported here); the one range model of
the driver with its step solvers (dense, Schur reduced, Schur CG; the grid or the observed
pairs) in :mod:`selfcal.toa.engine.schur_lm`, the covariance in
:mod:`selfcal.toa.engine.covariance`, the constrained path in :mod:`selfcal.toa.engine.constrained`; this
module keeps :func:`refine_toa` (validation of masks, constraints and priors, the choice of
solver); the result of both paths is assembled by
:func:`selfcal.toa.engine.model._solution`.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..._checks import as_matrix, as_points, check_choice, check_positive
from ...errors import DegenerateGeometryError, InputError
from ...optim.lm import irls
from ...robust import LOSSES, m_estimator_sigma2
from . import constrained as _constrained
from .model import (  # noqa: F401 -- the model's names, re-exported from their historical home
    _TUNING,
    OFFSET_MODES,
    NlsSolution,
    _check_counts,
    _flags,
    _make_layout,
    _pack,
    _robust_sigma,
    _solution,
    gauge_basis,
    toa_jacobian,
    toa_model,
    toa_residuals,
)
from .schur_lm import solve_schur_lm

__all__ = [
    "NlsSolution",
    "refine_toa",
    "toa_model",
    "toa_residuals",
    "toa_jacobian",
    "gauge_basis",
    "with_covariance",
    "OFFSET_MODES",
    "LOSSES",
]

Array = NDArray[np.float64]

#: smallest robust-loss scale (metres) :func:`refine_toa` estimates (when ``f_scale`` is not
#: given it fits at the estimated scale, then once more at the scale re-estimated from that
#: fit; both are at least this)
ROBUST_SCALE_FLOOR = 1e-9


# ---------------------------------------------------------------------------
# solvers
# ---------------------------------------------------------------------------


# ---------------------------------------------------------------------------
# public engine
# ---------------------------------------------------------------------------


def refine_toa(
    ranges: Array,
    receivers0: Array,
    sources0: Array,
    *,
    offsets: str = "none",
    receiver_offsets0: Array | None = None,
    source_offsets0: Array | None = None,
    loss: str = "linear",
    f_scale: float | None = None,
    max_nfev: int | None = None,
    xtol: float = 1e-10,
    solver: str = "auto",
    covariance: Any = True,
    fixed_receivers: Any = None,
    fixed_sources: Any = None,
    receiver_prior: Any = None,
    source_prior: Any = None,
    fixed_receiver_offsets: Any = None,
    fixed_source_offsets: Any = None,
    common_offsets: str = "none",
    receiver_offset_basis: Any = None,
    source_offset_basis: Any = None,
    noise: float | None = None,
    weights: Any = None,
    normal_inverse: Any = None,
) -> NlsSolution:
    """Refine receivers, sources (and offsets) by sparse nonlinear least squares (003 eq. 2, 16-17).

    Minimises ``sum_ij rho((|r_i - s_j| + d_i + o_j - y_ij)^2 / f_scale^2)`` over the
    observed entries (003 eq. 2b for ``loss="linear"``), with the analytic Jacobian
    (003 eq. 16) and the gauge handled as described in the module docstring.

    Parameters
    ----------
    ranges: (I, J) measured ranges in metres (rows = receivers, columns = sources),
        NaN = missing. Negative entries are legal when offsets are estimated.
    receivers0, sources0: (I, d), (J, d) initial positions, d in {2, 3}.
    offsets: "none" | "receivers" | "sources" | "both" - which offsets are unknowns.
    receiver_offsets0, source_offsets0: (I,), (J,) initial offsets (metres); zeros
        when omitted.
    loss: "linear" (Gaussian ML), "huber", "soft_l1" or "cauchy" (outlier-robust).
    f_scale: residual scale (metres) of the robust loss; default the 95%-efficiency
        tuning constant (Huber 1.345, Cauchy 2.385) times a robust (MAD) noise estimate,
        re-estimated once after a first refinement.
    max_nfev: cap on iterations / function evaluations.
    xtol: relative step tolerance.
    solver: "auto" / "schur" (Levenberg-Marquardt on the Schur-reduced normal equations,
        conjugate gradients with a Schur-Jacobi preconditioner) or "trf"
        (``scipy.optimize.least_squares(method="trf", x_scale="jac")`` with the sparse
        analytic Jacobian; ``tr_solver="exact"`` up to 600 unknowns, ``"lsmr"`` above: the
        constrained path's trf with the identity parametrisation, so its covariance, also
        ``"local"``, is exact) or
        "lm" (with constraints or weights: the driver's Levenberg-Marquardt on the reduced
        vector, :func:`selfcal.optim.lm.levenberg_marquardt`; without: as "schur").
    covariance: which 003 eq. 17 covariance blocks to compute: True / "all", "receivers",
        "sources", False / "none", or indices ``{"receivers": idx, "sources": idx}`` /
        ``(receiver_idx, source_idx)`` (:func:`selfcal.toa.engine.covariance.normalize_covariance`);
        blocks not asked for are NaN. Selected inversion from one factorization of the
        reduced system (:mod:`selfcal.toa.engine.covariance`: O(min(I,J)^2 max(I,J) d^3) time for
        all blocks, the dominant cost for very large networks). With constraints the
        same request is honoured by the sparse-LU path of :mod:`selfcal.toa.engine.constrained`.
        ``"local"``: every block approximated by the node's conditional covariance
        (:func:`selfcal.toa.engine.covariance.local_blocks`, O(I J d^2), relative error
        ~(d + 1) / partners on dense networks); the constrained path computes it exactly.
    fixed_receivers, fixed_sources: (I, d) / (J, d) bool masks (or (I,) / (J,) row
        masks) of coordinates held at their starting values: known heights are a fixed
        z column, known anchors fixed rows.
    receiver_prior, source_prior: Gaussian priors ``(mean, std)`` on positions ("known
        with a std"): mean (I, d) / (J, d) in metres with NaN where there is no prior,
        std (I,) / (I, d) metres. Each adds a residual row ``(sigma / std)(x - mean)``.
    fixed_receiver_offsets, fixed_source_offsets: (I,) / (J,) bool masks of offsets
        held at their starting values.
    common_offsets: "none" | "receivers" | "sources" | "both": the offsets of that kind
        are one common unknown (started at the mean of the starting offsets).
    receiver_offset_basis, source_offset_basis: general linear constraint
        ``d = receiver_offsets0 + B x`` with B (I, k) (likewise ``o``), e.g. a fixed
        mean with free zero-sum deviations.
    noise: range noise std (metres) weighting the priors; estimated from the fit
        (re-weighted until it settles) when omitted.
    normal_inverse: ``(theta, pattern) -> inverse | None``, a generalised inverse of ``J^T J`` the
        caller already holds at the estimate (the outlier rule's linearisation,
        :func:`selfcal.toa.verdict.leverage.kept_inverse`): with the linear loss the covariance
        blocks come from it (:func:`selfcal.toa.engine.covariance.blocks_from_inverse`, the
        same blocks to round-off) where it certifies that the selected inversion would accept
        the geometry; None (default) or its refusal: the selected inversion.
    weights: (I, J) per-entry weights, ``1 / std`` up to a common factor (finite and >= 0 on
        the observed entries; 0 = the entry does not count): weighted least squares, the ML
        fit when the entries' noise differs; a robust loss then applies to the weighted
        residuals (``f_scale`` in their units). ``sigma`` is the noise of a unit-weight entry,
        the covariance ``sigma^2 (J^T W J)^+``. Runs on the constrained path.

    Returns
    -------
    NlsSolution, in the canonical gauge (:func:`selfcal.geometry.canonical_gauge`),
    except with fixed or prior positions: then in the frame of those positions (the
    gauge they leave free, e.g. horizontal motions when only heights are known, is held
    at the start's), with ``solver="trf-constrained"``.

    Notes
    -----
    Any constraint keyword selects the constrained path of :mod:`selfcal.toa.engine.constrained`:
    fixed columns removed from the sparse analytic Jacobian, prior rows appended,
    ``scipy.optimize.least_squares(method="trf")``, covariance free of the gauge the
    constraints leave.

    Examples
    --------
    Known heights (the z column of every node fixed) with both offsets::

        fz = np.zeros((I, 3), bool); fz[:, 2] = True
        gz = np.zeros((J, 3), bool); gz[:, 2] = True
        sol = refine_toa(c * T, r0, s0, offsets="both", fixed_receivers=fz, fixed_sources=gz)
    """
    from .covariance import resolve_covariance

    check_choice(offsets, "offsets", OFFSET_MODES)
    check_choice(loss, "loss", LOSSES)
    check_choice(solver, "solver", ("auto", "trf", "schur", "lm"))
    Y = as_matrix(ranges, "ranges")
    I, J = Y.shape
    r0 = as_points(receivers0, "receivers0")
    d = r0.shape[1]
    s0 = as_points(sources0, "sources0", dim=d)
    if r0.shape[0] != I or s0.shape[0] != J:
        raise InputError(
            f"initial geometry has {r0.shape[0]} receivers and {s0.shape[0]} sources but the "
            f"range matrix is {I} x {J}"
        )
    has_r, has_s = _flags(offsets)
    dr0 = _offsets0(receiver_offsets0, I, "receiver_offsets0") if has_r else None
    os0 = _offsets0(source_offsets0, J, "source_offsets0") if has_s else None
    if f_scale is not None and not (np.isfinite(f_scale) and f_scale > 0):
        raise InputError(f"f_scale must be a positive number (metres), got {f_scale!r}")

    wts = None
    if weights is not None:
        wts = as_matrix(weights, "weights", allow_nan=True)
        if wts.shape != (I, J):
            raise InputError(f"weights has shape {wts.shape}; the range matrix is {I} x {J}")
        wo = wts[np.isfinite(Y)]
        if not (np.isfinite(wo).all() and (wo >= 0).all() and (wo > 0).any()):
            raise InputError("weights must be finite and >= 0 on the observed ranges, and not all 0")
    cons = dict(fixed_receivers=fixed_receivers, fixed_sources=fixed_sources,
                receiver_prior=receiver_prior, source_prior=source_prior,
                fixed_receiver_offsets=fixed_receiver_offsets,
                fixed_source_offsets=fixed_source_offsets, common_offsets=common_offsets,
                receiver_offset_basis=receiver_offset_basis, source_offset_basis=source_offset_basis)
    if _constrained.is_active(cons) or solver == "trf" or wts is not None:
        # the affine parametrisation (the identity, less the pinned gauge, without constraints)
        con = _constrained.make_constraints(I, J, d, offsets, receiver_offsets0=dr0,
                                            source_offsets0=os0, **cons)
        sol = _constrained.refine_constrained(
            Y, r0, s0, offsets, con, loss=loss, f_scale=f_scale, max_nfev=max_nfev, xtol=xtol,
            covariance=covariance, noise=check_positive(noise, "noise"), engine=solver, weights=wts)
        return sol if _constrained.is_active(cons) or wts is not None else dataclasses.replace(sol, solver="trf")

    cov_r, cov_s = resolve_covariance(covariance, I, J)
    theta0 = _pack(r0, s0, dr0, os0)
    obs = np.isfinite(Y)
    _check_counts(obs.sum(axis=1), obs.sum(axis=0), d + has_r, d + has_s)
    lay = _make_layout(r0, s0, offsets)
    m = int(obs.sum())
    g = lay.pins.size
    n_free = lay.n - g
    if m < n_free:
        raise DegenerateGeometryError(
            f"{m} observed ranges for {n_free} unknowns; add receivers, sources or measurements",
            kind="too-few-measurements",
        )
    # "auto" = Schur LM: measured faster than least_squares at every size we tried (8x10 to
    # 1000x1000), see benchmarks/bench_toa.py; "trf" stays available as the reference

    if loss == "linear":
        fs = 1.0
        theta, conv, nit = solve_schur_lm(theta0, Y, lay, loss, fs, max_nfev, xtol)
    else:
        f0 = toa_residuals(theta0, Y, d, offsets)
        k95 = _TUNING[loss]
        fs = f_scale if f_scale is not None else max(k95 * _robust_sigma(f0), ROBUST_SCALE_FLOOR)
        theta, conv, nit = solve_schur_lm(theta0, Y, lay, loss, fs, max_nfev, xtol)
        if f_scale is None:
            # the initial residuals mix geometry error with noise: re-scale on the refined ones
            shrink = float(np.sqrt(m / max(m - n_free, 1)))  # fitted residuals underestimate sigma
            fs = max(k95 * shrink * _robust_sigma(toa_residuals(theta, Y, d, offsets)), ROBUST_SCALE_FLOOR)
            theta, conv2, nit2 = solve_schur_lm(theta, Y, lay, loss, fs, max_nfev, xtol)
            conv, nit = conv2, nit + nit2

    return _finish(theta, Y, lay, offsets, loss, fs, covariance, cov_r, cov_s, normal_inverse, conv, nit)


def _finish(theta: Array, Y: Array, lay: Any, offsets: str, loss: str, fs: float, covariance: Any,
            cov_r: NDArray[np.intp], cov_s: NDArray[np.intp], normal_inverse: Any, conv: bool, nit: int) -> NlsSolution:
    """The :class:`NlsSolution` of :func:`refine_toa` ending at ``theta``: residuals, noise
    estimate, the requested covariance blocks (003 eq. 17), the canonical gauge."""
    from .covariance import blocks_from_inverse, gauge_free_blocks, is_local, local_blocks

    I, J = Y.shape
    d = lay.d
    has_r, has_s = _flags(offsets)
    obs = np.isfinite(Y)
    m = int(obs.sum())
    n_free = lay.n - lay.pins.size
    f = toa_residuals(theta, Y, d, offsets)
    cost, _ = irls(f, loss, fs)
    dof = m - n_free
    wmat = obs.astype(float)
    if loss == "linear":
        sigma = float(np.sqrt((f**2).sum() / dof)) if dof > 0 else float("nan")
        var = sigma**2
    else:
        # residuals of a fit with n_free unknowns shrink by sqrt(dof / m) on average
        sigma = _robust_sigma(f) * float(np.sqrt(m / dof)) if dof > 0 else float("nan")
        # the covariance of the M-estimate: the Gauss-Newton information of the entries used times
        # the M-estimator's variance factor (selfcal.robust.m_estimator_sigma2, the one of the
        # far-field fits), not sigma^2 (J^T W J)^+ with the IRLS weights W, which was 1.19x (Gaussian)
        # to 1.39x (t3) too small in variance at 10 x 20 (tests/toa/test_covariance.py)
        var = m_estimator_sigma2(f, np.ones(f.shape, bool), loss, fs, n_free) if dof > 0 else float("nan")

    if cov_r.size or cov_s.size:
        # a singular Fisher matrix beyond the gauge: the data do not determine the geometry
        if is_local(covariance):  # the approximate conditional blocks, O(I J d^2)
            Cr, Cs = local_blocks(theta, wmat, lay)
        else:
            inv = normal_inverse(theta, obs) if normal_inverse is not None and loss == "linear" else None
            held = None if inv is None else blocks_from_inverse(inv, theta, lay, cov_r, cov_s)
            Cr, Cs = held if held is not None else gauge_free_blocks(theta, wmat, lay, cov_r, cov_s)
        Cr, Cs = Cr * var, Cs * var
    else:
        Cr = np.full((I, d + has_r, d + has_r), np.nan)
        Cs = np.full((J, d + has_s, d + has_s), np.nan)
    if not np.isfinite(sigma):
        Cr, Cs = np.full_like(Cr, np.nan), np.full_like(Cs, np.nan)
    return _solution(theta, Y, d, offsets, Cr, Cs, canonical=True, shift=True, sigma=sigma, converged=conv,
                     iterations=nit, cost=cost, solver="schur-lm")


def with_covariance(sol: NlsSolution, ranges: Array, *, offsets: str, covariance: Any = True,
                    normal_inverse: Any = None) -> NlsSolution:
    """What :func:`refine_toa` (linear loss, from ``sol``) returns when its start is already its
    answer: ``sol``'s residuals, noise estimate and requested covariance blocks at ``sol``.

    For a ``sol`` that a linear-loss :func:`refine_toa` on the same ``ranges`` returned
    converged and whose Gauss-Newton step is below the step tolerance
    (:func:`selfcal.toa.verdict.leverage.settled`), a refinement from it stops after one step
    no longer than that: the estimate is ``sol`` to the solver's tolerance, and this spares
    that step (:func:`selfcal.toa.fit.finish`'s final refit when nothing changed since the
    search).

    Parameters
    ----------
    sol : a linear-loss fit of ``ranges`` (metres), in the canonical gauge.
    ranges : (I, J) the ranges it was fitted on, NaN = missing.
    offsets, covariance, normal_inverse : as in :func:`refine_toa`.

    Returns
    -------
    NlsSolution with ``iterations=0``, ``converged`` as ``sol``'s.

    Raises
    ------
    DegenerateGeometryError
        As :func:`refine_toa`: a (nearly) collinear geometry, a singular covariance.
    """
    from .covariance import resolve_covariance

    Y = as_matrix(ranges, "ranges")
    I, J = Y.shape
    cov_r, cov_s = resolve_covariance(covariance, I, J)
    lay = _make_layout(sol.receivers, sol.sources, offsets)
    theta = _pack(sol.receivers, sol.sources, sol.receiver_offsets, sol.source_offsets)
    return _finish(theta, Y, lay, offsets, "linear", 1.0, covariance, cov_r, cov_s, normal_inverse,
                   bool(sol.converged), 0)


def _offsets0(value: Array | None, n: int, name: str) -> Array:
    if value is None:
        return np.zeros(n)
    v = np.asarray(value, dtype=float).ravel()
    if v.shape != (n,) or not np.isfinite(v).all():
        raise InputError(f"{name}: expected {n} finite offsets, got shape {np.shape(value)}")
    return v
