"""LPS real data (Lund UWB flights): loader and blind anchor calibration against motion capture."""

from __future__ import annotations

import numpy as np
import pytest

from selfcal.datasets import load_lps
from selfcal.errors import InputError
from selfcal.experiments.lps import calibrate_lps
from selfcal.metrics import aligned_rmse

# the data set README's numbers for the authors' own estimate (ropt)
AUTHORS = {"data4": 0.235, "data5": 0.170}


@pytest.fixture(scope="module", params=["data4", "data5"])
def flight(request, shared_data):
    return load_lps(shared_data / "lps" / f"{request.param}.mat")


def test_loader_layout(flight):
    n = flight.n_positions
    assert flight.ranges.shape == (6, n) and n > 500
    assert flight.anchors_true.shape == (6, 3) and flight.tag_true.shape == (n, 3)
    assert flight.authors_anchors.shape == (6, 3) and flight.authors_tag.shape == (n, 3)
    miss = np.isnan(flight.ranges)
    assert 0 < miss.sum() < 0.02 * miss.size  # a few dropped ranges, kept as NaN
    # ranges agree with the motion-capture geometry up to the UWB bias and noise
    true = np.linalg.norm(flight.anchors_true[:, None] - flight.tag_true[None], axis=2)
    bias = np.nanmedian(flight.ranges - true, axis=1)
    assert np.all((bias > -0.3) & (bias < 0.0))


def test_authors_estimate_scores_as_documented(flight):
    rmse = aligned_rmse(flight.authors_anchors, flight.anchors_true).rmse_receivers
    assert rmse == pytest.approx(AUTHORS[flight.name], abs=1e-3)


def test_anchors_are_not_coplanar(flight):
    sv = np.linalg.svd(flight.anchors_true - flight.anchors_true.mean(0), compute_uv=False)
    assert sv[-1] / sv[0] > 0.3  # measured 0.38: a genuinely 3-D anchor set


def test_blind_calibration_is_near_the_authors(flight):
    # blind: ranges only. Measured anchor RMSE 0.251 m (data4) and 0.174 m (data5) with
    # offsets="none"; the bound allows 15 % above the authors' own 0.235 / 0.170 m
    res = calibrate_lps(flight.ranges, "none")
    rmse = aligned_rmse(res["receivers"], flight.anchors_true).rmse_receivers
    assert rmse < 1.15 * AUTHORS[flight.name] + 0.02


def test_anchor_bias_model_beats_the_authors_on_data5(shared_data):
    # per-anchor ranging offsets + Huber loss: measured 0.124 m vs the authors' 0.170 m
    flight = load_lps(shared_data / "lps" / "data5.mat")
    res = calibrate_lps(flight.ranges, "receivers-huber")
    rmse = aligned_rmse(res["receivers"], flight.anchors_true).rmse_receivers
    assert rmse < AUTHORS["data5"]
    assert np.all(res["receiver_offsets"] < 0)  # the documented negative UWB bias


def test_loader_refuses_other_files(tmp_path):
    bad = tmp_path / "x.mat"
    bad.write_bytes(b"not a mat file")
    with pytest.raises(InputError):
        load_lps(bad)
    with pytest.raises(FileNotFoundError):
        load_lps(tmp_path / "missing.mat")
    with pytest.raises(InputError):
        calibrate_lps(np.ones((6, 20)), "nope")


@pytest.mark.slow
def test_spike_rejection_then_profiled_offsets_beat_the_authors(flight):
    # an opt-in variant (common_offset="profile"), not the default: ~60 s per flight here
    # blind: NLOS spikes rejected in time (robust local quadratic, 3.5 sigma), then per-anchor
    # offsets whose common part minimises the trimmed residual scale. Measured anchor RMSE
    # 0.172 m (data4) and 0.111 m (data5) against the authors' 0.235 / 0.170 m
    res = calibrate_lps(flight.ranges, "clean-profile")
    rmse = aligned_rmse(res["receivers"], flight.anchors_true).rmse_receivers
    assert rmse < {"data4": 0.19, "data5": 0.13}[flight.name]
    assert rmse < 0.85 * AUTHORS[flight.name]
    assert res["n_rejected"] < 0.1 * np.isfinite(flight.ranges).sum()  # measured 6.5 % / 6.3 %
    assert np.all(res["receiver_offsets"] < 0)  # the documented negative UWB bias
    # an interior minimum of the profile, i.e. the common offset was determined, not clipped
    grid = res["profile"]["grid"]
    assert grid[0] < res["common_offset"] < grid[-1]
    assert res["converged"]


