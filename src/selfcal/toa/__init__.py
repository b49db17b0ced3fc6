"""Anchor-free TOA / range self-calibration (papers 003 and 004).

- :func:`solve_toa` / :class:`ToaResult` (:mod:`.solve`, :mod:`.result`): the entry point.
- :mod:`.fit`: one model fitted robustly (screen, drop, search, outliers, refit, trust test).
- :mod:`.search` / :mod:`.moves`: the one search (initialiser registry, plane moves).
- :mod:`.robust`: gross entries, the outlier rule, node dropping.
- :mod:`.select`: ``offsets="auto"`` (BIC) and ``dim="auto"`` (F test, planarity).
- :mod:`.model`: the range model ``|r_i - s_j| + d_i + o_j`` (:func:`toa_model`, residuals,
  Jacobian, gauge, parameter layout) that every engine below shares.
- :func:`refine_toa` / :class:`NlsSolution` (:mod:`.nls`): the sparse nonlinear least
  squares engine for the model, the only fit of the model.
- :mod:`.schur_lm`: the Levenberg-Marquardt driver of ``refine_toa`` (dense grid or pairs).
- :func:`solve_toa_sparse` / :func:`refine_toa_sparse` (:mod:`.sparse`): observed-pairs
  path for large sparse networks (multilateration growth from a dense seed patch).
- :func:`toa_crlb` / :class:`CrlbResult` (:mod:`.crlb`): the gauge-free Cramér-Rao bound.
- :mod:`.mds` (003 Algorithms 1/2, scalable initialiser), :mod:`.rank3` (004 rank-3).
"""

from __future__ import annotations

from .engine.crlb import CrlbResult, toa_crlb
from .engine.model import NlsSolution, toa_jacobian, toa_model, toa_residuals
from .engine.nls import refine_toa
from .result import (
    GeometryTest,
    ResidualTest,
    ToaResult,
    geometry_test,
    n_parameters,
    residual_test,
)
from .solve import solve_toa
from .sparse import SparseToaResult, refine_toa_sparse, solve_toa_sparse

__all__ = [
    "CrlbResult",
    "GeometryTest",
    "NlsSolution",
    "ResidualTest",
    "SparseToaResult",
    "ToaResult",
    "geometry_test",
    "n_parameters",
    "refine_toa",
    "refine_toa_sparse",
    "residual_test",
    "solve_toa",
    "solve_toa_sparse",
    "toa_crlb",
    "toa_jacobian",
    "toa_model",
    "toa_residuals",
]
