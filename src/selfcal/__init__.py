"""selfcal: self-calibration and localization of sensor networks.

The public API is re-exported here lazily, so ``import selfcal`` stays cheap and a
solver's dependencies load only when it is used::

    import selfcal
    result = selfcal.solve_toa(ranges, dim=3)
"""

from __future__ import annotations

import importlib
from typing import Any

from .errors import ConvergenceWarning, DegenerateGeometryError, InputError, SelfcalError

__version__ = "0.1.0"

# public name -> module that defines it
_LAZY: dict[str, str] = {
    "solve_toa": "selfcal.toa",
    "ToaResult": "selfcal.toa",
    "solve_toa_sparse": "selfcal.toa",
    "solve_farfield": "selfcal.tdoa",
    "FarfieldResult": "selfcal.tdoa",
    "solve_aoa": "selfcal.aoa",
    "AoaResult": "selfcal.aoa",
    "solve_slac": "selfcal.slac",
    "SlacResult": "selfcal.slac",
    "SlacLog": "selfcal.slac",
    "solve_range_slac": "selfcal.slac",
    "RangeLog": "selfcal.slac",
    "run_pipeline": "selfcal.acoustics",
    "PipelineResult": "selfcal.acoustics",
    "load_recording": "selfcal.acoustics",
    "simulate_conference": "selfcal.acoustics",
    "load_lps": "selfcal.datasets",
    "load_plaza": "selfcal.datasets",
    "load_pyramic": "selfcal.datasets",
    "Degeneracy": "selfcal.errors",
    "Status": "selfcal.errors",
    "align": "selfcal.geometry",
    "aligned_rmse": "selfcal.metrics",
    "read_matrix": "selfcal.io",
    "read_table": "selfcal.io",
    "write_json": "selfcal.io",
    "run_sweep": "selfcal.experiments",
}

__all__ = ["ConvergenceWarning", "DegenerateGeometryError", "InputError", "SelfcalError", "__version__", *_LAZY]


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'selfcal' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(__all__)
