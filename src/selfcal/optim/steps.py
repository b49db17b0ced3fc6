"""Step solvers and a generic model for :mod:`selfcal.optim.lm`.

The structured step solvers live beside their models (the bipartite Schur steps of the TOA
engines in :mod:`selfcal.toa.schur_lm` / :mod:`selfcal.toa.batch_lm`, the node-block Schur step
of :mod:`selfcal.toa.schur_affine`, the far-field Schur / CG steps in :mod:`selfcal.tdoa.lm`);
here are the dense pieces every one of them ends in, and :class:`ResidualModel` for a plain
``residuals + Jacobian`` problem.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np
import scipy.linalg
from numpy.typing import NDArray
from scipy.linalg import lapack

from .lm import Model

Array = NDArray[np.float64]

__all__ = ["ResidualModel", "cholesky_solve"]


def cholesky_solve(H: Array, rhs: Array) -> Array | None:
    """``H^-1 rhs`` by Cholesky (LAPACK posv); least squares when H is not numerically positive
    definite; None when not even that is finite.

    Examples
    --------
    >>> import numpy as np
    >>> np.round(cholesky_solve(np.array([[2.0, 0.0], [0.0, 4.0]]), np.array([2.0, 2.0])), 12).tolist()
    [1.0, 0.5]
    """
    _, x, info = lapack.dposv(H, rhs, lower=1, overwrite_a=0, overwrite_b=0)
    if info != 0:
        try:
            x = scipy.linalg.lstsq(H, rhs, check_finite=False)[0]
        except (np.linalg.LinAlgError, ValueError):
            return None
    return np.asarray(x, float) if np.isfinite(x).all() else None


class _DenseNormalStep:
    """``(J^T J + lam diag(J^T J)) dx = -J^T r`` (zero diagonal entries damped by 1)."""

    def __init__(self, Jm: Any, r: Array) -> None:
        A = Jm.T @ Jm
        self.A = np.asarray(A.toarray() if hasattr(A, "toarray") else A, float)
        self.g = np.asarray(Jm.T @ r, float)
        self.diag = np.diag(self.A).copy()
        self.diag[self.diag <= 0] = 1.0
        self.gnorm = math.sqrt(float(self.g @ self.g))

    def step(self, lam: float) -> Array | None:
        H = self.A.copy()
        H[np.diag_indices_from(H)] += lam * self.diag
        x = cholesky_solve(H, -self.g)
        return None if x is None else x

    def predicted(self, dx: Array) -> float:
        return -(float(self.g @ dx) + 0.5 * float(dx @ (self.A @ dx)))


class ResidualModel(Model):
    """``0.5 |fun(x)|^2`` with the Jacobian ``jac(x)`` (dense or SciPy sparse), dense step.

    For problems of up to a few hundred unknowns whose normal matrix is formed and factored
    densely at every iteration; the state of an evaluation is the residual vector.
    """

    def __init__(self, fun: Callable[[Array], Array], jac: Callable[[Array], Any]) -> None:
        self.fun, self.jac = fun, jac

    def evaluate(self, x: Array) -> tuple[float, Array]:
        r = self.fun(x)
        return 0.5 * float(r @ r), r

    def linearize(self, x: Array, state: Array) -> _DenseNormalStep:
        return _DenseNormalStep(self.jac(x), state)
