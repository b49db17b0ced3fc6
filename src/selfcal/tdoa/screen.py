"""Gross-error screening and robust structure fits for far-field matrices.

:func:`screen_gross_errors` (the default screen of :func:`~selfcal.tdoa.solve_farfield`),
:func:`lowrank_fit` (the weighted / robust fit of ``D = P Q^T + 1 c^T``) and
:func:`ransac_farfield` (RANSAC over the minimal solver, paper 000's future work).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from .._checks import as_rng
from ..robust import mad_std
from .minimal import solve_minimal
from .refine import farfield_residuals, loss_weight

__all__ = ["screen_gross_errors", "lowrank_fit", "ransac_farfield"]

Array = NDArray[np.float64]


def screen_gross_errors(D: Array, *, factor: float = 20.0) -> NDArray[np.bool_]:
    """Flag gross errors: (m, k) bool mask.

    Column medians remove the offsets C_j. In row i of the centred matrix an entry is gross
    when it lies more than ``factor`` robust spreads from the row median, the spread being
    ``max(1.4826 MAD_i, q90_i / 3, 0.05 q90)`` (q90_i: 90th percentile of the row's absolute
    deviations, q90 the same over the whole matrix). The quantile terms keep rows with
    two-valued or nearly constant data (parallel directions, a position near the median)
    from being flagged; the global term means a gross error must exceed the spread of the
    whole data set. Such entries cannot come from a far-field model with Gaussian noise;
    they are treated as missing.
    """
    X = D - np.nanmedian(D, axis=0, keepdims=True)
    med = np.nanmedian(X, axis=1, keepdims=True)
    dev = np.abs(X - med)
    mad = mad_std(X, axis=1, keepdims=True)
    q_row = np.nanpercentile(dev, 90, axis=1, keepdims=True) / 3.0
    q_all = 0.05 * float(np.nanpercentile(dev, 90))
    scale = np.maximum(np.maximum(mad, q_row), max(q_all, 1e-300))
    with np.errstate(invalid="ignore"):
        return np.asarray(np.isfinite(D) & (dev > factor * scale))


def lowrank_fit(
    D: Array,
    W: Array,
    *,
    rank: int = 3,
    loss: str = "linear",
    iterations: int = 50,
    start: Array | None = None,
) -> tuple[Array, float]:
    """Weighted (robust) fit of the far-field structure ``L = P Q^T + 1 c^T`` to D.

    ``P`` (m, rank), ``Q`` (k, rank), ``c`` (k,): the rank-3 factorisation plus one offset
    per column of the model ``D_ij = z_i . n_j + C_j`` without the unit-norm constraints,
    fitted by alternating least squares. Keeping the offsets structured (instead of a
    generic rank-4 fit) leaves no spare component in which a gross entry could hide.

    Parameters
    ----------
    D : (m, k), W : (m, k) weights (0 = missing / rejected).
    rank : rank of ``P Q^T`` (3 for far-field data).
    loss : IRLS loss on the residuals, scaled by 1.345 x their robust standard deviation
        (1.4826 MAD x sqrt(entries / residual dof)); robust losses also start from a
        winsorised D (each row of the column-centred matrix clipped to 3 robust spreads).
    start : optional complete (m, k) matrix whose structure starts the iteration
        (default: D with missing entries filled by column means).

    Returns
    -------
    L : (m, k) complete fitted matrix; sigma : robust noise estimate (1.4826 MAD of the
    residuals over used entries, inflated by the residual degrees of freedom).
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
        dev = np.abs(Xc - rmed)
        sc = np.maximum(mad_std(Xc, axis=1, keepdims=True),
                        np.nanpercentile(dev, 90, axis=1, keepdims=True) / 3.0)
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
            Wr = W * loss_weight((R / (1.345 * sigma)) ** 2, loss)
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
    return L, mad_std(R[obs], centre=False) * dof_fac


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
    m, k = D.shape
    finite = np.isfinite(D)
    rows = np.array([gen.choice(m, 4, replace=False) for _ in range(iterations)])
    cols = np.array([gen.choice(k, 6, replace=False) for _ in range(iterations)])
    sub = D[rows[:, :, None], cols[:, None, :]]
    ok = np.all(np.isfinite(sub), axis=(1, 2))
    sol = solve_minimal(np.where(np.isfinite(sub), sub, 0.0))
    good = np.flatnonzero(ok & sol.valid)
    if good.size == 0:
        return finite
    best_med, best_R, best_P = np.inf, None, None
    Df = np.where(finite, D, np.nan)
    for h in good:
        r, c = rows[h], cols[h]
        Zs = sol.positions[h]  # (4, 3), relative to row r[0]
        Ns = sol.directions[h]  # (6, 3)
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
        if med < best_med:
            best_med, best_R, best_P = med, R, Zall @ Nall.T + Cj[None, :]
    assert best_R is not None and best_P is not None
    # local optimisation: one minimal sample extrapolates poorly to the other rows and
    # columns, so refine the consensus model by a robust (Huber) structured fit of all entries
    # started from it, and threshold against that fit
    pred = np.where(np.isfinite(best_P), best_P, 0.0)
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
