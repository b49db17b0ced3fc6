"""The observed-pairs path (toa/sparse.py): same minimum as the dense engine, blind to noise level."""

from __future__ import annotations

import numpy as np
import pytest

from selfcal.errors import DegenerateGeometryError, InputError
from selfcal.metrics import aligned_rmse
from selfcal.toa import refine_toa, toa_crlb, toa_model
from selfcal.toa.sparse import (
    initialize_toa_sparse,
    refine_toa_sparse,
    simulate_sparse_network,
    solve_toa_sparse,
)


@pytest.mark.parametrize("seed", range(4))
def test_sparse_path_equals_dense_path(seed):
    """Same start, same observed set: the pairs engine and the dense engine reach the same point.

    Both run the same Levenberg-Marquardt iterations (one engine, two storage patterns), so
    the positions agree to round-off of the CG solves, far below the noise (1 cm).
    """
    rng = np.random.default_rng(seed)
    I, J = 9 + seed, 14 - seed
    r, s = rng.uniform(0, 5, (I, 3)), rng.uniform(0, 5, (J, 3))
    Y = toa_model(r, s) + rng.normal(0, 0.01, (I, J))
    Y[rng.random((I, J)) < 0.25] = np.nan
    r0, s0 = r + rng.normal(0, 0.1, r.shape), s + rng.normal(0, 0.1, s.shape)
    dense = refine_toa(Y, r0, s0, covariance="none")
    i, j = np.nonzero(np.isfinite(Y))
    sp = refine_toa_sparse(i, j, Y[i, j], r0, s0)
    assert sp.converged and dense.converged
    np.testing.assert_allclose(sp.receivers, dense.receivers, atol=1e-9)
    np.testing.assert_allclose(sp.sources, dense.sources, atol=1e-9)
    np.testing.assert_allclose(sp.noise_estimate, dense.sigma, rtol=1e-9)
    np.testing.assert_allclose(sp.residuals, dense.residuals[i, j], atol=1e-9)


@pytest.mark.parametrize("seed", [*range(2), *(pytest.param(k, marks=pytest.mark.slow) for k in range(2, 8))])
def test_blind_sparse_reaches_the_crlb(seed):
    """Blind on a sparse network (ranges only between nearby nodes): efficient against the CRLB.

    100 x 100 nodes with 20 % of the pairs observed (about 20 ranges per node, fewer at the
    cube's faces: a few corner nodes may stay unlocated, at most 5 %). The ML
    estimate's aligned RMSE fluctuates around the CRLB with a relative spread of about
    1/sqrt(2 n) ~ 5 % over n = 200 nodes x 3 coordinates; 1.3 allows a few spreads plus the
    small-sample bias of ML at this redundancy. The noise estimate's relative std is
    1/sqrt(2 dof) ~ 1 %: 10 % is generous.
    """
    I = J = 100
    r, s, i, j, y = simulate_sparse_network(I, J, 0.2, noise=0.01, size=20.0, rng=seed)
    sol = solve_toa_sparse(i, j, y, I, J, rng=seed)
    mr, ms = np.isfinite(sol.receivers[:, 0]), np.isfinite(sol.sources[:, 0])
    assert sol.converged and sol.located >= 0.95
    assert mr.sum() + ms.sum() == I + J - sol.unlocated_receivers.size - sol.unlocated_sources.size
    assert abs(sol.noise_estimate / 0.01 - 1) < 0.1
    mask = np.zeros((I, J), bool)
    mask[i, j] = True
    crlb = toa_crlb(r[mr], s[ms], 0.01, mask=mask[np.ix_(mr, ms)])
    e = aligned_rmse(sol.receivers[mr], r[mr], sol.sources[ms], s[ms])
    assert e.rmse_receivers < 1.3 * crlb.rmse_receivers
    assert e.rmse_sources < 1.3 * crlb.rmse_sources


def test_initialiser_locates_the_nodes_near_the_truth():
    """The growth reaches (almost) every node, within a few noise levels of the truth (before the fit)."""
    r, s, i, j, y = simulate_sparse_network(100, 100, 0.2, noise=0.01, size=20.0, rng=5)
    r0, s0, located, seed, seed_noise = initialize_toa_sparse(i, j, y, 100, 100, rng=0)
    assert located >= 0.95 and min(seed) >= 5 and 0.5 < seed_noise / 0.01 < 2
    mr, ms = np.isfinite(r0[:, 0]), np.isfinite(s0[:, 0])
    assert mr.sum() + ms.sum() == round(located * 200)
    e = aligned_rmse(r0[mr], r[mr], s0[ms], s[ms])
    assert e.rmse_receivers < 0.05 and e.rmse_sources < 0.05  # 5 noise levels


