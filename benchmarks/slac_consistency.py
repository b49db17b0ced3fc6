"""Consistency of the range-SLAC filter's (and smoother's) reported covariances over seeds.

Simulated CMU-style logs (``tests/datasets/cmu_logs.py``: 4 beacons at known positions with
unknown per-beacon range scale and offset, 3 % one-sided multipath outliers, odometry at
5 Hz) are drawn per case of :data:`CASES` (the plain log and each fault option of the
simulator) and seed; :func:`selfcal.slac.ranging.solve_range_slac` runs on each (through
``load_plaza``, as the CLI does) and is scored against the simulator's truth:

- ``nees``: the time-averaged position NEES of one log, ``mean_t e_t^T C_t^-1 e_t``
  (E = 2 for a consistent estimator); the table gives its median over seeds and the share
  of logs above chi2_2(0.99) = 9.21 (a consistent log exceeds it with probability <= 1 %,
  the time average being smaller in convex order than one chi2_2 term);
- ``cover``: the share of all poses (pooled over seeds) inside the reported 95 % ellipse;
- ``cal``: the share of beacons whose true (scale, offset) lies inside the final 95 %
  ellipse of the estimate's 2x2 covariance (``calibration_cov``);
- ``rmse``: the median position RMSE (m);
- ``flag``: the share of runs whose result says it failed its own test (``success`` False,
  the filter's innovation test), i.e. the runs that report they are not to be trusted.

Usage::

    PYTHONPATH=src:. OPENBLAS_NUM_THREADS=1 python benchmarks/slac_consistency.py \
        [--seeds 20] [--cases plain,odo-scale] [--method filter] [--compare REV] [--duration 240]

``--compare REV`` also runs ``src/selfcal/slac/ranging.py`` as it was at git revision REV
(loaded beside the current one, same process, same logs), one table row each.
"""

from __future__ import annotations

import argparse
import importlib.util
import subprocess
import sys
import tempfile
import time
import warnings
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np
from scipy import stats
from scipy.io import savemat

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:  # tests.datasets.cmu_logs (the simulator) lives beside src/
    sys.path.insert(0, str(ROOT))

#: the simulator's fault options (tests/datasets/cmu_logs.py), one case each
CASES: dict[str, dict[str, Any]] = {
    "plain": {},
    "no-outliers": {"outliers": 0.0},
    "outliers-10pc": {"outliers": 0.10},
    "gaps-silent": {"n_beacons": 5, "silent": 1, "gaps": 2, "heading_offset": -np.pi / 2},
    "far-beacon": {"far_beacon": 120.0, "n_beacons": 5},
    "brief": {"brief": 1, "n_beacons": 5},
    "dropouts": {"dropouts": 2},
    "odo-scale": {"odo_scale": 1.05},
    "standing": {"stand": 2},
    "dr-duplicates": {"dr_duplicates": 0.05},
}

Q95_2 = float(stats.chi2.ppf(0.95, 2))
NEES_BOUND = float(stats.chi2.ppf(0.99, 2))


def load_revision(rev: str) -> ModuleType:
    """``selfcal.slac.ranging`` as of git revision ``rev``, imported as a sibling module."""
    src = subprocess.run(["git", "-C", str(ROOT), "show", f"{rev}:src/selfcal/slac/ranging.py"],
                         check=True, capture_output=True, text=True).stdout
    tmp = Path(tempfile.mkdtemp()) / "ranging_rev.py"
    tmp.write_text(src)
    name = "selfcal.slac._ranging_" + "".join(c if c.isalnum() else "_" for c in rev)
    spec = importlib.util.spec_from_file_location(name, tmp)
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    sys.modules[name] = mod
    spec.loader.exec_module(mod)
    return mod


def simulated(seed: int, duration: float, **kw: Any) -> tuple[Any, Any]:
    """A simulated log loaded as the CLI loads a file, and its truth."""
    from tests.datasets.cmu_logs import cmu_log

    from selfcal.datasets.plaza import load_plaza

    m, tr = cmu_log(seed, duration=duration, **kw)
    with tempfile.TemporaryDirectory() as d, warnings.catch_warnings():
        warnings.simplefilter("ignore")
        p = Path(d) / "log.mat"
        savemat(p, m)
        return load_plaza(p), tr


