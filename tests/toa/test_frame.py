"""The user's frame: known nodes (exact / with a std) and reference frames (origin, x, xy, z)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy.stats import chi2

from selfcal.errors import DegenerateGeometryError, InputError
from selfcal.metrics import aligned_rmse
from selfcal.toa import solve_toa
from selfcal.toa.engine.nls import toa_model
from selfcal.toa.frame.frame import (
    apply_frame,
    calibrate_in_frame,
    parse_frame,
    parse_known,
    read_known_csv,
)

NOISE = 0.01  # m


def _net(seed: int, I: int = 7, J: int = 10, d: int = 3):
    rng = np.random.default_rng(seed)
    r = rng.uniform(0, 6, (I, d))
    s = rng.uniform(0, 6, (J, d))
    Y = toa_model(r, s) + NOISE * rng.standard_normal((I, J))
    return rng, r, s, Y


def _row(name: str, p: np.ndarray) -> str:
    return ",".join([name, *(repr(float(v)) for v in p)])  # repr: exact round trip


def _mahalanobis2(err: np.ndarray, cov: np.ndarray) -> float:
    return float(sum(e @ np.linalg.solve(c, e) for e, c in zip(err, cov, strict=True)))


def test_known_anchors_reproduce_coordinates_and_errors_match_covariance():
    """Exact known anchors stay exactly; the others' errors in the known frame (no alignment)
    are consistent with the reported covariance: the summed Mahalanobis distance over all
    free nodes and seeds is below the chi-square 99.9% quantile of its degrees of freedom."""
    m2, dof = 0.0, 0
    for seed in range(8):
        _, r, s, Y = _net(seed)
        known = {f"r{i}": r[i] for i in range(4)}
        res = calibrate_in_frame(Y, known=known, rng=seed)
        np.testing.assert_array_equal(res.receivers[:4], r[:4])
        assert res.frame.determined and res.frame.mirror_resolved and res.frame.residual_gauge == 0
        # truth (not aligned: the result is in the known frame)
        m2 += _mahalanobis2(res.receivers[4:] - r[4:], res.receiver_cov[4:])
        m2 += _mahalanobis2(res.sources - s, res.source_cov)
        dof += 3 * (3 + 10)
        assert res.frame.known_rms < 5 * NOISE  # blind solution agrees with the anchors
    assert m2 < chi2.ppf(0.999, dof)
    assert m2 > chi2.ppf(0.001, dof)  # and not over-pessimistic


def test_known_with_std_are_priors():
    """Known positions with a std pull the fit but are not held: the fitted known nodes
    move from their (noisy) given values, by amounts consistent with the stds."""
    moved = []
    for seed in range(6):
        rng, r, s, Y = _net(seed + 100)
        std = 0.03
        given = r[:5] + std * rng.standard_normal((5, 3))
        known = {f"r{i}": (*given[i], std) for i in range(5)}
        res = calibrate_in_frame(Y, known=known, rng=seed, noise=NOISE)
        moved.append(np.linalg.norm(res.receivers[:5] - given, axis=1))
        # the fit combines ranges and priors: closer to the truth than the given values
        assert np.sqrt(np.mean(np.sum((res.receivers[:5] - r[:5]) ** 2, 1))) < \
            np.sqrt(np.mean(np.sum((given - r[:5]) ** 2, 1)))
    assert np.median(np.concatenate(moved)) > 0.2 * 0.03  # really priors, not fixed


def test_mixed_exact_and_std_known_nodes_from_csv(tmp_path):
    _, r, s, Y = _net(7)
    f = tmp_path / "known.csv"
    lines = ["name,x,y,z,std"] + [_row(f"r{i}", r[i]) + "," for i in range(3)]
    lines.append(_row("s2", s[2]) + ",0.01")
    f.write_text("\n".join(lines) + "\n")
    res = calibrate_in_frame(Y, known=str(f), rng=0)
    np.testing.assert_array_equal(res.receivers[:3], r[:3])
    assert np.linalg.norm(res.sources[2] - s[2]) < 0.05
    assert res.frame.determined


def test_three_known_in_3d_report_the_mirror():
    """Three known nodes span a plane: the mirror through it is reported, the known nodes
    are reproduced and the result is the truth or its mirror image through that plane."""
    for seed in range(4):
        _, r, s, Y = _net(seed + 200)
        res = calibrate_in_frame(Y, known={f"r{i}": r[i] for i in range(3)}, rng=seed)
        info = res.frame
        assert not info.mirror_resolved and not info.determined and info.residual_gauge == 0
        assert "mirror" in info.message
        np.testing.assert_array_equal(res.receivers[:3], r[:3])
        n = np.cross(r[1] - r[0], r[2] - r[0])
        n /= np.linalg.norm(n)
        refl = r - 2 * ((r - r[0]) @ n)[:, None] * n
        err = min(np.abs(res.receivers - r).max(), np.abs(res.receivers - refl).max())
        assert err < 0.2  # 1 cm noise, 6 m network: a few cm, far below the mirror distance


def test_two_known_in_3d_leave_a_rotation():
    _, r, s, Y = _net(300)
    res = calibrate_in_frame(Y, known={"r0": r[0], "r1": r[1]}, rng=0)
    assert res.frame.residual_gauge == 1 and "rotation about the line" in res.frame.message
    np.testing.assert_array_equal(res.receivers[:2], r[:2])
    # distances are frame-free: the geometry is still right
    e = aligned_rmse(res.receivers, r, res.sources, s)
    assert e.rmse_receivers < 0.1
    assert np.isfinite(res.receiver_cov).all()


def test_inconsistent_known_node_shows_in_known_rms():
    """A typo in a known coordinate (1 m) shows as a large alignment RMS and residuals."""
    _, r, s, Y = _net(400)
    bad = r[:5].copy()
    bad[2, 0] += 1.0
    res = calibrate_in_frame(Y, known={f"r{i}": bad[i] for i in range(5)}, rng=0)
    assert res.frame.known_rms > 0.2
    assert res.residual_rms > 5 * NOISE


@pytest.mark.parametrize("dim", [2, 3])
def test_frame_rule_holds_exactly_on_random_networks(dim):
    """origin at 0, x on +x, xy in the upper half-plane, z=D above; distances unchanged."""
    for seed in range(10):
        rng, r, s, Y = _net(seed + 500, d=dim)
        blind = solve_toa(Y, dim=dim, rng=seed, covariance=False)
        a, b, c, dd = rng.choice(7, 4, replace=False)
        spec = f"origin=r{a},x={b},xy=r{c}" + (f",z=r{dd}" if dim == 3 else "")
        res = apply_frame(blind, spec)
        R = res.receivers
        assert np.all(R[a] == 0)
        assert R[b, 0] > 0 and np.all(R[b, 1:] == 0)
        assert R[c, 1] > 0 and (dim == 2 or R[c, 2] == 0)
        if dim == 3:
            assert R[dd, 2] > 0
        assert res.frame.mirror_resolved
        D0 = toa_model(blind.receivers, blind.sources)
        np.testing.assert_allclose(toa_model(res.receivers, res.sources), D0, atol=1e-9)
        # and it agrees with the truth put in the same frame (the mirror is resolved by D)
        truth = apply_frame(dataclasses.replace(blind, receivers=r, sources=s), spec)
        assert np.abs(res.receivers - truth.receivers).max() < 0.2


def test_frame_without_z_reports_the_choice():
    _, r, s, Y = _net(600)
    res = apply_frame(solve_toa(Y, rng=0, covariance=False), "origin=r0,x=r1,xy=r2")
    assert not res.frame.mirror_resolved and "z sign" in res.frame.message
    assert "handedness" in res.frame.message


def test_frame_covariance_in_the_reference_gauge():
    """With the matrix, covariances are those of the frame's gauge: A fixed, B's y/z, C's z."""
    _, r, s, Y = _net(700)
    res = calibrate_in_frame(Y, frame="origin=r0,x=r1,xy=r2,z=r3", rng=0)
    assert np.all(res.receiver_cov[0] == 0)
    np.testing.assert_array_equal(res.receiver_cov[1][1:, :], 0)
    np.testing.assert_array_equal(res.receiver_cov[2][2, :], 0)
    assert res.receiver_cov[1][0, 0] > 0 and res.receiver_cov[4].trace() > 0


