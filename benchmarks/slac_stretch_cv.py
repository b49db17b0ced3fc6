"""Leave-a-stretch-out cross-validation of the range-SLAC smoother's models (issue 31).

The log's ranges inside windows of ``W`` seconds (evenly spaced; 16, or fewer so that at most
half of the log is held out) are held out in two folds (odd and even windows); the smoother solves each fold's remaining log (all the odometry is kept),
and the held-out stretches are scored twice:

* ``pose``: position RMSE (m) against the ground truth inside the held-out windows, where only
  the odometry and the calibration learnt elsewhere carry the track (a wrong odometry scale, a
  wrong scale / offset shows here first);
* ``range``: RMS (m) of the held-out ranges predicted from the track and the calibration
  (``s_b |p - b_b| + o_b``): the criterion a user without ground truth can compute.

Variants (``--variants``; all solve the same folds in one process):

* ``default``: ``solve_range_slac(method="smoother")`` with its defaults;
* ``k-off``: the default with the odometry distance scale held at 1 (the weight of
  :func:`selfcal.slac.scale_prior.odo_scale_weight` replaced by 0; benchmark only);
* ``k-select``: the model of larger posterior probability only (weight rounded to 0 or 1:
  the rule before the model average);
* ``fixed``: ``RangeModelConfig(scale_prior="fixed")`` (fixed ``N(1, 0.1^2)`` per-beacon scales,
  no odometry scale);
* ``graph``: the GTSAM graph's model of ``benchmarks/compare_plaza.py`` run by the smoother:
  ``fixed`` + each range at the nearest pose in time + Huber without the chi-square gate.

Logs: ``plaza`` (the shared Plaza 1 file, ``--data``) and simulated CMU logs
(``tests/datasets/cmu_logs.py``, 240 s, ``--seeds``; ``sim-plaza`` one 6 % shared scale,
0.5 m noise; ``sim-odo`` the same with a 3 % odometry distance-scale error; ``sim-odo-small``
with a 0.5 % one). On 240-s logs use ``--window 15`` (8 windows).

    OPENBLAS_NUM_THREADS=1 PYTHONPATH=src:. python benchmarks/slac_stretch_cv.py \
        [--logs plaza sim-plaza sim-odo] [--variants default k-select k-off fixed graph] [--window 60] [--seeds 4]
"""

from __future__ import annotations

import argparse
import dataclasses
import tempfile
import time
import warnings
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
from scipy.io import savemat

from selfcal.datasets.plaza import load_plaza
from selfcal.slac import ranging
from selfcal.slac.ranging import RangeLog, RangeModelConfig, solve_range_slac

PLAZA = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "plaza" / "Plaza1.mat"
SIMS: dict[str, dict[str, Any]] = {
    "sim-plaza": {"range_scale": (0.06, 0.06), "range_noise": 0.5, "outliers": 0.0},
    "sim-odo": {"range_scale": (0.06, 0.06), "range_noise": 0.5, "outliers": 0.0, "odo_scale": 1.03},
    "sim-odo-small": {"range_scale": (0.06, 0.06), "range_noise": 0.5, "outliers": 0.0, "odo_scale": 1.005},
}


def nearest_pose_times(log: RangeLog) -> RangeLog:
    """The log with every range time moved to the nearest pose time (the graph's attachment)."""
    t = np.concatenate([[log.start_time], log.odo_times])
    rt = log.range_times
    i = np.clip(np.searchsorted(t, rt), 1, t.size - 1)
    j = np.where(np.abs(rt - t[i - 1]) < np.abs(t[i] - rt), i - 1, i)
    return dataclasses.replace(log, range_times=t[j].copy())


def solve(log: RangeLog, variant: str) -> Any:
    """The smoother under one variant (see the module docstring)."""
    orig = ranging.odo_scale_weight
    try:
        if variant == "k-off":
            ranging.odo_scale_weight = lambda k, v: 0.0  # type: ignore[assignment]
        elif variant == "k-select":
            ranging.odo_scale_weight = lambda k, v: float(orig(k, v) >= 0.5)  # type: ignore[assignment]
        cfg = {"default": RangeModelConfig(), "k-off": RangeModelConfig(), "k-select": RangeModelConfig(),
               "fixed": RangeModelConfig(scale_prior="fixed"),
               "graph": RangeModelConfig(scale_prior="fixed", gate_quantile=1.0)}[variant]
        return solve_range_slac(nearest_pose_times(log) if variant == "graph" else log, method="smoother", config=cfg)
    finally:
        ranging.odo_scale_weight = orig


