"""Offsets cross-validation with capped vs converged fold refits: choices, scores and CPU.

``solve_toa(offsets="auto")`` runs on the flights of ``benchmarks/offsets_auto_decisions.py``
(``simulate_uwb_flight(300 + seed, 250, layout, bias_std)``, columns in a fixed random
order); the inputs its :func:`selfcal.toa.verdict.crossval.cross_validate` receives (the
kept entries and every candidate's fit) are captured and scored twice in this process:

- capped (the library): each fold refit warm-started from the candidate's fit, at most
  the engine's 100 iterations;
- converged: each candidate first refitted on all columns, then every fold refit started
  from that fit, both with ``max_nfev=--cap`` (default 2000) so that the stopping rule
  decides wherever the fit converges at all.

Prints per flight the choice, CPU and CV RMS of both. Measured (2026-12-03, branch
``cvwarm`` on main 7d49f80, loaded 2-core machine, ``--seeds 0-3``, first through a
temporary hook in ``cross_validate``, the seed-0 LPS flights again with this script, the same
choices and scores): the same choice on 23 of 24 flights
(seed 0, LPS, no biases: none -> receivers), CV CPU median 1.54 -> 8.8 s, total 37 -> 177 s;
"both" fits still unconverged at the cap and its converged scores erratic (up to 3.1 m RMS).
See docs/design.md, "Fold refits are capped, not converged".

Run: ``OPENBLAS_NUM_THREADS=1 PYTHONPATH=src python benchmarks/cv_converged_folds.py --seeds 0
--layouts lps``.
"""

from __future__ import annotations

import argparse
import time
import warnings
from typing import Any

import numpy as np


def converged_cv(Z: np.ndarray, starts: dict[str, Any], cap: int) -> tuple[Any, float]:
    """cross_validate with every candidate refitted to convergence and the fold refits capped at ``cap``."""
    import selfcal.toa.engine.nls as nls
    from selfcal.errors import DegenerateGeometryError
    from selfcal.toa.verdict import crossval as cv

    t0 = time.process_time()
    orig = nls.refine_toa
    conv: dict[str, Any] = {}
    for m, (R, S, d, o) in starts.items():
        kw: dict[str, Any] = dict(cv._REFIT[m])
        if d is not None:
            kw["receiver_offsets0"] = d
        if o is not None:
            kw["source_offsets0"] = o
        try:  # a column with too few ranges for the model (the folds drop it): keep the given fit
            f = orig(Z, R, S, covariance=False, max_nfev=cap, **kw)
            conv[m] = (f.receivers, f.sources, f.receiver_offsets, f.source_offsets)
        except DegenerateGeometryError:
            conv[m] = (R, S, d, o)

    def capped(*a: Any, **kw: Any) -> Any:
        kw.setdefault("max_nfev", cap)
        return orig(*a, **kw)

    nls.refine_toa = capped
    try:
        choice = cv.cross_validate(Z, conv)
    finally:
        nls.refine_toa = orig
    return choice, time.process_time() - t0


def main() -> None:
    from selfcal.experiments.lps import simulate_uwb_flight
    from selfcal.toa import solve_toa
    from selfcal.toa.verdict import crossval as cv

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", default="0-3")
    ap.add_argument("--layouts", default="lps,room")
    ap.add_argument("--cap", type=int, default=2000)
    a = ap.parse_args()
    lo, _, hi = a.seeds.partition("-")
    seen: dict[str, Any] = {}
    orig = cv.cross_validate

    def spy(Z: np.ndarray, starts: dict[str, Any], **kw: Any) -> Any:
        seen["x"] = (Z, starts)
        return orig(Z, starts, **kw)

    same = n = 0
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for seed in range(int(lo), int(hi or lo) + 1):
            for layout in a.layouts.split(","):
                for bias in (0.0, 0.1, 0.2):
                    sim = simulate_uwb_flight(300 + seed, 250, layout=layout, bias_std=bias)
                    Y = sim["ranges"][:, np.random.default_rng(seed).permutation(sim["ranges"].shape[1])]
                    cv.cross_validate = spy
                    try:
                        solve_toa(Y, offsets="auto", rng=0)
                    finally:
                        cv.cross_validate = orig
                    Z, starts = seen["x"]
                    t0 = time.process_time()
                    c1 = orig(Z, starts)
                    t1 = time.process_time() - t0
                    c2, t2 = converged_cv(Z, starts, a.cap)
                    n, same = n + 1, same + (c1.chosen == c2.chosen)
                    rms = " ".join(f"{m} {np.sqrt(c1.scores[m]):.4f}/{np.sqrt(c2.scores.get(m, np.nan)):.4f}"
                                   for m in c1.scores)
                    print(f"seed {seed} {layout:4s} bias {bias:.1f}: capped {c1.chosen} {t1:.2f} s, converged "
                          f"{c2.chosen} {t2:.2f} s; CV RMS capped/converged {rms}", flush=True)
    print(f"same choice {same} of {n}")


if __name__ == "__main__":
    main()
