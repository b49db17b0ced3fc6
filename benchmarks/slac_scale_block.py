"""Which range-scale model should the range-SLAC smoother fit? (issue 31)

Simulated CMU-style logs (tests/datasets/cmu_logs.py, 150 s) under several faults, each solved
by the smoother with three scale models (``RangeModelConfig``):

* ``empirical`` (default): the scales' prior ``N(1, a^2 11^T + tau^2 I)`` estimated from the
  log by type-II maximum likelihood (empirical Bayes), an odometry distance scale kept by its
  Bayes factor, then the MAP under these priors;
* ``fixed 0.1``: the fixed prior ``N(1, 0.1^2 I)``, no odometry scale (the previous scale model);
* ``offset only``: ``scale_std=1e-4`` with the fixed prior (the scales held at 1).

Prints, per case, the mean / median / worst position RMSE (m) over the seeds and the median of
the empirical-Bayes ``[a, tau]``. No constant of the estimator is chosen from these numbers
(the empirical prior has none but its floor, 1e-4, see ``SCALE_PRIOR_FLOOR``).

    OPENBLAS_NUM_THREADS=1 PYTHONPATH=src:. python benchmarks/slac_scale_block.py [n_seeds] [case ...]

Cases (``cmu_log`` options): ``indep`` 2-9 % independent per beacon (the generator's default),
``exact`` exact scales, ``common`` one 6 % error shared by all beacons, ``mixed`` 0-9 %
independent, ``nlos-exact`` / ``nlos-indep`` 15 % NLOS ranges (+2-10 m) and 0.5 m noise (the
range noise the smoother estimates on Plaza 1), ``odo-exact`` exact range scales with a 3 %
odometry distance scale error (which a common range scale could wrongly absorb), ``far``
2-9 % with one beacon 30 m outside the path and one heard for only 15 s. ``plaza`` adds the
shared Plaza 1 log (``../shared/data/plaza/Plaza1.mat``).
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
from tests.datasets.cmu_logs import cmu_log

from selfcal.datasets.plaza import load_plaza
from selfcal.slac.ranging import RangeModelConfig, solve_range_slac

CASES: dict[str, dict[str, Any]] = {
    "indep": {"range_scale": (0.02, 0.09)},
    "exact": {"range_scale": (0.0, 0.0)},
    "common": {"range_scale": (0.06, 0.06)},
    "mixed": {"range_scale": (0.0, 0.09)},
    "nlos-exact": {"range_scale": (0.0, 0.0), "outliers": 0.15, "range_noise": 0.5},
    "nlos-indep": {"range_scale": (0.02, 0.09), "outliers": 0.15, "range_noise": 0.5},
    "odo-exact": {"range_scale": (0.0, 0.0), "odo_scale": 1.03},
    "far": {"range_scale": (0.02, 0.09), "far_beacon": 30.0, "brief": 1},
}
MODELS: dict[str, RangeModelConfig] = {
    "empirical": RangeModelConfig(),
    "fixed 0.1": RangeModelConfig(scale_prior="fixed"),
    "offset only": RangeModelConfig(scale_prior="fixed", scale_std=1e-4),
}
PLAZA = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "plaza" / "Plaza1.mat"


def sim_rmse(seed: int, case: dict[str, Any], cfg: RangeModelConfig, method: str = "smoother") -> tuple[float, Any]:
    """Position RMSE (m) of one simulated log and the result."""
    m, tr = cmu_log(seed, duration=150.0, **case)
    with tempfile.TemporaryDirectory() as d, warnings.catch_warnings():
        warnings.simplefilter("ignore")
        p = Path(d) / "log.mat"
        savemat(p, m)
        r = solve_range_slac(load_plaza(p), method=method, config=cfg)
    t = r.times
    e = r.poses[:, :2] - np.column_stack([np.interp(t, tr.times, tr.poses[:, 0]), np.interp(t, tr.times, tr.poses[:, 1])])
    return float(np.sqrt(np.mean(np.sum(e**2, axis=1)))), r


def main(n: int, cases: list[str]) -> None:
    print(f"{'case':<11} {'model':<12} {'mean':>6} {'median':>6} {'worst':>6}  EB [a, tau] (median)  CPU s")
    for name in cases:
        if name == "plaza":
            from selfcal.experiments.slac import score_plaza

            data = load_plaza(PLAZA)
            for label, cfg in MODELS.items():
                t0 = time.process_time()
                r = solve_range_slac(data, method="smoother", config=cfg)
                e = score_plaza(data, r)["position_rmse"]
                print(f"{'Plaza 1':<11} {label:<12} {e:6.3f} {e:6.3f} {e:6.3f}  "
                      f"{np.array2string(r.scale_prior_std, precision=4):<20}  {time.process_time() - t0:5.1f}")
            continue
        for label, cfg in MODELS.items():
            t0 = time.process_time()
            out = [sim_rmse(s, CASES[name], cfg) for s in range(n)]
            e = np.array([o[0] for o in out])
            ab = np.median(np.array([o[1].scale_prior_std for o in out]), axis=0)
            print(f"{name:<11} {label:<12} {e.mean():6.3f} {np.median(e):6.3f} {e.max():6.3f}  "
                  f"{np.array2string(ab, precision=4):<20}  {time.process_time() - t0:5.1f}", flush=True)


if __name__ == "__main__":
    args = sys.argv[1:]
    n_seeds = int(args.pop(0)) if args and args[0].isdigit() else 8
    main(n_seeds, args or [*CASES, "plaza"])
