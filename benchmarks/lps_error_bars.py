"""Squared normalised anchor errors of ``selfcal calibrate toa`` with its defaults on the raw LPS flights.

Each flight's raw ``d`` matrix is written as a CSV and run through the CLI; the anchors are
aligned onto the motion-capture positions by the best rigid motion (reflection allowed) and
each anchor's error is judged against its stated covariance, rotated with the alignment
(95 % bound of chi-square with 3 dof: 7.8).

Usage::

    PYTHONPATH=src python benchmarks/lps_error_bars.py [--data ../shared/data/lps]
"""

from __future__ import annotations

import argparse
import json
import tempfile
import warnings
from pathlib import Path

import numpy as np
from click.testing import CliRunner

from selfcal.cli import main
from selfcal.datasets import load_lps
from selfcal.geometry import align


def run(data: Path) -> None:
    warnings.simplefilter("ignore")
    for name in ("data4", "data5"):
        flight = load_lps(data / f"{name}.mat")
        d = Path(tempfile.mkdtemp())
        np.savetxt(d / "r.csv", flight.ranges, delimiter=",")
        res = CliRunner().invoke(main, ["calibrate", "toa", str(d / "r.csv"), "--out", str(d / "o.json")])
        out = json.loads((d / "o.json").read_text())
        R, C = np.array(out["receivers"], float), np.array(out["receiver_cov"], float)
        al = align(R, flight.anchors_true, reflection=True)
        E, Q = al.apply(R) - flight.anchors_true, al.rotation
        z2 = [float(e @ np.linalg.solve(Q @ c @ Q.T, e)) for e, c in zip(E, C, strict=True)]
        print(f"{name}: exit {res.exit_code}, offsets {out['offsets']}, anchor RMSE "
              f"{np.sqrt(np.mean(np.sum(E**2, 1))):.3f} m, stated std RMS "
              f"{np.sqrt(np.mean(np.trace(C, axis1=1, axis2=2))):.3f} m, squared normalised errors "
              f"{np.round(z2, 1).tolist()} (95 % bound 7.8)")


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "lps")
    run(ap.parse_args().data)
