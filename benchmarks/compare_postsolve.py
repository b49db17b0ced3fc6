"""The checks after the TOA solve against an older tree: the same answers, the same verdicts.

``solve_toa`` of an old tree (loaded as ``selfcal_old`` by :func:`compare_driver.load_old`) and
of the working tree on the same draws, with the same arguments and seed, each call cold (the
linearisation a tree keeps from its last fit dropped first, see ``compare_delays120.py``). Per
family and draw it compares what a user gets:

* ``verdict``: the exit-code verdict, the message, success and the ambiguous nodes are equal;
* ``outliers``: the flagged entries are equal;
* ``pos``: the largest position difference (m) between the trees, over the largest range;
* ``cov``: the largest difference of the receivers' and sources' covariance blocks, each
  tree's divided by its largest entry (an exact fit's noise estimate is round-off, 1e-15 m,
  and so is the covariances' scale: their shape, ``(J^T J)^+``, is what is compared);
* ``geo``: the permutation test's statistic (relative difference), the cross-validation's
  PRESS over its no-geometry PRESS (absolute difference: an exact fit's PRESS is round-off),
  and the two tests' decisions and p-value (equal or not);
* the CPU ratio new / old of the summed solve times.

Families: the paper-004 workload (``120t``: 120 units in the 30 x 30 x 12 m room, complete,
noise-free, both offsets, ``benchmarks/bench_delays.py``'s setup; ``120u``: 1 mm, a delay per
unit), the same noise-free workload with 1 % of the entries +2 m (gross errors in exact data,
where the robust refit must still run), 60 units with both offsets (1 mm, noise-free, 5 %
missing), 12 x 6 with both offsets (1 cm), and the flip and generic families of the uniqueness
tests (``tests/toa/uniqueness_families.py``).

Usage::

    PYTHONPATH=src python benchmarks/compare_postsolve.py [--old ddc1c24] [--seeds 10] [--only 120t,...]
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
from typing import Any

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
sys.path.insert(0, str(HERE.parent / "tests" / "toa"))

from compare_delays120 import _cold  # noqa: E402
from compare_driver import load_old  # noqa: E402


def _units120(seed: int, noise: float = 0.0, gross: float = 0.0) -> tuple[np.ndarray, dict[str, Any]]:
    from selfcal.scenarios.units import make_units

    sc = make_units(120, room="large", noise_std=noise / 343.0, equal_delays=noise == 0.0, rng=seed)
    Y = np.array(sc.ranges, float)
    if gross:
        g = np.random.default_rng([91, seed])
        Y[g.random(Y.shape) < gross] += 2.0
    return Y, {"dim": 3, "offsets": "both"}


def _units60(seed: int, noise: float) -> tuple[np.ndarray, dict[str, Any]]:
    from compare_search_skip import _units

    Y, _, _, kw = _units(seed, noise, False)
    kw = dict(kw)
    kw.pop("covariance", None)
    return Y, kw


def _small(seed: int) -> tuple[np.ndarray, dict[str, Any]]:
    from selfcal.toa import toa_model

    g = np.random.default_rng([93, seed])
    r, s = g.uniform(0, 10, (12, 3)), g.uniform(0, 10, (6, 3))
    Y = toa_model(r, s, g.uniform(0, 3, 12), g.uniform(0, 3, 6)) + g.normal(0, 0.01, (12, 6))
    return Y, {"dim": 3, "offsets": "both"}


def families() -> dict[str, Any]:
    import uniqueness_families as uf

    out: dict[str, Any] = {
        "120t": lambda k: _units120(k),
        "120t gross 1%": lambda k: _units120(k, gross=0.01),
        "120u 1mm": lambda k: _units120(k, noise=0.001),
        "units60 exact": lambda k: _units60(k, 0.0),
        "units60 1mm": lambda k: _units60(k, 1e-3),
        "12x6 both": _small,
    }
    for name, fam in {**uf.FAMILIES, **uf.GENERIC}.items():
        out[name] = (lambda f: lambda k: (lambda t: (t[0], t[3]))(f(k)))(fam)
    return out


def solve(mod: Any, tree: str, Y: Any, kw: dict[str, Any], seed: int) -> tuple[Any, float]:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        _cold(tree)
        c0 = time.process_time()
        try:
            res = mod.solve_toa(Y, rng=seed, **kw)
        except Exception as exc:  # a refusal is a verdict too
            res = ("raised", type(exc).__name__, str(exc))
        return res, time.process_time() - c0


def _rel(a: Any, b: Any) -> float:
    a, b = np.asarray(a, float), np.asarray(b, float)
    if a.shape != b.shape:
        return float("inf")
    both = np.isfinite(a) & np.isfinite(b)
    if not np.array_equal(both, np.isfinite(a)) or not np.array_equal(both, np.isfinite(b)):
        return float("inf")
    if not both.any():
        return 0.0
    scale = max(float(np.max(np.abs(a[both]))), 1e-300)
    return float(np.max(np.abs(a[both] - b[both]))) / scale


def compare(old: Any, new: Any, Y: np.ndarray) -> dict[str, Any]:
    if isinstance(old, tuple) or isinstance(new, tuple):
        same = isinstance(old, tuple) and isinstance(new, tuple) and old[:2] == new[:2]
        return {"verdict": same, "outliers": same, "pos": 0.0 if same else np.inf, "cov": 0.0, "geo": 0.0,
                "geo_same": same}
    span = float(np.nanmax(np.abs(Y)))
    v_old = (old.verdict, old.verdict_message, bool(old.success), tuple(np.flatnonzero(old.ambiguous_receivers)),
             tuple(np.flatnonzero(old.ambiguous_sources)))
    v_new = (new.verdict, new.verdict_message, bool(new.success), tuple(np.flatnonzero(new.ambiguous_receivers)),
             tuple(np.flatnonzero(new.ambiguous_sources)))
    pos = max(float(np.nanmax(np.abs(old.receivers - new.receivers), initial=0.0)),
              float(np.nanmax(np.abs(old.sources - new.sources), initial=0.0))) / span
    def unit(C: Any) -> Any:
        top = float(np.nanmax(np.abs(C), initial=0.0))
        return C / top if top > 0 else C

    cov = max(_rel(unit(old.receiver_cov), unit(new.receiver_cov)), _rel(unit(old.source_cov), unit(new.source_cov)))
    geo, geo_same = 0.0, True
    go, gn = old.geometry, new.geometry
    if (go is None) != (gn is None):
        geo, geo_same = float("inf"), False
    elif go is not None:
        geo_same = go.passed == gn.passed
        geo = abs(go.press / go.press_null - gn.press / gn.press_null)
        po, pn = go.permutation, gn.permutation
        if (po is None) != (pn is None):
            geo, geo_same = float("inf"), False
        elif po is not None:
            geo_same &= po.passed == pn.passed and po.p_value == pn.p_value
            geo = max(geo, _rel(po.statistic, pn.statistic), _rel(po.null_median, pn.null_median))
    return {"verdict": v_old == v_new, "outliers": bool(np.array_equal(old.outliers, new.outliers)), "pos": pos,
            "cov": cov, "geo": geo, "geo_same": geo_same}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--old", default="ddc1c24", help="commit of the tree before")
    ap.add_argument("--seeds", type=int, default=10)
    ap.add_argument("--only", default="", help="comma-separated substrings of family names")
    a = ap.parse_args()
    new_mod = importlib.import_module("selfcal.toa")
    with tempfile.TemporaryDirectory() as tmp:
        load_old(a.old, Path(tmp))
        old_mod = importlib.import_module("selfcal_old.toa")
        print(f"{'family':26s} {'draws':>5s} {'verdict':>7s} {'outl.':>5s} {'geo':>4s} {'max pos':>8s} "
              f"{'max cov':>8s} {'max geo':>8s} {'t_ratio':>7s}")
        for name, fam in families().items():
            if a.only and not any(o in name for o in a.only.split(",")):
                continue
            rows = []
            t_old = t_new = 0.0
            for seed in range(a.seeds):
                Y, kw = fam(seed)
                r_old, d_old = solve(old_mod, "selfcal_old", Y, kw, seed)
                r_new, d_new = solve(new_mod, "selfcal", Y, kw, seed)
                t_old, t_new = t_old + d_old, t_new + d_new
                rows.append(compare(r_old, r_new, Y))
                if not (rows[-1]["verdict"] and rows[-1]["outliers"] and rows[-1]["geo_same"]):
                    msg = [getattr(r, "verdict_message", r) for r in (r_old, r_new)]
                    print(f"  {name} seed {seed} differs: {msg[0]!r} -> {msg[1]!r}", flush=True)
            n = len(rows)
            print(f"{name:26s} {n:5d} {sum(r['verdict'] for r in rows):7d} {sum(r['outliers'] for r in rows):5d} "
                  f"{sum(r['geo_same'] for r in rows):4d} {max(r['pos'] for r in rows):8.1e} "
                  f"{max(r['cov'] for r in rows):8.1e} {max(r['geo'] for r in rows):8.1e} "
                  f"{t_new / max(t_old, 1e-12):7.2f}", flush=True)


if __name__ == "__main__":
    main()
