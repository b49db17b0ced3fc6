"""AOA results in the conventions users have (issue 31): position_std, the rotation as a quaternion and
as yaw / pitch / roll with standard deviations that match the Monte-Carlo spread, the covariance's
parameter order and units in the JSON, and one option name (--unit) with --units kept as a deprecated
alias."""

from __future__ import annotations

import json

import numpy as np
import pytest
from click.testing import CliRunner
from scipy.spatial.transform import Rotation

from selfcal.aoa import azel_to_bearings, solve_aoa
from selfcal.aoa.orientation import rotvec_to_matrix
from selfcal.aoa.result import COVARIANCE_PARAMETERS, COVARIANCE_UNITS, pose_summary
from selfcal.cli import main

BEACONS = np.array([[0.0, 0, 0], [5, 0, 0], [0, 5, 0], [5, 5, 1], [2, 3, 2.5], [4, 1, 2]])


def local_bearings(beacons, m, R):
    """Exact bearings in the receiver frame: R^T (b - m)/|b - m| (batched over m, R)."""
    g = beacons[None] - m[:, None]
    return np.einsum("bji,bkj->bki", R, g / np.linalg.norm(g, axis=-1, keepdims=True))


def noisy(rng, U0, sigma, B):
    noise = rng.normal(size=(B,) + U0.shape) * sigma
    U = U0 + noise - np.sum(noise * U0, -1, keepdims=True) * U0  # tangent-plane noise
    return U / np.linalg.norm(U, axis=-1, keepdims=True)


@pytest.mark.parametrize("seed", range(5))
def test_quaternion_and_yaw_pitch_roll_reproduce_the_rotation(seed):
    # independent reconstruction: R from the quaternion (scalar first) and from R = Rz(yaw) Ry(pitch) Rx(roll)
    rng = np.random.default_rng(seed)
    R = rotvec_to_matrix(rng.normal(size=(1, 3)))[0]
    out = pose_summary(R)
    w, x, y, z = out["quaternion"]
    assert w >= 0 and np.isclose(w * w + x * x + y * y + z * z, 1.0)
    Rq = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                   [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                   [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])
    np.testing.assert_allclose(Rq, R, atol=1e-12)
    yaw, pitch, roll = np.radians(out["yaw_pitch_roll_deg"])

    def rz(a):
        return np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])

    def ry(a):
        return np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])

    def rx(a):
        return np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])

    np.testing.assert_allclose(rz(yaw) @ ry(pitch) @ rx(roll), R, atol=1e-12)
    assert out["yaw_pitch_roll_std_deg"] is None and out["rotation_std_deg"] is None


@pytest.mark.parametrize("seed", range(3))
def test_pose_stds_match_the_monte_carlo_spread(seed):
    # 300 noisy bearing sets (0.5 deg) of one pose, ML with the noise given: the empirical std of
    # the position and of yaw / pitch / roll matches the predicted one within 20 % (the std of a
    # 300-sample std is ~4 %; the Gauss-Newton covariance is first order in the noise)
    rng = np.random.default_rng(100 + seed)
    m = np.array([[2.0, 2.0, -3.0]]) + rng.uniform(-0.5, 0.5, (1, 3))
    R = rotvec_to_matrix(rng.normal(scale=0.4, size=(1, 3)))
    U0 = local_bearings(BEACONS, m, R)[0]
    sigma = np.radians(0.5)
    res = solve_aoa(BEACONS, noisy(rng, U0, sigma, 300), sigma=sigma)
    out = res.to_dict()
    assert out["covariance_parameters"] == ["x", "y", "z", "wx", "wy", "wz"]
    assert out["covariance_units"] == ["m", "m", "m", "rad", "rad", "rad"]
    pstd = np.array(out["position_std"])
    np.testing.assert_allclose(pstd, np.sqrt(np.diagonal(res.covariance, axis1=1, axis2=2)[:, :3]))
    np.testing.assert_allclose(res.position.std(axis=0), pstd.mean(axis=0), rtol=0.2)
    ypr = np.array(out["yaw_pitch_roll_deg"])
    ypr0 = Rotation.from_matrix(R[0]).as_euler("ZYX", degrees=True)
    emp = np.std((ypr - ypr0 + 180.0) % 360.0 - 180.0, axis=0)
    np.testing.assert_allclose(emp, np.mean(out["yaw_pitch_roll_std_deg"], axis=0), rtol=0.2)
    q = np.array(out["quaternion"])
    assert q.shape == (300, 4) and np.allclose(np.linalg.norm(q, axis=1), 1.0)


