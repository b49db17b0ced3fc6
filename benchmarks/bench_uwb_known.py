"""Benchmark "uwb_known": cost of known anchors and bias models relative to the blind solve, same run.

``selfcal calibrate toa`` is run in this process (click's CliRunner, as a user runs it)
on one UWB matrix with several option sets, interleaved, ``--repeat`` times each; CPU
seconds (``time.process_time``, OPENBLAS_NUM_THREADS=1 advised; the machine is shared, so
wall time is inflated by others). The baseline is the blind default run on the same matrix
in the same process; every other variant is reported as a ratio of medians to it. Target
(issue 29): known anchors and bias models at most 3x the blind solve.

Matrices: a simulated room (7 anchors, 4 of them under an 8 x 6 x 3 m ceiling, one tag
carried through 220 positions, per-anchor biases N(-0.1, 0.1^2) m, noise 3 cm, 3 %
multipath spikes), once in time order (the moving-tag recipe applies) and once with the
columns shuffled (recipe none: the solver's search alone); the shared LPS flights
(``--data``, skipped with a line when missing). Known file: 4 anchors at their true
positions.

Variants: blind (defaults), ``--known``, ``--known`` with heights only (every anchor's
``A,,,z``: x, y empty), ``--offsets receivers``, ``--known --offsets receivers``,
``--offsets auto``.

Measured (2026-12-03, branch ``uwbmodel``, loaded 2-core machine, ``--repeat 1``), ratios
--known / --offsets receivers / --known --offsets receivers / --offsets auto: room 1.08 /
1.54 / 1.61 / 1.03 (blind 1.18 s); room-shuffled 1.01 / 1.83 / 2.07 / 5.62 (blind 0.82 s);
data4 0.95 / 1.70 / 1.65 / 0.95 (blind 9.17 s); data5 1.01 / 1.36 / 1.33 / 1.15 (blind 9.14 s).
Heights only (branch ``knownz``, same conditions, ``--cases room,room-shuffled``): room 1.14
(blind 0.92 s, exit 0, anchor RMSE 0.058 m vs blind 0.060 m), room-shuffled 1.27 (blind 0.64 s).
Measured (2026-12-03, branch ``uwbauto`` against main 33dc51a in the same session, loaded
2-core machine; rooms ``--repeat 3``, flights ``--repeat 1``), ratios --known / --offsets
receivers / --known --offsets receivers / --offsets auto, before -> after:
room 1.08 / 1.73 / 1.70 / 1.01 -> 1.03 / 1.51 / 1.51 / 0.90 (blind 0.84 s);
room-shuffled 1.03 / 2.20 / 2.18 / 6.54 -> 1.09 / 2.16 / 2.28 / 4.74 (blind 0.57 s; ``auto``
no longer searches the chosen model a second time for ``--dim auto``; the rest is the
chosen model's search, whose rank-3 offsets initialiser takes ~0.7 s and never won over
the nested start on 8 of 8 shuffled rooms, and the cross-validation, ~0.5 s);
data4 0.97 (exit 2: ``--dim auto`` chose 2-D and the known file has z) / 1.10 / 1.25 / 0.95
-> 0.45 (3-D: the known anchors span 3-D) / 1.13 / 1.27 / 1.01 (blind 8.5-9.7 s);
data5 0.98 / 1.55 / 1.60 / 0.99 -> 1.04 / 1.61 / 1.80 / 1.01 (blind 4.2 s). ``--known``
now includes the block jackknife and the random-effect refits (about 0.3-0.8 s).
Measured (2026-12-03, branch ``autooff`` against main 82fd91c, loaded 2-core machine,
``--cases room-shuffled,room --repeat 3``, before / after interleaved twice): room-shuffled
``--offsets auto`` 1.89 / 2.09 s -> 2.62 / 3.12 s CPU, ratio 5.57 / 5.25 -> 6.90 / 6.05 (blind
0.34-0.52 s; the load varied); room (recipe path) 1.03 / 0.98 -> 0.95 / 1.00. Run alone,
alternating, one ``calibrate toa --offsets auto`` each: 1.97 / 2.11 / 1.86 / 1.86 s before,
2.17 / 2.14 / 2.08 / 2.35 s after. The candidates' own starts (``choose_offsets``: "both"
always, which fixed the wrong choices of the slow offsets test) cost one refinement
(~0.2 s); the rank-d initialiser they need (~0.5 s) is shared with the chosen model's
search (which ran it before too), so it adds nothing.

Cases ``NAME-shuffled`` (any case: its columns in a fixed random order) and ``flight`` (a
simulated LPS flight, 6 x 250, biases N(-0.17, 0.1^2) m); ``--variants`` picks option sets
(blind always runs: the baseline); ``--api`` times ``solve_toa(offsets="none" /
"receivers" / "auto")`` (3-D, no recipe) instead of the CLI.

Measured (2026-12-03, branch ``autofast`` against main da8493a in the same session, loaded
2-core machine, ``--repeat 1``; ``PYTHONPATH`` the old or the new tree, alternating),
``--api --cases room-shuffled,flight-shuffled,data4-shuffled,data5-shuffled --variants
blind,receivers,auto``, auto / receivers CPU s (ratio), before -> after (two runs each,
the second in brackets where it differs): room-shuffled auto 2.70 [2.45] s (6.90 [6.61]) ->
1.76 s (6.30); flight-shuffled auto 8.32 [8.41] s (12.8 [14.4]) -> 5.92 s (17.2: its blind
0.65 -> 0.34 s); data4-shuffled auto 16.5 s (20.8 [21.1]) -> 7.40 s (16.4), receivers 5.52 s
(7.0) -> 1.89 s (4.2); data5-shuffled auto 12.0 s (21.1) -> 5.45 [4.54] s (17.6 [16.7]),
receivers 3.59 s (6.3) -> 1.19 s (3.8). CLI (``--cases room-shuffled,flight-shuffled,
data4-shuffled,data5-shuffled,data4,data5 --variants blind,auto,receivers,known+receivers``),
ratios auto / receivers / known+receivers before -> after: room-shuffled 5.31 / 2.83 / 2.81
-> 4.58 / 2.59 / 2.44; flight-shuffled 7.97 / 2.83 / 2.69 -> 7.17 / 4.16 / 3.43 (paths the
change does not touch: load noise); data4-shuffled 17.0 / 6.21 / 5.72 -> 12.2 / 3.33 / 3.35;
data5-shuffled 9.32 / 3.22 / 3.14 -> 5.80 / 1.76 / 1.55; data4 (time order) 1.04 / 3.48 /
2.79 -> 1.12 / 3.37 / 2.63 (blind 2.95 / 2.77 s, anchor RMSE 0.1656 m both); data5 1.03 / 1.93
/ 1.41 -> 1.03 / 1.87 / 1.39 (0.1552 m both). Every exit code, offsets model and anchor RMSE
the same before and after. What changed is in docs/design.md (per-anchor biases, cost).

Measured (2026-12-03, branch ``autoconv`` against main f00e93c in the same session, old tree
by ``PYTHONPATH``, loaded 2-core machine; the rank-d initialiser's complete-data
Gauss-Newton matrix kept as its structure, every fit bitwise the same). ``--api --cases
room-shuffled,flight-shuffled,data4-shuffled,data5-shuffled --variants blind,receivers,auto``,
two alternating runs per tree, ratios receivers / auto, before -> after: room-shuffled 3.33 /
5.95, 2.74 / 5.83 -> 3.07 / 6.32, 2.69 / 5.36 (joint path, unchanged: noise);
flight-shuffled 5.63 / 14.6, 5.67 / 14.7 -> 6.10 / 16.9, 6.20 / 17.5 (unchanged path);
data4-shuffled 3.90 / 19.6, 4.06 / 15.0 -> 2.73 / 16.0, 2.26 / 15.9 (receivers 1.46 / 1.72
-> 1.30 / 0.82 s CPU); data5-shuffled 3.88 / 14.6, 3.65 / 16.9 -> 3.01 / 15.3, 2.47 / 17.8.
CLI ``--cases data4-shuffled,data5-shuffled,data4,data5 --variants
blind,receivers,known+receivers``, one run per tree, ratios receivers / known+receivers:
data4-shuffled 3.33 / 3.11 -> 2.17 / 1.98; data5-shuffled 1.83 / 2.36 -> 1.39 / 1.35; data4
3.48 / 2.78 -> 2.71 / 2.13; data5 1.63 / 1.30 -> 1.37 / 1.16; exit codes, offsets models and
anchor RMSEs the same (blind data4 / data5 0.1656 / 0.1552 m). ``--cases
room-shuffled,flight-shuffled`` (paths the change does not touch): known+receivers 1.75 ->
2.45 (load: blind 0.48 vs 0.34 s), 3.17 -> 3.19. Known anchors with per-anchor biases are
within 3x on the shared flights and the room, 3.2x on the simulated shuffled flight (its
rank-d initialiser's dense joint step, missing entries); ``offsets="receivers"`` alone is
5.6-6.2x there (``--api``), and ``--offsets auto`` on shuffled columns is not within 3x
(15-18x on the flights): docs/design.md (branch ``autoconv``, "Why the candidates'
refinements crawl") gives what bounds it, measured with ``benchmarks/embedded_points.py``.

Run: ``OPENBLAS_NUM_THREADS=1 PYTHONPATH=src python benchmarks/bench_uwb_known.py
[--cases room,room-shuffled,data4,data5] [--variants blind,auto] [--api] [--repeat 1] [--out FILE]``.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import tempfile
import time
import warnings

import numpy as np

VARIANTS = {
    "blind": [],
    "known": ["--known", "{known}"],
    "heights": ["--known", "{heights}"],
    "receivers": ["--offsets", "receivers"],
    "known+receivers": ["--known", "{known}", "--offsets", "receivers"],
    "auto": ["--offsets", "auto"],
}


def room(shuffle: bool) -> tuple[np.ndarray, np.ndarray]:
    """(7, 220) ranges and the (7, 3) anchors of the simulated room (fixed seed)."""
    g = np.random.default_rng(7)
    A = np.array([[0.2, 0.2, 2.8], [7.8, 0.3, 2.7], [7.7, 5.8, 2.85], [0.3, 5.7, 2.75], [4.0, 0.2, 2.9],
                  [4.1, 5.8, 1.2], [0.2, 3.0, 0.4]])
    t = np.linspace(0, 1, 220)
    tag = np.c_[4 + 3 * np.sin(2 * np.pi * 1.3 * t), 3 + 2.3 * np.sin(2 * np.pi * 2.1 * t + 1),
                1.2 + 0.6 * np.sin(2 * np.pi * 3.1 * t)]
    D = np.linalg.norm(A[:, None] - tag[None], axis=2)
    Y = D + g.normal(-0.1, 0.1, 7)[:, None] + 0.03 * g.standard_normal(D.shape)
    sp = g.random(D.shape) < 0.03
    Y[sp] += g.exponential(0.4, int(sp.sum()))
    if shuffle:
        Y = Y[:, np.random.default_rng(1).permutation(Y.shape[1])]
    return Y, A


def flight() -> tuple[np.ndarray, np.ndarray]:
    """(6, 250) ranges and the (6, 3) anchors of a simulated LPS flight (fixed seed): the Lund
    geometry, per-anchor biases N(-0.17, 0.1^2) m, 4 cm noise, 5 % multipath bursts, 0.5 % missing."""
    from selfcal.experiments.lps import simulate_uwb_flight

    sim = simulate_uwb_flight(300, 250, layout="lps", bias_std=0.1)
    return sim["ranges"], sim["anchors"]


def cases(names: list[str], data: str) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Name -> (ranges, anchors); ``NAME-shuffled``: the columns in a fixed random order (recipe none)."""
    out = {}
    for n in names:
        base, shuffle = n.removesuffix("-shuffled"), n.endswith("-shuffled")
        if base == "room":
            Y, A = room(shuffle)
        elif base == "flight":
            Y, A = flight()
            if shuffle:
                Y = Y[:, np.random.default_rng(1).permutation(Y.shape[1])]
        else:
            path = os.path.join(data, f"{base}.mat")
            if not os.path.isfile(path):
                print(f"{n}: {path} not found, skipped")
                continue
            from selfcal.datasets.lps import load_lps

            fl = load_lps(path)
            Y, A = fl.ranges, fl.anchors_true
            if shuffle:
                Y = Y[:, np.random.default_rng(1).permutation(Y.shape[1])]
        out[n] = (Y, A)
    return out


