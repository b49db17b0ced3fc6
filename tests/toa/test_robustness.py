"""Robustness of the TOA engine with offsets="both" (follow-ups to issues 2, 3 and 7).

Each test is a reported defect: missing entries breaking the offsets initialiser, a
local minimum on a tiered conference room, and the observability verdict of the
covariance step.
"""

from __future__ import annotations

import json
import warnings

import numpy as np
import pytest

from selfcal.errors import ConvergenceWarning, DegenerateGeometryError, Status
from selfcal.geometry import align
from selfcal.scenarios.conference import conference_scene
from selfcal.toa import solve_toa
from selfcal.toa.init.offset_positions import offset_free_positions
from selfcal.toa.init.offsets_init import initialize_offsets

#: known gaps of the new search, kept visible as non-strict xfails (issue 12 closing note)
SEARCH_GAP = "known gap of the one-search solve_toa of issue 12 (toa/search.py) (issue 12): "

C = 343.0


def _room(I: int, J: int, missing: float, seed: int):
    """Receivers / senders uniform in an 8 x 6 x 3 m room, distinct delays, onsets; NaN at random."""
    g = np.random.default_rng(seed)
    box = np.array([8.0, 6.0, 3.0])
    r, s = g.uniform(0, 1, (I, 3)) * box, g.uniform(0, 1, (J, 3)) * box
    d, o = g.uniform(0, 0.02, I), g.uniform(0, 0.03, J)
    T = np.linalg.norm(r[:, None] - s[None], axis=-1) / C + d[:, None] + o[None]
    T[g.random(T.shape) < missing] = np.nan
    return r, s, T


def _aligned_max_error(res, r, s) -> float:
    est, true = np.vstack([res.receivers, res.sources]), np.vstack([r, s])
    return float(np.abs(align(est, true).apply(est) - true).max())


def _solve(T, seed):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ConvergenceWarning)
        return solve_toa(T, dim=3, offsets="both", speed=C, rng=seed)


@pytest.mark.parametrize("missing", [0.1, 0.2])
@pytest.mark.parametrize("seed", [0, 1, 9])  # seed 9 failed before the fix
def test_both_offsets_with_random_missing_entries_recovers_geometry(missing, seed):
    """20 x 20 in 3-D with 10-20 % of the entries missing: exact geometry and offsets."""
    r, s, T = _room(20, 20, missing, seed)
    res = _solve(T, seed)
    assert _aligned_max_error(res, r, s) < 1e-6
    obs = np.isfinite(T)
    pred = (np.linalg.norm(res.receivers[:, None] - res.sources[None], axis=-1) / C
            + res.receiver_offsets[:, None] + res.source_offsets[None])
    assert np.abs(pred - T)[obs].max() < 1e-9  # seconds


@pytest.mark.parametrize("seed", range(3))
def test_initialiser_with_missing_entries_stays_finite_and_at_room_scale(seed):
    """The reported failure: 8 x 20 with NaN gave positions of 1e13-1e50 m (rejected start)."""
    r, s, T = _room(8, 20, 0.1, seed)
    rr, ss, d0, o0 = initialize_offsets(T * C, 3, rng=seed)
    for a in (rr, ss, d0, o0):
        assert np.isfinite(a).all()
    assert np.ptp(np.vstack([rr, ss]), axis=0).max() < 100.0  # the room is 8 m across
    res = _solve(T, seed)
    assert _aligned_max_error(res, r, s) < 1e-6


def test_positions_step_survives_a_planar_side():
    """Stem microphones at one height above flat desks: the linear upgrade alone is singular.

    With the true offsets removed the ranges are exact; the position step must return a
    finite geometry at the scale of the room (it returned 1e6-1e8 m before).
    """
    sc = conference_scene(12, (12.0, 12.0, 3.0), layout="stem", rng=0)
    D = np.linalg.norm(sc.receivers[:, None] - sc.senders[None], axis=-1)
    r, s = offset_free_positions(D, np.zeros(D.shape, bool), 3, rng=0)
    assert np.isfinite(r).all() and np.isfinite(s).all()
    est, true = np.vstack([r, s]), np.vstack([sc.receivers, sc.senders])
    assert np.abs(align(est, true).apply(est) - true).max() < 2.0


