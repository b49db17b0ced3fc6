"""CMU Plaza real data: loader and a measurement-level localization / SLAC check against GT."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from selfcal.datasets import load_plaza
from selfcal.errors import InputError
from selfcal.experiments.slac import run_plaza
from selfcal.slac.measurement import RangeConfig, RangeFilter


@pytest.fixture(scope="module")
def plaza(shared_data):  # type: ignore[no-untyped-def]
    return load_plaza(shared_data / "plaza" / "Plaza1.mat")


def test_loader_shapes_and_consistency(plaza) -> None:  # type: ignore[no-untyped-def]
    assert plaza.beacons.shape == (4, 2) and sorted(plaza.beacon_ids.tolist()) == [0, 1, 5, 6]
    assert plaza.ranges.size == plaza.range_times.size == plaza.range_beacon.size > 3000
    assert plaza.odo.shape[0] == plaza.gt.shape[0] - 1
    assert np.all(np.diff(plaza.range_times) >= 0)
    # odometry increments integrate to roughly the ground-truth path length
    path = np.sum(np.linalg.norm(np.diff(plaza.gt[:, :2], axis=0), axis=1))
    assert np.sum(plaza.odo[:, 0]) == pytest.approx(path, rel=0.1)
    # ranges match GT distances up to the documented scale error of several percent
    p = plaza.gt_at(plaza.range_times)
    d = np.linalg.norm(p[:, :2] - plaza.beacons[plaza.range_beacon], axis=1)
    assert 1.02 < np.median(plaza.ranges / d) < 1.12


def test_loader_refuses_bad_files(tmp_path) -> None:  # type: ignore[no-untyped-def]
    with pytest.raises(InputError):
        load_plaza(tmp_path / "missing.mat")
    bad = tmp_path / "bad.mat"
    bad.write_bytes(b"not a mat file")
    with pytest.raises(InputError):
        load_plaza(bad)


def _head(data, n):  # type: ignore[no-untyped-def]
    t_end = data.gt_times[n - 1]
    keep = data.range_times <= t_end
    return replace(data, gt_times=data.gt_times[:n], gt=data.gt[:n], odo_times=data.odo_times[: n - 1],
                   odo=data.odo[: n - 1], range_times=data.range_times[keep], ranges=data.ranges[keep],
                   range_beacon=data.range_beacon[keep])


def test_slac_with_scale_and_bias_states_tracks_ground_truth(plaza) -> None:  # type: ignore[no-untyped-def]
    part = _head(plaza, 2500)  # first ~8 minutes keep the default test run short
    sl = run_plaza(part, mode="slac")
    loc = run_plaza(part, mode="localization")
    assert sl["position_rmse"] < 1.0
    assert sl["position_rmse"] < loc["position_rmse"]
    # the estimated scale factors agree with the several-% scale error of the ranges
    assert all(0.02 < v < 0.12 for v in sl["scale_factors"].values())


def test_range_filter_recovers_injected_bias_and_scale() -> None:
    g = np.random.default_rng(4)
    anchors = np.array([[0.0, 0.0], [30.0, 0.0], [0.0, 30.0], [30.0, 30.0]])
    cfg = RangeConfig(sigma_range=0.1, bias_std=1.0, scale_std=0.1, sigma_v=0.02, sigma_omega=0.01)
    x = np.array([10.0, 10.0, 0.0])
    f = RangeFilter(anchors, x[None], np.diag([0.01, 0.01, 0.001])[None], [(0, 1 + b) for b in range(4)], config=cfg)
    bias = np.array([0.0, 0.3, -0.2, 0.5, 0.1])  # node 0 is the robot (not a state)
    scale = np.array([0.05, 0.03, 0.06, 0.04])
    from selfcal.slac.motion import motion_step

    for s in range(1500):
        u = np.array([0.5, 0.25 * np.sin(s / 40)])
        x = motion_step(x, u, 0.2)
        f.predict(u[None], 0.2)
        obs = []
        for b in range(4):
            d = np.linalg.norm(anchors[b] - x[:2])
            obs.append((0, 1 + b, "range", (1 + scale[b]) * d - bias[1 + b] + 0.1 * g.standard_normal()))
        f.update(obs)
    cal = f.calibration()
    est_b = np.array([cal["biases"][k] for k in range(1, 5)])
    sd_b = np.array([cal["bias_std"][k] for k in range(1, 5)])
    est_s = np.array([cal["scales"][f"0-{k}"] for k in range(1, 5)])
    assert np.all(np.abs(est_b - bias[1:]) < 3 * sd_b + 1e-3)
    assert np.allclose(est_s, scale, atol=0.01)
    assert np.linalg.norm(f.poses[0, :2] - x[:2]) < 0.2
