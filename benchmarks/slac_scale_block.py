"""Does the smoother's per-beacon range-scale block help or harm? (issue 31)

Simulated CMU-style logs (tests/datasets/cmu_logs.py) with the default scale errors (2-9 %
long) and with exact scales (``range_scale=(0, 0)``; same seeds, same draws otherwise). Each
log is solved by the smoother with the scale block as shipped (``scale_std=0.1``) and with
it effectively removed (``scale_std=1e-4``: offset-only model). Prints RMSE (m) per case.

    OPENBLAS_NUM_THREADS=1 PYTHONPATH=src:. python benchmarks/slac_scale_block.py [n_seeds]
"""

from __future__ import annotations

import sys
import tempfile
import warnings
from pathlib import Path

import numpy as np
from scipy.io import savemat
from tests.datasets.cmu_logs import cmu_log

from selfcal.datasets.plaza import load_plaza
from selfcal.slac.ranging import RangeModelConfig, solve_range_slac


def rmse(seed: int, range_scale: tuple[float, float], scale_std: float, method: str = "smoother") -> float:
    m, tr = cmu_log(seed, duration=150.0, range_scale=range_scale)
    with tempfile.TemporaryDirectory() as d, warnings.catch_warnings():
        warnings.simplefilter("ignore")
        p = Path(d) / "log.mat"
        savemat(p, m)
        r = solve_range_slac(load_plaza(p), method=method, config=RangeModelConfig(scale_std=scale_std))
    t = r.times
    e = r.poses[:, :2] - np.column_stack([np.interp(t, tr.times, tr.poses[:, 0]), np.interp(t, tr.times, tr.poses[:, 1])])
    return float(np.sqrt(np.mean(np.sum(e**2, axis=1))))


def main(n: int = 6) -> None:
    for label, rs in (("scale errors 2-9 %", (0.02, 0.09)), ("exact scales", (0.0, 0.0))):
        on = np.array([rmse(s, rs, 0.1) for s in range(n)])
        off = np.array([rmse(s, rs, 1e-4) for s in range(n)])
        print(f"{label}: smoother RMSE with scale block mean {on.mean():.3f} m, offset-only {off.mean():.3f} m; "
              f"ratio per seed {np.round(on / off, 3).tolist()}")


if __name__ == "__main__":
    main(int(sys.argv[1]) if len(sys.argv) > 1 else 6)
