"""The pipeline's known-heights fit: its own LM (old) against the TOA fit with fixed z and weights (new).

Issue 30: ``selfcal.acoustics.geometry.refine_known_heights`` had its own Levenberg-Marquardt
and Jacobian; it is now :func:`selfcal.toa.engine.nls.refine_toa` with the z column of every
node fixed and per-entry weights. This script loads the old module from a git revision
(default e790be1~0 is not needed: ``--rev``, default ``33dc51a``, the last commit with the
private LM) into the same process and runs both from the same starts on simulated conference
rooms (``selfcal.scenarios.conference.conference_scene``: 8-20 units, flat and two-level
layouts, 10 us timing noise, 10 % missing entries on half the rooms), in the four ways the
pipeline calls it: least squares, per-entry weights, Cauchy loss with weights, and the
Cauchy start followed by the weighted least-squares finish.

Printed per row: the relative difference of the objective (weighted sum of squares, or the
Cauchy cost, both evaluated by this script on the returned solutions), the largest
horizontal position difference after a rigid 2-D alignment (m), the largest difference of the
pair offsets ``delta_i + tau_j`` (s), the ratio of the traces of the horizontal covariances,
and the CPU seconds of each. Usage::

    PYTHONPATH=src python benchmarks/compare_known_heights.py [--rooms 12] [--rev 33dc51a] [--driver-cauchy]

``--driver-cauchy``: the new side of the Cauchy rows is the driver's own Cauchy loss
(``refine_toa(loss="cauchy")``, one minimisation) instead of the IRLS of
``refine_known_heights`` (why the IRLS stays: issue 30's measurements, docs/design.md).
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

C = 343.0


def _old_module(rev: str) -> Any:
    src = subprocess.run(["git", "show", f"{rev}:src/selfcal/acoustics/geometry.py"], check=True,
                         capture_output=True, text=True, cwd=Path(__file__).resolve().parents[1]).stdout
    spec = importlib.util.spec_from_loader("selfcal.acoustics._geometry_old", loader=None)
    assert spec is not None
    mod = importlib.util.module_from_spec(spec)
    mod.__package__ = "selfcal.acoustics"
    sys.modules[spec.name] = mod
    exec(compile(src, f"{rev}:geometry.py", "exec"), mod.__dict__)
    return mod


def _field(sol: Any, key: str) -> Any:
    """A field of either form: the former dict or the typed result (:class:`selfcal.acoustics.solution.Calibration`)."""
    return sol[key] if isinstance(sol, dict) else getattr(sol, key)


def _objective(sol: Any, T: np.ndarray, w: np.ndarray, f_scale: float | None) -> float:
    r, s = _field(sol, "receivers"), _field(sol, "sources")
    pred = (np.linalg.norm(r[:, None] - s[None], axis=-1) / C + _field(sol, "receiver_offsets")[:, None]
            + _field(sol, "source_offsets")[None])
    e = (w * (T - pred))[np.isfinite(T)]
    if f_scale is None:
        return float(e @ e)
    return float(np.sum(np.log1p((e / f_scale) ** 2)))


def _align_xy(a: np.ndarray, b: np.ndarray) -> float:
    from selfcal.geometry import align

    return float(np.abs(align(a, b).apply(a) - b).max())


class _DriverCauchy:
    """``refine_known_heights`` whose Cauchy fit is ``refine_toa(loss="cauchy")`` on the driver
    (one minimisation of the robust cost) instead of its IRLS (``--driver-cauchy``)."""

    def __init__(self, mod: Any) -> None:
        self.mod = mod

    def refine_known_heights(self, T: np.ndarray, zr: np.ndarray, zs: np.ndarray, r0: np.ndarray, s0: np.ndarray,
                             dr0: np.ndarray, ds0: np.ndarray, *, speed: float, weights: Any = None,
                             f_scale: float | None = None) -> Any:
        if f_scale is None:
            return self.mod.refine_known_heights(T, zr, zs, r0, s0, dr0, ds0, speed=speed, weights=weights)
        from selfcal.toa.engine.nls import refine_toa

        obs = np.isfinite(T)
        w = np.asarray(weights, float)
        w = w / np.exp(np.mean(np.log(w[obs])))
        fixed_r, fixed_s = np.zeros((len(zr), 3), bool), np.zeros((len(zs), 3), bool)
        fixed_r[:, 2] = fixed_s[:, 2] = True
        sh = float(ds0[0])
        sol = refine_toa(speed * T, np.column_stack([r0, zr]), np.column_stack([s0, zs]), offsets="both",
                         receiver_offsets0=speed * (dr0 + sh), source_offsets0=speed * (ds0 - sh), max_nfev=50,
                         xtol=1e-12, solver="lm", fixed_receivers=fixed_r, fixed_sources=fixed_s, weights=w,
                         loss="cauchy", f_scale=f_scale * speed)
        return {"receivers": sol.receivers, "sources": sol.sources, "receiver_offsets": sol.receiver_offsets / speed,
                "source_offsets": sol.source_offsets / speed, "receiver_cov": sol.receiver_cov,
                "converged": sol.converged}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rooms", type=int, default=12)
    ap.add_argument("--rev", default="33dc51a")
    ap.add_argument("--driver-cauchy", action="store_true",
                    help="new Cauchy rows: the driver's Cauchy loss instead of the IRLS of refine_known_heights")
    args = ap.parse_args()
    from selfcal.acoustics import geometry as new
    from selfcal.scenarios.conference import conference_scene

    if args.driver_cauchy:  # the new side of the Cauchy rows: the driver's own Cauchy loss
        new = _DriverCauchy(new)

    old = _old_module(args.rev)
    rows = []
    for k in range(args.rooms):
        n = (8, 12, 16, 20)[k % 4]
        layout = "flat" if k % 2 == 0 else "tiered"
        try:
            sc = conference_scene(n, (9.0, 8.0, 3.0), layout=layout, rng=k)
        except Exception:  # a layout the simulator does not offer: flat
            sc = conference_scene(n, (9.0, 8.0, 3.0), layout="flat", rng=k)
        g = np.random.default_rng(100 + k)
        d = np.linalg.norm(sc.receivers[:, None] - sc.senders[None], axis=-1)
        std = g.uniform(5e-6, 20e-6, d.shape)
        T = d / C + sc.receiver_delays[:, None] + sc.sender_onsets[None] + g.normal(0, 1.0, d.shape) * std
        if k % 2:
            T[g.random(T.shape) < 0.1] = np.nan
        T[0, 1] += 3e-3 if k % 3 == 0 else 0.0  # one wrong detection on a third of the rooms
        W = 1.0 / std
        wn = W / np.exp(np.mean(np.log(W[np.isfinite(T)])))
        r0 = sc.receivers[:, :2] + g.normal(0, 0.15, (n, 2))
        s0 = sc.senders[:, :2] + g.normal(0, 0.15, (n, 2))
        dr0 = sc.receiver_delays + g.normal(0, 3e-4, n)
        ds0 = sc.sender_onsets + g.normal(0, 3e-4, n)
        ds0 = ds0 - ds0[0]
        f_sc = 2.385 * float(np.median(std))
        for case, kw, wobj, fobj in (
            ("ls", {}, np.ones_like(T), None),
            ("weighted", {"weights": W}, wn, None),
            # the fit's Cauchy objective: sum log(1 + (wn e / f_sc)^2), wn the weights at geometric mean 1
            ("cauchy+weights", {"weights": W, "f_scale": f_sc}, wn, f_sc),
        ):
            out = {}
            for name, mod in (("old", old), ("new", new)):
                t = time.process_time()
                sol = mod.refine_known_heights(T, sc.receivers[:, 2], sc.senders[:, 2], r0, s0, dr0, ds0, speed=C, **kw)
                out[name] = (sol, time.process_time() - t)
            a, b = out["old"][0], out["new"][0]
            ca, cb = _objective(a, T, wobj, fobj), _objective(b, T, wobj, fobj)
            pa = np.vstack([_field(a, "receivers"), _field(a, "sources")])[:, :2]
            pb = np.vstack([_field(b, "receivers"), _field(b, "sources")])[:, :2]
            off_a = _field(a, "receiver_offsets")[:, None] + _field(a, "source_offsets")[None]
            off_b = _field(b, "receiver_offsets")[:, None] + _field(b, "source_offsets")[None]
            tr = lambda s: float(np.trace(_field(s, "receiver_cov")[:, :2, :2], axis1=1, axis2=2).sum())  # noqa: E731
            rows.append({
                "room": k, "units": n, "layout": layout, "case": case,
                "cost_old": ca, "cost_new": cb, "rel_cost": (cb - ca) / max(abs(ca), 1e-300),
                "pos_diff_m": _align_xy(pb, pa), "pair_offset_diff_s": float(np.nanmax(np.abs(off_a - off_b))),
                "cov_trace_ratio": tr(b) / tr(a), "cpu_old_s": out["old"][1], "cpu_new_s": out["new"][1],
                "converged": [bool(_field(a, "converged")), bool(_field(b, "converged"))],
            })
            r = rows[-1]
            print(f"room {k:2d} {n:2d} units {layout:9s} {case:15s} rel cost {r['rel_cost']:+.2e}  "
                  f"pos {r['pos_diff_m']:.1e} m  offsets {r['pair_offset_diff_s']:.1e} s  "
                  f"cov ratio {r['cov_trace_ratio']:.6f}  cpu {r['cpu_old_s']:.3f} -> {r['cpu_new_s']:.3f} s  "
                  f"conv {r['converged']}")
    rel = np.array([r["rel_cost"] for r in rows])
    ratio = np.array([r["cpu_new_s"] / max(r["cpu_old_s"], 1e-9) for r in rows])
    both = np.array([all(r["converged"]) for r in rows])
    print(json.dumps({
        "rows": len(rows), "both_converged": int(both.sum()),
        "both_converged_max_abs_rel_cost": float(np.abs(rel[both]).max()),
        "both_converged_max_pos_diff_m": max(r["pos_diff_m"] for r, b in zip(rows, both, strict=True) if b),
        "max_abs_rel_cost": float(np.abs(rel).max()),
        "new_lower_or_equal": int(np.sum(rel <= 1e-8)),
        "max_pos_diff_m": max(r["pos_diff_m"] for r in rows),
        "cpu_ratio_median": float(np.median(ratio)), "cpu_ratio_max": float(ratio.max()),
    }, indent=1))


if __name__ == "__main__":
    main()