def test_sparse_input_errors():
    r, s, i, j, y = simulate_sparse_network(30, 30, 0.5, size=10.0, rng=0)
    with pytest.raises(InputError):
        refine_toa_sparse(i, j[:-1], y, r, s)
    with pytest.raises(InputError):
        refine_toa_sparse(np.r_[i, i[0]], np.r_[j, j[0]], np.r_[y, y[0]], r, s)  # repeated pair
    with pytest.raises(InputError):
        refine_toa_sparse(i, j, np.where(np.arange(y.size) == 3, np.nan, y), r, s)
    with pytest.raises(InputError):
        refine_toa_sparse(i, j + 30, y, r, s)
    keep = i != 0
    with pytest.raises(DegenerateGeometryError):
        refine_toa_sparse(np.r_[i[keep], 0], np.r_[j[keep], 0], np.r_[y[keep], 1.0], r, s)
    with pytest.raises(InputError):
        simulate_sparse_network(5, 5, 0.0)


def test_mirror_recheck_moves_a_mirrored_node_back():
    """A node with d + 1 ranges to nearly coplanar partners, placed at its mirror, is moved back.

    Four sources within 5 cm of the plane z = 0 and a receiver 3 m above it: the reflection
    fits the four ranges to ~cm (one redundant range), so only the comparison of the two
    placements' residuals can tell. Noise-free ranges: the true side fits exactly.
    """
    from selfcal.toa.sparse import _mirror_recheck

    rng = np.random.default_rng(0)
    s = np.c_[rng.uniform(-4, 4, (4, 2)), rng.uniform(-0.05, 0.05, 4)]
    r_true = np.array([[0.5, -0.3, 3.0]])
    i, j = np.zeros(4, np.intp), np.arange(4)
    y = np.linalg.norm(r_true[i] - s[j], axis=1)
    mirrored = r_true * [1, 1, -1]
    assert np.abs(np.linalg.norm(mirrored[i] - s[j], axis=1) - y).max() < 0.4  # the mirror nearly fits
    r, s2, wr, ws, moved = _mirror_recheck(i, j, y, mirrored, s, 3)
    assert moved == 1 and list(wr) == [0] and ws.size == 4
    np.testing.assert_allclose(r, r_true, atol=1e-9)
    r, _, _, _, moved = _mirror_recheck(i, j, y, r_true.copy(), s, 3)  # right side: stays
    assert moved == 0
    np.testing.assert_allclose(r, r_true, atol=0)


def test_blind_sparse_lists_its_weakly_placed_nodes():
    """weakly_placed_* = the located nodes with at most d + 1 fitted ranges (an independent count)."""
    I = J = 100
    r, s, i, j, y = simulate_sparse_network(I, J, 0.12, noise=0.01, size=20.0, rng=0)
    sol = solve_toa_sparse(i, j, y, I, J, rng=0)
    used = np.isfinite(sol.residuals)
    cr, cs = np.bincount(i[used], minlength=I), np.bincount(j[used], minlength=J)
    mr, ms = np.isfinite(sol.receivers[:, 0]), np.isfinite(sol.sources[:, 0])
    np.testing.assert_array_equal(sol.weakly_placed_receivers, np.flatnonzero(mr & (cr <= 4)))
    np.testing.assert_array_equal(sol.weakly_placed_sources, np.flatnonzero(ms & (cs <= 4)))
    assert sol.weakly_placed_receivers.size + sol.weakly_placed_sources.size > 0  # this network has some
    assert sol.mirrors_taken >= 0 and abs(sol.noise_estimate / 0.01 - 1) < 0.2


