"""Outliers on 12 x 40 networks (issue 27): how many results are honest (run by hand, not by ``make bench``).

Draws 3-D networks of 12 receivers x 40 sources uniform in a 10 m cube, 1 cm noise, a fraction
of the ranges off by U(1, 50) m either way, and runs ``solve_toa`` with its defaults (noise
unknown). Prints the successes, the dropped nodes, the injected errors in the ``outliers``
mask, and the nodes of successful results further from the truth (after rigid alignment) than
3x their own error bar plus 1 mm.

Usage::

    PYTHONPATH=src python benchmarks/outlier_sweep.py [--draws 60] [--fraction 0.06]
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


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--draws", type=int, default=60)
    ap.add_argument("--fraction", type=float, default=0.06)
    a = ap.parse_args()
    main(a.draws, a.fraction)
