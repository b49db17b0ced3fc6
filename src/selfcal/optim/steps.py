"""Step solvers and a generic model for :mod:`selfcal.optim.lm`.

The structured step solvers live beside their models (the bipartite Schur steps of the TOA
engines in :mod:`selfcal.toa.engine.schur_lm` / :mod:`selfcal.toa.engine.batch_lm`, the node-block Schur step
of :mod:`selfcal.toa.engine.schur_affine`, the far-field Schur / CG steps in :mod:`selfcal.tdoa.lm`);
here are the dense pieces every one of them ends in, the sparse normal-equations step of a
problem with a sparse Jacobian and no block structure to eliminate (a range graph: two nonzero
blocks per row), and :class:`ResidualModel` for a plain ``residuals + Jacobian`` problem.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np
import scipy.linalg
import scipy.sparse
import scipy.sparse.linalg
from numpy.typing import NDArray
from scipy.linalg import lapack

from .lm import Model, irls
from .structure import lm_step

Array = NDArray[np.float64]

__all__ = ["DenseStep", "ResidualModel", "cholesky_solve"]


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


class DenseStep:
    """The dense step solver: ``(H + lam diag H) x = -g`` by Cholesky (least squares if H is not
    numerically positive definite), scattered into the free parameters and projected off the gauge.

    Parameters
    ----------
    H, g : (nf, nf), (nf,) the normal matrix and gradient on the free parameters.
    dstep : flat positions of H's diagonal; proj : an object whose ``apply(dx)`` projects a step in
        place (:class:`selfcal.toa.engine.model.GaugeProjector`: off the gauge) or None;
    fidx : indices of the free parameters in the (n,) point (None: all).
    """

    def __init__(self, H: Array, g: Array, dstep: NDArray[np.intp], proj: Any,
                 fidx: NDArray[np.intp] | None, n: int) -> None:
        self.H, self.g, self.dstep, self.proj, self.fidx, self.n = H, g, dstep, proj, fidx, n
        self.hdiag = H.ravel()[dstep]
        self.gnorm = math.sqrt(float(g @ g))
        self.mg = -g

    def step(self, lam: float) -> Array | None:
        Hd = self.H.copy()
        Hd.ravel()[self.dstep] += lam * self.hdiag  # Marquardt: diag * (1 + lam)
        x = cholesky_solve(Hd, self.mg)
        if x is None:
            return None
        if self.fidx is None:
            dx = x
        else:
            dx = np.zeros(self.n)
            dx[self.fidx] = x
        if self.proj is not None:
            self.proj.apply(dx)  # no rigid drift (and no common offset shift)
        return dx

    def predicted(self, dx: Array) -> float:
        xv = dx if self.fidx is None else dx[self.fidx]
        return -(float(self.g @ xv) + 0.5 * float(xv @ (self.H @ xv)))


class _DenseNormalStep:
    """``(J^T W J + lam diag(J^T W J)) dx = -J^T W r`` by dense Cholesky (zero diagonal entries
    damped by 1), the step then passed through ``project`` (None: kept as is)."""

    sparse = False

    def __init__(self, Jm: Any, r: Array, w: Array | None = None,
                 project: Callable[[Array], Array] | None = None) -> None:
        if self.sparse:
            Jm = scipy.sparse.csr_matrix(Jm)
        Jw = Jm if w is None else (scipy.sparse.diags(w) @ Jm if scipy.sparse.issparse(Jm) else Jm * w[:, None])
        A = Jm.T @ Jw
        self.A = A.tocsc() if self.sparse else np.asarray(A.toarray() if hasattr(A, "toarray") else A, float)
        self.g = np.asarray(Jw.T @ r, float)
        self.diag = np.asarray(A.diagonal() if self.sparse else np.diag(self.A), float).copy()
        self.diag[self.diag <= 0] = 1.0
        self.gnorm = math.sqrt(float(self.g @ self.g))
        self.project = project

    def solve(self, lam: float) -> Array | None:
        H = self.A.copy()
        H[np.diag_indices_from(H)] += lam * self.diag
        return cholesky_solve(H, -self.g)

    def step(self, lam: float) -> Array | None:
        x = self.solve(lam)
        if x is None or not np.isfinite(x).all():
            return None
        return x if self.project is None else self.project(x)

    def predicted(self, dx: Array) -> float:
        return -(float(self.g @ dx) + 0.5 * float(dx @ (self.A @ dx)))


class _SparseNormalStep(_DenseNormalStep):
    """The same damped system with ``J^T W J`` kept sparse and factored by SuperLU per trial.

    For a Jacobian with a few nonzeros per row and no block structure to eliminate (a range
    graph's rows touch two nodes, any two): ``J^T W J`` has the graph's sparsity (a ``d x d``
    block per node and per measured pair), so its sparse LU (:func:`scipy.sparse.linalg.splu`,
    COLAMD ordering) costs a small multiple of its nonzeros on the sparse graphs of tags to
    anchors, where the dense Cholesky is ``O(n^3 / 3)``. A singular factorisation (a gauge
    direction the damping does not reach) refuses the trial (None).
    """

    sparse = True

    def solve(self, lam: float) -> Array | None:
        H = (self.A + scipy.sparse.diags(lam * self.diag)).tocsc()
        try:
            return np.asarray(scipy.sparse.linalg.splu(H).solve(-self.g), float)
        except RuntimeError:  # exactly singular
            return None


class ResidualModel(Model):
    """``0.5 sum rho(fun(x)^2)`` with the Jacobian ``jac(x)`` (dense or SciPy sparse).

    Parameters
    ----------
    fun : x -> (m,) residuals; jac : x -> (m, n) Jacobian (dense array or SciPy sparse).
    loss, f_scale : robust loss and its scale (:func:`selfcal.optim.lm.irls`; the linear
        loss by default). The weights ``rho'`` enter ``J^T W J`` and ``J^T W r``.
    step : ``"dense"`` (the full normal matrix, dense Cholesky; the default) or ``"auto"``
        (:func:`selfcal.optim.structure.lm_step` decides from the number of unknowns: dense up
        to :data:`~selfcal.optim.structure.DENSE_MAX_UNKNOWNS`, the sparse normal equations
        factored by SuperLU above).
    project : x -> (dx -> dx), optional
        The parametrisation's projection of a step at ``x`` (e.g. off the gauge directions:
        :class:`selfcal.toa.engine.model.GaugeProjector`), formed once per linearisation.

    Notes
    -----
    The state of an evaluation is the residual vector (the IRLS weights are recomputed from
    it at the linearisation).

    Examples
    --------
    A robust line fit with one gross error, 200 unknowns of which only 2 matter (the sparse
    step):

    >>> import numpy as np, scipy.sparse as sp
    >>> from selfcal.optim.lm import levenberg_marquardt
    >>> t = np.arange(10.0)
    >>> y = 2 * t + 1
    >>> y[3] += 50.0
    >>> fun = lambda x: np.concatenate([x[0] * t + x[1] - y, x[2:]])
    >>> jac = lambda x: sp.vstack([sp.csr_matrix(np.column_stack([t, np.ones(10), np.zeros((10, 198))])),
    ...                            sp.hstack([sp.csr_matrix((198, 2)), sp.identity(198)])]).tocsr()
    >>> res = levenberg_marquardt(ResidualModel(fun, jac, loss="cauchy", step="auto"), np.ones(200))
    >>> np.round(res.x[:2], 2).tolist()  # least squares: [1.09, 10.09]
    [2.0, 1.0]
    """

    def __init__(self, fun: Callable[[Array], Array], jac: Callable[[Array], Any], *, loss: str = "linear",
                 f_scale: float = 1.0, step: str = "dense",
                 project: Callable[[Array], Callable[[Array], Array]] | None = None) -> None:
        if step not in ("dense", "auto"):
            raise ValueError(f"step must be 'dense' or 'auto', got {step!r}")
        self.fun, self.jac = fun, jac
        self.loss, self.f_scale, self.step, self.project = loss, f_scale, step, project

    def evaluate(self, x: Array) -> tuple[float, Array]:
        r = self.fun(x)
        if self.loss == "linear":
            return 0.5 * float(r @ r), r
        return irls(r, self.loss, self.f_scale)[0], r

    def linearize(self, x: Array, state: Array) -> Any:
        w = None if self.loss == "linear" else irls(state, self.loss, self.f_scale)[1]
        proj = None if self.project is None else self.project(x)
        Jm = self.jac(x)
        if self.step == "dense":
            return _DenseNormalStep(Jm, state, w, proj)
        if lm_step(x.size) == "dense":  # a few columns: dense products beat sparse bookkeeping
            return _DenseNormalStep(Jm.toarray() if scipy.sparse.issparse(Jm) else Jm, state, w, proj)
        return _SparseNormalStep(Jm, state, w, proj)
