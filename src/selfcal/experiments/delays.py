"""Reproductions of paper 004's experiments (onset times and internal delays), Fig. 4.1-4.5.

Every trial is a module-level function ``trial(params, seed) -> dict`` run through
:func:`selfcal.experiments.runner.run_sweep`.

* Fig. 4.1-4.3 -- final Frobenius norm F (3.17) and ``||p_hat - p_real||`` (4.1) for 12-32 units
  (step 4, 20 tests each) in the 30 x 30 x 12 m and 12 x 12 x 2 m rooms, one run from the
  thesis random initialisation per test ("unfiltered"), and the runs with F <= 8e-7 s^2
  ("filtered"); for both the thesis iteration ("faithful") and our fast solver; plus the
  fast solver with the acceptance test + restarts (every test then gives an answer).
* Fig. 4.4 -- run time for 20 units (12 x 12 x 2 m, 25 runs) and 120 units (30 x 30 x 12 m,
  15 runs). The faithful iteration at 120 units is capped and its time to convergence
  extrapolated from its observed linear rate (stated in the JSON).
* Fig. 4.5 -- F per iteration for several lambda (listing A.1.3 scaling, seconds) on one
  fixed setup and initialisation.
* Beyond the thesis -- timing noise sigma = 10 and 50 us with distinct internal delays:
  rank-3 estimate alone and after the NLS refinement (``solve_toa(offsets="both")``),
  efficiency against the CRLB (``toa_crlb(..., offsets="both")``).

All quantities are reported in the thesis's units: seconds and s^2 (F in m^2 divided by c^2).
"""

from __future__ import annotations

import time
import warnings
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..errors import ConvergenceWarning
from ..io import write_json
from ..scenarios.units import SPEED_OF_SOUND, make_units, true_offset_vector
from ..toa.init.rank3 import estimate_offsets, fast_offsets
from ..toa.init.rank3_model import DELAY_MAX, ONSET_MAX, THESIS_TOL, Rank3Result, thesis_lambda
from ..toa.init.rank3_thesis import rank3_iteration
from .runner import run_sweep, write_rows

__all__ = [
    "PAPER",
    "UNITS",
    "LAMBDAS",
    "accuracy_trial",
    "timing_trial",
    "lambda_trial",
    "noise_trial",
    "reproduce_all",
]

Array = NDArray[np.float64]
C = SPEED_OF_SOUND
UNITS = (12, 16, 20, 24, 28, 32)
#: lambda values of Fig. 4.5 in the listing's convention (seconds, multiplied by I+J-1)
LAMBDAS = (0.0, 1e-4, 1e-3, 1e-2, 1e-1)
ACCEPT_S2 = 8e-7

#: the thesis's reported numbers (sec. 4.3, A.1.4)
PAPER: dict[str, Any] = {
    "p_error_s": "below 1e-6 for every accepted run, mostly below 1e-7 with more units (Fig. 4.2, 4.3)",
    "frobenius_accepted_s2": [1e-9, 1e-8],
    "accept_threshold_s2": ACCEPT_S2,
    "tol_s2": 1e-12,
    "max_iter": 1_000_000,
    "time_20_units_mean_s": 6.6,
    "time_20_units_max_s": 35.5,
    "time_120_units_mean_s": 84.2,
    "time_120_units_max_s": 105.4,
    "platform": "MATLAB 2016b, Intel Core i5-4690 3.5 GHz",
    "lambda": "no value of lambda is consistently fastest (Fig. 4.5)",
}


def _p_true(sc: Any) -> Array:
    return true_offset_vector(sc.delays, sc.onsets)


def _single_run(R: Array, method: str, max_iter: int, rng: np.random.Generator) -> Rank3Result:
    """One run from the thesis random initialisation (no acceptance test): the thesis's protocol."""
    if method == "faithful":
        return rank3_iteration(R, rng=rng, max_iter=max_iter)
    return fast_offsets(R, rng=rng)


