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
from scipy.optimize import brentq
from scipy.special import ndtri
from scipy.stats import median_abs_deviation

__all__ = ["CONVEX_LOSSES", "LOSSES", "TUNING", "loss_dpsi", "loss_rho", "loss_rho_inverse", "m_estimator_sigma2",
           "mad_std", "rejection_factor"]

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


def loss_dpsi(z: ArrayLike, loss: str) -> NDArray[np.float64]:
    """``psi'(r)`` of ``psi(r) = r rho'(r^2 / delta^2)`` as a function of ``z = r^2 / delta^2``.

    Parameters
    ----------
    z : squared scaled residuals ``r^2 / delta^2`` (any shape).
    loss : "linear", "huber", "soft_l1" or "cauchy" (:data:`LOSSES`).

    Returns
    -------
    ndarray
        ``psi'`` (same shape as z): 1 for the linear loss, the inlier indicator for Huber,
        ``(1 + z)^-1.5`` for soft_l1, ``(1 - z) / (1 + z)^2`` for cauchy (negative beyond delta).

    Examples
    --------
    >>> loss_dpsi([0.25, 4.0], "huber").tolist()
    [1.0, 0.0]
    """
    z = np.asarray(z, dtype=float)
    if loss == "huber":
        return (z <= 1.0).astype(float)
    if loss == "soft_l1":
        return np.asarray((1.0 + z) ** -1.5)
    if loss == "cauchy":
        return np.asarray((1.0 - z) / (1.0 + z) ** 2)
    return np.ones_like(z)


#: losses whose rho(r^2) is convex in r: the high-dimensional variance factor of
#: :func:`m_estimator_sigma2` applies (El Karoui et al. 2013 assume a convex loss)
CONVEX_LOSSES = ("huber", "soft_l1")


def m_estimator_sigma2(r: ArrayLike, mask: NDArray[np.bool_], loss: str, delta: float, n_par: int) -> float:
    """Variance factor of an M-estimate's covariance ``sigma_psi^2 (J^T J)^+``.

    For the convex losses (huber, soft_l1) the high-dimensional sandwich of El Karoui et al.
    (2013): with ``kappa = n_par / n`` and ``b`` the root of
    ``mean(b psi'(r) / (1 + b psi'(r))) = kappa`` (the trace identity ``sum h_i = n_par`` of the
    leverages in the leave-one-out relation ``r_(i) = r_i + b psi(r_i)``),
    ``sigma_psi^2 = (1 - kappa) b^2 mean(psi(r)^2) / kappa^2``. As ``kappa -> 0`` it is
    Huber's (1981, sec. 7.6) ``mean(psi^2) / mean(psi')^2``; for the linear loss it is
    exactly ``RSS / (n - n_par)``. Huber's classical factor (with his first-order correction
    ``K^2 = (1 + kappa var(psi') / mean(psi')^2)^2`` and ``n / (n - n_par)``) leaves the
    covariance too small when ``kappa`` is not small: 1.04-1.18 in the mean squared Mahalanobis
    distance per dimension at 10 x 20 (kappa = 0.42) under Gaussian to t3 noise, 0.97-1.09 with
    this one (``tests/tdoa/test_cov_calibration.py``). The fitted residuals are shrunk
    towards 0 by the fit (``r_i = prox(r_(i))``), which inflates ``mean(psi')`` and shrinks
    ``mean(psi^2)``; the root ``b`` undoes both. The redescending cauchy loss (not convex,
    where that theory does not hold) and fits with no root (fewer effective inliers than
    parameters) keep Huber's classical factor. Valid for heavy-tailed noise when the
    weights' spread does not depend on the design.
    Least squares after a data-dependent cut (the hard-rejection ``psi``) has its factor,
    relative to the refit's own, in :func:`rejection_factor`.

    Parameters
    ----------
    r : residuals (any shape); mask : which of them the fit used (bool, same shape);
    loss : "linear", "huber", "soft_l1" or "cauchy"; delta : the loss scale (residual units);
    n_par : identifiable parameters.

    Returns
    -------
    float
        ``sigma_psi^2`` in residual units squared.

    References
    ----------
    N. El Karoui, D. Bean, P. J. Bickel, C. Lim, B. Yu, "On robust regression with
    high-dimensional predictors", PNAS 110(36):14557-14562, 2013 (eq. 3 / Theorem 1).
    P. J. Huber, "Robust Statistics", Wiley 1981, sec. 7.6.

    Examples
    --------
    >>> import numpy as np
    >>> r = np.random.default_rng(0).standard_normal(20000)
    >>> ok = np.ones(r.shape, dtype=bool)
    >>> round(m_estimator_sigma2(r, ok, "huber", 1.345, 10), 1)
    1.0
    >>> bool(np.isclose(m_estimator_sigma2(r, ok, "linear", 1.0, 8000), np.sum(r**2) / 12000))
    True
    """
    e: NDArray[np.float64] = np.asarray(r, dtype=float)[np.asarray(mask, bool)]
    n = e.size
    if loss == "linear":
        return float(np.sum(e**2)) / max(n - n_par, 1)
    z = (e / delta) ** 2
    psi = e * loss_rho(z, loss)[1]
    dp = loss_dpsi(z, loss)
    mean_dp = float(np.mean(dp)) if n else 1.0
    if mean_dp <= 0:
        return float(np.sum(e**2)) / max(n - n_par, 1)
    kappa = n_par / max(n, 1)
    if loss in CONVEX_LOSSES and np.isfinite(psi).all() and 0 < kappa < float(np.mean(dp > 0)):
        def excess(b: float) -> float:  # mean leverage at b minus kappa: increasing in b
            return float(np.mean(b * dp / (1.0 + b * dp))) - kappa

        hi = kappa / mean_dp  # excess(hi) <= 0 (Jensen); its limit as b -> inf is positive
        for _ in range(200):
            if excess(hi) >= 0:
                b = float(brentq(excess, 0.0, hi, xtol=1e-14 * hi, rtol=1e-12))
                return float((1.0 - kappa) * b * b * np.mean(psi**2) / kappa**2)
            hi *= 4.0
    K = 1.0 + kappa * float(np.var(dp)) / mean_dp**2
    return float(K**2 * np.sum(psi**2) / max(n - n_par, 1) / mean_dp**2)


