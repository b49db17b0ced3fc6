"""Anchor-free TOA / range self-calibration (papers 003 and 004).

- :func:`solve_toa` / :class:`ToaResult`: the end-to-end solver (validation,
  initialisation, sparse NLS refinement, covariances).
- :func:`refine_toa` / :class:`NlsSolution` (:mod:`.nls`): the sparse nonlinear least
  squares engine for ``|r_i - s_j| + d_i + o_j`` shared by every initialiser.
- :func:`toa_crlb` / :class:`CrlbResult` (:mod:`.crlb`): the gauge-free Cramér-Rao bound.
- :mod:`.mds` (003 Algorithms 1/2, scalable initialiser), :mod:`.offsets` (004 rank-3).
"""

from __future__ import annotations

from .crlb import CrlbResult, toa_crlb
from .nls import NlsSolution, refine_toa, toa_jacobian, toa_model, toa_residuals
from .solve import ResidualTest, ToaResult, n_parameters, residual_test, solve_toa

__all__ = [
    "CrlbResult",
    "NlsSolution",
    "ResidualTest",
    "ToaResult",
    "n_parameters",
    "refine_toa",
    "residual_test",
    "solve_toa",
    "toa_crlb",
    "toa_jacobian",
    "toa_model",
    "toa_residuals",
]
