"""Robust structure fits of far-field matrices: the pieces below both the solver and the screen.

:func:`lowrank_fit` (the weighted / robust fit of ``D = P Q^T + 1 c^T``),
:func:`ransac_farfield` (RANSAC over the minimal solver, paper 000's future work), the robust
noise level of a fit and the model's parameter count. :mod:`selfcal.tdoa.screen` (the
gross-error screen) and :mod:`selfcal.tdoa.solve` (the unscreened solve that the screen's
deletion test re-runs on sub-matrices) both build on them.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from .._checks import as_rng
from ..robust import TUNING, mad_std
from .minimal import solve_minimal
from .refine import farfield_residuals, loss_weight

__all__ = ["far_field_parameters", "lowrank_fit", "consensus_prediction", "consensus_model", "ransac_farfield"]

Array = NDArray[np.float64]


def far_field_parameters(m: int, k: int, d: int = 3) -> int:
    """Free parameters of the far-field model on an m x k matrix in d dimensions.

    ``d (m - 1)`` positions (the first at the origin), ``(d - 1) k`` unit directions, ``k``
    offsets, minus the ``d (d - 1) / 2`` rotations: 3(m-1) + 3k - 3 in space (paper 000,
    Theorem 1: a 4 x 6 matrix has exactly as many entries as unknowns).
    """
    return d * (m - 1) + (d - 1) * k + k - d * (d - 1) // 2


def lowrank_fit(
    D: Array,
    W: Array,
    *,
    rank: int = 3,
    loss: str = "linear",
    iterations: int = 50,
    start: Array | None = None,
) -> tuple[Array, float]:
    """Weighted (robust) fit of ``L = P Q^T + 1 c^T`` to D: ``(L, sigma)``; see :func:`_lowrank_factors`."""
    L, sig, _, _ = _lowrank_factors(D, W, rank=rank, loss=loss, iterations=iterations, start=start)
    return L, sig


def _lowrank_factors(
    D: Array,
    W: Array,
    *,
    rank: int = 3,
    loss: str = "linear",
    iterations: int = 50,
    start: Array | None = None,
) -> tuple[Array, float, Array, Array]:
    """Weighted (robust) fit of the far-field structure ``L = P Q^T + 1 c^T`` to D.

    ``P`` (m, rank), ``Q`` (k, rank), ``c`` (k,): the rank-3 factorisation plus one offset
    per column of the model ``D_ij = z_i . n_j + C_j`` without the unit-norm constraints,
    fitted by alternating least squares. Keeping the offsets structured (instead of a
    generic rank-4 fit) leaves no spare component in which a gross entry could hide.

    Parameters
    ----------
    D : (m, k), W : (m, k) weights (0 = missing / rejected).
    rank : rank of ``P Q^T`` (3 for far-field data).
    loss : IRLS loss on the residuals, scaled by the loss's tuning constant
        (:data:`selfcal.robust.TUNING`: 1.345 for Huber) x their robust standard deviation
        (1.4826 MAD x sqrt(entries / residual dof)); robust losses also start from a
        winsorised D (each row of the column-centred matrix clipped to 3 robust spreads).
    start : optional complete (m, k) matrix whose structure starts the iteration
        (default: D with missing entries filled by column means).

    Returns
    -------
    L : (m, k) complete fitted matrix; sigma : robust noise estimate (1.4826 MAD of the
    residuals over used entries, inflated by the residual degrees of freedom); with
    :func:`_lowrank_factors` also returns the factors P (m, rank) and Q (k, rank).
    """
    m, k = D.shape
    obs = W > 0
    D0 = np.where(obs, D, 0.0)
    n_obs = int(obs.sum())
    dof_fac = np.sqrt(n_obs / max(n_obs - rank * (m + k - rank) - k, 1))
    # start: fill missing entries with the column means; with a robust loss, winsorise
    # first so that a gross entry cannot dominate the starting factorisation
    colmean = np.sum(D0 * obs, 0) / np.maximum(obs.sum(0), 1)
    if start is not None:
        F = np.asarray(start, dtype=float)
    elif loss == "linear":
        F = np.where(obs, D0, colmean[None, :])
    else:
        Dn = np.where(obs, D0, np.nan)
        cmed = np.nanmedian(Dn, axis=0, keepdims=True)
        Xc = Dn - cmed
        rmed = np.nanmedian(Xc, axis=1, keepdims=True)
        # high-breakdown spreads only (a row quantile would contain the gross entry itself when
        # the row is short): the row's MAD, floored at half the whole matrix's MAD for rows
        # whose entries barely vary (a position near the median one)
        sc = np.maximum(mad_std(Xc, axis=1, keepdims=True), 0.5 * mad_std(Xc[np.isfinite(Xc)]))
        Xc = np.clip(Xc, rmed - 3.0 * sc, rmed + 3.0 * sc)
        F = np.where(obs, Xc + cmed, cmed)
    c = F.mean(axis=0)
    U, s, Vt = np.linalg.svd(F - c, full_matrices=False)
    P = U[:, :rank] * s[:rank]
    Q = Vt[:rank].T
    Wr = W.astype(float)
    eye_q = 1e-10 * np.eye(rank + 1)
    eye_p = 1e-10 * np.eye(rank)
    ones = np.ones((m, 1))
    for it in range(iterations):
        R = np.where(obs, D0 - P @ Q.T - c, 0.0)
        # robust scale corrected for the fit's degrees of freedom: without the correction
        # the scale shrinks from one iteration to the next and the weights collapse
        sigma = mad_std(R[obs], centre=False) * dof_fac
        if loss != "linear" and sigma > 0:
            Wr = W * loss_weight((R / (TUNING[loss] * sigma)) ** 2, loss)
        Pa = np.hstack([P, ones])
        Hq = np.einsum("ij,ia,ib->jab", Wr, Pa, Pa) + eye_q * (1.0 + np.trace(Pa.T @ Pa))
        Qa = np.linalg.solve(Hq, np.einsum("ij,ij,ia->ja", Wr, D0, Pa)[..., None])[..., 0]
        Q, c = Qa[:, :rank], Qa[:, rank]
        Hp = np.einsum("ij,ja,jb->iab", Wr, Q, Q) + eye_p * (1.0 + np.trace(Q.T @ Q))
        P = np.linalg.solve(Hp, np.einsum("ij,ij,ja->ia", Wr, D0 - c, Q)[..., None])[..., 0]
        if loss == "linear" and np.all(obs) and it >= 1:
            break
    L = P @ Q.T + c
    R = np.where(obs, D0 - L, 0.0)
    sig = mad_std(R[obs], centre=False) * dof_fac
    return L, sig, P, Q


lowrank_fit.__doc__ = _lowrank_factors.__doc__  # one docstring (Parameters / Returns) for both


def consensus_prediction(D: Array, *, iterations: int = 200,
                         rng: np.random.Generator | int | None = None) -> Array | None:
    """The best minimal-sample hypothesis's prediction of the whole matrix (LMedS): (m, k) or None.

    Each hypothesis solves a random 4 x 6 sub-problem (Algorithm 1, batched), extends it to
    every column (``Dbar_j = Z n_j`` on the 3 sampled position differences) and every row
    (least squares over the sampled columns) and is scored by the median absolute residual;
    a sample free of gross errors predicts the clean structure. None when no sample of
    complete entries gives a valid (positive definite B) solution.
    """
    model = consensus_model(D, iterations=iterations, rng=rng)
    if model is None:
        return None
    Z, N, C = model
    P = Z @ N.T + C[None, :]
    return np.where(np.isfinite(P), P, 0.0)


def consensus_model(D: Array, *, iterations: int = 200,
                    rng: np.random.Generator | int | None = None) -> tuple[Array, Array, Array] | None:
    """The far-field model ``(Z (m, 3), N (k, 3), C (k,))`` of the best minimal sample (LMedS), or None.

    The hypothesis of :func:`consensus_prediction` (positions of every row, unit directions and
    offsets of every column) rather than its prediction: a robust start for a far-field fit.
    """
    gen = as_rng(rng)
    D = np.asarray(D, dtype=float)
    m, k = D.shape
    if m < 4 or k < 6:
        return None
    finite = np.isfinite(D)
    rows = np.array([gen.choice(m, 4, replace=False) for _ in range(iterations)])
    cols = np.array([gen.choice(k, 6, replace=False) for _ in range(iterations)])
    sub = D[rows[:, :, None], cols[:, None, :]]
    ok = np.all(np.isfinite(sub), axis=(1, 2))
    sol = solve_minimal(np.where(np.isfinite(sub), sub, 0.0))
    good = np.flatnonzero(ok & sol.valid)
    if good.size == 0:
        return None
    best_med: float = np.inf
    best: tuple[Array, Array, Array] | None = None
    Df = np.where(finite, D, np.nan)
    for h in good:
        r, c = rows[h], cols[h]
        Zs = sol.positions[h]  # (4, 3), relative to row r[0]
        Ns = sol.directions[h]  # (6, 3)
        if not (np.isfinite(Zs).all() and np.isfinite(Ns).all()) or np.linalg.cond(Zs[1:]) > 1e12:
            continue
        # every row: z_i - z_r0 from the sampled columns
        Y = Df[:, c] - Df[r[0], c][None, :]  # (m, 6)
        Zall = np.linalg.lstsq(Ns, np.nan_to_num(Y.T), rcond=None)[0].T
        # every column: n_j from the three sampled position differences, normalised
        Yc = Df[r[1:], :] - Df[r[0], :][None, :]  # (3, k)
        Nall = np.linalg.solve(Zs[1:], np.nan_to_num(Yc)).T
        Nall /= np.maximum(np.linalg.norm(Nall, axis=1, keepdims=True), 1e-300)
        Cj = Df[r[0], :]
        R = Df - Zall @ Nall.T - Cj[None, :]
        med = float(np.nanmedian(np.abs(R)))
        if np.isfinite(med) and med < best_med:
            best_med, best = med, (Zall, Nall, Cj)
    if best is None:
        return None
    Z, N, C = best
    if not (np.isfinite(Z).all() and np.isfinite(N).all()):
        return None
    # offsets of the columns whose sampled reference entry is missing: their median residual
    C = np.where(np.isfinite(C), C, np.nanmedian(Df - Z @ N.T, axis=0))
    if not np.isfinite(C).all():
        return None
    return Z, N, C


def ransac_farfield(
    D: Array,
    *,
    iterations: int = 200,
    threshold: float | None = None,
    rng: np.random.Generator | int | None = None,
) -> NDArray[np.bool_]:
    """RANSAC over the minimal solver (paper 000's future work): (m, k) inlier mask.

    Each hypothesis solves a random 4 x 6 sub-problem (Algorithm 1, batched over all
    hypotheses at once), extends it to every column by solving ``Dbar_j = Z n_j`` on the 3
    sampled position differences and to every row by least squares over the sampled
    columns, and scores it by the median absolute residual (LMedS). The best hypothesis's
    prediction starts a robust (Huber IRLS) structured fit (:func:`lowrank_fit`) of all entries (local optimisation);
    inliers are the entries within ``threshold`` of that fit (default 4 robust standard
    deviations). Missing entries are never inliers.
    """
    gen = as_rng(rng)
    D = np.asarray(D, dtype=float)
    finite = np.isfinite(D)
    pred = consensus_prediction(D, iterations=iterations, rng=gen)
    if pred is None:
        return finite
    # local optimisation: one minimal sample extrapolates poorly to the other rows and
    # columns, so refine the consensus model by a robust (Huber) structured fit of all entries
    # started from it, and threshold against that fit
    L, sig = lowrank_fit(np.where(finite, D, 0.0), finite.astype(float), rank=3, loss="huber", start=pred)
    lim = 4.0 * sig if threshold is None else float(threshold)
    with np.errstate(invalid="ignore"):
        inl = np.asarray(finite & (np.abs(D - L) <= lim))
    return inl


def _robust_sigma(D: Array, Z: Array, N: Array, C: Array, used: NDArray[np.bool_], *, dim: int = 3) -> float:
    """1.4826 MAD of the model residuals, corrected for the model's degrees of freedom."""
    r = farfield_residuals(np.where(used, D, np.nan), Z, N, C)
    n_obs = int(used.sum())
    m, k = D.shape
    g = dim * (dim - 1) // 2
    dof = max(n_obs - (dim * (m - 1) + dim * k - g), 1)
    return mad_std(r[used], centre=False) * float(np.sqrt(n_obs / dof))
