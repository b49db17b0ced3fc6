"""The MAP update of the SLAC filter with its Laplace covariance (paper 002, eqs. 22-26).

``x_hat = argmin NLL(x) + 1/2 (x - x_bar)^T P_bar^-1 (x - x_bar)``, solved by BFGS with the
analytic gradient in coordinates whitened by the posterior information at the start (so that
the identity is already a good inverse Hessian), then ``P_hat`` = the inverse Hessian of the
objective at the solution, with the likelihood Hessian replaced by its Fisher information
(``covariance="fisher"``) or taken by central differences of the gradient (``"fd"``, the
paper's numerical Hessian). Used by the filter (:mod:`selfcal.slac.filter`) and the fixed-lag
smoother (:mod:`selfcal.slac.smoother`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import scipy.linalg as sla
from numpy.typing import NDArray
from scipy.optimize import minimize

from .._checks import check_choice
from .linalg import safe_cholesky, spd_inverse, tri_solve

__all__ = ["UpdateInfo", "map_update", "quasi_newton"]

FArray = NDArray[np.float64]

(_GER,) = sla.get_blas_funcs(("ger",), (np.empty((1, 1)),))


@dataclass(frozen=True)
class UpdateInfo:
    """Outcome of one MAP update."""

    iterations: int
    converged: bool
    evaluations: int
    objective: float


def quasi_newton(
    obj: Callable[[FArray], tuple[float, FArray]],
    D: int,
    gtol: float,
    max_iter: int,
    u0: FArray | None = None,
) -> tuple[FArray, int, bool, int, float]:
    """BFGS from the identity in coordinates whitened by the expected Hessian at the start.

    The same iteration as scipy's BFGS (inverse-Hessian update, same stop rule
    ``max |gradient| < gtol``) without its generic line search: the whitening makes the unit
    step the Newton step of the local quadratic model, so it is tried first and only halved
    while the Armijo condition fails. Typically one objective evaluation per iteration and no
    Python-level line-search machinery (the cost of ``scipy.optimize.minimize`` here).

    ``u0`` (D,) is the start (default: the origin of the whitened coordinates).

    Returns
    -------
    u (D,), iterations, converged, evaluations, objective value.
    """
    u = np.zeros(D) if u0 is None else np.array(u0, dtype=float)
    f, g = obj(u)
    nfev = 1
    Hi = np.eye(D)
    for it in range(max_iter):
        if D == 0 or float(np.max(np.abs(g))) < gtol:
            return u, it, True, nfev, f
        p = -Hi @ g
        slope = float(g @ p)
        if slope >= 0:  # lost descent (rounding in Hi): restart from the whitened identity
            Hi = np.eye(D)
            p = -g
            slope = float(g @ p)
        alpha = 1.0
        for _ in range(40):
            f_new, g_new = obj(u + alpha * p)
            nfev += 1
            if np.isfinite(f_new) and f_new <= f + 1e-4 * alpha * slope:
                break
            alpha *= 0.5
        else:
            return u, it, False, nfev, f
        s_ = alpha * p
        y = g_new - g
        sy = float(s_ @ y)
        if sy > 1e-12 * float(np.sqrt((s_ @ s_) * (y @ y))):
            # BFGS inverse update: (I - r s y^T) Hi (I - r y s^T) + r s s^T
            r = 1.0 / sy
            Hy = Hi @ y
            # in place by BLAS dger on the Fortran view of the C-ordered Hi (rank-1 updates)
            HiF = Hi.T
            HiF = _GER(r * r * float(y @ Hy) + r, s_, s_, a=HiF, overwrite_a=1)
            HiF = _GER(-r, s_, Hy, a=HiF, overwrite_a=1)
            Hi = _GER(-r, Hy, s_, a=HiF, overwrite_a=1).T
        u = u + s_
        f, g = f_new, g_new
    return u, max_iter, float(np.max(np.abs(g))) < gtol, nfev, f


def map_update(
    x_bar: FArray,
    P_bar: FArray,
    fun_grad: Callable[[FArray], tuple[float, FArray]],
    information: Callable[[FArray], FArray],
    *,
    gtol: float = 1e-3,
    max_iter: int = 60,
    covariance: str = "fisher",
    preconditioner: Callable[[FArray], FArray] | None = None,
    optimizer: str = "bfgs",
    x_start: FArray | None = None,
) -> tuple[FArray, FArray, UpdateInfo]:
    """MAP update of eq. 22 (BFGS with the analytic gradient), Laplace covariance.

    Parameters
    ----------
    x_bar, P_bar : (D,), (D, D) predicted mean and covariance (eq. 20-21).
    fun_grad : x -> (NLL, dNLL/dx), the negative log-likelihood of eq. 24 and its gradient.
    information : x -> (D, D) Fisher information of the likelihood at x.
    covariance : "fisher" or "fd" (Hessian of the NLL by central differences of fun_grad).
    preconditioner : x -> (D, D) information used only to whiten the BFGS coordinates
        (default: ``information``).
    optimizer : "bfgs" (``scipy.optimize.minimize`` BFGS in the whitened coordinates, the
        paper's solver) or "quasi-newton" (:func:`quasi_newton`: the same BFGS iteration with
        unit-step-first Armijo backtracking; same stop rule, same optimum, several times less
        overhead per update).
    x_start : (D,) optional start of the iteration (warm start; default ``x_bar``). The
        whitening then uses the preconditioner information at ``x_start``.

    Returns
    -------
    x_hat (D,), P_hat (D, D), UpdateInfo.
    """
    check_choice(optimizer, "optimizer", ("bfgs", "quasi-newton"))
    Pinv = spd_inverse(P_bar)
    information_at = preconditioner or information
    H0 = Pinv + information_at(x_bar if x_start is None else x_start)
    C = safe_cholesky(H0)
    u0 = None if x_start is None else C.T @ (np.asarray(x_start, dtype=float) - x_bar)

    def to_x(u: FArray) -> FArray:
        return x_bar + tri_solve(C, u, trans=True)

    def obj(u: FArray) -> tuple[float, FArray]:
        x = to_x(u)
        r = x - x_bar
        nll, g = fun_grad(x)
        Pr = Pinv @ r
        return float(nll + 0.5 * r @ Pr), tri_solve(C, g + Pr)

    if optimizer == "bfgs":
        res = minimize(obj, np.zeros(x_bar.size) if u0 is None else u0, jac=True, method="BFGS",
                       options={"gtol": gtol, "maxiter": max_iter})
        u_hat, nit, ok, nfev, fval = res.x, int(res.nit), bool(res.success), int(res.nfev), float(res.fun)
    else:
        u_hat, nit, ok, nfev, fval = quasi_newton(obj, x_bar.size, gtol, max_iter, u0)
    x_hat = to_x(u_hat)
    if covariance == "fd":
        D = x_hat.size
        Hl = np.empty((D, D))
        scale = np.sqrt(np.clip(np.diag(P_bar), 1e-18, None))
        for d in range(D):
            h = 1e-4 * scale[d]
            e = np.zeros(D)
            e[d] = h
            Hl[:, d] = (fun_grad(x_hat + e)[1] - fun_grad(x_hat - e)[1]) / (2 * h)
        H = Pinv + 0.5 * (Hl + Hl.T)
    else:
        H = Pinv + information(x_hat)
    H = 0.5 * (H + H.T)
    try:
        P = spd_inverse(H)
    except np.linalg.LinAlgError:
        # an indefinite numerical Hessian: fall back on the Fisher information (always PSD)
        P = spd_inverse(Pinv + information(x_hat))
    info = UpdateInfo(nit, ok, nfev, fval)
    return x_hat, 0.5 * (P + P.T), info
