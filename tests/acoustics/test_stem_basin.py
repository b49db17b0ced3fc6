"""Few-unit 3-D conference scenes (issues 3, 7, paper 004): rank-3 candidates ranked by the full
model, the chi-square residual test of ``solve_toa(noise=...)`` and the pipeline's FAIL exit."""

from __future__ import annotations

import json
import warnings
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from selfcal.acoustics.pipeline import one_side_of_plane, timing_noise
from selfcal.cli import main
from selfcal.geometry import align
from selfcal.scenarios.conference import conference_scene
from selfcal.toa import n_parameters, residual_test, solve_toa, toa_model
from selfcal.toa.init.offsets_init import initialize_offsets_candidates

C = 343.0
ROOM = (12.0, 12.0, 3.0)


def _scene(units, layout, seed, jitter=0.0):
    sc = conference_scene(units, ROOM, layout=layout, rng=seed)
    d = np.linalg.norm(sc.receivers[:, None] - sc.senders[None], axis=-1)
    T = d / C + sc.sender_onsets[None] + sc.receiver_delays[:, None]
    return sc, T + np.random.default_rng(seed + 1000).normal(0.0, 1.0, T.shape) * jitter


def _model(r, s, sc):
    """004 eq. 3.1 in seconds: ``|r_i - s_j| / c + delta_i + tau_j`` (toa_model works in metres)."""
    return toa_model(r, s, sc.receiver_delays * C, sc.sender_onsets * C) / C


def _max_error(res, sc):
    """Largest position error after the rigid alignment, microphones on one side of the desks."""
    r = one_side_of_plane(np.asarray(res.receivers), np.zeros((len(res.receivers), 3, 3)), res.sources)[0]
    est, true = np.vstack([r, res.sources]), np.vstack([sc.receivers, sc.senders])
    return float(np.abs(align(est, true, reflection=True).apply(est) - true).max())


def _solve(T, seed, **kw):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return solve_toa(T, dim=3, offsets="both", speed=C, rng=seed, **kw)


def test_stem_8_units_seed_that_landed_in_a_wrong_basin():
    """Scene 0, solver seed 1000: the smallest-F rank-3 start ended 38 m off; now < 1 cm."""
    sc, T = _scene(8, "stem", 0)
    res = _solve(T, 1000, noise=1e-6)
    assert _max_error(res, sc) < 0.01
    assert res.fit is not None and res.fit.passed and res.fit.dof == 64 - n_parameters(8, 8, 3, "both")


@pytest.mark.slow
@pytest.mark.parametrize("scene", [0, 1, 2])
@pytest.mark.parametrize("seed", [0, 1000])
def test_stem_8_units_all_seeds(scene, seed):
    sc, T = _scene(8, "stem", scene)
    assert _max_error(_solve(T, seed, noise=1e-6), sc) < 0.01


def test_candidates_are_distinct_with_the_first_source_offset_zero():
    """At 8 units the rank-3 fit has several F ~ 0 solutions; the candidates keep them apart."""
    sc, T = _scene(8, "stem", 0)
    cands = initialize_offsets_candidates(T * C, 3, rng=1000)
    assert 1 <= len(cands) <= 4
    ps = [np.concatenate([d, o]) for _, _, d, o in cands]
    for a in range(len(ps)):
        for b in range(a):
            assert np.linalg.norm(ps[a] - ps[b]) > 1e-9
    for r, s, d, o in cands:
        assert r.shape == (8, 3) and s.shape == (8, 3) and d.shape == (8,) and o.shape == (8,)
        assert o[0] == 0.0


def test_residual_test_accepts_the_truth_and_rejects_a_wrong_geometry():
    sc, T = _scene(12, "tiered", 1, jitter=1e-6)
    n = n_parameters(12, 12, 3, "both")
    truth = T - _model(sc.receivers, sc.senders, sc)
    ok = residual_test(truth, 1e-6, 0)  # at the truth the residuals are the noise: 144 dof
    assert ok.passed and ok.p_value > 1e-3 and ok.dof == 144
    # a microphone mirrored through its desk (a wrong basin of the mirror type), offsets kept
    r = sc.receivers.copy()
    r[3, 2] = 2 * sc.senders[3, 2] - r[3, 2]
    bad = residual_test(T - _model(r, sc.senders, sc), 1e-6, n)
    assert not bad.passed and bad.p_value < 1e-3 and bad.chi2 > 10 * bad.dof
    # the refined fit from the truth passes; the same fit against a 100x smaller noise does not
    res = _solve(T, 0, noise=1e-6, method="nls",
                 init=(sc.receivers, sc.senders, sc.receiver_delays, sc.sender_onsets))
    assert res.fit is not None and res.fit.passed and res.to_dict()["fit"]["dof"] == 144 - n
    assert not _solve(T, 0, noise=1e-8, method="nls",
                      init=(sc.receivers, sc.senders, sc.receiver_delays, sc.sender_onsets)).fit.passed


