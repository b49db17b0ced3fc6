"""Benchmark "toa_minimal": blind solves of minimal 12 x 6 networks with both offsets.

Scene (issue 12): 12 microphones uniform in a 1.5 m cube, 6 sources uniform in a ball of
radius 4 m around the cube's centre, unknown receiver delays U(0, 10 ms) and source onsets
U(0, 100 ms), 20 us Gaussian timing noise, c = 343 m/s, every entry observed. Theory:
72 measurements for 3 * 18 - 6 + 12 + 6 - 1 = 65 unknowns, 7 redundant.

For every seeded draw:

- ``reference``: :func:`selfcal.toa.refine_toa` started from the truth (same-run baseline
  of both quality and time: the basin of the truth and the cost of one refinement there);
- ``blind``: ``solve_toa(T, dim=3, offsets="both", speed=343, rng=seed)`` with its defaults.

A blind solve "lands in the basin" when its sum of squared residuals over all entries is
at most the reference's times (1 + 1e-6) (it found that minimum or a lower one).

Run: ``python benchmarks/bench_toa_minimal.py [--draws 20] [--out DIR]``.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
import warnings
from pathlib import Path
from typing import Any

import numpy as np

C = 343.0
NOISE = 20e-6


def scene(seed: int, I: int = 12, J: int = 6) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(receivers, sources, delays s, onsets s, TOA matrix s) of one draw."""
    g = np.random.default_rng(seed)
    r = g.uniform(0.0, 1.5, (I, 3))
    u = g.normal(size=(J, 3))
    u /= np.linalg.norm(u, axis=1)[:, None]
    s = 0.75 + u * 4.0 * g.uniform(0, 1, (J, 1)) ** (1 / 3)
    d = g.uniform(0, 0.01, I)
    o = g.uniform(0, 0.1, J)
    T = np.linalg.norm(r[:, None] - s[None], axis=-1) / C + d[:, None] + o[None] + g.normal(0, NOISE, (I, J))
    return r, s, d, o, T


def one(seed: int) -> dict[str, Any]:
    """Reference and blind solve of one draw."""
    from selfcal.toa import refine_toa, solve_toa

    r, s, d, o, T = scene(seed)
    t0 = time.perf_counter()
    ref = refine_toa(T * C, r, s, offsets="both", receiver_offsets0=d * C, source_offsets0=o * C,
                     covariance=False, solver="trf")
    t_ref = time.perf_counter() - t0
    rss_ref = float(np.nansum(ref.residuals**2))
    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            res = solve_toa(T, dim=3, offsets="both", speed=C, rng=seed)
            rss = float(np.nansum((res.residuals * C) ** 2))
            ok, status = bool(rss <= rss_ref * (1 + 1e-6)), int(res.status)
        except Exception as exc:  # a failure is a data point here
            rss, ok, status = float("inf"), False, -99
            print(f"seed {seed}: {type(exc).__name__}: {exc}")
    t_blind = time.perf_counter() - t0
    return {"seed": seed, "in_basin": ok, "rss_blind_m2": rss, "rss_reference_m2": rss_ref,
            "t_blind_s": t_blind, "t_reference_s": t_ref, "status": status}


def main(out_dir: Path | None = None, draws: int = 20) -> dict[str, Any]:
    rows = [one(seed) for seed in range(draws)]
    rate = sum(r["in_basin"] for r in rows) / len(rows)
    tb = statistics.median(r["t_blind_s"] for r in rows)
    tr = statistics.median(r["t_reference_s"] for r in rows)
    out = {"benchmark": "toa_minimal", "draws": draws, "in_basin_rate": rate, "median_blind_s": tb,
           "median_reference_s": tr, "ratio_blind_to_reference": tb / tr,
           "unknowns": 3 * 18 - 6 + 12 + 6 - 1, "measurements": 72, "rows": rows}
    if out_dir is not None:
        out_dir.mkdir(parents=True, exist_ok=True)
        (out_dir / "bench_toa_minimal.json").write_text(json.dumps(out, indent=1))
    return out


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--draws", type=int, default=20)
    ap.add_argument("--out", type=Path, default=None)
    a = ap.parse_args()
    res = main(a.out, a.draws)
    print(json.dumps({k: v for k, v in res.items() if k != "rows"}, indent=1))
