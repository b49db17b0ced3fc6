"""The range model's dense step on the observed pairs (the search's direct call).

:func:`full_lm` is :class:`selfcal.toa.engine.schur_lm.RangeModel` (the one range model of
the engines) on the :class:`~selfcal.toa.engine.schur_lm.Pairs` pattern with the ``"dense"``
step solver (:class:`selfcal.optim.steps.DenseStep`), run by the one driver
(:func:`selfcal.optim.lm.levenberg_marquardt`); :func:`solve_dense_lm` is its entry (the
variable projection of the offsets, measured and not kept, is in
``benchmarks/bench_toa_varpro.py``). What makes the dense
step cheap on small problems (12 receivers x 6 sources with both offsets: 72 ranges, 66
unknowns, where the cost of an iteration is Python overhead, not arithmetic):

- the parameters stay in the receiver-major order of :mod:`selfcal.toa.engine.nls`; the
  Jacobian is one preallocated (m, n) array whose offset columns never change, so an
  iteration writes only the 2 d unit-vector entries per row;
- the gauge is projected without a QR per iteration
  (:class:`selfcal.toa.engine.model.GaugeProjector`, the same projector as ``I - Q Q^T`` with
  Q the orthonormal :func:`selfcal.toa.engine.nls.gauge_basis`, to round-off);
- each damped system is solved by one LAPACK ``posv`` call (Cholesky), least squares when
  it is not numerically positive definite;
- a mask of free parameters (the parametrisation of a partial refit, the search's moves):
  the fixed ones keep their values and no gauge is projected (the fixed nodes hold the frame).

Cost per iteration O(m n^2) flops for ``J^T W J`` plus O(n^3 / 3) for the factorisation;
at 12 x 6 with both offsets 0.23 ms per iteration against 0.67 ms for the Schur step (same
run, six draws from perturbed truths). Stacking many starts into one batched dense solve was
tried and measured no faster (the stacked (n, n) products and LU solves are flop-bound at
n = 72); what pays is the bipartite block structure of the normal equations, which
:mod:`selfcal.toa.engine.batch_lm` uses to run the search's race (the same iterates, start by
start).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from ...optim.lm import FTOL, levenberg_marquardt
from .model import _node_indices
from .schur_lm import DEFAULT_MAX_IT, Pairs, RangeModel

# FTOL (the relative cost decrease that stops) is read from this module at each call

Array = NDArray[np.float64]

__all__ = ["full_lm", "solve_dense_lm"]


def solve_dense_lm(
    theta0: Array, y: Array, ii: NDArray[np.intp], jj: NDArray[np.intp], I: int, J: int, d: int,
    offsets: str, loss: str, f_scale: float, max_nfev: int | None, xtol: float,
    free: NDArray[np.bool_] | None = None, max_it: int = 100,
) -> tuple[Array, bool, int]:
    """Levenberg-Marquardt with dense normal equations on the observed entries ``y``.

    Parameters
    ----------
    theta0 : (n,) start, receiver-major ``[r (I d), s (J d), d_i (I)?, o_j (J)?]`` (metres).
    y : (m,) observed ranges (metres); ii, jj : (m,) their receiver and source indices.
    I, J, d, offsets : the model (:mod:`selfcal.toa.engine.nls`).
    loss, f_scale : robust loss (:func:`selfcal.robust.loss_rho`) and its scale (metres);
        robust losses run iteratively reweighted normal equations with weights rho'(z).
    max_nfev : iteration cap (default ``max_it``); xtol : relative step tolerance.
    free : (n,) bool, the parameters to fit (default all, and then the gauge is projected out
        of every step); the others are held at ``theta0`` and no gauge is projected.
    max_it : iteration cap when ``max_nfev`` is None.

    Returns
    -------
    (theta, converged, iterations) as :func:`selfcal.toa.engine.schur_lm.solve_schur_lm`.

    Examples
    --------
    >>> import numpy as np
    >>> from selfcal.toa.engine import nls
    >>> g = np.random.default_rng(0)
    >>> r, s = g.uniform(0, 1.5, (12, 3)), g.normal(0, 2, (6, 3))
    >>> Y = nls.toa_model(r, s)
    >>> ii, jj = np.nonzero(np.isfinite(Y))
    >>> th, ok, nit = solve_dense_lm(nls._pack(r + 0.02, s, None, None), Y[ii, jj], ii, jj, 12, 6, 3,
    ...                              "none", "linear", 1.0, None, 1e-12)
    >>> bool(ok) and float(np.abs(nls.toa_residuals(th, Y, 3, "none")).max()) < 1e-6
    True
    """
    return full_lm(theta0, y, ii, jj, I, J, d, offsets, loss, f_scale, max_nfev, xtol, free=free, max_it=max_it)


def full_lm(
    theta0: Array, y: Array, ii: NDArray[np.intp], jj: NDArray[np.intp], I: int, J: int, d: int,
    offsets: str, loss: str, f_scale: float, max_nfev: int | None, xtol: float,
    free: NDArray[np.bool_] | None = None, max_it: int = DEFAULT_MAX_IT["dense"],
) -> tuple[Array, bool, int]:
    """The joint LM of :func:`solve_dense_lm` (positions and offsets damped together); same
    parameters and return: :class:`selfcal.toa.engine.schur_lm.RangeModel`
    on the observed pairs with the dense step."""
    r_idx, s_idx, _ = _node_indices(I, J, d, offsets)
    model = RangeModel(r_idx, s_idx, Pairs(ii, jj, I, J), np.asarray(y, float), d, I, loss, f_scale, "dense",
                       free=free)
    out = levenberg_marquardt(model, np.array(theta0, dtype=float), max_iter=max_nfev or max_it, xtol=xtol,
                              ftol=FTOL)
    return out.x, out.converged, out.iterations
