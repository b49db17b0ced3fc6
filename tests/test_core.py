"""Specification of the shared core: validation, alignment, metrics, I/O, sweep runner."""

from __future__ import annotations

import json

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from selfcal import DegenerateGeometryError, InputError
from selfcal._checks import as_matrix, check_toa_counts
from selfcal.experiments import run_sweep, write_rows
from selfcal.geometry import (
    align,
    canonical_gauge,
    rotation_from_rotvec,
    rotvec_from_rotation,
    sphere_exp,
)
from selfcal.io import read_matrix, write_json
from selfcal.metrics import (
    aligned_direction_errors,
    aligned_rmse,
    angle_error,
    rotation_angle_error,
)


def _random_rotation(rng: np.random.Generator, d: int, proper: bool = True) -> np.ndarray:
    Q, _ = np.linalg.qr(rng.normal(size=(d, d)))
    if proper and np.linalg.det(Q) < 0:
        Q[:, 0] *= -1
    return Q


@pytest.mark.parametrize("d", [2, 3])
@pytest.mark.parametrize("reflect", [False, True])
def test_align_recovers_rigid_transform(rng: np.random.Generator, d: int, reflect: bool) -> None:
    X = rng.normal(size=(12, d))
    R = _random_rotation(rng, d)
    if reflect:
        R = R @ np.diag([1.0] * (d - 1) + [-1.0])
    t = rng.normal(size=d)
    Y = X @ R.T + t
    al = align(X, Y, reflection=True)
    np.testing.assert_allclose(al.apply(X), Y, atol=1e-10)
    if reflect:
        # a proper-only alignment cannot undo a mirror image
        assert np.abs(align(X, Y, reflection=False).apply(X) - Y).max() > 1e-3


def test_align_similarity_scale(rng: np.random.Generator) -> None:
    X = rng.normal(size=(10, 3))
    Y = 2.5 * X @ _random_rotation(rng, 3).T + 1.0
    al = align(X, Y, scale=True)
    assert al.scale == pytest.approx(2.5, rel=1e-10)
    np.testing.assert_allclose(al.apply(X), Y, atol=1e-10)


def test_aligned_rmse_matches_definition(rng: np.random.Generator) -> None:
    R = rng.normal(size=(8, 2)) * 5
    noise = rng.normal(scale=0.1, size=R.shape)
    Rot = _random_rotation(rng, 2)
    est_R = (R + noise) @ Rot.T + 3.0
    err = aligned_rmse(est_R, R, est_R[:2], R[:2])
    al = align(est_R, R)
    expected = np.sqrt(np.mean(np.sum((al.apply(est_R) - R) ** 2, axis=1)))
    assert err.rmse_receivers == pytest.approx(expected)
    assert err.rmse_receivers < 0.2


def test_aligned_direction_errors_undo_the_rotation_and_mirror(rng: np.random.Generator) -> None:
    Z = rng.normal(size=(6, 3))
    N = rng.normal(size=(9, 3))
    N /= np.linalg.norm(N, axis=1, keepdims=True)
    Q = _random_rotation(rng, 3) @ np.diag([1.0, 1.0, -1.0])  # rotation + mirror, as self-calibration allows
    tilt = np.deg2rad(2.0)
    Rz = np.array([[np.cos(tilt), -np.sin(tilt), 0], [np.sin(tilt), np.cos(tilt), 0], [0, 0, 1]])
    est_N = N @ Rz.T  # every direction off by at most 2 deg (about z)
    err = aligned_direction_errors(Z @ Q.T + 4.0, est_N @ Q.T, Z, N)
    expected = np.arccos(np.clip(np.sum(est_N * N, axis=1), -1, 1))
    assert np.allclose(err, expected, atol=1e-9)
    assert np.all(err <= tilt + 1e-12)


def test_rotvec_roundtrip_and_sphere_exp(rng: np.random.Generator) -> None:
    v = rng.normal(size=(5, 3))
    R = rotation_from_rotvec(v)
    np.testing.assert_allclose(R @ np.swapaxes(R, -1, -2), np.broadcast_to(np.eye(3), R.shape), atol=1e-12)
    np.testing.assert_allclose(rotation_from_rotvec(rotvec_from_rotation(R)), R, atol=1e-10)
    n = np.array([0.0, 0.0, 1.0])
    out = sphere_exp(n, np.array([np.pi / 2, 0.0, 0.0]))
    np.testing.assert_allclose(out, [1.0, 0.0, 0.0], atol=1e-12)
    assert rotation_angle_error(R[0], R[0]) == pytest.approx(0.0, abs=1e-7)
    assert angle_error(np.pi - 0.1, -np.pi + 0.1) == pytest.approx(-0.2)


