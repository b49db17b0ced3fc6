"""Gross-error screening and robust structure fits for far-field matrices.

:func:`screen_gross_errors` (the default screen of :func:`~selfcal.tdoa.solve_farfield`),
:func:`lowrank_fit` (the weighted / robust fit of ``D = P Q^T + 1 c^T``) and
:func:`ransac_farfield` (RANSAC over the minimal solver, paper 000's future work). The residuals' tail model the
screen's threshold comes from is :mod:`selfcal.tdoa.tails` (re-exported here).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from .._checks import as_rng
from ..robust import TUNING, mad_std
from .minimal import solve_minimal
from .refine import farfield_residuals, loss_weight
from .tails import TAIL_CONFIDENCE, TAIL_DOF_GRID, TailModel, fit_tail_model

__all__ = ["SCREEN_ALPHA", "LEVERAGE_MAX", "TAIL_DOF_GRID", "TAIL_CONFIDENCE", "TailModel", "fit_tail_model", "GrossScreen", "entry_leverages", "far_field_parameters",
           "implausible_entries", "gross_error_screen", "screen_gross_errors", "lowrank_fit", "consensus_model",
           "ransac_farfield"]

Array = NDArray[np.float64]


#: family-wise false-alarm rate of :func:`screen_gross_errors` (probability that a clean
#: matrix with Gaussian noise loses any entry)
SCREEN_ALPHA = 0.01


def far_field_parameters(m: int, k: int, d: int = 3) -> int:
    """Free parameters of the far-field model on an m x k matrix in d dimensions.

    ``d (m - 1)`` positions (the first at the origin), ``(d - 1) k`` unit directions, ``k``
    offsets, minus the ``d (d - 1) / 2`` rotations: 3(m-1) + 3k - 3 in space (paper 000,
    Theorem 1: a 4 x 6 matrix has exactly as many entries as unknowns).
    """
    return d * (m - 1) + (d - 1) * k + k - d * (d - 1) // 2


def implausible_entries(D: Array, *, factor: float = 20.0) -> NDArray[np.bool_]:
    """Entries no far-field matrix with moderate noise can hold: (m, k) bool mask (model-free).

    Column medians remove the offsets C_j. In row i of the centred matrix an entry is flagged
    when it lies more than ``factor`` robust spreads from the row median, the spread being
    ``max(1.4826 MAD_i, q90_i / 3, 0.05 q90)`` (q90_i: 90th percentile of the row's absolute
    deviations, q90 the same over the whole matrix). The quantile terms keep rows with
    two-valued or nearly constant data (parallel directions, a position near the median)
    from being flagged; the global term means a gross error must exceed the spread of the
    whole data set. Only errors far beyond the array's size are caught, and with fewer than
    10 columns the row quantile contains the error itself: :func:`screen_gross_errors` adds
    the model-based test.
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


#: largest number of unknowns for which :func:`screen_gross_errors` computes each entry's leverage
#: (a dense pseudo-inverse, O(p^3)); above, every entry gets the mean leverage p / n
LEVERAGE_MAX = 300


#: the far-field model's own test (:mod:`~selfcal.tdoa.deletion`) runs on matrices of at most this
#: many observed entries whose structure keeps fewer than half of them spare; the others get the
#: structure's residual test. A cost bound: a suspect matrix costs m + k leave-one-out fits and a
#: dense SVD of the (n, 3 (m + k)) Jacobian per flagged entry (about 0.3 s CPU at 20 x 6)
MODEL_TEST_MAX = 200


