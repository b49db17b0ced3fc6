"""Benchmark "toa": speed, memory and accuracy of the TOA engine against SciPy, same run, same start.

Part 1, no offsets: 3-D networks of I receivers x J sources uniform in a 10 x 10 x 5 m volume,
range noise sigma = 1 cm, 5 % of the entries missing at random. For each size:

- ``init``: ``selfcal.toa.init.mds.initialize_toa(method="rank")``, timed once; every solver below
  starts from it (same start).
- ``ours_solve``: ``refine_toa(Y, r0, s0, covariance="none")`` (the Schur LM engine);
  ``ours_cov``: the exact covariance alone at the solution
  (:func:`selfcal.toa.engine.covariance.covariance_blocks`, selected inversion, all blocks, one BLAS
  thread) with ``cov_floor``, the CPU time of its four unavoidable BLAS calls on matrices of its
  size; ``ours_cov_2threads``: the same on two BLAS threads (compare wall time: CPU time counts
  both threads); ``ours_cov_local``: ``covariance="local"`` (each node's conditional block,
  O(I J d^2)) with its block-wise relative error against ``ours_cov``.
- ``ours_blind_cov`` / ``ours_blind_local``: ``solve_toa(Y, dim=3)`` end to end
  (initialisation, search, outlier rounds, final fit, exact / local covariances).
- ``scipy_trf``: ``scipy.optimize.least_squares(method="trf", x_scale="jac", tr_solver="lsmr")``
  with the analytic sparse Jacobian (:func:`selfcal.toa.toa_jacobian`), all coordinates free,
  no covariance: what a competent user would write.
- ``ratios``: every row over ``scipy_trf`` and over ``ours_solve``, CPU and wall, same run.
  ``SELFCAL_BENCH_TOA_ROWS`` (comma list of the row names above) runs a subset: a 2000 x 2000
  case is minutes of CPU; the baseline rows always run, so the ratios stay same-run.

Part 2, ``offsets="both"`` (paper 004): U units (a microphone and a loudspeaker 5 cm apart each)
in a 10 x 10 x 3 m room, internal delays U(0, 20 ms) and onsets U(0, 30 ms) times 343 m/s, range
noise 1 mm, 5 % missing; ``solve_toa(Y, offsets="both", covariance="none")`` blind, with its CPU
time, against two same-run baselines: ``truth_start``, one ``refine_toa`` from the true geometry and
offsets (``blind_over_truth_start`` CPU ratio; ``rss_over_truth_start`` ~ 1 says the blind solve
reached the same minimum), and up to ``OLD_INIT_MAX`` units ``init_before`` / ``init_now``, the
rank-d initialiser's old full-size multistart against the start it takes now.

Part 3, ``large`` (``SELFCAL_BENCH_TOA_LARGE``, default 2000x2000): refine + every covariance
block from a near-truth start, CPU time and peak memory, with the BLAS floor of the exact blocks
(syrk + potrf + trtri + trsm on matrices of the reduced system's size, same run) and one dense
factorization of the reduced system alone.

Part 4, ``sparse`` (``SELFCAL_BENCH_TOA_SPARSE``, default ``2000:0.01,10000:0.01`` = nodes per
side : fraction of pairs observed): :func:`selfcal.toa.solve_toa_sparse` blind on a network with
ranges only between nearby nodes (100 m cube, 1 cm), against the engine started at the truth and,
up to 3000 nodes, the CRLB; ``cov_one_receiver``: the exact covariance block of the best
connected receiver (:mod:`selfcal.toa.engine.sparse_covariance`, d CG solves on the pairs), its time
and predicted std; ``weakly_placed`` / ``mirrors_taken``: nodes left with <= d + 1 ranges and
how many the mirror re-check moved.

Every row carries the wall time (median over ``repeats``), the peak resident memory during its
first call (sampled every 5 ms from /proc, no tracing overhead; absolute and above the RSS at the
call's start) and its efficiency: aligned RMSE (003 eq. 18) over the
CRLB of the same network and mask (``toa_crlb``, gauge-free). The machine's load average is
recorded: on a shared machine times are only comparable within one run (ratios).

Run: ``python benchmarks/run_all.py --only toa --out /tmp/bench_toa``; smaller sizes with
``SELFCAL_BENCH_TOA_SIZES=100x100,300x300`` and ``SELFCAL_BENCH_TOA_UNITS=60,120`` (comma lists).
"""

