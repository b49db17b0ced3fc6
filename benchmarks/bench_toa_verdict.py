"""Benchmark "toa_verdict": false alarm, power and cost of the noise-unknown geometry verdict.

For every case (size, dimension, offsets, missing fraction) and seeded draw:

- ``random``: a uniform U(0, 10) matrix (no geometry) -- the permutation test
  (:func:`selfcal.toa.verdict.trust.permutation_test`) must pass at most its level, 1 / 20;
- ``network``: receivers and sources uniform in a 10 m square / cube, offsets U(0, 3 m) of
  the case's kinds, Gaussian noise ``--noise`` (m) -- it must pass.

``--solve`` runs ``solve_toa`` (noise unknown, the verdict end to end) on the networks instead
and reports the CPU share of the permutation test in the solve (same run).

Usage::

    PYTHONPATH=src python benchmarks/bench_toa_verdict.py --draws 40 [--noise 0.05] [--solve] [--out DIR]

``make bench`` (benchmarks/run_all.py) runs it with 10 draws per case.
"""

from __future__ import annotations

import argparse
import json
import time
import warnings
from pathlib import Path
from typing import Any

import numpy as np

CASES = [(5, 5, 2, "none", 0.0), (8, 10, 2, "none", 0.0), (8, 10, 3, "none", 0.0), (30, 40, 2, "none", 0.0),
         (30, 40, 3, "none", 0.0), (6, 30, 3, "none", 0.0), (8, 10, 2, "receivers", 0.0),
         (8, 10, 2, "sources", 0.0), (8, 10, 2, "both", 0.0), (8, 10, 3, "both", 0.0), (12, 6, 3, "both", 0.0),
         (10, 14, 3, "both", 0.0), (20, 20, 3, "both", 0.2)]


def network(I: int, J: int, dim: int, offsets: str, noise: float, g: np.random.Generator,
            missing: float) -> np.ndarray:
    """A noisy range matrix of a random network (metres)."""
    from selfcal.toa.engine.nls import toa_model

    Y = toa_model(g.uniform(0, 10, (I, dim)), g.uniform(0, 10, (J, dim)))
    if offsets in ("receivers", "both"):
        Y = Y + g.uniform(0, 3, I)[:, None]
    if offsets in ("sources", "both"):
        Y = Y + g.uniform(0, 3, J)[None]
    Y = Y + g.normal(0, noise, Y.shape)
    if missing:
        Y[g.random(Y.shape) < missing] = np.nan
    return Y


def main(out: Path | None = None, *, draws: int = 10, noise: float = 0.05, solve: bool = False) -> dict[str, Any]:
    """Run every case; print one line each; write ``toa_verdict.json`` under ``out``; return the rows."""
    import selfcal.toa.verdict.trust as trust
    from selfcal.toa import solve_toa

    warnings.simplefilter("ignore")
    spent = [0.0]
    inner = trust.permutation_test

    def timed(*args: Any, **kw: Any) -> Any:
        t = time.process_time()
        got = inner(*args, **kw)
        spent[0] += time.process_time() - t
        return got

    rows: dict[str, Any] = {}
    trust.permutation_test = timed  # type: ignore[assignment]
    try:
        for I, J, dim, off, miss in CASES:
            key = f"{I}x{J} {dim}-D {off} missing {miss:.0%}"
            if solve:
                spent[0] = 0.0
                t0 = time.process_time()
                ok = sum(solve_toa(network(I, J, dim, off, noise, np.random.default_rng(2000 + k), miss), dim=dim,
                                   offsets=off, rng=0).success for k in range(draws))
                tot = time.process_time() - t0
                rows[key] = {"networks_pass": ok, "draws": draws, "solve_cpu_s": tot / draws,
                             "permutation_share": spent[0] / tot}
                print(f"{key}: networks pass {ok}/{draws}, solve {tot / draws:.2f} s CPU, "
                      f"permutation test {100 * spent[0] / tot:.0f} %", flush=True)
                continue
            row: dict[str, Any] = {}
            for kind in ("random", "network"):
                n = untestable = 0
                t0 = time.process_time()
                for k in range(draws):
                    g = np.random.default_rng(1000 + k)
                    if kind == "random":
                        Y = g.uniform(0, 10, (I, J))
                        if miss:
                            Y[g.random(Y.shape) < miss] = np.nan
                    else:
                        Y = network(I, J, dim, off, noise, g, miss)
                    pt = inner(Y, dim, off)
                    untestable += pt is None
                    n += bool(pt is not None and pt.passed)
                row[kind] = {"pass": n, "tested": draws - untestable,
                             "ms_cpu": 1e3 * (time.process_time() - t0) / draws}
            rows[key] = row
            print(f"{key}: random pass {row['random']['pass']}/{row['random']['tested']}, networks pass "
                  f"{row['network']['pass']}/{row['network']['tested']} ({row['network']['ms_cpu']:.0f} ms CPU)",
                  flush=True)
    finally:
        trust.permutation_test = inner  # type: ignore[assignment]
    if out is not None:
        Path(out).mkdir(parents=True, exist_ok=True)
        (Path(out) / "toa_verdict.json").write_text(json.dumps(rows, indent=2))
    return rows


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--draws", type=int, default=40)
    ap.add_argument("--noise", type=float, default=0.05)
    ap.add_argument("--solve", action="store_true")
    ap.add_argument("--out", type=Path, default=None)
    a = ap.parse_args()
    main(a.out, draws=a.draws, noise=a.noise, solve=a.solve)
