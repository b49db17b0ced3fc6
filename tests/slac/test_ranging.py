"""Range model with per-beacon scale + offset (selfcal.slac.ranging) on synthetic logs with a
known 7 % scale error and offsets: the filter and the smoother recover them within their own
error bars and localize the robot."""

from __future__ import annotations

import numpy as np
import pytest

from selfcal.datasets.plaza import compose_odometry
from selfcal.errors import InputError
from selfcal.slac.ranging import RangeLog, RangeModelConfig, huber_weight, solve_range_slac

BEACONS = np.array([[0.0, 0.0], [40.0, 0.0], [40.0, 40.0], [0.0, 40.0]])
SCALE = np.array([1.07, 1.065, 1.075, 1.07])  # ~7 % long, as the CMU logs
OFFSET = np.array([0.3, -0.2, 0.1, 0.4])


def synthetic(seed: int, n: int = 1200, outliers: float = 0.03) -> tuple[RangeLog, np.ndarray]:
    """Robot on a noisy lap at 1 m/s (0.2 s odometry rows, 5 Hz), ranges at 2 Hz off the grid
    of odometry times, 0.2 m noise plus a fraction of +5..15 m multipath outliers."""
    g = np.random.default_rng(seed)
    dt = 0.2
    u_true = np.column_stack([np.full(n, 0.2), 0.2 * 2 * np.pi / 120 * np.ones(n) + 0.01 * np.sin(np.arange(n) / 30)])
    truth = compose_odometry(np.array([20.0, 5.0, 0.0]), u_true)
    odo = u_true + np.column_stack([0.05 * np.sqrt(0.2) * g.standard_normal(n), 0.002 * g.standard_normal(n)])
    t = dt * np.arange(n + 1)
    rt = np.sort(g.uniform(t[1], t[-1], int(n * dt * 2)))
    rb = g.integers(0, 4, rt.size)
    # truth at the range times: linear interpolation between the odometry poses
    p = np.column_stack([np.interp(rt, t, truth[:, 0]), np.interp(rt, t, truth[:, 1])])
    r = SCALE[rb] * np.linalg.norm(p - BEACONS[rb], axis=1) + OFFSET[rb] + 0.2 * g.standard_normal(rt.size)
    bad = g.random(rt.size) < outliers
    r[bad] += g.uniform(5, 15, bad.sum())
    log = RangeLog(BEACONS, np.array([10, 11, 12, 13]), 0.0, truth[0], t[1:], odo, rt, rb, r)
    return log, truth


@pytest.mark.parametrize("method", ["filter", "smoother"])
def test_recovers_scale_and_offset(method: str) -> None:
    z = []
    for seed in range(3):
        log, truth = synthetic(seed)
        res = solve_range_slac(log, method=method)
        assert res.success and res.poses.shape == truth.shape
        z.append((res.scale - SCALE) / res.scale_std)
        z.append((res.offset - OFFSET) / res.offset_std)
        # the estimate beats the scale error it has to remove: 7 % of ~20 m is 1.4 m of range error
        e = np.linalg.norm(res.poses[:, :2] - truth[:, :2], axis=1)
        assert np.sqrt(np.mean(e[100:] ** 2)) < 0.3
        assert abs(res.noise_estimate - 0.2) < 0.05  # the robust noise estimate ignores the outliers
        assert res.ranges_rejected >= 0.5 * 0.03 * log.ranges.size  # most gross outliers gated
    z = np.concatenate(z)
    # calibration errors within 4 of their own standard deviations (per-parameter false alarm
    # 6e-5 for a consistent Gaussian posterior); the smoother's are the batch Laplace stds
    assert np.all(np.abs(z) < 4), z
    assert np.all(np.abs(np.concatenate([res.scale - SCALE])) < 0.01)


def test_smoother_beats_filter_and_dead_reckoning() -> None:
    log, truth = synthetic(5)
    dr = compose_odometry(log.start_pose, log.odo)
    f = solve_range_slac(log, method="filter")
    s = solve_range_slac(log, method="smoother")

    def rmse(p: np.ndarray) -> float:
        return float(np.sqrt(np.mean(np.sum((p[:, :2] - truth[:, :2]) ** 2, axis=1))))

    assert rmse(s.poses) < rmse(f.poses) < rmse(dr)
    # position errors consistent with the smoother's own stds (2-D NEES mean ~2, loose bound for
    # the heavy-tailed outliers and the linearisation)
    nees = np.sum(((s.poses[:, :2] - truth[:, :2]) / s.pose_std[:, :2]) ** 2, axis=1)
    assert 0.5 < np.mean(nees) < 5


def test_huber_weight() -> None:
    assert huber_weight(np.array([0.0, 1.0, -2.69]), 1.345).tolist() == pytest.approx([1.0, 1.0, 0.5], abs=1e-3)


def test_to_dict_json_safe() -> None:
    import json

    log, _ = synthetic(0, n=200)
    r = solve_range_slac(log, method="filter")
    d = r.to_dict()
    json.dumps(d, allow_nan=False)
    assert len(repr(r)) < 600 and "scale" in r.summary()
    assert set(d) >= {"status", "message", "success", "scale", "scale_std", "offset", "offset_std", "noise_estimate"}


def test_bad_input() -> None:
    log, _ = synthetic(0, n=50)
    with pytest.raises(InputError, match="method"):
        solve_range_slac(log, method="ekf")
    with pytest.raises(InputError, match="scale_std"):
        RangeModelConfig(scale_std=-1)
    with pytest.raises(InputError, match="range_beacon"):
        RangeLog(BEACONS, np.arange(4), 0.0, log.start_pose, log.odo_times, log.odo, log.range_times,
                 log.range_beacon + 9, log.ranges)


@pytest.mark.parametrize("method", ["filter", "smoother"])
def test_degenerate_logs_give_finite_results(method: str) -> None:
    import json

    B = BEACONS[:3]
    no_ranges = RangeLog(B, np.arange(3), 0.0, np.zeros(3), np.array([1.0, 2.0]), np.array([[0.1, 0.0], [0.1, 0.0]]),
                         np.zeros(0), np.zeros(0, dtype=int), np.zeros(0))
    r = solve_range_slac(no_ranges, method=method)
    # without ranges the estimate is dead reckoning and the calibration keeps its prior
    assert np.allclose(r.poses, compose_odometry(np.zeros(3), no_ranges.odo))
    assert np.allclose(r.scale, 1.0) and np.allclose(r.scale_std, RangeModelConfig().scale_std)
    json.dumps(r.to_dict())
    dup = RangeLog(B, np.arange(3), 0.0, np.zeros(3), np.array([1.0, 1.0, 2.0]), np.full((3, 2), [0.1, 0.0]),
                   np.array([1.5]), np.array([0]), np.array([0.2]))
    r = solve_range_slac(dup, method=method)  # rows at one time are one increment
    assert np.allclose(r.poses[-1, :2], [0.3, 0.0], atol=0.05) and np.all(np.isfinite(r.pose_std))
