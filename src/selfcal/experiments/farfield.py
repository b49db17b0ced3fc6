"""Reproductions of paper 000's experiments (far-field TDOA), Fig. 1-4.

Every trial is a module-level function ``trial(params, seed) -> dict`` run through
:func:`selfcal.experiments.runner.run_sweep`; each trial handles a small batch of random
problems so that the per-task overhead stays small.

* Fig. 1 -- minimal solver (Algorithm 1) on true 3-D distances: receivers at the corners of
  a unit tetrahedron, 6 senders on a sphere of radius R around it; failure = B not positive
  definite, error = mean receiver position error after rigid alignment (+ reflection).
  Plus the exact far-field test (paper: mean error 6.8e-15 over 10,000 tests).
* Fig. 2 -- overdetermined initialisation (section 2.3) for several rx-sy sizes: the first 4
  receivers are the tetrahedron, the rest uniform in the unit cube.
* Fig. 3 -- alternating (Algorithm 2) vs Levenberg-Marquardt (Algorithm 3), m = k = 10,
  far-field data with Gaussian noise sigma = 0.1, both from the same initialisation.
* Fig. 4 -- m = 5, k = 10, R = 1e7 and 1e2, error vs noise of the initialisation and of LM,
  with the initialisation's failure rate.

Fig. 3-4 also report the maximum-likelihood refinement (LM with the offsets C_j free, the
cost whose residual is D_ij - z_i . n_j - C_j) and the Cramer-Rao bound of the aligned RMS
position error (:func:`selfcal.tdoa.refine.farfield_crlb`). Why LM does not lower the
position error in these figures (issue 4) is recorded in :data:`FINDING`: no defect of the
solver, but a near-efficient initialisation at low noise and an outward (scale) bias of the
ML estimate at sigma = 0.1 with only m = 10 entries per column.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..io import write_json
from ..metrics import aligned_direction_errors, aligned_rmse
from ..tdoa.initialize import initialize_farfield
from ..tdoa.minimal import quadric_design, solve_minimal
from ..tdoa.refine import farfield_crlb, refine_alternating, refine_lm
from .runner import run_sweep, write_rows

__all__ = [
    "FINDING",
    "TETRA",
    "PAPER",
    "fig1_trial",
    "fig2_trial",
    "fig3_trial",
    "fig4_trial",
    "reproduce_all",
]

Array = NDArray[np.float64]
TETRA = np.array([[0, 0, 0], [1, 0, 0], [0.5, np.sqrt(3) / 2, 0], [0.5, np.sqrt(3) / 6, np.sqrt(2 / 3)]])

#: the paper's reported numbers (where the text states them)
PAPER = {
    "fig1_exact_mean_error": 6.8e-15,
    "fig1_exact_tests": 10000,
    "fig3_lm_iterations": 20,
    "fig3_alternating_iterations": 150,
    "fig1_failure": "infrequent even at small relative distances",
    "fig2_failure": "drops, in many cases to zero; errors up to one order of magnitude below the minimal case",
}


#: audit of issue 4 (why LM does not lower the position error in Fig. 3-4); the numbers are
#: in the module docstring and in ``fig3`` / ``fig4`` of the JSON written by reproduce_all
FINDING = (
    "LM is not broken: from the same start it reaches the same cost as "
    "scipy.optimize.least_squares (to 1e-6 relative) and never a higher one than the "
    "initialisation. Two effects explain why it does not lower the position error: (1) at low "
    "noise the linear initialisation (rank-3 SVD + quadric) is already near efficient (its "
    "aligned MSE is 1.0-1.4x the far-field CRLB, the ML's ~1.0x), so there is little to gain; "
    "(2) at sigma = 0.1 with m = k = 10 the noise is a third of the array size and the ML "
    "estimate is biased outwards (median array scale 1.17-1.21x the truth, initialisation 1.13x): "
    "each column has 3 nuisance unknowns (n_j, C_j) fitted from only m = 10 entries, so a larger "
    "array fits more of the noise (Neyman-Scott type bias, vanishing with more columns: 1.04x "
    "at k = 40, 1.02x at k = 160 where ML beats the initialisation), and in about a quarter of "
    "the draws with a positive definite B the ML estimate collapses towards the "
    "coplanar-directions failure mode (smallest/largest singular value of N 0.006-0.16, array "
    "stretched to |z| up to 60): LM started at the TRUE geometry slides to the same or a "
    "higher-cost solution, so this tail is in the likelihood, not the solver. The paper's reduced cost "
    "(C_j pinned to D_1j, as in Algorithm 3) is not the ML cost either: row 1's noise enters "
    "every row. Fig. 3-4 therefore also report the ML refinement (C_j free) and the CRLB."
)


def _unit(v: Array) -> Array:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _pos_error(est: Array, true: Array) -> float:
    """Mean receiver position error after the best rigid motion with reflection."""
    return float(np.mean(aligned_rmse(est, true).receiver_errors)) if np.isfinite(est).all() else float("nan")


def _pos_rms(est: Array, true: Array) -> float:
    """Root mean squared receiver position error after rigid alignment (with reflection)."""
    return aligned_rmse(est, true).rmse_receivers if np.isfinite(est).all() else float("nan")


def _scale_ratio(est: Array, true: Array) -> float:
    """Size of the centred estimated array over that of the truth (1 = no scale bias)."""
    e, t = est - est.mean(axis=0), true - true.mean(axis=0)
    return float(np.linalg.norm(e) / np.linalg.norm(t))


def _crlb_rms(Z: Array, N: Array, sigma: float) -> float:
    """CRLB of the aligned RMS position error (free offsets), see :func:`farfield_crlb`."""
    if sigma <= 0:
        return 0.0
    cov = farfield_crlb(Z, N, sigma, free_offsets=True)
    return float(np.sqrt(np.trace(cov, axis1=1, axis2=2).mean()))


def _senders(rng: np.random.Generator, n: int, radius: float, centre: Array) -> Array:
    return centre + radius * _unit(rng.normal(size=(n, 3)))


def _tdoa(receivers: Array, senders: Array) -> Array:
    """True 3-D relative distances |s_j - r_i| (receivers = rows)."""
    return np.asarray(np.linalg.norm(senders[None, :, :] - receivers[:, None, :], axis=2))


# ----------------------------------------------------------------------------- Fig. 1
def fig1_trial(params: dict[str, Any], seed: int) -> dict[str, Any]:
    """A batch of minimal problems at one relative distance (or exact far field)."""
    rng = np.random.default_rng(seed)
    batch = int(params.get("batch", 250))
    centre = TETRA.mean(axis=0)
    culled = 0
    if params["model"] == "far-field":
        N = _unit(rng.normal(size=(batch, 6, 3)))
        D = TETRA @ np.swapaxes(N, -1, -2) + rng.normal(size=(batch, 1, 6))
        # the paper culls degenerate draws (directions near a conic); we cull when the
        # quadric system is conditioned worse than 1e4
        mu = np.linalg.svd(quadric_design(N), compute_uv=False)
        keep = mu[:, -1] / mu[:, 0] > 1e-4
        culled = int((~keep).sum())
        D = D[keep]
    else:
        R = float(params["distance"])
        S = np.stack([_senders(rng, 6, R, centre) for _ in range(batch)])
        D = np.linalg.norm(S[:, None, :, :] - TETRA[None, :, None, :], axis=3)
    sol = solve_minimal(D)
    errs = np.array([_pos_error(sol.positions[b], TETRA) for b in np.flatnonzero(sol.valid)])
    return {
        "n": int(len(D)),
        "culled": culled,
        "failures": int((~sol.valid).sum()),
        "error_sum": float(errs.sum()) if errs.size else 0.0,
        "error_max": float(errs.max()) if errs.size else float("nan"),
    }


# ----------------------------------------------------------------------------- Fig. 2
def fig2_trial(params: dict[str, Any], seed: int) -> dict[str, Any]:
    """A batch of overdetermined initialisations (section 2.3) for one size and distance."""
    rng = np.random.default_rng(seed)
    m, k, R = int(params["m"]), int(params["k"]), float(params["distance"])
    batch = int(params.get("batch", 25))
    fails, errs = 0, []
    for _ in range(batch):
        rec = np.vstack([TETRA, rng.uniform(0, 1, (m - 4, 3))])
        D = _tdoa(rec, _senders(rng, k, R, TETRA.mean(axis=0)))
        X = np.vstack([np.zeros((1, k)), D[1:] - D[0]])  # the paper's reduction (Algorithm 1)
        init = initialize_farfield(X)
        if not init.b_positive_definite:
            fails += 1
            continue
        errs.append(_pos_error(init.positions, rec))
    return {"n": batch, "failures": fails, "error_sum": float(np.sum(errs)), "n_ok": len(errs)}


# ----------------------------------------------------------------------------- Fig. 3
def _curve(hist: list[Array], truth: Array, length: int) -> list[float]:
    e = [_pos_error(Z, truth) for Z in hist]
    return (e + [e[-1]] * length)[:length]


def _iters_to(history: list[float], target: float, rel: float = 1e-6) -> int:
    """First iteration whose cost is within ``rel`` of ``target``."""
    h = np.asarray(history)
    hit = np.flatnonzero(h <= target * (1.0 + rel))
    return int(hit[0]) if hit.size else len(h)


def _iters_settled(curve: list[float], rel: float = 0.01) -> int:
    """First iteration after which the position error stays within ``rel`` of its final value."""
    e = np.asarray(curve)
    off = np.abs(e - e[-1]) > rel * abs(e[-1])
    idx = np.flatnonzero(off)
    return int(idx[-1] + 1) if idx.size else 0


def fig3_trial(params: dict[str, Any], seed: int) -> dict[str, Any]:
    """One noisy far-field problem: error per iteration of LM and alternating from one init."""
    rng = np.random.default_rng(seed)
    m, k, sigma = int(params["m"]), int(params["k"]), float(params["sigma"])
    length = int(params.get("length", 300))
    Z = rng.uniform(0, 1, (m, 3))
    Z -= Z[0]
    N = _unit(rng.normal(size=(k, 3)))
    D = Z @ N.T + sigma * rng.normal(size=(m, k))
    X = np.vstack([np.zeros((1, k)), D[1:] - D[0]])
    init = initialize_farfield(X)
    C = D[0].copy()  # the paper's reduced cost: C_j = D_1j
    lm = refine_lm(D, init.positions, init.directions, C, lam=1.0, adaptive=False,
                   max_iter=length, tol=1e-15, record_positions=True)
    lm_a = refine_lm(D, init.positions, init.directions, C, max_iter=length, tol=1e-15, record_positions=True)
    alt = refine_alternating(D, init.positions, init.directions, C, max_iter=4 * length, tol=1e-15,
                             record_positions=True)
    # the maximum-likelihood cost (C_j free, eq. 1 with offsets) from the same start
    ml = refine_lm(D, init.positions, init.directions, C, free_offsets=True, max_iter=length)
    best = min(lm.cost, lm_a.cost, alt.cost)
    curves = {name: _curve(o.position_history, Z, length if name == "lm" else 4 * length)
              for name, o in (("lm", lm), ("alt", alt))}
    return {
        "lm_settled": _iters_settled(curves["lm"]),
        "alt_settled": _iters_settled(curves["alt"]),
        "init_pd": bool(init.b_positive_definite),
        "lm_iters": _iters_to(lm.history, best),
        "lm_adaptive_iters": _iters_to(lm_a.history, best),
        "alt_iters": _iters_to(alt.history, best),
        "lm_curve": _curve(lm.position_history, Z, length),
        "lm_adaptive_curve": _curve(lm_a.position_history, Z, length),
        "alt_curve": _curve(alt.position_history, Z, length),
        "init_error": _pos_error(init.positions, Z),
        "ml_error": _pos_error(ml.positions, Z),
        "init_rms": _pos_rms(init.positions, Z),
        "lm_rms": _pos_rms(lm.positions, Z),
        "ml_rms": _pos_rms(ml.positions, Z),
        "crlb_rms": _crlb_rms(Z, N, sigma),
        "init_scale": _scale_ratio(init.positions, Z),
        "ml_scale": _scale_ratio(ml.positions, Z),
    }


# ----------------------------------------------------------------------------- Fig. 4
def fig4_trial(params: dict[str, Any], seed: int) -> dict[str, Any]:
    """A batch of m = 5, k = 10 problems with true 3-D distances plus Gaussian noise."""
    rng = np.random.default_rng(seed)
    R, sigma = float(params["distance"]), float(params["sigma"])
    m, k, batch = int(params.get("m", 5)), int(params.get("k", 10)), int(params.get("batch", 10))
    fails, e_init, e_lm, e_ml, r_init, r_lm, r_ml, r_crlb, d_ml = 0, [], [], [], [], [], [], [], []
    for _ in range(batch):
        rec = np.vstack([TETRA, rng.uniform(0, 1, (m - 4, 3))])
        S = _senders(rng, k, R, TETRA.mean(axis=0))
        D = _tdoa(rec, S) + sigma * rng.normal(size=(m, k))
        X = np.vstack([np.zeros((1, k)), D[1:] - D[0]])
        init = initialize_farfield(X)
        fails += int(not init.b_positive_definite)
        e_init.append(_pos_error(init.positions, rec))
        out = refine_lm(D, init.positions, init.directions, D[0].copy(), max_iter=200)
        e_lm.append(_pos_error(out.positions, rec))
        ml = refine_lm(D, init.positions, init.directions, D[0].copy(), free_offsets=True, max_iter=200)
        e_ml.append(_pos_error(ml.positions, rec))
        r_init.append(_pos_rms(init.positions, rec))
        r_lm.append(_pos_rms(out.positions, rec))
        r_ml.append(_pos_rms(ml.positions, rec))
        # far-field direction of sender j seen from the array: D_ij ~ const - z_i . u_j
        n_true = -_unit(S - TETRA.mean(axis=0))
        r_crlb.append(_crlb_rms(rec, n_true, sigma))
        d_ml.append(float(np.degrees(np.median(aligned_direction_errors(ml.positions, ml.directions, rec, n_true)))))
    return {"ml_direction_error_deg": d_ml, "n": batch, "failures": fails, "init_error_sum": float(np.sum(e_init)),
            "lm_error_sum": float(np.sum(e_lm)), "init_errors": e_init, "lm_errors": e_lm,
            "ml_errors": e_ml, "init_rms": r_init, "lm_rms": r_lm, "ml_rms": r_ml, "crlb_rms": r_crlb}


# ----------------------------------------------------------------------------- driver
def _rms_over(rows: list[dict[str, Any]], key: str, flat: bool = False) -> float:
    """sqrt(mean of squared per-draw RMS errors): comparable with the CRLB's trace."""
    v = np.array([e for x in rows for e in x[key]] if flat else [x[key] for x in rows], dtype=float)
    return float(np.sqrt(np.nanmean(v**2)))


