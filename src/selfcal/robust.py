"""Robust statistics: the one home of the robust scale and of the robust-loss table.

``1.4826 MAD`` estimates the standard deviation of Gaussian data with a 50 % breakdown
point (Hampel 1974; Rousseeuw & Croux 1993). Every solver that needs a robust noise level
calls :func:`mad_std`, which is :func:`scipy.stats.median_abs_deviation` with
``scale="normal"`` (the constant ``1 / Phi^-1(3/4) = 1.482602...``) and NaN omitted.

The robust losses are those of :func:`scipy.optimize.least_squares` (``rho`` of the squared,
scaled residual ``z = (r / f_scale)^2``); :data:`TUNING` gives ``f_scale`` in units of the
noise standard deviation for 95 % efficiency under Gaussian noise (Huber 1964; Holland &
Welsch 1977), soft_l1 (pseudo-Huber) borrowing Huber's constant.
"""

from __future__ import annotations

import warnings
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.special import ndtri
from scipy.stats import median_abs_deviation

__all__ = ["LOSSES", "TUNING", "loss_rho", "loss_rho_inverse", "mad_std"]

#: robust losses understood by every solver (scipy.optimize.least_squares names)
LOSSES = ("linear", "huber", "soft_l1", "cauchy")
#: residual scale, in noise standard deviations, of 95 % Gaussian efficiency per loss
TUNING = {"huber": 1.345, "soft_l1": 1.345, "cauchy": 2.385}


def loss_rho(z: ArrayLike, loss: str) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """``rho(z)`` and ``rho'(z)`` of squared, scaled residuals ``z = (r / f_scale)^2``.

    The IRLS weight of a residual is ``rho'(z)``; ``rho(z) = z`` for the linear loss.

    Parameters
    ----------
    z : array_like
        Squared, scaled residuals (>= 0).
    loss : {"linear", "huber", "soft_l1", "cauchy"}

    Returns
    -------
    rho, drho : ndarray
        The loss and its derivative with respect to z, the shape of ``z``.

    Examples
    --------
    >>> from selfcal.robust import loss_rho
    >>> rho, w = loss_rho([0.25, 4.0], "huber")
    >>> rho.tolist(), w.tolist()
    ([0.25, 3.0], [1.0, 0.5])
    """
    z = np.asarray(z, dtype=float)
    if loss == "linear":
        return z, np.ones_like(z)
    if loss == "huber":
        big = z > 1
        sq = np.sqrt(np.where(big, z, 1.0))
        return np.where(big, 2 * sq - 1, z), np.where(big, 1 / sq, 1.0)
    if loss == "soft_l1":
        t = np.sqrt(1 + z)
        return 2 * (t - 1), 1 / t
    if loss == "cauchy":
        return np.log1p(z), 1 / (1 + z)
    from .errors import InputError

    raise InputError(f"unknown loss {loss!r}; expected one of {LOSSES}")


def loss_rho_inverse(c: ArrayLike, loss: str) -> NDArray[np.float64]:
    """The ``z >= 0`` with ``rho(z) = c`` (:func:`loss_rho`; every ``rho`` is increasing from 0).

    Every loss has ``rho(z) <= z`` and ``f^2 rho(r^2 / f^2)`` increasing in ``f``, so a fit
    whose robust cost ``sum_k f^2 rho(r_k^2 / f^2)`` is at most ``C`` has every
    ``|r_k| <= f sqrt(rho^-1(C / f^2))`` at any scale ``f`` at least the one given: the bound
    :func:`selfcal.toa.fit.finish` uses to know what a robust refit can move.

    Parameters
    ----------
    c : array_like
        Values of ``rho`` (>= 0).
    loss : {"linear", "huber", "soft_l1", "cauchy"}

    Returns
    -------
    ndarray
        ``z``, the shape of ``c`` (inf where ``expm1`` overflows for Cauchy).

    Examples
    --------
    >>> import numpy as np
    >>> from selfcal.robust import loss_rho, loss_rho_inverse
    >>> z = np.array([0.1, 2.0, 50.0])
    >>> all(bool(np.allclose(loss_rho_inverse(loss_rho(z, k)[0], k), z)) for k in LOSSES)
    True
    """
    v: NDArray[np.float64] = np.maximum(np.asarray(c, dtype=float), 0.0)
    if loss == "linear":
        return v
    if loss == "huber":
        return np.where(v > 1, ((v + 1) / 2) ** 2, v)
    if loss == "soft_l1":
        return (1 + v / 2) ** 2 - 1
    if loss == "cauchy":
        with np.errstate(over="ignore"):
            return np.asarray(np.expm1(v), dtype=float)
    from .errors import InputError

    raise InputError(f"unknown loss {loss!r}; expected one of {LOSSES}")


#: MAD of the standard normal distribution, Phi^-1(3/4) (scipy's ``scale="normal"``)
_NORMAL_MAD = float(ndtri(0.75))


def _zero(x: NDArray[Any], axis: int | None = None) -> Any:
    return np.zeros(()) if axis is None else np.zeros(np.delete(np.shape(x), axis))


def mad_std(
    x: ArrayLike,
    axis: int | None = None,
    *,
    centre: bool = True,
    keepdims: bool = False,
) -> Any:
    """Normalised median absolute deviation ``1.4826 median|x - median(x)|``, NaN ignored.

    Parameters
    ----------
    x : array_like
        Data (any shape). NaN entries are left out.
    axis : int, optional
        Axis along which to compute; None (default) uses every entry.
    centre : bool
        Subtract the median first (default). ``False`` gives ``1.4826 median|x|``, the
        scale of residuals that are already centred by a fit.
    keepdims : bool
        Keep the reduced axis with length one (for broadcasting against ``x``).

    Returns
    -------
    float or ndarray
        The robust standard deviation (x's units); NaN where a slice has no finite entry.

    Examples
    --------
    >>> import numpy as np
    >>> from selfcal.robust import mad_std
    >>> float(mad_std([1.0, 2.0, 3.0, 4.0, 100.0]))  # 1.4826 x median(|x - 3|) = 1.4826
    1.482602218505602
    >>> mad_std(np.array([[1.0, -1.0, np.nan], [2.0, -2.0, 0.0]]), axis=1, centre=False)
    array([1.48260222, 2.96520444])
    """
    a = np.asarray(x, dtype=float)
    if a.size and not np.isnan(a).any():
        out = median_abs_deviation(a, axis=axis, center=np.median if centre else _zero, scale="normal")
    else:
        # NaN omitted, vectorised (scipy's nan_policy="omit" loops over the slices in Python,
        # ~50x slower on the (rows, window) arrays of the robust fits); same constant
        with warnings.catch_warnings():  # an all-NaN slice gives NaN, as documented
            warnings.simplefilter("ignore", RuntimeWarning)
            c = np.nanmedian(a, axis=axis, keepdims=True) if centre else 0.0
            out = np.nanmedian(np.abs(a - c), axis=axis) / _NORMAL_MAD
    if keepdims and axis is not None:
        out = np.expand_dims(out, axis)
    return float(out) if np.ndim(out) == 0 and not keepdims else out
