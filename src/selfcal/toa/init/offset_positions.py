"""Positions from offset-free ranges: the last step of the 004 initialiser, and multilateration with an offset."""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..._checks import as_matrix, check_dim
from ...errors import DegenerateGeometryError
from .rank3_model import Array, double_centre

__all__ = ["offset_free_positions", "positions_from_ranges"]


def positions_from_ranges(ranges: Any, dim: int = 3) -> tuple[Array, Array]:
    """Receiver and sender positions from an offset-free, complete (I, J) range matrix.

    Rank-d factorisation of the double-centred squared ranges ``-M/2 = X Y^T`` fixes the
    positions up to an invertible H: ``r_i = H^T x_i`` (r_1 = 0), ``s_j = s_1 + H^{-1} y_j``.
    The first column gives ``|r_i|^2 - 2 r_i^T s_1 = D_i1^2 - D_11^2``, linear in ``L = H H^T``
    and ``b = H s_1`` (the upgrade of Kuang et al. 2013); H = chol(L). Needs
    I-1 >= d(d+3)/2 (9 in 3-D, 5 in 2-D); otherwise the roles of receivers and senders are
    swapped. The result is a starting point for the NLS refinement, not a final estimate.
    """
    dim = check_dim(dim)
    D = as_matrix(ranges, "ranges", allow_nan=False, min_shape=(2, 2))
    need = dim * (dim + 3) // 2
    I, J = D.shape
    if I - 1 < need:
        if J - 1 >= need:
            s, r = positions_from_ranges(D.T, dim)
            return r, s
        raise DegenerateGeometryError(
            f"{I} x {J} ranges: the linear position upgrade needs at least {need + 1} receivers or senders "
            f"in {dim}-D; add units or give solve_toa an initial geometry",
            kind="too-few-units",
        )
    M = double_centre(D * D)
    U, s, Vt = np.linalg.svd(-0.5 * M, full_matrices=False)
    X = U[:, :dim] * np.sqrt(s[:dim])
    Y = Vt[:dim].T * np.sqrt(s[:dim])
    rhs = D[1:, 0] ** 2 - D[0, 0] ** 2
    iu = np.triu_indices(dim)
    quad = np.stack([X[:, a] * X[:, b] * (1.0 if a == b else 2.0) for a, b in zip(*iu, strict=True)], axis=1)
    sol, *_ = np.linalg.lstsq(np.hstack([quad, -2 * X]), rhs, rcond=None)
    L = np.zeros((dim, dim))
    L[iu] = sol[: len(iu[0])]
    L = L + np.triu(L, 1).T
    w, V = np.linalg.eigh(L)
    w = np.maximum(w, 1e-9 * max(float(w.max()), 1e-12))  # noise can make L indefinite: nearest PD
    L = (V * w) @ V.T
    H = np.linalg.cholesky(L)
    b = sol[len(iu[0]):]
    s1 = np.linalg.solve(H, b)
    receivers = np.vstack([np.zeros(dim), X @ H])
    sources = s1[None, :] + np.linalg.solve(H, Y.T).T
    sources = np.vstack([s1, sources])
    return receivers, sources


def _locate_with_offset(anchors: Array, rho: Array) -> tuple[Array, float] | None:
    """Point x and offset b with ``rho_k = |x - a_k| + b`` from >= d+2 anchors, linear (Bancroft form).

    Squaring ``rho_k - b = |x - a_k|`` gives ``rho_k^2 - |a_k|^2 = -2 a_k^T x + 2 rho_k b + w``
    with ``w = |x|^2 - b^2``: linear in (x, b, w); exact on noise-free data when the
    (d+2)-column system has full rank.
    """
    n, d = anchors.shape
    if n < d + 2:
        return None
    A = np.column_stack([-2.0 * anchors, 2.0 * rho, np.ones(n)])
    y = rho * rho - np.einsum("kd,kd->k", anchors, anchors)
    sol, _, rank, _ = np.linalg.lstsq(A, y, rcond=None)
    if rank < d + 2 or not np.isfinite(sol).all():
        return None
    return sol[:d], float(sol[d])


def _range_rms(D: Array, observed: NDArray[np.bool_], receivers: Array, sources: Array) -> float:
    """RMS of ``D_ij - |r_i - s_j|`` over the observed entries; inf for a non-finite geometry."""
    if not (np.isfinite(receivers).all() and np.isfinite(sources).all()):
        return float("inf")
    pred = np.linalg.norm(receivers[:, None, :] - sources[None, :, :], axis=-1)
    res = (D - pred)[observed]
    return float(np.sqrt(np.mean(res * res))) if res.size else float("inf")


def offset_free_positions(
    D: Array, missing: NDArray[np.bool_], dim: int, *, rng: np.random.Generator | int | None = None
) -> tuple[Array, Array]:
    """Positions from the offset-corrected ranges ``D = t - delta_i - tau_j`` (the last step of the init).

    Candidates: the linear upgrade :func:`positions_from_ranges` on the completed matrix
    (then up to 5 re-completions of the missing entries from the current geometry, each
    kept only if it lowers the misfit), and the 003 initialisers
    (:func:`selfcal.toa.init.mds.initialize_toa_info`) on the observed entries. The candidate
    with the smallest RMS of ``D_ij - |r_i - s_j|`` over the observed entries wins.

    Why several: the linear upgrade solves for ``L = H H^T`` from the squared norms of one
    side, which is (near-)singular when that side lies near a quadric, e.g. a plane
    (microphones on stems at one height, loudspeakers on flat desks): clamping an
    indefinite L then returns positions of 1e6-1e36 m. Those are scored (inf or huge misfit)
    and lose against the MDS family, which has no such degeneracy.

    Parameters
    ----------
    D : (I, J) metres, complete (missing entries completed by the rank-d fit).
    missing : (I, J) bool, the entries that were not measured.
    dim : 2 or 3.
    rng : seed or Generator for the randomised initialisers.

    Returns
    -------
    receivers (I, d), sources (J, d), metres, in an arbitrary gauge.
    """
    observed = ~missing
    cands: list[tuple[float, Array, Array]] = []
    try:
        r, s = positions_from_ranges(np.abs(D), dim)
        score = _range_rms(D, observed, r, s)
        for _ in range(5 if missing.any() else 0):
            # with noise a completed entry can be poorly determined by the rank alone: replace
            # the completed entries by the distances of the current geometry and re-solve
            pred = np.linalg.norm(r[:, None, :] - s[None, :, :], axis=-1)
            r2, s2 = positions_from_ranges(np.abs(np.where(missing, pred, D)), dim)
            score2 = _range_rms(D, observed, r2, s2)
            if not score2 < score:
                break
            r, s, score = r2, s2, score2
        cands.append((score, r, s))
    except (DegenerateGeometryError, np.linalg.LinAlgError):
        pass
    if not cands or not cands[0][0] <= 1e-9 * (1.0 + float(np.abs(D[observed]).max())):
        from . import mds

        try:
            info = mds.initialize_toa_info(np.where(observed, np.abs(D), np.nan), dim, rng=rng)
            cands.append((info.residual_rms, info.receivers, info.sources))
        except DegenerateGeometryError:
            pass
    if not cands:
        raise DegenerateGeometryError(
            "no position initialiser produced a finite geometry from the offset-corrected ranges",
            kind="init-failed",
        )
    _, receivers, sources = min(cands, key=lambda c: c[0])
    return receivers, sources
