"""Spec of ``selfcal calibrate toa`` (DESIGN.md CLI contract)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from click.testing import CliRunner

from selfcal.cli import main
from selfcal.metrics import aligned_rmse
from selfcal.toa import toa_model

DESIGN_KEYS = {
    "receivers", "sources", "receiver_offsets", "source_offsets", "receiver_cov", "source_cov",
    "residual_rms", "converged", "iterations", "method",
}


@pytest.fixture
def scene():
    rng = np.random.default_rng(3)
    r = rng.uniform(-5, 5, (8, 2))
    s = rng.uniform(-7, 7, (11, 2))
    return r, s, toa_model(r, s) + rng.normal(0, 0.01, (8, 11))


def run(*args):
    return CliRunner().invoke(main, ["calibrate", "toa", *map(str, args)])


def test_csv_with_missing_entries_gives_the_design_json_and_a_plot(tmp_path, scene):
    r, s, Y = scene
    Y = Y.copy()
    Y[0, 3] = np.nan
    path = tmp_path / "m.csv"
    np.savetxt(path, Y, delimiter=",")
    out, fig = tmp_path / "res.json", tmp_path / "fig.png"
    res = run(path, "--dim", 2, "--out", out, "--plot", fig)
    assert res.exit_code == 0, res.output
    data = json.loads(out.read_text())
    assert DESIGN_KEYS <= set(data)
    assert np.array(data["receivers"]).shape == (8, 2)
    assert np.array(data["source_cov"]).shape == (11, 2, 2)
    assert data["receiver_offsets"] is None
    err = aligned_rmse(np.array(data["receivers"]), r, np.array(data["sources"]), s)
    assert err.rmse_receivers < 0.05
    assert fig.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert "residual RMS" in res.output


def test_seconds_and_offsets_from_npy(tmp_path):
    rng = np.random.default_rng(5)
    r, s = rng.uniform(-5, 5, (10, 3)), rng.uniform(-7, 7, (14, 3))
    dr, o = rng.normal(0, 1, 10), rng.normal(0, 1, 14)
    path = tmp_path / "t.npy"
    np.save(path, toa_model(r, s, dr, o) / 343.0)
    out = tmp_path / "res.json"
    res = run(path, "--speed", 343, "--offsets", "both", "--out", out)
    assert res.exit_code == 0, res.output
    data = json.loads(out.read_text())
    assert data["source_offsets"][0] == 0.0
    np.testing.assert_allclose(np.array(data["source_offsets"]) * 343.0, o - o[0], atol=1e-5)
    assert data["units"]["offsets"] == "s"


@pytest.mark.parametrize(
    "content, message",
    [
        ("1,2,3\n4,-5,6\n7,8,9\n1,2,3\n", "negative"),
        ("1,2,x\n", "not a number"),
        ("1,2,3,4\n1,2,3,4\n", "too-few"),
        ("1,inf,3,4\n1,2,3,4\n1,2,3,4\n1,2,3,4\n", "infinite"),
    ],
)
def test_bad_input_is_one_line_exit_2_and_no_file(tmp_path, content, message):
    path = tmp_path / "bad.csv"
    path.write_text(content)
    out = tmp_path / "res.json"
    res = run(path, "--dim", 2, "--out", out)
    assert res.exit_code == 2
    err = res.stderr if hasattr(res, "stderr") else res.output
    assert message in err
    assert len(err.strip().splitlines()) == 1
    assert not out.exists()


def test_missing_file_is_exit_2(tmp_path):
    out = tmp_path / "res.json"
    res = run(tmp_path / "nope.csv", "--out", out)
    assert res.exit_code == 2
    assert not out.exists()
