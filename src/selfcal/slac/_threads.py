"""Limit the BLAS thread pools of numpy and scipy (private helper).

The filter does many small (~100 x 100) dense operations per step, where OpenBLAS threads
only add synchronisation cost (10x slower on a loaded 2-core machine). No third-party
dependency (threadpoolctl is not installed): the OpenBLAS libraries already loaded by numpy /
scipy are found in ``/proc/self/maps`` and their ``*_set_num_threads`` symbol is called.
"""

from __future__ import annotations

import ctypes
import os

__all__ = ["limit_blas_threads"]

_SYMBOLS = (
    "scipy_openblas_set_num_threads64_",
    "scipy_openblas_set_num_threads",
    "openblas_set_num_threads64_",
    "openblas_set_num_threads",
)


def limit_blas_threads(n: int = 1) -> int:
    """Set every loaded OpenBLAS pool to ``n`` threads; returns how many pools were set."""
    import numpy  # noqa: F401  (make sure the libraries are loaded)
    import scipy.linalg  # noqa: F401

    paths: set[str] = set()
    try:
        with open("/proc/self/maps") as fh:
            for line in fh:
                p = line.split()[-1]
                if "openblas" in os.path.basename(p).lower() and p.endswith(".so") or ".so." in p and "openblas" in p:
                    paths.add(p)
    except OSError:
        return 0
    done = 0
    for p in paths:
        try:
            lib = ctypes.CDLL(p)
        except OSError:
            continue
        for sym in _SYMBOLS:
            fn = getattr(lib, sym, None)
            if fn is not None:
                fn(int(n))
                done += 1
                break
    return done
