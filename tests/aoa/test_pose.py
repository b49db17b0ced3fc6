"""selfcal.aoa: receiver pose from angles of arrival (paper 001)."""

from __future__ import annotations

import json
import warnings

import numpy as np
import pytest
from click.testing import CliRunner

from selfcal.aoa import angles_to_bearings, bearings_to_angles, solve_aoa, tdoa_to_bearings
from selfcal.aoa.ml import refine_ml, residuals_2d, residuals_3d
from selfcal.aoa.orientation import orientation_from_vectors, rotvec_to_matrix
from selfcal.aoa.p3p import p3p
from selfcal.aoa.solution1 import solution1, torus_jacobian, torus_residuals
from selfcal.aoa.solution2 import solution2
from selfcal.errors import DegenerateGeometryError, InputError, Status

PAPER_BEACONS = np.array([[0.0, 0, 0], [5, 0, 0], [0, 5, 0]])


def local_bearings(beacons, m, R):
    """Exact bearings in the receiver frame: R^T (b - m)/|b - m| (batched over m, R)."""
    g = beacons[None] - m[:, None]
    return np.einsum("bji,bkj->bki", R, g / np.linalg.norm(g, axis=-1, keepdims=True))


def random_poses(rng, B, d=3):
    m = rng.uniform(-4, 4, size=(B, d))
    if d == 3:
        R = rotvec_to_matrix(rng.normal(size=(B, 3)))
    else:
        th = rng.uniform(-np.pi, np.pi, B)
        R = np.stack([np.stack([np.cos(th), -np.sin(th)], -1), np.stack([np.sin(th), np.cos(th)], -1)], -2)
    return m, R


# ----------------------------------------------------------------------------- TDOA -> AOA


def test_tdoa_to_bearings_recovers_direction_cosines():
    u = np.array([[0.3, -0.4, np.sqrt(1 - 0.25)], [0.0, 0.0, 1.0]])
    c, L12, L34 = 343.0, 0.2, 0.3
    out = tdoa_to_bearings(u[:, 0] * L12 / c, u[:, 1] * L34 / c, baseline_12=L12, baseline_34=L34, speed=c)
    np.testing.assert_allclose(out.vectors, u, atol=1e-12)
    assert not out.clipped.any()


def test_tdoa_noise_beyond_one_is_clipped_and_flagged():
    out = tdoa_to_bearings([1.1e-3, 0.5e-3], [0.0, 0.9e-3], baseline_12=0.343, baseline_34=0.343, speed=343.0)
    assert out.clipped.tolist() == [True, True]  # |cos a| > 1, then cos^2 a + cos^2 b > 1
    np.testing.assert_allclose(np.linalg.norm(out.vectors, axis=1), 1.0)
    assert (out.vectors[:, 2] >= 0).all()  # positive root of eq. 4: beacon in front of the panel


def test_angles_roundtrip():
    a, b = np.radians([60.0, 80.0]), np.radians([50.0, 95.0])
    u = angles_to_bearings(a, b).vectors
    a2, b2 = bearings_to_angles(u)
    np.testing.assert_allclose(a2, a, atol=1e-12)
    np.testing.assert_allclose(b2, b, atol=1e-12)


def test_tdoa_rejects_bad_baseline():
    with pytest.raises(InputError):
        tdoa_to_bearings([0.0], [0.0], baseline_12=0.0, baseline_34=1.0, speed=343.0)


# ----------------------------------------------------------------------------- exact recovery


def test_p3p_candidates_contain_truth_and_satisfy_equations():
    rng = np.random.default_rng(1)
    beacons = rng.normal(size=(3, 3)) * 3
    m, R = random_poses(rng, 300)
    U = local_bearings(beacons, m, R)
    pos, rot, valid = p3p(beacons, U)
    assert valid.any(axis=1).all()
    err = np.nanmin(np.linalg.norm(pos - m[:, None], axis=-1), axis=1)
    assert np.median(err) < 1e-9 and err.max() < 1e-6
    # every candidate reproduces the measured bearings (it solves the equations)
    for k in range(4):
        ok = valid[:, k]
        pred = local_bearings(beacons, pos[ok, k], rot[ok, k])
        np.testing.assert_allclose(pred, U[ok], atol=1e-7)
        np.testing.assert_allclose(np.linalg.det(rot[ok, k]), 1.0, atol=1e-9)


