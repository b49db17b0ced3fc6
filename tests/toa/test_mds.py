"""003 initialisers (selfcal.toa.init.mds): Algorithm 1, eq. 11, Algorithm 2, the rank method."""

from __future__ import annotations

import numpy as np
import pytest

from selfcal.errors import DegenerateGeometryError, InputError
from selfcal.geometry import pairwise_distances
from selfcal.metrics import aligned_rmse
from selfcal.scenarios.toa import paper003_network, paper003_source_angles, random_room
from selfcal.toa.init import mds


def _exact(I: int, J: int, dim: int, rng: np.random.Generator) -> tuple[np.ndarray, ...]:
    R = rng.uniform(-5, 5, (I, dim))
    S = rng.uniform(-7, 7, (J, dim))
    return R, S, pairwise_distances(R, S)


@pytest.mark.parametrize("dim", [2, 3])
def test_classical_mds_recovers_points_up_to_isometry(rng, dim):
    P = rng.normal(size=(12, dim)) * 3
    X = mds.classical_mds(pairwise_distances(P, P), dim)
    assert X.shape == (12, dim)
    assert np.allclose(pairwise_distances(X, X), pairwise_distances(P, P), atol=1e-9)


def test_classical_mds_refuses_nan_and_non_square():
    D = np.ones((4, 4)) - np.eye(4)
    D[0, 1] = np.nan
    with pytest.raises(InputError):
        mds.classical_mds(D, 2)
    with pytest.raises(InputError):
        mds.classical_mds(np.ones((3, 4)), 2)


def test_eq11_is_a_lower_bound_and_exact_for_aligned_sources(rng):
    R, S, Y = _exact(6, 40, 2, rng)
    D_hat = mds.estimate_receiver_distances(Y)
    D = pairwise_distances(R, R)
    assert np.all(D_hat <= D + 1e-12)  # eq. 10: reverse triangle inequality
    # a source on the extension of the line through receivers 0 and 1 makes eq. 11 exact
    s = R[1] + 3.0 * (R[1] - R[0])
    Y2 = np.column_stack([Y, pairwise_distances(R, s[None])])
    assert mds.estimate_receiver_distances(Y2)[0, 1] == pytest.approx(D[0, 1], abs=1e-12)


def test_eq11_blocks_and_missing_pairs(rng):
    _, _, Y = _exact(9, 7, 3, rng)
    full = mds.estimate_receiver_distances(Y)
    assert np.allclose(mds.estimate_receiver_distances(Y, block_elements=10), full)
    Y[0, :] = np.nan
    Y[0, 0] = 5.0
    Y[1, 0] = np.nan
    D = mds.estimate_receiver_distances(Y)
    assert np.isnan(D[0, 1]) and np.isfinite(mds.complete_distances(D)).all()


def test_disconnected_receivers_raise():
    D = np.full((4, 4), np.nan)
    np.fill_diagonal(D, 0)
    D[0, 1] = D[1, 0] = 1.0
    D[2, 3] = D[3, 2] = 1.0
    with pytest.raises(DegenerateGeometryError, match="disconnected"):
        mds.complete_distances(D)


def test_paper_source_angles_eq12():
    phi = paper003_source_angles(4)
    assert np.allclose(phi / np.pi, [0.0, 1.25, 0.5, 1.75])


def test_alg2_exact_when_every_pair_is_aligned():
    # receivers on a line with sources on its extension: eq. 11 is exact, so Alg. 2 is too
    R = np.column_stack([np.linspace(-3, 3, 5), np.zeros(5)])
    R[2, 1] = 1.0
    S = np.array([[20.0, 0.0], [-20.0, 0.0], [0.0, 15.0], [1, -12], [9, 9], [-8, 7]])
    ang = np.linspace(0, np.pi, 60, endpoint=False)
    S = np.vstack([S, 40 * np.column_stack([np.cos(ang), np.sin(ang)])])
    r, s = mds.mds_alg2(pairwise_distances(R, S), 2)
    err = aligned_rmse(r, R, s, S)
    assert err.rmse_receivers < 0.05 and err.rmse_sources < 0.1


@pytest.mark.parametrize("dim,I,J", [(2, 8, 10), (3, 8, 12), (3, 6, 20), (3, 25, 6)])
def test_rank_init_is_exact_on_noise_free_data(rng, dim, I, J):
    R, S, Y = _exact(I, J, dim, rng)
    r, s = mds.rank_init(Y, dim, rng=rng)
    err = aligned_rmse(r, R, s, S)
    assert err.rmse_receivers < 1e-8 and err.rmse_sources < 1e-8


