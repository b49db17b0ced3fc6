"""Benchmark "lps": the moving-tag recipe's common-offset test on the LPS flights, by engine.

The default ``common_offset="test"`` of :func:`selfcal.toa.recipes.recipes.moving_tag` refits the
flight with one common range offset, then once per time block (up to 16) for the block
jackknife t test (:mod:`selfcal.toa.recipes.common_offset`). Those constrained refits run on the
Schur-reduced Newton-LM of :mod:`selfcal.toa.engine.schur_affine` (``solver="auto"``); the
baseline is the SciPy trust-region path they ran on before (``solver="trf"``), measured in
the same run on the same offsets-free fit, interleaved, CPU time (``time.process_time``;
the machine is shared, wall time is inflated by the others).

Per flight: the base fit (``moving_tag(common_offset="free")``, not compared), then for
each engine the test's CPU seconds, c, its block jackknife se, t, and the differences of
the new engine's c and replicates from the baseline's in units of se; the ratio of the
medians over ``--repeat`` runs.

Measured (2026-12-02, branch ``constrained``, ``--repeat 2``, loaded 2-core machine):
data4 (16 blocks) trf 13.91 s, auto 1.54 s, ratio 9.0; c -0.3943 / -0.3944 m, se 0.0522,
t -7.553 / -7.550, |dc| / se 3.4e-4. data5 (12 blocks) trf 24.83 s, auto 2.03 s, ratio
12.2; c -0.3315 m both, se 0.0308, t -10.774 / -10.773, |dc| / se 2.5e-5.

Run: ``PYTHONPATH=src python benchmarks/bench_lps.py [--flights data4,data5] [--repeat 3]
[--data ../shared/data/lps]``; a flight file that is missing is skipped with a line saying so.
Writes JSON with ``--out FILE``.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import time
import warnings

import numpy as np


def _base(path: str):
    """The offsets-free moving-tag fit and the cleaned matrix it was fitted on."""
    from selfcal.datasets.lps import load_lps
    from selfcal.toa.recipes.recipes import moving_tag

    fl = load_lps(path)
    t0 = time.process_time()
    rr = moving_tag(fl.ranges, common_offset="free", rng=0)
    t_base = time.process_time() - t0
    cleaned = np.where(np.asarray(rr.rejected, bool), np.nan, fl.ranges)
    return rr.result, cleaned, t_base


def bench_flight(path: str, repeat: int) -> dict:
    """CPU seconds and the test's numbers per engine on one flight (interleaved runs)."""
    from selfcal.toa.recipes.common_offset import block_offset_test

    base, cleaned, t_base = _base(path)
    cpu: dict[str, list[float]] = {"trf": [], "auto": []}
    info: dict[str, dict] = {}
    for _ in range(repeat):
        for solver in ("trf", "auto"):
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                t0 = time.process_time()
                _, inf = block_offset_test(base, cleaned, 1.0, solver)
                cpu[solver].append(time.process_time() - t0)
            info[solver] = inf
    a, b = info["auto"], info["trf"]
    se = b.get("std", float("nan"))
    row = {
        "flight": os.path.splitext(os.path.basename(path))[0], "base_cpu_s": t_base,
        "blocks": a.get("blocks"),
        "cpu_trf_s": statistics.median(cpu["trf"]), "cpu_auto_s": statistics.median(cpu["auto"]),
        "c_trf": b.get("value"), "c_auto": a.get("value"), "se_trf": se, "se_auto": a.get("std"),
        "t_trf": b.get("t_statistic"), "t_auto": a.get("t_statistic"),
        "dc_over_se": (a["value"] - b["value"]) / se if "value" in a and "value" in b else float("nan"),
        "max_replicate_diff_over_se": float(np.max(np.abs(np.subtract(a["replicates"], b["replicates"])))) / se
        if "replicates" in a and "replicates" in b else float("nan"),
    }
    row["ratio"] = row["cpu_trf_s"] / row["cpu_auto_s"]
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--flights", default="data4,data5")
    ap.add_argument("--data", default=os.path.join(os.path.dirname(__file__), "..", "..", "shared", "data", "lps"))
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--out", default=None)
    args = ap.parse_args()
    rows = []
    for name in args.flights.split(","):
        path = os.path.join(args.data, f"{name}.mat")
        if not os.path.isfile(path):
            print(f"{name}: {path} not found, skipped")
            continue
        row = bench_flight(path, args.repeat)
        rows.append(row)
        print(f"{row['flight']}: common-offset test CPU trf {row['cpu_trf_s']:.2f} s, auto {row['cpu_auto_s']:.2f} s, "
              f"ratio {row['ratio']:.1f} (median of {args.repeat}); {row['blocks']} blocks; "
              f"c {row['c_trf']:.4f} / {row['c_auto']:.4f} m, se {row['se_trf']:.4f} / {row['se_auto']:.4f}, "
              f"t {row['t_trf']:.3f} / {row['t_auto']:.3f}; |dc|/se {abs(row['dc_over_se']):.1e}, "
              f"max |d replicate|/se {row['max_replicate_diff_over_se']:.1e}; base fit {row['base_cpu_s']:.1f} s",
              flush=True)
    if args.out:
        with open(args.out, "w") as fh:
            json.dump(rows, fh, indent=1)


if __name__ == "__main__":
    main()
