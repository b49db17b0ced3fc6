"""Onset times and internal delays (paper 004): the rank-3 iteration, the fast solver, the initialiser."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from selfcal.errors import ConvergenceWarning, DegenerateGeometryError, InputError
from selfcal.geometry import align
from selfcal.scenarios.units import ROOMS, make_units, true_offset_vector
from selfcal.toa.init import rank3
from selfcal.toa.init.offsets_init import complete_core, initialize_offsets
from selfcal.toa.init.rank3 import estimate_offsets, fast_offsets, rank3_lm
from selfcal.toa.init.rank3_joint import _rank1_factors, _rank3_lm_joint, _tail
from selfcal.toa.init.rank3_model import (
    THESIS_ACCEPT,
    apply_A,
    apply_Wt,
    check_rank_identifiable,
    gamma_term,
    offset_matrix,
    thesis_lambda,
    thesis_T,
    thesis_W,
)
from selfcal.toa.init.rank3_thesis import rank3_iteration

C = 343.0
US = 1e-6 * C  # one microsecond, in metres


def _setup(n: int, room: str, seed: int, **kw: object) -> tuple[np.ndarray, np.ndarray, object]:
    sc = make_units(n, room=room, rng=seed, **kw)  # type: ignore[arg-type]
    return sc.ranges, true_offset_vector(sc.delays, sc.onsets) * C, sc


# ----------------------------------------------------------------------------- the model (3.2-3.6)


def test_W_and_A_match_the_expanded_model(rng: np.random.Generator) -> None:
    R, p, _ = _setup(10, "small", 3, equal_delays=False)
    I, J = R.shape
    W = thesis_W(R)
    # independent: the linear part of (3.4) written out entry by entry
    delta, tau = p[:I], np.r_[0.0, p[I:]]
    A_ref = np.array([[2 * delta[0] * (R[0, j] - R[0, 0]) - 2 * delta[i] * (R[i, j] - R[i, 0])
                       - 2 * tau[j] * (R[i, j] - R[0, j]) for j in range(1, J)] for i in range(1, I)])
    np.testing.assert_allclose((W @ p).reshape(I - 1, J - 1, order="F"), A_ref, atol=1e-9)
    np.testing.assert_allclose(apply_A(R, p), A_ref, atol=1e-9)
    E = rng.normal(size=(I - 1, J - 1))
    np.testing.assert_allclose(apply_Wt(R, E), W.T @ E.ravel(order="F"), atol=1e-9)


def test_corrected_matrix_is_minus_twice_the_centred_gram_at_the_true_offsets() -> None:
    # distinct delays: T + A(p) + Gamma(p) = -2 (r_i - r_1)^T (s_j - s_1) exactly (3.6)
    R, p, sc = _setup(12, "large", 1, equal_delays=False)
    I, J = R.shape
    r = sc.microphones - sc.microphones[0]
    s = sc.speakers - sc.speakers[0]
    gram = -2 * r[1:] @ s[1:].T
    exact = offset_matrix(R, p, model="exact")
    np.testing.assert_allclose(exact, gram, atol=1e-8)
    np.testing.assert_allclose(thesis_T(R) + apply_A(R, p) + gamma_term(p, I, J), gram, atol=1e-8)
    # the thesis's Gamma = 0 model is exact only when the delays are equal
    assert np.linalg.norm(offset_matrix(R, p, model="linear") - gram) > 1.0
    R2, p2, sc2 = _setup(12, "large", 1, equal_delays=True)
    r2 = sc2.microphones - sc2.microphones[0]
    s2 = sc2.speakers - sc2.speakers[0]
    np.testing.assert_allclose(offset_matrix(R2, p2, model="linear"), -2 * r2[1:] @ s2[1:].T, atol=1e-8)


def test_lm_gradient_matches_finite_differences(rng: np.random.Generator) -> None:
    # J^T r of the variable projection must be the exact gradient of (*)/2
    R, p, _ = _setup(10, "small", 2, equal_delays=False)
    x = p + rng.normal(0.0, 0.5, p.size)

    def half_cost(v: np.ndarray) -> float:
        sv = np.linalg.svd(offset_matrix(R, v), compute_uv=False)
        return 0.5 * float(np.sum(sv[3:] ** 2))

    M = offset_matrix(R, x)
    _, Ud, Vd, resid = _tail(M, 3)
    Uf, Vf = _rank1_factors(R, x, "exact", (np.array([], int), np.array([], int)))
    g = np.einsum("ik,ik->k", Uf, resid @ Vf)
    h = 1e-5
    fd = np.array([(half_cost(x + h * e) - half_cost(x - h * e)) / (2 * h) for e in np.eye(x.size)])
    np.testing.assert_allclose(g, fd, rtol=1e-4, atol=1e-6 * np.abs(fd).max())


# ----------------------------------------------------------------------------- identifiability


@pytest.mark.parametrize(("units", "dim"), [(7, 3), (5, 3), (6, 2), (3, 2)])
def test_too_few_units_raise_by_name(units: int, dim: int) -> None:
    R = np.random.default_rng(0).uniform(1, 10, (units, units))
    for call in (estimate_offsets, rank3_iteration, rank3_lm):
        with pytest.raises(DegenerateGeometryError) as exc:
            call(R, dim=dim)
        assert exc.value.kind == "too-few-units"
    with pytest.raises(DegenerateGeometryError, match="too-few-units"):
        initialize_offsets(R, dim)


def test_identifiability_condition_for_unequal_sides() -> None:
    # (I-1-d)(J-1-d) >= I+J-1
    check_rank_identifiable(8, 8, 3)
    check_rank_identifiable(7, 7, 2)
    check_rank_identifiable(6, 19, 3)  # 2 * 15 = 30 >= 24
    with pytest.raises(DegenerateGeometryError):
        check_rank_identifiable(6, 12, 3)  # 2 * 8 = 16 < 17
    with pytest.raises(DegenerateGeometryError):
        check_rank_identifiable(5, 100, 3)  # a side below d + 2


def test_bad_input_is_refused() -> None:
    R, _, _ = _setup(12, "small", 0)
    with pytest.raises(InputError, match="method"):
        estimate_offsets(R, method="magic")
    with pytest.raises(InputError, match="p0"):
        rank3_iteration(R, p0=np.zeros(3))
    with pytest.raises(InputError):
        rank3_iteration(R, lam=-1.0)
    with pytest.raises(InputError, match="linear"):
        estimate_offsets(R, method="faithful", model="exact")


# ----------------------------------------------------------------------------- recovery, noise-free


@pytest.mark.parametrize("room", sorted(ROOMS))
@pytest.mark.parametrize("units", [12, 20, 32])
def test_fast_solver_recovers_the_offsets_of_thesis_setups(room: str, units: int) -> None:
    # every seed tried: the returned (accepted) estimate is within 1 us of the truth
    for seed in range(6):
        R, p, _ = _setup(units, room, seed)
        res = estimate_offsets(R, rng=seed)
        assert res.accepted, (seed, res.frobenius)
        assert np.max(np.abs(res.p - p)) < US, (seed, res.restarts)
        assert res.source_offsets[0] == 0.0
        assert res.iterations < 100  # tens, not thousands


def test_fast_solver_recovers_distinct_internal_delays() -> None:
    # beyond the thesis: one delay per microphone (Gamma != 0) with the exact model
    for seed in range(4):
        R, p, _ = _setup(16, "small", seed, equal_delays=False)
        res = estimate_offsets(R, rng=seed)
        assert np.max(np.abs(res.p - p)) < 1e-3 * US


def test_linear_model_is_biased_when_delays_differ() -> None:
    # the thesis's Gamma = 0 model cannot fit distinct delays: the rank-3 fit stays far from 0
    R, p, _ = _setup(16, "small", 0, equal_delays=False)
    lin = rank3_lm(R, model="linear", p0=p)
    assert lin.frobenius > 1e3 * rank3_lm(R, model="exact", p0=p).frobenius


def test_two_dimensional_rank_two_variant() -> None:
    for seed in range(3):
        R, p, _ = _setup(12, (20.0, 15.0), seed, equal_delays=False)
        res = estimate_offsets(R, dim=2, rng=seed)
        assert np.max(np.abs(res.p - p)) < US


def test_faithful_iteration_recovers_p_and_converges_slowly() -> None:
    R, p, _ = _setup(12, "large", 0)
    res = rank3_iteration(R, rng=0)
    assert res.converged and res.method == "faithful"
    assert res.frobenius < THESIS_ACCEPT
    assert np.max(np.abs(res.p - p)) < US  # thesis: errors below 1 us
    assert res.iterations > 1000  # the linear convergence the issue wants to beat
    # F (3.17) decreases overall along the run
    assert res.history[-1] < 1e-3 * res.history[0]


def test_acceptance_test_restarts_the_fast_solver_from_a_new_start() -> None:
    # seed 17 of this setup: the start from p = 0 and two random starts end in local minima
    R, p, _ = _setup(12, "small", 17)
    first = fast_offsets(R, p0=np.zeros(23))
    assert first.frobenius > THESIS_ACCEPT
    res = estimate_offsets(R, rng=17)
    assert res.accepted and res.restarts >= 1
    assert res.total_iterations > res.iterations
    assert np.max(np.abs(res.p - p)) < US


@pytest.mark.slow
def test_acceptance_test_restarts_the_faithful_iteration() -> None:
    # the thesis iteration on 12 units in the 12 x 12 x 2 m room: two aborted runs, then accepted
    R, p, _ = _setup(12, "small", 0)
    res = estimate_offsets(R, method="faithful", rng=np.random.default_rng(0), max_restarts=4)
    assert res.accepted and res.restarts >= 1
    assert np.max(np.abs(res.p - p)) < US


def test_early_abort_stops_a_faithful_run_heading_for_a_local_minimum() -> None:
    R, _, _ = _setup(12, "small", 2)
    run = rank3_iteration(R, rng=np.random.default_rng(2), abort_above=THESIS_ACCEPT)
    assert run.extra["aborted"] and not run.converged
    assert run.frobenius > THESIS_ACCEPT


def test_without_acceptance_the_best_run_is_returned_with_a_warning() -> None:
    R, _, _ = _setup(12, "small", 0, noise_std=50e-6)
    with pytest.warns(ConvergenceWarning):
        res = estimate_offsets(R, accept=1e-12, max_restarts=1, rng=0)
    assert res.accepted is False


def test_regularised_variant_switches_lambda_off_and_reaches_the_same_p() -> None:
    R, p, _ = _setup(12, "large", 0)
    plain = rank3_iteration(R, rng=0)
    reg = rank3_iteration(R, rng=0, lam=thesis_lambda(1e-3, 12, 12))
    assert reg.lam > 0 and reg.extra["lam_switch_iteration"] is not None
    assert np.max(np.abs(reg.p - p)) < US
    assert np.max(np.abs(reg.p - plain.p)) < US


def test_faithful_and_fast_agree_on_noisy_data() -> None:
    # same objective (*), same basin: the fixed points coincide, far below the noise error
    R, p, _ = _setup(14, "large", 0, noise_std=10e-6)
    p0 = p + np.random.default_rng(0).normal(0.0, 0.3, p.size)
    faithful = rank3_iteration(R, p0=p0, tol=1e-13)
    fast = rank3_lm(R, p0=p0, model="linear", centring="reference")
    assert fast.iterations < 50
    assert np.max(np.abs(faithful.p - fast.p)) < 0.05 * US
    assert np.max(np.abs(fast.p - p)) > 1.0 * US  # the noise effect both share
    assert fast.frobenius <= faithful.frobenius * (1 + 1e-9)


# ----------------------------------------------------------------------------- missing entries, initialiser


def test_missing_entries_are_completed_by_the_fast_solver() -> None:
    # (in the flat 12 x 12 x 2 m room an entry can be only weakly fixed by the rank: large room)
    R, p, _ = _setup(20, "large", 5, equal_delays=False)
    full = R.copy()
    R = R.copy()
    R[np.random.default_rng(0).random(R.shape) < 0.1] = np.nan
    R[0, 3] = R[4, 0] = np.nan  # also in the reference row and column
    res = estimate_offsets(R, rng=0)
    assert np.max(np.abs(res.p - p)) < US
    np.testing.assert_allclose(res.extra["completed"], full, atol=1e-6)
    with pytest.raises(InputError, match="nls"):
        estimate_offsets(R, method="faithful")


def test_initializer_gives_positions_and_offsets_in_the_solve_toa_convention() -> None:
    for seed in range(3):
        R, p, sc = _setup(14, "small", seed, equal_delays=False)
        r, s, d, tau = initialize_offsets(R, 3, rng=seed)
        assert r.shape == (14, 3) and s.shape == (14, 3) and tau[0] == 0.0
        np.testing.assert_allclose(np.r_[d, tau[1:]], p, atol=1e-3 * US)
        truth = np.vstack([sc.microphones, sc.speakers])
        est = np.vstack([r, s])
        np.testing.assert_allclose(align(est, truth).apply(est), truth, atol=1e-6)


def test_initializer_with_missing_entries_and_noise() -> None:
    R, p, sc = _setup(20, "small", 2, noise_std=10e-6, equal_delays=False)
    R = R.copy()
    R[np.random.default_rng(1).random(R.shape) < 0.05] = np.nan
    r, s, d, tau = initialize_offsets(R, 3, rng=0)
    truth = np.vstack([sc.microphones, sc.speakers])
    est = np.vstack([r, s])
    # a starting point for NLS: decimetre level at 10 us (3.4 mm) timing noise
    assert np.sqrt(np.mean((align(est, truth).apply(est) - truth) ** 2)) < 0.3


def test_nls_path_handles_missing_entries_and_distinct_delays() -> None:
    from selfcal import toa  # a broken import of selfcal must fail here, never skip
    sc = make_units(16, room="small", rng=3, equal_delays=False)
    times = sc.times.copy()
    times[np.random.default_rng(2).random(times.shape) < 0.1] = np.nan
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ConvergenceWarning)
        res = toa.solve_toa(times, dim=3, offsets="both", speed=C, rng=0)
    np.testing.assert_allclose(res.receiver_offsets, sc.delays + sc.onsets[0], atol=1e-6)
    np.testing.assert_allclose(res.source_offsets, sc.onsets - sc.onsets[0], atol=1e-6)


@pytest.mark.slow
@pytest.mark.parametrize("room", sorted(ROOMS))
def test_fast_solver_on_the_full_thesis_protocol(room: str) -> None:
    # 004 Fig. 4.1-4.3: 12-32 units, 20 tests each; with restarts every test is within 1 us
    for units in range(12, 33, 4):
        for seed in range(20):
            R, p, _ = _setup(units, room, 1000 + seed)
            res = estimate_offsets(R, rng=seed)
            assert res.accepted and np.max(np.abs(res.p - p)) < US, (units, seed)


# ----------------------------------------------------------------------------- scalable solver vs the reference


@pytest.mark.parametrize("seed", range(10))
def test_scalable_lm_reaches_the_minimum_of_the_joint_reference(seed: int, monkeypatch: pytest.MonkeyPatch) -> None:
    """rank3_lm (block Hessian, subspace iteration, CG for the missing times) == the old joint LM.

    Same data, same start near the truth (inside the basin): both must stop at the same
    stationary point of (*). Timing noise 10 us and 0 / 5 / 10 % missing entries; the
    agreement asked for (1e-6 relative in F, 1e-3 us in p) is far below the noise effect
    on p (~us), so a different basin or an early stop would fail it.
    """
    rng = np.random.default_rng(seed)
    R, p, _ = _setup(14 + seed % 3 * 4, ("small", "large")[seed % 2], 50 + seed, noise_std=10e-6,
                     equal_delays=False)
    R = R.copy()
    frac = (0.0, 0.05, 0.10)[seed % 3]
    R[rng.random(R.shape) < frac] = np.nan
    p0 = p + rng.normal(0.0, 2 * US, p.size)
    monkeypatch.setattr(rank3, "_DENSE_JOINT_MAX", 0)  # the scalable path even at this size
    new = rank3_lm(R, p0=p0)
    ref = _rank3_lm_joint(R, p0=p0)
    # never a worse stationary point than the reference (with missing entries the two take
    # different steps - CG vs a dense solve - and may stop at different points of a flat valley)
    # with missing entries the steps differ (CG vs dense), so the two may stop at different
    # points of a flat valley as when the cap stops them: 0.1 % of the objective (measured with
    # numpy 2.4.6 / scipy 1.17.1, seed 1, 5 % missing: 2.4e-4 after 86 vs 99 iterations, the
    # optimised times 3.6 us apart, below the noise effect on them); complete data: 1e-6
    flat = max(new.iterations, ref.iterations) >= 100 or frac > 0.0
    assert new.extra["objective"] <= ref.extra["objective"] * (1 + (1e-3 if flat else 1e-6))
    if frac == 0.0:  # complete data: the same Gauss-Newton matrix, the same steps (up to the
        # rounding of the subspace iteration vs a full eigendecomposition)
        assert new.frobenius == pytest.approx(ref.frobenius, rel=1e-6)
        assert np.max(np.abs(new.p - ref.p)) < 1e-2 * US
    elif ref.converged and np.max(np.abs(ref.p - p)) < 1e3 * US:  # the basin of the truth
        assert new.frobenius == pytest.approx(ref.frobenius, rel=1e-6)
        np.testing.assert_allclose(new.extra["completed"], ref.extra["completed"], atol=1e-2 * US)


def test_complete_core_equals_the_plain_greedy() -> None:
    """The incremental greedy == dropping rows / columns from the matrix itself."""

    def plain(missing: np.ndarray, dim: int) -> tuple[np.ndarray, np.ndarray] | None:
        rows, cols, m = np.arange(missing.shape[0]), np.arange(missing.shape[1]), missing.copy()
        while m.any():
            fr, fc = m.mean(axis=1), m.mean(axis=0)
            if fr.max() >= fc.max():
                k = int(np.argmax(fr))
                m, rows = np.delete(m, k, axis=0), np.delete(rows, k)
            else:
                k = int(np.argmax(fc))
                m, cols = np.delete(m, k, axis=1), np.delete(cols, k)
        I, J = rows.size, cols.size
        return None if I < dim + 2 or J < dim + 2 or (I - 1 - dim) * (J - 1 - dim) < I + J - 1 else (rows, cols)

    for seed in range(20):
        rng = np.random.default_rng(seed)
        miss = rng.random((rng.integers(8, 40), rng.integers(8, 40))) < rng.uniform(0.0, 0.1)
        a, b = complete_core(miss, 3), plain(miss, 3)
        assert (a is None) == (b is None)
        if a is not None and b is not None:
            np.testing.assert_array_equal(a[0], b[0])
            np.testing.assert_array_equal(a[1], b[1])


# ----------------------------------------------------------------------------- minimal networks (issue 12)


def _minimal_scene(seed: int, I: int = 12, J: int = 6) -> tuple[np.ndarray, ...]:
    """The 12 x 6 scene of benchmarks/bench_toa_minimal.py, noise-free, in metres."""
    g = np.random.default_rng(seed)
    r = g.uniform(0.0, 1.5, (I, 3))
    u = g.normal(size=(J, 3))
    u /= np.linalg.norm(u, axis=1)[:, None]
    s = 0.75 + u * 4.0 * g.uniform(0, 1, (J, 1)) ** (1 / 3)
    d, o = g.uniform(0, 0.01 * C, I), g.uniform(0, 0.1 * C, J)
    R = np.linalg.norm(r[:, None] - s[None], axis=-1) + d[:, None] + o[None]
    return r, s, d, o, R


def _rank_equation_jacobian(R: np.ndarray, p: np.ndarray, dim: int = 3) -> np.ndarray:
    """Finite-difference Jacobian of the rank-d equations U_perp^T M(p) V_perp at p (bases fixed at p)."""
    M0 = offset_matrix(R, p, model="exact", centring="reference")
    U, _, Vt = np.linalg.svd(M0)
    Up, Vp = U[:, dim:], Vt[dim:].T
    h = 1e-6 * (1.0 + np.abs(p).max())
    cols = [(Up.T @ (offset_matrix(R, p + h * e, model="exact", centring="reference")
                     - offset_matrix(R, p - h * e, model="exact", centring="reference")) @ Vp).ravel() / (2 * h)
            for e in np.eye(p.size)]
    return np.array(cols).T


@pytest.mark.parametrize("seed", range(5))
def test_at_12x6_the_rank3_offsets_form_exactly_a_one_parameter_family(seed: int) -> None:
    """Theory of the minimal network: 16 rank-3 equations for 17 offsets, no further degeneracy.

    At the noise-free truth the equations vanish (F = 0) and their Jacobian has rank 16 (a
    one-dimensional null space: the offsets are a curve, not a point); one source more
    (12 x 7: 24 equations for 18 offsets) makes the true offsets an isolated solution. The
    rank is judged at 1e-8 of the largest singular value, far above the finite-difference
    error and far below the smallest non-zero value measured (1.5e-4 to 6e-3 of the largest
    on these seeds). That weak conditioning is why the family is of no use with 20 us noise:
    projecting the noisy data's truth onto it moves the offsets by 5-27 m (bench_toa_minimal).
    """
    for J, null in ((6, 1), (7, 0)):
        r, s, d, o, R = _minimal_scene(seed, J=J)
        p = np.concatenate([d + o[0], o[1:] - o[0]])
        M = offset_matrix(R, p, model="exact", centring="reference")
        sv_M = np.linalg.svd(M, compute_uv=False)
        assert sv_M[3] <= 1e-9 * sv_M[0]  # rank 3 at the truth
        sv = np.linalg.svd(_rank_equation_jacobian(R, p), compute_uv=False)
        rank = int(np.sum(sv > 1e-8 * sv[0]))
        assert p.size - rank == null


def test_distance_lower_bounds_never_exceed_the_true_distances() -> None:
    """Offset-free double differences bound every pairwise distance from below (triangle inequality)."""
    from selfcal.toa.init.scaled_starts import distance_lower_bounds

    for seed in range(10):
        r, s, _, _, R = _minimal_scene(seed)
        R = R.copy()
        R[np.random.default_rng(seed).random(R.shape) < 0.1] = np.nan  # missing entries are skipped
        for pts, B in ((r, distance_lower_bounds(R)), (s, distance_lower_bounds(R.T))):
            true = np.linalg.norm(pts[:, None] - pts[None], axis=-1)
            assert np.all(B <= true + 1e-9)
            assert np.all(B[~np.eye(len(pts), dtype=bool)] > 0)  # and they are informative


def test_scaled_starts_apply_only_where_the_rank_method_cannot_identify_the_offsets() -> None:
    """The 'scaled' initialiser runs for both offsets where the rank-d method does not identify them
    (12 x 6: 16 < 17 equations) or only barely (12 x 7: 24 < 2 x 18, init.offsets_init._early_stop_ok),
    never on clearly identified sizes (12 x 10: 48 >= 2 x 21) or other models."""
    from selfcal.toa.search import INITIALISERS, SCALED_STARTS

    init = INITIALISERS["scaled"]
    for J, offsets, expect in ((6, "both", SCALED_STARTS), (7, "both", SCALED_STARTS), (10, "both", 0),
                               (6, "receivers", 0), (6, "none", 0)):
        _, _, _, _, R = _minimal_scene(0, J=J)
        got = init(R, 3, offsets, np.random.default_rng(0))
        assert len(got) == expect
        for r0, s0, d0, o0 in got:  # finite starts of the right shapes, offsets for both kinds
            assert r0.shape == (12, 3) and s0.shape == (J, 3) and d0 is not None and o0 is not None
            assert np.isfinite(r0).all() and np.isfinite(s0).all()


@pytest.mark.slow
def test_minimal_12x6_search_reaches_the_truth_started_minimum_or_lower() -> None:
    """12 x 6, both offsets, 20 us: the search (trf engine) finds the truth-started minimum or a lower one.

    Measured 15 of 18 draws with the scaled starts against 2 of 18 without them (same run). At a
    true rate of 0.75, 12 or more of 24 draws happen with probability 0.998 (binomial); at the
    rate without them (<= 0.3) with probability < 0.04. The issue's 95 % is not reached: on
    many draws the data admit minima far from the truth with a cost within a few sigma^2 of the
    truth-started one (7 redundant measurements; the CRLB is 0.4-1.1 m for receivers in a
    1.5 m cube), see benchmarks/bench_toa_minimal.py.
    """
    from selfcal.toa import refine_toa
    from selfcal.toa.search import search

    hits = 0
    for seed in range(24):
        g = np.random.default_rng(seed)  # the scene of benchmarks/bench_toa_minimal.py, 20 us noise
        r = g.uniform(0.0, 1.5, (12, 3))
        u = g.normal(size=(6, 3))
        u /= np.linalg.norm(u, axis=1)[:, None]
        s = 0.75 + u * 4.0 * g.uniform(0, 1, (6, 1)) ** (1 / 3)
        d, o = g.uniform(0, 0.01 * C, 12), g.uniform(0, 0.1 * C, 6)
        R = np.linalg.norm(r[:, None] - s[None], axis=-1) + d[:, None] + o[None] + g.normal(0, 20 * US, (12, 6))
        ref = refine_toa(R, r, s, offsets="both", receiver_offsets0=d, source_offsets0=o, covariance=False,
                         solver="trf")
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            out = search(R, 3, "both", rng=np.random.default_rng(seed), solver="trf")
        hits += bool(np.nansum(out.solution.residuals**2) <= np.nansum(ref.residuals**2) * (1 + 1e-6))
    assert hits >= 12


@pytest.mark.parametrize("seed", range(6))
def test_structured_step_gives_the_cholesky_steps_fit(seed: int, monkeypatch: pytest.MonkeyPatch) -> None:
    """The complete-data step of rank3_lm through the matrix's structure (rank3._Structure:
    diagonal minus low rank in the source offsets, Woodbury) is the Cholesky step to round-off:
    from the same start, on UWB-like 6 x 400 flights with noise and per-anchor biases, the same
    minimum (offsets within 1e-7 m, F within 1e-9 relative; the runs' own stopping tolerance is
    1e-12, round-off can move the last accepted step), and the structured solve is the one used."""
    g = np.random.default_rng(seed)
    A = g.uniform([0, 0, 0], [6, 5, 3], (6, 3))
    t = np.linspace(0, 1, 400)
    tag = np.c_[3 + 2 * np.sin(2 * np.pi * (1 + seed % 3) * t), 2.5 + 2 * np.cos(2 * np.pi * 1.7 * t), 1.5 + 0.7 * t]
    Y = np.linalg.norm(A[:, None] - tag[None], axis=2) + g.normal(-0.15, 0.1, 6)[:, None] + g.normal(0, 0.03, (6, 400))
    p0 = g.normal(0, 0.2, 6 + 400 - 1)
    used = []
    orig = rank3._ScalableStep._structured

    def counted(self, lam):
        dx = orig(self, lam)
        used.append(dx is not None)
        return dx

    monkeypatch.setattr(rank3._ScalableStep, "_structured", counted)
    fast = rank3_lm(Y, dim=3, p0=p0)
    assert used and np.mean(used) > 0.9
    monkeypatch.setattr(rank3._ScalableStep, "_structured", lambda self, lam: None)
    chol = rank3_lm(Y, dim=3, p0=p0)
    np.testing.assert_allclose(fast.p, chol.p, atol=1e-7)
    assert abs(fast.frobenius - chol.frobenius) <= 1e-9 * chol.frobenius


@pytest.mark.parametrize("seed", range(4))
def test_structured_matrix_is_the_formed_gauss_newton_matrix(seed: int, monkeypatch: pytest.MonkeyPatch) -> None:
    """The complete-data Gauss-Newton matrix that rank3_lm keeps as its structure (never formed:
    receiver blocks and ``diag(s) - Z Z^T``) is the matrix the dense joint step forms
    independently, ``(Pu^T Pu) o (Pv^T Pv)`` from the Jacobian's rank-one factors, at the same
    point of UWB-like 6 x 300 flights: its dense form to 1e-9 relative (the two paths' rank-d
    subspaces come from subspace iteration vs a full eigendecomposition, agreeing to ~1e-13),
    and its products, diagonal and Frobenius norm to round-off of its own dense form."""
    from selfcal.toa.init import rank3_joint

    g = np.random.default_rng(seed)
    A = g.uniform([0, 0, 0], [6, 5, 3], (6, 3))
    tag = g.uniform([0.5, 0.5, 0.3], [5.5, 4.5, 2.0], (300, 3))
    Y = np.linalg.norm(A[:, None] - tag[None], axis=2) + g.normal(-0.15, 0.1, 6)[:, None] + g.normal(0, 0.03, (6, 300))
    p0 = g.normal(0, 0.2, 6 + 300 - 1)
    seen: dict[str, object] = {}
    s_init, j_init = rank3._ScalableStep.__init__, rank3_joint._JointStep.__init__

    def s_spy(self, x, H, *a, **k):
        seen.setdefault("structure", H)
        s_init(self, x, H, *a, **k)

    def j_spy(self, *a, **k):
        j_init(self, *a, **k)
        seen.setdefault("formed", self.H)

    monkeypatch.setattr(rank3._ScalableStep, "__init__", s_spy)
    monkeypatch.setattr(rank3_joint._JointStep, "__init__", j_spy)
    monkeypatch.setattr(rank3, "_DENSE_JOINT_MAX", 0)
    rank3_lm(Y, dim=3, p0=p0, max_iter=1)
    rank3_joint._rank3_lm_joint(Y, dim=3, p0=p0, max_iter=1)
    st, H = seen["structure"], np.asarray(seen["formed"])
    assert isinstance(st, rank3._Structure)
    D = st.dense()
    scale = float(np.abs(H).max())
    np.testing.assert_allclose(D, H, atol=1e-9 * scale)
    x = g.standard_normal(D.shape[0])
    np.testing.assert_allclose(st @ x, D @ x, atol=1e-12 * scale * np.abs(x).sum())
    np.testing.assert_allclose(st.diagonal(), np.diag(D), atol=1e-12 * scale)
    assert abs(st.frobenius() - np.linalg.norm(D)) <= 1e-10 * np.linalg.norm(D)