@pytest.mark.parametrize("method", ["sol1", "p3p", "ml", "auto"])
def test_exact_bearings_give_exact_pose_with_four_beacons(method):
    rng = np.random.default_rng(2)
    beacons = np.array([[0.0, 0, 0], [5, 0, 0], [0, 5, 0], [4, 5, 2.5]])
    for _ in range(15):
        m, R = random_poses(rng, 1)
        res = solve_aoa(beacons, local_bearings(beacons, m, R)[0], method=method)
        np.testing.assert_allclose(res.position, m[0], atol=1e-9)
        np.testing.assert_allclose(res.rotation, R[0], atol=1e-9)
        assert res.residual_rms < 1e-9 and res.converged


def test_paper_setup_unique_pose_is_exact_for_every_method():
    # the paper's orientation; below the middle of the beacon triangle the pose is unique
    R = np.cos(np.radians([[45.0, 45.0, 90.0], [135.0, 45.0, 90.0], [90.0, 90.0, 0.0]])).T
    m = np.array([1.0, 2.0, -3.0])
    U = local_bearings(PAPER_BEACONS, m[None], R[None])[0]
    for method in ("sol1", "sol2", "p3p", "ml"):
        res = solve_aoa(PAPER_BEACONS, U, method=method)
        assert not res.ambiguous
        np.testing.assert_allclose(res.position, m, atol=1e-9)
        np.testing.assert_allclose(res.rotation, R, atol=1e-9)


@pytest.mark.parametrize("method", ["sol1", "sol2", "ml"])
def test_paper_solutions_exact_over_the_paper_grid(method):
    """Exact bearings on the paper's test plane (z = -3, 0.5 m grid) give the exact pose; the
    paper's Newton methods are local, so this is checked where the paper uses them."""
    R = np.cos(np.radians([[45.0, 45.0, 90.0], [135.0, 45.0, 90.0], [90.0, 90.0, 0.0]])).T
    xs = np.arange(0.25, 5.0, 0.5)
    m = np.array([[x, y, -3.0] for x in xs for y in xs])
    U = local_bearings(PAPER_BEACONS, m, np.broadcast_to(R, (len(m), 3, 3)))
    res = solve_aoa(PAPER_BEACONS, U, method=method, position_hint=[2.5, 2.5, -3.0])
    np.testing.assert_allclose(res.position, m, atol=1e-9)
    np.testing.assert_allclose(res.rotation, np.broadcast_to(R, (len(m), 3, 3)), atol=1e-9)


def test_three_beacons_return_every_candidate_and_hint_picks_one():
    rng = np.random.default_rng(5)
    found = 0
    for _ in range(40):
        m, R = random_poses(rng, 1)
        U = local_bearings(PAPER_BEACONS, m, R)[0]
        res = solve_aoa(PAPER_BEACONS, U, method="p3p")
        if not res.ambiguous:
            continue
        found += 1
        for c in res.candidates:  # every candidate satisfies the measurement equations
            np.testing.assert_allclose(local_bearings(PAPER_BEACONS, c.position[None], c.rotation[None])[0], U, atol=1e-7)
        assert min(np.linalg.norm(c.position - m[0]) for c in res.candidates) < 1e-7
        hinted = solve_aoa(PAPER_BEACONS, U, method="p3p", position_hint=m[0] + 0.01)
        np.testing.assert_allclose(hinted.position, m[0], atol=1e-7)
        d = json.loads(json.dumps(res.to_dict()))
        assert len(d["candidates"]) == len(res.candidates) > 1
    assert found >= 5


def test_batched_equals_single():
    rng = np.random.default_rng(3)
    beacons = np.array([[0.0, 0, 0], [5, 0, 0], [0, 5, 0], [5, 5, 1]])
    m, R = random_poses(rng, 20)
    U = local_bearings(beacons, m, R) + 1e-3 * rng.normal(size=(20, 4, 3))
    batch = solve_aoa(beacons, U)
    assert batch.position.shape == (20, 3) and batch.rotation.shape == (20, 3, 3)
    assert batch.covariance.shape == (20, 6, 6)
    for k in (0, 7, 19):
        single = solve_aoa(beacons, U[k])
        np.testing.assert_allclose(single.position, batch.position[k], atol=1e-8)


