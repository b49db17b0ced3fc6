"""The ``selfcal`` command: groups from :mod:`selfcal.commands._base`, commands per area.

Each module imported below attaches its commands to the groups; heavy imports
(matplotlib, dask, pyroomacoustics) happen inside the commands so that
``selfcal --help`` stays fast.
"""

from __future__ import annotations

import importlib

from .commands._base import main

_COMMAND_MODULES = ("toa", "graph", "toa_reproduce", "delays", "farfield", "aoa", "slac", "acoustics", "demo",
                    "plan")

for _name in _COMMAND_MODULES:
    importlib.import_module(f"selfcal.commands.{_name}")

__all__ = ["main"]

if __name__ == "__main__":  # pragma: no cover
    main()