def test_canonical_gauge_is_invariant_to_rigid_motion(rng: np.random.Generator) -> None:
    X = rng.normal(size=(9, 3)) * [5, 3, 1]
    A, _, _ = canonical_gauge(X)
    B, _, _ = canonical_gauge(X @ _random_rotation(rng, 3).T + 7.0)
    np.testing.assert_allclose(A, B, atol=1e-9)


@pytest.mark.parametrize("d", [2, 3])
@pytest.mark.parametrize("seed", range(5))
def test_canonical_gauge_mirror_rule(seed: int, d: int) -> None:
    """proper=False: a configuration and any mirror image / rigid motion of it give the same output,
    every principal axis with a non-negative third moment; proper=True keeps det +1, so mirror
    images stay mirror images (the handedness of the input)."""
    rng = np.random.default_rng(seed)
    X = rng.normal(size=(9, d)) * [5, 3, 1][:d] + rng.exponential(size=(9, d))  # skewed: moments nonzero
    M = _random_rotation(rng, d, proper=False)
    if np.linalg.det(M) > 0:
        M[:, 0] *= -1  # an improper orthogonal map: a mirror image
    A, _, al_a = canonical_gauge(X, proper=False)
    B, _, al_b = canonical_gauge(X @ M.T + 3.0, proper=False)
    np.testing.assert_allclose(A, B, atol=1e-9)
    assert np.all((A**3).sum(axis=0) >= 0)
    assert np.linalg.det(al_a.rotation) * np.linalg.det(al_b.rotation) == pytest.approx(-1.0)
    P, _, al_p = canonical_gauge(X)
    Q, _, al_q = canonical_gauge(X @ M.T + 3.0)
    assert np.linalg.det(al_p.rotation) == pytest.approx(1.0) and np.linalg.det(al_q.rotation) == pytest.approx(1.0)
    np.testing.assert_allclose(np.abs(P), np.abs(Q), atol=1e-9)  # the same up to the flipped last axis
    assert not np.allclose(P, Q, atol=1e-6)


@settings(max_examples=60, deadline=None)
@given(arrays(np.float64, st.tuples(st.integers(1, 6), st.integers(1, 6)), elements=st.sampled_from([0.0, 1.5, -2.0, np.nan, np.inf])))
def test_as_matrix_refuses_bad_values(a: np.ndarray) -> None:
    bad = np.isinf(a).any() or np.isnan(a).all() or (a[np.isfinite(a)] < 0).any()
    if bad:
        with pytest.raises(InputError):
            as_matrix(a, nonnegative=True)
    else:
        out = as_matrix(a, nonnegative=True)
        np.testing.assert_array_equal(np.isnan(out), np.isnan(a))


def test_as_matrix_refuses_wrong_ndim() -> None:
    with pytest.raises(InputError, match="2-D"):
        as_matrix(np.zeros(3))


def test_too_few_nodes_named() -> None:
    with pytest.raises(DegenerateGeometryError) as exc:
        check_toa_counts((3, 10), 30, 3, "none")
    assert exc.value.kind == "too-few-receivers"
    with pytest.raises(DegenerateGeometryError) as exc:
        check_toa_counts((10, 2), 20, 2, "none")
    assert exc.value.kind == "too-few-sources"


def test_read_matrix_csv_missing_and_errors(tmp_path) -> None:  # type: ignore[no-untyped-def]
    p = tmp_path / "m.csv"
    p.write_text("1,2,\nnan,4,5\n")
    m = read_matrix(p)
    assert m.shape == (2, 3) and np.isnan(m[0, 2]) and np.isnan(m[1, 0])
    p.write_text("1,x\n")
    with pytest.raises(InputError, match="row 1, column 2"):
        read_matrix(p)
    p.write_text("1,2\n3\n")
    with pytest.raises(InputError, match="different numbers"):
        read_matrix(p)
    q = tmp_path / "obj.npy"
    np.save(q, np.array([{"a": 1}], dtype=object), allow_pickle=True)
    with pytest.raises(InputError):
        read_matrix(q)


