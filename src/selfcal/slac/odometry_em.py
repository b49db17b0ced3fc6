"""Expectation-maximisation of the odometry noise densities of :mod:`selfcal.slac.ranging`.

The range-SLAC motion model drives ``x_n = f(x_{n-1}, u_n + w_n)`` with one increment
``u_n = [dd, dpsi]`` and noise ``w_n ~ N(0, diag(q_d(n), q_p(n)))`` whose variances are
densities times the increment (``q_d = a^2 |dd|``, ``q_p = g^2 (b^2 |dpsi| + c^2 |dd|)``).
Given the smoothed trajectory the noise of each increment is recovered,

    w_d = cos(psi_{n-1}) (x_n - x_{n-1}) + sin(psi_{n-1}) (y_n - y_{n-1}) - dd_n
    w_p = psi_n - psi_{n-1} - dpsi_n

and the EM update of a common factor ``lambda`` on each variance column is (Shumway &
Stoffer 1982, in the linearised model)

    lambda = mean_n (E[w_n]^2 + Var[w_n]) / q(n)                                     (EM)

with ``E[w]`` and ``Var[w] = J [[P_n, X_n], [X_n^T, P_{n-1}]] J^T`` from the smoother's
marginals ``P`` and lag-one cross-covariances ``X_n = Cov(x_n, x_{n-1})``. ``lambda = 1`` at
the maximum-likelihood noise level; a log whose odometry is noisier than assumed (gyro
drift, wheel slip, a wheel-radius error, rows logged twice) gives ``lambda > 1``.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

__all__ = ["odometry_noise_factors"]

FArray = NDArray[np.float64]


def odometry_noise_factors(m: FArray, P: FArray, X: FArray, inc: FArray, var: FArray) -> tuple[float, float]:
    """EM factors ``(lambda_d, lambda_p)`` of the distance and heading noise variances (eq. EM).

    Parameters
    ----------
    m : (N, 3) smoothed poses ``[x, y, psi]`` at the chain's nodes.
    P : (N, 3, 3) their marginal covariances; X : (N, 3, 3) ``Cov(x_n, x_{n-1})`` (row 0 unused).
    inc : (N, 2) increments ``[dd, dpsi]`` driving node n-1 -> n (row 0 unused).
    var : (N, 2) their assumed noise variances (row 0 unused; 0 = an exact increment).

    Returns
    -------
    (lambda_d, lambda_p) : float
        Mean of ``(E[w]^2 + Var[w]) / q`` over the increments with ``q > 0`` (NaN if none).

    Examples
    --------
    >>> import numpy as np
    >>> m = np.array([[0.0, 0.0, 0.0], [1.1, 0.0, 0.2]])
    >>> P = np.zeros((2, 3, 3)); X = np.zeros((2, 3, 3))
    >>> inc = np.array([[0.0, 0.0], [1.0, 0.1]]); var = np.array([[0.0, 0.0], [0.01, 0.01]])
    >>> [round(v, 6) for v in odometry_noise_factors(m, P, X, inc, var)]
    [1.0, 1.0]
    """
    x0, x1 = m[:-1], m[1:]
    c, s = np.cos(x0[:, 2]), np.sin(x0[:, 2])
    dx, dy = x1[:, 0] - x0[:, 0], x1[:, 1] - x0[:, 1]
    u, q = inc[1:], var[1:]
    w_d = c * dx + s * dy - u[:, 0]
    w_p = x1[:, 2] - x0[:, 2] - u[:, 1]
    n = x0.shape[0]
    J1 = np.zeros((n, 2, 3))
    J0 = np.zeros((n, 2, 3))
    J1[:, 0, 0], J1[:, 0, 1] = c, s
    J0[:, 0, 0], J0[:, 0, 1], J0[:, 0, 2] = -c, -s, -s * dx + c * dy
    J1[:, 1, 2], J0[:, 1, 2] = 1.0, -1.0
    V = (np.einsum("nij,njk,nlk->nil", J1, P[1:], J1) + np.einsum("nij,njk,nlk->nil", J0, P[:-1], J0)
         + 2 * np.einsum("nij,njk,nlk->nil", J1, X[1:], J0))
    out = []
    for col, w in ((0, w_d), (1, w_p)):
        ok = q[:, col] > 0
        if not ok.any():
            out.append(float("nan"))
            continue
        out.append(float(np.mean((w[ok] ** 2 + np.maximum(V[ok, col, col], 0.0)) / q[ok, col])))
    return out[0], out[1]