from __future__ import annotations

import json
import os
import platform
import statistics
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

SIZES = [(100, 100, 3), (1000, 1000, 1)]  # (I, J, repeats)
UNITS = [120, 500, 1000]
SIGMA = 0.01
SIGMA_UNITS = 0.001
MISSING = 0.05
DIM = 3
#: offsets='both' rows: the initialiser's before/after baseline runs up to this many units (the
#: old full-size multistart takes minutes above it)
OLD_INIT_MAX = 500


def _sizes() -> list[tuple[int, int, int]]:
    env = os.environ.get("SELFCAL_BENCH_TOA_SIZES")
    if env is None:
        return SIZES
    out = []
    for tok in filter(str.strip, env.split(",")):
        i, j = (int(v) for v in tok.lower().split("x"))
        out.append((i, j, 3 if i * j <= 1e5 else 1))
    return out


def _large() -> list[tuple[int, int]]:
    env = os.environ.get("SELFCAL_BENCH_TOA_LARGE", "2000x2000")
    return [tuple(int(v) for v in tok.lower().split("x")) for tok in filter(str.strip, env.split(","))]  # type: ignore[misc]


def _sparse() -> list[tuple[int, float]]:
    env = os.environ.get("SELFCAL_BENCH_TOA_SPARSE", "2000:0.01,10000:0.01")
    out = []
    for tok in filter(str.strip, env.split(",")):
        n, f = tok.split(":")
        out.append((int(n), float(f)))
    return out


def _units() -> list[int]:
    env = os.environ.get("SELFCAL_BENCH_TOA_UNITS")
    return UNITS if env is None else [int(v) for v in env.split(",") if v.strip()]


def _rss_mb() -> float:
    """Resident set size of this process, MiB (Linux /proc; ru_maxrss elsewhere)."""
    try:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20
    except OSError:
        import resource

        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**10


class _PeakRss:
    """Peak resident memory during a block, sampled every 5 ms by a thread (no tracing overhead)."""

    def __enter__(self) -> _PeakRss:
        self.base = self.peak = _rss_mb()
        self._stop = threading.Event()
        self._t = threading.Thread(target=self._run, daemon=True)
        self._t.start()
        return self

    def _run(self) -> None:
        while not self._stop.wait(0.005):
            self.peak = max(self.peak, _rss_mb())

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._t.join()
        self.peak = max(self.peak, _rss_mb())


def _timed(fn: Any, repeats: int = 1) -> tuple[dict[str, Any], Any]:
    """Median wall time over ``repeats`` and the peak resident memory of the first call.

    ``peak_rss_mb`` is the process's peak RSS during the call (data and interpreter included),
    ``peak_rss_increase_mb`` the part above the RSS at its start; ``cpu_s`` the median process
    CPU time (less inflated than wall time by other jobs on a shared machine).
    """
    times, cpus, out = [], [], None
    with _PeakRss() as mem:
        t, c = time.perf_counter(), time.process_time()
        out = fn()
        times.append(time.perf_counter() - t)
        cpus.append(time.process_time() - c)
    for _ in range(repeats - 1):
        t, c = time.perf_counter(), time.process_time()
        out = fn()
        times.append(time.perf_counter() - t)
        cpus.append(time.process_time() - c)
    return {"time_s": statistics.median(times), "times_s": times, "cpu_s": statistics.median(cpus),
            "peak_rss_mb": mem.peak, "peak_rss_increase_mb": mem.peak - mem.base}, out


