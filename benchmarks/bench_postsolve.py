"""Benchmark "postsolve": the cost of every check after the TOA solve, as a fraction of the solve.

``solve_toa`` (noise unknown, the CLI's default) runs, besides the search and the refits that
make the answer, the checks that judge it (:mod:`selfcal.toa.fit`). Each check is timed in the
same process by wrapping the function that runs it:

- ``outlier_flagging``: the outlier rule on every entry (``fit._flag``: leverages, studentized
  residuals, the Bonferroni cut), every round, and the bound that spares its robust refit on
  an exact fit (``fit._refit_cannot_flag``, which computes the rule's leverages first);
- ``leverages``: the final fit's leverages for the cross-validation (``fit.leverages`` outside
  the flagging);
- ``geometry_test``: the leave-one-out CV against the model without geometry and the
  permutation test (``fit.geometry_test``); ``permutation_test`` is its share;
- ``determinacy``: the Fisher blocks of small networks and the determinacy test
  (``fit.fisher_blocks`` + ``fit._judge_determinacy``);
- ``outlier_power``: can the estimated-scale rule flag anything (``fit.outlier_rule_has_power``);
- ``majority_scale``: the outlier-breakdown test with the noise estimated
  (``fit_result.majority_scale_check``: a fit of the majority at a far smaller scale; runs on
  successful results with at least 2 entries per unknown and at most 6,000 entries, so not at
  ``12x6`` or 120 units; ``12x40`` is the contamination families' size);
- ``uniqueness``: the uniqueness test (``fit_result.judge_fit``; older layouts ``fit.judge_fit``,
  ``fit.uniqueness_check`` / ``fit.uniqueness_test``).

Every repeat starts without the linearisation a previous call kept
(``selfcal.toa.verdict.leverage.normal_equations``: the repeats solve the same matrix, and a
kept one would make them cheaper than a first call).

``solve`` is the rest of the same call (initialisation, search, outlier refits, final fit,
covariance): every ratio is a stage over it, same call, medians over repeats; in wall-clock
time and in process CPU time (the second line of each case: on a shared, loaded machine the
wall-clock time of a stage also counts the time others' processes held the cores). ``checks`` is the
sum of the stages. Cases: ``12x6`` 3-D with both offsets (1 cm); the paper-004 workload, 120
units in the 30 x 30 x 12 m room, complete, both offsets: ``120t`` the thesis's simulation
(noise-free, one internal delay, ``benchmarks/bench_delays.py``'s setup) and ``120u`` with 1 mm
noise and a delay per unit; ``1000x1000`` 3-D (1 cm, 5 % missing, no offsets). Budget (issue 27): checks <= solve up to 1,000 measurements, <= 0.3 x
the solve at 1000 x 1000.

``cli``: ``calibrate toa`` on the 1000 x 1000 matrix (in this process) against ``solve_toa`` on
it: what the command adds around the solve (the recipe's time-order test, serialising and
writing the result), as a fraction of the solve.

Run::

    PYTHONPATH=src python benchmarks/bench_postsolve.py [--cases 12x6,120t,120u,1000x1000] [--repeats 5] [--cli 1000x1000]

``make bench`` (benchmarks/run_all.py) runs every case (1000 x 1000: 2 repeats).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import time
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

#: (module attribute in selfcal.toa.fit, selfcal.toa.fit_result or selfcal.toa.verdict.trust, stage name); missing names are skipped
STAGES = [
    ("fit", "_flag", "outlier_flagging"),
    ("fit", "_refit_cannot_flag", "outlier_flagging"),  # the rule's leverages on an exact fit
    ("fit", "leverages", "leverages"),
    ("fit_result", "leverages", "leverages"),
    ("fit_result", "geometry_test", "geometry_test"),
    ("trust", "permutation_test", "permutation_test"),
    ("fit_result", "fisher_blocks", "determinacy"),
    ("fit_result", "_judge_determinacy", "determinacy"),
    ("fit_result", "outlier_rule_has_power", "outlier_power"),
    ("fit_result", "majority_scale_check", "majority_scale"),
    ("fit", "uniqueness_check", "uniqueness"),
    ("fit", "uniqueness_test", "uniqueness"),
    ("fit", "judge_fit", "uniqueness"),
    ("fit_result", "judge_fit", "uniqueness"),
]
#: stages inside another one (counted in their parent's time, reported on their own)
NESTED = {"permutation_test"}


def _case(name: str, seed: int = 0) -> tuple[np.ndarray, int, str]:
    from selfcal.toa import toa_model

    g = np.random.default_rng(seed)
    if name == "12x6":
        r, s = g.uniform(0, 10, (12, 3)), g.uniform(0, 10, (6, 3))
        Y = toa_model(r, s, g.uniform(0, 3, 12), g.uniform(0, 3, 6)) + g.normal(0, 0.01, (12, 6))
        return Y, 3, "both"
    if name == "120t":  # the thesis's own simulation (bench_delays): noise-free, equal internal delays
        from selfcal.scenarios.units import make_units

        return make_units(120, room="large", rng=seed).ranges, 3, "both"
    if name == "120u":
        from selfcal.scenarios.units import make_units

        sc = make_units(120, room="large", noise_std=0.001 / 343.0, equal_delays=False, rng=seed)
        return sc.ranges, 3, "both"
    I, J = (int(v) for v in name.lower().split("x"))
    r, s = g.uniform(0, 1, (I, 3)) * [10, 10, 5], g.uniform(0, 1, (J, 3)) * [10, 10, 5]
    Y = toa_model(r, s) + g.normal(0, 0.01, (I, J))
    Y[g.random((I, J)) < 0.05] = np.nan
    return Y, 3, "none"


class _Clock:
    """Wrap the stage functions; accumulate the time spent in each (outermost call only)."""

    def __init__(self) -> None:
        import selfcal.toa.fit as fit
        import selfcal.toa.fit_result as fit_result
        import selfcal.toa.verdict.trust as trust

        self.mods = {"fit": fit, "fit_result": fit_result, "trust": trust}
        self.saved: list[tuple[Any, str, Any]] = []
        self.spent: dict[str, float] = {}
        self.cpu: dict[str, float] = {}
        self.depth = 0

    def _wrap(self, fn: Callable[..., Any], stage: str) -> Callable[..., Any]:
        def timed(*a: Any, **k: Any) -> Any:
            nested = stage in NESTED
            if self.depth and not nested:  # inside another stage (leverages inside the flagging)
                return fn(*a, **k)
            self.depth += 0 if nested else 1
            t, c = time.perf_counter(), time.process_time()
            try:
                return fn(*a, **k)
            finally:
                self.spent[stage] = self.spent.get(stage, 0.0) + time.perf_counter() - t
                self.cpu[stage] = self.cpu.get(stage, 0.0) + time.process_time() - c
                self.depth -= 0 if nested else 1

        return timed

    def __enter__(self) -> _Clock:
        for mod, attr, stage in STAGES:
            m = self.mods[mod]
            if hasattr(m, attr):
                fn = getattr(m, attr)
                self.saved.append((m, attr, fn))
                setattr(m, attr, self._wrap(fn, stage))
        return self

    def __exit__(self, *exc: object) -> None:
        for m, attr, fn in reversed(self.saved):
            setattr(m, attr, fn)


def _forget_linearisation() -> None:
    """Drop the linearisation kept from the last call (``leverage.normal_equations``): every
    repeat solves the same matrix, and a kept one would make the repeats cheaper than a first call."""
    import selfcal.toa.verdict.leverage as leverage

    leverage._LAST.clear()


def run_case(name: str, repeats: int) -> dict[str, Any]:
    """Medians over ``repeats`` calls of ``solve_toa`` (after one warm-up call) of every stage."""
    from selfcal.toa import solve_toa

    Y, dim, offsets = _case(name)
    warnings.simplefilter("ignore")
    solve_toa(Y, dim=dim, offsets=offsets, rng=0)  # warm-up (imports, caches)
    rows: list[dict[str, float]] = []
    cpu_rows: list[dict[str, float]] = []
    res = None
    for _ in range(repeats):
        _forget_linearisation()
        with _Clock() as clock:
            t, c = time.perf_counter(), time.process_time()
            res = solve_toa(Y, dim=dim, offsets=offsets, rng=0)
            total, total_cpu = time.perf_counter() - t, time.process_time() - c
        checks = sum(v for k, v in clock.spent.items() if k not in NESTED)
        rows.append({"total": total, "solve": total - checks, "checks": checks, **clock.spent})
        checks_cpu = sum(v for k, v in clock.cpu.items() if k not in NESTED)
        cpu_rows.append({"total": total_cpu, "solve": total_cpu - checks_cpu, "checks": checks_cpu, **clock.cpu})
    assert res is not None

    def summary(rs: list[dict[str, float]]) -> tuple[dict[str, float], dict[str, float]]:
        keys = sorted({k for r in rs for k in r})
        med = {k: statistics.median(r.get(k, 0.0) for r in rs) for k in keys}
        return med, {k: med[k] / med["solve"] for k in keys if k not in ("solve", "total")}

    med, ratios = summary(rows)
    med_cpu, ratios_cpu = summary(cpu_rows)
    return {"case": name, "shape": list(Y.shape), "measurements": int(np.isfinite(Y).sum()), "dim": dim,
            "offsets": offsets, "repeats": repeats, "median_s": med, "over_solve": ratios,
            "median_cpu_s": med_cpu, "cpu_over_solve": ratios_cpu,
            "verdict": res.verdict_message, "outliers": int(res.outliers.sum()) if res.outliers is not None else 0}


def run_cli(name: str) -> dict[str, Any]:
    """``calibrate toa`` in this process against ``solve_toa`` on the same matrix (once each).

    ``around_over_solve`` is what the command adds to the solve (reading, the time-order
    test of the recipe, serialising and writing the result) over the solve itself.
    """
    import contextlib
    import io
    import tempfile

    from selfcal.cli import main as cli
    from selfcal.toa import solve_toa

    Y, dim, offsets = _case(name)
    warnings.simplefilter("ignore")
    with tempfile.TemporaryDirectory() as tmp:
        src = Path(tmp) / "m.npy"
        np.save(src, Y)
        t = time.perf_counter()
        solve_toa(Y, dim=dim, offsets=offsets, rng=0)
        solve = time.perf_counter() - t
        t = time.perf_counter()
        with contextlib.redirect_stdout(io.StringIO()), contextlib.suppress(SystemExit):
            cli(["calibrate", "toa", str(src), "--offsets", offsets, "--dim", str(dim), "--out",
                 str(Path(tmp) / "r.json")], standalone_mode=False)
        total = time.perf_counter() - t
        size = sum(f.stat().st_size for f in Path(tmp).iterdir() if f.name.startswith("r."))
    return {"case": f"cli {name}", "solve_s": solve, "cli_s": total, "around_over_solve": (total - solve) / solve,
            "output_bytes": size}


def main(out_dir: Path | None = None, cases: str = "12x6,120t,120u,1000x1000", repeats: int = 5,
         cli: str = "1000x1000") -> dict[str, Any]:
    """Run the cases, print one line each, write ``postsolve.json`` under ``out_dir``."""
    report: dict[str, Any] = {"name": "postsolve", "load_average_at_start": list(os.getloadavg()),
                              "OPENBLAS_NUM_THREADS": os.environ.get("OPENBLAS_NUM_THREADS"), "cases": []}
    for name in filter(None, (c.strip() for c in cases.split(","))):
        reps = min(repeats, 2) if "1000" in name else repeats
        row = run_case(name, reps)
        report["cases"].append(row)
        parts = ", ".join(f"{k} {v:.3f}" for k, v in sorted(row["over_solve"].items()))
        print(f"[postsolve] {name} ({row['measurements']} measurements): solve {row['median_s']['solve']:.3f} s; "
              f"over the solve: {parts}")
        parts = ", ".join(f"{k} {v:.3f}" for k, v in sorted(row["cpu_over_solve"].items()))
        print(f"[postsolve] {name} CPU: solve {row['median_cpu_s']['solve']:.3f} s; over the solve: {parts}")
    for name in filter(None, (c.strip() for c in cli.split(","))):
        row = run_cli(name)
        report.setdefault("cli", []).append(row)
        print(f"[postsolve] calibrate toa {name}: {row['cli_s']:.2f} s against solve_toa {row['solve_s']:.2f} s "
              f"(around the solve {row['around_over_solve']:.2f} x the solve; output {row['output_bytes'] / 1e6:.1f} MB)")
    report["load_average_at_end"] = list(os.getloadavg())
    if out_dir is not None:
        Path(out_dir).mkdir(parents=True, exist_ok=True)
        (Path(out_dir) / "postsolve.json").write_text(json.dumps(report, indent=2, default=float))
    return report


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cases", default="12x6,120t,120u,1000x1000")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--cli", default="1000x1000", help="cases of the calibrate toa row ('' = none)")
    ap.add_argument("--out", type=Path, default=None)
    a = ap.parse_args()
    main(a.out, a.cases, a.repeats, a.cli)