# ----------------------------------------------------------------------------- Fig. 4.1-4.3
def accuracy_trial(params: dict[str, Any], seed: int) -> dict[str, Any]:
    """One test of Fig. 4.1-4.3: params room, units, method, max_iter."""
    gen = np.random.default_rng(seed)
    sc = make_units(int(params["units"]), room=params["room"], rng=gen)
    p = _p_true(sc)
    R = sc.ranges
    res = _single_run(R, params["method"], int(params.get("max_iter", 1_000_000)), gen)
    out: dict[str, Any] = {
        "frobenius_s2": res.frobenius / C**2,
        "p_error_s": float(np.linalg.norm(res.p / C - p)),
        "p_max_error_s": float(np.max(np.abs(res.p / C - p))),
        "accepted": bool(res.frobenius / C**2 <= ACCEPT_S2),
        "iterations": res.iterations,
        "converged": res.converged,
        "seconds": res.seconds,
    }
    if params["method"] == "fast":
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", ConvergenceWarning)
            rr = estimate_offsets(R, rng=gen)
        out.update(
            restarted_p_error_s=float(np.linalg.norm(rr.p / C - p)),
            restarted_accepted=bool(rr.accepted),
            restarts=rr.restarts,
            restarted_seconds=rr.seconds,
            restarted_iterations=rr.total_iterations,
        )
    return out


