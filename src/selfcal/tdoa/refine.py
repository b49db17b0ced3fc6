"""Refinement of a far-field TDOA reconstruction (paper 000, section 2.3).

Cost (paper 000, eq. 1, Problem 3), generalised with weights, missing entries and a robust
loss::

    F(Z, N, C) = sum_ij  delta^2 rho( (D_ij - z_i . n_j - C_j)^2 / delta^2 ),  |n_j| = 1,

over the observed entries, with ``z_1 = 0`` fixed (the gauge of Lemma 1). With
``free_offsets=False`` the offsets are pinned to ``C_j = D_1j`` and the cost is exactly the
paper's ``||Dbar - Z N||_F^2`` on the reduced matrix; with ``free_offsets=True`` the ``C_j``
are estimated too (the maximum-likelihood cost under i.i.d. noise on D, and the one that
keeps a corrupted first row from spoiling whole columns).

* :func:`refine_alternating` -- Algorithm 2: exact least squares for Z given N, then each
  ``n_j`` on the unit sphere, either globally (:func:`sphere_lstsq_global`, the secular
  equation) or locally (:func:`sphere_lstsq_local`, Gauss-Newton on the sphere).
* :func:`refine_lm` -- Algorithm 3: Levenberg-Marquardt with the exponential-map
  re-parametrisation ``n_j <- exp_{n_j}(T_j v_j)`` (T_j a tangent basis), Marquardt scaling
  ``J^T J + lambda diag(J^T J)``. The block structure (z_i couple to every column, each
  column's unknowns only to themselves) is used through a Schur complement, so one step
  costs O(m k + m^3) rather than a dense solve in 3m + 3k unknowns.

Robust losses are handled by iteratively re-weighted least squares (weights ``rho'``).

:func:`farfield_crlb` gives the Cramer-Rao bound of the positions (rigid gauge removed).
Audit (issue 4): with ``free_offsets=True`` LM reaches the same minimum as an independent
``scipy.optimize.least_squares`` and meets the bound at low noise; that it barely lowers
the error of the initialisation there is because the initialisation is already within
1.0-1.4x of the bound in MSE. At high noise relative to the array (sigma = 0.1, unit cube,
m = k = 10) the ML estimate is biased outwards (each column's direction and offset are fitted
from only m entries, so a larger array absorbs more noise) and can be worse than the
initialisation; in about a quarter of such draws the ML minimum itself (reached by LM
even when started at the true geometry) has nearly coplanar directions and a stretched
array. See ``selfcal.experiments.farfield.FINDING``. :func:`selfcal.tdoa.solve_farfield`
flags such solutions (``warnings``: ``directions-collapsed``, threshold
``selfcal.tdoa.solve.COLLAPSE_RATIO``).

One job per module: :mod:`.model` (losses, residuals, Jacobian, normal equations),
:mod:`.alternating` (Algorithm 2), :mod:`.lm` (Algorithm 3), :mod:`.covariance` and
:mod:`.crlb`; this module names the refinements (:data:`REFINERS`) and re-exports what its
importers use.
"""

from __future__ import annotations

from ..robust import LOSSES
from .alternating import refine_alternating
from .covariance import position_covariance
from .crlb import farfield_crlb
from .lm import COV_DIRECT_MAX, _lm_step, refine_lm
from .model import RefineResult, _normal_equations, farfield_residuals, loss_weight

__all__ = ["LOSSES", "REFINERS", "RefineResult", "loss_weight", "farfield_residuals", "refine_alternating",
           "refine_lm", "position_covariance", "farfield_crlb", "COV_DIRECT_MAX"]

#: the refinements by name (``solve_farfield(method=...)``), registry style
REFINERS = {"lm": refine_lm, "alternating": refine_alternating}

_PRIVATE = (_lm_step, _normal_equations)  # tests and benchmarks import them from here