def _conference_times(U, room, seed, jitter):
    sc = conference_scene(U, room, layout="tiered", rng=seed)
    d = np.linalg.norm(sc.receivers[:, None] - sc.senders[None], axis=-1)
    T = d / C + sc.sender_onsets[None] + sc.receiver_delays[:, None]
    return sc, T + np.random.default_rng(seed + 1000).normal(0, jitter, T.shape)


@pytest.mark.parametrize("seed", [7, 8, 9])
def test_tiered_conference_with_jitter_reaches_the_basin_of_the_truth(seed):
    """20 units on tiered rows, 5 us jitter: no worse than the refinement started at the truth.

    Before the node sweeps / pair flips these three seeds stopped in a local minimum (microphones
    low, their loudspeakers high) with a residual ~10 % above the truth-started one; the one
    search reaches it with the pair moves ranked by partial refits (1 flipped unit on seeds 7
    and 8, 4 on seed 9, applied together).
    """
    sc, T = _conference_times(20, (12.0, 12.0, 3.0), seed, 5e-6)
    res = _solve(T, seed)
    ref = solve_toa(T, dim=3, offsets="both", speed=C, method="nls",
                    init=(sc.receivers, sc.senders, sc.receiver_delays, sc.sender_onsets))
    assert res.residual_rms <= ref.residual_rms * (1 + 1e-6)
    assert _aligned_max_error(res, sc.receivers, sc.senders) < 0.05


# ----------------------------------------------------------------------------- [unobservable-node]


def _coplanar_speakers(seed=0, I=14, J=10):
    """J loudspeakers exactly in the plane z = 0.8 m, I microphones 0.3-0.5 m above it (I > J:
    the microphones are the nodes the Schur step eliminates)."""
    g = np.random.default_rng(seed)
    s = np.column_stack([g.uniform(0, 10, (J, 2)), np.full(J, 0.8)])
    r = np.column_stack([g.uniform(0, 10, (I, 2)), 0.8 + g.uniform(0.3, 0.5, I)])
    return r, s, g.uniform(0, 7, I), g.uniform(0, 10, J)


def _dense_jacobian(r, s):
    """d|r_i - s_j| + d_i + o_j / d(all positions, all offsets), written out entry by entry."""
    I, J = len(r), len(s)
    n = 4 * (I + J)
    Jm = np.zeros((I * J, n))
    for i in range(I):
        for j in range(J):
            u = (r[i] - s[j]) / np.linalg.norm(r[i] - s[j])
            row = i * J + j
            Jm[row, 3 * i:3 * i + 3] = u
            Jm[row, 3 * I + 3 * j:3 * I + 3 * j + 3] = -u
            Jm[row, 3 * (I + J) + i] = 1.0
            Jm[row, 3 * (I + J) + I + j] = 1.0
    return Jm


@pytest.mark.parametrize("scale", [1e-3, 1.0, 1e3])
def test_unobservable_verdict_is_the_geometry_not_the_units(scale):
    """A microphone in the plane of coplanar loudspeakers has a first-order free height.

    Independent check: the dense Jacobian then has one more null direction than the 7 of the
    gauge (rotations, translations, common offset shift). The covariance step must say so
    at every unit scale, and must not say so once the microphone is 1 cm off the plane.
    """
    from selfcal.errors import DegenerateGeometryError
    from selfcal.toa.engine.nls import refine_toa

    r, s, d, o = _coplanar_speakers()
    for h, singular in ((0.0, True), (0.01, False)):
        rr = r.copy()
        rr[0, 2] = 0.8 + h
        sv = np.linalg.svd(_dense_jacobian(rr, s), compute_uv=False)
        assert (sv[-8] / sv[0] < 1e-12) == singular  # 8th smallest: the first non-gauge direction
        R = (np.linalg.norm(rr[:, None] - s[None], axis=-1) + d[:, None] + o[None]) * scale
        args = (R, rr * scale, s * scale)
        kw = dict(offsets="both", receiver_offsets0=d * scale, source_offsets0=o * scale)
        if singular:
            with pytest.raises(DegenerateGeometryError) as exc:
                refine_toa(*args, **kw)
            assert exc.value.kind == "unobservable-node"
        else:
            sol = refine_toa(*args, **kw)
            assert np.isfinite(sol.receiver_cov).all()


