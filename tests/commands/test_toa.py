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


def _scene3d(seed=11, I=7, J=10, noise=0.01):
    rng = np.random.default_rng(seed)
    r, s = rng.uniform(0, 6, (I, 3)), rng.uniform(0, 6, (J, 3))
    return rng, r, s, toa_model(r, s) + noise * rng.standard_normal((I, J))


def test_known_file_puts_the_result_in_that_frame(tmp_path):
    _, r, s, Y = _scene3d()
    path = tmp_path / "m.csv"
    np.savetxt(path, Y, delimiter=",")
    known = tmp_path / "known.csv"
    known.write_text("".join(",".join([f"r{i}", *(repr(float(v)) for v in r[i])]) + "\n" for i in range(4)))
    out = tmp_path / "res.json"
    res = run(path, "--known", known, "--out", out)
    assert res.exit_code == 0, res.output
    data = json.loads(out.read_text())
    np.testing.assert_array_equal(np.array(data["receivers"])[:4], r[:4])
    assert data["frame"]["determined"] is True
    # no alignment: the other nodes are in the room's frame (1 cm noise, 6 m room)
    assert np.abs(np.array(data["sources"]) - s).max() < 0.1
    assert "frame fully determined" in res.output


def test_frame_option_and_its_report(tmp_path):
    _, r, s, Y = _scene3d(12)
    path = tmp_path / "m.csv"
    np.savetxt(path, Y, delimiter=",")
    out = tmp_path / "res.json"
    res = run(path, "--frame", "origin=r0,x=r1,xy=r2", "--out", out)
    assert res.exit_code == 0, res.output
    R = np.array(json.loads(out.read_text())["receivers"])
    assert np.all(R[0] == 0) and np.all(R[1, 1:] == 0) and R[2, 2] == 0 and R[2, 1] > 0
    assert "z sign" in res.output  # 3-D without z=D: the choice taken is reported


@pytest.mark.parametrize("args, message", [
    (("--frame", "origin=r0,x=r0,xy=r2"), "distinct"),
    (("--frame", "origin=r0,x=r1,xy=r2", "--known", "K"), "exclusive"),
    (("--known", "K"), "r99"),
])
def test_bad_frame_or_known_is_exit_2(tmp_path, args, message):
    _, r, s, Y = _scene3d(13)
    path = tmp_path / "m.csv"
    np.savetxt(path, Y, delimiter=",")
    (tmp_path / "K").write_text("r99,0,0,0\n")
    out = tmp_path / "res.json"
    res = run(path, *[tmp_path / a if a == "K" else a for a in args], "--out", out)
    assert res.exit_code == 2, res.output
    err = res.stderr if hasattr(res, "stderr") else res.output
    assert message in err and len(err.strip().splitlines()) == 1
    assert not out.exists()


def test_data_that_fit_no_geometry_exit_1_with_fail(tmp_path):
    """A uniform random matrix with the noise given: the chi-square test rejects the fit."""
    rng = np.random.default_rng(0)
    path = tmp_path / "m.csv"
    np.savetxt(path, rng.uniform(1, 10, (8, 8)), delimiter=",")
    out = tmp_path / "res.json"
    res = run(path, "--dim", 2, "--noise", 0.01, "--method", "nls", "--out", out)
    assert res.exit_code == 1, res.output
    assert "FAIL:" in res.output
    assert out.exists()  # the result is still written, marked untrustworthy


def test_auto_modes_pass_through(tmp_path):
    _, r, s, Y = _scene3d(14)
    path = tmp_path / "m.csv"
    np.savetxt(path, Y, delimiter=",")
    out = tmp_path / "res.json"
    res = run(path, "--offsets", "auto", "--out", out)
    assert res.exit_code in (0, 1), res.output


def test_moving_tag_recipe_rejects_spikes_and_drops_positions(tmp_path):
    rng = np.random.default_rng(2)
    anchors = rng.uniform(0, 5, (6, 3))
    t = np.linspace(0, 30, 240)
    tag = np.c_[2.5 + 2 * np.cos(t / 3), 2.5 + 2 * np.sin(t / 2), 1.5 + np.sin(t / 5)]
    Y = toa_model(anchors, tag) + 0.02 * rng.standard_normal((6, 240))
    spikes = [(1, 40), (3, 100), (4, 170)]
    for i, j in spikes:
        Y[i, j] += 1.2
    Y[2:, 60] = np.nan  # a position with only 2 ranges
    path = tmp_path / "m.csv"
    np.savetxt(path, Y, delimiter=",")
    out = tmp_path / "res.json"
    res = run(path, "--recipe", "moving-tag", "--out", out)
    assert res.exit_code == 0, res.output
    data = json.loads(out.read_text())
    assert 60 in data["recipe"]["dropped_sources"]
    assert data["recipe"]["n_rejected"] >= len(spikes)
    S = np.array(data["sources"], dtype=float)
    assert np.isnan(S[60]).all()
    # the result's masks and drops are in the input's numbering (6 x 240), not the kept columns'
    assert np.array(data["outliers"]).shape == (6, 240) and np.array(data["residuals"]).shape == (6, 240)
    assert set(data["recipe"]["dropped_sources"]) <= set(data["dropped_sources"])
    assert set(data["dropped_sources"]) == set(np.nonzero(np.isnan(S).any(axis=1))[0])
    err = aligned_rmse(np.array(data["receivers"]), anchors)
    assert err.rmse_receivers < 0.05
    assert "spikes rejected" in res.output