def test_spike_rejection_alone_helps_on_data4(shared_data):
    # measured 0.230 m after rejection vs 0.251 m on the raw ranges (offsets="none")
    flight = load_lps(shared_data / "lps" / "data4.mat")
    clean = calibrate_lps(flight.ranges, "clean")
    rmse = aligned_rmse(clean["receivers"], flight.anchors_true).rmse_receivers
    assert rmse < AUTHORS["data4"]
    assert np.isnan(clean["sources"]).any(axis=1).sum() < 0.05 * flight.n_positions


def _write_flight(path, n=40, ok_cols=None, gt_cols=None, data_is_struct=True):
    import scipy.io

    rng = np.random.default_rng(0)
    G = rng.uniform(0, 5, (3, 6))
    T = rng.uniform(1, 4, (3, n))
    d = np.linalg.norm(G.T[:, None] - T.T[None], axis=2)
    ok = np.ones((1, n if ok_cols is None else ok_cols), bool)
    data = {"d": d, "Gtr": G, "GTs_resamp": T[:, : (n if gt_cols is None else gt_cols)],
            "GTs_resamp_ok": ok, "ropt": G, "sopt": T, "description": "synthetic"}
    scipy.io.savemat(path, {"data": data if data_is_struct else np.zeros(3)})
    return d, G, T


def test_loader_short_validity_flags_warn_not_indexerror(tmp_path):
    """GTs_resamp_ok with fewer columns than d: the ranges are kept, the positions without
    a flag get NaN ground truth, and a LpsFormatWarning says so (never IndexError)."""
    from selfcal.datasets.lps import LpsFormatWarning
    from selfcal.datasets.lps import load_lps as load

    f = tmp_path / "data9.mat"
    d, _, _ = _write_flight(f, n=40, ok_cols=30)
    with pytest.warns(LpsFormatWarning, match="GTs_resamp_ok"):
        fl = load(f)
    np.testing.assert_array_equal(fl.ranges, d)
    assert np.isnan(fl.tag_true[30:]).all() and np.isfinite(fl.tag_true[:30]).all()
    f2 = tmp_path / "data8.mat"
    _write_flight(f2, n=40, gt_cols=35)
    with pytest.warns(LpsFormatWarning, match="GTs_resamp"):
        fl2 = load(f2)
    assert np.isnan(fl2.tag_true[35:]).all()
    f3 = tmp_path / "data7.mat"
    _write_flight(f3, data_is_struct=False)
    with pytest.raises(InputError):
        load(f3)


def test_position_with_two_ranges_is_dropped_not_fatal(shared_data):
    """reproduce lps aborted on a flight where one tag position has only 2 ranges."""
    flight = load_lps(shared_data / "lps" / "data5.mat")
    Y = flight.ranges.copy()
    Y[2:, 100] = np.nan
    res = calibrate_lps(Y, "none")
    assert res["n_dropped"] >= 1 and np.isnan(res["sources"][100]).all()
    assert aligned_rmse(res["receivers"], flight.anchors_true).rmse_receivers < 0.3


def _cli_default_anchor_rmse(tmp_path, flight, *extra):
    """``selfcal calibrate toa`` with its defaults on the raw ``d`` matrix written as CSV."""
    import json

    from click.testing import CliRunner

    from selfcal.cli import main

    csv = tmp_path / f"{flight.name}.csv"
    np.savetxt(csv, flight.ranges, delimiter=",")  # 6 x N, NaN missing, no preprocessing
    out = tmp_path / f"{flight.name}.json"
    res = CliRunner().invoke(main, ["calibrate", "toa", str(csv), "--out", str(out), *extra])
    assert res.exit_code in (0, 1), res.output
    data = json.loads(out.read_text())
    return aligned_rmse(np.array(data["receivers"], float), flight.anchors_true).rmse_receivers, data, res


