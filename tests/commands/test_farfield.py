"""Command line and reproductions for far-field TDOA (paper 000)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from click.testing import CliRunner

from selfcal.cli import main
from selfcal.experiments.farfield import fig1_trial, fig2_trial, fig3_trial, fig4_trial


def unit(v):
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


@pytest.fixture
def farfield_csv(tmp_path, rng):
    Z = rng.uniform(-0.5, 0.5, (10, 3))
    Z[0] = 0
    N = unit(rng.normal(size=(15, 3)))
    D = Z @ N.T + rng.normal(size=15)
    path = tmp_path / "D.csv"
    np.savetxt(path, D, delimiter=",")
    return path, Z, N, D


def test_cli_calibrates_and_writes_design_keys(tmp_path, farfield_csv):
    path, Z, _, D = farfield_csv
    out = tmp_path / "res.json"
    fig = tmp_path / "fig.png"
    r = CliRunner().invoke(main, ["calibrate", "tdoa-farfield", str(path), "--out", str(out), "--plot", str(fig)])
    assert r.exit_code == 0, r.output
    res = json.loads(out.read_text())
    for key in ("positions", "directions", "offsets", "residual_rms", "degeneracy", "converged", "method"):
        assert key in res
    P = np.array(res["positions"])
    assert np.allclose(P[0], 0) and res["degeneracy"] is None
    fit = P @ np.array(res["directions"]).T + np.array(res["offsets"])
    assert np.abs(fit - D).max() < 1e-9
    assert fig.stat().st_size > 0


def test_cli_speed_converts_seconds(tmp_path, farfield_csv):
    path, _, _, D = farfield_csv
    sec = tmp_path / "t.csv"
    np.savetxt(sec, D / 343.0, delimiter=",")
    out = tmp_path / "res.json"
    r = CliRunner().invoke(main, ["calibrate", "tdoa-farfield", str(sec), "--speed", "343", "--out", str(out)])
    assert r.exit_code == 0, r.output
    res = json.loads(out.read_text())
    # positions come back in metres, offsets in seconds (as in `calibrate toa --speed`)
    assert res["units"]["positions"] == "m" and res["units"]["offsets"] == "s"
    fit = np.array(res["positions"]) @ np.array(res["directions"]).T + 343.0 * np.array(res["offsets"])
    assert np.abs(fit - D).max() < 1e-9


def test_cli_degenerate_exits_2_naming_it_unless_allowed(tmp_path, rng):
    Z = rng.uniform(-0.5, 0.5, (8, 3))
    Z[:, 2] = 0  # planar motion
    N = unit(rng.normal(size=(12, 3)))
    path = tmp_path / "planar.csv"
    np.savetxt(path, Z @ N.T, delimiter=",")
    out = tmp_path / "res.json"
    r = CliRunner().invoke(main, ["calibrate", "tdoa-farfield", str(path), "--out", str(out)])
    assert r.exit_code == 2
    assert "planar-motion" in r.output and not out.exists()
    r = CliRunner().invoke(main, ["calibrate", "tdoa-farfield", str(path), "--out", str(out), "--allow-degenerate"])
    assert r.exit_code == 0, r.output
    assert json.loads(out.read_text())["degeneracy"] == "planar-motion"


def test_cli_pyramic_is_a_cone(tmp_path, shared_data):
    from selfcal.datasets import load_pyramic

    data = load_pyramic(shared_data / "pyramic")
    path = tmp_path / "pyr.npy"
    np.save(path, data.D)
    r = CliRunner().invoke(main, ["calibrate", "tdoa-farfield", str(path), "--out", str(tmp_path / "r.json")])
    assert r.exit_code == 2 and "cone" in r.output


def test_cli_reads_the_pyramic_json_layout(tmp_path, shared_data):
    src = shared_data / "pyramic" / "pyramic_tdoa_speaker0.json"
    out = tmp_path / "r.json"
    r = CliRunner().invoke(main, ["calibrate", "tdoa-farfield", str(src), "--out", str(out)])
    # the shared speaker's directions lie on a cone: named, exit 2, no traceback, no file
    assert r.exit_code == 2 and "[cone]" in r.output and "Traceback" not in r.output
    assert not out.exists()
    r = CliRunner().invoke(main, ["calibrate", "tdoa-farfield", str(src), "--out", str(out), "--allow-degenerate"])
    assert r.exit_code == 0, r.output
    res = json.loads(out.read_text())
    assert len(res["positions"]) == 48 and len(res["directions"]) == 180
    assert res["units"]["offsets"] == "s" and res["speed"] > 300


def test_cli_json_in_another_layout_is_one_line(tmp_path):
    path = tmp_path / "x.json"
    path.write_text(json.dumps({"tdoa": [[1.0]]}))
    r = CliRunner().invoke(main, ["calibrate", "tdoa-farfield", str(path), "--out", str(tmp_path / "r.json")])
    assert r.exit_code == 2 and "no 'delays'" in r.output and "Traceback" not in r.output
    # a Pyramic-like file with its metadata missing: one line naming what to give
    path.write_text(json.dumps({"delays": [[1.0]]}))
    r = CliRunner().invoke(main, ["calibrate", "tdoa-farfield", str(path), "--out", str(tmp_path / "r.json")])
    assert r.exit_code == 2 and "--speed" in r.output and "Traceback" not in r.output
    assert len(r.output.strip().splitlines()) == 1


def test_cli_transposed_matrix_is_named(tmp_path, farfield_csv):
    path, _, _, D = farfield_csv
    tr = tmp_path / "t.csv"
    np.savetxt(tr, D.T, delimiter=",")
    r = CliRunner().invoke(main, ["calibrate", "tdoa-farfield", str(tr), "--out", str(tmp_path / "r.json")])
    assert r.exit_code == 2 and "transposed?" in r.output, r.output
    assert "DLASCL" not in r.output and "Traceback" not in r.output


def test_cli_bad_matrix_exits_2(tmp_path):
    path = tmp_path / "bad.csv"
    path.write_text("1,2,x\n")
    r = CliRunner().invoke(main, ["calibrate", "tdoa-farfield", str(path), "--out", str(tmp_path / "r.json")])
    assert r.exit_code == 2


def test_fig1_exact_far_field_minimal_error_is_at_machine_precision():
    row = fig1_trial({"model": "far-field", "distance": 0.0, "batch": 200}, seed=1)
    ok = row["n"] - row["failures"]
    assert row["failures"] == 0
    assert row["error_sum"] / ok < 1e-12  # paper: 6.8e-15 on average


def test_fig1_far_field_approximation_improves_with_distance():
    near = fig1_trial({"model": "3d", "distance": 5.0, "batch": 200}, seed=2)
    far = fig1_trial({"model": "3d", "distance": 1e5, "batch": 200}, seed=2)
    e_near = near["error_sum"] / (near["n"] - near["failures"])
    e_far = far["error_sum"] / (far["n"] - far["failures"])
    assert e_far < 1e-3 * e_near
    assert far["failures"] <= near["failures"]


def test_fig2_more_data_lowers_error():
    small = fig2_trial({"m": 4, "k": 6, "distance": 100.0, "batch": 40}, seed=3)
    big = fig2_trial({"m": 10, "k": 20, "distance": 100.0, "batch": 40}, seed=3)
    assert big["error_sum"] / big["n_ok"] < small["error_sum"] / small["n_ok"]
    assert big["failures"] <= small["failures"]


def test_fig3_lm_converges_in_fewer_iterations_than_alternating():
    rows = [fig3_trial({"m": 10, "k": 10, "sigma": 0.01, "length": 60}, seed=s) for s in range(3)]
    assert np.median([r["lm_adaptive_iters"] for r in rows]) < np.median([r["alt_iters"] for r in rows])


def test_fig4_good_far_field_with_small_noise_is_accurate():
    row = fig4_trial({"distance": 1e7, "sigma": 1e-4, "batch": 5}, seed=4)
    assert row["lm_error_sum"] / row["n"] < 0.01


@pytest.mark.parametrize("dim,case", [("auto", "planar"), ("2", "planar"), (None, "planar")])
def test_cli_planar_array_with_dim(tmp_path, dim, case):
    rng = np.random.default_rng(5)
    th = 2 * np.pi * np.arange(16) / 16
    Z = 0.05 * np.column_stack([np.cos(th), np.sin(th)])
    az = rng.uniform(0, 2 * np.pi, 24)
    D = Z @ np.column_stack([np.cos(az), np.sin(az)]).T + 1e-5 * rng.normal(size=(16, 24))
    path = tmp_path / "ring.csv"
    np.savetxt(path, D, delimiter=",")
    out, fig = tmp_path / "r.json", tmp_path / "r.png"
    dim_opt = [] if dim is None else ["--dim", dim]  # None: the default (auto)
    r = CliRunner().invoke(main, ["calibrate", "tdoa-farfield", str(path), *dim_opt, "--out", str(out),
                                  "--plot", str(fig)])
    assert r.exit_code == 0, r.output
    res = json.loads(out.read_text())
    assert res["case"] == case and res["dim"] == 2 and np.array(res["positions"]).shape == (16, 2)
    assert fig.stat().st_size > 0
    assert res["dim_rule"].startswith("auto" if dim in (None, "auto") else "given")
    # asking for 3-D names the degeneracy and points at --dim 2
    r = CliRunner().invoke(main, ["calibrate", "tdoa-farfield", str(path), "--dim", "3", "--out", str(out)])
    assert r.exit_code == 2 and "coplanar-directions" in r.output and "--dim 2" in r.output


def test_help_states_the_dimension_test_and_its_level():
    r = CliRunner().invoke(main, ["calibrate", "tdoa-farfield", "--help"])
    assert r.exit_code == 0
    text = " ".join(r.output.split())
    assert "default: auto" in text and "false-alarm rate 0.001" in text


@pytest.mark.parametrize("seed", range(3))
def test_cli_circular_and_linear_arrays_with_defaults(tmp_path, seed):
    # issue 31: with the defaults a circular 16-microphone array with far sources in its plane is
    # calibrated in 2-D and a linear one along its line; errors against the truth after the best
    # rotation / reflection (planar) or the best scale (linear: the data fix positions up to scale),
    # bounded by 20 x the noise (CRLB-level errors are about the noise over sqrt(k))
    from selfcal.geometry import align

    rng = np.random.default_rng(40 + seed)
    sigma = 1e-5
    th = 2 * np.pi * np.arange(16) / 16
    Z = 0.05 * np.column_stack([np.cos(th), np.sin(th)])
    az = rng.uniform(0, 2 * np.pi, 24)
    D = Z @ np.column_stack([np.cos(az), np.sin(az)]).T + rng.normal(size=24) + sigma * rng.normal(size=(16, 24))
    path, out = tmp_path / "ring.csv", tmp_path / "ring.json"
    np.savetxt(path, D, delimiter=",")
    r = CliRunner().invoke(main, ["calibrate", "tdoa-farfield", str(path), "--out", str(out)])
    assert r.exit_code == 0, r.output
    res = json.loads(out.read_text())
    assert res["case"] == "planar" and res["dim"] == 2 and "false-alarm rate 0.001" in res["dim_rule"]
    P = np.array(res["positions"])
    al = align(P, Z - Z[0], reflection=True)
    assert np.sqrt(np.mean(np.sum((al.apply(P) - (Z - Z[0])) ** 2, axis=1))) < 20 * sigma

    x = np.linspace(0.0, 0.3, 10)
    N = rng.normal(size=(20, 3))
    N /= np.linalg.norm(N, axis=1, keepdims=True)
    D = np.outer(x, N[:, 0]) + rng.normal(size=20) + sigma * rng.normal(size=(10, 20))
    path, out = tmp_path / "line.csv", tmp_path / "line.json"
    np.savetxt(path, D, delimiter=",")
    r = CliRunner().invoke(main, ["calibrate", "tdoa-farfield", str(path), "--out", str(out)])
    assert r.exit_code == 0, r.output
    res = json.loads(out.read_text())
    assert res["case"] == "linear" and res["dim"] == 1
    p = np.array(res["positions"]).reshape(-1)
    a = float(p @ x / (p @ p))  # the best scale (reported with the largest |projection| = 1)
    assert np.max(np.abs(a * p - x)) < 20 * sigma / min(1.0, float(np.max(np.abs(N[:, 0]))))


def test_cli_pyramic_with_its_own_directions(tmp_path, shared_data):
    # the cone leaves a one-parameter family of blind solutions; with the file's source
    # directions the problem is linear. Residual at the GCC-PHAT noise level (about 1 mm)
    src = shared_data / "pyramic" / "pyramic_tdoa_speaker0.json"
    out = tmp_path / "r.json"
    r = CliRunner().invoke(main, ["calibrate", "tdoa-farfield", str(src), "--directions", "sources", "--out", str(out)])
    assert r.exit_code == 0, r.output
    res = json.loads(out.read_text())
    assert res["case"] == "known-directions" and "reference_rmse" in res
    assert res["residual_rms"] * res["speed"] < 1.5e-3


def test_cli_residual_test_against_a_given_noise(tmp_path):
    # the noise given (1e-3) is ten times smaller than the data's (1e-2): the chi-square test of
    # the residuals fails (exit 1, FAIL line); with the right noise it passes
    rng = np.random.default_rng(9)
    Z = rng.uniform(-0.5, 0.5, (10, 3))
    N = unit(rng.normal(size=(30, 3)))
    D = Z @ N.T + rng.normal(size=30) + 1e-2 * rng.normal(size=(10, 30))
    path = tmp_path / "D.csv"
    np.savetxt(path, D, delimiter=",")
    out = tmp_path / "r.json"
    r = CliRunner().invoke(main, ["calibrate", "tdoa-farfield", str(path), "--noise-std", "1e-3", "--out", str(out)])
    assert r.exit_code == 1 and "FAIL:" in r.output
    r = CliRunner().invoke(main, ["calibrate", "tdoa-farfield", str(path), "--noise-std", "1e-2", "--out", str(out)])
    assert r.exit_code == 0, r.output
