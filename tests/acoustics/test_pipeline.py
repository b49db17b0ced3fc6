"""Pipeline: per-sender matrix, planarity, known-height refinement, end to end (issue 7, paper 004)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from selfcal.acoustics.pipeline import (
    planarity,
    read_heights,
    refine_known_heights,
    sender_matrix,
)
from selfcal.cli import main
from selfcal.errors import InputError
from selfcal.scenarios.conference import conference_scene

C = 343.0


def _toa(scene, noise=0.0, rng=None):
    d = np.linalg.norm(scene.receivers[:, None] - scene.senders[None], axis=-1)
    T = d / C + scene.sender_onsets[None] + scene.receiver_delays[:, None]
    if noise:
        T = T + np.random.default_rng(rng).normal(0, noise, T.shape)
    return T


def test_sender_matrix_averages_repeated_events_and_keeps_nan():
    toa = np.array([[1.0, 3.0, 5.0], [np.nan, 2.0, np.nan], [np.nan, np.nan, np.nan]])
    T = sender_matrix(toa, np.array([0, 0, 1]), 2)
    np.testing.assert_array_equal(T[:, 0], [2.0, 2.0, np.nan])
    np.testing.assert_array_equal(T[:, 1], [5.0, np.nan, np.nan])


def test_planarity_separates_flat_desks_from_3d_layouts():
    flat = conference_scene(20, (12.0, 12.0, 3.0), layout="boundary", rng=1)
    assert planarity(np.vstack([flat.receivers, flat.senders])).near_planar
    for layout in ("tiered", "stem"):
        sc = conference_scene(20, (12.0, 12.0, 3.0), layout=layout, rng=1)
        assert not planarity(np.vstack([sc.receivers, sc.senders])).near_planar
    # A thick layout whose z is poorly determined (large normal variance) is also flagged.
    sc = conference_scene(20, (12.0, 12.0, 3.0), layout="stem", rng=1)
    pts = np.vstack([sc.receivers, sc.senders])
    cov = np.tile(np.diag([1e-4, 1e-4, 0.5]), (40, 1, 1))
    p = planarity(pts, cov)
    assert p.near_planar and abs(abs(p.normal[2]) - 1) < 1e-3 and p.normal_std == pytest.approx(np.sqrt(0.5), rel=1e-3)


def test_known_heights_refinement_recovers_geometry_and_offsets():
    sc = conference_scene(12, (10.0, 8.0, 3.0), layout="flat", rng=5)
    T = _toa(sc)
    g = np.random.default_rng(0)
    sol = refine_known_heights(
        T, sc.receivers[:, 2], sc.senders[:, 2],
        sc.receivers[:, :2] + g.normal(0, 0.2, (12, 2)), sc.senders[:, :2] + g.normal(0, 0.2, (12, 2)),
        sc.receiver_delays + 0.002, sc.sender_onsets + g.normal(0, 0.002, 12), speed=C,
    )
    assert sol.converged and sol.residual_rms < 1e-9
    from selfcal.geometry import align

    est = np.vstack([sol.receivers, sol.sources])
    true = np.vstack([sc.receivers, sc.senders])
    al = align(est[:, :2], true[:, :2])
    assert np.abs(al.apply(est[:, :2]) - true[:, :2]).max() < 1e-6
    np.testing.assert_allclose(est[:, 2], true[:, 2])  # heights are given, never re-estimated
    assert sol.source_offsets[0] == 0.0
    np.testing.assert_allclose(sol.source_offsets, sc.sender_onsets - sc.sender_onsets[0], atol=1e-9)
    np.testing.assert_allclose(sol.receiver_offsets, sc.receiver_delays + sc.sender_onsets[0], atol=1e-9)
    assert np.all(sol.receiver_cov[:, 2, :] == 0)


def test_known_heights_covariance_matches_monte_carlo_spread():
    """The reported horizontal covariance predicts the scatter of repeated noisy solves."""
    sc = conference_scene(10, (9.0, 8.0, 3.0), layout="flat", rng=8)
    sigma = 5e-6
    from selfcal.geometry import align

    errs, covs = [], []
    for k in range(30):
        T = _toa(sc, sigma, rng=k)
        sol = refine_known_heights(T, sc.receivers[:, 2], sc.senders[:, 2], sc.receivers[:, :2], sc.senders[:, :2],
                                   sc.receiver_delays, sc.sender_onsets, speed=C)
        est = np.vstack([sol.receivers, sol.sources])[:, :2]
        true = np.vstack([sc.receivers, sc.senders])[:, :2]
        errs.append(align(est, true, reflection=False).apply(est) - true)
        covs.append(np.trace(sol.receiver_cov[:, :2, :2], axis1=1, axis2=2).mean())
    mc = np.mean(np.sum(np.array(errs)[:, :10] ** 2, axis=2))
    assert 0.4 < mc / np.mean(covs) < 2.5


def test_read_heights_validates_names_and_lengths(tmp_path):
    p = tmp_path / "h.json"
    p.write_text(json.dumps({"receivers": {"a": 1.0, "b": 1.1}, "senders": [0.8, 0.8]}))
    zr, zs = read_heights(p, ("a", "b"), ("a", "b"))
    np.testing.assert_allclose(zr, [1.0, 1.1])
    p.write_text(json.dumps({"receivers": {"a": 1.0, "c": 1.1}, "senders": [0.8, 0.8]}))
    with pytest.raises(InputError, match="h.json.*'c'"):
        read_heights(p, ("a", "b"), ("a", "b"))
    p.write_text(json.dumps({"receivers": [1.0], "senders": [0.8, 0.8]}))
    with pytest.raises(InputError, match="field 'receivers'"):
        read_heights(p, ("a", "b"), ("a", "b"))


# ----------------------------------------------------------------------------- end to end (needs solve_toa)


def _simulate(out: Path, layout: str, units: int = 10, seed: int = 2) -> None:
    res = CliRunner().invoke(main, ["simulate", "conference", "--units", str(units), "--room", "8x7x3",
                                    "--rt60", "0.4", "--snr", "30", "--seed", str(seed), "--layout", layout,
                                    "--sample-rate", "16000", "--max-order", "2", "--out", str(out)])
    assert res.exit_code == 0, res.output


def test_pipeline_cli_flat_room_with_heights_meets_004(tmp_path):
    rec = tmp_path / "rec"
    _simulate(rec, "flat")
    out = tmp_path / "result.json"
    res = CliRunner().invoke(main, ["pipeline", str(rec), "--out", str(out), "--heights", str(rec / "heights.json"),
                                    "--report", str(tmp_path / "report"), "--plot", str(tmp_path / "map.png")])
    assert res.exit_code == 0, res.output
    data = json.loads(out.read_text())
    for key in ("receivers", "sources", "receiver_offsets", "source_offsets", "receiver_cov", "source_cov",
                "residual_rms", "converged", "iterations", "method", "toa_matrix", "detections_missed"):
        assert key in data
    assert np.array(data["toa_matrix"], dtype=float).shape == (10, 10)
    assert data["errors"]["position_max"] < 0.10 and data["errors"]["timing_max"] < 58e-6
    assert (tmp_path / "report" / "map.png").stat().st_size > 1000
    assert (tmp_path / "report" / "timing.png").is_file() and (tmp_path / "map.png").is_file()


def _outside_error_bars(data: dict, truth: dict) -> set[str]:
    """Units whose aligned 3-D position error exceeds 3 of its own error bars (squared
    Mahalanobis distance above chi-square(3)'s 0.9973 quantile, 14.2)."""
    from selfcal.geometry import align

    est = np.vstack([data["receivers"], data["sources"]]).astype(float)
    true = np.vstack([truth["receivers"], truth["senders"]]).astype(float)
    cov = np.concatenate([np.asarray(data["receiver_cov"], float), np.asarray(data["source_cov"], float)])
    names = list(data["receiver_names"]) + list(data["sender_names"])
    tr = align(est, true, reflection=True)
    err = tr.apply(est) - true
    Rm = np.asarray(tr.rotation)
    m2 = [e @ np.linalg.solve(Rm @ c @ Rm.T, e) for e, c in zip(err, cov, strict=True)]
    return {n for n, v in zip(names, m2, strict=True) if v > 14.16}


def test_boundary_desks_give_2d_or_z_within_its_error_bars(tmp_path):
    """Boundary microphones within 1 cm of their loudspeakers' plane: no confident wrong z.

    The one planarity test (``dimension_test``: F test of a 2-D fit against the 3-D one and
    the chi-square of the out-of-plane coordinates, level 1e-3) decides. On this recording
    (7 mm thick, 0.12 us timing noise) the F test does not reject the plane (F = 3.2,
    p = 0.004) while the chi-square alone would (p = 6e-13: the 3-D fit bends off the plane
    beyond its linearised error bars), so ``--dim 3`` is refused and ``--dim auto`` reports
    2-D, as under the per-point rule it replaced. (With the 2-D refinement started from
    offsets 343 times too large, F was 1.6e4 and z was reported.) The test holds whichever
    way a layout this thin goes: a refusal of ``--dim 3`` comes with the 2-D answer under
    ``--dim auto``, and a 3-D answer has no unit outside 3 x its error bar that it does not
    list as ambiguous.
    """
    rec = tmp_path / "rec"
    _simulate(rec, "boundary")
    (rec / "heights.json").unlink()  # (with --dim auto the pipeline would use the recording's heights)
    out = tmp_path / "result.json"
    res = CliRunner().invoke(main, ["pipeline", str(rec), "--out", str(out), "--dim", "3"])
    truth = json.loads((rec / "truth.json").read_text())
    if res.exit_code == 2:
        assert "near-planar" in res.output and not out.exists()
        res = CliRunner().invoke(main, ["pipeline", str(rec), "--out", str(out)])  # auto: falls back to 2-D
        assert res.exit_code == 0, res.output
        data = json.loads(out.read_text())
        assert data["dim"] == 2 and data["notes"] and data["errors"]["horizontal_only"]
        assert data["errors"]["position_max"] < 0.10
        return
    assert res.exit_code == 0, res.output
    data = json.loads(out.read_text())
    pl = data["planarity"]
    assert data["dim"] == 3 and not pl["near_planar"]
    assert pl["comparison"]["p_value"] <= 1e-3 and pl["thickness_p"] <= 1e-3
    assert data["errors"]["position_max"] < 0.10
    ambiguous = set(data["ambiguous_receivers"]) | set(data["ambiguous_senders"])
    assert _outside_error_bars(data, truth) <= ambiguous


def test_pipeline_tiered_room_in_3d(tmp_path):
    rec = tmp_path / "rec"
    _simulate(rec, "tiered", units=12)
    out = tmp_path / "result.json"
    res = CliRunner().invoke(main, ["pipeline", str(rec), "--out", str(out), "--dim", "3"])
    assert res.exit_code == 0, res.output
    data = json.loads(out.read_text())
    assert data["dim"] == 3 and not data["planarity"]["near_planar"]
    assert data["errors"]["position_max"] < 0.10 and data["errors"]["timing_max"] < 58e-6


def test_microphones_mirrored_under_coplanar_loudspeakers_are_put_back_on_one_side():
    """Coplanar senders: reflecting one receiver through their plane changes no distance."""
    from selfcal.acoustics.geometry import one_side_of_plane

    sc = conference_scene(12, (10.0, 8.0, 3.0), layout="stem", rng=4)
    d_true = np.linalg.norm(sc.receivers[:, None] - sc.senders[None], axis=-1)
    mixed = sc.receivers.copy()
    z0 = sc.senders[0, 2]
    mixed[[1, 4, 7], 2] = 2 * z0 - mixed[[1, 4, 7], 2]  # three microphones under the desk
    np.testing.assert_allclose(np.linalg.norm(mixed[:, None] - sc.senders[None], axis=-1), d_true)
    cov = np.tile(np.diag([1e-4, 2e-4, 3e-4]), (12, 1, 1))
    fixed, cov2, n = one_side_of_plane(mixed, cov, sc.senders)
    assert n == 3
    np.testing.assert_allclose(fixed, sc.receivers, atol=1e-9)
    np.testing.assert_allclose(cov2, cov, atol=1e-12)  # a reflection in z keeps a diagonal covariance


# ----------------------------------------------------------------------------- 2-D vs 3-D verdict (seeds)


def test_f_test_keeps_z_only_when_3d_fits_significantly_better():
    """compare_fits: F = ((RSS2 - RSS3) / k) / (RSS3 / dof) against F(k, dof) (nested models)."""
    from scipy.stats import f as f_dist

    from selfcal.acoustics.geometry import compare_fits

    m, n = 400, 40  # 20 units: k = n - 3 = 37 extra unknowns, dof = m - (4 n - 7) = 247
    thick = compare_fits(20e-6, 1e-6, m, n)  # a 2-D fit 20x worse than the noise: z is real
    assert thick.significant and thick.extra_parameters == 37 and thick.dof_3d == 247
    rss2, rss3 = m * 20e-6**2, m * 1e-6**2
    assert thick.f_statistic == pytest.approx((rss2 - rss3) / 37 / (rss3 / 247))
    # Under a planar truth the 3-D fit only absorbs noise: RSS3 ~ sigma^2 dof, RSS2 ~ sigma^2 (dof + k).
    planar = compare_fits(1e-6 * np.sqrt((247 + 37) / m), 1e-6 * np.sqrt(247 / m), m, n)
    assert not planar.significant and planar.f_statistic == pytest.approx(1.0)
    assert planar.p_value == pytest.approx(f_dist.sf(1.0, 37, 247))
    # A 3-D fit worse than the planar one (a local minimum) never proves z.
    assert not compare_fits(1e-6, 5e-6, m, n).significant
    # Exact planar data: both fits at rounding level, the noise floor keeps F finite and small.
    assert not compare_fits(3e-14, 1e-14, m, n).significant
    # Too few observations for a residual degree of freedom: z only if 2-D is off by more than the floor.
    assert not compare_fits(1e-11, 0.0, 30, n).significant and compare_fits(1e-6, 0.0, 30, n).significant


def _scene_toa(layout: str, seed: int, noise: float = 1e-6):
    sc = conference_scene(8, (8.0, 7.0, 3.0), layout=layout, rng=seed)
    if layout == "boundary":  # boundary microphones exactly at their loudspeakers' height
        sc = type(sc)(np.column_stack([sc.receivers[:, :2], sc.senders[:, 2]]), sc.senders,
                      sc.receiver_delays, sc.sender_onsets, sc.room, sc.layout)
    return sc, _toa(sc, noise, rng=seed)


@pytest.mark.parametrize("solver_seed", [0, 1000, 2000])
def test_planar_desks_give_2d_whatever_the_solver_seed(solver_seed):
    """Issue 7: never a confident z on flat desks, for any random start of the 3-D solver.

    Seeds 1000 and 2000 once returned a 3-D answer in a wrong basin (residual tens of us
    while a 2-D fit reached 0.1 us). The verdict comes from the 3-D fit's own geometry and
    covariances (issue 15: no 2-D comparison fit unless the layout is near-planar).
    """
    from selfcal.acoustics.calibrate import calibrate_matrix
    from selfcal.errors import DegenerateGeometryError
    from selfcal.geometry import align

    sc, T = _scene_toa("boundary", 1)
    with pytest.warns(UserWarning, match="near-planar"):
        sol, plan, notes = calibrate_matrix(T, speed=C, rng=solver_seed)
    assert sol.method.startswith("2d") and sol.receivers.shape == (8, 2)
    # the near-planar verdict is among the notes (a 3-D fit in the truth's basin may add, first,
    # that the loudspeakers' mirror images through the microphones' plane fit as well)
    assert plan.near_planar and any("near-planar" in n for n in notes)
    est = np.vstack([sol.receivers, sol.sources])
    true = np.vstack([sc.receivers, sc.senders])[:, :2]
    assert np.abs(align(est, true).apply(est) - true).max() < 0.02  # 1 us = 0.34 mm of range noise
    # asking for 3-D anyway is refused for every start, not a confident z from one basin
    with pytest.raises(DegenerateGeometryError, match="near-planar"):
        calibrate_matrix(T, speed=C, dim=3, rng=solver_seed)


@pytest.mark.parametrize(("layout", "solver_seed"), [("tiered", 1000), ("tiered", 2000), ("stem", 1000),
                                                     ("stem", 2000)])
def test_3d_layouts_keep_z_with_its_uncertainty(layout, solver_seed):
    """Tiered rows and stem microphones: the 3-D fit resolves its thickness, z is kept, with its std.

    The pipeline knows which microphone and loudspeaker share a unit (the same name) and
    starts the search from the units' two-way distances (:mod:`selfcal.acoustics.units`);
    blind, solver seeds 2000 (tiered) and 1000 (stem) end in wrong 3-D basins of
    ``solve_toa`` (residual 28 us at 1 us noise, 2.4 m off).
    """
    from selfcal.acoustics.calibrate import calibrate_matrix
    from selfcal.geometry import align

    sc, T = _scene_toa(layout, 1)
    units = np.column_stack([np.arange(len(T))] * 2)  # unit k: microphone k, loudspeaker k
    sol, plan, notes = calibrate_matrix(T, speed=C, rng=solver_seed, units=units)
    assert sol.method.startswith("3d") and not plan.near_planar
    assert any("z standard deviation" in n for n in notes)
    est = np.vstack([sol.receivers, sol.sources])
    true = np.vstack([sc.receivers, sc.senders])
    err = align(est, true).apply(est) - true
    assert np.abs(err).max() < 0.05
    zstd = np.sqrt(np.concatenate([sol.receiver_cov[:, 2, 2], sol.source_cov[:, 2, 2]]))
    assert np.all(zstd > 0) and np.sqrt(np.mean(err[:, 2] ** 2)) < 5 * np.sqrt(np.mean(zstd**2))
