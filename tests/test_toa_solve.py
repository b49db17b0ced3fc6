"""Spec of ``selfcal.solve_toa`` / ``ToaResult`` (toa/solve.py)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import selfcal
from selfcal.errors import DegenerateGeometryError, InputError
from selfcal.io import to_jsonable
from selfcal.metrics import aligned_rmse
from selfcal.toa import ToaResult, solve_toa, toa_model

DESIGN_KEYS = {
    "receivers", "sources", "receiver_offsets", "source_offsets", "receiver_cov", "source_cov",
    "residual_rms", "converged", "iterations", "method",
}


def network(rng, I, J, d, offsets="none"):
    r = rng.uniform(-5, 5, (I, d))
    s = rng.uniform(-7, 7, (J, d))
    dr = rng.normal(0, 1, I) if offsets in ("receivers", "both") else None
    o = rng.normal(0, 1, J) if offsets in ("sources", "both") else None
    return r, s, dr, o


def test_public_api_is_reexported():
    assert selfcal.solve_toa is solve_toa
    assert selfcal.ToaResult is ToaResult


@pytest.mark.parametrize("d", [2, 3])
@pytest.mark.parametrize("offsets", ["none", "receivers", "sources", "both"])
def test_noise_free_network_recovered_blind(d, offsets):
    """Blind start (003 MDS family / 004 rank-3 initialiser) then NLS: exact geometry."""
    rng = np.random.default_rng(7)
    I, J = 10, 14
    r, s, dr, o = network(rng, I, J, d, offsets)
    res = solve_toa(toa_model(r, s, dr, o), dim=d, offsets=offsets, rng=0)
    err = aligned_rmse(res.receivers, r, res.sources, s)
    assert err.rmse_receivers < 1e-6 and err.rmse_sources < 1e-6
    assert res.converged
    assert res.method.endswith("+nls") or "multistart" in res.method
    if offsets == "both":
        np.testing.assert_allclose(res.source_offsets, o - o[0], atol=1e-6)
        np.testing.assert_allclose(res.receiver_offsets, dr + o[0], atol=1e-6)


def test_noisy_network_reaches_the_noise_level(rng):
    I, J, d, sig = 8, 10, 2, 0.05
    r, s, _, _ = network(rng, I, J, d)
    res = solve_toa(toa_model(r, s) + rng.normal(0, sig, (I, J)), dim=d, rng=1)
    err = aligned_rmse(res.receivers, r, res.sources, s)
    assert err.rmse_receivers < 2 * sig
    assert res.sigma == pytest.approx(sig, rel=0.5)


def test_seconds_with_speed_give_offsets_in_seconds(rng):
    c = 343.0
    I, J, d = 8, 12, 3
    r, s, dr, o = network(rng, I, J, d, "both")
    metres = toa_model(r, s, dr, o)
    start = (r + 0.02, s - 0.02, dr, o)
    a = solve_toa(metres, dim=d, offsets="both", init=start)
    b = solve_toa(metres / c, dim=d, offsets="both", speed=c,
                  init=(start[0], start[1], dr / c, o / c))
    np.testing.assert_allclose(b.receivers, a.receivers, atol=1e-6)
    np.testing.assert_allclose(b.receiver_offsets * c, a.receiver_offsets, atol=1e-6)
    np.testing.assert_allclose(b.source_offsets * c, a.source_offsets, atol=1e-6)
    assert b.source_offsets[0] == 0.0
    assert b.to_dict()["units"]["offsets"] == "s"


def test_to_dict_has_the_design_keys_and_is_strict_json(rng):
    r, s, _, _ = network(rng, 6, 8, 3)
    Y = toa_model(r, s) + rng.normal(0, 0.01, (6, 8))
    Y[2, 3] = np.nan
    res = solve_toa(Y, init=(r, s))
    out = res.to_dict()
    assert DESIGN_KEYS <= set(out)
    assert out["receiver_offsets"] is None and out["source_offsets"] is None
    assert np.array(out["receiver_cov"]).shape == (6, 3, 3)
    assert res.n_missing == 1
    json.dumps(to_jsonable(out), allow_nan=False)
    # canonical gauge: receiver centroid at the origin
    np.testing.assert_allclose(np.mean(out["receivers"], axis=0), 0.0, atol=1e-9)


def test_rank3_method_returns_the_unrefined_initialiser(rng):
    I, J, d = 10, 14, 3
    r, s, dr, o = network(rng, I, J, d, "both")
    Y = toa_model(r, s, dr, o) + rng.normal(0, 0.01, (I, J))
    res = solve_toa(Y, dim=d, offsets="both", method="rank3", rng=0)
    ref = solve_toa(Y, dim=d, offsets="both", rng=0)
    assert res.method == "rank3" and res.iterations == 0
    assert np.isnan(res.receiver_cov).all()
    assert res.source_offsets[0] == 0.0
    assert ref.residual_rms <= res.residual_rms + 1e-12
    with pytest.raises(InputError):
        solve_toa(Y, dim=d, method="rank3")


def test_multistart_escapes_a_mirrored_start():
    """Two sources started at their mirror image: one refinement stays in the wrong
    basin; method='auto' detects the implausible fit and restarts."""
    rng = np.random.default_rng(4)
    I, J, d = 8, 10, 2
    r, s, _, _ = network(rng, I, J, d)
    Y = toa_model(r, s) + rng.normal(0, 0.01, (I, J))
    s0 = s.copy()
    s0[:2] = 2 * r.mean(axis=0) - s0[:2]
    one = solve_toa(Y, dim=2, init=(r, s0), method="nls")
    auto = solve_toa(Y, dim=2, init=(r, s0), method="auto", rng=0)
    assert aligned_rmse(one.receivers, r, one.sources, s).rmse_sources > 0.5
    assert aligned_rmse(auto.receivers, r, auto.sources, s).rmse_sources < 0.03
    assert auto.n_starts > 1 and "multistart" in auto.method


def test_robust_loss_through_solve_toa(rng):
    I, J, d, sig = 10, 20, 3, 0.01
    r, s, _, _ = network(rng, I, J, d)
    Y = toa_model(r, s) + rng.normal(0, sig, (I, J))
    bad = rng.random((I, J)) < 0.05
    Y[bad] += 2.0
    res = solve_toa(Y, dim=d, loss="cauchy", init=(r + 0.03, s - 0.03))
    assert aligned_rmse(res.receivers, r, res.sources, s).rmse_receivers < 3 * sig


# --- bad input: every class raises the named error (hypothesis-fuzzed) -------------------

FAST = settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
good = st.integers(min_value=4, max_value=7)


@FAST
@given(I=good, J=good, i=st.integers(0, 3), j=st.integers(0, 3), v=st.floats(-1e6, -1e-9))
def test_negative_range_without_offsets_is_an_input_error(I, J, i, j, v):
    Y = np.ones((I, J))
    Y[i, j] = v
    with pytest.raises(InputError, match="negative"):
        solve_toa(Y, dim=2)


@FAST
@given(I=good, J=good, i=st.integers(0, 3), j=st.integers(0, 3), v=st.sampled_from([np.inf, -np.inf]),
       offsets=st.sampled_from(["none", "receivers", "sources", "both"]))
def test_infinite_entry_is_an_input_error(I, J, i, j, v, offsets):
    Y = np.ones((I, J))
    Y[i, j] = v
    with pytest.raises(InputError, match="infinite"):
        solve_toa(Y, dim=2, offsets=offsets)


@FAST
@given(shape=st.sampled_from([(5,), (2, 3, 4), (0, 5), ()]))
def test_wrong_shape_is_an_input_error(shape):
    with pytest.raises(InputError):
        solve_toa(np.ones(shape), dim=2)


@FAST
@given(d=st.sampled_from([2, 3]), small=st.integers(1, 3), big=st.integers(8, 12), rows=st.booleans())
def test_too_few_nodes_is_degenerate(d, small, big, rows):
    n = min(small, d)  # fewer than d + 1 on one side
    shape = (n, big) if rows else (big, n)
    with pytest.raises(DegenerateGeometryError, match="too-few"):
        solve_toa(np.ones(shape), dim=d)


@FAST
@given(missing=st.integers(27, 90), seed=st.integers(0, 1000))
def test_too_few_observed_entries_is_degenerate(missing, seed):
    # 10 x 10 in 3-D with both offsets: 100 entries for n_parameters = 3*20 - 6 + 19 = 73
    # unknowns. The complete matrix (and one with 26 entries missing) passes the count, so
    # only the missing entries can make it fail: 27 or more leave <= 73 equations.
    from selfcal._checks import check_toa_counts
    from selfcal.toa import n_parameters

    assert n_parameters(10, 10, 3, "both") == 73
    check_toa_counts((10, 10), 100, 3, "both")
    check_toa_counts((10, 10), 100 - 26, 3, "both")
    rng = np.random.default_rng(seed)
    R, S = rng.uniform(0, 5, (10, 3)), rng.uniform(0, 5, (10, 3))
    Y = np.linalg.norm(R[:, None] - S[None], axis=-1)
    Y.flat[rng.choice(100, missing, replace=False)] = np.nan
    with pytest.raises(DegenerateGeometryError) as exc:
        solve_toa(Y, dim=3, offsets="both")
    assert exc.value.kind == "too-few-measurements"


@FAST
@given(opt=st.sampled_from([
    {"dim": 4}, {"offsets": "all"}, {"loss": "l1"}, {"method": "mds"}, {"speed": -343.0},
    {"speed": 0.0}, {"init": "mirror"}, {"init": (np.zeros((3, 2)), np.zeros((6, 2)))}, {"rng": "x"},
]))
def test_bad_options_are_input_errors(opt):
    Y = np.ones((5, 6))
    with pytest.raises(InputError):
        solve_toa(Y, **{"dim": 2, **opt})


def test_all_missing_is_an_input_error():
    with pytest.raises(InputError, match="missing"):
        solve_toa(np.full((5, 6), np.nan), dim=2)
