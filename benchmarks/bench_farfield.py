"""Far-field TDOA (paper 000) speed: batched minimal solver and LM for m = 48, k = 540.

Writes ``<out_dir>/farfield.json``. Medians over repetitions; ratios are against baselines
run in the same process (the minimal solver called one problem at a time; alternating
optimisation on the same LM problem), so machine load cancels to first order.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from selfcal.io import write_json
from selfcal.tdoa import (
    initialize_farfield,
    refine_alternating,
    refine_lm,
    solve_farfield,
    solve_minimal,
)


def _median_time(fn: Callable[[], Any], reps: int) -> float:
    times = []
    for _ in range(reps):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return float(np.median(times))


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def main(out_dir: Path) -> dict[str, Any]:
    """Run the benchmark and write ``out_dir/farfield.json``."""
    rng = np.random.default_rng(0)
    # ---- minimal solver, batched
    batch = 100_000
    Z = rng.uniform(-0.5, 0.5, (batch, 4, 3))
    Z[:, 0] = 0
    N = _unit(rng.normal(size=(batch, 6, 3)))
    D = Z @ np.swapaxes(N, -1, -2) + rng.normal(size=(batch, 1, 6))
    t_batch = _median_time(lambda: solve_minimal(D), 5)
    n_loop = 2000
    t_loop = _median_time(lambda: [solve_minimal(D[b]) for b in range(n_loop)], 3) / n_loop * batch
    sol = solve_minimal(D)
    fit = sol.positions @ np.swapaxes(sol.directions, -1, -2)
    resid = np.abs(fit - (D - D[:, :1])).max(axis=(1, 2))

    # ---- LM for m = 48, k = 540
    m, k, sigma = 48, 540, 1e-3
    Zt = rng.uniform(-0.2, 0.2, (m, 3))
    Zt[0] = 0
    Nt = _unit(rng.normal(size=(k, 3)))
    Dm = Zt @ Nt.T + rng.normal(size=k) + sigma * rng.normal(size=(m, k))
    X = Dm - Dm.mean(axis=0)
    init = initialize_farfield(X)
    Z0 = init.positions - init.positions[0]
    C0 = np.mean(Dm - Z0 @ init.directions.T, axis=0)
    lm_out = refine_lm(Dm, Z0, init.directions, C0, free_offsets=True)
    t_lm = _median_time(lambda: refine_lm(Dm, Z0, init.directions, C0, free_offsets=True), 3)
    alt_out = refine_alternating(Dm, Z0, init.directions, C0, free_offsets=True, max_iter=5000)
    t_alt = _median_time(lambda: refine_alternating(Dm, Z0, init.directions, C0, free_offsets=True,
                                                   max_iter=5000), 1)
    t_solve = _median_time(lambda: solve_farfield(Dm), 3)

    result = {
        "name": "farfield",
        "minimal_batch": batch,
        "minimal_batch_seconds_median": t_batch,
        "minimal_solves_per_second": batch / t_batch,
        "minimal_loop_solves_per_second": batch / t_loop,
        "minimal_batched_speedup_vs_loop": t_loop / t_batch,
        "minimal_valid_fraction": float(sol.valid.mean()),
        "minimal_max_residual_median": float(np.median(resid[sol.valid])),
        "lm_m": m,
        "lm_k": k,
        "lm_seconds_median": t_lm,
        "lm_iterations": lm_out.iterations,
        "lm_cost": lm_out.cost,
        "alternating_seconds": t_alt,
        "alternating_iterations": alt_out.iterations,
        "alternating_cost": alt_out.cost,
        "lm_speedup_vs_alternating": t_alt / t_lm,
        "solve_farfield_seconds_median": t_solve,
        "cpu_count": os.cpu_count(),
        "blas_threads_env": os.environ.get("OPENBLAS_NUM_THREADS") or os.environ.get("OMP_NUM_THREADS"),
    }
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    write_json(out_dir / "farfield.json", result)
    return result


if __name__ == "__main__":
    import json
    import sys

    print(json.dumps(main(Path(sys.argv[1] if len(sys.argv) > 1 else "benchmarks/results")), indent=2))
