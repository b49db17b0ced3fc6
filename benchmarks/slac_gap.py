"""What could separate the range-SLAC smoother from a factor-graph baseline? (issue 31)

The GTSAM batch graph of ``benchmarks/compare_plaza.py`` solves the same MAP problem as the
smoother with a few differences of robustness and noise handling. Each is tested here as a
switch of the smoother on simulated CMU-style logs with the faults real logs have (150 s,
``tests/datasets/cmu_logs.py``); nothing is chosen from Plaza 1:

* ``default``: chi-square gate (0.999) + Huber (k = 1.345), noise levels by EM;
* ``no gate``: Huber only, as the GTSAM graph (``gate_quantile=1``);
* ``least squares``: neither gate nor Huber (``huber=1e6``): the efficient estimator for
  Gaussian ranges;
* ``no EM``: the noise levels of the first pass kept (``noise_rounds=0``), as the GTSAM graph
  is given them;
* ``wide heading``: the wheel-odometry heading prior only (``heading_noise_grid=(1.0,)``).

Cases: ``plaza-like`` one 6 % scale shared by the beacons, 0.5 m Gaussian noise, no outliers
(what the shared Plaza 1 log shows against its ground truth: residual std 0.53 m, kurtosis 0,
no lag correlation, scales 1.068-1.071); ``nlos`` independent 2-9 % scales, 0.5 m noise, 15 %
NLOS ranges +2-10 m; ``odo`` the plaza-like case with a 3 % odometry distance-scale error;
``dropouts`` the plaza-like case with two 30 s radio outages and odometry gaps.

    OPENBLAS_NUM_THREADS=1 PYTHONPATH=src:. python benchmarks/slac_gap.py [n_seeds] [case ...]
"""

from __future__ import annotations

import sys
import time
from typing import Any

import numpy as np
from slac_scale_block import sim_rmse

from selfcal.slac.ranging import RangeModelConfig

PLAZA_LIKE: dict[str, Any] = {"range_scale": (0.06, 0.06), "range_noise": 0.5, "outliers": 0.0}
CASES: dict[str, dict[str, Any]] = {
    "plaza-like": PLAZA_LIKE,
    "nlos": {"range_scale": (0.02, 0.09), "range_noise": 0.5, "outliers": 0.15},
    "odo": {**PLAZA_LIKE, "odo_scale": 1.03},
    "dropouts": {**PLAZA_LIKE, "dropouts": 2, "gaps": 2},
}
VARIANTS: dict[str, RangeModelConfig] = {
    "default": RangeModelConfig(),
    "no gate": RangeModelConfig(gate_quantile=1.0),
    "least squares": RangeModelConfig(gate_quantile=1.0, huber=1e6),
    "no EM": RangeModelConfig(noise_rounds=0),
    "wide heading": RangeModelConfig(heading_noise_grid=(1.0,)),
}


def main(n: int, cases: list[str]) -> None:
    print(f"{'case':<11} {'variant':<14} {'mean':>6} {'median':>6} {'worst':>6}  CPU s")
    for name in cases:
        base = None
        for label, cfg in VARIANTS.items():
            t0 = time.process_time()
            e = np.array([sim_rmse(s, CASES[name], cfg)[0] for s in range(n)])
            base = e if base is None else base
            print(f"{name:<11} {label:<14} {e.mean():6.3f} {np.median(e):6.3f} {e.max():6.3f}  "
                  f"{time.process_time() - t0:5.1f}  ratio to default per seed {np.round(e / base, 2).tolist()}",
                  flush=True)


if __name__ == "__main__":
    args = sys.argv[1:]
    n_seeds = int(args.pop(0)) if args and args[0].isdigit() else 8
    main(n_seeds, args or list(CASES))
