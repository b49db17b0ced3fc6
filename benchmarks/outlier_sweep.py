"""Outliers on 12 x 40 networks (issue 27): how many results are honest (run by hand, not by ``make bench``).

Draws 3-D networks of 12 receivers x 40 sources uniform in a 10 m cube, 1 cm noise, a fraction
of the ranges off by U(1, 50) m either way, and runs ``solve_toa`` with its defaults (noise
unknown). Prints the successes, the dropped nodes, the injected errors in the ``outliers``
mask, and the nodes of successful results further from the truth (after rigid alignment) than
3x their own error bar plus 1 mm.

``--families`` runs instead the families of ``tests/toa/outlier_families.py`` (10-40 % of
the ranges off by +1..+5 m, one-sided or symmetric, noise given or unknown, 2-D and 3-D,
offsets none or per receiver; and clean generic networks, Gaussian or heavy-tailed (t with
3-5 dof, Laplace), for the false alarms) and prints,
per family: the injected errors in the ``outliers`` mask, the draws that report an outlier
breakdown, that are right (exit 0, within 3 error bars, every injected error flagged), right
but with injected errors left in the fit, wrong with exit 0 (a node outside 3x its error
bar; ``wrong>10cm``: of those, the draws where such a node is more than 10 cm = 10 noise std
off, not a tail of its covariance), and failed for another reason.

Usage::

    PYTHONPATH=src python benchmarks/outlier_sweep.py [--draws 60] [--fraction 0.06]
    PYTHONPATH=src python benchmarks/outlier_sweep.py --families [--draws 40] [--only 3d-plus-unknown,...]
    PYTHONPATH=src python benchmarks/outlier_sweep.py --cost [--draws 6]
"""

from __future__ import annotations

import argparse
import warnings

import numpy as np


def main(draws: int = 60, fraction: float = 0.06) -> dict[str, int]:
    from selfcal.errors import Status
    from selfcal.geometry import align
    from selfcal.toa import solve_toa, toa_model

    warnings.simplefilter("ignore")
    out = {"draws": draws, "success": 0, "dropped": 0, "injected": 0, "in_mask": 0, "outside_3sd": 0}
    for seed in range(draws):
        g = np.random.default_rng(1000 + seed)
        r, s = g.uniform(0, 10, (12, 3)), g.uniform(0, 10, (40, 3))
        Y = toa_model(r, s) + g.normal(0, 0.01, (12, 40))
        bad = g.random(Y.shape) < fraction
        Y[bad] += g.uniform(1, 50, bad.sum()) * g.choice([-1.0, 1.0], bad.sum())
        res = solve_toa(Y, dim=3, rng=0)
        ok = res.status == Status.SUCCESS
        out["success"] += int(ok)
        out["dropped"] += len(res.dropped_sources) + len(res.dropped_receivers)
        out["injected"] += int(bad.sum())
        out["in_mask"] += int((bad & res.outliers).sum())
        est, true = np.vstack([res.receivers, res.sources]), np.vstack([r, s])
        m = np.isfinite(est[:, 0])
        err = np.linalg.norm(align(est[m], true[m]).apply(est[m]) - true[m], axis=1)
        std = np.sqrt(np.trace(np.concatenate([res.receiver_cov, res.source_cov])[m], axis1=1, axis2=2))
        out["outside_3sd"] += int((err > 3 * std + 1e-3).sum()) if ok else 0
    print(out)
    return out


def families(draws: int = 40, only: str = "") -> dict[str, dict[str, int]]:
    """The table of the contamination and clean families (module docstring)."""
    import collections
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "toa"))
    from outlier_families import CLEAN, CONTAMINATED, HEAVY, classify

    every = {**CONTAMINATED, **CLEAN, **HEAVY}
    names = [n for n in every if not only or n in only.split(",")]
    cols = ("breakdown", "right", "right-unflagged", "wrong", "wrong>10cm", "failed")
    print(f"{'family':26s} {'draws':>5s} {'flagged':>11s} " + " ".join(f"{c:>15s}" for c in cols))
    table = {}
    for name in names:
        c: collections.Counter[str] = collections.Counter()
        for seed in range(draws):
            d = classify(every[name], seed)
            c[d["kind"]] += 1
            c["wrong>10cm"] += d["kind"] == "wrong" and d.get("worst_m", 0.0) > 0.1
            c["flagged"] += d["flagged"]
            c["bad"] += d["bad"]
        table[name] = dict(c)
        flagged = f"{c['flagged']}/{c['bad']}"
        print(f"{name:26s} {draws:5d} {flagged:>11s} " + " ".join(f"{c[k]:15d}" for k in cols), flush=True)
    return table


def cost(draws: int = 6) -> dict[str, float]:
    """Same-process A/B of ``solve_toa`` with and without the high-breakdown start (interleaved).

    The start is switched off by setting ``high_breakdown.HB_MAX_ENTRIES`` below every matrix; the
    median wall time of each is printed with their ratio.
    """
    import sys
    import time
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "toa"))
    from outlier_families import CLEAN, CONTAMINATED

    import selfcal.toa.verdict.high_breakdown as rb
    from selfcal.toa import solve_toa

    warnings.simplefilter("ignore")
    limit = rb.HB_MAX_ENTRIES
    cases = {"12x40 clean": CLEAN["clean-3d-unknown"], "8x10 clean": CLEAN["clean-small-3d-unknown"],
             "12x40 offsets clean": CLEAN["clean-3d-offsets-unknown"],
             "12x40 10-25% gross": CONTAMINATED["3d-plus-unknown-25"]}
    out = {}
    for name, fam in cases.items():
        t: dict[bool, list[float]] = {True: [], False: []}
        for seed in range(draws):
            Y, _, _, _, kw = fam(seed)
            for on in (False, True):
                rb.HB_MAX_ENTRIES = limit if on else -1
                t0 = time.perf_counter()
                solve_toa(Y, rng=seed, **kw)
                t[on].append(time.perf_counter() - t0)
        rb.HB_MAX_ENTRIES = limit
        a, b = float(np.median(t[False])), float(np.median(t[True]))
        out[name] = b / a
        print(f"{name:22s} without {a:.3f} s  with {b:.3f} s  ratio {b / a:.2f}")
    return out


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--draws", type=int, default=60)
    ap.add_argument("--fraction", type=float, default=0.06)
    ap.add_argument("--families", action="store_true", help="the families of tests/toa/outlier_families.py")
    ap.add_argument("--only", default="", help="comma-separated family names (with --families)")
    ap.add_argument("--cost", action="store_true", help="solve time with / without the high-breakdown start")
    a = ap.parse_args()
    if a.cost:
        cost(a.draws)
    elif a.families:
        families(a.draws, a.only)
    else:
        main(a.draws, a.fraction)