@pytest.mark.parametrize("seed", range(3))
def test_sparse_covariance_equals_the_dense_blocks(seed):
    """CG columns of N^+ (sparse path) = the dense path's selected inversion, to 1e-9 relative.

    Same network, same observed pairs and unequal weights; both are the Moore-Penrose
    marginal blocks (the gauge projected out), so they agree up to the CG tolerance.
    """
    from selfcal.toa.engine.covariance import covariance_blocks
    from selfcal.toa.engine.sparse_covariance import sparse_covariance_blocks

    rng = np.random.default_rng(seed)
    d = 2 + seed % 2
    I, J = 12 + seed, 15 - seed
    r, s = rng.uniform(0, 5, (I, d)), rng.uniform(0, 5, (J, d))
    W = rng.uniform(0.5, 2.0, (I, J)) * 1e4
    W[rng.random((I, J)) < 0.3] = 0.0
    i, j = np.nonzero(W > 0)
    Dr, Ds = covariance_blocks(r, s, W)
    want = (rng.choice(I, 3, replace=False), rng.choice(J, 2, replace=False))
    Cr, Cs = sparse_covariance_blocks(i, j, r, s, weights=W[i, j], covariance=want, rtol=1e-13)
    scale = max(np.abs(Dr).max(), np.abs(Ds).max())
    np.testing.assert_allclose(Cr[want[0]], Dr[want[0]], rtol=0, atol=1e-9 * scale)
    np.testing.assert_allclose(Cs[want[1]], Ds[want[1]], rtol=0, atol=1e-9 * scale)
    assert np.isnan(np.delete(Cr, want[0], axis=0)).all() and np.isnan(np.delete(Cs, want[1], axis=0)).all()
    with pytest.raises(InputError):
        sparse_covariance_blocks(i, j, r, s, covariance="local")


def test_sparse_solvers_return_the_requested_blocks(rng):
    """refine_toa_sparse / solve_toa_sparse covariance= : the dense path's blocks in the result's frame.

    The refine on a complete-ish network equals refine_toa's receiver_cov / source_cov (same
    minimum, same sigma, same canonical frame) to 1e-6 relative (CG tolerance 1e-10 and the
    minimum's own round-off); the blind solve returns finite blocks only where asked, equal to
    the dense path's blocks at its fitted positions on the pairs it used.
    """
    I, J = 10, 12
    r, s = rng.uniform(0, 5, (I, 3)), rng.uniform(0, 5, (J, 3))
    Y = toa_model(r, s) + rng.normal(0, 0.01, (I, J))
    Y[rng.random((I, J)) < 0.2] = np.nan
    i, j = np.nonzero(np.isfinite(Y))
    dense = refine_toa(Y, r, s)
    sp = refine_toa_sparse(i, j, Y[i, j], r, s, covariance="all")
    scale = max(np.abs(dense.receiver_cov).max(), np.abs(dense.source_cov).max())
    np.testing.assert_allclose(sp.receiver_cov, dense.receiver_cov, rtol=0, atol=1e-6 * scale)
    np.testing.assert_allclose(sp.source_cov, dense.source_cov, rtol=0, atol=1e-6 * scale)
    assert refine_toa_sparse(i, j, Y[i, j], r, s).receiver_cov is None
    with pytest.raises(InputError):
        refine_toa_sparse(i, j, Y[i, j], r, s, covariance="local")

    r, s, i, j, y = simulate_sparse_network(60, 60, 0.4, size=20.0, rng=1)
    sol = solve_toa_sparse(i, j, y, 60, 60, rng=0, covariance=([0, 7], [3]))
    assert np.isfinite(sol.receiver_cov[[0, 7]]).all() and np.isfinite(sol.source_cov[3]).all()
    assert np.isnan(np.delete(sol.receiver_cov, [0, 7], axis=0)).all()
    assert np.isnan(np.delete(sol.source_cov, [3], axis=0)).all()
    # independent: the dense path's blocks at the blind fit's positions, on the pairs it used
    from selfcal.toa.engine.covariance import covariance_blocks

    lr, ls = np.isfinite(sol.receivers[:, 0]), np.isfinite(sol.sources[:, 0])
    assert lr[[0, 7]].all() and ls[3]
    used = np.isfinite(sol.residuals)
    W = np.zeros((60, 60))
    W[i[used], j[used]] = 1.0
    Dr, Ds = covariance_blocks(sol.receivers[lr], sol.sources[ls], W[np.ix_(lr, ls)])
    ri, si = np.cumsum(lr) - 1, np.cumsum(ls) - 1
    n2 = sol.noise_estimate**2
    np.testing.assert_allclose(sol.receiver_cov[[0, 7]], n2 * Dr[ri[[0, 7]]], rtol=0, atol=1e-6 * n2 * np.abs(Dr).max())
    np.testing.assert_allclose(sol.source_cov[3], n2 * Ds[si[3]], rtol=0, atol=1e-6 * n2 * np.abs(Ds).max())
