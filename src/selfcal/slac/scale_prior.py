"""Empirical-Bayes priors of the range smoother's calibration scales (:mod:`selfcal.slac.ranging`).

:func:`scale_prior_eb`: the prior of the beacon range scales, ``s ~ N(1, a^2 11^T + tau^2 I)``
(a part common to all beacons and a per-beacon part), by type-II maximum likelihood from a
first solve's scale estimates and covariance; exact scales push both to
:data:`SCALE_PRIOR_FLOOR` (the offset-only model). :func:`odo_scale_weight`: the posterior
probability of an odometry distance-scale error against ``k = 1`` (Bayes factor), with which the
smoother averages the two models.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

__all__ = ["ODO_SCALE_STD", "SCALE_PRIOR_FLOOR", "odo_scale_weight", "scale_prior_eb"]

FArray = NDArray[np.float64]

#: Prior std of the causal filter's odometry distance scale ``k`` (``dd_true = k dd``): a
#: wheel-radius / encoder-calibration error of a few percent (the 5 % of ``odo_distance``),
#: a constant of the whole log, not a random walk -- integrated over a log of hundreds of
#: metres it is the dominant odometry error, and a filter without it is overconfident.
ODO_SCALE_STD = 0.05


#: Smallest prior std of the scales the empirical-Bayes step returns (common and per-beacon
#: part): 1e-4 is 2 mm at 20 m, a hundredth of decimetre ranging noise and ~20x below the
#: scale std one log's ranges give (0.001-0.003), so a scale at this prior is fixed in all
#: but name, while the smoother's gain solves stay well conditioned.
SCALE_PRIOR_FLOOR = 1e-4


def scale_prior_eb(s_hat: FArray, V: FArray, scale_std: float) -> tuple[FArray, FArray]:
    """Empirical-Bayes prior of the scales: ``s ~ N(1, a^2 11^T + tau^2 I)`` with the common
    part ``a`` and the per-beacon part ``tau`` at their type-II maximum likelihood.

    ``s_hat`` (B,), ``V`` (B, B): the scales' posterior mean and covariance under the fixed
    prior ``N(1, scale_std^2 I)`` (Laplace, marginal over poses and offsets). The data's
    information about ``delta = s - 1`` is Gaussian with precision ``L = V^-1 - I / scale_std^2``
    and information vector ``g = V^-1 (s_hat - 1)``; the evidence of a prior covariance S is
    ``log Z(S) = -1/2 log det(I + S L) + 1/2 g^T S (I + L S)^-1 g`` (the Gaussian integral,
    valid for singular S). It is maximised over ``log a, log tau`` in
    ``[log SCALE_PRIOR_FLOOR, 0]`` (a coarse grid, then L-BFGS-B; a flat evidence keeps the
    given prior). Returns S (B, B) and ``[a, tau]``.

    Exact scales drive both parts to the floor (the offset-only model); one clock or
    propagation-speed error shared by all beacons gives a large ``a`` and a small ``tau`` (one
    scale, pooled); independent per-beacon errors a large ``tau``. The estimate uses the log
    twice (empirical Bayes): 2 hyper-parameters against B scales.
    """
    from scipy.optimize import minimize

    B = s_hat.size
    Vi = np.linalg.inv(V)
    L = Vi - np.eye(B) / scale_std**2
    w, U = np.linalg.eigh(0.5 * (L + L.T))
    L = (U * np.maximum(w, 0.0)) @ U.T
    g = Vi @ (s_hat - 1.0)
    one = np.ones((B, B))
    eye = np.eye(B)

    def neg_log_z(th: FArray) -> float:
        S = np.exp(2 * th[0]) * one + np.exp(2 * th[1]) * eye
        M = eye + L @ S
        sign, logdet = np.linalg.slogdet(M)
        return float(0.5 * logdet - 0.5 * g @ (S @ np.linalg.solve(M, g)))

    def grad(th: FArray) -> FArray:
        # d/dth_k: 1/2 tr(M^-1 L dS_k) - 1/2 h^T dS_k h, h = M^-1 g (d(S M^-1) = M^-T dS M^-1);
        # dS_0 = 2 a^2 11^T, dS_1 = 2 tau^2 I. Analytic, so the minimiser is found to round-off
        # (a finite-difference gradient leaves it at ~sqrt(eps), and the prior would then
        # depend on the beacons' order at that level)
        a2, t2 = np.exp(2 * th[0]), np.exp(2 * th[1])
        M = eye + L @ (a2 * one + t2 * eye)
        h = np.linalg.solve(M, g)
        ML = np.linalg.solve(M, L)
        one_v = np.ones(B)
        return np.array([a2 * (float(one_v @ ML @ one_v) - float(h.sum()) ** 2),
                         t2 * (float(np.trace(ML)) - float(h @ h))])

    lo = np.log(SCALE_PRIOR_FLOOR)
    grid = np.linspace(lo, 0.0, 13)
    # the given prior (a = floor, tau = scale_std) first: where the data carry no information
    # about the scales the evidence is flat and the tie keeps the physics prior
    cands = [(lo, float(np.log(scale_std)))] + [(x, y) for x in grid for y in grid]
    th0 = min(cands, key=lambda t: neg_log_z(np.array(t)))
    # converged to round-off: the prior, hence the smoothed poses, must not depend on the order
    # of the beacons (or the frame) beyond the solver's precision
    sol = minimize(neg_log_z, np.array(th0), jac=grad, method="L-BFGS-B", bounds=[(lo, 0.0)] * 2,
                   options={"ftol": 1e-15, "gtol": 1e-12, "maxiter": 500})
    th = sol.x if sol.fun <= neg_log_z(np.array(th0)) else np.array(th0)
    a, tau = np.exp(th)
    return a**2 * one + tau**2 * eye, np.array([a, tau])


def odo_scale_weight(k_hat: float, v: float) -> float:
    """Posterior probability of the model ``k ~ N(1, ODO_SCALE_STD^2)`` against ``k = 1`` (prior
    odds 1), from the first solve's marginal of the odometry distance scale ``k``.

    ``k_hat``, ``v``: its posterior mean and variance under the ``ODO_SCALE_STD`` prior. The
    data's likelihood of ``k`` is ``N(k_lik, v_lik)`` with ``1 / v_lik = 1 / v - 1 / ODO_SCALE_STD^2``;
    the Bayes factor is ``BF = N(k_lik - 1; 0, v_lik + ODO_SCALE_STD^2) / N(k_lik - 1; 0, v_lik)``,
    the weight ``BF / (1 + BF)``. The smoother solves both models and averages them with this
    weight (Bayesian model averaging). Selecting the more probable one instead (``BF > 1``:
    ``z^2 > (1 + r) log(1 + 1/r)``, ``r = v_lik / ODO_SCALE_STD^2``, |z| > 2.4 at the ``v_lik``
    of a 150-s log) loses where the evidence is not decisive: a spurious ``k`` trades against
    the shared range scale (2 of 8 simulated logs without an odometry error at 1.7-4.5x the
    RMSE under a type-II ML prior of ``k``), a missed one leaves the wheel-radius error to the
    odometry noise. One parameter gives no information about its own prior variance, so the
    alternative's prior stays the physics one (``ODO_SCALE_STD``).

    Examples
    --------
    >>> round(odo_scale_weight(1.0, 0.003**2), 3)  # no evidence of a scale error: k = 1 favoured
    0.057
    >>> odo_scale_weight(0.97, 0.003**2) > 0.999  # a 3 % error, 10 sigma
    True
    """
    prec = 1.0 / v - 1.0 / ODO_SCALE_STD**2
    if not np.isfinite(prec) or prec <= 0:
        return 0.0  # no information about k: the simpler model
    v_lik = 1.0 / prec
    d = (k_hat - 1.0) / v * v_lik  # k_lik - 1: the information (k_hat - 1) / v times v_lik
    z2 = d * d / v_lik
    log_bf = -0.5 * np.log(1.0 + ODO_SCALE_STD**2 / v_lik) + 0.5 * z2 * ODO_SCALE_STD**2 / (v_lik + ODO_SCALE_STD**2)
    return float(1.0 / (1.0 + np.exp(-log_bf)))
