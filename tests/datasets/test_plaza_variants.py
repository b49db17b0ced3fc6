"""Other CMU range-only logs (Plaza 2, Gesling, ... ): generated variants of the Plaza 1 layout,
loaded and solved, scored against the generator's ground truth.

Thresholds come from the estimator's own uncertainty (a consistent estimator's errors are of
the size of its stated standard deviations): each beacon's scale / offset within
``Z_MAX`` of its stated std (normal two-sided 1e-4 per value, Bonferroni over the <= 12
values of a log: a false alarm in ~1e-3 of the logs), and the track's position RMSE within
``RMS_RATIO`` times the RMS of its stated position std (the RMS error over a track has the
expectation of the RMS std; a factor 3 leaves room for the heavy right tail of an average of
correlated chi-square terms). The loader must give the same answer whatever the file's
conventions are (heading offset, id order, row order).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy import stats
from scipy.io import savemat

from selfcal.cli import main
from selfcal.datasets.plaza import load_plaza
from selfcal.errors import InputError
from selfcal.experiments.slac import score_plaza
from selfcal.geometry import wrap_angle
from selfcal.slac.ranging import solve_range_slac

from .cmu_logs import cmu_log

Z_MAX = float(stats.norm.isf(0.5e-4))  # 3.89: two-sided 1e-4 per calibration value
RMS_RATIO = 3.0


def _save(tmp_path: Path, m: dict, name: str = "log.mat") -> Path:  # type: ignore[type-arg]
    p = tmp_path / name
    savemat(p, m)
    return p


def _check_smoother(tmp_path: Path, seed: int, **kw: object) -> None:
    m, tr = cmu_log(seed, **kw)  # type: ignore[arg-type]
    d = load_plaza(_save(tmp_path, m))
    # the loader applied the conventions: beacons by id, heading offset, time order
    assert np.array_equal(d.beacon_ids, tr.beacon_ids)
    assert np.allclose(d.beacons, tr.beacons)
    assert np.all(np.diff(d.range_times) >= 0)
    assert np.max(np.abs(wrap_angle(d.gt[:, 2] - tr.poses[:, 2]))) < 1e-9
    r = solve_range_slac(d, method="smoother")
    assert r.success, r.message
    heard = tr.heard
    zs = (r.scale - tr.scale) / r.scale_std
    zo = (r.offset - tr.offset) / r.offset_std
    assert np.all(np.abs(zs[heard]) < Z_MAX) and np.all(np.abs(zo[heard]) < Z_MAX), (zs, zo)
    # a beacon never heard keeps its prior: scale 1 +- 0.1, offset 0 +- 1 m (nothing learnt)
    if (~heard).any():
        assert np.allclose(r.scale[~heard], 1.0) and np.allclose(r.offset[~heard], 0.0)
        assert np.allclose(r.scale_std[~heard], 0.1, rtol=1e-6) and np.allclose(r.offset_std[~heard], 1.0, rtol=1e-6)
    sc = score_plaza(d, r)
    pstd = float(np.sqrt(np.mean(np.sum(r.pose_std[:, :2] ** 2, axis=1))))
    assert sc["position_rmse"] < RMS_RATIO * pstd, (sc["position_rmse"], pstd)
    # the noise estimate is the generator's (robust median estimator: a few % of 0.15 m)
    assert abs(r.noise_estimate / tr.range_noise - 1) < 0.2, r.noise_estimate


SLOW = pytest.mark.slow


@pytest.mark.parametrize("kw", [
    # a beacon seen only from 130-170 m (scale and offset nearly collinear): the smoother gated
    # out all its ranges from the filter's calibration (scale z = 6.7) before the refit
    {"n_beacons": 6, "ids": [40, 2, 17, 9, 33, 5]},
    # another log's heading convention, a beacon in TL never heard, odometry with 8 s gaps
    {"n_beacons": 5, "silent": 1, "gaps": 3, "heading_offset": np.pi},
    pytest.param({"heading_offset": np.pi}, marks=SLOW),
    pytest.param({"n_beacons": 3}, marks=SLOW),
    pytest.param({"n_beacons": 5, "silent": 1}, marks=SLOW),
    pytest.param({"gaps": 3}, marks=SLOW),
], ids=["six-far-beacon", "silent-gaps-pi", "offset-pi", "three-beacons", "silent-beacon", "odometry-gaps"])
def test_generated_logs_calibrate_to_the_truth(tmp_path: Path, kw: dict) -> None:  # type: ignore[type-arg]
    _check_smoother(tmp_path, 2, **kw)


_HEADING_GRID = pytest.mark.xfail(reason=(
    "the heading-noise factor is chosen by the causal filter's robust predictive likelihood; with "
    "8 s odometry gaps and multipath outliers it picks the stiffest (0.03) and the smoother ends "
    "0.64 m RMS with scale z up to -4.5 (0.061 m, |z| < 0.7 without the outliers; same on main)"))


@pytest.mark.slow
@pytest.mark.parametrize("seed", [3, 4, 5, 6, pytest.param(7, marks=_HEADING_GRID), 8])
def test_generated_logs_many_seeds(tmp_path: Path, seed: int) -> None:
    _check_smoother(tmp_path, seed, n_beacons=5, silent=1, gaps=2, heading_offset=-np.pi / 2)


def test_conventions_do_not_change_the_answer(tmp_path: Path) -> None:
    """Heading offset, TL row order, TD row order and the offset's stored type are conventions:
    the loaded log (and so every estimate) is the same."""
    m, _ = cmu_log(4, heading_offset=np.pi, unsorted=False)
    a = load_plaza(_save(tmp_path, m, "a.mat"))
    m2 = dict(m)
    g = np.random.default_rng(0)
    m2["TL"] = m["TL"][g.permutation(len(m["TL"]))]
    # equal-time rows keep their file order (stable sort): shuffle whole time stamps only
    t = m["TD"][:, 0]
    ut = np.unique(t)
    perm = g.permutation(ut.size)
    key = perm[np.searchsorted(ut, t)]
    m2["TD"] = m["TD"][np.argsort(key, kind="stable")]
    m2["GT"] = m["GT"].copy()
    m2["GT"][:, 3] += 2 * np.pi  # the same heading, one turn on
    b = load_plaza(_save(tmp_path, m2, "b.mat"))
    order = [list(b.beacon_ids).index(i) for i in a.beacon_ids]
    assert np.allclose(b.beacons[order], a.beacons)
    assert np.array_equal(a.range_times, b.range_times) and np.allclose(a.ranges, b.ranges)
    assert np.array_equal(b.beacon_ids[b.range_beacon], a.beacon_ids[a.range_beacon])
    assert np.allclose(wrap_angle(a.gt[:, 2] - b.gt[:, 2]), 0.0, atol=1e-9)


@pytest.mark.parametrize("value", [1e308, -1e308, 180.0, -7.0])
def test_heading_offset_beyond_one_turn_is_refused(tmp_path: Path, value: float) -> None:
    """1e308 rad has no angle (its ulp exceeds 2 pi) and 180 is degrees: both refused, in the
    file or as the option, with one line and exit 2."""
    m, _ = cmu_log(0, duration=20.0, heading_offset=0.0)
    m["init_heading_offset"] = np.array([[value]])
    with pytest.raises(InputError, match="exceeds one turn"):
        load_plaza(_save(tmp_path, m))
    del m["init_heading_offset"]
    p = _save(tmp_path, m, "none.mat")
    with pytest.raises(InputError, match="exceeds one turn"):
        load_plaza(p, init_heading_offset=value)
    from click.testing import CliRunner

    res = CliRunner().invoke(main, ["slac", "plaza", str(p), "-o", str(tmp_path / "r.json"),
                                    "--init-heading-offset", repr(value)])
    assert res.exit_code == 2 and "Traceback" not in res.output
    assert [ln for ln in res.stderr.splitlines() if ln.strip()] == [res.stderr.strip()]
    assert not (tmp_path / "r.json").exists()


def test_option_equal_to_the_file_modulo_one_turn_is_accepted(tmp_path: Path) -> None:
    m, _ = cmu_log(0, duration=20.0, heading_offset=np.pi)
    d = load_plaza(_save(tmp_path, m), init_heading_offset=-np.pi)
    assert d.init_heading_offset == pytest.approx(np.pi)


def test_cli_on_a_generated_log_writes_every_output(tmp_path: Path) -> None:
    m, tr = cmu_log(5, n_beacons=5, silent=1, gaps=1, heading_offset=np.pi, duration=120.0)
    p = _save(tmp_path, m)
    from click.testing import CliRunner

    o = tmp_path / "out"
    res = CliRunner().invoke(main, ["slac", "plaza", str(p), "-o", str(o / "r.json"), "--method", "smoother",
                                    "--csv", str(o / "t.csv"), "--tum", str(o / "t.tum")])
    assert res.exit_code == 0, res.output
    import json

    s = json.loads((o / "r.json").read_text())
    assert s["beacon_ids"] == [int(b) for b in tr.beacon_ids]
    assert s["init_heading_offset"] == pytest.approx(np.pi)
    assert s["methods"]["smoother"]["position_rmse"] < s["dead_reckoning"]["position_rmse"]
    assert (o / "t.csv").stat().st_size > 0 and (o / "t.tum").stat().st_size > 0


def test_sparse_matrices_are_read_and_ranges_outside_the_odometry_refused(tmp_path: Path) -> None:
    """A MATLAB sparse TD is the same numbers (before: "must be a (rows, 4) array, got shape ()");
    ranges that all lie outside the odometry span (another clock) leave nothing to calibrate
    (before: exit 0 with every scale at its prior 1.000, dead reckoning reported as a result)."""
    from scipy import sparse

    m, _ = cmu_log(1, duration=30.0)
    dense = load_plaza(_save(tmp_path, m, "a.mat"))
    sp = load_plaza(_save(tmp_path, {**m, "TD": sparse.csc_matrix(m["TD"])}, "b.mat"))
    assert np.array_equal(dense.ranges, sp.ranges) and np.array_equal(dense.range_times, sp.range_times)
    td = m["TD"].copy()
    td[:, 0] -= 1e4
    with pytest.raises(InputError, match="no TD range falls in the span of the odometry"):
        load_plaza(_save(tmp_path, {**m, "TD": td}, "c.mat"))
