"""``calibrate toa`` chooses the dimension by default (``--dim auto``) and says so.

A layout in a plane gets 2-D positions (no invented heights, issue 32), a layout with a
resolved thickness keeps 3-D; the choice, its F statistic and its level are printed and in
the JSON. Six seeds per family: the F test at level 1e-3 against 1 cm noise on a 0.5-8 m
thickness (3-D) or a 2 mm jitter (planar) is decided by orders of magnitude, so every draw
must go the right way.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
from click.testing import CliRunner

from selfcal.cli import main
from selfcal.toa.verdict.planarity import PLANAR_ALPHA


def _ranges(seed: int, planar: bool) -> np.ndarray:
    rng = np.random.default_rng(seed)
    R, S = rng.uniform(0, 8, (8, 3)), rng.uniform(0, 8, (20, 3))
    if planar:
        R[:, 2] = 1.0
        S[:, 2] = 1.0 + rng.normal(0, 0.002, 20)
    return np.linalg.norm(R[:, None] - S[None], axis=-1) + rng.normal(0, 0.01, (8, 20))


@pytest.mark.parametrize("planar", [False, True])
@pytest.mark.parametrize("seed", range(3))
def test_default_dimension_follows_the_data(tmp_path, seed, planar):
    path, out = tmp_path / "m.csv", tmp_path / "r.json"
    np.savetxt(path, _ranges(100 + seed, planar), delimiter=",")
    res = CliRunner().invoke(main, ["calibrate", "toa", str(path), "--recipe", "none", "-o", str(out)])
    want = 2 if planar else 3
    data = json.loads(out.read_text())
    assert res.exit_code == 0 and np.shape(data["receivers"])[1] == want, res.output
    assert f"dim {want} (auto: 3-D vs 2-D F =" in res.output and f"level {PLANAR_ALPHA:g}" in res.output
    assert data["selection"]["dim"]["chosen"] == want


def test_help_states_the_dimension_test_level():
    text = " ".join(CliRunner().invoke(main, ["calibrate", "toa", "--help"]).output.split())
    assert f"at level {PLANAR_ALPHA:g}" in text and "--dim [2|3|auto]" in text and "default: auto" in text