def _group(rows: list[dict[str, Any]], keys: tuple[str, ...]) -> dict[tuple[Any, ...], list[dict[str, Any]]]:
    out: dict[tuple[Any, ...], list[dict[str, Any]]] = {}
    for r in rows:
        out.setdefault(tuple(r[k] for k in keys), []).append(r)
    return out


def reproduce_all(
    out: Path,
    *,
    runs: int | None = None,
    full: bool = False,
    backend: str = "processes",
    scheduler: str | None = None,
    seed: int = 0,
) -> dict[str, Any]:
    """Run Fig. 1-4, write ``out/fig1..fig4.png``, per-trial CSVs and ``out/farfield.json``.

    Parameters
    ----------
    out : output folder. runs : trials per setting (default 4, or 40 with ``full``; each
        trial is a batch). full : paper-sized runs. backend, scheduler, seed : see
        :func:`run_sweep`.

    Returns
    -------
    The summary dict written to ``farfield.json`` (with a ``report`` list of text lines).
    """
    from ..plotting.farfield import (
        plot_convergence,
        plot_initialisation,
        plot_minimal_solver,
        plot_noise,
    )

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    r = runs if runs is not None else (40 if full else 4)
    sweep: dict[str, Any] = {"backend": backend, "scheduler": scheduler, "seed": seed}
    summary: dict[str, Any] = {"paper": PAPER, "runs": r, "full": full}
    report: list[str] = []

    # ---- Fig. 1
    dists = [1.0, 2.0, 5.0, 10.0, 1e2, 1e3, 1e4, 1e5, 1e6, 1e7]
    batch1 = 250
    grid1 = [{"model": "3d", "distance": d, "batch": batch1} for d in dists]
    grid1.append({"model": "far-field", "distance": 0.0, "batch": batch1})  # 0: no distance
    rows1 = run_sweep(fig1_trial, grid1, runs=r, desc="fig1 minimal", **sweep)
    write_rows(rows1, out / "fig1_trials.csv")
    fig1 = []
    for (model, d), rs in _group(rows1, ("model", "distance")).items():
        n = sum(x["n"] for x in rs)
        f = sum(x["failures"] for x in rs)
        ok = n - f
        fig1.append({"model": model, "distance": None if model == "far-field" else d, "tests": n,
                     "culled": sum(x["culled"] for x in rs), "failure_rate": f / max(n, 1),
                     "mean_error": sum(x["error_sum"] for x in rs) / max(ok, 1)})
    summary["fig1"] = fig1
    exact = next(x for x in fig1 if x["model"] == "far-field")
    report.append(f"Fig.1 exact far-field minimal solver: mean position error {exact['mean_error']:.2g} over "
                  f"{exact['tests']} tests (paper: 6.8e-15 over 10,000)")
    for x in fig1[:-1]:
        report.append(f"  R={x['distance']:<8g} failure rate {x['failure_rate']:.3f}  mean error {x['mean_error']:.3g}")
    plot_minimal_solver(fig1, out / "fig1.png")

    # ---- Fig. 2
    sizes = [(4, 6), (4, 8), (5, 8), (6, 10), (8, 16), (10, 20)]
    dists2 = [1.0, 2.0, 5.0, 10.0, 1e2, 1e3, 1e4, 1e5, 1e6, 1e7]
    grid2 = [{"m": m, "k": k, "distance": d, "batch": 25} for (m, k) in sizes for d in dists2]
    rows2 = run_sweep(fig2_trial, grid2, runs=r, desc="fig2 init", **sweep)
    write_rows(rows2, out / "fig2_trials.csv")
    fig2 = []
    for (m, k, d), rs in _group(rows2, ("m", "k", "distance")).items():
        n = sum(x["n"] for x in rs)
        ok = sum(x["n_ok"] for x in rs)
        fig2.append({"size": f"r{m}-s{k}", "distance": d, "tests": n, "failure_rate": 1 - ok / max(n, 1),
                     "mean_error": sum(x["error_sum"] for x in rs) / max(ok, 1)})
    summary["fig2"] = fig2
    plot_initialisation(fig2, out / "fig2.png")
    for size in ("r4-s6", "r10-s20"):
        x = next(v for v in fig2 if v["size"] == size and v["distance"] == 1e2)
        report.append(f"Fig.2 {size} at R=100: failure rate {x['failure_rate']:.3f}, mean error {x['mean_error']:.3g}")

    # ---- Fig. 3
    length = 300
    grid3 = [{"m": 10, "k": 10, "sigma": 0.1, "length": length}]
    rows3 = run_sweep(fig3_trial, grid3, runs=max(r * 5, 10), desc="fig3 convergence", **sweep)
    # medians: a few draws whose B is not positive definite start far away and would
    # dominate a mean
    lm_curve = np.nanmedian([x["lm_curve"] for x in rows3], axis=0)
    lma_curve = np.nanmedian([x["lm_adaptive_curve"] for x in rows3], axis=0)
    alt_curve = np.nanmedian([x["alt_curve"] for x in rows3], axis=0)
    fig3 = {
        "trials": len(rows3),
        "lm_iterations_median": float(np.median([x["lm_iters"] for x in rows3])),
        "lm_error_settled_median": float(np.median([x["lm_settled"] for x in rows3])),
        "alternating_error_settled_median": float(np.median([x["alt_settled"] for x in rows3])),
        "init_error_median": float(np.nanmedian([x["init_error"] for x in rows3])),
        "lm_final_error_median": float(np.nanmedian([x["lm_curve"][-1] for x in rows3])),
        "alternating_final_error_median": float(np.nanmedian([x["alt_curve"][-1] for x in rows3])),
        "lm_adaptive_iterations_median": float(np.median([x["lm_adaptive_iters"] for x in rows3])),
        "alternating_iterations_median": float(np.median([x["alt_iters"] for x in rows3])),
        "init_error_mean": float(np.nanmean([x["init_error"] for x in rows3])),
        "lm_final_error_mean": float(np.nanmean([x["lm_curve"][-1] for x in rows3])),
        "alternating_final_error_mean": float(np.nanmean([x["alt_curve"][-1] for x in rows3])),
        "ml_final_error_median": float(np.nanmedian([x["ml_error"] for x in rows3])),
        "ml_final_error_mean": float(np.nanmean([x["ml_error"] for x in rows3])),
        # root of the mean squared aligned error over draws, beside its Cramer-Rao bound
        "rmse": {name: _rms_over(rows3, key) for name, key in
                 (("init", "init_rms"), ("lm_paper_cost", "lm_rms"), ("ml", "ml_rms"),
                  ("crlb", "crlb_rms"))},
        "scale_ratio_median": {"init": float(np.nanmedian([x["init_scale"] for x in rows3])),
                               "ml": float(np.nanmedian([x["ml_scale"] for x in rows3]))},
        "lm_curve": lm_curve[:60].tolist(),
        "alternating_curve": alt_curve[:300].tolist(),
    }
    summary["fig3"] = fig3
    report.append(f"Fig.3 m=k=10, sigma=0.1: iterations to converge (median) LM lambda=1 "
                  f"{fig3['lm_iterations_median']:.0f}, adaptive LM {fig3['lm_adaptive_iterations_median']:.0f}, "
                  f"alternating {fig3['alternating_iterations_median']:.0f}; error settled (1%) after LM "
                  f"{fig3['lm_error_settled_median']:.0f} / alternating "
                  f"{fig3['alternating_error_settled_median']:.0f} (paper: ~20 vs ~150); median error init "
                  f"{fig3['init_error_median']:.3f} -> LM {fig3['lm_final_error_median']:.3f}, alternating "
                  f"{fig3['alternating_final_error_median']:.3f}, ML (free C_j) "
                  f"{fig3['ml_final_error_median']:.3f}; RMSE init {fig3['rmse']['init']:.3g}, ML "
                  f"{fig3['rmse']['ml']:.3g}, CRLB {fig3['rmse']['crlb']:.3g}")
    plot_convergence({"alternating (Alg. 2)": alt_curve, "LM, lambda = 1 (Alg. 3)": lm_curve,
                      "LM, adaptive lambda": lma_curve}, out / "fig3.png")

    # ---- Fig. 4
    sigmas = [0.0, 1e-4, 1e-3, 3e-3, 1e-2, 3e-2, 1e-1]
    grid4 = [{"distance": d, "sigma": s, "batch": 10} for d in (1e7, 1e2) for s in sigmas]
    rows4 = run_sweep(fig4_trial, grid4, runs=r, desc="fig4 noise", **sweep)
    write_rows(rows4, out / "fig4_trials.csv")
    fig4 = []
    for (d, s), rs in _group(rows4, ("distance", "sigma")).items():
        n = sum(x["n"] for x in rs)
        fig4.append({"distance": d, "sigma": s, "tests": n,
                     "failure_rate": sum(x["failures"] for x in rs) / n,
                     "init_error": sum(x["init_error_sum"] for x in rs) / n,
                     "lm_error": sum(x["lm_error_sum"] for x in rs) / n,
                     "init_error_median": float(np.median([e for x in rs for e in x["init_errors"]])),
                     "lm_error_median": float(np.median([e for x in rs for e in x["lm_errors"]])),
                     "ml_error": float(np.mean([e for x in rs for e in x["ml_errors"]])),
                     "ml_error_median": float(np.median([e for x in rs for e in x["ml_errors"]])),
                     "ml_direction_error_deg_median": float(np.median(
                         [e for x in rs for e in x["ml_direction_error_deg"]])),
                     "rmse": {name: _rms_over(rs, key, flat=True) for name, key in
                              (("init", "init_rms"), ("lm_paper_cost", "lm_rms"), ("ml", "ml_rms"),
                               ("crlb", "crlb_rms"))}})
    summary["fig4"] = fig4
    plot_noise(fig4, out / "fig4.png")
    for d in (1e7, 1e2):
        x = next(v for v in fig4 if v["distance"] == d and v["sigma"] == 1e-2)
        report.append(f"Fig.4 R={d:g}, sigma=0.01: mean (median) error init {x['init_error']:.3g} "
                      f"({x['init_error_median']:.3g}), LM {x['lm_error']:.3g} ({x['lm_error_median']:.3g}), "
                      f"ML median {x['ml_error_median']:.3g}; RMSE init {x['rmse']['init']:.3g}, ML "
                      f"{x['rmse']['ml']:.3g}, CRLB {x['rmse']['crlb']:.3g}; "
                      f"init failure rate {x['failure_rate']:.2f}")

    summary["finding"] = FINDING
    summary["report"] = report
    write_json(out / "farfield.json", summary)
    return summary
