"""Unit mistakes a newcomer makes, named through the CLI (issue 32).

Each mistake is made on a random room over several seeds (never one pinned scene): the
command must refuse it (exit 2, one ``selfcal: error:`` line naming the fix) when the
evidence is strong, or warn (a ``selfcal: warning:`` line naming the fix) when it is not;
the same data with the unit given explicitly must run and agree with the ground truth.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from scipy.spatial.transform import Rotation

from selfcal.cli import main

SEEDS = range(6)


def invoke(*args: object):
    return CliRunner().invoke(main, [str(a) for a in args])


# ----------------------------------------------------------------------------- AOA


def _aoa_scene(seed: int, dim: int = 3) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Six beacons in an 8 x 6 x 3 m room, a rotated receiver inside, 1 deg noise; (beacons,
    angles in radians, true position). Azimuth/elevation per beacon (N x 2; N x 1 in 2-D)."""
    rng = np.random.default_rng(seed)
    n = 6
    b = np.column_stack([rng.uniform(0, 8, n), rng.uniform(0, 6, n), rng.uniform(0, 3, n)])[:, :dim]
    m = np.array([rng.uniform(1, 7), rng.uniform(1, 5), rng.uniform(0.5, 2.5)])[:dim]
    R = Rotation.from_euler("z", rng.uniform(-np.pi, np.pi)).as_matrix()[:dim, :dim]
    v = (b - m) @ R  # receiver frame: R^T (b - m)
    az = np.arctan2(v[:, 1], v[:, 0]) + rng.normal(0, np.radians(1), n)
    if dim == 2:
        return b, az[:, None], m
    el = np.arcsin(v[:, 2] / np.linalg.norm(v, axis=1)) + rng.normal(0, np.radians(1), n)
    return b, np.column_stack([az, el]), m


@pytest.mark.parametrize("dim", [3, 2])
@pytest.mark.parametrize("seed", SEEDS)
def test_aoa_radians_read_as_degrees_is_refused(tmp_path: Path, seed: int, dim: int) -> None:
    b, ang, m = _aoa_scene(seed, dim)
    np.savetxt(tmp_path / "b.csv", b, delimiter=",")
    np.savetxt(tmp_path / "a.csv", ang, delimiter=",")
    out = tmp_path / "r.json"
    res = invoke("locate", "aoa", tmp_path / "b.csv", tmp_path / "a.csv", "--angles", "azel", "-o", out)
    assert res.exit_code == 2, res.output
    assert "--unit rad" in res.stderr and res.stderr.count("\n") == 1
    assert not out.exists()
    # the fix named works: radians put the receiver where it is (1 deg noise over a few metres:
    # well within 0.5 m)
    res = invoke("locate", "aoa", tmp_path / "b.csv", tmp_path / "a.csv", "--angles", "azel",
                 "--unit", "rad", "-o", out)
    assert res.exit_code == 0, res.output
    assert np.linalg.norm(np.array(json.loads(out.read_text())["position"]) - m) < 0.5
    # degrees said explicitly: the user is trusted (no refusal)
    res = invoke("locate", "aoa", tmp_path / "b.csv", tmp_path / "a.csv", "--angles", "azel",
                 "--unit", "deg", "-o", out)
    assert res.exit_code in (0, 1), res.output


@pytest.mark.parametrize("seed", SEEDS)
def test_aoa_axis_angles_in_radians_are_refused(tmp_path: Path, seed: int) -> None:
    """--angles axes (angles to the receiver's x and y axes): radians read as degrees make
    angle pairs of a few degrees to both axes, which no direction has; the fix is named."""
    b, ang, m = _aoa_scene(seed)
    az, el = ang[:, 0], ang[:, 1]
    v = np.column_stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
    np.savetxt(tmp_path / "b.csv", b, delimiter=",")
    np.savetxt(tmp_path / "a.csv", np.arccos(np.clip(v[:, :2], -1, 1)), delimiter=",")
    out = tmp_path / "r.json"
    res = invoke("locate", "aoa", tmp_path / "b.csv", tmp_path / "a.csv", "--angles", "axes", "-o", out)
    assert res.exit_code == 2 and "--unit rad" in res.stderr, res.output
    res = invoke("locate", "aoa", tmp_path / "b.csv", tmp_path / "a.csv", "--angles", "axes", "--unit", "rad",
                 "-o", out)
    assert res.exit_code in (0, 1), res.output  # (the side of the xy plane is unknown with axes angles)


