"""Gross-error screening of far-field matrices.

:func:`gross_error_screen` (the default screen of :func:`~selfcal.tdoa.solve_farfield`). The
robust structure fits it builds on (:func:`~selfcal.tdoa.structure.lowrank_fit`,
:func:`~selfcal.tdoa.structure.ransac_farfield`) live in :mod:`selfcal.tdoa.structure` and the
residuals' tail model the screen's threshold comes from in :mod:`selfcal.tdoa.tails`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from ..robust import mad_std
from .structure import _lowrank_factors
from .tails import TailModel, fit_tail_model

__all__ = ["SCREEN_ALPHA", "LEVERAGE_MAX", "GrossScreen", "entry_leverages", "implausible_entries",
           "gross_error_screen"]

Array = NDArray[np.float64]


#: family-wise false-alarm rate of :func:`gross_error_screen` (probability that a clean
#: matrix with Gaussian noise loses any entry)
SCREEN_ALPHA = 0.01


def implausible_entries(D: Array, *, factor: float = 20.0) -> NDArray[np.bool_]:
    """Entries no far-field matrix with moderate noise can hold: (m, k) bool mask (model-free).

    Column medians remove the offsets C_j. In row i of the centred matrix an entry is flagged
    when it lies more than ``factor`` robust spreads from the row median, the spread being
    ``max(1.4826 MAD_i, q90_i / 3, 0.05 q90)`` (q90_i: 90th percentile of the row's absolute
    deviations, q90 the same over the whole matrix). The quantile terms keep rows with
    two-valued or nearly constant data (parallel directions, a position near the median)
    from being flagged; the global term means a gross error must exceed the spread of the
    whole data set. Only errors far beyond the array's size are caught, and with fewer than
    10 columns the row quantile contains the error itself: :func:`gross_error_screen` adds
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


#: largest number of unknowns for which :func:`gross_error_screen` computes each entry's leverage
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
    (:func:`~selfcal.tdoa.structure.lowrank_fit`, rank ``rank``) to the entries not yet flagged, and an entry is
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
