"""Loaders for public real data sets; every loader takes the path to the user's copy."""

from __future__ import annotations

import importlib
from typing import Any

_LAZY = {"load_lps": "selfcal.datasets.lps", "load_plaza": "selfcal.datasets.plaza", "load_pyramic": "selfcal.datasets.pyramic"}
__all__ = list(_LAZY)


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(name)
