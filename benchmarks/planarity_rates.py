"""Benchmark "planarity rates": how often the one planarity test calls a layout 3-D (issue 30).

The project decides "is z determined, or is the layout (near-)planar?" with one test,
:func:`selfcal.toa.verdict.select.dimension_test` (``dim="auto"`` of ``solve_toa`` /
``calibrate toa``, the acoustic pipeline): the F test of a 2-D fit (refined from the 3-D
one) against the 3-D fit, and the chi-square of the 3-D layout's out-of-plane coordinates
against its own covariances, both at ``PLANAR_ALPHA`` = 1e-3. This script measures, over
simulated draws of an 8 x 10 network with both offsets (the pipeline's model: seconds,
c = 343 m/s, 1 us timing noise = 0.34 mm of range, an 8 x 7 m floor):

- ``generic``: heights uniform in 0-3 m (power: the rate called 3-D should be 1);
- ``planar``: every height 0 (false alarm: the rate called 3-D should be <= 1e-3);
- ``near-c``: heights N(0, c sqrt(sigma L)) with ``sigma`` the range noise and ``L`` = 5 m:
  at a planar truth the 3-D fit bends off the plane by about ``sqrt(sigma L)`` (4 cm here),
  the scale at which thickness becomes detectable by a fit (c = 0.3, 1, 3).

Per family, the rate called 3-D by: ``new`` (the test), ``chi2`` (the thickness
chi-square alone, no F test), ``F`` (the F test alone, corrected by its bootstrap null where
borderline: ``planarity.bartlett_corrected``), ``F_asymptotic`` (the F test against F(k, dof)
without that correction), ``F_known_noise`` (the same
likelihood ratio against the true noise variance, chi-square(n - 3)), ``old_pipeline`` (the per-point rule
the pipeline used before: thickness >= 3 RMS normal stds and >= 1 % of the extent), and
for the answer each rule reports (3-D, or the 2-D fit): the median node error against the
truth (a 2-D answer's includes the height it does not report: each node's distance from the
truth's best plane) and the number of draws with a node outside 3 of its own error bars
(squared Mahalanobis distance of the reported coordinates above chi-square(d)'s 0.9973 quantile).
The 3-D answer is the one ``dimension_test`` reports: its covariances widened by the
bootstrap's mean-square error where the bootstrap ran and the answer stayed 3-D;
``new_outside_3sd_linearised`` counts with the linearised bars instead, and ``widened``
lists those draws (bar widening factor per node, median and max; outside before / after).

``plan`` (:func:`plan_vs_calibration`): ``selfcal plan``'s named "anchor-mirror" against the
ambiguous anchors the calibration's uniqueness test lists on simulated ranges of the plan.

Run: ``OPENBLAS_NUM_THREADS=1 PYTHONPATH=src .venv/bin/python benchmarks/planarity_rates.py [draws [families] | plan]``
(default 40 draws of every family; families comma-separated, e.g. ``200 planar``; about
0.6 s per draw).
"""

from __future__ import annotations

import json
import sys
import time
import warnings
from typing import Any

import numpy as np
import scipy.stats

C = 343.0
NOISE = 1e-6  # s
FAMILIES = ("generic", "planar", "near-0.3", "near-1", "near-3")