def window_starts(log: RangeLog, window: float, n_max: int = 16) -> np.ndarray:
    """Start times of the held-out windows: evenly spaced, at most ``n_max`` and at most half
    of the log held out in all (so each fold keeps at least three quarters of its ranges)."""
    t0, t1 = log.start_time, float(log.odo_times[-1])
    n = min(n_max, int((t1 - t0) // (2 * window)))
    if n < 2:
        raise ValueError(f"a {t1 - t0:.0f}-s log is too short for two windows of {window} s")
    return t0 + (np.arange(n) + 0.5) * (t1 - t0) / n - window / 2


def stretch_cv(log: RangeLog, truth: Callable[[np.ndarray], np.ndarray], variant: str, window: float) -> dict[str, float]:
    """Held-out pose RMSE and range-prediction RMS of one variant on one log (two folds: the
    odd and the even windows of :func:`window_starts`)."""
    starts = window_starts(log, window)
    pe, re = [], []
    for f in range(2):
        held = np.zeros(log.range_times.size, dtype=bool)
        for a in starts[f::2]:
            held |= (log.range_times >= a) & (log.range_times < a + window)
        sub = dataclasses.replace(log, range_times=log.range_times[~held], range_beacon=log.range_beacon[~held],
                                  ranges=log.ranges[~held])
        r = solve(sub, variant)
        inwin = np.zeros(r.times.size, dtype=bool)
        for a in starts[f::2]:
            inwin |= (r.times >= a) & (r.times < a + window)
        pe.append(np.sum((r.poses[inwin, :2] - truth(r.times[inwin])) ** 2, axis=1))
        th, b = log.range_times[held], log.range_beacon[held]
        px, py = np.interp(th, r.times, r.poses[:, 0]), np.interp(th, r.times, r.poses[:, 1])
        d = np.hypot(px - log.beacons[b, 0], py - log.beacons[b, 1])
        re.append(log.ranges[held] - (r.scale[b] * d + r.offset[b]))
    p, q = np.concatenate(pe), np.concatenate(re)
    return {"pose": float(np.sqrt(p.mean())), "range": float(np.sqrt(np.mean(q**2)))}


def logs(names: list[str], seeds: int, data: Path) -> Iterator[tuple[str, RangeLog, Callable[[np.ndarray], np.ndarray]]]:
    """(name, log, truth(times) -> (n, 2) positions) for each requested log."""
    for name in names:
        if name == "plaza":
            d = load_plaza(data)
            yield name, RangeLog.from_dataset(d), (lambda t, d=d: d.gt_at(t)[:, :2])
            continue
        from tests.datasets.cmu_logs import cmu_log

        for s in range(seeds):
            m, tr = cmu_log(s, duration=240.0, **SIMS[name])
            with tempfile.TemporaryDirectory() as tmp, warnings.catch_warnings():
                warnings.simplefilter("ignore")
                p = Path(tmp) / "log.mat"
                savemat(p, m)
                lg = RangeLog.from_dataset(load_plaza(p))

            def truth(t: np.ndarray, tr: Any = tr) -> np.ndarray:
                return np.column_stack([np.interp(t, tr.times, tr.poses[:, 0]), np.interp(t, tr.times, tr.poses[:, 1])])

            yield f"{name}/{s}", lg, truth


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--logs", nargs="+", default=["plaza", "sim-plaza", "sim-odo"])
    ap.add_argument("--variants", nargs="+", default=["default", "k-select", "k-off", "fixed", "graph"])
    ap.add_argument("--window", type=float, default=60.0, help="seconds per held-out window")
    ap.add_argument("--seeds", type=int, default=4)
    ap.add_argument("--data", type=Path, default=PLAZA)
    a = ap.parse_args()
    warnings.simplefilter("ignore")
    rows: dict[tuple[str, str], list[dict[str, float]]] = {}
    for name, log, truth in logs(a.logs, a.seeds, a.data):
        for v in a.variants:
            t0 = time.process_time()
            r = stretch_cv(log, truth, v, a.window)
            rows.setdefault((name.split("/")[0], v), []).append(r)
            print(f"{name:<12} {v:<8} held-out pose RMSE {r['pose']:.4f} m, range RMS {r['range']:.4f} m "
                  f"({time.process_time() - t0:.0f} CPU-s)", flush=True)
    print(f"\n{'log':<10} {'variant':<8} {'pose RMSE (mean)':>17} {'range RMS (mean)':>17}  logs")
    for (name, v), rs in rows.items():
        print(f"{name:<10} {v:<8} {np.mean([r['pose'] for r in rs]):17.4f} {np.mean([r['range'] for r in rs]):17.4f}  {len(rs)}")


if __name__ == "__main__":
    main()
