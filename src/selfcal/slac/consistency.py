"""Consistency tests of a Kalman filter on its own normalised innovations.

:func:`innovation_tests` (NIS level and lag-one whiteness, Bar-Shalom et al. 2001, 5.4) is
how the causal range-SLAC filter (:func:`selfcal.slac.ranging.solve_range_slac`) tests
its covariances; it reads only the innovations, so any Kalman filter can use it.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy import stats

__all__ = ["innovation_tests"]

FArray = NDArray[np.float64]
IArray = NDArray[np.int64]


def innovation_tests(nu: FArray, beacon: IArray, gate2: float, *, tolerance: float = 1.3,
                     alpha: float = 0.01) -> dict[str, float]:
    """Consistency tests of a Kalman filter on its normalised innovations (Bar-Shalom et al. 2001, 5.4).

    Parameters
    ----------
    nu : (K,) normalised innovations ``y_k / sqrt(S_k)`` of the ranges the filter applied,
        in time order (``S_k = H P H^T + sigma^2``, before any robust down-weighting).
    beacon : (K,) the beacon of each range (the whiteness test pairs consecutive ranges of
        one beacon).
    gate2 : the gate on ``nu^2`` the applied ranges passed (``inf``: none).
    tolerance : the variance ratio ``lambda`` (true / reported) tolerated before a run counts
        as inconsistent; 1.3 is where a reported 95 % ellipse (2-D) still covers 90 %
        (``P(chi2_2 < chi2_2(0.95) / 1.3) = 0.90``).
    alpha : level of each test.

    Returns
    -------
    dict
        ``nis_mean`` (the time-averaged NIS) and ``nis_lo`` / ``nis_hi``, the interval it
        must lie in (``mu / tolerance`` and ``tolerance mu`` widened by the two-sided
        ``1 - alpha`` normal quantile of its sampling error), ``nis_p`` (the p-value of the
        violated side, 1 inside); ``whiteness_rho`` (the lag-one autocorrelation of each
        beacon's innovations, pooled over ``pairs`` pairs), ``whiteness_z``
        (``sqrt(pairs) rho``) and ``whiteness_p`` (p-value of ``rho <= rho_max`` with
        ``(1 + rho_max) / (1 - rho_max) = tolerance``); ``passed`` (0.0 when the NIS is
        above ``nis_hi`` or the whiteness test rejects: the covariances are overconfident)
        and ``conservative`` (1.0 when the NIS is below ``nis_lo``: the covariances are too
        large, which does not fail the run).

    Notes
    -----
    Under a consistent filter the normalised innovations are independent N(0, 1) (the
    innovations of a Kalman filter are white, Kailath 1968), so the time-averaged NIS of
    ``K`` of them estimates the variance ratio ``lambda`` with the sampling error of
    ``chi2_K / K``. The applied ranges passed the gate, so their NIS is the chi2(1)
    truncated at ``gate2``, whose mean ``mu = P(chi2_3 < c) / P(chi2_1 < c)`` and second
    moment ``3 P(chi2_5 < c) / P(chi2_1 < c)`` give the normal interval (K is in the
    hundreds). A filter whose range noise is estimated from its own innovations matches the
    NIS level by construction, so the level test sees a wrong noise model; an
    overconfident state covariance shows instead as innovations that stay on one side for
    many ranges (a state error persists), i.e. positive autocorrelation, which the
    whiteness test (``sqrt(n) (rho - rho_max) ~ N(0, 1)`` at the boundary) detects; an
    AR(1) error of correlation ``rho`` inflates the variance of an average by
    ``(1 + rho) / (1 - rho)``, hence ``rho_max`` from the same tolerance.

    Both are tests of practical, not only statistical, significance: with thousands of
    ranges a test of exact consistency rejects a real log for a 5 % misfit of the noise
    model's tails (Plaza 1: NIS 1.09, rho 0.04), while the failures it must catch have
    variance ratios of several (NEES 10-200).

    References
    ----------
    - Bar-Shalom, Y., Li, X. R. and Kirubarajan, T., "Estimation with Applications to
      Tracking and Navigation", Wiley (2001), section 5.4.2 (NIS and whiteness tests).
    - Mehra, R. K., "On the identification of variances and adaptive Kalman filtering",
      IEEE TAC 15 (1970).
    - Wellek, S., "Testing Statistical Hypotheses of Equivalence", Chapman & Hall (2003).

    Examples
    --------
    >>> import numpy as np
    >>> g = np.random.default_rng(0)
    >>> t = innovation_tests(g.standard_normal(2000), np.arange(2000) % 4, np.inf)
    >>> bool(t["passed"]), bool(t["nis_lo"] < t["nis_mean"] < t["nis_hi"])
    (True, True)
    >>> bool(innovation_tests(2 * g.standard_normal(2000), np.arange(2000) % 4, np.inf)["passed"])
    False
    """
    nu = np.asarray(nu, dtype=float)
    beacon = np.asarray(beacon)
    K = nu.size
    out = {"nis_mean": float("nan"), "nis_lo": float("nan"), "nis_hi": float("nan"), "nis_p": float("nan"),
           "whiteness_rho": float("nan"), "whiteness_z": float("nan"), "whiteness_p": float("nan"),
           "pairs": 0.0, "passed": 1.0, "conservative": 0.0}
    if K < 2:
        return out
    c = float(gate2)
    p1 = float(stats.chi2.cdf(c, 1)) if np.isfinite(c) else 1.0
    mu = float(stats.chi2.cdf(c, 3)) / p1 if np.isfinite(c) else 1.0
    m2 = 3.0 * float(stats.chi2.cdf(c, 5)) / p1 if np.isfinite(c) else 3.0
    sd = float(np.sqrt((m2 - mu * mu) / K))
    lam = float(tolerance)
    z = float(stats.norm.ppf(1 - alpha / 2))
    nis = float(np.mean(nu**2))
    p_hi = float(stats.norm.sf((nis - lam * mu) / (lam * sd)))
    p_lo = float(stats.norm.cdf((nis - mu / lam) / (sd / lam)))
    out.update(nis_mean=nis, nis_lo=(mu - z * sd) / lam, nis_hi=lam * (mu + z * sd),
               nis_p=min(1.0, 2 * min(p_hi, p_lo)))
    num = a2 = b2 = 0.0
    n = 0
    for b in np.unique(beacon):
        v = nu[beacon == b]
        if v.size < 2:
            continue
        num += float(v[1:] @ v[:-1])
        a2 += float(v[1:] @ v[1:])
        b2 += float(v[:-1] @ v[:-1])
        n += v.size - 1
    rho_max = (lam - 1) / (lam + 1)
    if n >= 2 and a2 > 0 and b2 > 0:
        rho = float(num / np.sqrt(a2 * b2))
        out.update(whiteness_rho=rho, whiteness_z=float(np.sqrt(n) * rho),
                   whiteness_p=float(stats.norm.sf(np.sqrt(n) * (rho - rho_max))), pairs=float(n))
    over = nis > out["nis_hi"] or (np.isfinite(out["whiteness_p"]) and out["whiteness_p"] < alpha)
    out["passed"] = 0.0 if over else 1.0
    out["conservative"] = 1.0 if nis < out["nis_lo"] else 0.0
    return out
