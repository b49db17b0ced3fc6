"""Blind preprocessing of range series along a smooth trajectory (selfcal.toa.recipes.preprocess)."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from selfcal.errors import InputError
from selfcal.metrics import aligned_rmse
from selfcal.toa.recipes.preprocess import (
    fit_offsets_profile_common,
    local_polynomial_prediction,
    observed_columns,
    reject_range_outliers,
    robust_scale,
)

ANCHORS = np.array([[0.0, 0.0, 0.2], [6.0, 0.3, 2.8], [5.5, 5.0, 0.4],
                    [0.4, 6.0, 2.5], [3.0, -0.5, 1.5], [-0.3, 3.0, 0.9]])


def flight(n: int = 500) -> tuple[np.ndarray, np.ndarray]:
    """A smooth quadcopter-like loop inside the anchor hull, sampled at 10 Hz."""
    t = np.arange(n) * 0.1
    w = 2 * np.pi * t / 25.0
    tag = np.column_stack([2.8 + 2.5 * np.cos(w), 2.8 + 2.5 * np.sin(2 * w), 1.4 + 1.1 * np.sin(3 * w)])
    return t, tag


def true_ranges(tag: np.ndarray) -> np.ndarray:
    return np.linalg.norm(ANCHORS[:, None] - tag[None], axis=2)


def test_prediction_is_exact_on_polynomials_and_ignores_the_sample_itself():
    t = np.linspace(0.0, 3.0, 40)
    y = 1.0 - 0.5 * t + 0.3 * t**2
    y_spiked = y.copy()
    y_spiked[20] += 5.0  # leave-one-out: the spike cannot pull its own prediction
    pred = local_polynomial_prediction(y_spiked, t, half_window=5, degree=2)
    assert np.allclose(pred[20], y[20], atol=1e-9)
    assert np.allclose(np.delete(pred, np.arange(14, 27)), np.delete(y, np.arange(14, 27)), atol=1e-9)


def test_spikes_are_found_and_clean_samples_kept(rng):
    t, tag = flight()
    R = true_ranges(tag) + 0.03 * rng.standard_normal((6, t.size))
    spikes = rng.random(R.shape) < 0.03
    R_obs = R + spikes * rng.uniform(0.4, 1.5, R.shape)  # NLOS: longer paths
    R_obs[rng.random(R.shape) < 0.01] = np.nan
    out = reject_range_outliers(R_obs, t)
    observed = np.isfinite(R_obs)
    recall = (out.outliers & spikes & observed).sum() / (spikes & observed).sum()
    false_rate = (out.outliers & ~spikes).sum() / (~spikes & observed).sum()
    assert recall > 0.97
    assert false_rate < 0.01
    assert np.allclose(out.scale, 0.03, rtol=0.3)  # the robust scale sees the noise, not the spikes
    assert np.all(np.isnan(out.ranges[out.outliers]))
    assert np.array_equal(np.isnan(out.ranges), np.isnan(R_obs) | out.outliers)


def test_one_sided_rejection_keeps_short_ranges(rng):
    t, tag = flight(300)
    R = true_ranges(tag) + 0.02 * rng.standard_normal((6, t.size))
    R[2, 100] -= 1.0
    R[3, 150] += 1.0
    both = reject_range_outliers(R, t)
    pos = reject_range_outliers(R, t, one_sided=True)
    assert both.outliers[2, 100] and both.outliers[3, 150]
    assert not pos.outliers[2, 100] and pos.outliers[3, 150]


def test_robust_scale_and_observed_columns(rng):
    e = 0.1 * rng.standard_normal(20000)
    e[:500] = 50.0
    assert robust_scale(e) == pytest.approx(0.1, rel=0.05)
    # trimmed RMS keeping 50 % of all = the 51.3 % smallest of the 97.5 % Gaussian entries:
    # sqrt(E[z^2 | |z| < q]) with P(|z| < q) = 0.513 is 0.3883 (0.3777 without spikes)
    assert robust_scale(e, "trimmed", keep=0.5) == pytest.approx(0.1 * 0.3883, rel=0.03)
    Y = np.ones((6, 4))
    Y[:3, 1] = np.nan  # 3 ranges: not enough in 3-D (mirror ambiguity)
    Y[:2, 2] = np.nan
    assert observed_columns(Y, 3).tolist() == [True, False, True, True]


def test_profile_recovers_the_common_offset(rng):
    t, tag = flight(400)
    offsets = np.array([-0.12, -0.25, -0.18, -0.3, -0.08, -0.2])  # UWB-like, mean -0.188
    R = true_ranges(tag) + offsets[:, None] + 0.05 * rng.standard_normal((6, t.size))
    # start: a perturbed truth, as an offsets="none" solution would be
    r0 = ANCHORS + 0.1 * rng.standard_normal(ANCHORS.shape)
    s0 = tag + 0.1 * rng.standard_normal(tag.shape)
    fit = fit_offsets_profile_common(R, r0, s0)
    # the least-squares residual alone cannot fix the common offset; the robust profile does
    assert fit.common == pytest.approx(offsets.mean(), abs=0.04)
    assert np.mean(fit.receiver_offsets) == pytest.approx(fit.common, abs=1e-9)
    assert np.argmin(fit.profile) not in (0, fit.grid.size - 1)  # an interior minimum
    assert aligned_rmse(fit.receivers, ANCHORS).rmse_receivers < 0.1
    assert fit.converged
    # residual RMS = noise sigma corrected for the fitted unknowns (6 gauge directions free)
    m, n = R.size, 3 * (6 + t.size) + 5 - 6
    assert fit.residual_rms == pytest.approx(0.05 * np.sqrt(1 - n / m), rel=0.1)


def test_bad_input_is_refused():
    with pytest.raises(InputError):
        reject_range_outliers(np.ones((3, 50)), half_window=2, degree=2)
    with pytest.raises(InputError):
        reject_range_outliers(np.ones((3, 50)), times=np.zeros(50))
    with pytest.raises(InputError):
        reject_range_outliers(np.ones((3, 5)))
    with pytest.raises(InputError):
        fit_offsets_profile_common(np.ones((3, 10)), np.zeros((3, 3)), np.zeros((10, 3)))
    with pytest.raises(InputError):
        fit_offsets_profile_common(np.ones((6, 10)), np.zeros((6, 3)), np.zeros((9, 3)))
    with pytest.raises(InputError):
        fit_offsets_profile_common(np.ones((6, 10)), np.zeros((6, 3)), np.zeros((10, 3)), grid=[0.0, 0.1])


def test_moving_tag_keeps_a_common_range_offset_by_default():
    """moving_tag's default (common_offset="test") on a simulated LPS flight (6 anchors, 240
    tag positions through them, 4 cm noise, multipath spikes) with a common ranging bias of
    -0.17 m: the block test keeps it (|t| ~ 10 measured against t_15's 2.13 at 5 %), within 4
    of its jackknife standard deviations, the result says offsets="common", and the anchors
    come out better than with common_offset="free". Level and power over seeds:
    tests/toa/test_recipes_common_offset.py."""
    from selfcal.experiments.lps import simulate_uwb_flight
    from selfcal.metrics import aligned_rmse
    from selfcal.toa.recipes.recipes import moving_tag

    sim = simulate_uwb_flight(3, n_positions=240, layout="lps", bias_std=0.0)
    A = sim["anchors"]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        rec = moving_tag(sim["ranges"], rng=0, covariance=False)
        free = moving_tag(sim["ranges"], rng=0, common_offset="free", covariance=False)
    test = rec.details["common_offset_test"]
    assert test["adopted"] and rec.result.offsets == "common" and rec.details["offsets"] == "common"
    assert abs(test["value"] + 0.17) < 4 * test["std"]
    assert free.result.offsets == "none" and "common_offset_test" not in free.details
    err = {k: aligned_rmse(r.receivers, A).rmse_receivers for k, r in (("rec", rec), ("free", free))}
    assert err["rec"] < err["free"]
