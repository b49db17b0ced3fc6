"""Far-field TDOA self-calibration (paper 000).

``solve_farfield(D)`` recovers receiver positions, unit transmitter directions and
per-transmitter offsets from relative distances ``D_ij = z_i . n_j + C_j``; see
:mod:`selfcal.tdoa.farfield`. The building blocks are public: the batched minimal solver
(:func:`solve_minimal`, Algorithm 1), the failure-mode analysis (:func:`analyse_degeneracy`),
the overdetermined initialisation (:func:`initialize_farfield`), alternating optimisation
(:func:`refine_alternating`, Algorithm 2) and Levenberg-Marquardt on the spheres
(:func:`refine_lm`, Algorithm 3). ``solve_farfield(D, dim=2 | 1 | "auto")`` calibrates planar
and linear arrays (the determined part of paper 000's degenerate cases); the transposed
layout is refused by :func:`check_orientation`.
"""

from .degeneracy import DEGENERACIES, DegeneracyReport, analyse_degeneracy, fit_quadric
from .farfield import (
    FarfieldInit,
    FarfieldResult,
    check_orientation,
    fit_A_nonlinear,
    initialize_farfield,
    lowrank_fit,
    ransac_farfield,
    reduce_matrix,
    screen_gross_errors,
    solve_farfield,
)
from .minimal import MinimalSolution, solve_minimal
from .refine import (
    RefineResult,
    farfield_crlb,
    farfield_jacobian,
    farfield_residuals,
    refine_alternating,
    refine_lm,
    sphere_lstsq_global,
    sphere_lstsq_local,
)

__all__ = [
    "DEGENERACIES",
    "DegeneracyReport",
    "FarfieldInit",
    "FarfieldResult",
    "MinimalSolution",
    "RefineResult",
    "analyse_degeneracy",
    "check_orientation",
    "farfield_crlb",
    "farfield_jacobian",
    "farfield_residuals",
    "fit_A_nonlinear",
    "fit_quadric",
    "initialize_farfield",
    "lowrank_fit",
    "ransac_farfield",
    "reduce_matrix",
    "refine_alternating",
    "refine_lm",
    "screen_gross_errors",
    "solve_farfield",
    "solve_minimal",
    "sphere_lstsq_global",
    "sphere_lstsq_local",
]
