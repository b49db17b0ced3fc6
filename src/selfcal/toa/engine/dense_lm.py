"""The dense engine of small range problems: the joint iteration (:mod:`selfcal.toa.engine.joint_lm`)
or, with ``varpro``, the offsets projected out (:mod:`selfcal.toa.engine.varpro`).

The iteration, its gauge projector and its measured costs are documented in
:mod:`selfcal.toa.engine.joint_lm`; this module only chooses between the two (the joint
iteration lives below both so that the variable-projection engine, which falls back to it,
does not import its dispatcher).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from .joint_lm import DenseStep, GaugeProjector, damping_after_success, full_lm

Array = NDArray[np.float64]

__all__ = ["VARPRO_DEFAULT", "DenseStep", "GaugeProjector", "damping_after_success", "full_lm", "solve_dense_lm"]


#: default of ``solve_dense_lm(varpro=None)``: whether full fits of offset-bearing models
#: eliminate the offsets (:mod:`selfcal.toa.engine.varpro`); see that module's notes for the measurements
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
        (:func:`selfcal.toa.engine.varpro.solve_varpro_lm`: LM on the positions, the offsets re-solved
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
        from .varpro import solve_varpro_lm

        return solve_varpro_lm(theta0, y, ii, jj, I, J, d, offsets, loss, f_scale, max_nfev, xtol,
                               free=free, max_it=max_it)
    return full_lm(theta0, y, ii, jj, I, J, d, offsets, loss, f_scale, max_nfev, xtol, free=free, max_it=max_it)
