"""Benchmark "basin rates": wrong basins of the TOA search on generic 8 x 10 networks (3-D, both offsets).

The draw of ``tests/toa/test_planarity.py`` / ``benchmarks/planarity_rates.py`` (generic
family): 8 receivers x 10 sources in an 8 x 7 x 3 m room, offsets uniform up to 20 / 30 ms,
1 us timing noise, c = 343 m/s; ``solve_toa(T, dim=3, offsets="both", speed=c)`` with the
noise not given (the CLI's default). Two configurations on the same seeds, interleaved in
one process:

- ``before``: the scaled starts only where the rank-d method is not identifiable (the rule
  before: 12 x 6 in 3-D), so at 8 x 10 the race has the 004 and 003 starts alone;
- ``after``: the scaled starts also where it is barely identifiable
  (:func:`selfcal.toa.init.starts._offsets_weakly_identified`).

Per configuration: draws in a wrong basin (the answer's sum of squares above the truth-started
refinement's by more than 1e-6 relative), of those reported as a success (exit 0); draws
with a node outside 3 of its own error bars (``tests/toa/outlier_families.outside``) with
exit 0, and with exit 1; false alarms (exit 1, every node within its bars); the search's
CPU time. And, on the draws where both land in the truth's basin, the largest difference
of the answers' positions after a rigid alignment (metres: the change on well-posed draws).

Run: ``OPENBLAS_NUM_THREADS=1 PYTHONPATH=src python benchmarks/basin_rates.py [first [count]]``
(default seeds 0-199, about 0.8 s per draw and configuration).
"""

from __future__ import annotations

import sys
import time
import warnings
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "toa"))

C = 343.0
NOISE = 1e-6


def draw(seed: int, I: int = 8, J: int = 10) -> tuple[np.ndarray, ...]:
    """Receivers, sources (m), offsets (s) and the TOA matrix (s) of one generic draw."""
    g = np.random.default_rng(seed)
    R = np.c_[g.uniform(0, 8, I), g.uniform(0, 7, I), g.uniform(0, 3, I)]
    S = np.c_[g.uniform(0, 8, J), g.uniform(0, 7, J), g.uniform(0, 3, J)]
    D = np.linalg.norm(R[:, None] - S[None], axis=-1)
    d, o = g.uniform(0, 0.02, I), g.uniform(0, 0.03, J)
    return R, S, d, o, D / C + d[:, None] + o[None] + g.normal(0, NOISE, (I, J))


def run(first: int = 0, count: int = 200) -> dict[str, Any]:
    """Counts per configuration over seeds ``first .. first + count - 1``; prints and returns them."""
    from outlier_families import outside

    import selfcal.toa.init.starts as starts
    from selfcal.geometry import align
    from selfcal.toa import solve_toa
    from selfcal.toa.engine.nls import refine_toa

    rule = starts._offsets_weakly_identified
    configs = {"before": starts._offsets_unidentified, "after": rule}
    keys = ("wrong_basin", "wrong_basin_exit0", "outside_exit0", "outside_exit1", "false_alarm", "right")
    stats: dict[str, dict[str, Any]] = {k: {**{x: 0 for x in keys}, "cpu_s": 0.0, "seeds": []} for k in configs}
    max_change = 0.0
    try:
        for seed in range(first, first + count):
            R, S, d, o, T = draw(seed)
            Y = T * C
            truth = refine_toa(Y, R, S, offsets="both", receiver_offsets0=d * C, source_offsets0=o * C,
                               covariance=False)
            ss_truth = float(np.nansum(truth.residuals ** 2))
            got = {}
            for name, fn in configs.items():
                starts._offsets_weakly_identified = fn
                t0 = time.process_time()
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")
                    res = solve_toa(T, dim=3, offsets="both", speed=C, rng=seed)
                st = stats[name]
                st["cpu_s"] += time.process_time() - t0
                ss = float(np.nansum((np.asarray(res.residuals) * C) ** 2))
                wrong = ss > ss_truth * (1 + 1e-6)
                n_out = outside(res, R, S)
                st["wrong_basin"] += wrong
                st["wrong_basin_exit0"] += wrong and res.success
                st["outside_exit0"] += n_out > 0 and res.success
                st["outside_exit1"] += n_out > 0 and not res.success
                st["false_alarm"] += n_out == 0 and not res.success
                st["right"] += n_out == 0 and res.success
                if wrong or n_out:
                    st["seeds"].append(seed)
                got[name] = (wrong, np.vstack([res.receivers, res.sources]))
            if not got["before"][0] and not got["after"][0]:
                a, b = got["before"][1], got["after"][1]
                b = align(b, a, reflection=True).apply(b)  # the same gauge (rotation, translation)
                max_change = max(max_change, float(np.linalg.norm(a - b, axis=1).max()))
    finally:
        starts._offsets_weakly_identified = rule
    out = {"seeds": [first, first + count - 1], **stats, "max_change_m_same_basin": max_change}
    for k, v in out.items():
        print(k, v)
    return out


if __name__ == "__main__":
    a = [int(x) for x in sys.argv[1:3]]
    run(*a)
