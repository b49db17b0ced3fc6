"""``solve_toa(offsets="auto")`` decisions on simulated UWB flights, for before / after comparisons.

24 flights (``simulate_uwb_flight(300 + seed, 250, layout, bias_std)``, seeds 0-3, layouts
"lps" / "room", per-anchor bias std 0 / 0.1 / 0.2 m, 5 % multipath bursts, 0.5 % missing),
columns in a fixed random order (no recipe: the solver's own choice). Per flight: the
chosen offsets model, every candidate's CV score, the receivers, the verdict, and the CPU
seconds of ``offsets="auto"`` and of the blind ``offsets="none"`` solve in the same process.
A run writes JSON (``--out``); ``--compare OLD NEW`` reports how many choices agree, the
largest change of a CV score and of a receiver coordinate, and the CPU.

Measured (2026-12-03, branch ``autofast`` against main da8493a, the old tree by
``PYTHONPATH``, loaded 2-core machine): the same choice on 24 of 24 flights (16 none, 8
receivers), CV scores and receivers bitwise the same, verdicts the same; CPU of ``auto``
median 6.97 -> 5.33 s, its ratio to the blind solve median 21.4 -> 22.1 (the blind solve got
faster too).

Run: ``OPENBLAS_NUM_THREADS=1 PYTHONPATH=src python benchmarks/offsets_auto_decisions.py
--out new.json``; ``... --compare old.json new.json``.
"""

from __future__ import annotations

import argparse
import json
import time
import warnings

import numpy as np


def run(out: str) -> None:
    from selfcal.experiments.lps import simulate_uwb_flight
    from selfcal.toa import solve_toa

    rows = []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for seed in range(4):
            for layout in ("lps", "room"):
                for bias in (0.0, 0.1, 0.2):
                    sim = simulate_uwb_flight(300 + seed, 250, layout=layout, bias_std=bias)
                    Y = sim["ranges"][:, np.random.default_rng(seed).permutation(sim["ranges"].shape[1])]
                    t0 = time.process_time()
                    res = solve_toa(Y, offsets="auto", rng=0)
                    cpu = time.process_time() - t0
                    t0 = time.process_time()
                    solve_toa(Y, offsets="none", rng=0)
                    blind = time.process_time() - t0
                    sel = res.selection["offsets"]
                    rows.append({"seed": seed, "layout": layout, "bias_std": bias, "chosen": sel["chosen"],
                                 "cv_mse": sel["cv_mse"], "receivers": np.asarray(res.receivers).tolist(),
                                 "verdict": [int(res.verdict), res.verdict_message], "cpu_s": cpu, "blind_s": blind})
                    print(f"seed {seed} {layout:4s} bias {bias:.1f}: {sel['chosen']:9s} CPU {cpu:5.2f} s, "
                          f"ratio {cpu / blind:5.1f}", flush=True)
    with open(out, "w") as fh:
        json.dump(rows, fh)


def compare(old: str, new: str) -> None:
    a, b = json.load(open(old)), json.load(open(new))
    same = sum(x["chosen"] == y["chosen"] for x, y in zip(a, b, strict=True))
    cv = max(abs(x["cv_mse"][m] - y["cv_mse"][m]) / x["cv_mse"][m] for x, y in zip(a, b, strict=True) for m in x["cv_mse"])
    rec = max(float(np.nanmax(np.abs(np.array(x["receivers"], float) - np.array(y["receivers"], float))))
              for x, y in zip(a, b, strict=True))
    verdicts = sum(x["verdict"] == y["verdict"] for x, y in zip(a, b, strict=True))
    print(f"same choice {same} of {len(a)}; same verdict {verdicts}; largest relative CV-score change {cv:.2e}; "
          f"largest receiver change {rec:.2e} m")
    for name, rows in (("old", a), ("new", b)):
        print(f"{name}: auto CPU median {np.median([r['cpu_s'] for r in rows]):.2f} s, ratio to blind median "
              f"{np.median([r['cpu_s'] / r['blind_s'] for r in rows]):.1f}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="offsets_auto_decisions.json")
    ap.add_argument("--compare", nargs=2, metavar=("OLD", "NEW"))
    args = ap.parse_args()
    if args.compare:
        compare(*args.compare)
    else:
        run(args.out)


if __name__ == "__main__":
    main()