def test_solve_leaves_the_saddle_of_a_microphone_started_in_the_loudspeaker_plane():
    """The in-plane point is a saddle (zero out-of-plane gradient), not the solution.

    Started there, the refinement used to stop on the plane and the covariance step raised
    [unobservable-node]; solve_toa now moves the node off the plane and fits exactly. Each
    microphone's side of the plane is the mirror ambiguity of coplanar loudspeakers, so we
    compare heights above the plane.
    """
    r, s, d, o = _coplanar_speakers()
    R = np.linalg.norm(r[:, None] - s[None], axis=-1) + d[:, None] + o[None]
    r0 = r.copy()
    r0[0, 2] = 0.8
    r0[0, :2] += 0.2
    res = solve_toa(R, dim=3, offsets="both", init=(r0, s, d, o))
    assert res.residual_rms < 1e-9

    def heights(rr, ss):
        c = ss.mean(axis=0)
        n = np.linalg.svd(ss - c)[2][-1]
        return np.abs((rr - c) @ n)

    np.testing.assert_allclose(heights(res.receivers, res.sources), heights(r, s), atol=1e-6)


# ----------------------------------------------------------------------------- issue 12: robust and honest


def _net(seed, I=10, J=14, d=3, sig=0.01):
    g = np.random.default_rng(seed)
    r, s = g.uniform(-5, 5, (I, d)), g.uniform(-7, 7, (J, d))
    D = np.linalg.norm(r[:, None] - s[None], axis=-1)
    return r, s, D + g.normal(0, sig, D.shape), g


def _err(res, r, s):
    from selfcal.metrics import aligned_rmse

    ok_r, ok_s = np.isfinite(res.receivers).all(1), np.isfinite(res.sources).all(1)
    return aligned_rmse(res.receivers[ok_r], r[ok_r], res.sources[ok_s], s[ok_s]).rmse_receivers


@pytest.mark.parametrize("value", [1e300, 1e12, -1e9])
def test_a_single_absurd_entry_never_crashes_and_is_flagged(value):
    """Before issue 12 a 1e300 entry crashed MDS (LinAlgError: SVD did not converge)."""
    r, s, Y, _ = _net(0)
    Y[3, 5] = value
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        res = solve_toa(Y, dim=3, rng=0, noise=0.01)
    assert res.outliers[3, 5] and res.outliers.sum() <= 2
    assert _err(res, r, s) < 0.03  # ~3 sigma: the other 139 entries are clean
    json.dumps(res.to_dict(), allow_nan=False)


def test_the_gross_entry_fence_flags_no_clean_entry_of_small_matrices():
    """Median polish zeroes a residual per row and column, so on 5 x 5 the quartiles of its
    residuals collapsed and the far-out fence dropped every node of clean networks (found by
    the permutation hypothesis test). Clean 5-9 node networks over 100 draws: nothing is
    flagged (2000 draws measured: the largest clean entry at 2.5 of the 3 spreads); a 1e300 / 1e6 typo in them still is."""
    from selfcal.toa.verdict.robust import gross_entries

    for seed in range(100):
        g = np.random.default_rng(seed)
        I, J, d = int(g.integers(5, 10)), int(g.integers(5, 10)), int(g.integers(2, 4))
        Y = np.linalg.norm(g.uniform(-5, 5, (I, 1, d)) - g.uniform(-7, 7, (1, J, d)), axis=-1)
        Y = Y + g.normal(0, 0.01, Y.shape) + (g.normal(0, 1, (1, J)) if seed % 2 else 0.0)
        assert not gross_entries(Y).any()
        for typo in (1e300, 1e6):
            Z = Y.copy()
            Z[seed % I, seed % J] = typo
            assert gross_entries(Z)[seed % I, seed % J]