def test_2d_exact_and_noisy():
    rng = np.random.default_rng(4)
    beacons = np.array([[0.0, 0], [4, 0], [0, 3]])
    m, R = random_poses(rng, 30, d=2)
    U = local_bearings(beacons, m, R)
    res = solve_aoa(beacons, U, method="linear")
    np.testing.assert_allclose(res.position, m, atol=1e-9)
    np.testing.assert_allclose(res.rotation, R, atol=1e-9)
    b5 = np.vstack([beacons, [[5, 5], [-3, 4]]])
    U5 = local_bearings(b5, m, R)
    th = np.arctan2(U5[..., 1], U5[..., 0]) + np.radians(0.5) * rng.normal(size=U5.shape[:2])
    noisy = np.stack([np.cos(th), np.sin(th)], -1)
    lin = solve_aoa(b5, noisy, method="linear")
    ml = solve_aoa(b5, noisy, method="ml")
    e_lin = np.linalg.norm(lin.position - m, axis=1)
    e_ml = np.linalg.norm(ml.position - m, axis=1)
    assert np.mean(e_ml) <= np.mean(e_lin) + 1e-12
    assert np.all(ml.residual_rms <= lin.residual_rms + 1e-12)


# ----------------------------------------------------------------------------- derivatives


def test_torus_jacobian_matches_finite_differences():
    rng = np.random.default_rng(6)
    b = rng.normal(size=(4, 3)) * 3
    pairs = np.array([[0, 1], [1, 2], [2, 0], [0, 3]])
    m = rng.normal(size=(2, 3))
    cos = rng.uniform(-0.5, 0.9, size=(2, 4))
    J = torus_jacobian(b, cos, pairs, m)
    h = 1e-6
    for k in range(3):
        dm = np.zeros(3)
        dm[k] = h
        fd = (torus_residuals(b, cos, pairs, m + dm) - torus_residuals(b, cos, pairs, m - dm)) / (2 * h)
        np.testing.assert_allclose(J[..., k], fd, atol=1e-6)


@pytest.mark.parametrize("noise", ["sphere", "angles"])
def test_ml_jacobian_matches_finite_differences(noise):
    rng = np.random.default_rng(7)
    b = rng.normal(size=(5, 3)) * 3
    m, R = random_poses(rng, 2)
    U = local_bearings(b, m, R) + 0.01 * rng.normal(size=(2, 5, 3))
    U /= np.linalg.norm(U, axis=-1, keepdims=True)
    _, J = residuals_3d(b, U, m, R, noise=noise, jacobian=True)
    h = 1e-6
    for k in range(6):
        s = np.zeros(6)
        s[k] = h
        plus = residuals_3d(b, U, m + s[:3], R @ rotvec_to_matrix(s[3:]), noise=noise)[0]
        minus = residuals_3d(b, U, m - s[:3], R @ rotvec_to_matrix(-s[3:]), noise=noise)[0]
        np.testing.assert_allclose(J[..., k], (plus - minus) / (2 * h), atol=1e-6)
    m2, R2 = random_poses(rng, 2, d=2)
    b2 = rng.normal(size=(4, 2)) * 3
    U2 = local_bearings(b2, m2, R2)
    th = np.arctan2(R2[:, 1, 0], R2[:, 0, 0])
    _, J2 = residuals_2d(b2, U2, m2, th, jacobian=True)
    for k in range(3):
        s = np.zeros(3)
        s[k] = h
        fd = (residuals_2d(b2, U2, m2 + s[:2], th + s[2])[0] - residuals_2d(b2, U2, m2 - s[:2], th - s[2])[0]) / (2 * h)
        np.testing.assert_allclose(J2[..., k], fd, atol=1e-6)


def test_ml_covariance_matches_monte_carlo_spread():
    rng = np.random.default_rng(8)
    b = np.array([[0.0, 0, 0], [5, 0, 0], [0, 5, 0], [5, 5, 1], [2, 3, 2.5], [4, 1, 2]])
    m = np.array([[2.0, 2.0, -3.0]])
    R = rotvec_to_matrix(np.array([[0.1, -0.2, 0.3]]))
    U0 = local_bearings(b, m, R)[0]
    sigma = np.radians(0.5)
    B = 400
    noise = rng.normal(size=(B, 6, 3)) * sigma
    U = U0 + noise - np.sum(noise * U0, -1, keepdims=True) * U0  # tangent-plane noise
    res = solve_aoa(b, U, sigma=sigma)
    emp = np.cov((res.position - m).T)
    pred = res.position_cov.mean(axis=0)
    np.testing.assert_allclose(np.sqrt(np.diag(emp)), np.sqrt(np.diag(pred)), rtol=0.2)


