"""Gross-error screens of the far-field solver on real residuals and heavy-tailed simulations (issue 31).

Screens compared (each feeds the same solver: flagged entries are treated as missing, least
squares on the rest):

* ``none``      -- no screen, least squares on every entry;
* ``gaussian``  -- the structure residual test with the Gaussian Bonferroni rule at 1 %
                   family-wise (the rule of 22a1f9d; ``gross_error_screen(tail="gaussian",
                   model_test=False)``, with d6ed9d5's robust first round);
* ``deletion``  -- the same plus the far-field model's deletion test of small matrices
                   (d6ed9d5, the default before issue 31; ``tail="gaussian"``);
* ``tail``      -- the default since issue 31: scale and Student-t tail (plus a uniform gross
                   part) fitted to the studentised residuals by maximum likelihood, the lower 95 %
                   bound on the dof, Bonferroni quantile of that t at 1 % family-wise
                   (``gross_error_screen()``; small matrices: a unit-variance t_3 null);
* ``huber``     -- no screen, Huber IRLS (``loss="huber"``); its reported rejections
                   (> 4 robust std) count as its false alarms;
* ``tail+cauchy`` -- the ``tail`` screen, then the Cauchy loss at 2.385 robust std (the
                   Student-t likelihood of about 6 dof: weights ``1 / (1 + r^2 / (nu s^2))``),
                   a candidate for heavy-tailed residuals; its rejections (> 4 robust std) count
                   as false alarms.

Sections (each chosen by cross-validation or simulation, none by one file's score):

A. the shared Pyramic speaker-0 file (one speaker: a cone, so positions are fitted with the
   file's own directions, semi-blind): entries flagged, RMS distance to the hand-measured
   microphones after rigid alignment, and leave-directions-out prediction error (6 folds of
   interleaved azimuths; positions from the other folds, each held-out column's offset its
   median residual; RMS and median absolute error over held-out entries, mm);
B. blind 3-speaker Pyramic-like matrices (real microphone layout, elevations 13.16, -15.5,
   1.0 deg) whose noise is resampled from the shared file's own residuals (its real tail,
   its two huge errors included): aligned position error against the truth (mm), per seed;
C. false alarms on simulations with heavy-tailed noise (Student t with 3 and 5 dof, Laplace,
   Gaussian; unit variance x 0.1 mm, a 5 cm array): fraction of clean draws with any flag
   (stated: <= 1 %), and with 2 injected gross errors (0.1-0.5 x the array's extent): the
   fraction caught and the other entries flagged.

Run: ``OPENBLAS_NUM_THREADS=1 PYTHONPATH=src python benchmarks/farfield_screens.py [--draws 25]
[--seeds 8] [--out DIR]``; writes ``<out>/farfield_screens.json`` and prints the tables.
"""

from __future__ import annotations

import argparse
import time
import warnings
from pathlib import Path
from typing import Any

import numpy as np

from selfcal.datasets import load_pyramic
from selfcal.datasets.pyramic import join_pyramic, pyramic_from_dict, simulate_pyramic
from selfcal.io import write_json
from selfcal.metrics import aligned_rmse
from selfcal.tdoa import solve_farfield
from selfcal.tdoa.screen import gross_error_screen
from selfcal.tdoa.structure import _lowrank_factors

SHARED = Path("/work/shared/data/pyramic/pyramic_tdoa_speaker0.json")
SCREENS = ("none", "gaussian", "deletion", "tail", "huber", "tail+cauchy")

LOSS = {"huber": "huber", "tail+cauchy": "cauchy"}


def _mask(name: str, D: np.ndarray) -> np.ndarray:
    if name in ("none", "huber", "huber-noscreen"):
        return np.zeros(D.shape, dtype=bool)
    if name == "gaussian":
        return gross_error_screen(D, tail="gaussian", model_test=False).mask
    if name == "deletion":
        return gross_error_screen(D, tail="gaussian").mask
    return gross_error_screen(D).mask


