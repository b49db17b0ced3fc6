"""selfcal.slac: simultaneous localization and calibration of antenna responses and ranging biases (paper 002).

Modules: :mod:`~selfcal.slac.antenna` (manifold separation, eqs. 7-9), :mod:`~selfcal.slac.signals`
(OFDM snapshots, eqs. 3-4), :mod:`~selfcal.slac.likelihood` (concentrated likelihoods, eqs. 18-19),
:mod:`~selfcal.slac.motion` (eq. 14), :mod:`~selfcal.slac.filter` (IEKF-like MAP filter, eqs. 20-26; its
state layout :mod:`~selfcal.slac.state`, link bookkeeping :mod:`~selfcal.slac.links`, MAP / Laplace update
:mod:`~selfcal.slac.laplace`, linear algebra :mod:`~selfcal.slac.linalg`),
:mod:`~selfcal.slac.doa` (coherent ML DoA),
:mod:`~selfcal.slac.run` (logs and :func:`solve_slac`), :mod:`~selfcal.slac.smoother` (optional fixed-lag
smoother, beyond the paper), :mod:`~selfcal.slac.ranging` (one robot, odometry + beacon ranges with
per-beacon scale and offset: robust filter and batch smoother, :func:`solve_range_slac`),
:mod:`~selfcal.slac.export` (trajectory CSV / TUM).
"""

from __future__ import annotations

import importlib
from typing import Any

#: the entry points (the building blocks stay in their modules: ``selfcal.slac.likelihood``, ...)
_LAZY = {
    "SlacLog": "run", "SlacResult": "run", "solve_slac": "run",
    "SlacConfig": "filter", "SlacFilter": "filter", "SlacSmoother": "smoother",
    "estimate_doa": "doa",
    "RangeLog": "ranging", "RangeModelConfig": "ranging", "RangeSlacResult": "ranging",
    "solve_range_slac": "ranging", "write_trajectory_csv": "export", "write_trajectory_tum": "export",
}
__all__ = sorted(_LAZY)


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        return getattr(importlib.import_module(f"selfcal.slac.{_LAZY[name]}"), name)
    raise AttributeError(name)