def test_default_recipe_detects_the_moving_tag(flight):
    """Reduced version of the acceptance run: on the raw ``d`` matrix the default recipe
    (``auto``) recognises the columns as one tag in time order, so ``calibrate toa``
    rejects the multipath spikes in time before the fit."""
    from selfcal.toa.recipes.recipes import detect_time_order

    test = detect_time_order(flight.ranges)
    assert test.detected and test.p_value <= 1e-3
    assert test.ratio < 0.2  # a densely sampled flight is far smoother than a random order


@pytest.mark.slow
def test_calibrate_toa_defaults_on_the_raw_flights(tmp_path, flight):
    """Acceptance (issue 12): ``selfcal calibrate toa`` with its defaults on the raw ``d``
    matrix (6 x N CSV, NaN missing, negative ranges kept, no preprocessing) reaches an
    anchor RMSE after rigid alignment below the authors' stored estimate. The defaults are
    chosen by principle (recipe auto -> moving-tag: one-sided Bonferroni spike rejection;
    offsets none; one common range offset, a UWB antenna delay, kept by the block jackknife
    t test over time blocks, selfcal.toa.recipes.common_offset). Measured: c = -0.395 / -0.332 m,
    t = -7.6 (16 blocks of 38 positions) / -10.8 (12 blocks of 50), anchor RMSE 0.184 /
    0.155 m against the authors' 0.235 / 0.170 m (0.236 / 0.176 m without the offset).
    Then per-anchor offsets are not kept on either flight: on data5 they predict held-out
    positions worse; on data4 better (CV RMS 0.1595 vs 0.1690 m) but with anchors estimated
    worse (anchor check: 0.247 vs 0.128 m; measured 0.309 vs 0.166 m after alignment), issue 29.
    Measured at the issue-29 anchor check: 0.166 / 0.155 m."""
    rmse, data, res = _cli_default_anchor_rmse(tmp_path, flight)
    assert data["recipe"]["name"] == "moving-tag"
    assert res.exit_code == 0, res.output
    test = data["recipe"]["common_offset_test"]
    assert data["offsets"] == "common" and test["adopted"] and test["value"] < 0  # the documented negative bias
    assert test["blocks"] >= 6 and test["p_value"] < test["alpha"]
    assert rmse < AUTHORS[flight.name]


def test_reproduce_lps_survives_a_two_range_position(tmp_path):
    """``selfcal reproduce lps`` on a flight with a position of only 2 ranges: every variant
    runs, the position is dropped and counted, nothing aborts."""
    import json

    import scipy.io
    from click.testing import CliRunner

    from selfcal.cli import main
    from selfcal.experiments.lps import simulate_uwb_flight

    sim = simulate_uwb_flight(5, n_positions=80, sparse_positions=1)
    data = {"d": sim["ranges"], "Gtr": sim["anchors"].T, "GTs_resamp": sim["tag"].T,
            "GTs_resamp_ok": np.ones((1, 80), bool), "ropt": sim["anchors"].T, "sopt": sim["tag"].T}
    f = tmp_path / "data1.mat"
    scipy.io.savemat(f, {"data": data})
    out = tmp_path / "lps"
    res = CliRunner().invoke(main, ["reproduce", "lps", "--data", str(f), "--out", str(out),
                                    "--simulate", "0", "--variants", "none,clean,receivers-huber"])
    assert res.exit_code == 0, res.output
    rep = json.loads((out / "lps.json").read_text())
    rows = rep["flights"]["data1"]["variants"]
    assert set(rows) == {"none", "clean", "receivers-huber"}
    assert rep["leave_one_flight_out"]["all_cases"] is None  # one case: nothing to hold out
    assert all(r.get("n_dropped", 0) >= 1 for r in rows.values() if "error" not in r)
    assert rep["recommended"] == "clean"


