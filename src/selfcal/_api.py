"""Package-level name resolution shared by the subpackages' ``__init__`` modules.

A subpackage exports its entry points; a building block that it once exported stays
reachable there for a transition, with a ``DeprecationWarning`` that names its module.
"""

from __future__ import annotations

import importlib
import warnings
from collections.abc import Callable, Mapping
from typing import Any

__all__ = ["moved_names"]


def moved_names(package: str, moved: Mapping[str, str]) -> Callable[[str], Any]:
    """A module ``__getattr__`` that resolves the names of ``moved`` from their modules.

    Parameters
    ----------
    package : str
        The package's ``__name__``.
    moved : mapping
        Former package-level name -> submodule (relative to ``package``) that defines it.

    Returns
    -------
    callable
        ``__getattr__(name)``: the object, with a ``DeprecationWarning``, for a moved name;
        ``AttributeError`` for any other.
    """

    def __getattr__(name: str) -> Any:
        if name in moved:
            home = f"{package}.{moved[name]}"
            warnings.warn(f"{package}.{name} is a building block: import it from {home}",
                          DeprecationWarning, stacklevel=2)
            return getattr(importlib.import_module(home), name)
        raise AttributeError(f"module {package!r} has no attribute {name!r}")

    return __getattr__
