"""Far-field TDOA self-calibration (paper 000).

``solve_farfield(D)`` recovers receiver positions, unit transmitter directions and
per-transmitter offsets from relative distances ``D_ij = z_i . n_j + C_j``; see
:mod:`selfcal.tdoa.farfield`. ``solve_farfield(D, dim=2 | 1 | "auto")`` calibrates planar
and linear arrays (the determined part of paper 000's degenerate cases).

The package exports the entry points: the solver and its result, the batched minimal
solver (:func:`solve_minimal`, Algorithm 1), refinement from a given start
(:func:`refine_lm`, Algorithm 3), the failure-mode analysis (:func:`analyse_degeneracy`) and
the Cramer-Rao bound (:func:`farfield_crlb`). The building blocks stay importable from
their modules: :mod:`~selfcal.tdoa.initialize` (overdetermined initialisation),
:mod:`~selfcal.tdoa.alternating` (Algorithm 2), :mod:`~selfcal.tdoa.lm`,
:mod:`~selfcal.tdoa.model` (residuals, Jacobian), :mod:`~selfcal.tdoa.screen` (gross-error
screening, RANSAC), :mod:`~selfcal.tdoa.orientation` (the transposed-layout check),
:mod:`~selfcal.tdoa.degeneracy` (quadric fit, the degeneracy table).
"""

from __future__ import annotations

from .crlb import farfield_crlb
from .degeneracy import DegeneracyReport, analyse_degeneracy
from .farfield import solve_farfield
from .lm import refine_lm
from .minimal import MinimalSolution, solve_minimal
from .model import RefineResult
from .result import FarfieldResult

__all__ = [
    "DegeneracyReport",
    "FarfieldResult",
    "MinimalSolution",
    "RefineResult",
    "analyse_degeneracy",
    "farfield_crlb",
    "refine_lm",
    "solve_farfield",
    "solve_minimal",
]


def __dir__() -> list[str]:
    return sorted(__all__)