def test_leave_one_flight_out_selects_on_the_other_flights():
    from selfcal.experiments.lps import leave_one_flight_out

    scores = {"a": {"x": 0.1, "y": 0.3}, "b": {"x": 0.5, "y": 0.2}, "c": {"x": 0.2, "y": 0.25}}
    out = leave_one_flight_out(scores, ["x", "y"])
    # held-out a: median over b, c is x 0.35, y 0.225 -> y, scored 0.3 on a
    assert out["per_flight"]["a"] == {"selected": "y", "held_out_rmse": 0.3}
    assert out["per_flight"]["b"]["selected"] == "x"  # a, c: x 0.15 < y 0.275
    assert out["median_held_out_rmse"] == pytest.approx(0.3)


def test_simulated_flight_has_the_documented_structure():
    from selfcal.experiments.lps import simulate_uwb_flight

    sim = simulate_uwb_flight(0, n_positions=200)
    Y, A, T = sim["ranges"], sim["anchors"], sim["tag"]
    assert Y.shape == (6, 200) and np.isnan(Y).any()
    D = np.linalg.norm(A[:, None] - T[None], axis=2)
    clean = ~sim["spikes"] & np.isfinite(Y)
    # without spikes, ranges = truth + per-anchor bias + noise (0.04 m): bias recovered
    est = np.array([np.median((Y - D)[i][clean[i]]) for i in range(6)])
    np.testing.assert_allclose(est, sim["bias"], atol=0.02)
    assert np.all((Y - D)[sim["spikes"] & np.isfinite(Y)] > sim["bias"].min() - 0.2)


def test_spike_threshold_has_its_stated_false_alarm_rate():
    """``spike_threshold`` is Bonferroni over the observed entries: on pure Gaussian noise
    the probability that any entry of a 6 x 600 matrix exceeds it is at most alpha = 1 %.
    Over 400 matrices the count of matrices with a false alarm is Binomial(400, <= 0.01):
    mean <= 4, and P(X >= 13) < 3e-4 (Poisson(4) tail), the bound asserted."""
    from selfcal.toa.recipes.recipes import spike_threshold
    from selfcal.toa.verdict.robust import OUTLIER_ALPHA

    rng = np.random.default_rng(0)
    Z = rng.standard_normal((400, 6, 600))
    k1 = spike_threshold(Z[0], one_sided=True)
    k2 = spike_threshold(Z[0], one_sided=False)
    assert k2 > k1 > 4.0  # the two-sided test splits alpha over both tails
    hits1 = int(np.sum(Z.max(axis=(1, 2)) > k1))
    hits2 = int(np.sum(np.abs(Z).max(axis=(1, 2)) > k2))
    assert hits1 <= 12 and hits2 <= 12
    assert OUTLIER_ALPHA == 0.01



@pytest.mark.slow
def test_moving_tag_warnings_name_undetermined_positions_in_the_callers_numbering(shared_data):
    """The recipe fits the kept columns only; the solver's warning about undetermined tag
    positions must use the caller's column numbers, as the result's message and JSON do
    (before: data4 warned 511 / 553 for positions 512 / 555)."""
    import warnings

    from selfcal.errors import ConvergenceWarning
    from selfcal.toa.recipes.recipes import moving_tag

    Y = load_lps(shared_data / "lps" / "data4.mat").ranges.copy()
    Y[:, :3] = np.nan  # three unusable positions first: every later column number shifts by 3
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        rec = moving_tag(Y, common_offset="free")
    det = rec.result.determinacy
    assert det is not None and det.n_undetermined > 0 and {0, 1, 2} <= set(rec.dropped_sources)
    texts = [str(w.message) for w in caught if issubclass(w.category, ConvergenceWarning)]
    assert any(det.names() in t for t in texts), texts
    for j in np.flatnonzero(det.undetermined_sources):
        assert np.isfinite(rec.result.sources[j]).all()  # a kept column, named by its own number
