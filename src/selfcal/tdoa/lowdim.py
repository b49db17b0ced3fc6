"""Planar (d = 2) and linear (d = 1) far-field calibration: the determined part of paper 000's
degenerate cases (section 2.2), and the choice of the dimension (``dim="auto"``)."""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..errors import DegenerateGeometryError, InputError
from ..robust import TUNING as _TUNING
from .covariance import linear_position_covariance
from .degeneracy import DETERMINED as _DETERMINED
from .degeneracy import DegeneracyReport, top_svd
from .initialize import initialize_farfield
from .refine import refine_lm
from .structure import _robust_sigma

__all__: list[str] = []

Array = NDArray[np.float64]


def _effective_dim(dim: int | str, report: DegeneracyReport) -> int:
    """The dimension to solve in: ``dim`` itself, or at "auto" the rank test's verdict.

    A rank-2 matrix whose 2-D quadric is inconsistent (``planar-motion``: directions off the
    positions' plane) has no determined planar solution; 3 is returned so that the caller
    reports it as a degeneracy. Asking for a dimension the data contradict raises.
    """
    rank = int(report.rank)
    sv = ", ".join(f"{v:.3g}" for v in report.singular_values[:4])
    detail = f"numerical rank {rank} (singular values {sv}; noise threshold {report.rank_threshold:.3g})"
    if dim == "auto":
        if rank == 2 and report.kind == "coplanar-directions":
            return 2
        if rank == 1:
            return 1
        return 3
    if dim == 2 and rank == 3:
        raise InputError(
            f"dim=2 but the data are 3-D: {detail}; use dim=3 (or 'auto'; gross errors also raise the rank: "
            "try loss='huber')")
    if dim == 2 and rank == 2 and report.kind == "planar-motion":
        return 3  # reported as planar-motion (not determined) by the caller
    if dim == 2 and rank < 2:
        raise InputError(
            f"dim=2 but the data have {detail}: positions on a line or parallel directions; use dim=1 "
            "(or 'auto')")
    if dim == 1 and rank > 1:
        raise InputError(f"dim=1 but the data have {detail}; use dim={min(rank, 3)} (or 'auto')")
    return int(dim)


def _solve_low_dim(D: Array, X: Array, used: NDArray[np.bool_], d: int, report: DegeneracyReport, *,
                   offsets: str, loss: str, f_scale: float | None, method: str, max_iter: int | None,
                   tol: float | None, cone_tol: float) -> dict[str, Any]:
    """Planar (d = 2) or linear (d = 1) far-field calibration from the complete centred X."""
    m, k = D.shape
    free = offsets == "free"
    if d == 1:
        # rank-1 model D_ij = x_i u_j + C_j: the SVD of the centred (filled) matrix is its least
        # squares fit; |u_j| <= 1 bounds the scale, fixed here at max |u_j| = 1
        U, s, Vt = top_svd(X, 1)
        u = s[0] * Vt[0]
        a = float(np.max(np.abs(u)))
        if a <= 0:
            raise InputError("matrix: every column is constant: no position is observable")
        x = U[:, 0] * a
        x = x - x[0]
        q = u / a
        parallel = report.kind == "parallel-directions"
        pos, dirs = x[:, None], q[:, None]
        C = np.asarray(np.nanmean(np.where(used, D - pos @ dirs.T, np.nan), axis=0))
        if offsets == "reference":
            C = D[0].copy()
        case = "parallel" if parallel else "linear"
        line_cov = linear_position_covariance(D, pos, dirs, C, used.astype(float), scale_free=not parallel)
        return {"positions": pos, "directions": dirs, "offsets": C, "cov": line_cov, "converged": True,
                "iterations": 0, "method": "svd-rank1", "pd": True, "history": [], "case": case,
                "determined": _DETERMINED[case]}
    if k < 3 or m < 3:
        raise DegenerateGeometryError(f"{m} x {k}: planar far-field calibration needs at least 3 positions and "
                                      "3 directions", kind="too-few-sources" if k < 3 else "too-few-receivers")
    # the 2-D analogue of the cone (Theorem 2): the quadric system for B2 is rank deficient when
    # the directions lie on two lines through the origin
    Us, s, Vt = top_svd(X, 2)
    nt = (s[:2, None] * Vt[:2]).T
    a_, b_ = nt[:, 0], nt[:, 1]
    M = np.stack([a_ * a_, b_ * b_, np.sqrt(2.0) * a_ * b_], axis=1)
    _, mu, Wt = np.linalg.svd(M, full_matrices=False)
    om = Wt[-1]
    Om = np.array([[om[0], om[2] / np.sqrt(2.0)], [om[2] / np.sqrt(2.0), om[1]]])
    nu = 2.0 * report.noise_std * float(np.linalg.norm(nt @ Om))
    if k < 4 or mu[-1] / max(nu, 1e-300) < cone_tol:
        raise DegenerateGeometryError(
            f"planar calibration: the {k} directions lie on (at most) two lines through the origin "
            f"(quadric SNR {mu[-1] / max(nu, 1e-300):.3g} < {cone_tol:g}), so B2 in ntilde^T B2 ntilde = 1 is not "
            "determined; add directions from other angles", kind="cone")
    init = initialize_farfield(X, dim=2)
    Z, N = init.positions - init.positions[0], init.directions
    C = np.asarray(np.nanmean(np.where(used, D - Z @ N.T, np.nan), axis=0)) if free else D[0].copy()
    hist: list[float] = []
    cov: Array | None = None
    its, conv, meth = 0, True, "init"
    if method in ("auto", "lm", "alternating"):
        meth = "lm"
        delta = 1.0
        if loss != "linear":
            rob = _robust_sigma(D, Z, N, C, used, dim=2)
            delta = f_scale if f_scale is not None else _TUNING[loss] * max(rob, 1e-12 * (np.nanmax(np.abs(X)) + 1e-300))
        out = refine_lm(D, Z, N, C, mask=used, free_offsets=free, loss=loss, delta=delta,
                        max_iter=max_iter or 200, tol=tol or 1e-12)
        Z, N, C, cov, hist, its, conv = (out.positions, out.directions, out.offsets, out.position_cov,
                                         out.history, out.iterations, out.converged)
    return {"positions": Z, "directions": N, "offsets": C, "cov": cov, "converged": conv, "iterations": its,
            "method": meth, "pd": init.b_positive_definite, "history": hist, "case": "planar",
            "determined": _DETERMINED["planar"]}