def test_orientation_planar_variant_is_exact_on_plane():
    rng = np.random.default_rng(9)
    R = rotvec_to_matrix(rng.normal(size=(1, 3)))
    G = np.zeros((1, 3, 3))
    G[0, :, :2] = rng.normal(size=(3, 2))  # global vectors in the plane z = 0 (paper eq. 15-18)
    L = np.einsum("bji,bkj->bki", R, G)
    A, planar = orientation_from_vectors(G, L)
    assert planar.all()
    np.testing.assert_allclose(A[0], R[0].T, atol=1e-12)


# ----------------------------------------------------------------------------- degeneracies


def test_collinear_beacons_raise():
    b = np.array([[0.0, 0, 0], [1, 1, 1], [2, 2, 2], [3, 3, 3]])
    with pytest.raises(DegenerateGeometryError) as exc:
        solve_aoa(b, np.tile([0.0, 0, 1], (4, 1)))
    assert exc.value.kind == "collinear-beacons"


def test_receiver_on_beacon_plane_raises():
    m = np.array([[2.0, -1.0, 0.0]])
    U = local_bearings(PAPER_BEACONS, m, np.eye(3)[None])[0]
    with pytest.raises(DegenerateGeometryError) as exc:
        solve_aoa(PAPER_BEACONS, U)
    assert exc.value.kind == "receiver-on-beacon-plane"


def test_danger_circle_2d_raises():
    beacons = np.array([[1.0, 0], [0, 1], [-1, 0]])
    m = np.array([[np.cos(-1.0), np.sin(-1.0)]])  # on the circle through the beacons
    U = local_bearings(beacons, m, np.eye(2)[None])[0]
    with pytest.raises(DegenerateGeometryError) as exc:
        solve_aoa(beacons, U)
    assert exc.value.kind == "danger-circle"


def test_danger_cylinder_3d_raises():
    # unit circle through the beacons in z = 0; the receiver on the cylinder over it
    ang = np.array([0.0, 2.0, 4.0])
    beacons = np.column_stack([np.cos(ang), np.sin(ang), np.zeros(3)])
    m = np.array([[np.cos(1.0), np.sin(1.0), -2.0]])
    U = local_bearings(beacons, m, np.eye(3)[None])[0]
    with pytest.raises(DegenerateGeometryError) as exc:
        solve_aoa(beacons, U, method="p3p")
    assert exc.value.kind == "danger-cylinder"


def test_bad_input_raises_input_error():
    with pytest.raises(InputError):
        solve_aoa(PAPER_BEACONS, np.ones((3, 2)))
    with pytest.raises(InputError):
        solve_aoa(PAPER_BEACONS, np.zeros((3, 3)))
    with pytest.raises(InputError):
        solve_aoa(PAPER_BEACONS, np.eye(3), method="linear")
    with pytest.raises(DegenerateGeometryError) as exc:
        solve_aoa(PAPER_BEACONS[:2], np.eye(3)[:2])
    assert exc.value.kind == "too-few-beacons"


def test_missing_beacon_nan_row_is_dropped():
    b = np.array([[0.0, 0, 0], [5, 0, 0], [0, 5, 0], [5, 5, 2], [1, 4, 3]])
    m, R = np.array([[1.0, 1.0, -2.0]]), rotvec_to_matrix(np.array([[0.2, 0.1, -0.3]]))
    U = local_bearings(b, m, R)[0]
    U[1] = np.nan
    res = solve_aoa(b, U)
    np.testing.assert_allclose(res.position, m[0], atol=1e-9)


# ----------------------------------------------------------------------------- paper solutions


