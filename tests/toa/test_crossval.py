"""Offset (ranging-bias) models chosen by held-out prediction (selfcal.toa.verdict.crossval), issue 29."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from selfcal.experiments.lps import simulate_uwb_flight
from selfcal.toa.engine.nls import refine_toa
from selfcal.toa.verdict.crossval import (
    SIGN_ALPHA,
    cross_validate,
    locate_sources,
    one_se_choice,
    sign_test_p,
)


def test_locate_sources_recovers_exact_positions_and_offsets():
    """Noise-free ranges: every column's position (and offset) exactly; the leverages of a
    column sum to its number of parameters (the trace of a projection)."""
    for seed in range(5):
        g = np.random.default_rng(seed)
        R, S = g.uniform(0, 5, (7, 3)), g.uniform(1, 4, (30, 3))
        d = g.normal(-0.1, 0.1, 7)
        o = g.normal(0, 0.3, 30)
        Y = np.linalg.norm(R[:, None] - S[None], axis=2) + d[:, None]
        X, _, E, H = locate_sources(Y, R, d)
        np.testing.assert_allclose(X, S, atol=1e-6)
        np.testing.assert_allclose(H.sum(axis=0), 3, atol=1e-8)
        X2, o2, _, H2 = locate_sources(Y + o[None], R, d, source_offset=True)
        np.testing.assert_allclose(X2, S, atol=1e-5)
        np.testing.assert_allclose(o2, o, atol=1e-5)
        np.testing.assert_allclose(H2.sum(axis=0), 4, atol=1e-8)
        assert np.nanmax(np.abs(E)) < 1e-8


def test_locate_sources_leaves_underdetermined_columns_nan():
    g = np.random.default_rng(1)
    R, S = g.uniform(0, 5, (6, 3)), g.uniform(1, 4, (5, 3))
    Y = np.linalg.norm(R[:, None] - S[None], axis=2)
    Y[:3, 2] = np.nan  # 3 ranges: a 3-D point needs 4 to be scored
    X, _, E, H = locate_sources(Y, R)
    assert np.isnan(X[2]).all() and np.isnan(E[:, 2]).all() and np.isfinite(X[[0, 1, 3, 4]]).all()


def test_one_se_rule_keeps_the_simpler_model_within_one_standard_error():
    fold = {"common": [1.0, 1.2, 0.8, 1.1], "receivers": [0.9, 1.25, 0.85, 1.0]}
    scores = {k: float(np.mean(v)) for k, v in fold.items()}
    chosen, best, se = one_se_choice(scores, fold, 6, 400)
    assert best == "receivers" and chosen == "common"  # 0.0375 better, se of the difference 0.043
    fold["receivers"] = [0.5, 0.6, 0.4, 0.55]
    scores = {k: float(np.mean(v)) for k, v in fold.items()}
    assert one_se_choice(scores, fold, 6, 400)[0] == "receivers"


def _plain_one_se(scores, fold):
    """The one-SE rule without the sign test, written out here (the independent computation)."""
    best = min(scores, key=scores.get)
    d = np.asarray(fold["sources"]) - np.asarray(fold["both"])
    se = np.std(d, ddof=1) / np.sqrt(d.size)
    return "sources" if best == "sources" or scores["sources"] - scores["both"] <= se else "both"


def _pooled(fold, sizes):
    """Entry-pooled CV scores from per-fold means (folds of unequal size, as cross_validate pools them)."""
    return {m: float(np.dot(v, sizes) / sizes.sum()) for m, v in fold.items()}


@pytest.mark.parametrize("draws", [400, pytest.param(4000, marks=pytest.mark.slow)])
def test_sign_test_adopts_the_model_that_wins_every_fold_and_keeps_its_level(draws):
    """The sign test added to the one-SE rule, on synthetic per-fold scores (K = 10 folds of 1 or 2
    sources, as 14 sources give; "sources" the simpler model, "both" the larger one).

    - Heavy-tailed wins: "both" better in every fold by a factor exp(N(3, 2)) (log-normal, so a
      few folds carry most of the difference). It is always adopted; the plain one-SE rule
      (computed here independently) keeps "sources" in 9.8 % of these draws (measured, 4000
      draws), which is the failure the sign test repairs.
    - Null: the two models' fold scores exchangeable (a log-normal common scale times
      independent heavy-tailed Student-t1 factors per model): the sign test can only remove the
      simpler model where the plain rule kept it, so the larger model's extra adoptions are sign-test
      rejections under the null, at most P(10 of 10) = 2^-10 per draw; asserted below
      SIGN_ALPHA (0.01) with binomial slack (measured: 1 of 4000 draws; the plain rule adopts
      the larger model in 21 % of the null draws, as a one-SE rule at t > 1 does)."""
    g = np.random.default_rng(2929)
    sizes = np.array([1, 2, 1, 2, 1, 1, 2, 1, 2, 1], float)
    kept_by_plain, extra = 0, 0
    for _ in range(draws):
        base = np.exp(g.normal(-5, 1, 10))
        fold = {"sources": list(base * np.exp(g.normal(3, 2, 10)) + base), "both": list(base)}
        scores = _pooled(fold, sizes)
        assert one_se_choice(scores, fold, 10, 14)[0] == "both"
        kept_by_plain += _plain_one_se(scores, fold) == "sources"
        scale = np.exp(g.normal(-5, 1, 10))
        fold = {m: list(scale * np.exp(0.5 * np.clip(g.standard_t(1, 10), -20, 20))) for m in ("sources", "both")}
        scores = _pooled(fold, sizes)
        new, plain = one_se_choice(scores, fold, 10, 14)[0], _plain_one_se(scores, fold)
        assert not (new == "sources" and plain == "both")  # the sign test never favours the simpler model
        extra += new == "both" and plain == "sources"
    assert kept_by_plain > 0  # the plain rule does fail on heavy-tailed wins
    assert extra <= SIGN_ALPHA * draws + 3 * np.sqrt(SIGN_ALPHA * draws)


def test_sign_test_p_is_the_binomial_tail():
    """Against the binomial tail written out: wins w of n non-tied folds -> sum_{k >= w} C(n, k) / 2^n."""
    from math import comb

    g = np.random.default_rng(7)
    for _ in range(50):
        n = int(g.integers(1, 13))
        a, b = g.normal(size=n), g.normal(size=n)
        b[g.random(n) < 0.2] = np.nan
        ok = np.isfinite(b)
        w, m = int((a[ok] > b[ok]).sum()), int(ok.sum())
        want = sum(comb(m, k) for k in range(w, m + 1)) / 2**m if m else 1.0
        assert sign_test_p(a, b) == pytest.approx(want)


def _choice(seed, bias_std, layout="lps", n=300):
    """The CV choice between a common offset and per-anchor offsets on one simulated flight.

    Both models are refined from the truth (the choice rule isolated from the search):
    ``simulate_uwb_flight`` with per-anchor biases N(-0.17, bias_std^2) m, AR-free noise of
    4 cm, no spikes (the recipe removes them before the choice)."""
    sim = simulate_uwb_flight(seed, n, layout=layout, bias_std=bias_std, spike_rate=0.0, sparse_positions=0)
    Y = sim["ranges"]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        com = refine_toa(Y, sim["anchors"], sim["tag"], offsets="receivers", common_offsets="receivers",
                         covariance=False)
        rec = refine_toa(Y, com.receivers, com.sources, offsets="receivers", receiver_offsets0=com.receiver_offsets,
                         covariance=False)
    st = {"common": (com.receivers, com.sources, com.receiver_offsets, None),
          "receivers": (rec.receivers, rec.sources, rec.receiver_offsets, None)}
    return cross_validate(Y, st)


def test_bias_model_choice_on_simulated_flights_reduced():
    """Reduced version of the slow test below: 5 draws each. Over 20 draws (slow test) the
    per-anchor model was adopted on 2 / 20 flights without per-anchor biases and on 17 / 20
    with biases of 0.15 m std; the bounds here allow one draw more on the wrong side
    (P(>= 2 false of 5) ~ 8 % at the measured 10 % rate; these draws: 0 and 5)."""
    no = [_choice(s, 0.0).chosen for s in range(5)]
    yes = [_choice(s, 0.15).chosen for s in range(5)]
    assert no.count("receivers") <= 1
    assert yes.count("receivers") >= 4


@pytest.mark.slow
def test_bias_model_choice_on_simulated_flights_over_many_draws():
    """How often the held-out choice is right, 20 draws per case (LPS geometry: the tag flies
    through the anchor volume, so per-anchor biases are identifiable; 4 cm noise).
    Measured per-anchor adoptions: bias std 0 -> 2 / 20 (false adoptions: the one-SE rule
    bounds them near the one-sided 16 % of a 1-SE excursion; measured 10 %), 0.05 m -> 3,
    0.1 m -> 13, 0.15 m -> 17, 0.2 m -> 18 of 20. Biases below the noise are often not
    worth their parameters for prediction; the bounds leave 2-3 draws of margin."""
    rate = {bs: [_choice(s, bs).chosen for s in range(20)].count("receivers") for bs in (0.0, 0.1, 0.15, 0.2)}
    assert rate[0.0] <= 4
    assert rate[0.1] >= 10 and rate[0.15] >= 15 and rate[0.2] >= 16


def test_cross_validate_reports_its_evidence():
    cv = _choice(3, 0.15)
    d = cv.to_dict()
    assert d["chosen"] in ("common", "receivers") and d["folds"] >= 4
    assert set(d["cv_rmse"]) == {"common", "receivers"} and d["entries"] > 0
    assert all(len(v) == d["folds"] for v in d["fold_mse"].values())
    assert "held-out" in cv.line()


def test_progress_is_silent_off_a_terminal_and_under_quiet(capsys):
    from selfcal import progress

    progress.set_quiet(False)
    with progress.stage("x", 3) as update:
        update(1)
        progress.report(2, 3)
    progress.set_quiet(True)
    assert not progress.enabled()
    progress.set_quiet(False)
    assert capsys.readouterr().err == ""  # pytest's stderr is not a terminal


def test_cli_default_adopts_per_anchor_biases_reports_the_evidence_and_keeps_them_with_known(tmp_path):
    """``calibrate toa`` with its defaults on a simulated LPS flight with per-anchor biases
    of 0.2 m std: the JSON says offsets "receivers" with the held-out evidence in the recipe
    block, the summary has the choice line, and ``--known`` refits the same model."""
    import json

    from click.testing import CliRunner

    from selfcal.cli import main

    sim = simulate_uwb_flight(4, 400, layout="lps", bias_std=0.2)
    csv = tmp_path / "f.csv"
    np.savetxt(csv, sim["ranges"], delimiter=",")
    out = tmp_path / "r.json"
    res = CliRunner().invoke(main, ["calibrate", "toa", str(csv), "--out", str(out)])
    assert res.exit_code in (0, 1), res.output
    data = json.loads(out.read_text())
    ch = data["recipe"]["offsets_choice"]
    assert data["offsets"] == "receivers" and ch["chosen"] == "receivers"
    assert ch["cv_mse"]["receivers"] < ch["cv_mse"]["common"] and ch["folds"] >= 4
    assert "by held-out prediction" in res.output
    known = tmp_path / "k.csv"
    known.write_text("".join(f"r{i},{x},{y},{z}\n" for i, (x, y, z) in enumerate(sim["anchors"][:4])))
    out2 = tmp_path / "k.json"
    res2 = CliRunner().invoke(main, ["calibrate", "toa", str(csv), "--known", str(known), "--out", str(out2)])
    assert res2.exit_code in (0, 1), res2.output
    d2 = json.loads(out2.read_text())
    assert d2["offsets"] == "receivers" and np.ptp(d2["receiver_offsets"]) > 0.05


def _error_bars(bias_model: bool, draws: int):
    """Empirical RMS anchor error (aligned to the truth) and the stated std, per anchor,
    over ``draws`` noise draws of one LPS flight with per-anchor biases of 0.15 m std."""
    from selfcal.geometry import align

    sim = simulate_uwb_flight(2, 400, layout="lps", bias_std=0.15, spike_rate=0.0, sparse_positions=0, missing=0.0)
    A, T, b = sim["anchors"], sim["tag"], sim["bias"]
    D = np.linalg.norm(A[:, None] - T[None], axis=2) + b[:, None]
    g = np.random.default_rng(0)
    errs, stds = [], []
    kw = {"offsets": "receivers"} if bias_model else {"offsets": "receivers", "common_offsets": "receivers"}
    for _ in range(draws):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            t = refine_toa(D + 0.04 * g.standard_normal(D.shape), A, T, receiver_offsets0=b, **kw)
        al = align(t.receivers, A)
        errs.append(t.receivers @ al.rotation.T + al.translation - A)
        stds.append(np.sqrt(np.trace(t.receiver_cov, axis1=1, axis2=2)))
    return np.sqrt(np.mean(np.sum(np.array(errs) ** 2, axis=2), axis=0)), np.mean(stds, axis=0)


def test_error_bars_cover_the_truth_with_the_bias_model_and_miss_without():
    """Per-anchor biases present (0.15 m std, 4 cm noise), 20 draws: with the per-anchor model
    the stated std of each anchor is its empirical RMS error within 35 % (measured 0.023-0.080
    vs 0.024-0.076 m over 40 draws; 20 draws estimate an RMS to ~10 %); with one common offset
    the errors are the unmodelled biases', measured 4.8-22.7 times the stated std on every
    anchor (issue 29: up to 8 sigma on the shared flights)."""
    emp, std = _error_bars(True, 20)
    np.testing.assert_allclose(std, emp, rtol=0.35)
    emp0, std0 = _error_bars(False, 5)
    assert np.min(emp0 / std0) > 3


def _bias_choice(family: str, seeds):
    """The default path's bias choice (``calibrate toa`` defaults up to the choice) on simulated
    LPS flights of one family of benchmarks/lps_bias_choice.py, both anchor models scored."""
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
    from lps_bias_choice import FAMILIES, score

    out = []
    for s in seeds:
        sim = simulate_uwb_flight(s, 500, layout="lps", **FAMILIES[family])
        out.append(score(sim["ranges"], sim["anchors"]))
    return out


def test_anchor_mse_is_the_shift_and_spreads_of_the_refits():
    """Independent computation: refits equal to the fits (no spread) leave MSE_simple = the
    squared shift and MSE_wide = 0; refits shifted alike leave the shift's noise at zero."""
    from selfcal.toa.verdict.focused import anchor_mse

    g = np.random.default_rng(0)
    R = g.uniform(0, 3, (6, 3))
    W = R + g.normal(0, 0.1, R.shape)
    W -= W.mean(0) - R.mean(0)
    st = {"common": (R,), "receivers": (W,)}
    est = anchor_mse("common", "receivers", st, {"common": [R] * 5, "receivers": [W] * 5})
    from selfcal.geometry import align

    shift = np.sqrt(np.mean(np.sum((R - align(W, R, reflection=False).apply(W)) ** 2, axis=1)))
    assert est.rmse["receivers"] == pytest.approx(0, abs=1e-9)
    assert est.rmse["common"] == pytest.approx(shift, rel=1e-9) and est.shift == pytest.approx(shift, rel=1e-9)
    jit = [g.normal(0, 0.05, R.shape) for _ in range(8)]
    est = anchor_mse("common", "receivers", st, {"common": [R + j for j in jit], "receivers": [W + j for j in jit]})
    assert est.shift_noise < 0.02 < est.spread["common"]  # the same jitter in both cancels in the shift