@pytest.mark.parametrize("seed", range(2))
def test_gross_outliers_are_flagged_and_do_not_pull_the_fit(seed):
    """5 % gross outliers (0.5-2 m on 1 cm noise): every one in the mask, positions within 2x
    the outlier-free error (the issue's acceptance criterion)."""
    r, s, Y, g = _net(seed, 10, 20)
    clean = solve_toa(Y, dim=3, rng=0, noise=0.01)
    bad = g.random(Y.shape) < 0.05
    Yb = Y + np.where(bad, g.uniform(0.5, 2.0, Y.shape), 0.0)
    res = solve_toa(Yb, dim=3, rng=0, noise=0.01)
    assert res.outliers[bad].all()
    assert _err(res, r, s) <= 2 * _err(clean, r, s)
    assert res.success


def test_clean_data_flag_no_outlier_beyond_the_bonferroni_rate():
    """With Gaussian noise the rule flags any inlier with probability <= alpha = 0.01 per matrix
    (Bonferroni over the m entries). Over 6 matrices P(two or more with a flag) < 0.002."""
    flagged = 0
    for seed in range(6):
        _, _, Y, _ = _net(10 + seed, 8, 10, 2)
        res = solve_toa(Y, dim=2, rng=0)
        flagged += bool(res.outliers.any())
    assert flagged <= 1


def test_nodes_with_too_few_ranges_are_dropped_and_reported():
    """A receiver with 2 ranges in 3-D (it needs d + 1 = 4) and a source with 3: dropped, reported,
    NaN rows; the rest is calibrated."""
    r, s, Y, _ = _net(3)
    Y[0, 2:] = np.nan
    Y[3:, 7] = np.nan
    res = solve_toa(Y, dim=3, rng=0, noise=0.01)
    assert res.dropped_receivers == (0,) and res.dropped_sources == (7,)
    assert np.isnan(res.receivers[0]).all() and np.isnan(res.sources[7]).all()
    assert np.isfinite(np.delete(res.receivers, 0, axis=0)).all()
    out = res.to_dict()
    assert out["dropped_receivers"] == [0] and out["dropped_sources"] == [7]
    json.dumps(out, allow_nan=False)
    assert _err(res, r, s) < 0.03


def test_dropping_everything_is_a_degenerate_geometry_error():
    _, _, Y, _ = _net(4, 6, 6)
    Y[:, 2:] = np.nan
    with pytest.raises(DegenerateGeometryError):
        solve_toa(Y, dim=3)


@pytest.mark.parametrize(("seed", "offsets", "dim"), [(0, "none", 3), (1, "none", 2), (2, "both", 2), (3, "sources", 2)])
def test_a_uniform_random_matrix_fails_its_own_test(seed, offsets, dim):
    """No geometry: the cross-validated test (PRESS of the geometry vs offsets alone) rejects it,
    success is False and a ConvergenceWarning is raised."""
    Y = np.random.default_rng(seed).uniform(0, 10, (8, 10))
    with pytest.warns(ConvergenceWarning):
        res = solve_toa(Y, dim=dim, offsets=offsets, rng=0)
    assert not res.success and res.status == Status.FAILED_TEST and res.geometry is not None
    assert res.to_dict()["success"] is False