# ----------------------------------------------------------------------------- Fig. 4.4
def _extrapolate(res: Rank3Result, tol: float) -> float:
    """Iterations a capped faithful run still needs, from its observed linear rate of dF."""
    if res.converged:
        return 0.0
    dF = np.abs(np.diff(res.history))
    tail = dF[len(dF) // 2:]
    tail = tail[tail > 0]
    if tail.size < 10:
        return float("nan")
    n = np.arange(tail.size)
    slope = np.polyfit(n, np.log(tail), 1)[0]
    if slope >= 0:
        return float("nan")  # not yet in its linear regime: no honest extrapolation
    return float(max(0.0, np.log(tol / tail[-1]) / slope))


def timing_trial(params: dict[str, Any], seed: int) -> dict[str, Any]:
    """Run time of one estimate (Fig. 4.4): params room, units, method, max_iter.

    The fast method runs with the acceptance test and restarts (the default of
    :func:`estimate_offsets`); the faithful iteration runs once, capped at ``max_iter``, and
    the iterations it still needs are extrapolated from its observed linear rate.
    """
    gen = np.random.default_rng(seed)
    sc = make_units(int(params["units"]), room=params["room"], rng=gen)
    p = _p_true(sc)
    R = sc.ranges
    t0 = time.perf_counter()
    if params["method"] == "faithful":
        res = rank3_iteration(R, rng=gen, max_iter=int(params["max_iter"]))
    else:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", ConvergenceWarning)
            res = estimate_offsets(R, rng=gen)
    seconds = time.perf_counter() - t0
    extra_iters = _extrapolate(res, THESIS_TOL) if params["method"] == "faithful" else 0.0
    per_iter = seconds / max(res.iterations, 1)
    return {
        "seconds": seconds,
        "iterations": res.total_iterations,
        "converged": res.converged,
        "restarts": res.restarts,
        "accepted": bool(res.frobenius / C**2 <= ACCEPT_S2),
        "p_error_s": float(np.linalg.norm(res.p / C - p)),
        "seconds_per_iteration": per_iter,
        "extrapolated_iterations": res.iterations + extra_iters,
        "extrapolated_seconds": seconds + per_iter * extra_iters,
    }


# ----------------------------------------------------------------------------- Fig. 4.5
def lambda_trial(params: dict[str, Any], seed: int) -> dict[str, Any]:
    """Convergence of the regularised iteration for one lambda (Fig. 4.5) on a fixed setup.

    params: lam_s (listing convention, seconds), units, room, setup_seed, max_iter. The
    setup and the initialisation depend only on ``setup_seed`` so every lambda sees the same.
    """
    gen = np.random.default_rng(int(params["setup_seed"]))
    U = int(params["units"])
    sc = make_units(U, room=params["room"], rng=gen)
    p0 = np.concatenate([gen.uniform(0, DELAY_MAX, U), gen.uniform(0, ONSET_MAX, U - 1)])
    lam = thesis_lambda(float(params["lam_s"]), U, U)
    res = rank3_iteration(sc.ranges, p0=p0, lam=lam, max_iter=int(params["max_iter"]))
    h = res.history / C**2
    idx = np.unique(np.round(np.geomspace(1, h.size, 300)).astype(int) - 1)
    return {
        "iterations": res.iterations,
        "converged": res.converged,
        "lam_switch_iteration": res.extra.get("lam_switch_iteration"),
        "frobenius_s2": float(h[-1]),
        "p_error_s": float(np.linalg.norm(res.p / C - _p_true(sc))),
        "history_iteration": (idx + 1).tolist(),
        "history_frobenius_s2": h[idx].tolist(),
        "seconds": res.seconds,
    }


# ----------------------------------------------------------------------------- noise (beyond)
def _min_norm_offset_errors(err_delta: Array, err_tau: Array) -> Array:
    """Offset errors in the minimum-norm gauge of the CRLB (remove the unobservable common shift)."""
    c = (err_delta.sum() - err_tau.sum()) / (err_delta.size + err_tau.size)
    return np.concatenate([err_delta - c, err_tau + c])


def noise_trial(params: dict[str, Any], seed: int) -> dict[str, Any]:
    """Timing noise sigma (s), distinct delays: rank-3 alone, then NLS; squared errors and CRLB."""
    from ..metrics import aligned_rmse
    from ..toa import solve_toa, toa_crlb

    gen = np.random.default_rng(seed)
    sigma = float(params["sigma"])
    sc = make_units(int(params["units"]), room=params["room"], rng=gen, noise_std=sigma, equal_delays=False)
    p = _p_true(sc)
    U = sc.delays.size
    rank3 = estimate_offsets(sc.ranges, accept=None, rng=gen)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ConvergenceWarning)
        res = solve_toa(sc.times, dim=3, offsets="both", speed=C, rng=gen)
    assert res.receiver_offsets is not None and res.source_offsets is not None
    err_nls = _min_norm_offset_errors(res.receiver_offsets - p[:U],
                                      np.concatenate([[0.0], res.source_offsets[1:] - p[U:]]))
    err_r3 = _min_norm_offset_errors(rank3.receiver_offsets / C - p[:U],
                                     np.concatenate([[0.0], rank3.source_offsets[1:] / C - p[U:]]))
    al = aligned_rmse(res.receivers, sc.microphones, res.sources, sc.speakers, fit_on="all")
    bound = toa_crlb(sc.microphones, sc.speakers, sigma * C, offsets="both")
    assert bound.receiver_offset_var is not None and bound.source_offset_var is not None
    off_var = np.concatenate([bound.receiver_offset_var, bound.source_offset_var]) / C**2
    pos_se = float((al.rmse_receivers**2 * U + (al.rmse_sources or 0.0) ** 2 * U) / (2 * U))
    return {
        "offset_mse_nls_s2": float(np.mean(err_nls**2)),
        "offset_mse_rank3_s2": float(np.mean(err_r3**2)),
        "offset_crlb_s2": float(np.mean(off_var)),
        "position_mse_m2": pos_se,
        "position_crlb_m2": float((bound.rmse_receivers**2 + bound.rmse_sources**2) / 2),
        "nls_converged": bool(res.converged),
        "method": res.method,
    }


# ----------------------------------------------------------------------------- aggregation + figures
def _stats(values: list[float]) -> dict[str, float]:
    a = np.asarray(values, dtype=float)
    if a.size == 0:
        return {"n": 0}
    return {"n": int(a.size), "mean": float(np.mean(a)), "median": float(np.median(a)),
            "min": float(np.min(a)), "max": float(np.max(a))}


