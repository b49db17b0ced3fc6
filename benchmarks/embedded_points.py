"""Why the offsets candidates' refinements crawl: embedded point iterations, measured (not in the library).

``solve_toa(offsets="auto")`` runs on the shuffled UWB matrices of
``benchmarks/bench_uwb_known.py``; the inputs its cross-validation receives (kept entries,
every candidate's fit) are captured, and then

1. each candidate is refitted on all kept entries from its fit, the engine's
   Levenberg-Marquardt with the cap raised (``--cap``, default 2000) so that the stopping
   rule decides: plain, and with ``k`` *embedded point iterations* after every accepted step
   (each eliminated node, a tag position with its offset where the model has one, re-solved
   with the kept side fixed: ``k`` Gauss-Newton steps per node, a node's step halved up to 8
   times until its own cost does not rise; Jeong, Nister, Steedly, Szeliski & Kweon,
   "Pushing the envelope of modern methods for bundle adjustment", PAMI 2012, sec. 5);
2. ``cross_validate`` is run plain and with ``k`` embedded iterations (the library's capped,
   warm-started fold refits otherwise unchanged).

Prints iterations, CPU, final cost and anchor RMSE per candidate, and the CV choice,
scores and CPU. The embedded step is patched in here (a copy of the driver's loop that
calls it after each accepted step); nothing of it is in ``selfcal``.

Measured (2026-12-03, branch ``autoconv``, loaded 2-core machine, ``--cases
data4-shuffled,data5-shuffled,flight-shuffled``, cap 2000), full-data refits from the
candidates, iterations (CPU s) for k = 0 (the library's loop) / 1 / 2:

- data4: "none" 33 / 20 / 20; "receivers" 307 (0.43) / 121 (0.17) / 57 (0.10), cost 11.6414
  vs 11.6442 (a neighbouring minimum), anchor RMSE 0.443 / 0.441 / 0.440 m; "sources" 1865
  (1.67) / 24 (0.05) / 21 (0.06), cost 8.376 -> 8.348 (lower); "both" 355 / 146 / 57, anchor
  RMSE 4.41 / 117 / 4.43 m (k = 1: per-node steps of a source and its offset run along the
  far-field valley);
- data5: "receivers" 45 / 24 / 15 (same cost); "sources" 403 (0.48) / 32 / 26; "both" 146
  (0.18) / 970 (2.28) / 789 (2.38), to a lower cost 10.01 -> 8.19;
- flight: "none" 124 / 35 / 28; "receivers" 50 / 12 / 11 (same cost).

Cross-validation (same choice, "receivers", in every row), CPU s and "receivers" / "both"
held-out RMS (m): data4 from the candidates 3.78 (0.1868 / 0.2499), k = 1 3.38 (0.1672 /
0.2578), k = 2 4.26 (0.1645 / 0.2441); from the converged refits k = 0 2.38 (0.1637 /
0.2301), k = 2 1.34 (0.1641 / 0.2297); data5 from the candidates 3.07 / 3.18 / 4.32 s, from
the converged refits 2.32 (k = 0) / 3.46 s (k = 2; "both" 0.2597 -> 0.4289 m); flight 1.70
/ 1.76 / 2.48 s (its "sources" / "both" full refits fail: a column with 3 ranges). For
comparison, scipy's ``least_squares`` (trf, ``x_scale="jac"``) from the data4 "receivers"
start: 113-131 evaluations to the same minimum; geodesic acceleration (Transtrum & Sethna
2012) in a dense copy of the loop: 313 iterations (no gain). See docs/design.md ("Why the
candidates' refinements crawl").

Run: ``OPENBLAS_NUM_THREADS=1 PYTHONPATH=src python benchmarks/embedded_points.py
--cases data4-shuffled --inner 0,1,2``.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
import warnings
from typing import Any

import numpy as np


def embedded(model: Any, theta: np.ndarray, cost: float, state: Any, k: int) -> tuple[np.ndarray, float, Any]:
    """``k`` Gauss-Newton steps per eliminated node of ``model`` (a RangeModel), kept side fixed."""
    from selfcal.robust import loss_rho
    from selfcal.toa.engine.schur_lm import diagonal_blocks

    pat, d = model.pat, model.d

    def pair_cost(f: np.ndarray) -> np.ndarray:
        if model.linear:
            c = 0.5 * f * f
        else:
            c = 0.5 * model.f_scale**2 * np.asarray(loss_rho((f / model.f_scale) ** 2, model.loss)[0], float)
        return c if model.obs is None else np.where(model.obs, c, 0.0)

    for _ in range(k):
        f, w, U = state
        _, D = diagonal_blocks(U, w, model.hasK, model.hasE, pat)
        wf = w * f
        gE = np.empty((pat.nE, d + model.hasE))
        for p in range(d):
            gE[:, p] = -pat.esum(wf, U[p])
        if model.hasE:
            gE[:, d] = pat.esum(wf)
        with np.errstate(all="ignore"):
            y = -np.linalg.solve(D + 1e-9 * np.eye(D.shape[1]), gE[:, :, None])[:, :, 0]
        ok = np.isfinite(y).all(axis=1)
        y[~ok] = 0.0
        c0 = pat.esum(pair_cost(f))
        best, todo, t = np.zeros_like(y), ok.copy(), 1.0
        for _h in range(8):
            if not todo.any():
                break
            trial = theta.copy()
            trial[model.e_idx] += np.where(todo[:, None], t * y, best)
            c2 = pat.esum(pair_cost(model.evaluate(trial)[1][0]))
            good = todo & (c2 <= c0)
            best[good] = t * y[good]
            todo &= ~good
            t *= 0.5
        new = theta.copy()
        new[model.e_idx] += best
        c, st = model.evaluate(new)
        if not c <= cost:
            break
        theta, cost, state = new, c, st
    return theta, cost, state


def patched_driver(k: int, log: dict[str, Any]) -> Any:
    """The driver's loop (selfcal.optim.lm.levenberg_marquardt, adaptive damping) with the
    embedded iterations after each accepted, unconverged step."""
    from selfcal.optim.lm import TRIALS, LeastSquaresResult, damping_after_success

    def lm(model: Any, x0: np.ndarray, *, max_iter: int = 100, xtol: float = 1e-12, ftol: float = 1e-8,
           **_: Any) -> Any:
        x = np.array(x0, float)
        cost, state = model.evaluate(x)
        lam, nu, it, converged = 1e-4, 2.0, 0, False
        while it < max_iter:
            it += 1
            lin = model.linearize(x, state)
            improved = False
            for _ in range(TRIALS):
                dx = lin.step(lam)
                if dx is None:
                    lam, nu = lam * nu, 2 * nu
                    continue
                trial = model.retract(x, dx)
                c2, s2 = model.evaluate(trial)
                if c2 <= cost:
                    rel = (cost - c2) <= ftol * max(cost, 1e-300)
                    lam, nu = damping_after_success(lam, cost - c2, lin.predicted(dx)), 2.0
                    small = model.small_step(x, dx, xtol)
                    x, cost, state, improved = trial, c2, s2, True
                    converged = bool(small or rel or c2 == 0.0)
                    break
                lam, nu = lam * nu, 2 * nu
            if not improved:
                converged = model.stationary(lin, cost)
                break
            if converged:
                break
            if k and model.fidx is None:
                x, cost, state = embedded(model, x, cost, state, k)
        log["it"], log["converged"] = it, converged
        return LeastSquaresResult(x, cost, converged, it, state, True)

    return lm


def main() -> None:
    sys.path.insert(0, os.path.dirname(__file__))
    from bench_uwb_known import cases

    import selfcal.toa.engine.schur_lm as sl
    from selfcal.metrics import aligned_rmse
    from selfcal.toa import solve_toa
    from selfcal.toa.engine.nls import refine_toa
    from selfcal.toa.verdict import crossval as cv

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", default="room-shuffled,flight-shuffled,data4-shuffled,data5-shuffled")
    ap.add_argument("--data", default=os.path.join(os.path.dirname(__file__), "..", "..", "shared", "data", "lps"))
    ap.add_argument("--inner", default="0,1,2", help="embedded Gauss-Newton steps per node (0: the library's loop)")
    ap.add_argument("--cap", type=int, default=2000)
    a = ap.parse_args()
    ks = [int(v) for v in a.inner.split(",")]
    orig_cv, orig_lm = cv.cross_validate, sl.levenberg_marquardt
    seen: dict[str, Any] = {}

    def spy(Z: np.ndarray, starts: dict[str, Any], **kw: Any) -> Any:
        seen["x"] = (Z, starts)
        return orig_cv(Z, starts, **kw)

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for name, (Y, A) in cases(a.cases.split(","), a.data).items():
            cv.cross_validate = spy
            try:
                solve_toa(Y, offsets="auto", rng=0)
            finally:
                cv.cross_validate = orig_cv
            Z, starts = seen["x"]
            conv: dict[int, dict[str, Any]] = {}
            for m, (R, S, dr, o) in starts.items():
                kw: dict[str, Any] = dict(cv._REFIT[m])
                if dr is not None:
                    kw["receiver_offsets0"] = dr
                if o is not None:
                    kw["source_offsets0"] = o
                for k in ks:
                    log: dict[str, Any] = {}
                    sl.levenberg_marquardt = patched_driver(k, log)  # k = 0: the library's loop
                    t0 = time.process_time()
                    try:
                        sol = refine_toa(Z, R, S, covariance=False, max_nfev=a.cap, **kw)
                        conv.setdefault(k, {})[m] = (sol.receivers, sol.sources, sol.receiver_offsets,
                                                     sol.source_offsets)
                        it = log.get("it", "-")
                        print(f"{name:15s} {m:9s} inner {k}: iterations {it}, CPU {time.process_time() - t0:.2f} s, "
                              f"cost {0.5 * np.nansum(sol.residuals ** 2):.5f}, anchor RMSE "
                              f"{float(aligned_rmse(sol.receivers, A).rmse_receivers):.4f} m", flush=True)
                    except Exception as exc:  # noqa: BLE001 -- a failed refit is a row of the table
                        print(f"{name:15s} {m:9s} inner {k}: failed ({exc})")
                    finally:
                        sl.levenberg_marquardt = orig_lm
            for k in ks:
                for label, st in (("from the candidates", starts), ("from the converged refits", conv.get(k))):
                    if st is None or len(st) != len(starts):
                        continue
                    sl.levenberg_marquardt = patched_driver(k, {}) if k else orig_lm
                    t0 = time.process_time()
                    try:
                        c = orig_cv(Z, st)
                    finally:
                        sl.levenberg_marquardt = orig_lm
                    rms = ", ".join(f"{m} {np.sqrt(v):.4f}" for m, v in c.scores.items())
                    print(f"{name:15s} CV inner {k} {label}: {c.chosen}, CPU {time.process_time() - t0:.2f} s "
                          f"(+ the refits above), RMS {rms}", flush=True)


if __name__ == "__main__":
    main()