def _solve(name: str, D: np.ndarray, **kw: Any) -> tuple[Any, int]:
    """The solver's result with screen ``name`` and the number of entries it set aside."""
    mask = _mask(name, D)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        res = solve_farfield(np.where(mask, np.nan, D), screen=False, loss=LOSS.get(name, "linear"), **kw)
    return res, int(mask.sum()) + (int(res.rejected.sum()) if name in LOSS else 0)


def section_a() -> dict[str, Any]:
    p = load_pyramic(SHARED)
    D, N, ref = p.D, p.directions, p.positions
    k = D.shape[1]
    folds = [np.arange(f, k, 6) for f in range(6)]
    out: dict[str, Any] = {}
    for name in SCREENS:
        res, flagged = _solve(name, D, directions=N)
        rmse = aligned_rmse(res.positions, ref).rmse_receivers
        errs = []
        for test in folds:
            train = np.setdiff1d(np.arange(k), test)
            r, _ = _solve(name, D[:, train], directions=N[train])
            pred = r.positions @ N[test].T
            e = D[:, test] - pred
            e = e - np.nanmedian(e, axis=0)
            errs.append(e[1:].ravel())  # row 0 is the reference (identically 0)
        e = np.concatenate(errs)
        out[name] = {"flagged": flagged, "hand_rmse_mm": 1e3 * float(rmse),
                     "cv_rms_mm": 1e3 * float(np.sqrt(np.mean(e[np.abs(e) < 1.0] ** 2))),
                     "cv_mad_mm": 1e3 * float(np.median(np.abs(e)))}
    return out


def _real_residuals() -> np.ndarray:
    p = load_pyramic(SHARED)
    D = p.D
    L, _, _, _ = _lowrank_factors(D, np.isfinite(D).astype(float), rank=3, loss="cauchy")
    r = (D - L)[1:]  # row 0 is the reference microphone
    return r[np.isfinite(r)].ravel()


def section_b(seeds: int, step: float) -> dict[str, Any]:
    p = load_pyramic(SHARED)
    pool = _real_residuals()
    mics = p.microphones
    out: dict[str, list[float]] = {n: [] for n in SCREENS}
    flags: dict[str, list[int]] = {n: [] for n in SCREENS}
    for seed in range(seeds):
        rng = np.random.default_rng(1000 + seed)
        files = simulate_pyramic(mics, [13.16, -15.5, 1.0], azimuth_step_deg=step, noise_std=0.0,
                                 sample_rate=None, gross=0, rng=rng)
        data = join_pyramic([pyramic_from_dict(f) for f in files])
        D = data.D.copy()
        D[1:] += rng.choice(pool, size=D[1:].shape)
        truth = data.positions
        for name in SCREENS:
            try:
                res, n = _solve(name, D)
                err = aligned_rmse(res.positions, truth).rmse_receivers
            except Exception as exc:  # noqa: BLE001 - a refusal is a result here
                err, n = float("nan"), -1
                print(f"  seed {seed} {name}: {type(exc).__name__}: {str(exc)[:70]}")
            out[name].append(1e3 * float(err))
            flags[name].append(n)
    return {n: {"error_mm": out[n], "median_mm": float(np.nanmedian(out[n])), "mean_mm": float(np.nanmean(out[n])),
                "flagged": flags[n]} for n in SCREENS}


def _noise(rng: np.random.Generator, kind: str, shape: tuple[int, int]) -> np.ndarray:
    if kind == "t3":
        return rng.standard_t(3, shape) / np.sqrt(3.0)
    if kind == "t5":
        return rng.standard_t(5, shape) / np.sqrt(5.0 / 3.0)
    if kind == "laplace":
        return rng.laplace(size=shape) / np.sqrt(2.0)
    return rng.standard_normal(shape)


def _problem(rng: np.random.Generator, m: int, k: int, kind: str, sigma: float = 1e-4) -> np.ndarray:
    Z = rng.uniform(-0.025, 0.025, (m, 3))
    N = rng.normal(size=(k, 3))
    N /= np.linalg.norm(N, axis=1, keepdims=True)
    return Z @ N.T + rng.normal(size=k) + sigma * _noise(rng, kind, (m, k))


