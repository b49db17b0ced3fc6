"""Benchmark "toa_varpro": the dense engine with and without variable projection of the offsets.

Same scenes as ``bench_toa_minimal.py`` (12 x 6, both offsets, 20 us). Two studies, both
engines in the same run:

- ``--per-start``: every start the search builds for a draw (the nested offsets-free fit and
  :data:`selfcal.toa.search.INITIALISERS`, canonical order) refined by
  :func:`selfcal.toa.engine.dense_lm.full_lm` and :func:`solve_varpro_lm` (below) to
  convergence or ``--cap`` iterations (least squares); per start: sum of squared residuals,
  converged, iterations, CPU, the largest source distance from the receivers' centroid;
  "best basin" = within 0.01 sigma^2 of the lowest sum over both engines;
- default: the blind ``solve_toa`` with its dense step (``selfcal.toa.search.solve_dense_lm``)
  joint / replaced by :func:`solve_varpro_lm`, scored as in
  ``bench_toa_minimal`` against one truth-started ``trf`` fit, plus the largest source
  distance and whether the solve raised.

Measured (2026-12-02, 2 loaded cores, slices of 25 / 10 draws; numbers below): blind seeds 0-199, 165 joint vs 176 VarPro in the basin
(McNemar p = 0.11), CPU median 0.94 vs 0.85 s, a source beyond 100 m in 3 vs 49 results, 3
VarPro solves raised; per start (seeds 0-39) converged 50 % vs 79 %, median 496 vs 160
iterations.

Variable projection of the offsets (:func:`solve_varpro_lm`): Levenberg-Marquardt on the
positions alone, a parametrisation of the same model and step.

The range model ``y_ij = |r_i - s_j| + d_i + o_j`` is linear in the offsets. For a given
geometry the offsets minimising the (weighted) cost are a small linear least-squares problem
over the observed entries, so they can be eliminated (Golub & Pereyra 1973): the reduced
residual is ``P (dist(x) - y)`` with ``P = I - A (A^T W A)^+ A^T W`` the weighted projector
off the offset design A (0/1 columns, one per offset of the model), and because A does not
depend on the positions, ``P J_x`` is the *exact* Jacobian of the reduced residual (Kaufman's
1975 approximation drops nothing here). Each iteration:

1. the normal matrix of the full problem ``J^T W J`` is formed as in
   :func:`selfcal.toa.engine.dense_lm.full_lm`; the offset block is eliminated (Schur
   complement), which is ``J_x^T W P J_x``, the reduced Gauss-Newton matrix;
2. the damped reduced system is solved for the position step, which is projected off the
   rigid gauge (:class:`selfcal.toa.engine.model.GaugeProjector`, positions only);
3. at the trial positions the offsets are *re-solved* (not moved by their linearised step):
   the cost compared is the variable-projection cost ``min_z cost(x, z)``.

With the least-squares loss the projector is fixed, so it is formed once (an (m, m) matrix)
and an iteration is two products with it plus the joint engine's step. Robust losses make
the offsets a nonlinear (IRLS) sub-problem; they run the joint engine. Measured before that
choice: with one IRLS step for the offsets per trial (weights of the trial positions, a
majorise-minimise step) the iteration reached a stationary point, but on one of 18 soft-L1
problems (12 x 8, both offsets, seed 3 of ``tests/toa/test_varpro.py``) it took 867
iterations against 57 for the joint engine, the lagging weights slowing the final rate.

The offset gauge (``d_i + c, o_j - c`` with both kinds) is the null vector v of ``A^T W A``;
it is handled analytically: ``A^T W A + alpha v v^T`` is positive definite on a connected
observation graph and equals the pseudo-inverse on right-hand sides orthogonal to v (all of
them here, ``v^T A^T = 0``), and the shift is set so that ``sum d - sum o`` keeps its
starting value, the convention of the dense engine (which projects the shift off each step).
Offsets "none" have nothing to project and run :func:`selfcal.toa.engine.dense_lm.full_lm`;
so do partial refits (a ``free`` mask), where the fixed nodes already hold the frame.

Measured (not kept in the library: the joint engine is its dense step). Same run, 12 x 6 with both offsets, the benchmark scene of ``benchmarks/bench_toa_minimal.py``
(2 shared cores, loaded; ``python benchmarks/bench_toa_varpro.py``):

- per start (the search's starts of seeds 0-39, 1090 starts, each run to convergence or 500
  iterations, least squares): converged 79 % vs 50 % for the joint engine, median 160 vs 496
  iterations, 0.50 vs 0.38 ms per iteration (an earlier Schur-complement form; the fixed
  projector form is on par: 0.42-0.56 vs 0.43-0.56 ms on the same draws), 124 vs 140 s CPU
  in all. The starts that reach the draw's lowest basin get there in a median 82 vs 125
  iterations. But 52 % of VarPro's starts end with a source beyond 100 m (34 % beyond 1 km)
  against 4.5 % for the joint engine (seeds 40-47): with the offsets eliminated, the
  far-field valley (a source receding along its direction while its offset absorbs the
  range) is followed to its end instead of crawled along, and its end has a lower cost.
  Geodesic acceleration (Transtrum & Sethna 2012) on top converged still more starts (89 %,
  median 112 iterations) at 0.62 ms per iteration, with the same far-field ends (43 %); not kept.
- blind ``solve_toa``, seeds 0-199: in the basin (cost at most the truth-started fit's + 0.01
  sigma^2) 165 joint vs 176 VarPro (25 gained, 14 lost, McNemar p = 0.11), CPU median 0.94
  vs 0.85 s; the same minimum as the truth-started fit 59 vs 61; a source beyond 100 m in
  3 vs 49 results (13 for the truth-started fit), and 3 VarPro solves (seeds 15, 19, 160)
  raised DegenerateGeometryError: the first round ended with every source about 3.9 km away
  and the outlier round's refit from there (1800 km) could not fix the gauge.
- the same with the race over the starts of the merged search (main at 655ad68), seeds 0-47:
  in the basin 44 joint vs 40 VarPro (4 gained, 8 lost, McNemar p = 0.39), CPU median 2.11 vs
  1.39 s (paired ratio 0.68), a source beyond 100 m in 2 vs 11 results (3 for the
  truth-started fit), one VarPro solve raised (seed 44).

References
----------
Golub, G. H. & Pereyra, V. (1973). The differentiation of pseudo-inverses and nonlinear least
squares problems whose variables separate. SIAM J. Numer. Anal. 10(2), 413-432.
Kaufman, L. (1975). A variable projection method for solving separable nonlinear least
squares problems. BIT 15, 49-57.
Hong, J. H., Zach, C. & Fitzgibbon, A. (2017). Revisiting the variable projection method for
separable nonlinear least squares problems. CVPR, 5939-5947.

Run: ``python benchmarks/bench_toa_varpro.py [--first 0] [--draws 10] [--per-start] [--cap 500] [--out DIR]``.
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import time
import warnings
from pathlib import Path
from typing import Any

import numpy as np
from bench_toa_minimal import NOISE, C, _rmse, scene
from numpy.typing import NDArray
from scipy.linalg import lapack

Array = NDArray[np.float64]


def solve_varpro_lm(
    theta0: Array, y: Array, ii: NDArray[np.intp], jj: NDArray[np.intp], I: int, J: int, d: int,
    offsets: str, loss: str, f_scale: float, max_nfev: int | None, xtol: float,
    free: NDArray[np.bool_] | None = None, max_it: int = 100,
) -> tuple[Array, bool, int]:
    """Levenberg-Marquardt on the positions with the offsets projected out (variable projection).

    Same call and return as :func:`selfcal.toa.engine.dense_lm.solve_dense_lm`.

    Parameters
    ----------
    theta0 : (n,) start, receiver-major ``[r (I d), s (J d), d_i (I)?, o_j (J)?]`` (metres);
        its offsets only set the offset gauge (``sum d - sum o``): the offsets are re-solved
        at the start's geometry.
    y : (m,) observed ranges (metres); ii, jj : (m,) their receiver and source indices.
    I, J, d, offsets : the model (:mod:`selfcal.toa.engine.nls`).
    loss, f_scale : loss and its scale; any loss but "linear" runs the joint engine.
    max_nfev : iteration cap (default ``max_it``); xtol : relative step tolerance.
    free : (n,) bool mask of fitted parameters; when given (a partial refit) or when the
        model has no offsets, the call is :func:`full_lm`'s.

    Returns
    -------
    (theta, converged, iterations): the point (offsets included, in the dense engine's
    gauge), whether a stopping rule was met, iterations (normal matrices formed).

    Notes
    -----
    Per iteration O(m^2 k + m k^2) for the reduced normal matrix ``(P J_x)^T (P J_x)``
    (k = (I + J) d positions, P the (m, m) projector formed once in O(m^2 p + p^3)) and
    O(k^3 / 3) per damping trial, which costs one product ``P (dist - y)``. The projector
    needs the offsets determined by the observation pattern (every node observed and, with
    both kinds, a connected bipartite graph); otherwise the joint engine runs.

    Examples
    --------
    >>> import numpy as np
    >>> from selfcal.toa.engine import nls
    >>> g = np.random.default_rng(0)
    >>> r, s = g.uniform(0, 1.5, (12, 3)), g.normal(0, 2, (6, 3))
    >>> Y = nls.toa_model(r, s, g.uniform(0, 3, 12), g.uniform(0, 30, 6))
    >>> ii, jj = np.nonzero(np.isfinite(Y))
    >>> th0 = nls._pack(r + 0.05, s - 0.05, np.zeros(12), np.zeros(6))
    >>> th, ok, nit = solve_varpro_lm(th0, Y[ii, jj], ii, jj, 12, 6, 3, "both", "linear", 1.0, None, 1e-12)
    >>> bool(ok) and float(np.abs(nls.toa_residuals(th, Y, 3, "both")).max()) < 1e-6
    True
    """
    import selfcal.toa.engine.dense_lm as DL
    from selfcal.optim.lm import levenberg_marquardt
    from selfcal.optim.steps import DenseStep
    from selfcal.toa.engine.dense_lm import full_lm
    from selfcal.toa.engine.model import _node_indices
    from selfcal.toa.engine.schur_lm import Pairs, RangeModel

    has_r, has_s = offsets in ("receivers", "both"), offsets in ("sources", "both")
    if not (has_r or has_s) or loss != "linear" or (free is not None and not bool(np.all(free))):
        return full_lm(theta0, y, ii, jj, I, J, d, offsets, loss, f_scale, max_nfev, xtol,
                       free=free, max_it=max_it)
    theta = np.array(theta0, dtype=float)
    k = (I + J) * d
    m = y.size
    # the offset design A (m, p) and the projector P = I - A (A^T A)^+ A^T off its columns
    cols = ([np.eye(I)[ii]] if has_r else []) + ([np.eye(J)[jj]] if has_s else [])
    A = np.hstack(cols)
    G = A.T @ A
    v = np.concatenate([np.ones(I), -np.ones(J)]) if has_r and has_s else None
    if v is not None:  # the offset gauge d + c, o - c: null vector of G, made positive definite
        G += (float(np.trace(G)) / G.shape[0] / v.size) * np.outer(v, v)
    fac, info = lapack.dpotrf(G, lower=1, clean=1)
    if info != 0:  # offsets not determined by the pattern: the joint engine
        return full_lm(theta0, y, ii, jj, I, J, d, offsets, loss, f_scale, max_nfev, xtol, max_it=max_it)
    AG, _ = lapack.dpotrs(fac, A.T, lower=1)  # (A^T A)^+ A^T on the gauge-free complement
    Pm = -A @ AG
    Pm.ravel()[:: m + 1] += 1.0
    shift0 = float(v @ theta[k:]) if v is not None else 0.0
    r_idx, s_idx, _ = _node_indices(I, J, d, "none")

    class Projected(RangeModel):
        """The positions' cost with the offsets projected out; a step moves the positions only
        (the range model without offsets, its residuals and Jacobian projected by ``Pm``)."""

        def evaluate(self, t: Array) -> tuple[float, tuple[Array, Array, Any]]:
            U, dist = self.geometry(t)
            f = Pm @ (dist - y)
            return 0.5 * float(f @ f), (f, dist, U)

        def linearize(self, t: Array, state: tuple[Array, Array, Any]) -> DenseStep:
            f, _, U = state
            Jx = self.jacobian(U)
            Jr = Pm @ Jx  # the reduced Jacobian (exact: A does not depend on the positions)
            # gradient Jx^T f = Jr^T f, since P f = f
            return DenseStep(np.dot(Jr.T, Jr), np.dot(Jx.T, f), self.dstep, self.projector(t), None, k)

        def retract(self, t: Array, dx: Array) -> Array:
            trial = t.copy()
            trial[:k] += dx
            return trial

        def small_step(self, t: Array, dx: Array, xtol: float) -> bool:
            return math.sqrt(float(dx @ dx)) <= xtol * (xtol + math.sqrt(float(t[:k] @ t[:k])))

    model = Projected(r_idx, s_idx, Pairs(ii, jj, I, J), y, d, I, "linear", 1.0, "dense")
    out = levenberg_marquardt(model, theta, max_iter=max_nfev or max_it, xtol=xtol, ftol=DL.FTOL)
    theta, converged, it = out.x, out.converged, out.iterations
    dist = out.state[1]
    # the offsets of the final geometry, in the gauge of the start (sum d - sum o kept)
    z = AG @ (y - dist)
    if v is not None:
        z += ((shift0 - float(v @ z)) / v.size) * v
    theta[k:] = z
    return theta, converged, it


def per_start(seed: int, cap: int) -> dict[str, Any]:
    """Every start of the search for one draw, refined by both engines."""
    from selfcal.toa import fit
    from selfcal.toa.engine import nls
    from selfcal.toa.engine.dense_lm import full_lm
    from selfcal.toa.search import INITIALISERS, _pack_start, _sane, canonical_order

    _, _, _, _, T = scene(seed)
    Y = T * C
    pr, pc = canonical_order(Y)
    Yc = Y[np.ix_(pr, pc)]
    rng = np.random.default_rng(seed)
    starts = []
    nested = fit._nested_start(Yc, 3, "both", rng, "auto", None, None)
    if nested:
        starts.append(nested)
    for name, init in INITIALISERS.items():
        try:
            got = init(Yc, 3, "both", rng)
        except Exception:  # an initialiser that does not apply
            continue
        starts += [(name, st) for st in got if _sane(st, Yc)]
    ii, jj = np.nonzero(np.isfinite(Yc))
    rows = []
    for name, st in starts:
        th0 = _pack_start(st)
        rec: dict[str, Any] = {"start": name}
        for eng, fn in (("joint", full_lm), ("varpro", solve_varpro_lm)):
            c0 = time.process_time()
            th, conv, it = fn(th0, Yc[ii, jj], ii, jj, 12, 6, 3, "both", "linear", 1.0, cap, 1e-10)
            cpu = time.process_time() - c0
            f = nls.toa_residuals(th, Yc, 3, "both")
            R, S = th[:36].reshape(12, 3), th[36:54].reshape(6, 3)
            rec[eng] = {"rss": float(np.nansum(f**2)), "converged": bool(conv), "iterations": int(it), "cpu_s": cpu,
                        "far_m": float(np.linalg.norm(S - R.mean(0), axis=1).max())}
        rows.append(rec)
    best = min(min(r["joint"]["rss"], r["varpro"]["rss"]) for r in rows)
    for r in rows:
        for eng in ("joint", "varpro"):
            r[eng]["best_basin"] = bool(r[eng]["rss"] <= best + 0.01 * (NOISE * C) ** 2)
    return {"seed": seed, "starts": rows}


def blind(seed: int) -> dict[str, Any]:
    """One truth-started reference and the blind solve with each engine."""
    import selfcal.toa.search as search
    from selfcal.toa import refine_toa, solve_toa, toa_crlb

    r, s, d, o, T = scene(seed)
    sigma = NOISE * C
    ref = refine_toa(T * C, r, s, offsets="both", receiver_offsets0=d * C, source_offsets0=o * C,
                     covariance=False, solver="trf")
    rss_ref = float(np.nansum(ref.residuals**2))
    crlb = toa_crlb(r, s, sigma, offsets="both")
    crlb_all = float(np.sqrt((12 * crlb.rmse_receivers**2 + 6 * crlb.rmse_sources**2) / 18))
    row: dict[str, Any] = {"seed": seed, "rss_reference_m2": rss_ref,
                           "far_reference_m": float(np.linalg.norm(ref.sources - ref.receivers.mean(0), axis=1).max())}
    saved = search.solve_dense_lm
    try:
        for eng in ("joint", "varpro"):
            search.solve_dense_lm = saved if eng == "joint" else solve_varpro_lm  # type: ignore[assignment]
            c0 = time.process_time()
            err = None
            try:
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")
                    res = solve_toa(T, dim=3, offsets="both", speed=C, rng=seed)
                rss = float(np.nansum((res.residuals * C) ** 2))
                dist = _rmse(res.receivers, res.sources, ref.receivers, ref.sources)
                far = float(np.linalg.norm(res.sources - res.receivers.mean(0), axis=1).max())
            except Exception as exc:  # a failure is a data point here
                rss, dist, far, err = float("inf"), float("nan"), float("nan"), type(exc).__name__
            row[eng] = {"in_basin": bool(rss <= rss_ref + 0.01 * sigma**2), "rss_m2": rss,
                        "same_minimum": bool(dist <= 0.01 * crlb_all), "far_m": far, "error": err,
                        "cpu_s": time.process_time() - c0}
    finally:
        search.solve_dense_lm = saved  # type: ignore[assignment]
    return row


def main(first: int = 0, draws: int = 10, starts: bool = False, cap: int = 500,
         out_dir: Path | None = None) -> dict[str, Any]:
    seeds = range(first, first + draws)
    if starts:
        rows = [per_start(k, cap) for k in seeds]
        summary: dict[str, Any] = {}
        for eng in ("joint", "varpro"):
            S = [st[eng] for r in rows for st in r["starts"]]
            summary[eng] = {
                "starts": len(S), "best_basin": sum(x["best_basin"] for x in S),
                "converged": sum(x["converged"] for x in S),
                "iterations_median": statistics.median(x["iterations"] for x in S),
                "ms_per_iteration": 1e3 * sum(x["cpu_s"] for x in S) / max(1, sum(x["iterations"] for x in S)),
                "far_100m": sum(x["far_m"] > 100 for x in S)}
    else:
        rows = [blind(k) for k in seeds]
        summary = {eng: {"in_basin": sum(r[eng]["in_basin"] for r in rows),
                         "same_minimum": sum(r[eng]["same_minimum"] for r in rows),
                         "errors": sum(r[eng]["error"] is not None for r in rows),
                         "far_100m": sum(r[eng]["far_m"] > 100 for r in rows),
                         "cpu_median_s": statistics.median(r[eng]["cpu_s"] for r in rows)}
                   for eng in ("joint", "varpro")}
        summary["far_100m_reference"] = sum(r["far_reference_m"] > 100 for r in rows)
    result = {"benchmark": "toa_varpro", "seeds": [first, first + draws - 1], "per_start": starts,
              "summary": summary, "draws": rows}
    print(json.dumps({"seeds": result["seeds"], "summary": summary}, indent=1))
    if out_dir is not None:
        out_dir.mkdir(parents=True, exist_ok=True)
        (out_dir / f"toa_varpro_{'starts' if starts else 'blind'}_{first}.json").write_text(json.dumps(result))
    return result


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--first", type=int, default=0)
    ap.add_argument("--draws", type=int, default=10)
    ap.add_argument("--per-start", action="store_true")
    ap.add_argument("--cap", type=int, default=500)
    ap.add_argument("--out", type=Path, default=None)
    a = ap.parse_args()
    main(a.first, a.draws, a.per_start, a.cap, a.out)