def rejection_factor(u: ArrayLike, n_par: int = 0) -> float:
    """Variance factor of least squares on the entries a data-dependent cut kept.

    Least squares refitted on the entries with ``|u| <= 1`` (``u`` each studentized
    residual over the cut of an outlier rule) is the M-estimate of the hard-rejection
    ``psi(u) = u 1{|u| <= 1}``, whose ``psi'`` has, besides the inlier indicator, a negative
    delta at each end of the cut: moving the fit moves the entries at the cut in or out. In
    the high-dimensional system of :func:`m_estimator_sigma2` (``kappa = n_par / n``,
    ``n`` every entry judged) the root ``b`` of ``b / (1 + b) mean(psi') = kappa`` is then
    ``kappa / (P - D - kappa)``, ``P`` the fraction kept and ``D = f(1) + f(-1)`` the density
    of ``u`` at the cut (the delta's weight; by Stein's identity over the Gaussian part of a
    leave-one-out residual, the density of the studentized residuals — the standardized
    leave-one-out ones the rule cuts — not of the errors). ``sigma_psi^2`` is
    ``(1 - kappa) b^2 mean(psi^2) / kappa^2``; the refit's own ``RSS / (n_kept - n_par)
    (J^T J)^+`` is that with ``D = 0`` (to ``O(1 - P)``), so its variance is too small by
    ``((P - kappa) / (P - D - kappa))^2`` — the factor returned. As ``kappa -> 0`` it is
    Huber's (1981, sec. 7.6) sandwich ``mean(psi^2) / mean(psi')^2`` over the refit's,
    ``(P / (P - D))^2`` (1.12 for Student t3 errors at a cut of 4 robust standard deviations,
    1.002 for Gaussian ones, whose density there is negligible).

    ``D`` is a Gaussian kernel density estimate at ``+-1`` over every finite ``u`` with the
    normal-reference bandwidth ``h = 1.06 s n^(-1/5)`` (Silverman 1986, eq. 3.28), ``s`` the
    normal-consistent MAD of ``u`` (:func:`mad_std`: entries far beyond the cut, gross
    errors, widen neither the bandwidth nor the estimate at the cut). Where
    ``P - D <= kappa`` (no root: fewer effective inliers than parameters) the low-dimensional
    form is used; the factor is capped at 4 (a cut in the bulk of the data, not its tail).

    Parameters
    ----------
    u : array_like
        Residual over its cut of every entry judged (any shape); NaN = not judged.
    n_par : int
        Identifiable parameters of the fit (0: the low-dimensional sandwich).

    Returns
    -------
    float
        The factor (>= 1) to multiply the refit's covariance by; 1.0 with no finite ``u``
        or nothing kept.

    References
    ----------
    N. El Karoui, D. Bean, P. J. Bickel, C. Lim, B. Yu, "On robust regression with
    high-dimensional predictors", PNAS 110(36):14557-14562, 2013.
    P. J. Huber, "Robust Statistics", Wiley 1981, sec. 7.6.
    B. W. Silverman, "Density Estimation for Statistics and Data Analysis", Chapman & Hall
    1986, sec. 3.4.2.

    Examples
    --------
    >>> import numpy as np
    >>> g = np.random.default_rng(0)
    >>> round(rejection_factor(g.standard_normal(20000) / 4.0), 3)  # Gaussian, cut at 4 sigma
    1.005
    >>> t3 = g.standard_t(3, 20000) / np.sqrt(3.0)
    >>> round(rejection_factor(t3 / (4.0 * mad_std(t3))), 2)  # theory: 1.12
    1.12
    >>> round(rejection_factor(t3 / (4.0 * mad_std(t3)), n_par=8000), 2)  # kappa = 0.4
    1.21
    """
    a = np.asarray(u, dtype=float)
    a = a[np.isfinite(a)]
    n = a.size
    p_kept = float(np.mean(np.abs(a) <= 1.0)) if n else 0.0
    h = 1.06 * float(mad_std(a)) * n ** -0.2 if n else 0.0
    if p_kept == 0.0 or not h > 0:
        return 1.0
    kde = np.exp(-0.5 * ((a - 1.0) / h) ** 2) + np.exp(-0.5 * ((a + 1.0) / h) ** 2)
    at_cut = float(np.mean(kde)) / (h * np.sqrt(2.0 * np.pi))  # D = f(1) + f(-1)
    kappa = n_par / n
    if p_kept - at_cut - kappa > 0 and p_kept - kappa > 0:
        factor = ((p_kept - kappa) / (p_kept - at_cut - kappa)) ** 2
    else:
        factor = 1.0 / max(1.0 - at_cut / p_kept, 0.5) ** 2
    return float(min(max(factor, 1.0), 4.0))
