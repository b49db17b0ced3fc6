"""The block jackknife's scale of a fit's receiver covariances (measured ranges are not white).

Range errors along a flight are serially correlated and depend on where the tag is, so the
model covariance of a fit is too small on measured UWB ranges. :func:`block_jackknife_scale`
refits without each of K contiguous column blocks (the folds of :mod:`selfcal.toa.verdict.crossval`)
and scales each receiver's covariance by ``max(1, tr(C^-1 V) / d)``, ``V`` the jackknife
covariance; used by :func:`selfcal.toa.frame.known.fit_known` through
:mod:`selfcal.toa.frame.error_scale`.
"""

from __future__ import annotations

import dataclasses
import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ...errors import ConvergenceWarning, DegenerateGeometryError, InputError
from .crossval import _REFIT, _folds, located_block

__all__ = ["JackknifeScale", "bias_effect", "block_jackknife_scale", "jackknife_blind_fit", "scaled_receiver_cov"]

Array = NDArray[np.float64]


@dataclass(frozen=True)
class JackknifeScale:
    """Per-receiver covariance scale from the block jackknife (:func:`block_jackknife_scale`).

    Attributes
    ----------
    scale : (I,) array
        Factor applied to each receiver's covariance, ``max(1, ratio)`` (1 for receivers
        the fit holds fixed or that have no covariance).
    ratio : (I,) array
        ``tr(C_i^-1 V_i) / d``: the jackknife covariance ``V_i`` in units of the model's
        ``C_i`` (about 1 when the model's noise description is right; NaN where undefined).
    folds : int
        K, the number of column blocks.
    correlation_length : int
        Residual correlation length (columns) behind K.
    bias_tau : float, optional
        Set by :func:`selfcal.toa.frame.known.fit_known` when it adds the random effect of
        per-receiver biases the model does not hold: their estimated std (m).
    """

    scale: Array
    ratio: Array
    folds: int
    correlation_length: int
    bias_tau: float | None = None

    def to_dict(self, names: Sequence[str] | None = None) -> dict[str, Any]:
        """JSON-safe dictionary (per-receiver values keyed by ``names``, default ``r<i>``)."""
        keys = list(names) if names is not None else [f"r{i}" for i in range(len(self.scale))]
        return {"estimator": "block jackknife over contiguous column blocks, covariance scaled by "
                             "max(1, tr(C^-1 V) / d)",
                "folds": self.folds, "correlation_length": self.correlation_length,
                "scale": {k: float(v) for k, v in zip(keys, self.scale, strict=True)},
                "ratio": {k: (None if not np.isfinite(v) else float(v)) for k, v in zip(keys, self.ratio, strict=True)},
                "bias_tau": self.bias_tau}


