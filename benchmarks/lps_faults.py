"""Fault simulator for UWB flights of the Lund LPS kind, and a sweep of ``calibrate toa`` over it.

A flight: 6 anchors around a ~2.4 x 2.0 x 1.2 m volume at mixed heights (the layout of
:func:`selfcal.experiments.lps.simulate_uwb_flight` with ``layout="lps"``), one tag on a
smooth trajectory through and around it, ranges = distance + per-anchor bias + noise.
:func:`flight` draws one with one fault of :data:`FAULTS` applied:

- ``clean``: per-anchor bias N(-0.17, 0.05^2) m, 4 cm noise, 0.5 % NaN, no spikes;
- ``bias``: per-anchor biases N(0, 0.15^2) m (larger than the real system's spread);
- ``offset``: one common range offset of -0.4 m (a UWB antenna delay), biases 2 cm;
- ``nan-bursts``: 1-5 bursts of 20-200 consecutive NaN per anchor;
- ``spikes``: multipath returns, +U(0.3, 3) m on 1-5 % of the ranges;
- ``two-gaps``: anchor 0 unseen over the first half, anchor 1 over the second half;
- ``blind-anchor``: anchor 0 never sees the tag; ``rare-anchor``: it sees 5 positions;
- ``moved-anchor``: anchor 0 is bumped by 0.3-0.6 m halfway through the flight;
- ``planar``: the tag flies at one height (+- 1 cm);
- ``short``: 60 tag positions;
- ``gap-planar``: ``two-gaps`` where the tag flies at one height on the first half.

:func:`run_case` runs the ``calibrate toa`` path in-process (``apply_recipe("auto", ...)``
with the CLI's defaults, then the CLI's verdict ``commands.toa._trustworthy``) and scores
the anchors after rigid alignment (reflection allowed) on the anchors the result kept.

Run: ``PYTHONPATH=src:benchmarks python benchmarks/lps_faults.py [--faults a,b] [--seeds 0-9]
[--n 1500] [--truth]``: one line per case and a table per fault (exit code, anchor RMSE median / max,
how many runs name the problem in their message).
"""

from __future__ import annotations

import argparse
import time
import warnings
from typing import Any

import numpy as np

FAULTS = ("clean", "bias", "offset", "nan-bursts", "spikes", "two-gaps", "blind-anchor", "rare-anchor",
          "moved-anchor", "planar", "short", "gap-planar")

#: the LPS anchor layout (unit box corners at mixed heights), scaled to BOX
_CORNERS = np.array([[0, 0, 0], [1, 0, 1], [1, 1, 0], [0, 1, 1], [0.5, 0, 0.9], [0.5, 1, 0.1]], float)
BOX = np.array([2.4, 2.0, 1.2])


def _trajectory(g: np.random.Generator, n: int, planar: bool = False) -> np.ndarray:
    t = np.linspace(0, 1, n)
    tag = np.zeros((n, 3))
    for a in range(3):
        f, ph, amp = g.uniform(1, 4, 3), g.uniform(0, 2 * np.pi, 3), g.uniform(0.1, 0.3, 3)
        tag[:, a] = 0.5 + (amp[:, None] * np.sin(2 * np.pi * f[:, None] * t + ph[:, None])).sum(0) / 2
    tag = (0.5 + 1.86 * (tag.clip(0, 1) - 0.5)) * BOX
    if planar:
        tag[:, 2] = 0.6 + g.uniform(-0.01, 0.01, n)
    return tag


