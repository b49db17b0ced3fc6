"""Near-planar rooms through the pipeline's defaults: 2-D, or z within its own error bars (issue 27).

The boundary desks of :mod:`selfcal.scenarios.conference` (8 x 7 x 3 m, 10 units, 16 kHz):
loudspeakers exactly coplanar, microphones within 1 cm of their plane, 0.1 us of detection
noise. The layout is a few mm thick, below the 3-D fit's bending scale
``sqrt(noise x extent)`` (about 1 cm): the heights enter the ranges only at second order,
and a 3-D answer comes back bent by 1-2 cm against linearised z bars of 2-8 mm. Before the
thickness chi-square took the heights at second order
(``selfcal.toa.verdict.select._thickness_cov``), 26 of 40 seeds (0-39) ended 3-D at
exit 0 with units beyond 3 of their error bars; now 6 (``KNOWN_BENT``), the other 34 2-D
(horizontal error <= 0.55 mm). The F test's bootstrap null does not change them (below):
they need honest error bars for a bent 3-D fit, not a planarity decision. The property tested is the promise of exit 0 (issue 27):
no unit outside 3 of its own error bars (squared Mahalanobis distance of the aligned 3-D
position above chi-square(3)'s 0.9973 quantile) unless the result lists it as ambiguous; a 2-D answer is judged on the 004 requirement of its in-plane positions.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from click.testing import CliRunner

from selfcal.cli import main

from .test_pipeline import _outside_error_bars

# Seeds 6, 7 and 12 ended 3-D, exit 0, with units outside 3 error bars not listed ambiguous
# (before the second-order thickness covariances; 12 until the search's scaled starts too).
DEFAULT_SEEDS = (6, 7, 12)
# Seeds of 0-39 that still end 3-D at exit 0 with units beyond 3 error bars (not listed
# ambiguous), measured on main after the search's scaled starts joined 8-10-unit races
# (`benchmarks/near_planar_rooms.py boundary 0 40`: 6 of 40; 8 before that change, with
# 12, 16, 27, 35 instead of 3, 22): heights 1.7-4.1 cm off, F significant.
# Their ML fits are bent (seed 11 started at the truth comes back to the same answer).
# The parametric bootstrap of the F test's null (`selfcal.toa.verdict.planarity.
# bartlett_corrected`) runs on 5 of them (31: F at 4.7 critical values, out of its band)
# and keeps them 3-D: Bartlett factors 0.95-1.29, corrected p 3e-8 to 2e-6; their F
# (8.9-17.9, and 5.8-16.9 in the 2-D seeds 0, 6, 7) is beyond all 20 replicates simulated
# from each one's 2-D fit (replicate F at most 2.0-3.7). The data do reject the plane: the microphones are +-8 mm
# about the loudspeakers' plane (thickness std 4 mm in seed 11) and 6-13 cm from their own
# loudspeaker, so the two-way ranges carry their heights at 0.3 mm against 10-20 um of
# noise. What fails is the 3-D fit's linearised z error bars, not the planarity
# decision: the truth lies inside the fit's likelihood region (its likelihood ratio
# against the ML fit 85 and 35 on 54 position parameters in seeds 11 and 3, below the
# chi-square 0.9973 quantile 87), 1.7-4.1 cm away against bars of a few mm.
# Profile-likelihood error bars would not fix them either (benchmarks/near_planar_profile.py,
# docs/design.md): per-unit height intervals at chi-square(1)'s 0.9973 quantile cover every
# unit only in 31; in the others 5-16 units' true heights have a profile likelihood ratio
# above 9 (up to 14-53): the ML fit's bias along the bend is not in the likelihood's shape.
KNOWN_BENT = {3, 11, 20, 22, 24, 31}


def _boundary(tmp: Path, seed: int) -> tuple[int, dict, dict]:
    rec = tmp / f"rec{seed}"
    res = CliRunner().invoke(main, ["simulate", "conference", "--units", "10", "--room", "8x7x3", "--rt60", "0.4",
                                    "--snr", "30", "--seed", str(seed), "--layout", "boundary", "--sample-rate",
                                    "16000", "--max-order", "2", "--out", str(rec)])
    assert res.exit_code == 0, res.output
    (rec / "heights.json").unlink()  # blind: the pipeline's own decision
    out = tmp / f"result{seed}.json"
    res = CliRunner().invoke(main, ["pipeline", str(rec), "--out", str(out)])
    data = json.loads(out.read_text()) if out.exists() else {}
    return res.exit_code, data, json.loads((rec / "truth.json").read_text())


def _check(code: int, data: dict, truth: dict) -> None:
    if code != 0:
        return  # flagged: not a confident answer
    if data["dim"] == 2:
        assert data["errors"]["horizontal_only"] and data["errors"]["position_max"] < 0.10
        return
    ambiguous = set(data["ambiguous_receivers"]) | set(data["ambiguous_senders"])
    assert _outside_error_bars(data, truth) <= ambiguous


@pytest.mark.parametrize("seed", DEFAULT_SEEDS)
def test_boundary_desks_are_2d_or_within_error_bars(tmp_path, seed):
    _check(*_boundary(tmp_path, seed))


@pytest.mark.slow
@pytest.mark.parametrize("seed", [s for s in range(40) if s not in DEFAULT_SEEDS])
def test_boundary_desks_are_2d_or_within_error_bars_slow(tmp_path, seed):
    if seed in KNOWN_BENT:
        pytest.xfail("a bent 3-D ML fit the second-order correction does not catch (KNOWN_BENT, docs/design.md)")
    _check(*_boundary(tmp_path, seed))
