"""Near-planar rooms through the pipeline's defaults: 2-D, or z within its own error bars (issue 27).

The boundary desks of :mod:`selfcal.scenarios.conference` (8 x 7 x 3 m, 10 units, 16 kHz):
loudspeakers exactly coplanar, microphones within 1 cm of their plane, 0.1 us of detection
noise. The layout is a few mm thick, below the 3-D fit's bending scale
``sqrt(noise x extent)`` (about 1 cm): the heights enter the ranges only at second order,
and a 3-D answer comes back bent by 1-2 cm against linearised z bars of 2-8 mm. Before the
thickness chi-square took the heights at second order
(``selfcal.toa.verdict.select._thickness_cov``), 26 of 40 seeds (0-39) ended 3-D at
exit 0 with units beyond 3 of their error bars; now 6 (``KNOWN_BENT``), the other 34 2-D
(horizontal error <= 0.55 mm). The F test's bootstrap null does not change their
decision (below): they need honest error bars for a bent 3-D fit, which the bootstrap's
mean-square error now gives 5 of them. The property tested is the promise of exit 0 (issue 27):
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
# Seeds of 0-39 whose 3-D answer is bent (heights 1.7-4.1 cm off, F significant; their ML
# fits are bent: seed 11 started at the truth comes back to the same answer): 3, 11, 20,
# 22, 24, 31 (`benchmarks/near_planar_rooms.py boundary 0 40`, 6 of 40 on main). The data
# reject the plane (F beyond every replicate of the F test's parametric bootstrap), so
# they stay 3-D; what failed is the linearised z error bars. Where that bootstrap runs
# (the second-order band: 3, 11, 20, 22, 24) and the answer stays 3-D, the bars now add
# the 3-D estimator's mean-square error at the 2-D fit from the same replicates
# (`selfcal.toa.verdict.select._widened`), which covers every unit of those five (bars
# x3.8-4.9 median, x6.6-15.5 max over units). Seed 31 has F at 4.7 critical values, out of
# the bootstrap's band (4): no replicate runs, its bars are the linearised ones and 5 of 20
# units stay beyond 3 of them. Profile-likelihood bars would not cover it either way
# (benchmarks/near_planar_profile.py, docs/design.md).
KNOWN_BENT = {31}
# a bent room whose bars the bootstrap widened (the default run's representative)
WIDENED_SEED = 11


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
        pytest.xfail("a bent 3-D ML fit outside the bootstrap's F band (KNOWN_BENT, docs/design.md)")
    _check(*_boundary(tmp_path, seed))


def test_a_bent_room_keeps_z_with_bars_that_cover_it_and_says_why(tmp_path):
    """Seed 11 (thickness std 4 mm, F significant after the bootstrap's correction): 3-D at
    exit 0, 4.1 cm off in height against linearised bars of a few mm before; the bars now
    include the bootstrap's mean-square error at the 2-D fit and the result says so (a note
    in the pipeline's JSON): every unit within 3 of its bars."""
    code, data, truth = _boundary(tmp_path, WIDENED_SEED)
    assert code == 0 and data["dim"] == 3
    assert any("error bars widened" in n for n in data["notes"])
    assert not _outside_error_bars(data, truth)
