"""The search's start-skipping rule against the tree before it: the same minimum over many draws.

:func:`selfcal.toa.search.search` stops computing initialisers once a start passes its stopping
rule unrefined (residuals at the solver's precision, or the chi-square test at a given noise with
the linear loss). Within one search that cannot change the winner (the race ends at the first
start in order that passes); across the searches of one solve (``offsets="auto"``, the nested
fit) the skipped initialisers no longer draw from the shared generator, so later random starts
differ. This script measures the effect end to end: ``solve_toa`` of the old tree (loaded as
``selfcal_old`` by :func:`compare_driver.load_old`) and of the working tree on the same draws,
with the same arguments and seed, over

* the flip and generic families of the uniqueness tests (``tests/toa/uniqueness_families.py``),
* the bench_toa networks (:mod:`bench_toa`: 100 x 100 at 1 cm, 5 % missing; units with both
  offsets at 1 mm, 5 % missing), scaled down to 40 x 40 and 60 units so that many seeds fit,
* the same units noise-free and with the noise given (where the rule applies).

Per family: draws whose final cost ``0.5 sum r^2`` is equal (relative difference <= 1e-8),
lower or higher in the new tree, draws whose verdict (success, ambiguous nodes) changed, and the
CPU ratio new / old of the summed solve times.

Usage::

    PYTHONPATH=src python benchmarks/compare_search_skip.py [--old 3c2af32] [--seeds 30]
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
import warnings
from pathlib import Path
from typing import Any

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
sys.path.insert(0, str(HERE.parent / "tests" / "toa"))

from compare_driver import load_old  # noqa: E402


def _units(seed: int, noise: float, given: bool, miss: float = 0.05, U: int = 60) -> tuple:
    from selfcal.toa import toa_model

    rng = np.random.default_rng([77, seed])
    box = np.array([10.0, 10.0, 3.0])
    mic = rng.uniform(0, 1, (U, 3)) * box
    spk = mic + rng.normal(0, 0.05, (U, 3))
    d, o = rng.uniform(0, 0.020 * 343, U), rng.uniform(0, 0.030 * 343, U)
    Y = toa_model(mic, spk, d, o) + (rng.normal(0, noise, (U, U)) if noise else 0.0)
    Y[rng.random((U, U)) < miss] = np.nan
    kw: dict[str, Any] = {"dim": 3, "offsets": "both", "covariance": "none"}
    if given:
        kw["noise"] = noise
    return Y, mic, spk, kw


def _scene(seed: int, n: int = 40) -> tuple:
    from selfcal.toa import toa_model

    rng = np.random.default_rng([78, seed])
    box = np.array([10.0, 10.0, 5.0])
    r, s = rng.uniform(0, 1, (n, 3)) * box, rng.uniform(0, 1, (n, 3)) * box
    Y = toa_model(r, s) + rng.normal(0, 0.01, (n, n))
    Y[rng.random((n, n)) < 0.05] = np.nan
    return Y, r, s, {"dim": 3}


def families() -> dict[str, Any]:
    import uniqueness_families as uf

    out = {**uf.FAMILIES, **uf.GENERIC}
    out["bench_toa 40x40 1cm"] = _scene
    out["units 60 both 1mm"] = lambda k: _units(k, 1e-3, False)
    out["units 60 both 1mm given"] = lambda k: _units(k, 1e-3, True)
    out["units 60 both exact"] = lambda k: _units(k, 0.0, False)
    out["units 60 both exact auto"] = lambda k: (lambda t: (t[0], t[1], t[2], {**t[3], "offsets": "auto"}))(
        _units(k, 0.0, False))
    return out


def solve(mod: Any, Y: Any, kw: dict[str, Any], seed: int) -> tuple[float, float, Any]:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        c0 = time.process_time()
        try:
            res = mod.solve_toa(Y, rng=seed, **kw)
        except Exception as exc:  # a refusal (DegenerateGeometryError) is a verdict too
            return float("nan"), time.process_time() - c0, ("raised", type(exc).__name__)
        dt = time.process_time() - c0
    cost = 0.5 * float(np.nansum(res.residuals ** 2))
    verdict = (bool(res.success), tuple(np.flatnonzero(res.ambiguous_receivers)),
               tuple(np.flatnonzero(res.ambiguous_sources)))
    return cost, dt, verdict


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--old", default="3c2af32", help="commit of the tree before the rule")
    ap.add_argument("--seeds", type=int, default=30)
    ap.add_argument("--only", default="", help="comma-separated substrings of family names")
    a = ap.parse_args()
    import importlib

    new = importlib.import_module("selfcal.toa")
    with tempfile.TemporaryDirectory() as tmp:
        load_old(a.old, Path(tmp))
        old = importlib.import_module("selfcal_old.toa")
        print(f"{'family':28s} {'draws':>5s} {'equal':>5s} {'lower':>5s} {'higher':>6s} {'verdict':>7s} "
              f"{'t_ratio':>7s}")
        for name, fam in families().items():
            if a.only and not any(o in name for o in a.only.split(",")):
                continue
            n = eq = lo = hi = vd = 0
            t_old = t_new = 0.0
            for seed in range(a.seeds):
                Y, _, _, kw = fam(seed)
                c_old, d_old, v_old = solve(old, Y, kw, seed)
                c_new, d_new, v_new = solve(new, Y, kw, seed)
                t_old, t_new = t_old + d_old, t_new + d_new
                n += 1
                vd += v_old != v_new
                if (np.isnan(c_old) and np.isnan(c_new)) or abs(c_new - c_old) <= 1e-8 * max(c_old, 1e-300) \
                        or max(c_old, c_new) < 1e-20:
                    eq += 1
                elif c_new < c_old:
                    lo += 1
                else:
                    hi += 1
            print(f"{name:28s} {n:5d} {eq:5d} {lo:5d} {hi:6d} {vd:7d} {t_new / max(t_old, 1e-12):7.2f}", flush=True)


if __name__ == "__main__":
    main()
