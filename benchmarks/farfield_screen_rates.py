"""False alarms and detections of the far-field gross-error screen on small arrays (issue 16 table).

Run: ``PYTHONPATH=src python benchmarks/farfield_screen_rates.py [M K ...]`` (default: the issue's
sizes); one JSON line per size.
"""

from __future__ import annotations

import json
import sys
from typing import Any

import numpy as np


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def screen_rates(m: int, k: int, *, clean: int = 100, gross: int = 30, sigma: float = 1e-4,
                 error: float = 1.0, seed: int | None = None) -> dict[str, Any]:
    """False alarms and detections of the default gross-error screen on a 5 cm array (issue 16 table).

    ``clean`` matrices of m microphones uniform in a 5 cm cube and k random far-field sources
    (unit offsets, ``sigma`` metres of Gaussian noise), then ``gross`` more with ``error``
    metres added to one random entry, each screened by
    :func:`~selfcal.tdoa.screen.gross_error_screen` (family-wise false-alarm rate 1 %).

    Parameters
    ----------
    m, k : matrix size; clean, gross : numbers of draws; sigma, error : metres;
    seed : base seed (default ``7 + 100 m + k``).

    Returns
    -------
    dict: ``false_alarms`` (clean draws with any flag), ``caught`` (gross entries flagged),
    ``extra`` (other entries flagged in the gross draws), ``methods`` (count per screen
    method), ``untestable_median`` (entries reported unchecked, clean draws), ``cpu_s``.

    Examples
    --------
    >>> out = screen_rates(4, 6, clean=2, gross=1)
    >>> out["untestable_median"], out["caught"]      # 4 x 6: no spare measurement at all
    (24.0, 0)
    """
    import time

    from selfcal.tdoa.screen import gross_error_screen

    rng = np.random.default_rng(7 + 100 * m + k if seed is None else seed)

    def draw() -> np.ndarray:
        Z = rng.uniform(-0.025, 0.025, (m, 3))
        N = _unit(rng.normal(size=(k, 3)))
        return Z @ N.T + rng.normal(size=k) + sigma * rng.standard_normal((m, k))

    t0 = time.process_time()
    false, unt = 0, []
    for _ in range(clean):
        g = gross_error_screen(draw())
        false += bool(g.mask.any())
        unt.append(int(g.untestable.sum()))
    caught = extra = 0
    methods: dict[str, int] = {}
    for _ in range(gross):
        D = draw()
        i, j = int(rng.integers(m)), int(rng.integers(k))
        D[i, j] += error
        g = gross_error_screen(D)
        caught += bool(g.mask[i, j])
        extra += int(g.mask.sum()) - int(g.mask[i, j])
        methods[g.method] = methods.get(g.method, 0) + 1
    return {"m": m, "k": k, "false_alarms": false, "clean": clean, "caught": caught, "gross": gross,
            "extra": extra, "methods": methods, "untestable_median": float(np.median(unt)) if unt else 0.0,
            "cpu_s": time.process_time() - t0}


if __name__ == "__main__":
    sizes = [int(a) for a in sys.argv[1:]] or [5, 7, 6, 8, 8, 9, 10, 6, 20, 6, 12, 12]
    for m, k in zip(sizes[::2], sizes[1::2], strict=True):
        print(json.dumps(screen_rates(m, k)), flush=True)