def entry_leverages(P: Array, Q: Array, W: Array) -> Array:
    """Leverage ``h_ij = g_ij^T (J^T W J)^+ g_ij`` of every entry in the fit of ``P Q^T + 1 c^T``: (m, k).

    ``g_ij`` is the gradient of ``L_ij = P_i . Q_j + c_j`` in (P, Q, c). For an entry in the
    least-squares fit (W_ij = 1) the residual variance is ``sigma^2 (1 - h_ij)``; for one left
    out, the prediction error variance is ``sigma^2 (1 + h_ij)``. The pseudo-inverse removes
    the GL(rank) gauge of the factorisation.
    """
    m, r = P.shape
    k = Q.shape[0]
    Pa = np.hstack([P, np.ones((m, 1))])
    q = r + 1
    npar = m * r + k * q
    H = np.zeros((npar, npar))
    Hpp = np.einsum("ij,ja,jb->iab", W, Q, Q)
    Hqq = np.einsum("ij,ia,ib->jab", W, Pa, Pa)
    Hpq = W[:, :, None, None] * Q[None, :, :, None] * Pa[:, None, None, :]  # (m, k, r, q)
    idx_p = np.arange(m)
    idx_q = np.arange(k)
    H[: m * r, : m * r].reshape(m, r, m, r)[idx_p, :, idx_p, :] = Hpp
    H[m * r:, m * r:].reshape(k, q, k, q)[idx_q, :, idx_q, :] = Hqq
    H[: m * r, m * r:] = Hpq.transpose(0, 2, 1, 3).reshape(m * r, k * q)
    H[m * r:, : m * r] = H[: m * r, m * r:].T
    Hi = np.linalg.pinv(H, rcond=1e-10, hermitian=True)
    A = Hi[: m * r, : m * r].reshape(m, r, m, r)[idx_p, :, idx_p, :]  # (m, r, r)
    Cq = Hi[m * r:, m * r:].reshape(k, q, k, q)[idx_q, :, idx_q, :]  # (k, q, q)
    B = Hi[: m * r, m * r:].reshape(m, r, k, q).transpose(0, 2, 1, 3)  # (m, k, r, q)
    h = (np.einsum("ja,iab,jb->ij", Q, A, Q) + 2.0 * np.einsum("ja,ijab,ib->ij", Q, B, Pa)
         + np.einsum("ia,jab,ib->ij", Pa, Cq, Pa))
    return np.asarray(np.clip(h, 0.0, 1.0))


def _redundant(used: NDArray[np.bool_], n_fit: int, rank: int) -> bool:
    """Enough redundancy for the residual test: at least a third of the kept entries are residual
    degrees of freedom (mean leverage <= 2/3), every column keeps 2 entries and every row ``rank``."""
    n = int(used.sum())
    return bool(n - n_fit >= n / 3.0 and (used.sum(axis=0) >= 2).all() and (used.sum(axis=1) >= rank).all())


@dataclass(frozen=True)
class GrossScreen:
    """Outcome of :func:`gross_error_screen`.

    mask : (m, k) entries found gross; untestable : (m, k) observed entries that cannot be
    checked (too few spare measurements: an error as large as the array could pass, see
    :mod:`~selfcal.tdoa.deletion`); method : ``"structure"`` (the residual test below),
    ``"model"`` (the far-field model's deletion test of small matrices) or ``"pre-screen"``
    (only the model-free stage ran); rule : the test and its false-alarm rate, in words.
    """

    mask: NDArray[np.bool_]
    untestable: NDArray[np.bool_]
    method: str
    rule: str = ""

    @property
    def message(self) -> str:
        """One line about the untestable entries ('' when every entry could be checked)."""
        n = int(self.untestable.sum())
        if n == 0:
            return ""
        return (f"{n} entries cannot be checked for gross errors: too few spare measurements (an error as "
                "large as the array could pass unnoticed in them); add receivers or transmitters")


def screen_gross_errors(
    D: Array,
    *,
    alpha: float = SCREEN_ALPHA,
    rank: int = 3,
    noise_std: float | None = None,
    factor: float = 20.0,
    rounds: int = 4,
    tail: str = "fitted",
) -> NDArray[np.bool_]:
    """Flag gross errors with a stated false-alarm rate: (m, k) bool mask (:func:`gross_error_screen`)."""
    return gross_error_screen(D, alpha=alpha, rank=rank, noise_std=noise_std, factor=factor, rounds=rounds,
                              tail=tail).mask


