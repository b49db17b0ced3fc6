"""Fixed-lag range-SLAC smoother (issue 31): the RTS recursion limited to the next ``lag_s`` seconds of
data. Its two limits are independent computations (the filtered pass, the whole-log RTS over the same
pass); in between it improves on the causal filter."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from selfcal.errors import InputError
from selfcal.slac import ranging
from selfcal.slac.ranging import RangeModelConfig, solve_range_slac
from tests.slac.test_ranging import synthetic


def _pass(log, cfg):  # type: ignore[no-untyped-def]
    ch = ranging._build_chain(log, cfg)
    return ch, ranging._forward(ch, log, cfg, cfg.range_noise, ref=None, weights=None, store=True,
                                progress=False)


@pytest.mark.parametrize("seed", range(2))
def test_limits_are_the_filter_and_the_whole_log_rts(seed):
    log, _ = synthetic(seed, n=300)
    cfg = RangeModelConfig()
    ch, ps = _pass(log, cfg)
    ms0, _ = ranging._fixed_lag(ps, ch.times, 1e-9)  # no data after a node: the filtered estimate
    np.testing.assert_allclose(ms0, ps.mf, atol=1e-12)
    msL, PsL = ranging._fixed_lag(ps, ch.times, 1e9)  # the whole log: the RTS smoother
    ms, Ps, _ = ranging._rts(ps)
    np.testing.assert_allclose(msL, ms, atol=1e-9)
    np.testing.assert_allclose(PsL, Ps, atol=1e-9)


def _rmse(p: np.ndarray, truth: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum((p[100:, :2] - truth[100:, :2]) ** 2, axis=1))))


def _improves(seeds: range) -> None:
    for seed in seeds:
        log, truth = synthetic(seed)
        f = solve_range_slac(log, method="filter")
        fl = solve_range_slac(log, method="fixed-lag", config=RangeModelConfig(lag_s=30.0))
        assert fl.method == "fixed-lag" and fl.poses.shape == truth.shape

        assert _rmse(fl.poses, truth) < _rmse(f.poses, truth)


def test_fixed_lag_improves_on_the_filter():
    # synthetic laps (7 % scale error, 3 % multipath outliers): 30 s of look-ahead lowers the
    # position RMSE below the causal filter's on each (measured on 4 of 4 seeds, test_..._slow)
    _improves(range(20, 21))


@pytest.mark.slow
def test_fixed_lag_improves_on_the_filter_slow():
    _improves(range(20, 24))


def test_lag_is_validated():
    with pytest.raises(InputError, match="lag_s"):
        RangeModelConfig(lag_s=0.0)
    assert dataclasses.asdict(RangeModelConfig())["lag_s"] == 30.0