def test_deep_search_runs_only_when_the_first_fit_fails():
    sc, T = _scene(12, "tiered", 1, jitter=1e-6)
    good = _solve(T, 0, noise=1e-6)
    assert good.fit.passed and good.success
    T2 = T.copy()
    T2[2, 5] += 2e-3  # one corrupted TOA (70 cm): no geometry fits it at 1 us
    bad = _solve(T2, 0, noise=1e-6)
    # the search (toa/search.py) tries more candidates, and the verdict stays honest
    assert "search" in bad.method and not bad.fit.passed and not bad.success


def test_timing_noise_adds_jitter_and_has_a_floor():
    q = np.full((4, 8), 200.0)  # huge quality: the matched-filter std is far below the 20 ns floor
    senders = np.repeat(np.arange(4), 2)  # two events per sender, averaged
    floor = timing_noise(q, (1000.0, 8000.0), senders, 4)
    assert floor == pytest.approx(20e-9 / np.sqrt(2))
    assert timing_noise(q, (1000.0, 8000.0), senders, 4, jitter=5e-6) == pytest.approx(
        np.sqrt((20e-9**2 + 5e-6**2) / 2))
    low = timing_noise(np.full((4, 8), 20.0), (1000.0, 8000.0), senders, 4)
    assert low > floor  # 20 dB: 3 / (2 pi f_rms 10) is above the floor


def _simulate(out: Path, jitter_us: float) -> None:
    res = CliRunner().invoke(main, ["simulate", "conference", "--units", "10", "--room", "8x7x3", "--rt60", "0.4",
                                    "--snr", "30", "--seed", "2", "--layout", "flat", "--sample-rate", "16000",
                                    "--max-order", "2", "--jitter-us", str(jitter_us), "--out", str(out)])
    assert res.exit_code == 0, res.output


def test_pipeline_cli_exits_1_when_the_fit_fails_the_residual_test(tmp_path):
    rec = tmp_path / "rec"
    _simulate(rec, 30.0)  # 30 us clock jitter in the recording
    assert json.loads((rec / "setup.json").read_text())["clock_jitter"] == pytest.approx(30e-6)
    out = tmp_path / "result.json"
    args = ["pipeline", str(rec), "--out", str(out), "--heights", str(rec / "heights.json")]
    res = CliRunner().invoke(main, args)  # the jitter declared in setup.json is in the noise: the fit is fine,
    # but one event per sender at 30 us leaves the delays too uncertain for 004 (issue 15: an honest FAIL)
    assert res.exit_code == 1, res.output
    assert "requirement not met: delay std" in res.output and "repeat the probes" in res.output
    data = json.loads(out.read_text())
    assert data["fit"]["passed"] and data["fit"]["dof"] > 0 and data["failed"] is True
    res = CliRunner().invoke(main, [*args, "--jitter", "0"])  # declared: no jitter -> residuals far too large
    assert res.exit_code == 1
    assert "FAIL: calibration failed the residual test" in res.output
    data = json.loads(out.read_text())
    assert data["failed"] is True and not data["fit"]["passed"]
    assert any("positions NOT reliable" in n for n in data["notes"])


@pytest.mark.parametrize("bad", [-1e-6, "5us", float("inf")])
def test_setup_clock_jitter_must_be_a_nonnegative_number(bad):
    from selfcal.acoustics.recording import parse_setup
    from selfcal.errors import InputError

    raw = {"sample_rate": 48000, "receivers": ["a"], "senders": ["a"],
           "probe": {"type": "chirp", "f0": 500, "f1": 8000, "duration": 0.05},
           "events": [{"sender": "a", "time": 0.1}], "clock_jitter": bad}
    with pytest.raises(InputError, match="clock_jitter"):
        parse_setup(raw)
    raw["clock_jitter"] = 2e-6
    assert parse_setup(raw).clock_jitter == 2e-6