@pytest.mark.parametrize("seed", SEEDS)
def test_aoa_degrees_are_not_flagged(tmp_path: Path, seed: int) -> None:
    b, ang, m = _aoa_scene(seed)
    np.savetxt(tmp_path / "b.csv", b, delimiter=",")
    np.savetxt(tmp_path / "a.csv", np.degrees(ang), delimiter=",")
    out = tmp_path / "r.json"
    res = invoke("locate", "aoa", tmp_path / "b.csv", tmp_path / "a.csv", "--angles", "azel", "-o", out)
    assert res.exit_code == 0, res.output
    assert "warning" not in res.stderr
    assert np.linalg.norm(np.array(json.loads(out.read_text())["position"]) - m) < 0.5


# ----------------------------------------------------------------------------- ranges


def _ranges(seed: int) -> np.ndarray:
    """8 receivers x 10 sources in an 8 x 6 x 3 m room, 2 cm ranging noise; metres."""
    rng = np.random.default_rng(seed)
    room = np.array([8.0, 6.0, 3.0])
    r, s = rng.uniform(0, 1, (8, 3)) * room, rng.uniform(0, 1, (10, 3)) * room
    return np.linalg.norm(r[:, None] - s[None], axis=2) + rng.normal(0, 0.02, (8, 10))


def _receivers(path: Path) -> np.ndarray:
    return np.array(json.loads(path.read_text())["receivers"])


@pytest.mark.parametrize("seed", SEEDS)
def test_millimetres_read_as_metres_are_refused(tmp_path: Path, seed: int) -> None:
    D = _ranges(seed)
    np.savetxt(tmp_path / "m.csv", D, delimiter=",")
    np.savetxt(tmp_path / "mm.csv", np.round(D * 1000), delimiter=",", fmt="%.0f")
    out = tmp_path / "r.json"
    # an 8 m room in millimetres is a network of ~9 km "metres": beyond any ranging network
    res = invoke("calibrate", "toa", tmp_path / "mm.csv", "--dim", 3, "-o", out)
    assert res.exit_code == 2, res.output
    assert "--unit mm" in res.stderr and not out.exists()
    res = invoke("calibrate", "toa", tmp_path / "mm.csv", "--dim", 3, "--unit", "mm", "-o", out)
    assert res.exit_code == 0, res.output
    ref = tmp_path / "ref.json"
    assert invoke("calibrate", "toa", tmp_path / "m.csv", "--dim", 3, "-o", ref).exit_code == 0
    # the same fit up to the 0.5 mm rounding: the inter-receiver distances agree within 1 cm
    # (2 cm noise, so 1 cm is far above the rounding and far below a unit mistake)
    A, B = _receivers(out), _receivers(ref)
    dA = np.linalg.norm(A[:, None] - A[None], axis=2)
    dB = np.linalg.norm(B[:, None] - B[None], axis=2)
    assert np.max(np.abs(dA - dB)) < 0.01


@pytest.mark.parametrize("seed", SEEDS)
def test_centimetres_read_as_metres_are_warned_about(tmp_path: Path, seed: int) -> None:
    D = _ranges(seed)
    np.savetxt(tmp_path / "cm.csv", D * 100, delimiter=",", fmt="%.1f")
    out = tmp_path / "r.json"
    # an 8 m room in centimetres is ~900 "m": beyond a room or hall, within a campus -> a warning
    res = invoke("calibrate", "toa", tmp_path / "cm.csv", "--dim", 3, "-o", out)
    assert res.exit_code in (0, 1), res.output
    assert "selfcal: warning:" in res.stderr and "--unit cm" in res.stderr
    res = invoke("calibrate", "toa", tmp_path / "cm.csv", "--dim", 3, "--unit", "cm", "-o", out)
    assert res.exit_code == 0 and "warning" not in res.stderr, res.output


@pytest.mark.parametrize("seed", SEEDS)
def test_metres_of_a_room_pass_silently(tmp_path: Path, seed: int) -> None:
    np.savetxt(tmp_path / "m.csv", _ranges(seed), delimiter=",")
    res = invoke("calibrate", "toa", tmp_path / "m.csv", "--dim", 3, "-o", tmp_path / "r.json")
    assert res.exit_code == 0 and "warning" not in res.stderr, res.output


@pytest.mark.parametrize("seed", SEEDS)
def test_kilometres_read_as_metres_are_refused(tmp_path: Path, seed: int) -> None:
    D = _ranges(seed)
    np.savetxt(tmp_path / "km.csv", D / 1000, delimiter=",", fmt="%.6f")
    out = tmp_path / "r.json"
    res = invoke("calibrate", "toa", tmp_path / "km.csv", "--dim", 3, "-o", out)
    assert res.exit_code == 2 and "--unit km" in res.stderr and not out.exists(), res.output
    res = invoke("calibrate", "toa", tmp_path / "km.csv", "--dim", 3, "--unit", "km", "-o", out)
    assert res.exit_code == 0, res.output
