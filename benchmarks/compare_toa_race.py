"""Same-run comparison of search configurations on the minimal 12 x 6 scene (issue 12).

Each configuration is ``BATCH:STARTS``: ``BATCH`` 1 races the starts in lockstep
(:mod:`selfcal.toa.engine.batch_lm`), 0 one at a time through the dense LM (the iterates are the
same, only the cost differs); ``STARTS`` is :data:`selfcal.toa.search.SCALED_STARTS`. Every
configuration solves the same draw in turn (the scene, the truth-started reference and the
"in the basin" rule of ``benchmarks/bench_toa_minimal.py``), so the CPU ratios are paired and
same-run. Prints one line per seed (in basin, CPU seconds per configuration), then the rate,
the median CPU, the median paired ratio to the first configuration, and the draws gained and
lost against it with the exact McNemar p-value.

Run: ``PYTHONPATH=src:benchmarks python benchmarks/compare_toa_race.py --first 560 --draws 200 --configs 0:8,1:24``
"""

from __future__ import annotations

import argparse
import statistics
import time
import warnings

import numpy as np


def main(first: int, draws: int, configs: list[tuple[bool, int]]) -> dict[tuple[bool, int], list[tuple[bool, float]]]:
    import bench_toa_minimal as b
    from scipy.stats import binomtest

    from selfcal.toa import refine_toa, search, solve_toa

    res: dict[tuple[bool, int], list[tuple[bool, float]]] = {c: [] for c in configs}
    saved = search.BATCH_RACE, search.SCALED_STARTS
    sig = b.NOISE * b.C
    try:
        for seed in range(first, first + draws):
            r, s, d, o, T = b.scene(seed)
            ref = refine_toa(T * b.C, r, s, offsets="both", receiver_offsets0=d * b.C, source_offsets0=o * b.C,
                             covariance=False, solver="trf")
            rss_ref = float(np.nansum(ref.residuals**2))
            line = []
            for c in configs:
                search.BATCH_RACE, search.SCALED_STARTS = c
                t0 = time.process_time()
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")
                    try:
                        out = solve_toa(T, dim=3, offsets="both", speed=b.C, rng=seed)
                        rss = float(np.nansum((out.residuals * b.C) ** 2))
                    except Exception:  # a failure is a data point here
                        rss = np.inf
                dt = time.process_time() - t0
                ok = bool(rss <= rss_ref + 0.01 * sig**2)
                res[c].append((ok, dt))
                line.append(f"{int(ok)} {dt:.2f}")
            print(seed, " | ".join(line), flush=True)
    finally:
        search.BATCH_RACE, search.SCALED_STARTS = saved
    base = configs[0]
    for c in configs:
        v = res[c]
        k = sum(x[0] for x in v)
        ci = binomtest(k, len(v)).proportion_ci(0.95, method="exact")
        line = (f"batch={int(c[0])} starts={c[1]}: in basin {k} / {len(v)} ({100 * k / len(v):.1f} %, CI "
                f"{100 * ci.low:.1f}-{100 * ci.high:.1f}), median CPU {statistics.median(x[1] for x in v):.3f} s")
        if c != base:
            gained = sum(x[0] and not y[0] for x, y in zip(v, res[base], strict=True))
            lost = sum(y[0] and not x[0] for x, y in zip(v, res[base], strict=True))
            p = binomtest(gained, gained + lost).pvalue if gained + lost else 1.0
            ratio = statistics.median(x[1] / y[1] for x, y in zip(v, res[base], strict=True))
            line += f", paired CPU ratio {ratio:.2f}, gained {gained} lost {lost} (McNemar p = {p:.2g})"
        print(line)
    return res


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--first", type=int, default=0)
    ap.add_argument("--draws", type=int, default=20)
    ap.add_argument("--configs", default="0:8,1:24", help="comma-separated BATCH:STARTS (default 0:8,1:24)")
    a = ap.parse_args()
    main(a.first, a.draws, [(x.split(":")[0] == "1", int(x.split(":")[1])) for x in a.configs.split(",")])
