"""The moving-tag recipe's common range offset: block jackknife t test over time blocks.

Simulated LPS-like flights (``simulate_uwb_flight(layout="lps")``: 6 anchors in a
2.4 x 2.0 x 1.2 m volume, the tag flying through it) with the faults of the real system.
Each case starts the test from the offsets-free fit refined from the truth, so the
property tested is the test's, not the search's.
"""

from __future__ import annotations

import types

import numpy as np
import pytest

from selfcal.experiments.lps import simulate_uwb_flight
from selfcal.toa.engine.nls import refine_toa
from selfcal.toa.recipes.common_offset import (
    COMMON_OFFSET_ALPHA,
    MAX_BLOCKS,
    block_edges,
    block_offset_test,
    residual_correlation_length,
)


def _base(sim):
    """Offsets-free fit of a clean simulated flight, started at the truth (the recipe's base)."""
    Y = sim["ranges"]
    sol = refine_toa(Y, sim["anchors"], sim["tag"], covariance=False)
    base = types.SimpleNamespace(receivers=sol.receivers, sources=sol.sources, residuals=sol.residuals,
                                 outliers=np.zeros(Y.shape, bool), dim=3)
    return base, Y


def _flight(seed, n=240, **kw):
    # no spikes / sparse positions: the recipe removes those before this test runs
    return simulate_uwb_flight(seed, n, layout="lps", spike_rate=0.0, missing=0.0, sparse_positions=0, **kw)


def test_correlation_length_of_white_and_ar1_noise():
    """White residuals enter the 95 % band at lag 1; AR(1) with rho = 0.8 has autocorrelation
    0.8^l, inside the band 1.96 / sqrt(2000) = 0.044 from l = 14. The mean of 6 sample
    autocorrelations has a standard error ~0.02 there (Bartlett: (1 + rho^2) / (1 - rho^2) / n
    per row), so the first entry lies where 0.8^l -+ 0.04 crosses 0.044: l in [11, 25]."""
    from scipy.signal import lfilter

    rng = np.random.default_rng(0)
    assert residual_correlation_length(rng.standard_normal((6, 2000))) <= 2
    E = lfilter([1.0], [1.0, -0.8], rng.standard_normal((6, 2000)), axis=1)
    assert 10 <= residual_correlation_length(E) <= 26
    e = block_edges(600, 48)
    assert len(e) - 1 == 12 and e[0] == 0 and e[-1] == 600
    assert len(block_edges(600, 1)) - 1 == MAX_BLOCKS


def _decisions(kind, seeds):
    kw = {"common": {"bias_std": 0.0}, "none": {"bias_std": 0.0, "bias_mean": 0.0},
          "none_ar": {"bias_std": 0.0, "bias_mean": 0.0, "noise_corr": 0.8}}[kind]
    out = []
    for seed in seeds:
        sim = _flight(seed, **kw)
        _, info = block_offset_test(*_base(sim))
        out.append(info)
    return out


def test_common_bias_of_the_documented_size_is_kept():
    """A common bias of -0.17 m (the documented LPS mean) on 240 positions: the jackknife
    standard error is ~0.015 m (measured), so |t| ~ 11 against the t_15 quantile 2.13 at
    5 %: kept, with the value within 4 standard errors of the truth."""
    for info in _decisions("common", [1]):  # seed 0: the frame test below
        assert info["adopted"], info
        assert abs(info["value"] + 0.17) < 4 * info["std"] + 0.02


def test_no_bias_is_not_kept_even_with_serially_correlated_noise():
    """Without a bias the test keeps the offset with probability 5 % per flight (these seeds:
    |t| = 1.1 and 0.2); with AR(1) noise (rho = 0.8, the measured flights' lag-1 residual
    autocorrelation) the blocks grow to the correlation length and the level holds, where
    the iid nested F test does not (it counts 1440 ranges as independent)."""
    infos = _decisions("none", [0]) + _decisions("none_ar", [0])
    assert not any(i["adopted"] for i in infos), infos
    assert infos[-1]["correlation_length"] > 3  # the AR(1) residuals made the blocks longer


@pytest.mark.slow
def test_block_test_level_and_power_over_seeds():
    """10 seeds each (~100 s CPU). Power: common bias -0.17 m kept on >= 8 of 10 (measured
    10 of 10, |t| 2.9-14 against t_15's 2.13; the weakest seed's trajectory determines c
    least). Level 5 %: no bias, white or AR(1) noise, kept on <= 4 of 20 (Binomial(20, 0.05)
    >= 5 has probability 1.6 %; measured 0 of 20, largest |t| 2.1)."""
    assert COMMON_OFFSET_ALPHA == 0.05
    kept = sum(i["adopted"] for i in _decisions("common", range(10)))
    assert kept >= 8
    null = _decisions("none", range(10)) + _decisions("none_ar", range(10))
    assert sum(i["adopted"] for i in null) <= 4


def test_kept_common_offset_is_reported_and_kept_by_frame_refits():
    """With a kept common offset the result says offsets="common" (one value for every
    anchor), and a --frame / --known refit fits that model, not one offset per anchor."""
    from selfcal.toa.frame.frame import apply_frame
    from selfcal.toa.frame.known import fit_known
    from selfcal.toa.frame.nodes import parse_known
    from selfcal.toa.recipes.common_offset import choose_common_offset
    from selfcal.toa.solve import solve_toa

    sim = _flight(0, bias_std=0.0)
    Y = sim["ranges"]
    base = solve_toa(Y, dim=3, offsets="none", rng=0)
    res, info = choose_common_offset(base, Y)
    assert info["adopted"] and res.offsets == "common"
    assert np.ptp(res.receiver_offsets) == 0.0
    # the noise estimate is the new fit's (the 0.17 m bias no longer inflates it)
    assert res.sigma == res.noise_estimate < base.noise_estimate
    nodes = parse_known({f"r{i}": sim["anchors"][i] for i in range(6)}, 6, Y.shape[1], 3)
    framed = fit_known(Y, res, nodes, offsets="common")
    assert framed.result.offsets == "common"
    offs = np.asarray(framed.result.receiver_offsets)
    assert np.ptp(offs) < 1e-12 and abs(offs[0] + 0.17) < 0.05
    # the reference-frame covariance refit keeps the model too (finite, one offset)
    fr = apply_frame(res, "origin=r0,x=r1,xy=r2", matrix=Y, offsets="common")
    assert fr.result.offsets == "common" and np.isfinite(fr.result.receiver_cov).all()


def test_cli_reports_the_common_offset_and_keeps_it_in_the_frame_refit(tmp_path):
    """``calibrate toa`` (defaults) on a simulated LPS flight with a common bias: the JSON says
    offsets "common" with one value, the summary line says so, and ``--frame`` refits it."""
    import json

    from click.testing import CliRunner

    from selfcal.cli import main

    sim = _flight(1, bias_std=0.0)
    csv = tmp_path / "f.csv"
    np.savetxt(csv, sim["ranges"], delimiter=",")
    out = tmp_path / "r.json"
    res = CliRunner().invoke(main, ["calibrate", "toa", str(csv), "--frame", "origin=r0,x=r1,xy=r2", "--out", str(out)])
    assert res.exit_code == 0, res.output
    data = json.loads(out.read_text())
    assert data["offsets"] == "common" and data["recipe"]["common_offset_test"]["adopted"]
    offs = np.array(data["receiver_offsets"], float)
    assert np.ptp(offs) < 1e-12 and abs(offs[0] + 0.17) < 0.05
    assert "offsets=common" in res.output
