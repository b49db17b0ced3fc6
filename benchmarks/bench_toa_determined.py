"""Benchmark "toa_determined": how often the determinacy test flags TOA results, by case.

The test (:func:`selfcal.toa.verdict.trust.determinacy_test`): a node is *undetermined* when the
largest semi-axis of its 95 % confidence ellipsoid (the result's gauge-free covariance,
at the given noise or the fit's estimate) exceeds the robust RMS radius of its node set;
more than half of the tested nodes undetermined fails the result (exit 1 from
``selfcal calibrate toa``), fewer are named in a warning.

Two families of scenes:

- ``wellposed``: receivers and sources uniform in a 10 m square / cube, offsets U(0, 3 m)
  where fitted, every entry observed, Gaussian range noise 1 or 5 cm; sizes 8 x 10,
  12 x 14, 30 x 40 in 2-D and 3-D, offsets none / both. Per draw: any node flagged, and
  the result failed by the rule. ``--mode truth`` refines from the truth
  (:func:`selfcal.toa.refine_toa`, the minimum a blind solve of a well-posed network finds)
  and applies the test with the noise given and with it estimated: cheap enough for
  hundreds of seeds; ``--mode blind`` runs ``solve_toa`` itself (noise not given).
- ``minimal``: the 12 x 6 scenes with both offsets of ``bench_toa_minimal.scene``
  (12 microphones in a 1.5 m cube, 6 sources within 4 m, 20 us timing noise): the blind
  solve's verdict against its aligned RMSE to the truth (all 18 nodes, rigid alignment on
  all), noise given and not.

Measured (2026-12-02, code of branch ``undetermined``):

- ``wellposed --mode truth --draws 100``: 0 of 100 draws with any node flagged in every case
  except 8 x 10 both 5 cm (2-D: 15 any / 0 failed with the noise given, 14 / 1 estimated;
  3-D: 59 / 11 given, 60 / 12 estimated; the truth-started fit is 0.26 / 0.74 m off in
  median, max 37 / 5.3 m, so these networks are not well posed) and 12 x 14 3-D both 5 cm
  (1 / 0 with the noise estimated). Largest extent / scale elsewhere 0.95 (12 x 14 3-D both
  5 cm), 0.15 at 30 x 40.
- ``wellposed --mode blind --draws 20 --sizes 8x10`` (2-D, and 3-D without offsets): 0 flagged
  except 2-D both 5 cm: 5 of 20 with a node named, none failed.
- ``minimal --draws 48`` (noise estimated): every fit with aligned RMSE > 2 m fails (29 / 29);
  45 / 48 fail; the 3 successes (0.76, 1.28, 1.99 m) name 1-2 nodes. ``--given``: 48 / 48 fail.
  Nodes off by more than their true set's radius: 223 of 267 named (noise estimated), 193 of
  223 (given).

Run: ``python benchmarks/bench_toa_determined.py --family wellposed --mode truth --draws 100``;
``--family minimal --draws 48 [--first 0] [--given]``. Prints one line per case and writes
JSON with ``--out DIR``.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
import warnings
from pathlib import Path
from typing import Any

import numpy as np

SIZES = ((8, 10), (12, 14), (30, 40))
DIMS = (2, 3)
OFFSETS = ("none", "both")
NOISES = (0.01, 0.05)


def network(I: int, J: int, dim: int, offsets: str, noise: float,
            g: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, np.ndarray | None, np.ndarray]:
    """(receivers, sources, receiver offsets, source offsets, noisy range matrix), metres."""
    from selfcal.toa import toa_model

    r, s = g.uniform(0, 10, (I, dim)), g.uniform(0, 10, (J, dim))
    d = g.uniform(0, 3, I) if offsets == "both" else None
    o = g.uniform(0, 3, J) if offsets == "both" else None
    Y = toa_model(r, s, d, o) + g.normal(0, noise, (I, J))
    return r, s, d, o, Y


def _truth_case(I: int, J: int, dim: int, offsets: str, noise: float, draws: int, first: int) -> dict[str, Any]:
    from selfcal.metrics import aligned_rmse
    from selfcal.toa import refine_toa
    from selfcal.toa.verdict.trust import determinacy_test, fisher_blocks

    out: dict[str, Any] = {"given_any": 0, "given_failed": 0, "est_any": 0, "est_failed": 0, "draws": draws,
                           "max_ratio": 0.0}
    errs = []
    for seed in range(first, first + draws):
        g = np.random.default_rng([I, J, dim, int(offsets == "both"), int(noise * 1000), seed])
        r, s, d, o, Y = network(I, J, dim, offsets, noise, g)
        sol = refine_toa(Y, r, s, offsets=offsets, receiver_offsets0=d, source_offsets0=o)
        e = aligned_rmse(sol.receivers, r, sol.sources, s, fit_on="all")
        errs.append(float(np.sqrt(np.mean(np.r_[e.receiver_errors, e.source_errors] ** 2))))
        for tag, nz in (("given", noise), ("est", sol.sigma)):
            # what solve_toa does on networks of <= DENSE_MAX_UNKNOWNS unknowns
            Cr, Cs = fisher_blocks(Y, sol.receivers, sol.sources, sol.receiver_offsets, sol.source_offsets,
                                   offsets, nz)
            t = determinacy_test(sol.receivers, sol.sources, Cr, Cs, noise=nz, observed=np.isfinite(Y),
                                 offsets=offsets)
            out[f"{tag}_any"] += int(t.n_undetermined > 0)
            out[f"{tag}_failed"] += int(t.failed)
            if tag == "given":
                ratio = max(np.nanmax(t.receiver_extent) / t.receiver_scale,
                            np.nanmax(t.source_extent) / t.source_scale)
                out["max_ratio"] = max(out["max_ratio"], float(ratio))
    out["rmse_median_m"] = float(np.median(errs))
    out["rmse_max_m"] = float(np.max(errs))
    return out


def _blind_case(I: int, J: int, dim: int, offsets: str, noise: float, draws: int, first: int) -> dict[str, Any]:
    from selfcal.toa import solve_toa

    out = {"any": 0, "failed": 0, "failed_other": 0, "draws": draws, "cpu_s": 0.0}
    for seed in range(first, first + draws):
        g = np.random.default_rng([I, J, dim, int(offsets == "both"), int(noise * 1000), seed])
        _, _, _, _, Y = network(I, J, dim, offsets, noise, g)
        c0 = time.process_time()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            res = solve_toa(Y, dim=dim, offsets=offsets, rng=seed)
        out["cpu_s"] += time.process_time() - c0
        t = res.determinacy
        out["any"] += int(t is not None and t.n_undetermined > 0)
        out["failed"] += int(t is not None and t.failed)
        out["failed_other"] += int(not res.success and not (t is not None and t.failed))
    return out


def wellposed(mode: str, draws: int, first: int, sizes: Any = SIZES) -> list[dict[str, Any]]:
    rows = []
    for I, J in sizes:
        for dim in DIMS:
            for offsets in OFFSETS:
                for noise in NOISES:
                    c0 = time.process_time()
                    f = _truth_case if mode == "truth" else _blind_case
                    row = {"I": I, "J": J, "dim": dim, "offsets": offsets, "noise_m": noise,
                           **f(I, J, dim, offsets, noise, draws, first)}
                    row["case_cpu_s"] = time.process_time() - c0
                    print(json.dumps(row), flush=True)
                    rows.append(row)
    return rows


def minimal(draws: int, first: int, given: bool) -> list[dict[str, Any]]:
    sys.path.insert(0, str(Path(__file__).parent))
    from bench_toa_minimal import NOISE, C, scene

    from selfcal.geometry import align
    from selfcal.metrics import aligned_rmse
    from selfcal.toa import solve_toa
    from selfcal.toa.verdict.trust import set_scale

    rows = []
    for seed in range(first, first + draws):
        r, s, _, _, T = scene(seed)
        c0 = time.process_time()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            res = solve_toa(T, dim=3, offsets="both", speed=C, rng=seed, noise=NOISE if given else None)
        cpu = time.process_time() - c0
        e = aligned_rmse(res.receivers, r, res.sources, s, fit_on="all")
        err = np.r_[e.receiver_errors, e.source_errors]
        t = res.determinacy
        # per node: aligned on the nodes the test calls determined (all when fewer than d + 1),
        # "metres off" = error above the robust radius of the node's true set
        u = np.zeros(18, bool) if t is None else np.r_[t.undetermined_receivers, t.undetermined_sources]
        P, Pt = np.vstack([res.receivers, res.sources]), np.vstack([r, s])
        ok = np.isfinite(P).all(axis=1)
        core = ok & ~u if (ok & ~u).sum() >= 4 else ok
        al = align(P[core], Pt[core])
        en = np.linalg.norm(al.apply(np.where(ok[:, None], P, 0.0)) - Pt, axis=1)
        big = ok & (en > np.r_[np.full(12, set_scale(r)), np.full(6, set_scale(s))])
        row_nodes = {"nodes_off": int(big.sum()), "nodes_off_flagged": int((big & u).sum()),
                     "flagged": int(u.sum()), "flagged_off": int((u & big).sum()),
                     "core_rmse_m": float(np.sqrt(np.mean(en[core & ~u] ** 2))) if (core & ~u).any() else None}
        row = {"seed": seed, "given": given, "status": int(res.status), "message": res.message[:60],
               "rmse_m": float(np.sqrt(np.nanmean(err**2))), "rmse_receivers_m": float(e.rmse_receivers),
               "undetermined": None if t is None else t.n_undetermined, "tested": None if t is None else t.tested,
               "determinacy_failed": bool(t is not None and t.failed), **row_nodes, "cpu_s": cpu}
        print(json.dumps(row), flush=True)
        rows.append(row)
    return rows


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--family", choices=("wellposed", "minimal"), default="wellposed")
    ap.add_argument("--mode", choices=("truth", "blind"), default="truth")
    ap.add_argument("--draws", type=int, default=100)
    ap.add_argument("--first", type=int, default=0)
    ap.add_argument("--given", action="store_true", help="minimal: give the solver the true noise")
    ap.add_argument("--sizes", default=None, help="e.g. 8x10,12x14")
    ap.add_argument("--out", type=Path, default=None)
    a = ap.parse_args()
    sizes = SIZES if a.sizes is None else tuple(tuple(int(v) for v in x.split("x")) for x in a.sizes.split(","))
    rows = wellposed(a.mode, a.draws, a.first, sizes) if a.family == "wellposed" else \
        minimal(a.draws, a.first, a.given)
    if a.out is not None:
        a.out.mkdir(parents=True, exist_ok=True)
        name = f"toa_determined_{a.family}_{a.mode if a.family == 'wellposed' else ('given' if a.given else 'est')}"
        (a.out / f"{name}_{a.first}.json").write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
