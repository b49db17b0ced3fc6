"""The range model's dense step on the observed pairs (the search's direct call), joint or with the offsets projected out.

:func:`full_lm` is :class:`selfcal.toa.engine.schur_lm.RangeModel` (the one range model of
the engines) on the :class:`~selfcal.toa.engine.schur_lm.Pairs` pattern with the ``"dense"``
step solver (:class:`selfcal.optim.steps.DenseStep`), run by the one driver
(:func:`selfcal.optim.lm.levenberg_marquardt`); :func:`solve_dense_lm` routes to it or to the
variable projection of the offsets (:func:`solve_varpro_lm`, below). What makes the dense
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

Variable projection of the offsets (:func:`solve_varpro_lm`): Levenberg-Marquardt on the
positions alone, a parametrisation of the same model and step.

The range model ``y_ij = |r_i - s_j| + d_i + o_j`` is linear in the offsets. For a given
geometry the offsets minimising the (weighted) cost are a small linear least-squares problem
over the observed entries, so they can be eliminated (Golub & Pereyra 1973): the reduced
residual is ``P (dist(x) - y)`` with ``P = I - A (A^T W A)^+ A^T W`` the weighted projector
off the offset design A (0/1 columns, one per offset of the model), and because A does not
depend on the positions, ``P J_x`` is the *exact* Jacobian of the reduced residual (Kaufman's
1975 approximation drops nothing here). Each iteration:

1. the normal matrix of the full problem ``J^T W J`` is formed as in
   :func:`full_lm`; the offset block is eliminated (Schur
   complement), which is ``J_x^T W P J_x``, the reduced Gauss-Newton matrix;
2. the damped reduced system is solved for the position step, which is projected off the
   rigid gauge (:class:`selfcal.toa.engine.model.GaugeProjector`, positions only);
3. at the trial positions the offsets are *re-solved* (not moved by their linearised step):
   the cost compared is the variable-projection cost ``min_z cost(x, z)``.

With the least-squares loss the projector is fixed, so it is formed once (an (m, m) matrix)
and an iteration is two products with it plus the joint engine's step. Robust losses make
the offsets a nonlinear (IRLS) sub-problem; they run the joint engine. Measured before that
choice: with one IRLS step for the offsets per trial (weights of the trial positions, a
majorise-minimise step) the iteration reached a stationary point, but on one of 18 soft-L1
problems (12 x 8, both offsets, seed 3 of ``tests/toa/test_varpro.py``) it took 867
iterations against 57 for the joint engine, the lagging weights slowing the final rate.

The offset gauge (``d_i + c, o_j - c`` with both kinds) is the null vector v of ``A^T W A``;
it is handled analytically: ``A^T W A + alpha v v^T`` is positive definite on a connected
observation graph and equals the pseudo-inverse on right-hand sides orthogonal to v (all of
them here, ``v^T A^T = 0``), and the shift is set so that ``sum d - sum o`` keeps its
starting value, the convention of the dense engine (which projects the shift off each step).
Offsets "none" have nothing to project and run :func:`full_lm`;
so do partial refits (a ``free`` mask), where the fixed nodes already hold the frame.

Measured (not the default, :data:`VARPRO_DEFAULT` is False). Same run, 12 x 6 with both offsets, the benchmark scene of ``benchmarks/bench_toa_minimal.py``
(2 shared cores, loaded; ``python benchmarks/bench_toa_varpro.py``):

- per start (the search's starts of seeds 0-39, 1090 starts, each run to convergence or 500
  iterations, least squares): converged 79 % vs 50 % for the joint engine, median 160 vs 496
  iterations, 0.50 vs 0.38 ms per iteration (an earlier Schur-complement form; the fixed
  projector form is on par: 0.42-0.56 vs 0.43-0.56 ms on the same draws), 124 vs 140 s CPU
  in all. The starts that reach the draw's lowest basin get there in a median 82 vs 125
  iterations. But 52 % of VarPro's starts end with a source beyond 100 m (34 % beyond 1 km)
  against 4.5 % for the joint engine (seeds 40-47): with the offsets eliminated, the
  far-field valley (a source receding along its direction while its offset absorbs the
  range) is followed to its end instead of crawled along, and its end has a lower cost.
  Geodesic acceleration (Transtrum & Sethna 2012) on top converged still more starts (89 %,
  median 112 iterations) at 0.62 ms per iteration, with the same far-field ends (43 %); not kept.
- blind ``solve_toa``, seeds 0-199: in the basin (cost at most the truth-started fit's + 0.01
  sigma^2) 165 joint vs 176 VarPro (25 gained, 14 lost, McNemar p = 0.11), CPU median 0.94
  vs 0.85 s; the same minimum as the truth-started fit 59 vs 61; a source beyond 100 m in
  3 vs 49 results (13 for the truth-started fit), and 3 VarPro solves (seeds 15, 19, 160)
  raised DegenerateGeometryError: the first round ended with every source about 3.9 km away
  and the outlier round's refit from there (1800 km) could not fix the gauge.
- the same with the race over the starts of the merged search (main at 655ad68), seeds 0-47:
  in the basin 44 joint vs 40 VarPro (4 gained, 8 lost, McNemar p = 0.39), CPU median 2.11 vs
  1.39 s (paired ratio 0.68), a source beyond 100 m in 2 vs 11 results (3 for the
  truth-started fit), one VarPro solve raised (seed 44).

References
----------
Golub, G. H. & Pereyra, V. (1973). The differentiation of pseudo-inverses and nonlinear least
squares problems whose variables separate. SIAM J. Numer. Anal. 10(2), 413-432.
Kaufman, L. (1975). A variable projection method for solving separable nonlinear least
squares problems. BIT 15, 49-57.
Hong, J. H., Zach, C. & Fitzgibbon, A. (2017). Revisiting the variable projection method for
separable nonlinear least squares problems. CVPR, 5939-5947.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.linalg import lapack

from ...optim.lm import FTOL, levenberg_marquardt
from ...optim.steps import DenseStep
from .model import _node_indices
from .schur_lm import DEFAULT_MAX_IT, Pairs, RangeModel

# FTOL (the relative cost decrease that stops) is read from this module at each call

Array = NDArray[np.float64]

__all__ = ["VARPRO_DEFAULT", "full_lm", "solve_dense_lm", "solve_varpro_lm"]


#: default of ``solve_dense_lm(varpro=None)``: whether full fits of offset-bearing models
#: eliminate the offsets (:func:`solve_varpro_lm`); see the module docstring for the measurements
VARPRO_DEFAULT = False


def solve_dense_lm(
    theta0: Array, y: Array, ii: NDArray[np.intp], jj: NDArray[np.intp], I: int, J: int, d: int,
    offsets: str, loss: str, f_scale: float, max_nfev: int | None, xtol: float,
    free: NDArray[np.bool_] | None = None, max_it: int = 100, varpro: bool | None = None,
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
    varpro : eliminate the offsets by variable projection
        (:func:`solve_varpro_lm`: LM on the positions, the offsets re-solved
        at every trial) instead of damping them with the positions; default
        :data:`VARPRO_DEFAULT`. Only full fits of models with offsets are affected.

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
    if VARPRO_DEFAULT if varpro is None else varpro:
        return solve_varpro_lm(theta0, y, ii, jj, I, J, d, offsets, loss, f_scale, max_nfev, xtol,
                               free=free, max_it=max_it)
    return full_lm(theta0, y, ii, jj, I, J, d, offsets, loss, f_scale, max_nfev, xtol, free=free, max_it=max_it)


def full_lm(
    theta0: Array, y: Array, ii: NDArray[np.intp], jj: NDArray[np.intp], I: int, J: int, d: int,
    offsets: str, loss: str, f_scale: float, max_nfev: int | None, xtol: float,
    free: NDArray[np.bool_] | None = None, max_it: int = DEFAULT_MAX_IT["dense"],
) -> tuple[Array, bool, int]:
    """The joint LM of :func:`solve_dense_lm` (positions and offsets damped together); same
    parameters (without ``varpro``) and return: :class:`selfcal.toa.engine.schur_lm.RangeModel`
    on the observed pairs with the dense step."""
    r_idx, s_idx, _ = _node_indices(I, J, d, offsets)
    model = RangeModel(r_idx, s_idx, Pairs(ii, jj, I, J), np.asarray(y, float), d, I, loss, f_scale, "dense",
                       free=free)
    out = levenberg_marquardt(model, np.array(theta0, dtype=float), max_iter=max_nfev or max_it, xtol=xtol,
                              ftol=FTOL)
    return out.x, out.converged, out.iterations


def solve_varpro_lm(
    theta0: Array, y: Array, ii: NDArray[np.intp], jj: NDArray[np.intp], I: int, J: int, d: int,
    offsets: str, loss: str, f_scale: float, max_nfev: int | None, xtol: float,
    free: NDArray[np.bool_] | None = None, max_it: int = 100,
) -> tuple[Array, bool, int]:
    """Levenberg-Marquardt on the positions with the offsets projected out (variable projection).

    Same call and return as :func:`solve_dense_lm`.

    Parameters
    ----------
    theta0 : (n,) start, receiver-major ``[r (I d), s (J d), d_i (I)?, o_j (J)?]`` (metres);
        its offsets only set the offset gauge (``sum d - sum o``): the offsets are re-solved
        at the start's geometry.
    y : (m,) observed ranges (metres); ii, jj : (m,) their receiver and source indices.
    I, J, d, offsets : the model (:mod:`selfcal.toa.engine.nls`).
    loss, f_scale : loss and its scale; any loss but "linear" runs the joint engine.
    max_nfev : iteration cap (default ``max_it``); xtol : relative step tolerance.
    free : (n,) bool mask of fitted parameters; when given (a partial refit) or when the
        model has no offsets, the call is :func:`full_lm`'s.

    Returns
    -------
    (theta, converged, iterations): the point (offsets included, in the dense engine's
    gauge), whether a stopping rule was met, iterations (normal matrices formed).

    Notes
    -----
    Per iteration O(m^2 k + m k^2) for the reduced normal matrix ``(P J_x)^T (P J_x)``
    (k = (I + J) d positions, P the (m, m) projector formed once in O(m^2 p + p^3)) and
    O(k^3 / 3) per damping trial, which costs one product ``P (dist - y)``. The projector
    needs the offsets determined by the observation pattern (every node observed and, with
    both kinds, a connected bipartite graph); otherwise the joint engine runs.

    Examples
    --------
    >>> import numpy as np
    >>> from selfcal.toa.engine import nls
    >>> g = np.random.default_rng(0)
    >>> r, s = g.uniform(0, 1.5, (12, 3)), g.normal(0, 2, (6, 3))
    >>> Y = nls.toa_model(r, s, g.uniform(0, 3, 12), g.uniform(0, 30, 6))
    >>> ii, jj = np.nonzero(np.isfinite(Y))
    >>> th0 = nls._pack(r + 0.05, s - 0.05, np.zeros(12), np.zeros(6))
    >>> th, ok, nit = solve_varpro_lm(th0, Y[ii, jj], ii, jj, 12, 6, 3, "both", "linear", 1.0, None, 1e-12)
    >>> bool(ok) and float(np.abs(nls.toa_residuals(th, Y, 3, "both")).max()) < 1e-6
    True
    """
    has_r, has_s = offsets in ("receivers", "both"), offsets in ("sources", "both")
    if not (has_r or has_s) or loss != "linear" or (free is not None and not bool(np.all(free))):
        return full_lm(theta0, y, ii, jj, I, J, d, offsets, loss, f_scale, max_nfev, xtol,
                       free=free, max_it=max_it)
    theta = np.array(theta0, dtype=float)
    k = (I + J) * d
    m = y.size
    # the offset design A (m, p) and the projector P = I - A (A^T A)^+ A^T off its columns
    cols = ([np.eye(I)[ii]] if has_r else []) + ([np.eye(J)[jj]] if has_s else [])
    A = np.hstack(cols)
    G = A.T @ A
    v = np.concatenate([np.ones(I), -np.ones(J)]) if has_r and has_s else None
    if v is not None:  # the offset gauge d + c, o - c: null vector of G, made positive definite
        G += (float(np.trace(G)) / G.shape[0] / v.size) * np.outer(v, v)
    fac, info = lapack.dpotrf(G, lower=1, clean=1)
    if info != 0:  # offsets not determined by the pattern: the joint engine
        return full_lm(theta0, y, ii, jj, I, J, d, offsets, loss, f_scale, max_nfev, xtol, max_it=max_it)
    AG, _ = lapack.dpotrs(fac, A.T, lower=1)  # (A^T A)^+ A^T on the gauge-free complement
    Pm = -A @ AG
    Pm.ravel()[:: m + 1] += 1.0
    shift0 = float(v @ theta[k:]) if v is not None else 0.0
    r_idx, s_idx, _ = _node_indices(I, J, d, "none")

    class Projected(RangeModel):
        """The positions' cost with the offsets projected out; a step moves the positions only
        (the range model without offsets, its residuals and Jacobian projected by ``Pm``)."""

        def evaluate(self, t: Array) -> tuple[float, tuple[Array, Array, Any]]:
            U, dist = self.geometry(t)
            f = Pm @ (dist - y)
            return 0.5 * float(f @ f), (f, dist, U)

        def linearize(self, t: Array, state: tuple[Array, Array, Any]) -> DenseStep:
            f, _, U = state
            Jx = self.jacobian(U)
            Jr = Pm @ Jx  # the reduced Jacobian (exact: A does not depend on the positions)
            # gradient Jx^T f = Jr^T f, since P f = f
            return DenseStep(np.dot(Jr.T, Jr), np.dot(Jx.T, f), self.dstep, self.projector(t), None, k)

        def retract(self, t: Array, dx: Array) -> Array:
            trial = t.copy()
            trial[:k] += dx
            return trial

        def small_step(self, t: Array, dx: Array, xtol: float) -> bool:
            return math.sqrt(float(dx @ dx)) <= xtol * (xtol + math.sqrt(float(t[:k] @ t[:k])))

    model = Projected(r_idx, s_idx, Pairs(ii, jj, I, J), y, d, I, "linear", 1.0, "dense")
    out = levenberg_marquardt(model, theta, max_iter=max_nfev or max_it, xtol=xtol, ftol=FTOL)
    theta, converged, it = out.x, out.converged, out.iterations
    dist = out.state[1]
    # the offsets of the final geometry, in the gauge of the start (sum d - sum o kept)
    z = AG @ (y - dist)
    if v is not None:
        z += ((shift0 - float(v @ z)) / v.size) * v
    theta[k:] = z
    return theta, converged, it