def score(res: Any, data: Any, tr: Any) -> dict[str, Any]:
    """NEES, 95 % coverage, calibration coverage and RMSE of one result against the truth."""
    t = res.times
    e = res.poses[:, :2] - np.column_stack([np.interp(t, tr.times, tr.poses[:, 0]),
                                            np.interp(t, tr.times, tr.poses[:, 1])])
    q = np.einsum("ni,nij,nj->n", e, np.linalg.inv(res.pose_cov), e)
    heard = {int(b): i for i, b in enumerate(tr.beacon_ids) if tr.heard[i]}
    cal_in = []
    cov = getattr(res, "calibration_cov", None)
    for j, b in enumerate(res.beacon_ids):
        if int(b) not in heard:
            continue
        i = heard[int(b)]
        d = np.array([res.scale[j] - tr.scale[i], res.offset[j] - tr.offset[i]])
        C = cov[j] if cov is not None and len(cov) else np.diag([res.scale_std[j] ** 2, res.offset_std[j] ** 2])
        cal_in.append(float(d @ np.linalg.solve(C, d)) <= Q95_2)
    return {"nees": float(np.mean(q)), "inside": int(np.sum(q <= Q95_2)), "poses": int(q.size),
            "cal_in": int(np.sum(cal_in)), "cal_n": len(cal_in), "rmse": float(np.sqrt(np.mean(np.sum(e**2, 1)))),
            "flag": not bool(res.success)}


def sweep(cases: list[str], seeds: int, method: str, duration: float,
          solvers: dict[str, Any]) -> list[dict[str, Any]]:
    rows = []
    for case in cases:
        per: dict[str, list[dict[str, Any]]] = {k: [] for k in solvers}
        for seed in range(seeds):
            data, tr = simulated(seed, duration, **CASES[case])
            for name, solve in solvers.items():
                t0 = time.process_time()
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")
                    r = solve(data, method=method)
                s = score(r, data, tr)
                s["cpu"] = time.process_time() - t0
                per[name].append(s)
        for name, ss in per.items():
            nees = np.array([s["nees"] for s in ss])
            rows.append({
                "case": case, "code": name, "seeds": len(ss), "nees_median": float(np.median(nees)),
                "nees_over": float(np.mean(nees > NEES_BOUND)),
                "cover": sum(s["inside"] for s in ss) / max(1, sum(s["poses"] for s in ss)),
                "cal": sum(s["cal_in"] for s in ss) / max(1, sum(s["cal_n"] for s in ss)),
                "rmse_median": float(np.median([s["rmse"] for s in ss])),
                "flag": float(np.mean([s["flag"] for s in ss])),
                "cpu_median": float(np.median([s["cpu"] for s in ss])),
            })
            print(_fmt(rows[-1]), flush=True)
    return rows


_HEAD = f"{'case':<15} {'code':<8} {'seeds':>5} {'NEES med':>8} {'>9.21':>6} {'cover95':>7} {'cal95':>6} " \
        f"{'RMSE m':>7} {'flag':>5} {'CPU s':>6}"


def _fmt(r: dict[str, Any]) -> str:
    return (f"{r['case']:<15} {r['code']:<8} {r['seeds']:>5d} {r['nees_median']:>8.2f} {r['nees_over']:>6.2f} "
            f"{r['cover']:>7.3f} {r['cal']:>6.2f} {r['rmse_median']:>7.3f} {r['flag']:>5.2f} {r['cpu_median']:>6.2f}")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=20)
    ap.add_argument("--cases", default=",".join(CASES), help="comma-separated, from: " + ", ".join(CASES))
    ap.add_argument("--method", default="filter", choices=("filter", "smoother"))
    ap.add_argument("--duration", type=float, default=240.0, help="seconds of driving per log")
    ap.add_argument("--compare", default="", help="git revision whose ranging.py runs beside the current one")
    a = ap.parse_args(argv)
    cases = [c for c in a.cases.split(",") if c]
    bad = [c for c in cases if c not in CASES]
    if bad or a.seeds < 1:
        print(f"error: unknown case(s) {bad}; choose from {list(CASES)}" if bad else "error: --seeds must be >= 1",
              file=sys.stderr)
        return 2
    from selfcal.slac.ranging import solve_range_slac

    solvers: dict[str, Any] = {"current": solve_range_slac}
    if a.compare:
        solvers = {a.compare[:8]: load_revision(a.compare).solve_range_slac, **solvers}
    print(f"method={a.method} seeds={a.seeds} duration={a.duration:g} s")
    print(_HEAD, flush=True)
    rows = sweep(cases, a.seeds, a.method, a.duration, solvers)
    print("\n" + _HEAD)
    for r in rows:
        print(_fmt(r))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