def block_jackknife_scale(residuals: Array, receivers: Array, receiver_cov: Array,
                          refit: Any, *, folds: int | None = None) -> JackknifeScale | None:
    """How much larger the receivers' error is than their model covariance says: block jackknife.

    The model covariance ``C = sigma^2 (J^T J)^-1`` of a least-squares fit assumes errors
    independent from range to range with one variance. Measured UWB ranges break both: errors
    are serially correlated along a moving tag's path and depend on where the tag is
    (antenna patterns, NLOS stretches, multipath), so a receiver's stated standard deviation
    can be several times smaller than its error (LPS flights with known anchors: 2-8x).
    The delete-a-block jackknife (Kunsch 1989; Efron & Stein 1981) needs neither assumption:
    the fit is repeated ``K`` times, each time without one contiguous block of columns (the
    blocks of :func:`cross_validate`, longer than the residual correlation length), and

        ``V_i = (K - 1) / K * sum_k (r_i^(k) - mean_k r_i^(k)) (.)^T``

    estimates the covariance of receiver ``i``. ``V_i`` from ``K <= 10`` blocks is noisy
    (about ``d (K - 1)`` degrees of freedom), so it is not used as the covariance itself: the
    model's ``C_i`` (its shape well determined) is scaled by ``max(1, tr(C_i^-1 V_i) / d)``.
    Under the model the ratio is 1 within its sampling spread and the scale stays near 1 (the
    ``max`` makes the stated regions slightly conservative); where the data vary more from block
    to block than the model says, the error bars grow by what the data show.
    What the jackknife cannot see is an error common to every block (a constant per-anchor
    ranging bias the model does not hold): that is the bias model's job
    (:func:`choose_receiver_offsets`).

    Parameters
    ----------
    residuals : (I, J) array
        The fit's residuals (NaN = not used), columns in time order for a moving tag: sets
        the block length.
    receivers : (I, d) array
        The fit's receivers.
    receiver_cov : (I, d, d) array
        Their model covariances (zero for receivers the fit holds fixed).
    refit : callable
        ``refit(columns) -> (I, d) receivers``: the same fit, started from this one, on the
        columns ``columns`` (a boolean (J,) mask) only; may raise
        :class:`~selfcal.errors.DegenerateGeometryError` / :class:`ValueError`.
    folds : int, optional
        K (default from the residual correlation length, as in :func:`cross_validate`).

    Returns
    -------
    JackknifeScale or None
        None when a block's refit fails (the covariance is then left as the model's).

    Examples
    --------
    >>> import numpy as np
    >>> from selfcal.toa.engine.nls import refine_toa
    >>> g = np.random.default_rng(1)
    >>> R, S = g.uniform(0, 5, (6, 3)), g.uniform(1, 4, (200, 3))
    >>> Y = np.linalg.norm(R[:, None] - S[None], axis=2) + 0.02 * g.standard_normal((6, 200))
    >>> fit = refine_toa(Y, R, S, fixed_receivers=np.arange(6) < 4)
    >>> refit = lambda c: refine_toa(Y[:, c], fit.receivers, fit.sources[c], fixed_receivers=np.arange(6) < 4,
    ...                              covariance=False).receivers
    >>> js = block_jackknife_scale(fit.residuals, fit.receivers, fit.receiver_cov, refit)
    >>> js.folds, bool(np.all(js.scale[:4] == 1)), bool(np.all(js.ratio[4:] < 3))
    (10, True, True)
    """
    from .offset_fit import residual_correlation_length

    E = np.asarray(residuals, float)
    R = np.asarray(receivers, float)
    C = np.asarray(receiver_cov, float)
    I, d = R.shape
    J = E.shape[1]
    L = residual_correlation_length(E)
    edges = np.linspace(0, J, int(folds) + 1).round().astype(np.intp) if folds else _folds(J, L)
    K = len(edges) - 1
    fails = (DegenerateGeometryError, InputError, np.linalg.LinAlgError, ValueError)
    reps = []
    for k in range(K):
        cols = np.ones(J, bool)
        cols[edges[k]:edges[k + 1]] = False
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", ConvergenceWarning)
                reps.append(np.asarray(refit(cols), float))
        except fails:
            return None
    X = np.array(reps)  # (K, I, d)
    D = X - X.mean(axis=0)
    V = (K - 1) / K * np.einsum("kia,kib->iab", D, D)
    ratio = np.full(I, np.nan)
    for i in range(I):
        tr = np.trace(C[i]) if np.isfinite(C[i]).all() else 0.0
        if tr <= 0 or not np.isfinite(V[i]).all():
            continue
        # tr(C^-1 V) / d on the subspace C spans (a receiver fixed along some axes has C singular there)
        ratio[i] = float(np.trace(np.linalg.pinv(C[i], rcond=1e-10, hermitian=True) @ V[i])) / np.linalg.matrix_rank(
            C[i], hermitian=True)
    scale = np.where(np.isfinite(ratio), np.maximum(ratio, 1.0), 1.0)
    return JackknifeScale(scale, ratio, K, int(L))


def jackknife_blind_fit(res: Any, sub: Array, scale: float = 1.0) -> tuple[Any, JackknifeScale | None]:
    """A blind moving-tag fit with its receivers' covariances scaled by the block jackknife.

    The same estimator as :func:`block_jackknife_scale` for a fit without known nodes: each
    refit (the fit's own offset model, started from it, without one contiguous block of tag
    positions) is moved onto the fit's receivers by the best rigid motion (Kabsch, no
    reflection: :func:`selfcal.geometry.align`) before the spread is taken, so the gauge
    does not count as error. Aligning on the receivers removes their common rigid motion
    from the spread, so under the model the ratio is at most about 1 and the scale stays 1;
    it grows where the flight's blocks disagree by more than the model's noise allows
    (serially correlated, position-dependent UWB errors).

    Parameters
    ----------
    res : ToaResult
        A fit of ``sub`` with ``offsets`` "none", "common" or "receivers" and receiver covariances.
    sub : (I, J) array
        The matrix it was fitted on, matrix units; columns in time order.
    scale : float
        Metres per matrix unit.

    Returns
    -------
    (result, scale)
        ``res`` with ``receiver_cov`` scaled, and the :class:`JackknifeScale`; ``res`` itself
        and None where the jackknife cannot run (no covariance, a failed refit, other offsets).
    """
    import types

    from ...geometry import align
    from ..engine.nls import refine_toa

    if res.offsets not in ("none", "common", "receivers") or res.receiver_cov is None or res.residuals is None:
        return res, None
    kr, ks, _, Z, R, S, d0 = located_block(res, sub, scale)
    C = np.asarray(res.receiver_cov, float)[kr]
    if kr.sum() < res.receivers.shape[1] + 1 or not np.isfinite(C).all():
        return res, None
    kw: dict[str, Any] = _REFIT[str(res.offsets)]

    def refit(cols: NDArray[np.bool_]) -> Array:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            Rk = np.asarray(refine_toa(Z[:, cols], R, S[cols], receiver_offsets0=d0, covariance=False, **kw).receivers,
                            float)
        return align(Rk, R, reflection=False).apply(Rk)

    fit = types.SimpleNamespace(receivers=R, sources=S, receiver_offsets=d0, source_offsets=None, receiver_cov=C,
                                residuals=np.asarray(res.residuals, float)[np.ix_(kr, ks)])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        got = scaled_receiver_cov(fit, Z, kw, refit, align_receivers=True)
    if got is None:
        return res, None
    Cs, js = got
    cov = np.array(res.receiver_cov, float)
    cov[kr] = Cs
    full = np.ones(kr.size)
    full[kr] = js.scale
    ratio = np.full(kr.size, np.nan)
    ratio[kr] = js.ratio
    return dataclasses.replace(res, receiver_cov=cov), dataclasses.replace(js, scale=full, ratio=ratio)


