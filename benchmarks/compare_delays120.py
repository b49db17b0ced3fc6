"""The thesis workload (004: 120 units, complete, both offsets) before and after, one process.

``solve_toa(offsets="both")`` end to end (every check) of an old tree (``selfcal_old``, loaded by
:func:`compare_driver.load_old`) and of the working tree, alternately on the seeds of
``benchmarks/bench_delays.py`` (best of ``--repeats`` CPU times per seed, median over seeds),
against the thesis iteration (``rank3_iteration`` to its convergence threshold, as in
``bench_delays._faithful``) in the same process: CPU seconds, ratio of the thesis iteration to
them, ratio of the thesis's reported MATLAB time (84.2 s) to them.

Every call starts cold: the linearisation a tree keeps from its last fit
(``toa.verdict.leverage._LAST``, reused within one call by the checks after the solve) is
dropped before each call, else the repeats of one seed (the same matrix) would reuse the
previous call's and time less than a first call does (~20 ms at 120 units).

Usage::

    PYTHONPATH=src python benchmarks/compare_delays120.py [--old 3c2af32] [--seeds 3] [--repeats 3]
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys
import tempfile
import time
import warnings
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

from bench_delays import _case, _faithful  # noqa: E402
from compare_driver import load_old  # noqa: E402

MATLAB_120 = 84.2  # s, 004's reported mean for 120 units


def _cold(mod_name: str) -> None:
    """Drop the linearisation kept from the tree's last call (absent in old trees)."""
    for sub in ("toa.verdict.leverage", "toa.leverage"):
        try:
            lev = importlib.import_module(f"{mod_name}.{sub}")
        except ModuleNotFoundError:
            continue
        getattr(lev, "_LAST", []).clear()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--old", default="3c2af32")
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--thesis-runs", type=int, default=2)
    a = ap.parse_args()
    new = importlib.import_module("selfcal.toa")
    with tempfile.TemporaryDirectory() as tmp:
        load_old(a.old, Path(tmp))
        old = importlib.import_module("selfcal_old.toa")
        names = {"old": "selfcal_old", "new": "selfcal"}
        cpu: dict[str, list[float]] = {"old": [], "new": []}
        for seed in range(a.seeds):
            R, _ = _case(120, "large", seed)
            best = {"old": np.inf, "new": np.inf}
            for _ in range(a.repeats):
                for name, mod in (("old", old), ("new", new)):
                    with warnings.catch_warnings():
                        warnings.simplefilter("ignore")
                        _cold(names[name])
                        c0 = time.process_time()
                        mod.solve_toa(R, dim=3, offsets="both", rng=seed)
                        best[name] = min(best[name], time.process_time() - c0)
            for k in cpu:
                cpu[k].append(best[k])
        thesis = _faithful(120, "large", a.thesis_runs, 1_000_000)["median_cpu_seconds_to_convergence"]
        print(f"thesis iteration (same run): {thesis:.3f} s CPU to convergence (median of {a.thesis_runs})")
        print(f"{'tree':6s} {'CPU s':>8s} {'x thesis':>9s} {'x MATLAB':>9s}   per seed")
        for k in ("old", "new"):
            m = float(np.median(cpu[k]))
            print(f"{k:6s} {m:8.4f} {thesis / m:9.1f} {MATLAB_120 / m:9.0f}   "
                  + " ".join(f"{v:.4f}" for v in cpu[k]))


if __name__ == "__main__":
    main()
