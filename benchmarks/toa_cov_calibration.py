"""Calibration of ``solve_toa``'s default covariance over noise draws (issue 27 follow-up).

The default path flags outliers by the Bonferroni rule and refits least squares on the entries
kept; its covariance carries the hard-rejection factor ``selfcal.robust.rejection_factor``. For
each noise law and seed this draws ``RUNS`` matrices on one random 10 x 20 geometry in a 5 m
cube (3-D, no offsets, 1 cm noise) and prints the mean squared Mahalanobis distance per
dimension (1 when calibrated) of the positions after Procrustes alignment, without ("before")
and with ("after") the factor: the same fits, the factor each applied recorded
(``tests/toa/test_covariance.py::_default_calibration``).

Usage::

    OPENBLAS_NUM_THREADS=1 PYTHONPATH=src python benchmarks/toa_cov_calibration.py \\
        gauss,t3,t5,laplace 0,1,2 150

NOISE: gauss, t3, t5 (Student t scaled to unit variance), laplace.
"""

from __future__ import annotations

import pathlib
import sys
import time
import warnings

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1] / "tests" / "toa"))

from test_covariance import _default_calibration  # noqa: E402


def main() -> None:
    kinds = sys.argv[1].split(",")
    seeds = [int(x) for x in sys.argv[2].split(",")]
    runs = int(sys.argv[3])
    warnings.simplefilter("ignore")
    for kind in kinds:
        for seed in seeds:
            t0 = time.perf_counter()
            after, before = _default_calibration(kind, seed, runs)
            print(f"{kind:8s} seed {seed}: before {before:.3f} after {after:.3f} factor {before / after:.4f} "
                  f"({time.perf_counter() - t0:.0f} s)", flush=True)


if __name__ == "__main__":
    main()
