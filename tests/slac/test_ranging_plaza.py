"""CMU Plaza real data: loader sanity, the range-only SLAC filter / smoother against ground
truth (a short default run, the full-log acceptance numbers as a slow test) and the command."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from selfcal.cli import main as cli_main
from selfcal.datasets import load_plaza
from selfcal.experiments.slac import plaza_summary


@pytest.fixture(scope="module")
def plaza(shared_data):  # type: ignore[no-untyped-def]
    return load_plaza(shared_data / "plaza" / "Plaza1.mat")


def test_loader_shapes_and_consistency(plaza) -> None:  # type: ignore[no-untyped-def]
    assert plaza.beacons.shape == (4, 2) and sorted(plaza.beacon_ids.tolist()) == [0, 1, 5, 6]
    assert plaza.ranges.size == plaza.range_times.size == plaza.range_beacon.size > 3000
    assert plaza.odo.shape[0] == plaza.gt.shape[0] - 1
    assert np.all(np.diff(plaza.range_times) >= 0)
    assert plaza.init_heading_offset == 0.0
    # odometry increments integrate to roughly the ground-truth path length
    path = np.sum(np.linalg.norm(np.diff(plaza.gt[:, :2], axis=0), axis=1))
    assert np.sum(plaza.odo[:, 0]) == pytest.approx(path, rel=0.1)
    # ranges match GT distances up to the documented scale error of several percent
    p = plaza.gt_at(plaza.range_times)
    d = np.linalg.norm(p[:, :2] - plaza.beacons[plaza.range_beacon], axis=1)
    assert 1.02 < np.median(plaza.ranges / d) < 1.12


def _head(data, n):  # type: ignore[no-untyped-def]
    t_end = data.odo_times[n - 1]
    keep = data.range_times <= t_end
    return replace(data, odo_times=data.odo_times[:n], odo=data.odo[:n], range_times=data.range_times[keep],
                   ranges=data.ranges[keep], range_beacon=data.range_beacon[keep])


def test_short_run_beats_dead_reckoning(plaza) -> None:  # type: ignore[no-untyped-def]
    s = plaza_summary(_head(plaza, 1500))  # first 5 minutes keep the default run short
    f, sm = s["methods"]["filter"], s["methods"]["smoother"]
    assert sm["position_rmse"] < f["position_rmse"] < s["dead_reckoning"]["position_rmse"]
    # the scale estimates agree with the several-% scale error that the loader test measures
    assert all(1.02 < v < 1.12 for v in sm["scale"])
    assert sm["success"]


@pytest.mark.slow
def test_full_log_meets_the_anchors(plaza) -> None:  # type: ignore[no-untyped-def]
    # issue 14's anchors on Plaza 1: FilterPy EKF + bias states 0.32 m, GTSAM batch graph 0.23 m
    s = plaza_summary(plaza)
    assert s["methods"]["filter"]["position_rmse"] <= 0.32
    assert s["methods"]["smoother"]["position_rmse"] <= 0.23


def test_plaza_command_writes_everything(tmp_path: Path, plaza) -> None:  # type: ignore[no-untyped-def]
    from scipy.io import savemat

    d = _head(plaza, 300)
    gt = np.column_stack([d.gt_times, d.gt[:, :2], d.gt[:, 2]])
    tl = np.column_stack([d.beacon_ids, d.beacons])
    td = np.column_stack([d.range_times, np.zeros_like(d.ranges), d.beacon_ids[d.range_beacon], d.ranges])
    dr = np.column_stack([d.odo_times, d.odo])
    f = tmp_path / "small.mat"
    savemat(f, {"TL": tl, "TD": td, "GT": gt, "DR": dr, "init_heading_offset": np.array([[0]], dtype=np.uint8)})
    out = tmp_path / "r.json"
    r = CliRunner().invoke(cli_main, ["slac", "plaza", str(f), "--out", str(out), "--method", "filter",
                                      "--csv", str(tmp_path / "t.csv"), "--tum", str(tmp_path / "t.tum"),
                                      "--plot", str(tmp_path / "t.png")])
    assert r.exit_code == 0, r.output
    js = json.loads(out.read_text())
    assert set(js["methods"]) == {"filter"} and js["methods"]["filter"]["position_rmse"] < 1.0
    csv = np.loadtxt(tmp_path / "t.csv", delimiter=",", skiprows=1)
    tum = np.loadtxt(tmp_path / "t.tum")
    assert csv.shape == (301, 7) and tum.shape == (301, 8)
    assert np.allclose(np.arctan2(tum[:, 6], tum[:, 7]) * 2 % (2 * np.pi), csv[:, 3] % (2 * np.pi), atol=1e-6)
    assert (tmp_path / "t.png").read_bytes()[:4] == b"\x89PNG"
    bad = CliRunner().invoke(cli_main, ["slac", "plaza", str(tmp_path / "none.mat"), "--out", str(out)])
    assert bad.exit_code == 2 and "not found" in bad.output