def section_c(draws: int, shapes: list[tuple[int, int]]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for m, k in shapes:
        for kind in ("t3", "t5", "laplace", "gaussian"):
            row: dict[str, Any] = {}
            for name in SCREENS:
                rng = np.random.default_rng(7 * m + k)
                fa = caught = extra = 0
                for _ in range(draws):
                    D = _problem(rng, m, k, kind)
                    if name == "huber":
                        fa += bool(_solve(name, D, allow_degenerate=True)[1])
                    else:
                        fa += bool(_mask(name, D).any())
                    D = _problem(rng, m, k, kind)
                    cells = rng.choice(m * k, 2, replace=False)
                    ext = float(np.ptp(D - D.mean(axis=0)))
                    G = np.zeros(m * k, dtype=bool)
                    G[cells] = True
                    G = G.reshape(m, k)
                    D[G] += rng.choice([-1.0, 1.0], 2) * rng.uniform(0.1, 0.5, 2) * ext
                    if name == "huber":
                        res, _ = _solve(name, D, allow_degenerate=True)
                        flg = res.rejected
                    else:
                        flg = _mask(name, D)
                    caught += int((flg & G).sum())
                    extra += int((flg & ~G).sum())
                row[name] = {"false_alarm": fa / draws, "caught": caught / (2 * draws), "extra_per_draw": extra / draws}
            out[f"{m}x{k} {kind}"] = row
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--draws", type=int, default=25, help="draws per cell of section C")
    ap.add_argument("--seeds", type=int, default=8, help="bootstrap seeds of section B")
    ap.add_argument("--step", type=float, default=4.0, help="turntable step of section B (deg)")
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results"))
    args = ap.parse_args()
    t0 = time.process_time()
    a = section_a()
    print("A. shared Pyramic speaker 0, semi-blind (file's directions): flagged, hand-measured RMSE, "
          "leave-directions-out prediction error")
    print(f"  {'screen':9s} {'flagged':>7s} {'hand mm':>8s} {'CV rms mm':>9s} {'CV mad mm':>9s}")
    for n, v in a.items():
        print(f"  {n:9s} {v['flagged']:7d} {v['hand_rmse_mm']:8.3f} {v['cv_rms_mm']:9.4f} {v['cv_mad_mm']:9.4f}")
    b = section_b(args.seeds, args.step)
    print(f"B. blind 3-speaker simulation, real microphones, noise resampled from the shared file's residuals "
          f"({args.seeds} seeds, {args.step:g} deg steps): aligned position error (mm)")
    for n, v in b.items():
        print(f"  {n:9s} median {v['median_mm']:.3f}  mean {v['mean_mm']:.3f}  per seed "
              + " ".join(f"{x:.3f}" for x in v["error_mm"]) + f"  flagged {v['flagged']}")
    c = section_c(args.draws, [(6, 8), (12, 24), (30, 60)])
    print(f"C. heavy-tailed simulations ({args.draws} draws per cell, 5 cm array, 0.1 mm noise): "
          "false alarm (clean draws with a flag) / gross caught / other entries flagged per draw")
    print(f"  {'case':16s} " + " ".join(f"{n:>20s}" for n in SCREENS))
    for case, row in c.items():
        print(f"  {case:16s} " + " ".join(
            f"{row[n]['false_alarm']:6.3f}/{row[n]['caught']:5.2f}/{row[n]['extra_per_draw']:6.2f}" for n in SCREENS))
    print(f"CPU {time.process_time() - t0:.0f} s")
    args.out.mkdir(parents=True, exist_ok=True)
    write_json(args.out / "farfield_screens.json", {"shared_file": a, "bootstrap_3_speakers": b,  "heavy_tails": c})
    print(f"wrote {args.out / 'farfield_screens.json'}")


if __name__ == "__main__":
    main()
