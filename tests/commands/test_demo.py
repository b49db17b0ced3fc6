"""`selfcal demo` (what `make demo` runs): paper 004's requirements hold end to end (issue 7)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from click.testing import CliRunner

from selfcal.cli import main


def _run_demo(out, seed: int, extra: tuple[str, ...] = ()) -> tuple[int, str, dict]:
    res = CliRunner().invoke(main, ["demo", "--out", str(out), "--seed", str(seed), *extra])
    data = json.loads((out / "result.json").read_text()) if (out / "result.json").is_file() else {}
    return res.exit_code, res.output, data


def _check(code: int, text: str, data: dict) -> None:
    assert code == 0, text
    pass_lines = [ln for ln in text.splitlines() if ln.startswith(("PASS", "FAIL"))]
    assert len(pass_lines) == 1 and pass_lines[0].startswith("PASS")
    err = data["errors"]
    assert err["position_max"] <= 0.10 and err["timing_max"] <= 58e-6  # 004: 10 cm, 58 us
    assert data["detections_missed"] == 0
    assert np.array(data["receivers"], dtype=float).shape == (20, 3)
    assert np.array(data["toa_matrix"], dtype=float).shape == (20, 20)


def test_demo_one_seed_passes_and_writes_its_files(tmp_path):
    out = tmp_path / "demo-output"
    code, text, data = _run_demo(out, 0)
    _check(code, text, data)
    for name in ("map.png", "timing.png"):
        assert (out / name).stat().st_size > 5000
    for word in ("position error", "timing error", "time detect", "time calibrate", "time simulate"):
        assert word in text


@pytest.mark.slow
@pytest.mark.parametrize("seed", [1, 2, 3, 4, 5])
def test_demo_passes_for_five_seeds(tmp_path, seed):
    _check(*_run_demo(tmp_path / "demo-output", seed))


@pytest.mark.slow
@pytest.mark.parametrize("layout", ["tiered", "stem"])
def test_demo_3d_layouts_pass_without_jitter(tmp_path, layout):
    """Tiered rooms and stem microphones are solved in 3-D (no known heights)."""
    code, text, data = _run_demo(tmp_path / "demo-output", 0, ("--layout", layout, "--jitter", "0"))
    _check(code, text, data)
    assert data["method"].startswith("3d")