def test_solutions_agree_with_ml_on_three_beacons_when_all_solve():
    """Three beacons: six angles for six unknowns, so Solutions 1, 2 and ML give the same exact
    fit whenever they land on the same root (the paper's Table 1 differences are not intrinsic)."""
    from selfcal.experiments.aoa import TRUE_ROTATION, _noisy_bearings

    rng = np.random.default_rng(11)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for _ in range(10):
            m = np.array([rng.uniform(1, 4), rng.uniform(1, 4), -3.0])
            U, _ = _noisy_bearings(PAPER_BEACONS, m, TRUE_ROTATION, 1.0, rng)
            s1, s2 = solution1(PAPER_BEACONS, U[None]), solution2(PAPER_BEACONS, U[None])
            pos, rot, valid = p3p(PAPER_BEACONS, U[None])
            k = np.flatnonzero(valid[0])
            ml = refine_ml(PAPER_BEACONS, np.repeat(U[None], k.size, 0), pos[0, k], rot[0, k])
            if s1["converged"][0] and s2["converged"][0]:
                assert np.min(np.linalg.norm(ml["position"] - s1["position"][0], axis=1)) < 1e-7
                np.testing.assert_allclose(s1["position"][0], s2["position"][0], atol=1e-7)


def test_reproduction_reduced_ml_beats_paper_solutions():
    """Reduced Table 1 (coarse grid): the paper's order of magnitude, and ML with the paper's
    suggested fourth beacon beats both paper solutions; ML solves at least as many trials."""
    from selfcal.experiments.aoa import aoa_trial, paper_grid, summarize
    from selfcal.experiments.runner import run_sweep

    rows = run_sweep(aoa_trial, paper_grid(1.0), runs=3, seed=1, progress=False)
    t = summarize(rows)
    for meth in ("sol1", "sol2"):
        assert 0.1 < t[meth]["location_m"] < 1.0
        assert 0.5 < t[meth]["x_deg"] < 8.0
        assert t["ml4"]["location_m"] < t[meth]["location_m"]
        for ax in "xyz":
            assert t["ml4"][f"{ax}_deg"] < t[meth][f"{ax}_deg"]
        assert t["ml"]["solved_fraction"] >= t[meth]["solved_fraction"]


# ----------------------------------------------------------------------------- command line


def test_cli_locate_aoa_vectors_and_angles(tmp_path):
    from selfcal.cli import main

    b = np.array([[0.0, 0, 0], [5, 0, 0], [0, 5, 0], [5, 5, 1]])
    R = np.cos(np.radians([[45.0, 45.0, 90.0], [135.0, 45.0, 90.0], [90.0, 90.0, 0.0]])).T
    m = np.array([[2.0, 1.0, -3.0]])
    U = local_bearings(b, m, R[None])[0]
    np.savetxt(tmp_path / "b.csv", b, delimiter=",")
    np.savetxt(tmp_path / "u.csv", U, delimiter=",")
    a, be = bearings_to_angles(U)
    np.savetxt(tmp_path / "ang.csv", np.degrees(np.column_stack([a, be])), delimiter=",")
    runner = CliRunner()
    r = runner.invoke(main, ["locate", "aoa", str(tmp_path / "b.csv"), str(tmp_path / "u.csv"), "--out", str(tmp_path / "r.json")])
    assert r.exit_code == 0, r.output
    d = json.loads((tmp_path / "r.json").read_text())
    np.testing.assert_allclose(d["position"], m[0], atol=1e-9)
    np.testing.assert_allclose(d["rotation"], R, atol=1e-9)
    assert {"position", "rotation", "residual_rms", "method"} <= set(d)
    r = runner.invoke(main, ["locate", "aoa", str(tmp_path / "b.csv"), str(tmp_path / "ang.csv"), "--angles", "deg",
                             "--method", "sol1", "--out", str(tmp_path / "r2.json")])
    assert r.exit_code == 0, r.output
    np.testing.assert_allclose(json.loads((tmp_path / "r2.json").read_text())["position"], m[0], atol=1e-9)


def test_cli_hint_selects_candidate_and_json_lists_all(tmp_path):
    from selfcal.cli import main

    rng = np.random.default_rng(5)
    while True:  # find a pose with several exact candidates
        m, R = random_poses(rng, 1)
        U = local_bearings(PAPER_BEACONS, m, R)[0]
        if solve_aoa(PAPER_BEACONS, U, method="p3p").ambiguous:
            break
    np.savetxt(tmp_path / "b.csv", PAPER_BEACONS, delimiter=",")
    np.savetxt(tmp_path / "u.csv", U, delimiter=",")
    hint = ",".join(f"{v:.6f}" for v in m[0] + 0.01)
    r = CliRunner().invoke(main, ["locate", "aoa", str(tmp_path / "b.csv"), str(tmp_path / "u.csv"),
                                  "--hint", hint, "--out", str(tmp_path / "r.json")])
    assert r.exit_code == 0, r.output
    d = json.loads((tmp_path / "r.json").read_text())
    np.testing.assert_allclose(d["position"], m[0], atol=1e-7)
    assert len(d["candidates"]) >= 2