def run_case(Y: np.ndarray, A: np.ndarray, repeat: int, tmp: str,
             variants: list[str] | None = None) -> dict[str, dict[str, float]]:
    from click.testing import CliRunner

    from selfcal.cli import main
    from selfcal.metrics import aligned_rmse

    mat = os.path.join(tmp, "m.csv")
    np.savetxt(mat, Y, delimiter=",")
    known = os.path.join(tmp, "known.csv")
    with open(known, "w") as fh:
        fh.writelines(f"r{i},{A[i, 0]},{A[i, 1]},{A[i, 2]}\n" for i in range(4))
    heights = os.path.join(tmp, "heights.csv")
    with open(heights, "w") as fh:
        fh.write("name,x,y,z\n")
        fh.writelines(f"r{i},,,{A[i, 2]}\n" for i in range(A.shape[0]))
    chosen = {v: VARIANTS[v] for v in (variants or list(VARIANTS))}
    cpu: dict[str, list[float]] = {v: [] for v in chosen}
    rows: dict[str, dict[str, float]] = {}
    runner = CliRunner()
    runner.invoke(main, ["calibrate", "toa", mat, "--out", os.path.join(tmp, "warm.json")])  # imports, untimed
    for _ in range(repeat):
        for v, extra in chosen.items():
            out = os.path.join(tmp, f"{v}.json")
            if os.path.isfile(out):  # a run that writes nothing must not be read as the last case's
                os.remove(out)
            args = ["calibrate", "toa", mat, "--out", out, *[a.format(known=known, heights=heights) for a in extra]]
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                t0 = time.process_time()
                res = runner.invoke(main, args)
                cpu[v].append(time.process_time() - t0)
            data = json.loads(open(out).read()) if os.path.isfile(out) else {}
            rec = np.array(data.get("receivers", np.full_like(A, np.nan)), float)
            dim = rec.shape[1]
            rec = np.c_[rec, np.zeros((rec.shape[0], A.shape[1] - dim))]  # a 2-D answer (dim auto) in its plane
            rows[v] = {"exit": res.exit_code, "offsets": data.get("offsets"), "dim": dim,
                       "rmse": float(aligned_rmse(rec, A).rmse_receivers) if np.isfinite(rec).all() else float("nan")}
    base = statistics.median(cpu["blind"])
    for v in chosen:
        rows[v]["cpu_s"] = statistics.median(cpu[v])
        rows[v]["ratio"] = rows[v]["cpu_s"] / base
    return rows


