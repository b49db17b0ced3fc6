"""Far-field TDOA (paper 000) speed: batched minimal solver, LM for m = 48, k = 540, and the
scaling table (48 x 540, 500 x 1000, 2000 x 200, 2000 x 2000).

Writes ``<out_dir>/farfield.json``. Medians over repetitions; ratios are against baselines
run in the same process (the minimal solver called one problem at a time; alternating
optimisation on the same LM problem; for the scaling table the dense path this module had
before issue 16 -- every LM step eliminating the directions into a dense 3(m-1) system and
the covariance by a dense pseudo-inverse of it -- on the same problem from the same start),
so machine load cancels to first order. The dense baseline is skipped where 3(m-1) > 1500
(its O(m^3) pseudo-inverse alone would take minutes; the issue measured 6.5 min and 1.6 GB at
2000 x 200), and the row says so. Peak memory is numpy's allocations seen by tracemalloc.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from selfcal.io import write_json
from selfcal.tdoa import refine_lm, solve_farfield, solve_minimal
from selfcal.tdoa.alternating import refine_alternating
from selfcal.tdoa.initialize import initialize_farfield


def _median_time(fn: Callable[[], Any], reps: int) -> float:
    times = []
    for _ in range(reps):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return float(np.median(times))


#: CPU seconds of the last :func:`_timed_peak` call (wall time is inflated on a shared machine)
_LAST_CPU = [0.0]


def _timed_peak(fn: Callable[[], Any]) -> tuple[Any, float, float]:
    """(result, wall seconds, peak MiB of traced allocations) of one call; its CPU seconds in
    ``_LAST_CPU[0]``."""
    import tracemalloc

    tracemalloc.start()
    t0, c0 = time.perf_counter(), time.process_time()
    out = fn()
    dt = time.perf_counter() - t0
    _LAST_CPU[0] = time.process_time() - c0
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    return out, dt, peak / 2**20


#: (m, k) of the scaling table; dense baseline only where 3(m-1) <= DENSE_MAX
SCALING_SIZES = ((48, 540), (500, 1000), (2000, 200), (2000, 2000))
DENSE_MAX = 1500


def scaling_table(sizes: tuple[tuple[int, int], ...] = SCALING_SIZES, *, seed: int = 0) -> list[dict[str, Any]]:
    """LM + covariance from the same initialisation: sparse (Schur / CG) vs the dense baseline."""
    return [_scaling_row(m, k, seed) for m, k in sizes]


def _scaling_row(m: int, k: int, seed: int) -> dict[str, Any]:
    """One row of :func:`scaling_table`."""
    rng = np.random.default_rng(seed)
    Zt = rng.uniform(-0.5, 0.5, (m, 3))
    Zt[0] = 0
    Nt = _unit(rng.normal(size=(k, 3)))
    D = Zt @ Nt.T + rng.normal(size=k) + 1e-3 * rng.normal(size=(m, k))
    init = initialize_farfield(D - D.mean(axis=0))
    Z0 = init.positions - init.positions[0]
    C0 = np.mean(D - Z0 @ init.directions.T, axis=0)
    # the covariance as refine_lm decides by default (skipped above COV_DIRECT_MAX unknowns)
    sparse, t_sp, mem_sp = _timed_peak(lambda: refine_lm(D, Z0, init.directions, C0, free_offsets=True))
    row: dict[str, Any] = {"m": m, "k": k, "entries": m * k, "sparse_seconds": t_sp, "sparse_peak_mib": mem_sp,
                           "sparse_cpu_seconds": _LAST_CPU[0],
                           "sparse_iterations": sparse.iterations, "data_mib": D.nbytes / 2**20,
                           "covariance_computed": sparse.position_cov is not None}
    if 3 * (m - 1) <= DENSE_MAX:
        dense, t_de, mem_de = _timed_peak(lambda: refine_lm(
            D, Z0, init.directions, C0, free_offsets=True, covariance=True, linear_solver="directions",
            covariance_method="dense"))
        row.update({"dense_seconds": t_de, "dense_cpu_seconds": _LAST_CPU[0], "dense_peak_mib": mem_de,
                    "speedup_vs_dense": t_de / t_sp, "cpu_speedup_vs_dense": _LAST_CPU[0] / row["sparse_cpu_seconds"],
                    "cov_max_rel_diff": float(np.abs(sparse.position_cov - dense.position_cov).max()
                                              / np.abs(dense.position_cov).max()),
                    "cost_rel_diff": abs(sparse.cost - dense.cost) / dense.cost})
    else:
        row["dense_skipped"] = f"3(m-1) = {3 * (m - 1)} > {DENSE_MAX}: the dense pseudo-inverse would take minutes"
        if min(3 * (m - 1), 3 * k) <= DENSE_MAX:
            # one LM step each way on the same normal equations: the dense baseline's step
            # (a 3(m-1) system) against the Schur step over the small side
            from selfcal.tdoa.refine import _lm_step, _normal_equations

            H = _normal_equations(D, Z0, init.directions, C0, np.ones((m, k)), True)
            t_step_de = _median_time(lambda: _lm_step(*H[:5], 1e-3, side="directions"), 1)
            t_step_sp = _median_time(lambda: _lm_step(*H[:5], 1e-3), 3)
            row.update({"dense_step_seconds": t_step_de, "sparse_step_seconds": t_step_sp,
                        "step_speedup_vs_dense": t_step_de / t_step_sp})
    return row


def format_table(rows: list[dict[str, Any]]) -> str:
    """The scaling table as markdown: size, sparse seconds / peak MiB, dense baseline, ratio."""
    lines = ["| m x k | sparse LM + cov [s wall / CPU] | peak [MiB] | dense baseline [s wall / CPU] | "
             "dense / sparse (CPU) | note |",
             "|---|---|---|---|---|---|"]
    for r in rows:
        dense = f"{r['dense_seconds']:.2f} / {r['dense_cpu_seconds']:.2f}" if "dense_seconds" in r else "-"
        ratio = f"{r['cpu_speedup_vs_dense']:.2f}" if "cpu_speedup_vs_dense" in r else (
            f"{r['step_speedup_vs_dense']:.1f} (one step)" if "step_speedup_vs_dense" in r else "-")
        note = "covariance skipped (above COV_DIRECT_MAX)" if not r["covariance_computed"] else ""
        if "dense_skipped" in r:
            note = (note + "; " if note else "") + "dense baseline skipped (minutes)"
        lines.append(f"| {r['m']} x {r['k']} | {r['sparse_seconds']:.2f} / {r['sparse_cpu_seconds']:.2f} | "
                     f"{r['sparse_peak_mib']:.0f} | {dense} | "
                     f"{ratio} | {note} |")
    return "\n".join(lines)


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
    sizes = SCALING_SIZES if not os.environ.get("SELFCAL_BENCH_QUICK") else SCALING_SIZES[:2]
    table = scaling_table(sizes)

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
        "scaling": table,
        "cpu_count": os.cpu_count(),
        "blas_threads_env": os.environ.get("OPENBLAS_NUM_THREADS") or os.environ.get("OMP_NUM_THREADS"),
    }
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    write_json(out_dir / "farfield.json", result)
    import sys

    print("far-field scaling (LM from the same start, wall seconds; dense = the pre-issue-16 path):", file=sys.stderr)
    print(format_table(table), file=sys.stderr)
    return result


if __name__ == "__main__":
    import json
    import sys

    print(json.dumps(main(Path(sys.argv[1] if len(sys.argv) > 1 else "benchmarks/results")), indent=2))