def test_cli_degenerate_input_exits_2_without_output(tmp_path):
    from selfcal.cli import main

    np.savetxt(tmp_path / "b.csv", [[0, 0, 0], [1, 1, 1], [2, 2, 2]], delimiter=",")
    np.savetxt(tmp_path / "u.csv", np.eye(3), delimiter=",")
    r = CliRunner().invoke(main, ["locate", "aoa", str(tmp_path / "b.csv"), str(tmp_path / "u.csv"), "--out", str(tmp_path / "r.json")])
    assert r.exit_code == 2
    assert "collinear-beacons" in r.output
    assert not (tmp_path / "r.json").exists()


def test_cli_reproduce_aoa_small(tmp_path):
    from selfcal.cli import main

    r = CliRunner().invoke(main, ["reproduce", "aoa", "--runs", "1", "--step", "2.5", "--backend", "serial", "--out", str(tmp_path)])
    assert r.exit_code == 0, r.output
    d = json.loads((tmp_path / "aoa_reproduction.json").read_text())
    assert set(d["table1"]) == {"sol1", "sol2", "ml", "ml4"}
    assert (tmp_path / "location_error.png").stat().st_size > 0
    assert (tmp_path / "orientation_sol1.png").exists()


@pytest.mark.slow
def test_reproduction_full_grid_in_paper_range():
    from selfcal.experiments.aoa import aoa_trial, paper_grid, summarize
    from selfcal.experiments.runner import run_sweep

    rows = run_sweep(aoa_trial, paper_grid(0.2), runs=20, seed=0, backend="processes", progress=False)
    t = summarize(rows)
    for meth in ("sol1", "sol2"):
        assert t["ml4"]["location_m"] < t[meth]["location_m"] < 1.0


# ----------------------------------------------------------------------------- conventions (issue 16)


def _azel_deg(U):
    return np.degrees(np.column_stack([np.arctan2(U[:, 1], U[:, 0]), np.arcsin(np.clip(U[:, 2], -1, 1))]))


@pytest.mark.parametrize("seed", range(4))
def test_cli_azimuth_elevation_gives_the_same_pose_as_unit_vectors(tmp_path, seed):
    from selfcal.cli import main

    rng = np.random.default_rng(seed)
    b = rng.uniform(-5, 5, (5, 3))
    m, R = random_poses(rng, 1)
    U = local_bearings(b, m, R)[0] + 1e-3 * rng.normal(size=(5, 3))
    U /= np.linalg.norm(U, axis=1, keepdims=True)
    np.savetxt(tmp_path / "b.csv", b, delimiter=",")
    np.savetxt(tmp_path / "u.csv", U, delimiter=",")
    np.savetxt(tmp_path / "azel.csv", _azel_deg(U), delimiter=",")
    np.savetxt(tmp_path / "azel_rad.csv", np.radians(_azel_deg(U)), delimiter=",")
    runner = CliRunner()
    outs = []
    for args in (["u.csv"], ["azel.csv", "--angles", "azel"], ["azel_rad.csv", "--angles", "azel", "--units", "rad"]):
        r = runner.invoke(main, ["locate", "aoa", str(tmp_path / "b.csv"), str(tmp_path / args[0]), *args[1:],
                                 "--out", str(tmp_path / "r.json")])
        assert r.exit_code == 0, r.output
        outs.append(json.loads((tmp_path / "r.json").read_text()))
    for o in outs[1:]:
        np.testing.assert_allclose(o["position"], outs[0]["position"], atol=1e-8)
        np.testing.assert_allclose(o["rotation"], outs[0]["rotation"], atol=1e-8)