def _summarise_accuracy(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    out = []
    keys = sorted({(r["room"], r["method"], r["units"]) for r in rows})
    for room, method, units in keys:
        sel = [r for r in rows if (r["room"], r["method"], r["units"]) == (room, method, units)]
        acc = [r for r in sel if r["accepted"]]
        item: dict[str, Any] = {
            "room": room, "method": method, "units": units, "tests": len(sel),
            "accepted": len(acc),
            "frobenius_s2": _stats([r["frobenius_s2"] for r in sel]),
            "frobenius_s2_filtered": _stats([r["frobenius_s2"] for r in acc]),
            "p_error_s": _stats([r["p_error_s"] for r in sel]),
            "p_error_s_filtered": _stats([r["p_error_s"] for r in acc]),
            "iterations": _stats([r["iterations"] for r in sel]),
            "seconds": _stats([r["seconds"] for r in sel]),
        }
        if method == "fast":
            item["with_restarts"] = {
                "accepted": sum(bool(r["restarted_accepted"]) for r in sel),
                "p_error_s": _stats([r["restarted_p_error_s"] for r in sel]),
                "restarts": _stats([r["restarts"] for r in sel]),
                "seconds": _stats([r["restarted_seconds"] for r in sel]),
            }
        out.append(item)
    return out


def reproduce_all(
    out: Path,
    *,
    runs: int = 20,
    faithful_runs: int = 2,
    max_iter: int = 50_000,
    timing_runs: tuple[int, int] = (25, 15),
    faithful_timing_runs: tuple[int, int] = (3, 2),
    cap_120: int = 20_000,
    lambda_max_iter: int = 100_000,
    noise_runs: int = 10,
    units: tuple[int, ...] = UNITS,
    full: bool = False,
    backend: str = "processes",
    scheduler: str | None = None,
    seed: int = 0,
    progress: bool = True,
) -> dict[str, Any]:
    """Run every 004 reproduction, write ``delays.json``, the tidy rows and the PNG figures to ``out``.

    Defaults are reduced for the faithful iteration (``faithful_runs`` tests per point, capped
    at ``max_iter`` iterations; 120-unit timing capped at ``cap_120`` and extrapolated).
    ``full=True`` is the thesis protocol: 20 faithful tests per point, 1e6 iterations, 25 / 15
    timing runs of both methods, uncapped.
    """
    from ..plotting.delays import plot_accuracy, plot_lambda, plot_noise, plot_timing

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    if full:
        faithful_runs, max_iter = runs, 1_000_000
        faithful_timing_runs, cap_120 = timing_runs, 1_000_000
    sweep: dict[str, Any] = {"backend": backend, "scheduler": scheduler, "progress": progress}
    rooms = ("large", "small")

    t0 = time.perf_counter()
    acc_rows = run_sweep(accuracy_trial, [{"room": r, "units": u, "method": "fast"} for r in rooms for u in units],
                         runs=runs, seed=seed, desc="Fig 4.1-4.3 fast", **sweep)
    if faithful_runs > 0:
        acc_rows += run_sweep(
            accuracy_trial,
            [{"room": r, "units": u, "method": "faithful", "max_iter": max_iter} for r in rooms for u in units],
            runs=faithful_runs, seed=seed + 1, desc="Fig 4.1-4.3 faithful", **sweep)
    write_rows(acc_rows, out / "accuracy_rows.csv")
    acc = _summarise_accuracy(acc_rows)
    plot_accuracy(acc, out / "fig4_1-4_3_accuracy.png", accept_s2=ACCEPT_S2)

    grid_t = [{"room": "small", "units": 20, "method": "fast", "max_iter": 0},
              {"room": "large", "units": 120, "method": "fast", "max_iter": 0}]
    t_rows = []
    for g, n in zip(grid_t, timing_runs, strict=True):
        t_rows += run_sweep(timing_trial, [g], runs=n, seed=seed + 2, desc=f"Fig 4.4 fast {g['units']}", **sweep)
    for g, n, cap in zip(grid_t, faithful_timing_runs, (1_000_000, cap_120), strict=True):
        if n > 0:
            t_rows += run_sweep(timing_trial, [{**g, "method": "faithful", "max_iter": cap}], runs=n,
                                seed=seed + 2, desc=f"Fig 4.4 faithful {g['units']}", **sweep)
    write_rows(t_rows, out / "timing_rows.csv")
    plot_timing(t_rows, out / "fig4_4_timing.png",
                thesis_means={20: PAPER["time_20_units_mean_s"], 120: PAPER["time_120_units_mean_s"]})
    timing = []
    for g in grid_t:
        for method in ("fast", "faithful"):
            sel = [r for r in t_rows if r["units"] == g["units"] and r["method"] == method]
            if sel:
                timing.append({
                    "room": g["room"], "units": g["units"], "method": method, "runs": len(sel),
                    "seconds": _stats([r["seconds"] for r in sel]),
                    "extrapolated_seconds": _stats([r["extrapolated_seconds"] for r in sel]),
                    "iterations": _stats([r["iterations"] for r in sel]),
                    "extrapolated_iterations": _stats([r["extrapolated_iterations"] for r in sel]),
                    "seconds_per_iteration": _stats([r["seconds_per_iteration"] for r in sel]),
                    "p_error_s": _stats([r["p_error_s"] for r in sel]),
                    "accepted": sum(bool(r["accepted"]) for r in sel),
                    "capped": sum(not r["converged"] for r in sel) if method == "faithful" else 0,
                })

    lam_rows = run_sweep(lambda_trial, [{"lam_s": lam, "units": 12, "room": "large", "setup_seed": seed,
                                         "max_iter": lambda_max_iter} for lam in LAMBDAS],
                         runs=1, seed=seed + 3, desc="Fig 4.5", **sweep)
    plot_lambda(lam_rows, out / "fig4_5_lambda.png")
    lam_summary = [{k: r[k] for k in ("lam_s", "iterations", "converged", "lam_switch_iteration",
                                      "frobenius_s2", "p_error_s", "seconds")} for r in lam_rows]

    noise_summary: list[dict[str, Any]] = []
    if noise_runs > 0:
        n_rows = run_sweep(noise_trial, [{"room": r, "units": 20, "sigma": s} for r in rooms for s in (10e-6, 50e-6)],
                           runs=noise_runs, seed=seed + 4, desc="noise + NLS", **sweep)
        write_rows(n_rows, out / "noise_rows.csv")
        for room in rooms:
            for s in (10e-6, 50e-6):
                sel = [r for r in n_rows if r["room"] == room and r["sigma"] == s]
                mse = float(np.mean([r["offset_mse_nls_s2"] for r in sel]))
                crlb = float(np.mean([r["offset_crlb_s2"] for r in sel]))
                pmse = float(np.mean([r["position_mse_m2"] for r in sel]))
                pcrlb = float(np.mean([r["position_crlb_m2"] for r in sel]))
                noise_summary.append({
                    "room": room, "units": 20, "sigma": s, "runs": len(sel),
                    "offset_rmse_nls_s": np.sqrt(mse),
                    "offset_rmse_rank3_s": float(np.sqrt(np.mean([r["offset_mse_rank3_s2"] for r in sel]))),
                    "offset_crlb_s": np.sqrt(crlb),
                    "offset_efficiency": float(np.sqrt(mse / crlb)),
                    "position_rmse_m": np.sqrt(pmse), "position_crlb_m": np.sqrt(pcrlb),
                    "position_efficiency": float(np.sqrt(pmse / pcrlb)),
                    "nls_converged": sum(bool(r["nls_converged"]) for r in sel),
                })
        plot_noise(noise_summary, out / "noise_efficiency.png")

    summary = {
        "paper": PAPER,
        "settings": {"runs": runs, "faithful_runs": faithful_runs, "max_iter": max_iter,
                     "timing_runs": list(timing_runs), "faithful_timing_runs": list(faithful_timing_runs),
                     "cap_120": cap_120, "lambda_max_iter": lambda_max_iter, "noise_runs": noise_runs,
                     "units": list(units), "full": full, "seed": seed, "speed": C,
                     "accept_s2": ACCEPT_S2, "backend": backend},
        "accuracy": acc,
        "timing": timing,
        "lambda": lam_summary,
        "noise": noise_summary,
        "wall_seconds": time.perf_counter() - t0,
    }
    write_json(out / "delays.json", summary)
    return summary