def _random_or_network(kind, I, J, dim, offsets, g):
    if kind == "random":
        return g.uniform(0, 10, (I, J))
    r, s = g.uniform(0, 10, (I, dim)), g.uniform(0, 10, (J, dim))
    Y = np.linalg.norm(r[:, None] - s[None], axis=-1)
    if offsets in ("receivers", "both"):
        Y = Y + g.uniform(0, 3, I)[:, None]
    if offsets in ("sources", "both"):
        Y = Y + g.uniform(0, 3, J)[None]
    return Y + g.normal(0, 0.05, Y.shape)  # 5 cm on a 10 m network


_PERM_CASES = [(8, 10, 2, "none"), (8, 10, 3, "none"), (8, 10, 2, "sources"), (8, 10, 2, "both"),
               (10, 14, 3, "both"), (30, 40, 3, "none")]


def test_the_permutation_test_has_its_level_on_random_matrices():
    """Uniform random matrices (no geometry): the permutation test passes at most its level.

    With 19 exchangeable copies a matrix without geometry passes with probability 1 / 20
    (exactly for offsets="none", Freedman-Lane residual permutation otherwise). Over 40
    matrices the count is Binomial(40, 0.05): P(X >= 7) = 0.003, so 6 is the bound
    (measured: 15 of 240 over six sizes, 5 of 210 over seven offset cases).
    """
    from selfcal.toa.result import permutation_test

    passed = 0
    for k in range(40):
        I, J, dim, offsets = _PERM_CASES[k % len(_PERM_CASES)]
        pt = permutation_test(_random_or_network("random", I, J, dim, offsets, np.random.default_rng(k)), dim, offsets)
        assert pt is not None and 0 < pt.p_value <= 1
        passed += pt.passed
    assert passed <= 6


def test_the_permutation_test_passes_genuine_networks():
    """Noisy networks (5 cm on 10 m, 2-D and 3-D, every offsets mode, 8 x 10 to 30 x 40, 20 %
    missing): every one passes (measured 0 misses in 30-40 draws per case; the misses are at
    5 x 5 in 2-D, 3 of 40, and 12 x 6 with both offsets, 2 of 30, where few entries are spare)."""
    from selfcal.toa.result import permutation_test

    for k in range(24):
        I, J, dim, offsets = _PERM_CASES[k % len(_PERM_CASES)]
        g = np.random.default_rng(100 + k)
        Y = _random_or_network("net", I, J, dim, offsets, g)
        if k % 4 == 3:
            Y[g.random(Y.shape) < 0.2] = np.nan
        pt = permutation_test(Y, dim, offsets)
        assert pt is not None and pt.passed, (k, pt)


@pytest.mark.parametrize("anchors", [5, 6])
def test_the_permutation_test_passes_a_moving_tag_seen_by_five_or_six_anchors(anchors):
    """A UWB flight whose anchor never saw the tag is a 5-anchor network, still well posed
    (5 ranges per tag position for 3 unknowns). The test's fixed procedure refines its MDS
    start a few iterations (``PERMUTATION_REFINE``): without that, 4 of 10 clean 5-anchor
    flights failed (p = 0.25, 0.70, ...; an honest result given exit 1). Measured with it:
    10 of 10 at 5 and at 6 anchors; all 6 seeds here must pass."""
    from selfcal.experiments.lps import simulate_uwb_flight
    from selfcal.toa.verdict.trust import permutation_test

    for seed in range(1, 7):
        Y = simulate_uwb_flight(seed, 500, layout="lps", spike_rate=0.0, bias_std=0.0)["ranges"][:anchors]
        pt = permutation_test(Y, 3, "none")
        assert pt is not None and pt.passed, (seed, pt)


def _random_verdicts(seeds, **kw):
    out = []
    for seed in seeds:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            out.append(solve_toa(np.random.default_rng(seed).uniform(0, 10, (8, 10)), rng=0, **kw))
    return out