API_VARIANTS = {"blind": "none", "receivers": "receivers", "auto": "auto"}


def run_api(Y: np.ndarray, A: np.ndarray, repeat: int, variants: list[str]) -> dict[str, dict[str, float]]:
    """The library call instead of the CLI: ``solve_toa(Y, offsets=...)`` (3-D, no recipe), CPU s."""
    from selfcal.metrics import aligned_rmse
    from selfcal.toa import solve_toa

    chosen = [v for v in variants if v in API_VARIANTS]
    cpu: dict[str, list[float]] = {v: [] for v in chosen}
    rows: dict[str, dict[str, float]] = {}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        solve_toa(Y[:, :40], rng=0)  # imports, untimed
        for _ in range(repeat):
            for v in chosen:
                t0 = time.process_time()
                res = solve_toa(Y, offsets=API_VARIANTS[v], rng=0)
                cpu[v].append(time.process_time() - t0)
                rows[v] = {"exit": 0 if res.success else 1, "offsets": res.offsets, "dim": 3,
                           "rmse": float(aligned_rmse(res.receivers, A).rmse_receivers)}
    base = statistics.median(cpu["blind"])
    for v in chosen:
        rows[v]["cpu_s"] = statistics.median(cpu[v])
        rows[v]["ratio"] = rows[v]["cpu_s"] / base
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", default="room,room-shuffled,data4,data5")
    ap.add_argument("--data", default=os.path.join(os.path.dirname(__file__), "..", "..", "shared", "data", "lps"))
    ap.add_argument("--repeat", type=int, default=1)
    ap.add_argument("--variants", default=",".join(VARIANTS), help="comma-separated; blind is always run")
    ap.add_argument("--out", default=None)
    ap.add_argument("--api", action="store_true",
                    help="solve_toa(offsets=none / receivers / auto) instead of the CLI (variants blind, receivers, auto)")
    args = ap.parse_args()
    table = {}
    with tempfile.TemporaryDirectory() as tmp:
        for name, (Y, A) in cases(args.cases.split(","), args.data).items():
            variants = ["blind", *[v for v in args.variants.split(",") if v != "blind"]]
            rows = run_api(Y, A, args.repeat, variants) if args.api else run_case(Y, A, args.repeat, tmp, variants)
            table[name] = rows
            for v, r in rows.items():
                print(f"{name:14s} {v:16s} CPU {r['cpu_s']:6.2f} s  ratio {r['ratio']:4.2f}  exit {r['exit']}  "
                      f"dim {r['dim']}  offsets {r['offsets']}  anchor RMSE {r['rmse']:.4f} m", flush=True)
    if args.out:
        with open(args.out, "w") as fh:
            json.dump(table, fh, indent=1)


if __name__ == "__main__":
    main()
