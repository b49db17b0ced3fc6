"""Constrained fits of the bipartite range model: fixed coordinates, offset constraints, priors.

This is the constrained path of :func:`selfcal.toa.engine.nls.refine_toa` (the one engine of
the range model ``y_ij = |r_i - s_j| + d_i + o_j + e_ij``, 003 eq. 2 with the offsets of
004 sec. 3). ``refine_toa`` dispatches here when any of its constraint keywords is set;
the unconstrained gauge-free path stays in :mod:`selfcal.toa.engine.nls`.

Parametrisation. The full parameter vector ``theta = [r (I d), s (J d), d_i (I)?, o_j
(J)?]`` (receiver-major, as :func:`selfcal.toa.engine.nls.toa_residuals`) is written as an
affine map of a reduced vector, ``theta = base + T x``:

- positions: a fixed coordinate keeps its starting value, a free one is a column of the
  identity (known heights = fixed z column, known anchors = fixed rows);
- offsets: ``d = d_0 + B_r x_r`` for any (I, k) basis ``B_r``; fixed offsets drop
  columns of the identity, a common offset is the single column of ones (likewise
  ``o`` with ``B_s``).

Priors ``N(mu, std^2)`` on positions ("known with a std") add residual rows
``(sigma / std) (theta_k - mu_k)`` in the units of the range residuals, where
``sigma`` is the range noise (given, or estimated from the fit and re-estimated until it
settles, at most three passes). The Jacobian is the analytic sparse Jacobian of the
ranges times the sparse ``T`` (fixed columns removed), stacked on the prior rows, and the
fit is ``scipy.optimize.least_squares(method="trf")``.

Gauge. The constraints remove the part of the rigid-motion (and common-shift) gauge
they pin; what is left (e.g. horizontal translations and the rotation about z when
only heights are known) is computed as the gauge directions of
:func:`selfcal.toa.engine.nls.gauge_basis` that vanish on fixed and prior coordinates and lie
in the range of the offset bases. That residual gauge is fixed by pinning as many
reduced coordinates (column-pivoted QR), and the covariance is reported free of it,
``sigma^2 P (J^T W J)_pinned^-1 P`` with ``P`` the projector off the residual gauge
(the Moore-Penrose inverse, 003 eq. 17). Its node blocks come from a sparse LU of the
reduced normal matrix, solved for the columns each node needs (no dense inverse).

Engines. Above 120 free unknowns with the linear loss the fit runs on the Schur-reduced
Newton-LM of :mod:`selfcal.toa.engine.schur_affine` (:func:`_engine_partition`), whose covariance
blocks come from the same partition; SciPy trf stays the path of small problems, robust
losses and ``solver="trf"`` (the reference of the tests; without constraints too, as the
identity parametrisation), and ``solver="lm"``: the driver on the reduced vector (the
pipeline's known-heights fit, with per-entry ``weights``).

Length (about 630 lines, above the ~600 guideline): validation of the constraint keywords,
the parametrisation, the residual gauge, the weighted fit and its covariance are one job
(the constrained engine's interface); the Schur iteration lives in
:mod:`selfcal.toa.engine.schur_affine`.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
import scipy.linalg
import scipy.sparse
import scipy.sparse.linalg
from numpy.typing import NDArray
from scipy.optimize import least_squares

from ...errors import DegenerateGeometryError, InputError
from ...optim.lm import irls, levenberg_marquardt
from ...optim.steps import ResidualModel
from ...optim.structure import TRF_EXACT_MAX, lm_step
from ...robust import m_estimator_sigma2
from .model import (
    _TUNING,
    _check_counts,
    _node_indices,
    _robust_sigma,
    _solution,
    _unpack,
    gauge_basis,
    toa_jacobian,
    toa_residuals,
)
from .schur_affine import MAX_GLOBAL, RangeSchurModel, local_blocks

Array = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

# least_squares "exact" trust-region solves (dense SVD) up to this many unknowns
# most entries of the Schur engine's dense coupling array (local slots x global unknowns)
_COUPLING_MAX = 4_000_000


class _Run:
    """One inner solve: the reduced vector, its convergence flag and its iterations."""

    def __init__(self, x: Array, converged: bool, iterations: int) -> None:
        self.x, self.converged, self.iterations = x, converged, iterations


@dataclass(frozen=True)
class Constraints:
    """Validated constraint set of one constrained fit (internal).

    Attributes
    ----------
    fixed_r, fixed_s: (I, d), (J, d) bool, True = coordinate fixed at its start.
    prior_r_mean, prior_s_mean: (I, d), (J, d) prior means, NaN = no prior.
    prior_r_std, prior_s_std: (I, d), (J, d) prior standard deviations (m), inf = none.
    basis_r, basis_s: (I, k_r), (J, k_s) offset bases or None (kind not estimated).
    base_r, base_s: (I,), (J,) offset value at x = 0.
    x0_r, x0_s: (k_r,), (k_s,) starting reduced offsets.
    own_r, own_s: (I,), (J,) bool, True where a node has an offset of its own (a column
        of the basis touching only it), for the node-count check.
    offsets_constrained: any offset is fixed, common or on a given basis.
    """

    fixed_r: BoolArray
    fixed_s: BoolArray
    prior_r_mean: Array
    prior_s_mean: Array
    prior_r_std: Array
    prior_s_std: Array
    basis_r: Array | None
    basis_s: Array | None
    base_r: Array
    base_s: Array
    x0_r: Array
    x0_s: Array
    own_r: BoolArray
    own_s: BoolArray
    offsets_constrained: bool

    @property
    def has_positions(self) -> bool:
        """True when positions are fixed or have priors (the result keeps that frame)."""
        return bool(
            self.fixed_r.any() or self.fixed_s.any()
            or np.isfinite(self.prior_r_mean).any() or np.isfinite(self.prior_s_mean).any()
        )


def _mask(value: Any, n: int, d: int, name: str) -> BoolArray:
    """(n, d) bool mask from None, an (n,) row mask or an (n, d) mask."""
    if value is None:
        return np.zeros((n, d), bool)
    a = np.asarray(value)
    if a.dtype != bool:
        raise InputError(f"{name}: expected a boolean mask of shape ({n},) or ({n}, {d}), got dtype {a.dtype}")
    if a.shape == (n,):
        return np.repeat(a[:, None], d, axis=1)
    if a.shape != (n, d):
        raise InputError(f"{name}: expected shape ({n},) or ({n}, {d}), got {a.shape}")
    return a.copy()


def _prior(value: Any, n: int, d: int, name: str) -> tuple[Array, Array]:
    """(mean, std) arrays (n, d) from None or ``(mean (n, d) NaN = none, std (n,) / (n, d))``."""
    if value is None:
        return np.full((n, d), np.nan), np.full((n, d), np.inf)
    try:
        mean, std = value
    except (TypeError, ValueError):
        raise InputError(f"{name}: expected a pair (mean (n, d) with NaN = no prior, std (n,) or (n, d))") from None
    mu = np.array(mean, dtype=float)
    if mu.shape != (n, d) or np.isinf(mu).any():
        raise InputError(f"{name}: mean must be a ({n}, {d}) array (NaN = no prior), got shape {mu.shape}")
    sd = np.array(std, dtype=float)
    if sd.shape == (n,):
        sd = np.repeat(sd[:, None], d, axis=1)
    if sd.shape != (n, d):
        raise InputError(f"{name}: std must have shape ({n},) or ({n}, {d}), got {sd.shape}")
    on = np.isfinite(mu)
    if (on & ~(np.isfinite(sd) & (sd > 0))).any():
        raise InputError(f"{name}: every prior std must be a finite positive number (m); "
                         "for an exact position use the fixed mask instead")
    return mu, np.where(on, sd, np.inf)


def _offset_param(
    kind: str, n: int, has: bool, start: Array | None, fixed: Any, common: bool, basis: Any
) -> tuple[Array | None, Array, Array, BoolArray, bool]:
    """(basis, base, x0, own, constrained) of one kind of offsets."""
    if not has:
        if fixed is not None or common or basis is not None:
            raise InputError(f"{kind} offset constraints were given but the {kind} offsets are not "
                             f"estimated; use offsets='{kind}s' or 'both'")
        return None, np.zeros(n), np.zeros(0), np.zeros(n, bool), False
    v0 = np.zeros(n) if start is None else np.asarray(start, float)
    given = sum(x is not None and x is not False for x in (fixed, basis)) + int(common)
    if given > 1:
        raise InputError(f"{kind} offsets: give at most one of a fixed mask, a common offset and a basis")
    if basis is not None:
        B = np.array(basis, dtype=float)
        if B.ndim != 2 or B.shape[0] != n or not np.isfinite(B).all():
            raise InputError(f"{kind}_offset_basis: expected a finite ({n}, k) array, got shape {B.shape}")
        own = np.array([(B[i] != 0).any() and not (np.delete(B, i, axis=0)[:, B[i] != 0] != 0).any()
                        for i in range(n)])
        return B, v0.copy(), np.zeros(B.shape[1]), own, True
    if common:
        return np.ones((n, 1)), np.zeros(n), np.array([float(np.mean(v0))]), np.zeros(n, bool), True
    if fixed is not None:
        f = np.asarray(fixed)
        if f.dtype != bool or f.shape != (n,):
            raise InputError(f"fixed_{kind}_offsets: expected a boolean mask of shape ({n},), got {f.shape}")
        free = np.nonzero(~f)[0]
        B = np.eye(n)[:, free]
        return B, np.where(f, v0, 0.0), v0[free], ~f, bool(f.any())
    return np.eye(n), np.zeros(n), v0.copy(), np.ones(n, bool), False


def make_constraints(
    I: int, J: int, d: int, offsets: str, *,
    receiver_offsets0: Array | None, source_offsets0: Array | None,
    fixed_receivers: Any = None, fixed_sources: Any = None,
    receiver_prior: Any = None, source_prior: Any = None,
    fixed_receiver_offsets: Any = None, fixed_source_offsets: Any = None,
    common_offsets: str = "none",
    receiver_offset_basis: Any = None, source_offset_basis: Any = None,
) -> Constraints:
    """Validate the constraint keywords of :func:`selfcal.toa.engine.nls.refine_toa`."""
    has_r, has_s = offsets in ("receivers", "both"), offsets in ("sources", "both")
    if common_offsets not in ("none", "receivers", "sources", "both"):
        raise InputError(f"common_offsets must be 'none', 'receivers', 'sources' or 'both'; got {common_offsets!r}")
    com_r, com_s = common_offsets in ("receivers", "both"), common_offsets in ("sources", "both")
    fr = _mask(fixed_receivers, I, d, "fixed_receivers")
    fs = _mask(fixed_sources, J, d, "fixed_sources")
    pr_m, pr_s = _prior(receiver_prior, I, d, "receiver_prior")
    ps_m, ps_s = _prior(source_prior, J, d, "source_prior")
    Br, b0r, x0r, own_r, cr = _offset_param("receiver", I, has_r, receiver_offsets0,
                                             fixed_receiver_offsets, com_r, receiver_offset_basis)
    Bs, b0s, x0s, own_s, cs = _offset_param("source", J, has_s, source_offsets0,
                                             fixed_source_offsets, com_s, source_offset_basis)
    return Constraints(fr, fs, pr_m, ps_m, pr_s, ps_s, Br, Bs, b0r, b0s, x0r, x0s, own_r, own_s,
                       cr or cs)


def is_active(constraints: Mapping[str, Any]) -> bool:
    """True when any constraint keyword (name -> value) differs from its default (None / "none")."""
    return any(v is not None and not (isinstance(v, str) and v == "none") for v in constraints.values())


@dataclass(frozen=True)
class _Param:
    """The affine map ``theta = base + T x`` and its bookkeeping."""

    T: scipy.sparse.csc_matrix  # (n, p)
    base: Array  # (n,)
    x0: Array  # (p,)
    pos_cols: NDArray[np.intp]  # theta index of each position column of x
    n_pos: int  # number of position columns (first in x)
    prior_x: NDArray[np.intp]  # x indices with a prior
    prior_mu: Array
    prior_std: Array


def _parametrise(con: Constraints, r0: Array, s0: Array) -> _Param:
    I, d = r0.shape
    J = s0.shape[0]
    npos = (I + J) * d
    pos0 = np.concatenate([r0.ravel(), s0.ravel()])
    fixed = np.concatenate([con.fixed_r.ravel(), con.fixed_s.ravel()])
    free = np.nonzero(~fixed)[0]
    mu = np.concatenate([con.prior_r_mean.ravel(), con.prior_s_mean.ravel()])
    sd = np.concatenate([con.prior_r_std.ravel(), con.prior_s_std.ravel()])
    blocks = [scipy.sparse.csc_matrix((np.ones(free.size), (free, np.arange(free.size))),
                                      shape=(npos, free.size))]
    base = [np.where(fixed, pos0, 0.0)]
    x0 = [pos0[free]]
    for B, b0, xx in ((con.basis_r, con.base_r, con.x0_r), (con.basis_s, con.base_s, con.x0_s)):
        if B is not None:
            blocks.append(scipy.sparse.csc_matrix(B))
            base.append(b0)
            x0.append(xx)
    T = scipy.sparse.block_diag(blocks, format="csc")
    on = np.isfinite(mu[free])
    return _Param(T, np.concatenate(base), np.concatenate(x0), free, free.size,
                  np.nonzero(on)[0], mu[free][on], sd[free][on])


def _residual_gauge(par: _Param, con: Constraints, r0: Array, s0: Array, offsets: str) -> Array:
    """Orthonormal basis (p, g') of the gauge directions that survive the constraints."""

    Q = gauge_basis(r0, s0, offsets)  # (n, g)
    I, d = r0.shape
    J = s0.shape[0]
    npos = (I + J) * d
    fixed = np.concatenate([con.fixed_r.ravel(), con.fixed_s.ravel()])
    rows = [Q[:npos][fixed], Q[par.pos_cols[par.prior_x]]]
    k = npos
    coeffs = []
    for B in (con.basis_r, con.basis_s):
        if B is None:
            continue
        nB = B.shape[0]
        Qo = Q[k : k + nB]
        c, *_ = np.linalg.lstsq(B, Qo, rcond=None)
        rows.append(Qo - B @ c)  # the part of the gauge motion the offset basis cannot follow
        coeffs.append(c)
        k += nB
    M = np.vstack(rows) if rows else np.zeros((0, Q.shape[1]))
    if M.shape[0]:
        _, sv, Vt = np.linalg.svd(M, full_matrices=True)
        tol = 1e-9 * max(1.0, float(np.abs(Q).max()))
        rank = int((sv > tol).sum())
        N = Vt[rank:].T
    else:
        N = np.eye(Q.shape[1])
    if N.shape[1] == 0:
        return np.zeros((par.x0.size, 0))
    G = np.concatenate([Q[par.pos_cols] @ N] + [c @ N for c in coeffs], axis=0)
    q, _ = np.linalg.qr(G)
    return np.asarray(q)


def _engine_partition(
    TF: scipy.sparse.csc_matrix, I: int, J: int, d: int, offsets: str, engine: str, loss: str
) -> tuple[NDArray[np.intp], NDArray[np.intp]] | None:
    """The (blocks, global) partition of the Schur engine, or None when the trf path runs.

    "auto": the Schur engine for the Gaussian (linear) loss above
    :data:`selfcal.toa.engine.schur_lm.DENSE_MAX_UNKNOWNS` free unknowns (small problems keep
    SciPy's dense trust region) while its dense reduced system stays small
    (:data:`selfcal.toa.engine.schur_affine.MAX_GLOBAL` global unknowns, the coupling array under
    :data:`_COUPLING_MAX` entries); "schur" whenever it fits; "trf" never. Robust losses stay
    on trf under "auto": the engine's iteratively reweighted steps reach the same stationary
    points, but from the same start a different one more often (simulated flights with 2 %
    gross 0.5 m errors, Huber at a given scale: a higher cost than trf's on 3 of 8 seeds, a
    lower one on 1; the same on 4).
    """
    if engine in ("trf", "lm") or (engine == "auto" and (lm_step(TF.shape[1]) == "dense" or loss != "linear")):
        return None
    r_idx, s_idx, n = _node_indices(I, J, d, offsets)
    e_idx = s_idx if I <= J else r_idx  # eliminate the larger node set
    node = -np.ones(n, np.intp)
    node[e_idx] = np.arange(e_idx.shape[0])[:, None]
    blocks, glob = local_blocks(TF, node)
    if glob.size > MAX_GLOBAL or blocks.size * glob.size > _COUPLING_MAX:
        return None
    return blocks, glob


def refine_constrained(
    Y: Array, r0: Array, s0: Array, offsets: str, con: Constraints, *,
    loss: str, f_scale: float | None, max_nfev: int | None, xtol: float,
    covariance: Any, noise: float | None, engine: str = "auto", weights: Array | None = None,
) -> Any:
    """Constrained fit of the range model; returns a :class:`selfcal.toa.engine.nls.NlsSolution`.

    See the module docstring. Called by :func:`selfcal.toa.engine.nls.refine_toa` only.
    ``covariance`` is any request of :func:`selfcal.toa.engine.covariance.normalize_covariance`
    (True / "all", "receivers", "sources", "none" / False, or indices): only the requested
    node blocks are solved for, the others are NaN, as on the unconstrained path.
    ``engine``: "auto" (the Schur-reduced LM of :mod:`selfcal.toa.engine.schur_affine` on
    problems above ``DENSE_MAX_UNKNOWNS`` free unknowns with the linear loss, SciPy's trf
    otherwise, :func:`_engine_partition`), "schur"
    (the Schur engine whenever its reduced system fits), "trf" (SciPy
    ``least_squares(method="trf")`` always: the independent reference) or "lm" (the
    driver, :func:`selfcal.optim.lm.levenberg_marquardt`, on the reduced vector with the
    step :func:`selfcal.optim.structure.lm_step` chooses; ``ftol = xtol``).
    ``weights``: (I, J) per-entry weights (``1 / std``, finite and >= 0 on the observed
    entries) or None: every range residual and its Jacobian row is scaled by its weight
    (weighted least squares, or the robust loss on the weighted residuals); ``sigma`` is then
    the noise of a unit-weight entry and the covariance ``sigma^2 (J^T W J)^+``. Weighted fits
    run on SciPy's trf (the Schur engine has no weights).
    """
    from .covariance import resolve_covariance

    I, J = Y.shape
    d = r0.shape[1]
    want_r, want_s = resolve_covariance(covariance, I, J)
    has_r, has_s = offsets in ("receivers", "both"), offsets in ("sources", "both")
    obs = np.isfinite(Y)
    need_r, need_s = ((~fixed & ~np.isfinite(mu)).sum(axis=1) + own.astype(int)
                      for fixed, mu, own in ((con.fixed_r, con.prior_r_mean, con.own_r),
                                             (con.fixed_s, con.prior_s_mean, con.own_s)))
    _check_counts(obs.sum(axis=1), obs.sum(axis=0), need_r, need_s)
    par = _parametrise(con, r0, s0)
    Gx = _residual_gauge(par, con, r0, s0, offsets)
    p = par.x0.size
    gp = Gx.shape[1]
    if gp:
        _, R, piv = scipy.linalg.qr(Gx.T, pivoting=True, mode="economic")
        dg = np.abs(np.diag(R))
        if dg.size < gp or dg[-1] < 1e-6 * dg[0]:
            raise DegenerateGeometryError(
                "the residual gauge cannot be fixed: the free points are (nearly) collinear",
                kind="degenerate-geometry")
        pins = np.sort(piv[:gp])
    else:
        pins = np.zeros(0, np.intp)
    F = np.setdiff1d(np.arange(p), pins)
    m = int(obs.sum())
    n_prior = par.prior_x.size
    if m + n_prior < F.size:
        raise DegenerateGeometryError(
            f"{m} observed ranges and {n_prior} prior coordinates for {F.size} unknowns; "
            "add measurements or known coordinates", kind="too-few-measurements")
    TF = par.T[:, F].tocsc()
    # prior coordinates are never pinned: the residual gauge vanishes on them
    prior_pos = np.searchsorted(F, par.prior_x)
    xbase = par.x0.copy()
    w = None if weights is None else np.asarray(weights, float)[obs]

    def meas(th: Array) -> Array:  # the (weighted) range residuals
        f = toa_residuals(th, Y, d, offsets)
        return f if w is None else w * f

    part = None if w is not None else _engine_partition(TF, I, J, d, offsets, engine, loss)
    schur = None if part is None else RangeSchurModel(obs, I, J, d, offsets, TF, prior_pos, *part)

    def theta_of(xf: Array) -> Array:
        x = xbase.copy()
        x[F] = xf
        return par.base + par.T @ x

    def run(xf0: Array, wprior: Array, fs: float) -> Any:
        def fun(xf: Array) -> Array:
            th = theta_of(xf)
            f = meas(th)
            if n_prior:
                f = np.concatenate([f, wprior * (xf[prior_pos] - par.prior_mu)])
            return f

        dense = F.size <= TRF_EXACT_MAX

        def jac(xf: Array) -> Any:
            Jm = toa_jacobian(theta_of(xf), Y, d, offsets) @ TF
            if w is not None:
                Jm = scipy.sparse.diags(w) @ Jm
            if n_prior:
                Jp = scipy.sparse.csr_matrix((wprior, (np.arange(n_prior), prior_pos)), shape=(n_prior, F.size))
                Jm = scipy.sparse.vstack([Jm, Jp], format="csr")
            return Jm.toarray() if dense else scipy.sparse.csr_matrix(Jm)

        if schur is not None:
            x, ok, nit_ = schur.solve(xf0, fun, theta_of, wprior, loss, fs, xtol, max_nfev or 200)
            return _Run(x, ok, nit_)
        if engine == "lm":  # the one driver on the reduced vector (dense or sparse step by size)
            out = levenberg_marquardt(ResidualModel(fun, jac, loss=loss, f_scale=fs, step="auto"), xf0,
                                      max_iter=max_nfev or 200, xtol=xtol, ftol=xtol)
            return _Run(out.x, out.converged, out.iterations)
        sol = least_squares(
            fun, xf0, jac=jac, method="trf", x_scale="jac", tr_solver="exact" if dense else "lsmr",
            loss=loss, f_scale=fs, xtol=xtol, ftol=1e-12 if dense else 1e-10, gtol=1e-12,
            max_nfev=max_nfev or max(1000, 2 * F.size))
        return _Run(sol.x, bool(sol.status > 0), int(sol.njev or sol.nfev))

    def sigma_of(f_meas: Array, f_prior: Array) -> float:
        dof = m + n_prior - F.size
        if dof <= 0:
            return float("nan")
        if loss == "linear":
            return float(np.sqrt(((f_meas**2).sum() + (f_prior**2).sum()) / dof))
        return _robust_sigma(f_meas) * float(np.sqrt(m / dof))

    xf = par.x0[F].copy()
    fs = 1.0
    if loss != "linear":
        f0 = meas(theta_of(xf))
        fs = f_scale if f_scale is not None else max(_TUNING[loss] * _robust_sigma(f0), 1e-9)
    # prior weights sigma / std: sigma given, or estimated (start: the fit with the prior
    # coordinates held at their means, i.e. a unit weight on std / sigma_hat = huge)
    if noise is not None:
        sig_w = float(noise)
    elif n_prior:
        sig_w = float(np.min(par.prior_std)) * 1e3  # prior rows dominate: coordinates ~ held
    else:
        sig_w = 1.0
    nit = 0
    conv = False
    passes = 1 if (noise is not None or not n_prior) else 4
    w_used = sig_w
    for k in range(passes):
        w_used = sig_w
        wprior = sig_w / par.prior_std
        sol = run(xf, wprior, fs)
        xf, conv = sol.x, sol.converged
        nit += sol.iterations
        if loss != "linear" and f_scale is None and k == 0:
            # the starting residuals mix geometry error with noise: re-scale on the fitted ones
            f_meas = meas(theta_of(xf))
            shrink = float(np.sqrt(m / max(m - F.size + n_prior, 1)))
            fs = max(_TUNING[loss] * shrink * _robust_sigma(f_meas), 1e-9)
            if passes == 1:
                sol = run(xf, wprior, fs)
                xf, conv = sol.x, sol.converged
                nit += sol.iterations
        if passes > 1:
            f_meas = meas(theta_of(xf))
            est = _sigma_fixed_point(f_meas, (xf[prior_pos] - par.prior_mu) / par.prior_std,
                                     m, n_prior, F.size, loss)
            if not (np.isfinite(est) and est > 0):
                break
            settled = k > 0 and abs(est - sig_w) <= 0.05 * sig_w
            sig_w = est
            if settled:
                break
    sig_w = w_used

    th = theta_of(xf)
    r, s, _, _ = _unpack(th, I, J, d, offsets)
    f = toa_residuals(th, Y, d, offsets)
    if w is not None:
        f = w * f  # the cost, the noise and the covariance are those of the weighted residuals
    wprior = sig_w / par.prior_std
    fp = wprior * (xf[prior_pos] - par.prior_mu) if n_prior else np.zeros(0)
    cost, drho = irls(np.concatenate([f, fp]), loss, fs)
    sigma = sigma_of(f, fp)
    var = sigma**2
    if loss != "linear" and not n_prior and np.isfinite(sigma):
        # the M-estimate's covariance, as refine_toa's (nls._finish): the Gauss-Newton information
        # of the ranges used times selfcal.robust.m_estimator_sigma2, not sigma^2 with the IRLS
        # weights (1.15-1.18x / 1.29-1.34x too small in variance, Gaussian / t3, 10 x 20 with 4 known
        # receivers). With priors their rows' weights are relative to sigma: kept as they were
        drho = np.ones_like(drho)
        var = m_estimator_sigma2(f, np.ones(f.shape, bool), loss, fs, int(F.size))
    if w is not None:
        drho = np.concatenate([drho[:m] * w**2, drho[m:]])  # J^T W J of the weighted rows

    nr, ns = d + has_r, d + has_s
    if (want_r.size or want_s.size) and np.isfinite(sigma):
        Gsol = _residual_gauge(par, con, r, s, offsets)  # the gauge at the solution
        inv = None
        if schur is not None:
            inv = schur.inverse(th, drho, wprior)
        Cr, Cs = _node_covariances(th, Y, d, offsets, par, F, Gsol, TF, prior_pos, wprior, drho,
                                   m, I, J, has_r, has_s, want_r, want_s, inverse=inv)
        Cr, Cs = Cr * var, Cs * var
    else:
        Cr = np.full((I, nr, nr), np.nan)
        Cs = np.full((J, ns, ns), np.nan)
    return _solution(th, Y, d, offsets, Cr, Cs, canonical=not con.has_positions,
                     shift=not con.offsets_constrained, sigma=sigma, converged=conv, iterations=nit, cost=cost,
                     solver="schur-lm-constrained" if schur is not None
                     else ("lm-constrained" if engine == "lm" else "trf-constrained"))


def _sigma_fixed_point(f_meas: Array, zp: Array, m: int, n_prior: int, n_free: int, loss: str) -> float:
    """Noise estimate consistent with its own prior weights.

    With prior rows ``(sigma / std)(x - mu)`` the residual sum of squares is
    ``RSS_meas + sigma^2 sum zp^2`` and its expectation ``sigma^2 (m + n_prior - n_free)``;
    solving for sigma gives ``sigma^2 = RSS_meas / (m - n_free + n_prior - sum zp^2)``.
    """

    dof = m + n_prior - n_free
    if loss != "linear":
        return _robust_sigma(f_meas) * float(np.sqrt(m / max(dof, 1)))
    den = dof - float(zp @ zp)
    if den <= 0.5:
        den = max(m - n_free, 1)
    return float(np.sqrt((f_meas @ f_meas) / den))


class _LuInverse:
    """The pinned inverse of the constrained normal matrix by one sparse LU (``solve``, ``block``)."""

    def __init__(self, th: Array, Y: Array, d: int, offsets: str, TF: scipy.sparse.csc_matrix,
                 prior_pos: NDArray[np.intp], wprior: Array, drho: Array, m: int) -> None:

        Jm = toa_jacobian(th, Y, d, offsets) @ TF
        W = scipy.sparse.diags(drho[:m])
        N = (Jm.T @ W @ Jm).tocsc()
        if prior_pos.size:
            N = N + scipy.sparse.csc_matrix((drho[m:] * wprior**2, (prior_pos, prior_pos)), shape=N.shape)
        try:
            self.lu = scipy.sparse.linalg.splu(N.tocsc())
        except RuntimeError:
            raise DegenerateGeometryError(
                "the normal equations are singular beyond the gauge: the constrained geometry is "
                "degenerate (too few ranges per node, or coplanar points in 3-D)", kind="degenerate-geometry") from None
        du = np.abs(self.lu.U.diagonal())
        if du.min() <= 1e-12 * du.max():
            raise DegenerateGeometryError(
                "the normal equations are numerically singular beyond the gauge: the constrained "
                "geometry is degenerate", kind="degenerate-geometry")
        self.n = N.shape[0]

    def solve(self, B: Array) -> Array:
        return np.asarray(self.lu.solve(B))

    def block(self, cols: NDArray[np.intp]) -> Array:
        E = np.zeros((self.n, cols.size))
        E[cols, np.arange(cols.size)] = 1.0
        return np.asarray(self.lu.solve(E))[cols]


def _node_covariances(
    th: Array, Y: Array, d: int, offsets: str, par: _Param, F: NDArray[np.intp], Gx: Array,
    TF: scipy.sparse.csc_matrix, prior_pos: NDArray[np.intp], wprior: Array, drho: Array,
    m: int, I: int, J: int, has_r: bool, has_s: bool,
    want_r: NDArray[np.intp] | None = None, want_s: NDArray[np.intp] | None = None,
    inverse: Any = None,
) -> tuple[Array, Array]:
    """Node blocks of ``T P (J^T W J)_pinned^-1 P T^T`` (unit noise), (I, nr, nr), (J, ns, ns).

    Only the nodes in ``want_r`` / ``want_s`` (None = all) are solved for (one sparse LU,
    then the columns each requested node touches); the other blocks are NaN. ``inverse``:
    the pinned inverse as an object with ``solve(B)`` and ``block(cols)`` (default a sparse
    LU of the normal matrix, :class:`_LuInverse`; the Schur engine's
    :class:`selfcal.toa.engine.schur_affine.SchurInverse` on its path).
    """

    if inverse is None:
        inverse = _LuInverse(th, Y, d, offsets, TF, prior_pos, wprior, drho, m)
    p = par.x0.size
    pos_of = -np.ones(p, np.intp)
    pos_of[F] = np.arange(F.size)
    gp = Gx.shape[1]
    # C = pinned inverse (zero rows / columns at the pins); Y = C G, Z = G^T C G
    Yg = np.zeros((p, gp))
    if gp:
        Yg[F] = inverse.solve(np.ascontiguousarray(Gx[F]))
    Z = Gx.T @ Yg
    r_idx, s_idx, _ = _node_indices(I, J, d, offsets)
    T = par.T.tocsr()
    out = []
    for idx, want in ((r_idx, want_r), (s_idx, want_s)):
        nn, mm = idx.shape
        want = np.arange(nn) if want is None else np.asarray(want, np.intp)
        blocks = np.full((nn, mm, mm), np.nan)
        blocks[want] = 0.0
        chunk = max(1, 512 // mm)
        for a in range(0, want.size, chunk):
            nodes = want[a : a + chunk]
            sel = idx[nodes]
            Tsub = T[sel.ravel()]
            cols = np.unique(Tsub.indices)
            if cols.size == 0:
                continue
            free = pos_of[cols] >= 0
            fc = pos_of[cols[free]]
            Css = np.zeros((cols.size, cols.size))
            if fc.size:
                Css[np.ix_(free, free)] = inverse.block(fc)  # pinned inverse on the free columns
            if gp:
                Gs, Ys = Gx[cols], Yg[cols]
                Css = Css - Gs @ Ys.T - Ys @ Gs.T + Gs @ Z @ Gs.T
            Ts = Tsub[:, cols]
            TcS = np.asarray(Ts @ Css).reshape(sel.shape[0], mm, cols.size)  # sparse T: O(nnz cols)
            Tc = Ts.toarray().reshape(sel.shape[0], mm, cols.size)
            blocks[nodes] = np.einsum("npc,nrc->npr", TcS, Tc)
        out.append(blocks)
    return out[0], out[1]
