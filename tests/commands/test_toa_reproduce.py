"""003 reproduction (Fig. 5-7): reduced Monte Carlo against the paper's statements and the CRLB."""

from __future__ import annotations

import json

import numpy as np
import pytest
from click.testing import CliRunner

from selfcal.experiments.runner import run_sweep
from selfcal.experiments.toa_mds_nls import example_network, summarise, trial_003


def _sweep(grid, runs, seed=0):
    return run_sweep(trial_003, grid, runs=runs, seed=seed, progress=False)


@pytest.fixture(scope="module")
def fig6():
    rows = _sweep([{"sigma": s, "n_sources": 10} for s in (0.01, 0.3)], runs=20)
    return {e["sigma"]: e for e in summarise(rows, "sigma")}


def test_fig6_nls_is_efficient_and_about_the_range_error(fig6):
    for sigma, e in fig6.items():
        assert e["failed"] == 0
        # NLS reaches the gauge-free CRLB (ratio measured 0.92-1.0 on 20 runs)
        assert 0.7 < e["nls_rmse"] / e["crlb_rmse"] < 1.3
        # 003: "a position error about the same size as the range error"
        assert 0.3 * sigma < e["nls_rmse"] < 1.2 * sigma


def test_fig6_mds_saturates_and_nls_improves_on_it(fig6):
    lo, hi = fig6[0.01], fig6[0.3]
    # MDS (Alg. 2) near 30 cm at sigma = 30 cm (003 Fig. 6/7): measured 0.38 m RMS, 0.33 median
    assert 0.2 < hi["mds_rmse_median"] < 0.5
    # below 10 cm of noise the eq. 11 approximation dominates: MDS stays at ~10 cm
    assert lo["mds_rmse"] > 5 * lo["nls_rmse"] and lo["mds_rmse"] > 0.05
    assert hi["nls_rmse"] < hi["mds_rmse"]


def test_fig7_more_sources_help_and_mds_approaches_sigma():
    rows = _sweep([{"sigma": 0.3, "n_sources": k} for k in (4, 20)], runs=15, seed=3)
    s = {e["n_sources"]: e for e in summarise(rows, "n_sources")}
    assert s[20]["nls_rmse"] < s[4]["nls_rmse"] and s[20]["mds_rmse"] < s[4]["mds_rmse"]
    assert 0.2 < s[20]["mds_rmse_median"] < 0.4  # 003 Fig. 7: MDS stabilises at ~30 cm


def test_fig5_ellipses_are_calibrated():
    ex = example_network(seed=0)
    # 95 % ellipses from eq. 17: most points inside; sensors better known than sources (003)
    inside = (ex["inside95_receivers"] * 8 + ex["inside95_sources"] * 10) / 18
    assert inside >= 0.7
    assert ex["mean_trace_receivers"] < ex["mean_trace_sources"]


def test_cli_writes_figures_and_json(tmp_path, monkeypatch):
    from selfcal.cli import main
    from selfcal.commands import toa_reproduce

    monkeypatch.setattr(toa_reproduce, "NOISE_LEVELS", (0.1, 0.3))
    monkeypatch.setattr(toa_reproduce, "SOURCE_COUNTS", (6, 10))
    out = tmp_path / "rep"
    res = CliRunner().invoke(main, ["reproduce", "toa-mds-nls", "--runs", "2", "--backend", "serial",
                                    "--out", str(out)])
    assert res.exit_code == 0, res.output
    for name in ("fig5_network.png", "fig6_rmse_vs_noise.png", "fig7_rmse_vs_sources.png", "trials.csv"):
        assert (out / name).stat().st_size > 0
    data = json.loads((out / "toa_mds_nls.json").read_text())
    assert [e["sigma"] for e in data["fig6"]] == [0.1, 0.3]
    assert np.isfinite(data["fig6"][1]["nls_rmse"])


def test_cli_bad_input_exits_2(tmp_path):
    from selfcal.cli import main

    res = CliRunner().invoke(main, ["reproduce", "toa-mds-nls", "--runs", "0", "--out", str(tmp_path / "o")])
    assert res.exit_code == 2 and not (tmp_path / "o" / "toa_mds_nls.json").exists()
    res = CliRunner().invoke(main, ["reproduce", "lps", "--data", str(tmp_path / "nowhere")])
    assert res.exit_code == 2


@pytest.mark.slow
def test_full_reproduction_500_runs():
    rows = _sweep([{"sigma": 0.3, "n_sources": 10}], runs=500, seed=7)
    e = summarise(rows, "sigma")[0]
    assert e["failed"] <= 5
    assert 0.8 < e["nls_rmse_median"] / e["crlb_rmse_median"] < 1.2
    assert 0.25 < e["mds_rmse_median"] < 0.45
