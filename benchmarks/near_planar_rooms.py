"""Benchmark "near-planar rooms": the pipeline's defaults on simulated conference rooms (issue 27).

Per seed: ``selfcal simulate conference`` (8 x 7 x 3 m, 10 units, RT60 0.4 s, SNR 30 dB,
16 kHz, image order 2), the recording's heights removed, ``selfcal pipeline`` with its
defaults (``--dim auto``). Counted per layout: exit 0 with a unit beyond 3 of its own error
bars (squared Mahalanobis distance of the aligned 3-D position above chi-square(3)'s
0.9973 quantile), and of those the ones not listed ambiguous; exit 0 in 2-D; exit 0 in 3-D
with every unit inside its bars; flagged (exit != 0). ``widened``: the bar widening factors
(median, max over units) where the planarity test's bootstrap widened the 3-D answer's bars.

Run: ``OPENBLAS_NUM_THREADS=1 PYTHONPATH=src .venv/bin/python benchmarks/near_planar_rooms.py
LAYOUT FIRST LAST [WORKDIR]`` (seeds FIRST..LAST-1; about 2.5 s per seed). One JSON line per
seed, then the summary.
"""

from __future__ import annotations

import json
import re
import sys
import tempfile
from pathlib import Path

import numpy as np
from click.testing import CliRunner

from selfcal.cli import main
from selfcal.geometry import align


def outside(data: dict, truth: dict) -> set[str]:
    """Units whose aligned 3-D error exceeds 3 of its own error bars (chi-square(3) 0.9973)."""
    est = np.vstack([data["receivers"], data["sources"]]).astype(float)
    true = np.vstack([truth["receivers"], truth["senders"]]).astype(float)
    cov = np.concatenate([np.asarray(data["receiver_cov"], float), np.asarray(data["source_cov"], float)])
    names = list(data["receiver_names"]) + list(data["sender_names"])
    tr = align(est, true, reflection=True)
    err = tr.apply(est) - true
    Rm = np.asarray(tr.rotation)
    m2 = [e @ np.linalg.solve(Rm @ c @ Rm.T, e) for e, c in zip(err, cov, strict=True)]
    return {n for n, v in zip(names, m2, strict=True) if v > 14.16}


def one(layout: str, seed: int, work: Path) -> dict:
    """The pipeline's outcome on one simulated room."""
    rec = work / f"{layout}{seed}"
    res = CliRunner().invoke(main, ["simulate", "conference", "--units", "10", "--room", "8x7x3", "--rt60", "0.4",
                                    "--snr", "30", "--seed", str(seed), "--layout", layout, "--sample-rate", "16000",
                                    "--max-order", "2", "--out", str(rec)])
    assert res.exit_code == 0, res.output
    (rec / "heights.json").unlink(missing_ok=True)
    out = work / f"{layout}{seed}.json"
    res = CliRunner().invoke(main, ["pipeline", str(rec), "--out", str(out)])
    row: dict = {"layout": layout, "seed": seed, "exit": res.exit_code}
    if out.exists():
        data = json.loads(out.read_text())
        truth = json.loads((rec / "truth.json").read_text())
        row.update(dim=data["dim"], position_max=data["errors"]["position_max"])
        # bars widened by the planarity bootstrap's mean-square error (dimension_test): its note
        wide = [m for n in data.get("notes", []) if (m := re.search(r"bars x(\S+) median, x(\S+) max", n))]
        if wide:
            row.update(widened=[float(wide[0].group(1)), float(wide[0].group(2))])
        if data["dim"] == 3:
            o = outside(data, truth)
            row.update(outside=sorted(o),
                       unlisted=sorted(o - set(data["ambiguous_receivers"]) - set(data["ambiguous_senders"])))
    return row


def summary(rows: list[dict]) -> dict:
    """Counts over the rows."""
    ok = [r for r in rows if r["exit"] == 0]
    return {"draws": len(rows), "exit0_outside": sum(bool(r.get("outside")) for r in ok),
            "exit0_outside_unlisted": sum(bool(r.get("unlisted")) for r in ok),
            "exit0_2d": sum(r.get("dim") == 2 for r in ok),
            "exit0_3d_covered": sum(r.get("dim") == 3 and not r.get("outside") for r in ok),
            "flagged": len(rows) - len(ok)}


if __name__ == "__main__":
    layout, first, last = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(sys.argv[4]) if len(sys.argv) > 4 else Path(tmp)
        rows = []
        for s in range(first, last):
            rows.append(one(layout, s, work))
            print(json.dumps(rows[-1]), flush=True)
        print(json.dumps(summary(rows)))