def test_frame_errors():
    _, r, s, Y = _net(800)
    blind = solve_toa(Y, rng=0, covariance=False)
    with pytest.raises(InputError):
        parse_frame("origin=r0,y=r1")
    with pytest.raises(InputError):
        parse_frame("x=r1")
    with pytest.raises(InputError):
        apply_frame(blind, "origin=r0,x=r1")  # 3-D needs xy
    with pytest.raises(InputError):
        apply_frame(blind, "origin=r0,x=r99,xy=r2")
    with pytest.raises(InputError):
        calibrate_in_frame(Y, known={"r0": r[0]}, frame="origin=r0,x=r1,xy=r2")
    pts = blind.receivers.copy()
    pts[2] = 0.5 * (pts[0] + pts[1])  # collinear
    bad = dataclasses.replace(blind, receivers=pts)
    with pytest.raises(DegenerateGeometryError):
        apply_frame(bad, "origin=r0,x=r1,xy=r2")


def test_read_known_csv(tmp_path):
    f = tmp_path / "k.csv"
    f.write_text("# anchors\nA,0,0,0\nB,1,0,0,0.02\nC,0,1,0,\n")
    k = read_known_csv(f)
    assert k == {"A": (0.0, 0.0, 0.0), "B": (1.0, 0.0, 0.0, 0.02), "C": (0.0, 1.0, 0.0)}
    nodes = parse_known(k, 3, 5, 3, receiver_names=["A", "B", "C"])
    assert [(n.kind, n.index, n.std) for n in nodes] == [("receiver", 0, None), ("receiver", 1, 0.02),
                                                          ("receiver", 2, None)]
    for text in ("A,0,0\n", "A,0,0,x\n", "A,0,0,0\nA,1,1,1\n", "A,0,0,inf\n", "name,x,q,z\nA,0,0,0\n",
                 "A,0,0,0,-1\n"):
        f.write_text(text)
        with pytest.raises(InputError):
            read_known_csv(f)
    with pytest.raises(InputError):
        read_known_csv(tmp_path / "missing.csv")
    with pytest.raises(InputError):
        parse_known({"q7": (0, 0, 0)}, 3, 5, 3)


def test_known_nodes_with_offsets_and_seconds():
    """Known anchors with both offsets on a TOA matrix in seconds: offsets come back in
    seconds, positions in metres in the known frame."""
    rng = np.random.default_rng(900)
    c = 343.0
    r, s = rng.uniform(0, 6, (8, 3)), rng.uniform(0, 6, (12, 3))
    dr, o = rng.normal(0, 0.3, 8), rng.normal(0, 0.3, 12)
    T = (toa_model(r, s, dr, o) + NOISE * rng.standard_normal((8, 12))) / c
    res = calibrate_in_frame(T, known={f"r{i}": r[i] for i in range(4)}, offsets="both", speed=c, rng=0)
    np.testing.assert_array_equal(res.receivers[:4], r[:4])
    assert np.abs(res.sources - s).max() < 0.15
    # offsets are determined up to the common shift d + k, o - k (first source offset 0)
    np.testing.assert_allclose(res.source_offsets * c, o - o[0], atol=0.15)
    assert res.to_dict()["frame"]["kind"] == "known"