def _scene(I: int, J: int, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    from selfcal.toa import toa_model

    rng = np.random.default_rng(seed)
    box = np.array([10.0, 10.0, 5.0])
    r = rng.uniform(0, 1, (I, DIM)) * box
    s = rng.uniform(0, 1, (J, DIM)) * box
    Y = toa_model(r, s) + rng.normal(0, SIGMA, (I, J))
    Y[rng.random((I, J)) < MISSING] = np.nan
    return r, s, Y


def _accuracy(re: np.ndarray, se: np.ndarray, r: np.ndarray, s: np.ndarray, crlb: Any) -> dict[str, float]:
    from selfcal.metrics import aligned_rmse

    e = aligned_rmse(re, r, se, s)
    out = {"rmse_receivers": e.rmse_receivers, "rmse_sources": float(e.rmse_sources or np.nan)}
    out["efficiency_receivers"] = out["rmse_receivers"] / crlb.rmse_receivers
    out["efficiency_sources"] = out["rmse_sources"] / crlb.rmse_sources
    return out


def _scipy_trf(Y: np.ndarray, r0: np.ndarray, s0: np.ndarray) -> tuple[np.ndarray, np.ndarray, Any]:
    from scipy.optimize import least_squares

    from selfcal.toa import toa_jacobian, toa_residuals

    I, J = Y.shape
    x0 = np.concatenate([r0.ravel(), s0.ravel()])
    res = least_squares(lambda x: toa_residuals(x, Y, DIM), x0, jac=lambda x: toa_jacobian(x, Y, DIM),
                        method="trf", x_scale="jac", tr_solver="lsmr")
    return res.x[: I * DIM].reshape(I, DIM), res.x[I * DIM:].reshape(J, DIM), res


def _rows() -> set[str] | None:
    """Rows of the dense cases to run (``SELFCAL_BENCH_TOA_ROWS``, comma list; None = all).

    A 2000 x 2000 case takes minutes of CPU; its rows can be measured in separate runs
    (``ours_solve`` and ``scipy_trf`` are always run: every ratio is against them, same run).
    """
    env = os.environ.get("SELFCAL_BENCH_TOA_ROWS")
    return None if not env else {t.strip() for t in env.split(",") if t.strip()}


def _cpu_ratio(case: dict[str, Any], a: str, b: str) -> dict[str, float]:
    """``a / b`` in CPU time and in wall time (both rows of the same run)."""
    return {"cpu": case[a]["cpu_s"] / case[b]["cpu_s"], "wall": case[a]["time_s"] / case[b]["time_s"]}


def _dense_case(I: int, J: int, reps: int) -> dict[str, Any]:
    """Same network, same start (the rank initialiser), one process, these rows:

    ``scipy_trf`` (the baseline), ``ours_solve``, ``ours_cov`` (exact blocks, one BLAS
    thread), ``ours_cov_2threads`` (the same, two threads: CPU time counts both, compare wall),
    ``ours_cov_local`` (``covariance="local"``), ``ours_blind_cov`` (``solve_toa`` end to end
    with exact blocks at the default threads) and ``ours_blind_local``. ``ratios``: each row
    over the solve and over SciPy, CPU and wall.
    """
    from selfcal.toa import refine_toa, solve_toa, toa_crlb
    from selfcal.toa.engine.covariance import covariance_blocks, dense_threads
    from selfcal.toa.init.mds import initialize_toa

    want = _rows()

    def on(name: str) -> bool:
        return want is None or name in want

    r, s, Y = _scene(I, J, seed=I + J)
    obs = np.isfinite(Y)
    crlb = toa_crlb(r, s, SIGMA, mask=obs)
    case: dict[str, Any] = {"shape": [I, J], "missing": MISSING, "repeats": reps, "dense_threads": dense_threads(),
                            "crlb": {"rmse_receivers": crlb.rmse_receivers, "rmse_sources": crlb.rmse_sources}}
    row, (r0, s0) = _timed(lambda: initialize_toa(Y, DIM, method="rank", rng=0))
    case["init"] = row
    row, (rt, st, res) = _timed(lambda: _scipy_trf(Y, r0, s0), 1)
    case["scipy_trf"] = {**row, "nfev": int(res.nfev), "status": int(res.status), **_accuracy(rt, st, r, s, crlb)}
    row, sol = _timed(lambda: refine_toa(Y, r0, s0, covariance="none"), reps)
    case["ours_solve"] = {**row, "iterations": sol.iterations, "converged": sol.converged,
                          **_accuracy(sol.receivers, sol.sources, r, s, crlb)}
    w = np.where(obs, 1.0, 0.0)
    exact = None
    if on("ours_cov"):
        row, exact = _timed(lambda: covariance_blocks(sol.receivers, sol.sources, w, threads=1), reps)
        case["ours_cov"] = row
        case["cov_floor"] = _blas_floor(DIM * min(I, J), DIM * max(I, J))
    if on("ours_cov_2threads"):
        row, _ = _timed(lambda: covariance_blocks(sol.receivers, sol.sources, w, threads=2), reps)
        case["ours_cov_2threads"] = row
    if on("ours_cov_local"):
        row, loc = _timed(lambda: covariance_blocks(sol.receivers, sol.sources, w, covariance="local"), reps)
        if exact is not None:  # block-wise relative Frobenius error against the exact blocks
            err = [np.linalg.norm(a - b, axis=(1, 2)) / np.linalg.norm(b, axis=(1, 2)) for a, b in zip(loc, exact, strict=True)]
            row["rel_error_max"] = float(max(e.max() for e in err))
            row["rel_error_median"] = float(np.median(np.concatenate(err)))
        case["ours_cov_local"] = row
    for key, spec in (("ours_blind_cov", "all"), ("ours_blind_local", "local")):
        if on(key):
            row, blind = _timed(lambda spec=spec: solve_toa(Y, dim=DIM, rng=0, covariance=spec), 1)
            pred = float(np.sqrt(np.nanmean(np.trace(blind.receiver_cov, axis1=1, axis2=2))))
            case[key] = {**row, "method": blind.method, "predicted_rmse_receivers": pred,
                         **_accuracy(blind.receivers, blind.sources, r, s, crlb)}
    case["ratios"] = {}
    for key in ("ours_solve", "ours_cov", "ours_cov_2threads", "ours_cov_local", "ours_blind_cov", "ours_blind_local"):
        if key in case:
            case["ratios"][f"{key}_over_scipy"] = _cpu_ratio(case, key, "scipy_trf")
            if key != "ours_solve":
                case["ratios"][f"{key}_over_solve"] = _cpu_ratio(case, key, "ours_solve")
    if "cov_floor" in case:
        case["ratios"]["cov_floor_over_solve"] = {"cpu": case["cov_floor"]["total_cpu_s"] / case["ours_solve"]["cpu_s"]}
    return case


def _blas_floor(nA: int, nB: int) -> dict[str, Any]:
    """CPU time of the four BLAS / LAPACK calls the exact covariance blocks cannot avoid.

    Random matrices of the reduced system's sizes (nA = d x kept nodes, nB = d x eliminated
    nodes): ``syrk`` (S = A - H H^T, nA^2 nB flops), ``potrf`` (nA^3 / 3), ``trtri`` (the K
    blocks, nA^3 / 3) and ``trsm`` (the E blocks, nA^2 nB). Their sum is the floor of the
    selected inversion on this machine, measured in the same run as the solve.
    """
    import scipy.linalg

    rng = np.random.default_rng(0)
    H = np.asfortranarray(rng.normal(size=(nA, nB)))
    out: dict[str, Any] = {"nA": nA, "nB": nB}
    c = time.process_time()
    S = scipy.linalg.blas.dsyrk(1.0, H, trans=0, lower=1)
    out["syrk_cpu_s"] = time.process_time() - c
    S = np.asfortranarray(S + S.T - np.diag(np.diag(S)) + nB * np.eye(nA))
    c = time.process_time()
    L, _ = scipy.linalg.lapack.dpotrf(S, lower=1, clean=1, overwrite_a=1)
    out["potrf_cpu_s"] = time.process_time() - c
    c = time.process_time()
    scipy.linalg.solve_triangular(L, H, lower=True, check_finite=False, overwrite_b=True)
    out["trsm_cpu_s"] = time.process_time() - c
    c = time.process_time()
    scipy.linalg.lapack.dtrtri(L, lower=1, overwrite_c=1)
    out["trtri_cpu_s"] = time.process_time() - c
    out["total_cpu_s"] = out["syrk_cpu_s"] + out["potrf_cpu_s"] + out["trsm_cpu_s"] + out["trtri_cpu_s"]
    return out


def _large_case(I: int, J: int) -> dict[str, Any]:
    """Refine + all covariance blocks from a near-truth start (3 cm): time, CPU, peak memory.

    The start is the truth plus 3 cm so the row measures the engine and the covariance at
    this size, not the initialiser; ``floor`` is the BLAS floor of the covariance (above)
    and ``factorization_floor_cpu_s`` one dense Cholesky of the reduced system alone.
    """
    from selfcal.toa import refine_toa

    r, s, Y = _scene(I, J, seed=I + J)
    rng = np.random.default_rng(1)
    r0, s0 = r + rng.normal(0, 0.03, r.shape), s + rng.normal(0, 0.03, s.shape)
    case: dict[str, Any] = {"shape": [I, J], "missing": MISSING, "start": "truth + 3 cm"}
    row, sol = _timed(lambda: refine_toa(Y, r0, s0, covariance="none"))
    case["solve"] = {**row, "iterations": sol.iterations}
    row, _ = _timed(lambda: refine_toa(Y, r0, s0, covariance="all"))
    case["solve_cov"] = row
    case["cov_cpu_s"] = row["cpu_s"] - case["solve"]["cpu_s"]
    nA, nB = DIM * min(I, J), DIM * max(I, J)
    case["floor"] = _blas_floor(nA, nB)
    case["factorization_floor_cpu_s"] = case["floor"]["potrf_cpu_s"]
    return case


def _sparse_case(N: int, fraction: float) -> dict[str, Any]:
    """Blind sparse network: N x N nodes in a 100 m cube, ranges only below the distance that
    gives ``fraction`` of the pairs, 1 cm noise (:func:`selfcal.toa.sparse.simulate_sparse_network`).

    Accuracy: against the same engine started at the truth (``oracle``: the ML estimate
    itself; a ratio of 1 says the blind run found the ML minimum) and, up to 3000 nodes, the
    CRLB of the observed pairs (``toa_crlb`` with the mask).
    """
    from selfcal.metrics import aligned_rmse
    from selfcal.toa import refine_toa_sparse, solve_toa_sparse, toa_crlb
    from selfcal.toa.sparse import simulate_sparse_network

    r, s, i, j, y = simulate_sparse_network(N, N, fraction, noise=SIGMA, rng=N)
    case: dict[str, Any] = {"nodes": [N, N], "fraction": fraction, "pairs": int(i.size),
                            "ranges_per_node": i.size / N}
    row, sol = _timed(lambda: solve_toa_sparse(i, j, y, N, N, rng=0))
    mr, ms = np.isfinite(sol.receivers[:, 0]), np.isfinite(sol.sources[:, 0])
    e = aligned_rmse(sol.receivers[mr], r[mr], sol.sources[ms], s[ms])
    case["blind"] = {**row, "converged": sol.converged, "iterations": sol.iterations,
                     "located": sol.located, "seed_shape": list(sol.seed_shape),
                     "noise_estimate": sol.noise_estimate, "rmse_receivers": e.rmse_receivers,
                     "rmse_sources": e.rmse_sources,
                     "weakly_placed": int(sol.weakly_placed_receivers.size + sol.weakly_placed_sources.size),
                     "mirrors_taken": sol.mirrors_taken}
    # exact covariance of one located receiver (the best connected), d CG solves on the pairs
    from selfcal.toa.engine.sparse_covariance import sparse_covariance_blocks

    used_pairs = np.isfinite(sol.residuals)
    ri_, si_ = np.cumsum(mr) - 1, np.cumsum(ms) - 1
    k = int(np.argmax(np.bincount(i[used_pairs], minlength=N)))
    row, (Cr, _) = _timed(lambda: sparse_covariance_blocks(ri_[i[used_pairs]], si_[j[used_pairs]], sol.receivers[mr],
                                                           sol.sources[ms], covariance=([ri_[k]], None)))
    case["cov_one_receiver"] = {**row, "predicted_std_m": float(sol.noise_estimate * np.sqrt(np.trace(Cr[ri_[k]])))}
    # the oracle: the same engine from the truth, on the nodes and pairs the blind fit used
    used = mr[i] & ms[j]
    ri, si = np.cumsum(mr) - 1, np.cumsum(ms) - 1
    orc = refine_toa_sparse(ri[i[used]], si[j[used]], y[used], r[mr], s[ms])
    eo = aligned_rmse(orc.receivers, r[mr], orc.sources, s[ms])
    case["oracle"] = {"rmse_receivers": eo.rmse_receivers, "rmse_sources": eo.rmse_sources}
    case["blind_over_oracle"] = e.rmse_receivers / eo.rmse_receivers
    if N <= 3000:
        mask = np.zeros((N, N), bool)
        mask[i, j] = True
        crlb = toa_crlb(r[mr], s[ms], SIGMA, mask=mask[np.ix_(mr, ms)])
        case["efficiency_receivers"] = e.rmse_receivers / crlb.rmse_receivers
        case["efficiency_sources"] = e.rmse_sources / crlb.rmse_sources
    return case


def _units_case(U: int, seed: int = 0) -> dict[str, Any]:
    from selfcal.toa import refine_toa, solve_toa, toa_crlb, toa_model

    rng = np.random.default_rng(seed)
    box = np.array([10.0, 10.0, 3.0])
    mic = rng.uniform(0, 1, (U, DIM)) * box
    spk = mic + rng.normal(0, 0.05, (U, DIM))
    d = rng.uniform(0, 0.020 * 343, U)
    o = rng.uniform(0, 0.030 * 343, U)
    Y = toa_model(mic, spk, d, o) + rng.normal(0, SIGMA_UNITS, (U, U))
    miss = rng.random((U, U)) < MISSING
    Y[miss] = np.nan
    crlb = toa_crlb(mic, spk, SIGMA_UNITS, offsets="both", mask=~miss)
    cpu = time.process_time()
    row, res = _timed(lambda: solve_toa(Y, dim=DIM, offsets="both", rng=0, covariance="none"), 1)
    row["cpu_s"] = time.process_time() - cpu
    out: dict[str, Any] = {"units": U, "missing": MISSING, **row, "method": res.method,
                           "crlb": {"rmse_receivers": crlb.rmse_receivers, "rmse_sources": crlb.rmse_sources},
                           **_accuracy(res.receivers, res.sources, mic, spk, crlb)}
    rss_blind = float(np.nansum(res.residuals**2))
    # same-run baseline 1: one refinement of the engine started from the truth (the floor of
    # any blind solve, and the minimum it must reach: rss_over_truth_start ~ 1)
    cpu = time.process_time()
    row, ref = _timed(lambda: refine_toa(Y, mic, spk, offsets="both", receiver_offsets0=d, source_offsets0=o,
                                         covariance="none"), 1)
    row["cpu_s"] = time.process_time() - cpu
    out["truth_start"] = {**row, "iterations": ref.iterations, "rss_m2": float(np.nansum(ref.residuals**2))}
    out["rss_blind_m2"] = rss_blind
    out["rss_over_truth_start"] = rss_blind / out["truth_start"]["rss_m2"]
    out["blind_over_truth_start"] = out["cpu_s"] / max(row["cpu_s"], 1e-9)
    # same-run baseline 2 (up to OLD_INIT_MAX units): the rank-d initialiser as it ran before
    # 2026-12-01, the full-size multistart with the missing entries as unknowns (max_candidates=2
    # keeps that path), against the one start solve_toa now takes (max_candidates=1)
    if U <= OLD_INIT_MAX:
        from selfcal.toa.init.offsets_init import initialize_offsets_candidates

        for key, k in (("init_now", 1), ("init_before", 2)):
            cpu = time.process_time()
            row, _ = _timed(lambda k=k: initialize_offsets_candidates(Y, DIM, rng=0, max_candidates=k), 1)
            out[key] = {**row, "cpu_s": time.process_time() - cpu}
        out["init_now_over_before"] = out["init_now"]["cpu_s"] / out["init_before"]["cpu_s"]
    return out


def main(out_dir: Path) -> dict[str, Any]:
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    report: dict[str, Any] = {
        "name": "toa",
        "setup": (f"part 1: 3-D, uniform in 10x10x5 m, sigma = {SIGMA} m, {MISSING:.0%} missing, all solvers from "
                  "the rank initialiser; part 2: offsets='both', units in 10x10x3 m, sigma = "
                  f"{SIGMA_UNITS} m, {MISSING:.0%} missing, blind"),
        "machine": {"cpus": os.cpu_count(), "load_average_at_start": list(os.getloadavg()),
                    "python": platform.python_version(), "numpy": np.__version__,
                    "OPENBLAS_NUM_THREADS": os.environ.get("OPENBLAS_NUM_THREADS")},
        "cases": [],
        "large": [],
        "sparse": [],
        "offsets_both": [],
    }
    for I, J, reps in _sizes():
        case = _dense_case(I, J, reps)
        report["cases"].append(case)
        parts = [f"[toa] {I}x{J} (CPU s): scipy trf {case['scipy_trf']['cpu_s']:.3g}, solve {case['ours_solve']['cpu_s']:.3g}"]
        for key, label in (("ours_cov", "cov"), ("ours_cov_2threads", "cov 2 threads (wall)"),
                           ("ours_cov_local", "cov local"), ("ours_blind_cov", "blind+cov"),
                           ("ours_blind_local", "blind+local")):
            if key in case:
                v = case[key]["time_s" if "2threads" in key else "cpu_s"]
                ratio = case["ratios"][f"{key}_over_scipy"]["wall" if "2threads" in key else "cpu"]
                parts.append(f"{label} {v:.3g} (x{ratio:.2f} scipy)")
        print(", ".join(parts))
    for I, J in _large():
        case = _large_case(I, J)
        report["large"].append(case)
        print(f"[toa] {I}x{J} near-truth: solve {case['solve']['cpu_s']:.3g} s CPU, +cov {case['cov_cpu_s']:.3g} s "
              f"(BLAS floor {case['floor']['total_cpu_s']:.3g} s, one potrf {case['factorization_floor_cpu_s']:.3g} s), "
              f"peak RSS {case['solve_cov']['peak_rss_mb']:.0f} MB")
    for N, frac in _sparse():
        case = _sparse_case(N, frac)
        report["sparse"].append(case)
        b = case["blind"]
        print(f"[toa] sparse {N}x{N} ({case['pairs']} pairs): blind {b['time_s']:.3g} s ({b['cpu_s']:.3g} s CPU), "
              f"peak RSS {b['peak_rss_mb']:.0f} MB, noise {b['noise_estimate']:.4g}, blind/oracle "
              f"{case['blind_over_oracle']:.3f}, weakly placed {b['weakly_placed']}, one receiver's covariance "
              f"{case['cov_one_receiver']['cpu_s']:.3g} s CPU")
    for U in _units():
        row = _units_case(U)
        report["offsets_both"].append(row)
        print(f"[toa] offsets=both {U} units: {row['time_s']:.3g} s ({row['cpu_s']:.3g} s CPU, "
              f"x{row['blind_over_truth_start']:.2f} a truth-started refinement), peak RSS {row['peak_rss_mb']:.0f} MB, "
              f"rss/truth-start {row['rss_over_truth_start']:.6f}, efficiency {row['efficiency_receivers']:.3f}")
    report["machine"]["load_average_at_end"] = list(os.getloadavg())
    path = out_dir / "toa.json"
    tmp = path.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(report, indent=2, default=float))
    tmp.replace(path)
    return report


if __name__ == "__main__":
    import sys

    print(json.dumps(main(Path(sys.argv[1] if len(sys.argv) > 1 else "benchmarks/results")), indent=2))