def test_bias_choice_keeps_real_biases_and_refuses_position_errors_reduced():
    """Reduced version of the slow test below (3 draws per family): per-anchor biases of
    0.25 m std are kept (measured 6 of 10 draws, these 3 of 3; the bound allows one draw
    more on the wrong side), and on flights with position-dependent errors and no biases
    the chosen anchor model is the more accurate one (measured 9 of 10, these 3 of 3)."""
    yes = _bias_choice("biases25", range(3))
    assert sum(r["chosen"] == "receivers" for r in yes) >= 2
    pos = _bias_choice("position", range(3))
    assert sum(r["right_final"] for r in pos) >= 2
    for r in yes + pos:  # the evidence is reported for both models
        assert r["anchor_rmse_est"] is not None and len(r["anchor_rmse_est"]) == 2


@pytest.mark.slow
def test_bias_choice_over_simulated_families():
    """How often the default choice is right, 10 draws per family of benchmarks/lps_bias_choice.py
    ("right": the chosen anchor model's RMSE within 1 cm of the better of the two).

    Measured (seeds 0-9), right by prediction alone / with the anchor check: no offsets 10/10,
    common 10/10, biases 0.10 m 7/7, 0.15 m 7/6, 0.25 m 8/8, position-dependent 8/9, NLOS
    10/10, biases + position 7/9, biases + AR + NLOS 8/8. The property the check adds: where
    the per-anchor refit's anchors are worse by over 5 cm (48 draws), prediction alone adopts
    it 9 times, with the check once; its price: where they are better by over 5 cm (21 draws)
    it is adopted 13 times instead of 20. The bounds leave about two draws of margin."""
    fams = ("none", "common", "biases10", "biases15", "biases25", "position", "nlos",
            "biases15+position", "biases10+ar+nlos")
    rows = {f: _bias_choice(f, range(10)) for f in fams}
    right = {f: sum(r["right_final"] for r in rs) for f, rs in rows.items()}
    for f in ("none", "common", "nlos"):
        assert right[f] >= 9, (f, right[f])
    for f in ("biases10", "biases15", "biases25", "position", "biases15+position", "biases10+ar+nlos"):
        assert right[f] >= 5, (f, right[f])
    allr = [r for rs in rows.values() for r in rs]
    worse = [r for r in allr if r["rmse_wide"] > r["rmse_simple"] + 0.05]
    better = [r for r in allr if r["rmse_wide"] < r["rmse_simple"] - 0.05]
    assert sum(r["chosen"] == "receivers" for r in worse) <= max(3, len(worse) // 10)
    assert sum(r["chosen"] == "receivers" for r in better) >= len(better) // 2
    assert sum(r["right_final"] for r in allr) >= sum(r["right_pred"] for r in allr) - 3