_BIAS_ALPHA = 0.05  # level of the test that the per-receiver offsets spread beyond their noise
_BIAS_STEP = 0.01  # m, the finite-difference step of a row's bias (the fit is linear in it at this scale)


def bias_effect(sol: Any, Y: Array, kw: dict[str, Any], *, align_receivers: bool = False
                ) -> tuple[float, Array] | None:
    """Random per-receiver biases around the common offset: ``(tau, tau^2 G_i G_i^T per receiver)``.

    ``sol`` is the common-offset fit of ``Y`` (metres) with the fit options ``kw``; None when
    the per-receiver refit or a shifted refit fails. ``align_receivers``: a blind fit's
    shifted refits come back in their own gauge; each is moved onto ``sol``'s receivers by the
    best rigid motion (Kabsch, no reflection) before the difference is taken.
    """
    from scipy.stats import chi2

    from ...geometry import align
    from ..engine.nls import refine_toa

    I = Y.shape[0]
    base = {k: v for k, v in kw.items() if k not in ("offsets", "common_offsets")}
    try:
        full = refine_toa(Y, sol.receivers, sol.sources, offsets="receivers", receiver_offsets0=sol.receiver_offsets,
                          source_offsets0=sol.source_offsets, covariance=True, **base)
        d = np.asarray(full.receiver_offsets, float)
        var = np.asarray(full.receiver_offset_std, float) ** 2
        if not (np.isfinite(d).all() and np.isfinite(var).all()) or I < 2:
            return None
        tau2 = max(0.0, float(np.sum((d - d.mean()) ** 2) - (1 - 1 / I) * np.sum(var)) / (I - 1))
        # no spread beyond the offsets' own noise (chi-square of their deviations from the
        # precision-weighted mean, level 0.05): no random effect
        w = 1.0 / var
        spread = float(np.sum(w * (d - np.sum(w * d) / np.sum(w)) ** 2))
        if tau2 == 0.0 or spread <= chi2.ppf(1 - _BIAS_ALPHA, I - 1):
            return 0.0, np.zeros_like(sol.receiver_cov)
        G = np.zeros((*sol.receivers.shape, I))
        for k in range(I):
            Yk = Y.copy()
            Yk[k] += _BIAS_STEP
            sk = refine_toa(Yk, sol.receivers, sol.sources, receiver_offsets0=sol.receiver_offsets,
                            source_offsets0=sol.source_offsets, covariance=False, **kw)
            Rk = np.asarray(sk.receivers, float)
            if align_receivers:
                Rk = align(Rk, np.asarray(sol.receivers, float), reflection=False).apply(Rk)
            G[:, :, k] = (Rk - sol.receivers) / _BIAS_STEP
    except (DegenerateGeometryError, np.linalg.LinAlgError, ValueError):
        return None
    return float(np.sqrt(tau2)), tau2 * np.einsum("iak,ibk->iab", G, G)


def scaled_receiver_cov(sol: Any, Y: Array, kw: dict[str, Any], refit: Any, *, align_receivers: bool = False
                        ) -> tuple[Array, JackknifeScale] | None:
    """A fit's receiver covariances scaled by :func:`block_jackknife_scale`, plus, for the
    common-offset model, the random effect of per-receiver biases (:func:`bias_effect`).

    ``sol``: the fit (receivers, sources, receiver / source offsets, receiver_cov, residuals)
    of ``Y`` (metres) with the fit options ``kw``; ``refit(columns) -> receivers`` as for
    :func:`block_jackknife_scale`; ``align_receivers`` as for :func:`bias_effect` (a blind fit).
    Returns ``(receiver_cov, scale)``, or None when the jackknife cannot run. Used by
    :func:`jackknife_blind_fit` and :func:`selfcal.toa.frame.error_scale.jackknife_scaled`.
    """
    js = block_jackknife_scale(sol.residuals, sol.receivers, sol.receiver_cov, refit)
    if js is None:
        return None
    cov = sol.receiver_cov * js.scale[:, None, None]
    if kw.get("offsets") == "receivers" and kw.get("common_offsets") == "receivers":
        extra = bias_effect(sol, Y, kw, align_receivers=align_receivers)
        if extra is not None:
            cov = cov + extra[1]
            js = dataclasses.replace(js, bias_tau=extra[0])
    return cov, js