def test_random_2d_matrices_fail_their_test_over_seeds():
    """8 x 10, 2-D, no offsets, noise unknown (the case the PRESS rule passed 5 of 10): the
    verdict passes at most the permutation test's level, 1 / 20. Over 8 seeds the passes are
    at most Binomial(8, 0.05): P(X >= 3) = 0.006, so 2 is the bound."""
    res = _random_verdicts(range(8), dim=2)
    assert sum(r.success for r in res) <= 2
    assert all(r.geometry is not None and r.geometry.permutation is not None for r in res)


@pytest.mark.slow
def test_random_2d_matrices_fail_their_test_over_many_seeds():
    """As above over 100 seeds: P(Binomial(100, 0.05) >= 12) = 0.004, so 11 is the bound."""
    res = _random_verdicts(range(100, 200), dim=2)
    assert sum(r.success for r in res) <= 11


@pytest.mark.parametrize("seed", [5, 8])
def test_a_random_matrix_whose_best_fit_is_collinear_fails_instead_of_raising(seed):
    """8 x 10, 2-D, source offsets: the search's winner is (nearly) collinear on these seeds; the
    robust refit from it used to raise DegenerateGeometryError. Bad-but-valid data: a result
    that fails its test, with a ConvergenceWarning, JSON-safe."""
    Y = np.random.default_rng(seed).uniform(0, 10, (8, 10))
    with pytest.warns(ConvergenceWarning):
        res = solve_toa(Y, dim=2, offsets="sources", rng=0)
    assert res.status == Status.FAILED_TEST and not res.success
    json.dumps(res.to_dict(), allow_nan=False)


@pytest.mark.slow
def test_random_matrices_with_offsets_never_raise():
    """30 seeds x {sources, receivers, both} of 8 x 10 2-D uniform matrices: a result every time,
    passing at most the test's level (P(Binomial(90, 0.05) >= 11) = 0.009)."""
    passed = 0
    for offsets in ("sources", "receivers", "both"):
        for r in _random_verdicts(range(30), dim=2, offsets=offsets):
            json.dumps(r.to_dict(), allow_nan=False)
            passed += r.success
    assert passed <= 10


def test_one_entry_of_leverage_near_one_does_not_decide_the_geometry_verdict():
    """A clean 8 x 10 3-D network (1 cm noise) with source 0 seen by 4 receivers only: its
    entries have leverages up to ~0.9999 (measured 0.92-0.99988 over 6 seeds). One such entry
    with a 3-sigma residual and h = 1 - 1e-4 multiplies its PRESS term by 1e8: the sum-PRESS
    rule of the last stop then failed the network (as on the LPS flight data4: 4.44e3 vs
    1.12e3); the median-PRESS rule and the permutation test pass it."""
    from selfcal.toa.result import geometry_test
    from selfcal.toa.verdict.leverage import leverages

    g = np.random.default_rng(0)
    r, s = g.uniform(0, 10, (8, 3)), g.uniform(0, 10, (10, 3))
    Y = np.linalg.norm(r[:, None] - s[None], axis=-1) + g.normal(0, 0.01, (8, 10))
    Y[4:, 0] = np.nan
    res = solve_toa(Y, dim=3, rng=0)
    assert res.success and res.geometry.passed
    H = leverages(Y, res.receivers, res.sources, None, None, "none")
    E = res.residuals.copy()
    H[0, 0], E[0, 0] = 1 - 1e-4, 0.03
    geo = geometry_test(Y, E, H, 3, "none")
    ok = np.isfinite(E)
    sum_press = float(np.sum((E[ok] / (1 - H[ok])) ** 2))
    assert sum_press > geo.press_null  # the old rule would have failed this clean network
    assert geo.passed and geo.press < 1e-3 * geo.press_null


def _nesting_rss(seeds, I, J, dim):
    out = []
    for seed in seeds:
        g = np.random.default_rng(seed)
        Y = _random_or_network("net", I, J, dim, "receivers", g)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            res = solve_toa(Y, dim=dim, offsets="auto", loss="linear", rng=0)
        out.append(res.selection["offsets"]["rss"])
    return out


