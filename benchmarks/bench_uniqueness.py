"""Benchmark "uniqueness": the cost of the uniqueness and forced-model tests as a fraction of the solve.

Issue 27 budget: every check after the solve together costs at most the solve itself up to
1000 measurements and at most 0.3x the solve at 1000 x 1000; these two tests should be a
small part of that. Same run, same process, CPU time (``time.process_time``):

- ``solve``: ``solve_toa`` end to end (noise unknown), with the uniqueness test inside it
  (:func:`selfcal.toa.verdict.uniqueness.judge_fit`, timed by a wrapper) -- ``uniqueness_share`` is
  its time over the rest of the solve;
- ``forced_model``: :func:`selfcal.toa.verdict.model_test.forced_model_test` on the result (what
  ``calibrate toa`` runs after the solve when the model is not ``auto``: offsets "none"
  against "both"), over the same solve.

Cases: ``12x6`` (3-D, both offsets, 1 mm, the minimal 004 network, 5 draws), ``120 units``
(paper 004 workload: a microphone and a loudspeaker 5 cm apart per unit in a 10 x 10 x 3 m
room, both offsets, complete, 1 mm; as ``bench_toa.py`` part 2), ``1000x1000`` (3-D, no
offsets, 1 cm, 5 % missing, one draw). ``SELFCAL_BENCH_UNIQ_CASES=12x6,units120`` runs a subset.

Usage::

    PYTHONPATH=src python benchmarks/bench_uniqueness.py [--out DIR]
"""

from __future__ import annotations

import argparse
import json
import os
import time
import warnings
from pathlib import Path
from typing import Any

import numpy as np

CASES = ("12x6", "units120", "1000x1000")


def _scene(case: str, seed: int) -> tuple[np.ndarray, dict[str, Any]]:
    from selfcal.toa import toa_model

    g = np.random.default_rng(seed)
    if case == "12x6":
        r, s = g.uniform(0, 10, (12, 3)), g.uniform(0, 10, (6, 3))
        Y = toa_model(r, s, g.uniform(0, 3, 12), g.uniform(0, 3, 6)) + g.normal(0, 0.001, (12, 6))
        return Y, {"dim": 3, "offsets": "both"}
    if case == "units120":
        U = 120
        mic = g.uniform(0, 1, (U, 3)) * [10.0, 10.0, 3.0]
        spk = mic + g.normal(0, 0.05, (U, 3))
        Y = toa_model(mic, spk, g.uniform(0, 0.020 * 343, U), g.uniform(0, 0.030 * 343, U)) + g.normal(0, 0.001, (U, U))
        return Y, {"dim": 3, "offsets": "both"}
    I = J = 1000
    r, s = g.uniform(0, 10, (I, 3)) * [1, 1, 0.5], g.uniform(0, 10, (J, 3)) * [1, 1, 0.5]
    Y = toa_model(r, s) + g.normal(0, 0.01, (I, J))
    Y[g.random((I, J)) < 0.05] = np.nan
    return Y, {"dim": 3, "offsets": "none"}


def main(out: Path | None = None) -> dict[str, Any]:
    """Run the cases; print one line each; write ``uniqueness.json`` under ``out``; return the rows."""
    import selfcal.toa.fit as fit
    from selfcal.toa import solve_toa
    from selfcal.toa.verdict.model_test import forced_model_test

    warnings.simplefilter("ignore")
    spent = [0.0]
    inner = fit.judge_fit

    def timed(*args: Any, **kw: Any) -> Any:
        t = time.process_time()
        got = inner(*args, **kw)
        spent[0] += time.process_time() - t
        return got

    env = os.environ.get("SELFCAL_BENCH_UNIQ_CASES")
    cases = CASES if env is None else tuple(c for c in env.split(",") if c.strip())
    rows: dict[str, Any] = {}
    fit.judge_fit = timed  # type: ignore[assignment]
    try:
        for case in cases:
            draws = 5 if case == "12x6" else 1
            tot = uni = forced = 0.0
            flagged = 0
            for k in range(draws):
                Y, kw = _scene(case, 100 + k)
                spent[0] = 0.0
                t0 = time.process_time()
                res = solve_toa(Y, rng=0, covariance=case != "1000x1000", **kw)
                tot += time.process_time() - t0
                uni += spent[0]
                flagged += not res.success
                # the CLI's forced-model test (offsets "none" against "both"; "both" has nothing larger)
                ok_r, ok_s = np.isfinite(res.receivers).all(1), np.isfinite(res.sources).all(1)
                Yf = np.where(np.isfinite(res.residuals) & ~res.outliers, Y, np.nan)[np.ix_(ok_r, ok_s)]
                t0 = time.process_time()
                forced_model_test(Yf, res.receivers[ok_r], res.sources[ok_s],
                                  None if res.receiver_offsets is None else res.receiver_offsets[ok_r],
                                  None if res.source_offsets is None else res.source_offsets[ok_s],
                                  offsets=res.offsets)
                forced += time.process_time() - t0
            solve_only = (tot - uni) / draws
            row = {"draws": draws, "solve_cpu_s": solve_only, "uniqueness_cpu_s": uni / draws,
                   "uniqueness_over_solve": uni / max(tot - uni, 1e-12), "forced_model_cpu_s": forced / draws,
                   "forced_model_over_solve": forced / max(tot - uni, 1e-12), "flagged": flagged}
            rows[case] = row
            print(f"[uniqueness] {case}: solve {solve_only:.3g} s CPU, uniqueness test {uni / draws:.3g} s "
                  f"({row['uniqueness_over_solve']:.3f}x), forced-model test {forced / draws:.3g} s "
                  f"({row['forced_model_over_solve']:.3f}x), flagged {flagged}/{draws}", flush=True)
    finally:
        fit.judge_fit = inner  # type: ignore[assignment]
    if out is not None:
        out.mkdir(parents=True, exist_ok=True)
        (out / "uniqueness.json").write_text(json.dumps(rows, indent=1))
    return rows


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=None)
    main(**vars(ap.parse_args()))