def test_known_refit_leaves_out_the_rejected_spikes(tmp_path):
    """With ``--known`` the constrained refit uses the entries the blind fit used: a 1.5 m
    multipath spike rejected by the recipe does not pull its tag position back (seen on the
    raw matrix it moved that position by 1.49 m; 0.033 m without it). Bound: 0.1 m, 5x the position std
    that 6 ranges of 2 cm noise give."""
    rng = np.random.default_rng(4)
    anchors = rng.uniform(0, 5, (6, 3))
    t = np.linspace(0, 30, 200)
    tag = np.c_[2.5 + 2 * np.cos(t / 3), 2.5 + 2 * np.sin(t / 2), 1.5 + np.sin(t / 5)]
    Y = toa_model(anchors, tag) + 0.02 * rng.standard_normal((6, 200))
    Y[1, 80] += 1.5
    path = tmp_path / "m.csv"
    np.savetxt(path, Y, delimiter=",")
    known = tmp_path / "known.csv"
    known.write_text("".join(",".join([f"r{i}", *(repr(float(v)) for v in anchors[i])]) + "\n" for i in range(6)))
    out = tmp_path / "res.json"
    # --common-offset free: this test is about the spikes; the kept-common-offset refit is
    # tests/toa/test_recipes_common_offset.py's (the block test costs ~16 refits here)
    res = run(path, "--recipe", "moving-tag", "--common-offset", "free", "--known", known, "--out", out)
    assert res.exit_code == 0, res.output
    data = json.loads(out.read_text())
    assert data["recipe"]["n_rejected"] >= 1
    S = np.array(data["sources"], dtype=float)
    assert np.linalg.norm(S[80] - tag[80]) < 0.1

def test_time_order_test_false_alarm_rate_and_power():
    """Independent sources: p-values are uniform, so detection at 1e-3 is rare (0 of 30
    here; P(any) = 3%); a sampled trajectory is detected every time."""
    from selfcal.toa.recipes.recipes import detect_time_order

    hits = 0
    for seed in range(30):
        _, r, s, Y = _scene3d(seed, I=6, J=40)
        hits += detect_time_order(Y, rng=seed).detected
    assert hits == 0
    rng = np.random.default_rng(1)
    anchors = rng.uniform(0, 5, (6, 3))
    t = np.linspace(0, 10, 60)
    tag = np.c_[2 + np.cos(t / 2), 2 + np.sin(t / 3), 1 + 0.3 * t / 10]
    test = detect_time_order(toa_model(anchors, tag) + 0.03 * rng.standard_normal((6, 60)))
    assert test.detected and test.ratio < 0.5


def test_negative_ranges_are_measurements_not_bad_input(tmp_path, scene):
    """Slightly negative ranges (bias + noise near zero range) are accepted (issue 12)."""
    r, s, Y = scene
    Y = Y.copy()
    Y[0, 0] = -0.01
    path = tmp_path / "m.csv"
    np.savetxt(path, Y, delimiter=",")
    out = tmp_path / "res.json"
    res = run(path, "--dim", 2, "--out", out)
    assert res.exit_code in (0, 1), res.output
    assert out.exists()


@pytest.mark.parametrize("entries", ["npz", "auto-small-limit"])
def test_per_entry_arrays_go_to_a_binary_sidecar(tmp_path, scene, monkeypatch, entries):
    """Above ENTRIES_JSON_MAX entries (or with --entries npz) residuals and the outliers mask go
    to OUT.npz, not into the JSON (a 1000 x 1000 matrix took 27 s to convert and write)."""
    import selfcal.commands.toa as cmd

    r, s, Y = scene
    path = tmp_path / "m.npy"
    np.save(path, Y)
    out = tmp_path / "res.json"
    if entries == "npz":
        res = run(path, "--dim", 2, "--entries", "npz", "--out", out)
    else:
        monkeypatch.setattr(cmd, "ENTRIES_JSON_MAX", Y.size - 1)
        res = run(path, "--dim", 2, "--out", out)
    assert res.exit_code == 0, res.output
    data = json.loads(out.read_text())
    assert data["residuals"] is None and data["outliers"] is None
    assert data["entries"]["file"] == "res.npz" and data["entries"]["shape"] == list(Y.shape)
    with np.load(tmp_path / "res.npz") as z:
        R, O = z["residuals"], z["outliers"]
    assert R.shape == Y.shape and O.dtype == bool and O.shape == Y.shape
    assert data["n_outliers"] == int(O.sum())
    # the same numbers as the JSON route
    out2 = tmp_path / "res2.json"
    assert run(path, "--dim", 2, "--entries", "json", "--out", out2).exit_code == 0
    inline = json.loads(out2.read_text())
    assert np.allclose(np.array(inline["residuals"], float), R, equal_nan=True, atol=1e-12)
    assert not (tmp_path / "res2.npz").exists()


def test_sidecar_never_overwrites_the_input(tmp_path, scene):
    r, s, Y = scene
    path = tmp_path / "m.npz"  # a known-nodes CSV that happens to be named like the sidecar
    text = "name,x,y\nr0,0,0\nr1,1,0\nr2,0,1\n"
    path.write_text(text)
    src = tmp_path / "m.npy"
    np.save(src, Y)
    res = run(src, "--dim", 2, "--entries", "npz", "--known", path, "--out", tmp_path / "m.json")
    assert res.exit_code == 2 and "would overwrite the input" in res.output, res.output
    assert path.read_text() == text