def test_2d_heading_and_its_std():
    rng = np.random.default_rng(3)
    b = np.array([[0.0, 0.0], [5.0, 0.0], [0.0, 5.0], [5.0, 5.0]])
    th = 0.4
    R = np.array([[[np.cos(th), -np.sin(th)], [np.sin(th), np.cos(th)]]])
    m = np.array([[2.0, 1.0]])
    U0 = local_bearings(b, m, R)[0]
    sigma = np.radians(0.5)
    res = solve_aoa(b, noisy(rng, U0, sigma, 300), sigma=sigma)
    out = res.to_dict()
    assert out["covariance_parameters"] == list(COVARIANCE_PARAMETERS[2]) and out["covariance_units"] == list(
        COVARIANCE_UNITS[2])
    h = np.array(out["heading_deg"])
    np.testing.assert_allclose(np.mean(h), np.degrees(th), atol=0.2)
    np.testing.assert_allclose(np.std(h), np.mean(out["heading_std_deg"]), rtol=0.2)


def test_cli_writes_the_pose_conventions_and_unit_options(tmp_path):
    b = BEACONS[:4]
    R = rotvec_to_matrix(np.array([[0.2, -0.1, 0.5]]))
    m = np.array([[2.0, 1.0, -3.0]])
    U = local_bearings(b, m, R)[0]
    az, el = np.arctan2(U[:, 1], U[:, 0]), np.arcsin(U[:, 2])
    np.testing.assert_allclose(azel_to_bearings(az, el), U, atol=1e-12)
    np.savetxt(tmp_path / "b.csv", b, delimiter=",")
    np.savetxt(tmp_path / "rad.csv", np.column_stack([az, el]), delimiter=",")
    runner = CliRunner()
    base = ["locate", "aoa", str(tmp_path / "b.csv"), str(tmp_path / "rad.csv"), "--angles", "azel",
            "--sigma-deg", "0.5", "--method", "ml"]
    r = runner.invoke(main, [*base, "--unit", "rad", "--out", str(tmp_path / "a.json")])
    assert r.exit_code == 0, r.output
    assert "deprecated" not in r.output
    d = json.loads((tmp_path / "a.json").read_text())
    np.testing.assert_allclose(d["position"], m[0], atol=1e-8)
    for key in ("position_std", "quaternion", "yaw_pitch_roll_deg", "yaw_pitch_roll_std_deg", "rotation_std_deg",
                "covariance_parameters", "covariance_units"):
        assert d[key] is not None, key
    assert len(d["position_std"]) == 3 and all(s > 0 for s in d["position_std"])
    np.testing.assert_allclose(Rotation.from_quat(np.r_[d["quaternion"][1:], d["quaternion"][0]]).as_matrix(),
                               R[0], atol=1e-8)
    assert d["units"]["yaw_pitch_roll_deg"] == "deg" and d["units"]["position_std"] == "m"
    # the old spelling works and says it is deprecated (stderr)
    r = runner.invoke(main, [*base, "--units", "rad", "--out", str(tmp_path / "b.json")])
    assert r.exit_code == 0, r.output
    assert "--units is deprecated" in r.output
    np.testing.assert_allclose(json.loads((tmp_path / "b.json").read_text())["position"], m[0], atol=1e-8)
    # degrees by default
    np.savetxt(tmp_path / "deg.csv", np.degrees(np.column_stack([az, el])), delimiter=",")
    r = runner.invoke(main, ["locate", "aoa", str(tmp_path / "b.csv"), str(tmp_path / "deg.csv"), "--angles", "azel",
                             "--out", str(tmp_path / "c.json")])
    assert r.exit_code == 0, r.output
    # contradicting spellings are one clear line, exit 2
    r = runner.invoke(main, [*base, "--unit", "deg", "--units", "rad", "--out", str(tmp_path / "e.json")])
    assert r.exit_code == 2 and "disagree" in r.output