@pytest.mark.parametrize(("I", "J", "dim"), [(8, 10, 2), (6, 12, 3)])
def test_a_model_never_ends_above_the_models_it_nests(I, J, dim):
    """offsets="auto" fits none, receivers, sources, both; each larger model is started from the
    best fit of those it nests with the new offsets at zero, a point of the larger model with
    the same cost, and its search accepts only lower costs. With the linear loss every model
    is fitted on the same entries, so RSS(receivers), RSS(sources) <= RSS(none) and
    RSS(both) <= all three, to round-off (1e-9 relative). Before, "receivers" ended at
    28.1 vs 24.0 for the offsets-free fit on the LPS flight data4."""
    _assert_nested(_nesting_rss(range(1), I, J, dim))


def _assert_nested(fits):
    tol = 1 + 1e-9  # round-off of the final refinement
    for rss in fits:
        assert rss["receivers"] <= rss["none"] * tol and rss["sources"] <= rss["none"] * tol
        assert rss["both"] <= min(rss["none"], rss["receivers"], rss["sources"]) * tol


@pytest.mark.slow
def test_a_model_never_ends_above_the_models_it_nests_over_seeds():
    _assert_nested(_nesting_rss(range(1, 11), 8, 10, 2) + _nesting_rss(range(1, 11), 6, 12, 3))


def test_a_wrong_noise_level_fails_the_chi_square_test():
    _, _, Y, _ = _net(5, 8, 10, 2, sig=0.05)
    with pytest.warns(ConvergenceWarning, match="chi-square"):
        res = solve_toa(Y, dim=2, rng=0, noise=0.005)
    assert res.status == Status.FAILED_TEST and not res.success and res.noise == 0.005


# ----------------------------------------------------------------------------- minimal 12 x 6 (issue 12)