def gross_error_screen(
    D: Array,
    *,
    alpha: float = SCREEN_ALPHA,
    rank: int = 3,
    noise_std: float | None = None,
    factor: float = 20.0,
    rounds: int = 4,
    tail: str = "fitted",
    model_test: bool = True,
) -> GrossScreen:
    """Flag gross errors with a stated false-alarm rate; say which entries cannot be checked.

    Two stages. (1) :func:`implausible_entries`, the model-free pre-screen (errors far beyond
    the array's size), so that they cannot spoil the fit of stage 2. (2) A residual test
    against the far-field structure: the least-squares fit ``L`` of ``D = P Q^T + 1 c^T``
    (:func:`lowrank_fit`, rank ``rank``) to the entries not yet flagged, and an entry is
    gross when

    ``|D_ij - L_ij| > s t sqrt(1 -/+ h)``,  ``t = T_nu^-1(1 - alpha / (2 n))``

    (Bonferroni over the n observed entries; ``h`` the entry's leverage in the least-squares
    fit of the kept entries, :func:`entry_leverages`, or the mean leverage above
    :data:`LEVERAGE_MAX` unknowns; ``1 - h`` for an entry in the fit, ``1 + h`` for one left
    out, whose residual is a prediction error). The scale ``s`` and the tail ``nu`` are
    fitted to the studentised residuals (``tail="fitted"``, the default:
    :func:`fit_tail_model`, a Student-t plus a uniform gross part over the array's extent,
    ``nu`` the lower 95 % confidence bound), so the quantile is that of the tail the data
    have, not a Gaussian one: real delay residuals (GCC-PHAT) have t tails of 5-8 dof, whose
    extreme quantiles a Gaussian rule at the same ``alpha`` puts 1.3 % of a real file's entries
    beyond (issue 31). ``tail="gaussian"`` (or a given ``noise_std``) is the Gaussian rule,
    ``t = Phi^-1(1 - alpha / (2 n))`` with sigma = ``noise_std`` or 1.4826 MAD. The first fit
    is robust (Cauchy IRLS, or least squares where that is sharper, e.g. exact data): a
    least-squares fit smeared by one large error has heavy-tailed residuals that would hide
    it. The fit is repeated without the flagged entries until the flags
    stop changing (at most ``rounds`` fits): a gross entry set aside no longer pulls the fit,
    and a clean one flagged next to it is given back. (Where the redundancy test below
    passes, one spike cannot be absorbed by the rank-``rank`` fit; in smaller matrices it
    can, and the far-field model's own test below takes over.)

    False-alarm rate: a clean matrix loses any entry with probability <= ``alpha`` when the
    noise is i.i.d. Student-t with the fitted dof or more, or lighter-tailed (Laplace,
    Gaussian); checked with t_3, t_5, Laplace and Gaussian noise over many seeds in
    ``tests/tdoa/test_screen_tails.py`` (measured 0 of 25 clean draws per case in
    ``benchmarks/farfield_screens.py``, where the Gaussian rule flags 40-100 % of heavy-tailed
    12 x 24 and 30 x 60 matrices). A gross error
    is caught when it exceeds about ``s t`` plus what the fit absorbs of it. The residual
    test needs redundancy: it runs when at least a third of the entries are residual degrees
    of freedom of the fit (``n - rank (m + k - rank) - k >= n / 3``, e.g. 12 x 12 or 10 x 30
    in space). Where fewer than half the entries are spare for the structure (5 x 7, 8 x 9,
    20 x 6, 12 x 12, ...; at most :data:`MODEL_TEST_MAX` entries) and in space, the deletion
    test of :mod:`~selfcal.tdoa.deletion` runs instead (the structure test when the far-field
    model cannot be fitted, e.g. a planar array): each entry against the far-field model proper
    (unit directions: ``k - 3`` fewer unknowns than the structure), one candidate at a time,
    with its own redundancy ``1 - h_ij``; entries whose redundancy is ~0 (every entry of the
    minimal 4 x 6 problem, which any matrix fits exactly) are reported as ``untestable``.

    Parameters
    ----------
    D : (m, k) relative distances (metres), NaN = missing.
    alpha : family-wise false-alarm rate (default :data:`SCREEN_ALPHA`).
    rank : dimension of the model (3 in space; 2 or 1 for planar / linear arrays).
    noise_std : known noise standard deviation (metres) or None (estimated).
    factor : threshold of the pre-screen, in robust spreads.
    rounds : most fits of stage 2.
    tail : ``"fitted"`` (default) or ``"gaussian"`` (the rule before issue 31, for comparison).
    model_test : let small matrices take the far-field model's deletion test (default).

    Returns
    -------
    GrossScreen: ``mask`` (m, k) bool, True = gross (treated as missing by the solver),
    ``untestable`` (m, k) bool, ``method``.

    Examples
    --------
    A +1 m error in a 5 cm array of 12 microphones with 12 transmitters:

    >>> import numpy as np
    >>> rng = np.random.default_rng(0)
    >>> Z = rng.uniform(-0.025, 0.025, (12, 3))
    >>> N = rng.normal(size=(12, 3))
    >>> N /= np.linalg.norm(N, axis=1, keepdims=True)
    >>> D = Z @ N.T + rng.normal(size=12) + 1e-4 * rng.standard_normal((12, 12))
    >>> D[3, 4] += 1.0
    >>> np.argwhere(gross_error_screen(D).mask).tolist()
    [[3, 4]]
    """
    from scipy.stats import norm
    from scipy.stats import t as student

    if tail not in ("fitted", "gaussian"):
        from ..errors import InputError

        raise InputError(f"tail must be 'fitted' or 'gaussian', got {tail!r}")
    gaussian = tail == "gaussian" or noise_std is not None
    D = np.asarray(D, dtype=float)
    finite = np.isfinite(D)
    pre = implausible_entries(D, factor=factor)
    m, k = D.shape
    n_all = int(finite.sum())
    none = np.zeros((m, k), dtype=bool)
    if n_all == 0:
        return GrossScreen(pre, none, "pre-screen", "model-free pre-screen only (errors far beyond the array; too few spare measurements for a residual test)")
    t = float(norm.isf(alpha / (2.0 * n_all)))
    used = finite & ~pre
    n = int(used.sum())
    n_fit = rank * (m + k - rank) + k  # unknowns of the least-squares fit below
    if model_test and rank == 3 and m >= 4 and k >= 6 and n <= MODEL_TEST_MAX and n - n_fit < n / 2.0:
        # the far-field model's own test where the structure keeps fewer than half the entries
        # spare: there the model's k - 3 extra spare measurements (unit directions) are a large
        # share of the redundancy (5 x 7: 5 against 1; 20 x 6: 48 against 45, and the structure's
        # fit of its 6 columns is easily pulled by one large error)
        from .deletion import deletion_screen

        dele = deletion_screen(D, used, alpha=alpha, noise_std=noise_std, tail="gaussian" if gaussian else tail)
        if dele.tested or not _redundant(used, n_fit, rank):
            rule = (f"far-field model deletion test, Bonferroni at {alpha:g} family-wise against "
                    + ("a Gaussian null" if gaussian else "a unit-variance t_3 null (false-alarm rate <= "
                       f"{alpha:g} for noise tails of 3 dof or lighter)") if dele.tested else "model-free pre-screen only (errors far beyond the array; too few spare measurements for a residual test)")
            return GrossScreen(pre | dele.flags, dele.untestable, "model" if dele.tested else "pre-screen", rule)
    if not _redundant(used, n_fit, rank):
        return GrossScreen(pre, used, "pre-screen", "model-free pre-screen only (errors far beyond the array; too few spare measurements for a residual test)")
    flags = pre.copy()
    untestable = none
    extent = float(np.max(np.abs(np.where(finite, D - np.nanmean(D, axis=0, keepdims=True), 0.0)))) + 1e-300
    verified = False
    # then least squares on the entries kept, every entry tested against it, until the flags settle:
    # excluded entries cannot pull the fit, and clean ones flagged by the rough start come back
    # A large error pulls the least-squares fit and hides among the flags it causes (20 x 6, +1 m on
    # a 5 cm array: 14 clean entries flagged, the gross one not): when the first least-squares
    # round flags anything, its flags are replaced by those of a robust (Cauchy) fit, and the
    # least-squares rounds go on from there. Clean data never take the robust round.
    # With the fitted tail the first round is always robust: a least-squares fit smeared by a large
    # error has heavy-tailed residuals, and the tail fitted to them would hide the error itself.
    robust_round = not gaussian
    model: TailModel | None = None
    for _ in range(max(int(rounds), 1) + 1):
        used = finite & ~flags
        n = int(used.sum())
        if not _redundant(used, n_fit, rank):
            break
        W = used.astype(float)
        L, _, P, Q = _lowrank_factors(D, W, rank=rank, loss="cauchy" if robust_round else "linear")
        if robust_round and not gaussian:
            # of the robust and the least-squares fit, the one with the smaller robust residual
            # scale (a gross error smears the least-squares residuals; on exact or nearly exact data
            # the least-squares fit is the sharper one)
            L2, _, P2, Q2 = _lowrank_factors(D, W, rank=rank, loss="linear")
            fl = 1e-9 * float(np.max(np.abs(L2 - L2.mean(axis=0))))  # the rounding level, as below
            if max(mad_std((D - L2)[used], centre=False), fl) <= max(mad_std((D - L)[used], centre=False), fl):
                L, P, Q = L2, P2, Q2
        h_raw = entry_leverages(P, Q, W) if n_fit <= LEVERAGE_MAX else np.full((m, k), min(n_fit / n, 1.0))
        h = np.minimum(h_raw, 0.99)
        res = np.abs(np.where(finite, D, 0.0) - L)
        stud_sd = np.where(used, np.sqrt(1.0 - h), np.sqrt(1.0 + h))
        floor = 1e-9 * float(np.max(np.abs(L - L.mean(axis=0))))  # the rounding level of the fit
        if gaussian:
            # robust sigma from the studentised residuals of the kept entries
            sigma = float(noise_std) if noise_std is not None else float(
                mad_std((res / np.sqrt(1.0 - h))[used], centre=False))
            sigma = max(sigma, floor)
            thr, power = t * sigma, 0.8416 * sigma
        else:
            # scale and tail of every residual tested (kept ones and predictions alike; the gross
            # ones go to the model's uniform part), then the Bonferroni quantile of that t
            model = fit_tail_model((res / stud_sd)[finite & ~pre], span=extent)
            sigma = max(model.scale, floor)
            thr = sigma * float(student.isf(alpha / (2.0 * n_all), model.dof))
            power = sigma * float(student.isf(0.2, model.dof))
        if not sigma > 0:
            break
        # minimal detectable bias (80 % power) beyond the array's extent: the entry cannot be checked
        untestable = used & (thr + power > extent * np.sqrt(np.clip(1.0 - h_raw, 0.0, 1.0)))
        with np.errstate(invalid="ignore"):
            new = pre | (finite & ~untestable & (res > thr * stud_sd))
        if gaussian and not verified and not robust_round and (new & ~pre).any():
            robust_round = True  # redo this round robustly (flags unchanged)
            continue
        verified = True
        robust_round = False
        if np.array_equal(new, flags):
            break
        flags = new
    if not verified:
        return GrossScreen(pre, used, "pre-screen", "model-free pre-screen only (errors far beyond the array; too few spare measurements for a residual test)")
    if gaussian or model is None:
        rule = (f"structure residual test, Bonferroni at {alpha:g} family-wise, Gaussian quantile (false-alarm "
                "rate holds for Gaussian noise only)")
    else:
        rule = (f"structure residual test, Bonferroni at {alpha:g} family-wise against the fitted tail: "
                f"{model.describe()}; false-alarm rate <= {alpha:g} for {model.tails_covered()}")
    return GrossScreen(np.asarray(flags), untestable & ~flags, "structure", rule)


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