def test_rank_init_completes_missing_entries(rng):
    sc = random_room(20, 40, dim=3, sigma=0.0, missing_fraction=0.2, rng=rng)
    r, s = mds.rank_init(sc.ranges, 3, rng=rng)
    err = aligned_rmse(r, sc.receivers, s, sc.sources)
    assert err.rmse_receivers < 1e-5 and err.rmse_sources < 1e-5


def test_rank_init_needs_enough_points_for_the_upgrade(rng):
    _, _, Y = _exact(5, 5, 2, rng)
    with pytest.raises(DegenerateGeometryError, match="upgrade"):
        mds.rank_init(Y, 2)


def test_multilaterate_exact_and_vectorised(rng):
    P = rng.uniform(-5, 5, (7, 3))
    X = rng.uniform(-9, 9, (50, 3))
    Y = pairwise_distances(X, P)
    Y[0, :3] = np.nan  # four anchors left: still determined
    assert np.allclose(mds.multilaterate(P, Y), X, atol=1e-7)


@pytest.mark.parametrize("method", ["alg2", "mds-multilat", "rank", "auto"])
def test_paper_setup_initial_error_is_near_the_noise(method):
    # 003 Fig. 6/7: at sigma = 0.3 m the MDS initial error is a few tens of cm
    errs = []
    for seed in range(15):
        sc = paper003_network(rng=seed)
        r, s = mds.initialize_toa(sc.ranges, 2, method=method, rng=seed)
        errs.append(aligned_rmse(r, sc.receivers).rmse_receivers)
    assert 0.05 < np.median(errs) < 0.6


def test_auto_scales_and_is_exact_on_large_noise_free_problem(rng):
    sc = random_room(300, 400, dim=3, sigma=0.0, rng=rng)
    info = mds.initialize_toa_info(sc.ranges, 3, rng=rng)
    assert info.method == "rank"
    assert aligned_rmse(info.receivers, sc.receivers).rmse_receivers < 1e-8
    assert set(info.to_dict()) >= {"receivers", "sources", "method", "residual_rms"}


@pytest.mark.parametrize("dim", [2, 3])
def test_blind_start_reaches_micrometres_after_nls(rng, dim):
    from selfcal.toa import solve_toa

    sc = random_room(10, 15, dim=dim, sigma=0.0, rng=rng)
    r0, s0 = mds.initialize_toa(sc.ranges, dim, rng=rng)
    res = solve_toa(sc.ranges, dim=dim, init=(r0, s0))
    assert aligned_rmse(res.receivers, sc.receivers).rmse_receivers < 1e-6


def test_bad_input():
    with pytest.raises(InputError):
        mds.initialize_toa(np.array([[1.0, -2, 3], [1, 2, 3], [1, 2, 3]]), 2)
    with pytest.raises(InputError):
        mds.initialize_toa(np.ones((3, 3)), 2, method="nope")
    with pytest.raises(InputError):
        mds.initialize_toa(np.ones((2, 9)), 2)


def test_3d_paper_variant_blind_start_converges():
    from selfcal.toa import solve_toa

    errs = []
    for seed in range(6):
        sc = paper003_network(n_sources=20, dim=3, sigma=0.0, rng=seed)
        r0, s0 = mds.initialize_toa(sc.ranges, 3, rng=seed)
        res = solve_toa(sc.ranges, dim=3, init=(r0, s0), covariance=False)
        errs.append(aligned_rmse(res.receivers, sc.receivers).rmse_receivers)
    assert np.median(errs) < 1e-6


def test_an_absurd_entry_is_a_clear_error_not_a_linalg_crash():
    """One 1e300 entry used to escape as LinAlgError ("SVD did not converge")."""
    from selfcal.errors import SelfcalError
    from selfcal.toa.init.mds import initialize_toa

    g = np.random.default_rng(0)
    r, s = g.uniform(-5, 5, (8, 3)), g.uniform(-5, 5, (10, 3))
    Y = np.linalg.norm(r[:, None] - s[None], axis=-1)
    Y[2, 3] = 1e300
    try:
        initialize_toa(Y, 3, rng=0)  # a start (however bad) or one of our errors, never a LinAlgError
    except SelfcalError:
        pass
