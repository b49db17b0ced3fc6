"""The smoother's odometry-scale model: averaged, selected or left out (issue 31).

The range-SLAC smoother weighs the model with an odometry distance scale ``k ~ N(1, 0.05^2)``
against ``k = 1`` by their Bayes factor (:func:`selfcal.slac.scale_prior.odo_scale_weight`).
Variants (``benchmarks/slac_stretch_cv.py``'s :func:`solve`), all on the same logs:

* ``default``: both models solved and averaged with their posterior probabilities;
* ``k-select``: the more probable model only (the rule before the average);
* ``k-off``: ``k = 1`` always (the GTSAM graph's odometry model);
* ``graph``: the GTSAM graph's whole model (fixed scale priors, no ``k``, nearest pose, no gate).

Simulated 150-s CMU logs (``tests/datasets/cmu_logs.py``), position RMSE (m) per seed, then the
mean and the per-seed ratio to ``default``; ``plaza`` adds the shared Plaza 1 file.

    OPENBLAS_NUM_THREADS=1 PYTHONPATH=src:. python benchmarks/slac_odo_average.py [n_seeds] [case ...]

Cases: ``exact`` exact range scales, 0.15 m noise, 3 % outliers; ``common`` one 6 % range scale;
``indep`` 2-9 % per beacon; ``plaza-like`` one 6 % scale, 0.5 m Gaussian noise, no outliers;
``odo`` plaza-like + a 3 % odometry distance-scale error; ``odo-small`` plaza-like + a 0.5 %
one (the size the ground truth of Plaza 1 shows: 0.996-0.999); ``nlos`` 2-9 %, 0.5 m noise,
15 % NLOS ranges; ``t3`` plaza-like with Student-t (3 dof, scale 0.3 m) noise; ``laplace``
plaza-like with Laplace noise (std 0.5 m).
"""

from __future__ import annotations

import sys
import tempfile
import time
import warnings
from pathlib import Path
from typing import Any

import numpy as np
from scipy.io import savemat
from slac_stretch_cv import PLAZA, solve
from tests.datasets.cmu_logs import cmu_log

from selfcal.datasets.plaza import load_plaza
from selfcal.slac.ranging import RangeLog

PL: dict[str, Any] = {"range_scale": (0.06, 0.06), "range_noise": 0.5, "outliers": 0.0}
CASES: dict[str, dict[str, Any]] = {
    "exact": {"range_scale": (0.0, 0.0)},
    "common": {"range_scale": (0.06, 0.06)},
    "indep": {"range_scale": (0.02, 0.09)},
    "plaza-like": PL,
    "odo": {**PL, "odo_scale": 1.03},
    "odo-small": {**PL, "odo_scale": 1.005},
    "nlos": {"range_scale": (0.02, 0.09), "range_noise": 0.5, "outliers": 0.15},
    "t3": {**PL, "range_tail": "t3", "range_noise": 0.3},
    "laplace": {**PL, "range_tail": "laplace"},
}
VARIANTS = ("default", "k-select", "k-off", "graph")


def sim(seed: int, case: dict[str, Any], variant: str) -> tuple[float, Any]:
    """Position RMSE (m) of one simulated 150-s log under one variant, and the result."""
    m, tr = cmu_log(seed, duration=150.0, **case)
    with tempfile.TemporaryDirectory() as d, warnings.catch_warnings():
        warnings.simplefilter("ignore")
        p = Path(d) / "log.mat"
        savemat(p, m)
        r = solve(RangeLog.from_dataset(load_plaza(p)), variant)
    t = r.times
    e = r.poses[:, :2] - np.column_stack([np.interp(t, tr.times, tr.poses[:, 0]), np.interp(t, tr.times, tr.poses[:, 1])])
    return float(np.sqrt(np.mean(np.sum(e**2, axis=1)))), r


def main(n: int, cases: list[str]) -> None:
    print(f"{'case':<11} {'variant':<9} {'mean':>6} {'worst':>6}  weight of k (median)  CPU s  ratio to default per seed")
    for name in cases:
        if name == "plaza":
            from selfcal.experiments.slac import score_plaza

            data = load_plaza(PLAZA)
            for v in VARIANTS:
                t0 = time.process_time()
                r = solve(RangeLog.from_dataset(data), v)
                e = score_plaza(data, r)["position_rmse"]
                print(f"{'Plaza 1':<11} {v:<9} {e:6.3f} {e:6.3f}  {r.odometry_scale_weight:20.3f}  "
                      f"{time.process_time() - t0:5.1f}", flush=True)
            continue
        base = None
        for v in VARIANTS:
            t0 = time.process_time()
            out = [sim(s, CASES[name], v) for s in range(n)]
            e = np.array([o[0] for o in out])
            base = e if base is None else base
            w = np.median([o[1].odometry_scale_weight for o in out])
            print(f"{name:<11} {v:<9} {e.mean():6.3f} {e.max():6.3f}  {w:20.3f}  {time.process_time() - t0:5.1f}  "
                  f"{np.round(e / base, 2).tolist()}", flush=True)


if __name__ == "__main__":
    args = sys.argv[1:]
    n_seeds = int(args.pop(0)) if args and args[0].isdigit() else 8
    main(n_seeds, args or [*CASES, "plaza"])