def flight(fault: str, seed: int, n: int = 1500) -> dict[str, Any]:
    """One simulated flight with ``fault`` applied.

    Returns a dict: ``ranges`` (6, N) metres with NaN, ``anchors`` (6, 3) true positions
    (before any move), ``tag`` (N, 3), ``noise`` (the range noise std, m), ``fault``,
    ``faulty`` (the anchor indices the fault is about, may be empty).
    """
    if fault not in FAULTS:
        raise ValueError(f"fault must be one of {FAULTS}")
    g = np.random.default_rng([seed, FAULTS.index(fault)])
    if fault == "short":
        n = 60
    anchors = (_CORNERS + g.uniform(-0.08, 0.08, _CORNERS.shape)).clip(0, 1) * BOX
    tag = _trajectory(g, n, planar=fault == "planar")
    if fault == "gap-planar":
        tag[: n // 2, 2] = 0.6 + g.uniform(-0.01, 0.01, n // 2)
    A = np.repeat(anchors[:, None], n, axis=1)  # anchor position per sample
    faulty: tuple[int, ...] = ()
    if fault == "moved-anchor":
        v = g.normal(size=3)
        A[0, n // 2:] += g.uniform(0.3, 0.6) * v / np.linalg.norm(v)
        faulty = (0,)
    D = np.linalg.norm(A - tag[None], axis=2)
    noise = 0.04
    bias = g.normal(-0.17, 0.05, 6)
    if fault == "bias":
        bias = g.normal(0.0, 0.15, 6)
    elif fault == "offset":
        bias = -0.4 + g.normal(0.0, 0.02, 6)
    Y = D + bias[:, None] + noise * g.standard_normal(D.shape)
    Y[g.random(D.shape) < 0.005] = np.nan
    if fault == "spikes":
        hit = g.random(D.shape) < g.uniform(0.01, 0.05)
        Y[hit] += g.uniform(0.3, 3.0, int(hit.sum()))
    elif fault == "nan-bursts":
        for i in range(6):
            for _ in range(int(g.integers(1, 6))):
                a = int(g.integers(0, n))
                Y[i, a:a + int(g.integers(20, 201))] = np.nan
    elif fault in ("two-gaps", "gap-planar"):
        Y[0, : n // 2] = np.nan
        Y[1, n // 2:] = np.nan
        faulty = (0, 1)
    elif fault == "blind-anchor":
        Y[0] = np.nan
        faulty = (0,)
    elif fault == "rare-anchor":
        keep = g.choice(n, 5, replace=False)
        row = np.full(n, np.nan)
        row[keep] = Y[0, keep]
        Y[0] = row
        faulty = (0,)
    return {"ranges": Y, "anchors": anchors, "tag": tag, "noise": noise, "fault": fault, "faulty": faulty}


def anchor_rmse(est: np.ndarray, true: np.ndarray) -> float:
    """RMSE (m) of the finite rows of ``est`` after rigid alignment (reflection allowed) to ``true``."""
    from selfcal.geometry import align

    ok = np.isfinite(est).all(axis=1)
    if ok.sum() < 4:
        return float("nan")
    a = align(est[ok], true[ok])
    return float(np.sqrt(np.mean(np.sum((a.apply(est[ok]) - true[ok]) ** 2, axis=1))))


def run_case(fl: dict[str, Any], seed: int = 0, truth: bool = False) -> dict[str, Any]:
    """``calibrate toa``'s path on the flight's ranges (CLI defaults): exit code, message, anchor RMSE.

    ``truth``: also :func:`truth_gap` (key ``gap``; NaN otherwise).
    """
    from selfcal.commands.toa import _trustworthy
    from selfcal.errors import SelfcalError
    from selfcal.toa.recipes.recipes import apply_recipe

    t0 = time.process_time()
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            rec = apply_recipe("auto", fl["ranges"], common_offset="test", method="auto", rng=seed, speed=None)
    except SelfcalError as exc:
        return {"rc": 2, "rmse": float("nan"), "message": str(exc), "cpu": time.process_time() - t0,
                "dropped": (), "gap": float("nan")}
    res = rec.result
    ok, why = _trustworthy(res)
    cpu = time.process_time() - t0
    return {"rc": 0 if ok else 1, "rmse": anchor_rmse(np.asarray(res.receivers), fl["anchors"]),
            "message": str(getattr(res, "message", "") or why), "cpu": cpu,
            "dropped": tuple(getattr(res, "dropped_receivers", ()) or ()),
            "gap": truth_gap(fl, res) if truth else float("nan")}


def truth_gap(fl: dict[str, Any], res: Any) -> float:
    """(RSS of the result - RSS refined from the truth in the result's model) / noise^2.

    On the entries the result used (inliers of its kept nodes), its own model (``none`` or
    ``common``), both ends refined to convergence: below zero, the data prefer the blind
    answer (its error is the estimator's); far above, the search missed the truth's basin.
    """
    from selfcal.toa.engine.nls import refine_toa

    used = np.isfinite(res.residuals) & ~np.asarray(res.outliers, bool)
    kr, ks = np.isfinite(res.receivers).all(axis=1), np.isfinite(res.sources).all(axis=1)
    Z = np.where(used, fl["ranges"], np.nan)[np.ix_(kr, ks)]
    kw: dict[str, Any] = {"offsets": "none"}
    d0 = None
    if res.offsets == "common":
        kw = {"offsets": "receivers", "common_offsets": "receivers"}
        d0 = np.asarray(res.receiver_offsets)[kr]
    elif res.offsets != "none":
        kw = {"offsets": res.offsets}
    try:
        blind = refine_toa(Z, res.receivers[kr], res.sources[ks], receiver_offsets0=d0, covariance=False, **kw)
        truth = refine_toa(Z, fl["anchors"][kr], fl["tag"][ks], covariance=False, **kw)
    except Exception:  # noqa: BLE001 - a diagnostic only
        return float("nan")
    return float((np.nansum(blind.residuals**2) - np.nansum(truth.residuals**2)) / fl["noise"] ** 2)


def names_problem(fl: dict[str, Any], out: dict[str, Any]) -> bool:
    """Does the run name the faulty anchor (message 'receivers i' / 'receiver i' or dropped)?"""
    msg = out["message"]
    if not fl["faulty"]:
        return fl["fault"] in ("planar",) and ("undetermined" in msg or "planar" in msg)
    return all(f"receiver {i}" in msg or f"receivers {i}" in msg or f", {i}" in msg or i in out["dropped"]
               for i in fl["faulty"])


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--faults", default=",".join(FAULTS))
    ap.add_argument("--seeds", default="0-9")
    ap.add_argument("--n", type=int, default=1500)
    ap.add_argument("--truth", action="store_true",
                    help="also refit each result's model from the truth: (RSS blind - RSS truth) / noise^2")
    a = ap.parse_args(argv)
    lo, _, hi = a.seeds.partition("-")
    seeds = range(int(lo), int(hi or lo) + 1)
    for fault in a.faults.split(","):
        rows = []
        for seed in seeds:
            fl = flight(fault, seed, a.n)
            out = run_case(fl, truth=a.truth)
            out["named"] = names_problem(fl, out)
            rows.append(out)
            print(f"{fault:13s} seed {seed:3d} rc {out['rc']} rmse {out['rmse']:.3f} m cpu {out['cpu']:.1f} s "
                  f"named {out['named']}" + (f" gap {out['gap']:.0f}" if a.truth else "") + f" | {out['message'][:160]}", flush=True)
        rc = [r["rc"] for r in rows]
        e = np.array([r["rmse"] for r in rows])
        print(f"== {fault}: rc0 {rc.count(0)} rc1 {rc.count(1)} rc2 {rc.count(2)} | rmse median "
              f"{np.nanmedian(e):.3f} max {np.nanmax(e):.3f} | rc0 & rmse > 0.3: "
              f"{sum(r['rc'] == 0 and r['rmse'] > 0.3 for r in rows)} | named {sum(r['named'] for r in rows)}",
              flush=True)


if __name__ == "__main__":
    main()