@pytest.mark.parametrize("method", ["auto", "sol1", "sol2", "p3p"])
def test_axis_angles_with_a_beacon_below_the_receiver_plane(method):
    # angles to the x / y axes lose the side of the receiver's xy plane; the ML refinement
    # over both sides recovers the exact pose for every method
    b = np.array([[0.0, 0, 0], [5, 0, 0], [0, 5, 0], [5, 5, 1], [2, 3, -6.0]])
    m = np.array([[2.0, 1.0, -3.0]])
    R = np.eye(3)[None]
    U = local_bearings(b, m, R)[0]
    assert U[4, 2] < 0  # the fifth beacon is below the receiver's xy plane
    a, be = bearings_to_angles(U)
    Uax = angles_to_bearings(a, be).vectors  # what --angles axes produces (z >= 0)
    res = solve_aoa(b, Uax, method=method, sign_z_unknown=True)
    np.testing.assert_allclose(res.position, m[0], atol=1e-6)
    np.testing.assert_allclose(res.rotation, R[0], atol=1e-6)
    assert res.success and res.method.endswith("+ml")


def test_bearings_that_fit_no_pose_fail_the_residual_test(tmp_path):
    from selfcal.cli import main

    rng = np.random.default_rng(2)
    b = rng.uniform(-5, 5, (8, 3))
    m, R = random_poses(rng, 1)
    U = local_bearings(b, m, R)[0]
    Uwrong = U[np.roll(np.arange(8), 1)]  # bearings listed against the wrong beacons: fit to ~21 deg
    res = solve_aoa(b, Uwrong)

    assert not res.success and res.status == Status.FAILED_TEST and "not a pose" in res.message
    assert res.to_dict()["fit"]["passed"] is False
    np.savetxt(tmp_path / "b.csv", b, delimiter=",")
    np.savetxt(tmp_path / "u.csv", Uwrong, delimiter=",")
    r = CliRunner().invoke(main, ["locate", "aoa", str(tmp_path / "b.csv"), str(tmp_path / "u.csv"),
                                  "--out", str(tmp_path / "r.json")])
    assert r.exit_code == 1 and "FAIL:" in r.output


def test_residual_test_passes_correct_noisy_poses():
    # 1 degree noise, sigma not given: the test assumes <= 5 degrees, so a correct pose fails only
    # if its chi-square exceeds 25x its 0.999 quantile -- never in 40 draws
    rng = np.random.default_rng(11)
    b = rng.uniform(-5, 5, (6, 3))
    for _ in range(40):
        m, R = random_poses(rng, 1)
        U = local_bearings(b, m, R)[0] + np.radians(1.0) * rng.normal(size=(6, 3))
        assert solve_aoa(b, U).success


def test_sol1_on_the_danger_cylinder_raises_like_the_default():
    ang = np.array([0.0, 2.0, 4.0])
    beacons = np.column_stack([np.cos(ang), np.sin(ang), np.zeros(3)])
    m = np.array([[np.cos(1.0), np.sin(1.0), -2.0]])
    U = local_bearings(beacons, m, np.eye(3)[None])[0]
    for method in ("auto", "sol1", "sol2"):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            with pytest.raises(DegenerateGeometryError, match="danger cylinder") as exc:
                solve_aoa(beacons, U, method=method)
        assert exc.value.kind == "danger-cylinder"


def test_cli_degrees_given_as_2d_unit_vectors_are_refused(tmp_path):
    from selfcal.cli import main

    b = np.array([[0.0, 0], [5, 0], [0, 5], [5, 5]])
    np.savetxt(tmp_path / "b.csv", b, delimiter=",")
    np.savetxt(tmp_path / "u.csv", np.array([[45.0, 0], [120, 0], [200, 0], [300, 0]]), delimiter=",")
    out = tmp_path / "r.json"
    r = CliRunner().invoke(main, ["locate", "aoa", str(tmp_path / "b.csv"), str(tmp_path / "u.csv"), "--out", str(out)])
    assert r.exit_code == 2 and "not a unit vector" in r.output and "--angles azel" in r.output
    assert not out.exists()


def test_cli_pose_plot(tmp_path):
    from selfcal.cli import main

    b = np.array([[0.0, 0, 0], [5, 0, 0], [0, 5, 0], [5, 5, 1]])
    U = local_bearings(b, np.array([[2.0, 1.0, -3.0]]), np.eye(3)[None])[0]
    np.savetxt(tmp_path / "b.csv", b, delimiter=",")
    np.savetxt(tmp_path / "u.csv", U, delimiter=",")
    r = CliRunner().invoke(main, ["locate", "aoa", str(tmp_path / "b.csv"), str(tmp_path / "u.csv"),
                                  "--out", str(tmp_path / "r.json"), "--plot", str(tmp_path / "p.png")])
    assert r.exit_code == 0, r.output
    assert (tmp_path / "p.png").stat().st_size > 0
