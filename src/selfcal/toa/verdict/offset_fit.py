"""Two pieces shared by the common-offset recipe and the offsets cross-validation.

:func:`residual_correlation_length` (the block length of both tests: the first lag at which
the residuals' autocorrelation enters the white-noise band) and :func:`_with_common` (a
result with a receiver-offset fit written in). They sit in the verdict layer, below
:mod:`selfcal.toa.recipes.common_offset`, so that :mod:`selfcal.toa.verdict.crossval` does
not import a recipe (docs/design.md, the toa layers).
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np
from numpy.typing import NDArray

__all__ = ["residual_correlation_length"]

Array = NDArray[np.float64]


def residual_correlation_length(residuals: Any, max_lag: int | None = None) -> int:
    """First lag at which the rows' mean residual autocorrelation enters the white-noise band.

    Parameters
    ----------
    residuals: (I, J) residuals, columns in time order, NaN = missing / not used.
    max_lag: largest lag examined (default ``J // 2``).

    Returns
    -------
    int: the smallest lag ``l >= 1`` with ``|rho(l)| < 1.96 / sqrt(J)``, ``rho`` the
    NaN-aware sample autocorrelation averaged over the rows; ``max_lag`` when it never
    enters the band.

    Examples
    --------
    >>> rng = np.random.default_rng(0)
    >>> residual_correlation_length(rng.standard_normal((6, 500)))
    1
    """
    E = np.array(residuals, dtype=float)
    J = E.shape[1]
    top = J // 2 if max_lag is None else int(max_lag)
    with np.errstate(all="ignore"):
        E = E - np.nanmean(E, axis=1, keepdims=True)
        var = np.nanmean(E * E, axis=1)
    ok = np.isfinite(var) & (var > 0)
    if not ok.any() or top < 1:
        return max(top, 1)
    E, var = E[ok], var[ok]
    band = 1.96 / np.sqrt(J)
    for lag in range(1, top + 1):
        with np.errstate(all="ignore"):
            rho = np.nanmean(E[:, :-lag] * E[:, lag:], axis=1) / var
        if abs(float(np.nanmean(rho))) < band:
            return lag
    return top


def _with_common(base: Any, com: Any, sub: Array, scale: float, kr: NDArray[np.bool_], ks: NDArray[np.bool_],
                 used: NDArray[np.bool_], offs: Array, mode: str = "common") -> Any:
    """``base`` with the receiver-offset fit ``com`` (on the rows ``kr``, columns ``ks``) written in.

    ``mode``: "common" (one offset shared by every receiver, one parameter more than the
    offsets-free fit) or "receivers" (one per receiver).
    """
    from ...geometry import n_parameters
    from ..engine.nls import toa_model
    from .robust import noise_scale

    I, J = base.receivers.shape[0], base.sources.shape[0]
    d = base.receivers.shape[1]

    def put(a: Array, k: NDArray[np.bool_], tail: tuple[int, ...]) -> Array:
        out = np.full((k.size,) + tail, np.nan)
        out[k] = a
        return out

    R = np.full((I, J), np.nan)
    model = toa_model(com.receivers, com.sources, offs) / scale
    blk = sub[np.ix_(kr, ks)]
    R[np.ix_(kr, ks)] = np.where(np.isfinite(blk), blk - model, np.nan)
    inl = used & np.isfinite(R)
    # the noise estimate of the new residuals, as the solver computes it (robust scale of the
    # fitted residuals times sqrt(m / dof)), one parameter more than the offsets-free fit
    m = int(inl.sum())
    n_extra = 1 if mode == "common" else int(kr.sum())
    dof = m - n_parameters(int(kr.sum()), int(ks.sum()), d, "none") - n_extra
    noise = noise_scale(R[inl]) * float(np.sqrt(m / dof)) if dof > 0 else float("nan")
    names = {f.name for f in dataclasses.fields(base)}
    kw = {
        "receivers": put(com.receivers, kr, (d,)), "sources": put(com.sources, ks, (d,)),
        "receiver_offsets": put(offs / scale, kr, ()), "offsets": mode,
        "receiver_cov": put(com.receiver_cov, kr, (d, d)), "source_cov": put(com.source_cov, ks, (d, d)),
        "residual_rms": float(np.sqrt(np.mean(R[inl] ** 2))) if inl.any() else float("nan"),
        "sigma": noise, "noise_estimate": noise,
        "converged": com.converged, "iterations": int(base.iterations) + int(com.iterations),
        "method": f"{base.method}+{mode}-offset" if mode == "common" else f"{base.method}+receiver-offsets",
        "residuals": R,
        "receiver_offset_std": None if com.receiver_offset_std is None
        else put(np.asarray(com.receiver_offset_std) / scale, kr, ()),
    }
    return dataclasses.replace(base, **{k: v for k, v in kw.items() if k in names})