def _minimal_bench():
    import importlib.util
    from pathlib import Path

    spec = importlib.util.spec_from_file_location(
        "bench_toa_minimal", Path(__file__).resolve().parents[2] / "benchmarks" / "bench_toa_minimal.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _minimal_draw(seed):
    return _minimal_bench().one(seed)


def _blind_descends_to_the_reference(seed):
    """Whether the truth-started refinement (trf) run again from the blind answer reaches the
    truth-started fit's sum of squares + 0.01 sigma^2: the blind answer lies in the valley the
    truth's descent follows, stopped earlier along it."""
    from selfcal.toa import refine_toa

    mod = _minimal_bench()
    r, s, d, o, T = mod.scene(seed)
    c, sigma = mod.C, mod.NOISE * mod.C
    ref = refine_toa(T * c, r, s, offsets="both", receiver_offsets0=d * c, source_offsets0=o * c,
                     covariance=False, solver="trf")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            res = solve_toa(T, dim=3, offsets="both", speed=c, rng=seed)  # as mod.one(seed)
            again = refine_toa(T * c, res.receivers, res.sources, offsets="both",
                               receiver_offsets0=np.asarray(res.receiver_offsets) * c,
                               source_offsets0=np.asarray(res.source_offsets) * c, covariance=False, solver="trf")
        except Exception:  # a failed solve or refinement is a miss
            return False
    return float(np.nansum(again.residuals**2)) <= float(np.nansum(ref.residuals**2)) + 0.01 * sigma**2


@pytest.mark.slow
def test_minimal_12x6_blind_solves_land_in_the_basin_of_the_truth():
    """12 mics x 6 sources, both offsets, 20 us: >= 95 % of 200 seeded draws in the truth's basin.

    Binomial: with a true rate of 97 %, 190 / 200 is passed with probability 0.9; a rate of
    90 % passes it with probability < 0.01. "In the basin": a sum of squares at most the
    truth-started fit's + 0.01 sigma^2 (the benchmark's docstring), or, where the blind answer
    is above that, the same refinement run from it gets there. The second clause is needed
    because the truth's basin need not hold a minimum: in all 13 draws of seeds 0-199 that the
    first clause missed (25, 29, 32, 38, 56, 84, 103, 126, 156, 162, 174, 198, 199; measured on
    the main of 2026-12-03) the truth-started refinement itself ran away from the truth (node
    extents 15 m to 5.6e6 m against 2.8-4.4 m; 4 of them stopped at the iteration cap) down a
    valley in which the cost keeps falling, so the comparison measured how far each run walked
    along it: the blind answers were 0.010-0.068 sigma^2 above it (0.48 for seed 103), and
    refined again 9 of the 13 reach it (38, 103, 156, 198 stay 0.02-0.47 sigma^2 above: counted
    as misses, 196 of 200). None of the 13 was a confident answer: 12 ended FAILED_TEST ("the
    data do not determine the geometry") and seed 126 names its 3 undetermined nodes. Seeds
    0-199 are the ones the number of scaled starts was chosen on (selfcal.toa.search.SCALED_STARTS);
    the held-out measurement is in benchmarks/bench_toa_minimal.py.
    """
    hits = sum(_minimal_draw(seed)["in_basin"] or _blind_descends_to_the_reference(seed) for seed in range(200))
    assert hits >= 190


def test_minimal_12x6_reduced_most_blind_solves_land_in_the_basin():
    """The reduced default version: 16 draws none of the studies used (seeds 760-775), >= 13.

    At the measured rate (~95 %) 13 of 16 or more happen with probability 0.99 (binomial); at
    the rate of the search before the racing of 24 scaled starts was affordable (~90 %) with
    probability 0.93, at 70 % with 0.25: a guard against a search that lost its way, the slow
    test above is the specification.
    """
    hits = sum(_minimal_draw(seed)["in_basin"] for seed in range(760, 776))
    assert hits >= 13


@pytest.mark.parametrize("offsets", ["none", "receivers", "sources", "both"])
def test_leverages_equal_the_hat_diagonal_of_the_dense_jacobian(offsets):
    # leverages() forms (J^T J)^+ from the sparse normal matrix; the hat diagonal of the dense
    # Jacobian's SVD is the independent computation. Squaring the condition number costs
    # digits (1e-7 measured), far below what studentisation needs (h is in [0, 1]).
    from selfcal.toa.engine.nls import _pack, toa_jacobian
    from selfcal.toa.verdict.leverage import leverages

    for seed in range(6):
        rng = np.random.default_rng(seed)
        I, J, d = int(rng.integers(6, 25)), int(rng.integers(6, 25)), int(rng.choice([2, 3]))
        r, s = rng.uniform(-3, 3, (I, d)), rng.uniform(-3, 3, (J, d))
        dr = rng.normal(size=I) if offsets in ("receivers", "both") else None
        ds = rng.normal(size=J) if offsets in ("sources", "both") else None
        Y = np.linalg.norm(r[:, None] - s[None], axis=-1)
        miss = rng.random(Y.shape) < 0.1
        Y[miss] = np.nan
        held = miss & (rng.random(Y.shape) < 0.5)
        H = leverages(Y, r, s, dr, ds, offsets, held_out=held)
        theta = _pack(r, s, dr, ds)
        U, sv, Vt = np.linalg.svd(toa_jacobian(theta, Y, d, offsets).toarray(), full_matrices=False)
        k = int(np.sum(sv > sv[0] * 1e-10))
        assert np.allclose(H[~miss], np.sum(U[:, :k] ** 2, axis=1), atol=1e-6)
        Jo = toa_jacobian(theta, np.where(held, 1.0, np.nan), d, offsets).toarray()
        assert np.allclose(H[held], np.sum(((Jo @ Vt[:k].T) / sv[:k]) ** 2, axis=1), atol=1e-6)
        assert np.all(np.isnan(H[miss & ~held]))