def test_write_json_is_strict_and_atomic(tmp_path) -> None:  # type: ignore[no-untyped-def]
    p = tmp_path / "r.json"
    write_json(p, {"a": np.array([1.0, np.nan]), "b": np.float32(2.0)})
    assert json.loads(p.read_text()) == {"a": [1.0, None], "b": 2.0}
    with pytest.raises(TypeError):
        write_json(p, {"a": object()})
    assert json.loads(p.read_text())["b"] == 2.0  # the old file survives a failed write
    assert [f.name for f in tmp_path.iterdir()] == ["r.json"]


def _square_trial(params: dict, seed: int) -> dict:  # type: ignore[type-arg]
    return {"value": params["x"] ** 2, "draw": float(np.random.default_rng(seed).normal())}


@pytest.mark.parametrize("backend", ["serial", "processes", "dask"])
def test_sweep_is_seeded_and_backend_independent(backend: str, tmp_path) -> None:  # type: ignore[no-untyped-def]
    grid = [{"x": 1}, {"x": 2}]
    a = run_sweep(_square_trial, grid, runs=3, seed=7, backend="serial", progress=False)
    b = run_sweep(_square_trial, grid, runs=3, seed=7, backend=backend, workers=2, progress=False)
    assert a == b
    assert [r["value"] for r in a] == [1, 1, 1, 4, 4, 4]
    assert len({r["seed"] for r in a}) == 6
    write_rows(a, tmp_path / "rows.csv")
    assert (tmp_path / "rows.csv").read_text().splitlines()[0].startswith("x,rep,seed,value")


def test_written_files_respect_the_umask(tmp_path) -> None:  # type: ignore[no-untyped-def]
    import os

    p = tmp_path / "r.json"
    write_json(p, {"a": 1})
    umask = os.umask(0)
    os.umask(umask)
    assert (p.stat().st_mode & 0o777) == (0o666 & ~umask)


def test_magnitude_and_run_count_guards() -> None:
    """Entries whose sums of squares overflow float64 and run counts whose trials cannot be held
    in memory are refused by name; the bound itself is the documented one."""
    from selfcal._checks import MAX_ABS_ENTRY, TRIAL_BYTES, check_magnitude, check_runs
    from selfcal.errors import InputError

    assert MAX_ABS_ENTRY == pytest.approx(np.sqrt(np.finfo(float).max / 1e12))
    ok = np.full((3, 4), MAX_ABS_ENTRY / 2)
    assert np.isfinite(float(ok[0, 0]) ** 2 * 1e12)  # 1e12 such squares still sum to a finite number
    check_magnitude(np.where(np.eye(3, 4) > 0, np.nan, ok), "m")  # NaN = missing, not large
    with pytest.raises(InputError, match=r"entry \(0, 0\).*another unit"):
        check_magnitude(np.where(np.eye(3, 4) > 0, 2 * MAX_ABS_ENTRY, 1.0), "m")
    assert check_runs(20) == 20 and check_runs(0, minimum=0) == 0
    with pytest.raises(InputError, match="memory"):
        check_runs(int(1e20))
    with pytest.raises(InputError):
        check_runs(0)
    assert TRIAL_BYTES >= 1024


def test_as_matrix_refuses_a_matrix_in_an_overflowing_unit_but_leaves_single_absurd_entries_to_the_solver():
    """A matrix whose typical entry is beyond MAX_ABS_ENTRY is a unit mistake: refused with one
    line. One absurd entry in a plausible matrix is a gross outlier for the TOA solver's robust
    fit (issue 12), so ``huge="scale"`` (default) passes it; ``huge="entry"`` refuses it."""
    from selfcal._checks import MAX_ABS_ENTRY, as_matrix
    from selfcal.errors import InputError

    M = np.arange(1.0, 13.0).reshape(3, 4)
    one = M.copy()
    one[1, 2] = 1e300
    assert as_matrix(one)[1, 2] == 1e300
    with pytest.raises(InputError, match="another unit"):
        as_matrix(one, huge="entry")
    with pytest.raises(InputError, match="another unit"):
        as_matrix(np.full((3, 4), 10 * MAX_ABS_ENTRY))
    assert np.array_equal(as_matrix(M, huge="entry"), M)