def draw(family: str, g: np.random.Generator, I: int = 8, J: int = 10) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Receivers, senders (m) and the TOA matrix (s) of one draw."""
    R = np.c_[g.uniform(0, 8, I), g.uniform(0, 7, I), np.zeros(I)]
    S = np.c_[g.uniform(0, 8, J), g.uniform(0, 7, J), np.zeros(J)]
    if family == "generic":
        R[:, 2], S[:, 2] = g.uniform(0, 3, I), g.uniform(0, 3, J)
    elif family.startswith("near-"):
        h = float(family[5:]) * np.sqrt(NOISE * C * 5.0)
        R[:, 2], S[:, 2] = g.normal(0, h, I), g.normal(0, h, J)
    D = np.linalg.norm(R[:, None] - S[None], axis=-1)
    T = D / C + g.uniform(0, 0.02, I)[:, None] + g.uniform(0, 0.03, J)[None] + g.normal(0, NOISE, (I, J))
    return R, S, T


def _error(res: Any, R: np.ndarray, S: np.ndarray) -> tuple[float, bool]:
    """(median node error, any node outside 3 error bars) of a reported answer against the truth.

    A 3-D answer: the aligned 3-D error. A 2-D answer: aligned with the truth's coordinates
    in the truth's best plane; its error includes each node's distance from that plane (the
    height it does not report). Outside 3 error bars: squared Mahalanobis distance of the
    reported coordinates above the chi-square(d) 0.9973 quantile.
    """
    from scipy.stats import chi2

    from selfcal.geometry import align

    est = np.vstack([res.receivers, res.sources])
    cov = np.concatenate([res.receiver_cov, res.source_cov])
    d = est.shape[1]
    true = np.vstack([R, S])
    c = true.mean(axis=0)
    _, _, vt = np.linalg.svd(true - c, full_matrices=False)
    height = (true - c) @ vt[2]
    ref = true if d == 3 else (true - c) @ vt[:2].T
    ok = np.isfinite(est).all(axis=1)
    tr = align(est[ok], ref[ok], reflection=True)
    e = tr.apply(est[ok]) - ref[ok]
    full = np.sqrt(np.sum(e**2, axis=1) + (0.0 if d == 3 else height[ok] ** 2))
    Rm = np.asarray(tr.rotation)
    # nodes without a finite error bar claim none (the determinacy test reports them)
    m2 = [float(x @ np.linalg.pinv(Rm @ C @ Rm.T) @ x) for x, C in zip(e, cov[ok], strict=True)
          if np.isfinite(C).all()]
    return float(np.median(full)), bool(m2 and max(m2) > chi2.ppf(0.9973, d))


def one(family: str, seed: int) -> dict[str, Any]:
    """The decisions of every rule on one draw."""
    from selfcal.acoustics.calibrate import _toa_options, _toa_solver
    from selfcal.errors import DegenerateGeometryError
    from selfcal.toa import solve_toa
    from selfcal.toa.verdict.planarity import PLANAR_ALPHA
    from selfcal.toa.verdict.select import dimension_test


    g = np.random.default_rng(seed)
    R, S, T = draw(family, g)
    try:
        r3 = solve_toa(T, dim=3, offsets="both", speed=C, rng=seed)
    except DegenerateGeometryError:
        return {"degenerate": True}
    keep3, pl, r2, stats, r3w = dimension_test(T, r3, "both", _toa_solver(seed), _toa_options(C, None))
    cmp = pl.comparison
    # the same likelihood ratio against the true noise variance: chi-square(k)
    known = bool(cmp is not None and scipy.stats.chi2.sf(
        cmp.observations * (cmp.residual_2d**2 - cmp.residual_3d**2) / NOISE**2, cmp.extra_parameters) <= PLANAR_ALPHA)
    old_flat = bool(pl.extents[-1] < 0.01 * pl.extents[0] or pl.extents[-1] < 3.0 * pl.normal_std)
    e3, out3 = _error(r3w, R, S)  # the reported 3-D answer (bars widened where the bootstrap ran)
    out3_lin = _error(r3, R, S)[1]  # its linearised bars alone
    e2, out2 = _error(r2, R, S) if r2 is not None else (float("nan"), False)
    return {"degenerate": False, "new": bool(keep3), "chi2": bool(pl.thickness_p <= PLANAR_ALPHA),
            "F": bool(cmp is not None and cmp.significant),
            "F_asymptotic": bool(cmp is not None and cmp.p_asymptotic < PLANAR_ALPHA), "F_known_noise": known, "old_pipeline": not old_flat,
            "err3": e3, "err2": e2, "out3": out3, "out2": out2, "out3_linearised": out3_lin,
            "widened": bool(stats.get("bars_widened")), "widening": stats.get("bar_widening_median"),
            "widening_max": stats.get("bar_widening_max"), "seed": seed}


def main(draws: int = 40, families: tuple[str, ...] = FAMILIES) -> dict[str, Any]:
    """Rates over ``draws`` seeds per family; prints and returns them."""
    warnings.simplefilter("ignore")
    out: dict[str, Any] = {}
    t0 = time.process_time()
    for fam in families:
        rows = [one(fam, 1000 * FAMILIES.index(fam) + s) for s in range(draws)]
        ok = [r for r in rows if not r["degenerate"]]
        summary: dict[str, Any] = {"draws": draws, "degenerate_3d": draws - len(ok)}
        for rule in ("new", "chi2", "F", "F_asymptotic", "F_known_noise", "old_pipeline"):
            summary[f"{rule}_called_3d"] = sum(r[rule] for r in ok)
        for rule in ("new", "old_pipeline"):
            errs = [r["err3"] if r[rule] else r["err2"] for r in ok]
            summary[f"{rule}_median_error_m"] = float(np.nanmedian(errs)) if errs else None
            summary[f"{rule}_outside_3sd"] = sum(r["out3"] if r[rule] else r["out2"] for r in ok)
        # the reported answer with the 3-D fit's linearised bars (before the bootstrap's widening)
        summary["new_outside_3sd_linearised"] = sum(r["out3_linearised"] if r["new"] else r["out2"] for r in ok)
        wide = [r for r in ok if r["widened"] and r["new"]]
        summary["widened"] = [{"seed": r["seed"], "median": round(r["widening"], 2), "max": round(r["widening_max"], 2),
                               "outside_before": r["out3_linearised"], "outside_after": r["out3"],
                               "median_error_mm": round(r["err3"] * 1e3, 1)} for r in wide]
        out[fam] = summary
        print(fam, json.dumps(summary), flush=True)
    out["cpu_s"] = time.process_time() - t0
    return out




def plan_vs_calibration(amplitudes: tuple[float, ...] = (0.03, 0.1, 0.3), anchor_stds: tuple[float, ...] = (0.05, 0.2),
                        draws: int = 5) -> list[dict[str, Any]]:
    """``selfcal plan``'s "anchor-mirror" against what a calibration of the planned flight sees.

    The layout of ``tests/toa/test_plan.py`` (7 anchors, 150 tag positions whose height
    varies by +-``amplitude`` m about 1.2 m), 5 cm range noise, per-anchor biases of
    0.1 m std: the plan's verdict (the thickness chi-square with the CRLB, and the 1 %
    rule it replaced) against the uniqueness test of ``solve_toa(offsets="receivers")`` on
    simulated ranges (anchors it lists as ambiguous). Then the same with the path of the
    test (heights 1.2 +- 0.6 m) and the anchors' heights 2.8 m + N(0, ``anchor_std``):
    "tag-mirror" against the tag positions the calibration lists as ambiguous.
    Run: ``... benchmarks/planarity_rates.py plan``.
    """
    from selfcal.toa import solve_toa
    from selfcal.toa.plan import layout_ambiguities, plan_layout

    warnings.simplefilter("ignore")
    rows = []
    cases = [("path", a) for a in amplitudes] + [("anchors", a) for a in anchor_stds]
    for what, amp in cases:
        for seed in range(draws):
            g = np.random.default_rng(seed)
            A = np.array([[0.2, 0.2, 2.8], [7.8, 0.3, 2.7], [7.7, 5.8, 2.85], [0.3, 5.7, 2.75], [4.0, 0.2, 2.9],
                          [4.1, 5.8, 1.2], [0.2, 3.0, 0.4]]) + g.uniform(-0.1, 0.1, (7, 3))
            t = np.linspace(0, 1, 150)
            f = g.uniform(1, 3, 3)
            P = np.c_[4 + 3 * np.sin(2 * np.pi * f[0] * t), 3 + 2.3 * np.sin(2 * np.pi * f[1] * t + 1),
                      1.2 + (amp if what == "path" else 0.6) * np.sin(2 * np.pi * f[2] * t)]
            if what == "anchors":
                A[:, 2] = 2.8 + amp * g.standard_normal(7)
            kind = "anchor-mirror" if what == "path" else "tag-mirror"
            named = kind in [a.kind for a in plan_layout(A, P, noise=0.05, room=(8, 6, 3)).ambiguities]
            named_old = kind in [a.kind for a in layout_ambiguities(A, P)]
            n = np.random.default_rng(100 + seed)
            Y = (np.linalg.norm(A[:, None] - P[None], axis=-1) + n.normal(0, 0.05, (7, 150))
                 + n.normal(0, 0.1, (7, 1)))
            res = solve_toa(Y, dim=3, offsets="receivers", rng=seed)
            row = {"varied": what, "std_or_amplitude": amp, "seed": seed, "plan_named": kind if named else None,
                   "ratio_rule_named": kind if named_old else None,
                   "calibration_ambiguous_anchors": int(np.asarray(res.ambiguous_receivers).sum()),
                   "calibration_ambiguous_tags": int(np.asarray(res.ambiguous_sources).sum())}
            print(json.dumps(row), flush=True)
            rows.append(row)
    return rows


if __name__ == "__main__":
    if sys.argv[1:2] == ["plan"]:
        plan_vs_calibration()
    else:
        main(int(sys.argv[1]) if len(sys.argv) > 1 else 40, tuple(sys.argv[2].split(",")) if len(sys.argv) > 2 else FAMILIES)
