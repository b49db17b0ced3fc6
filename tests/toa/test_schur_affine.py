"""The Schur-reduced engine of the constrained fits (toa/engine/schur_affine.py).

Two kinds of checks:

- the engine's pieces against an explicit dense computation (the normal-equation blocks
  of a random sparse Jacobian with one eliminated node per row; a linear least-squares
  problem, whose minimiser ``numpy.linalg.lstsq`` gives in closed form);
- whole constrained fits of simulated moving-tag flights (6 anchors x 130 tag positions,
  a common range offset, known anchors, known heights, priors) against the independent
  SciPy trf path (``solver="trf"``) from the same start. Both minimise the same cost to a
  relative step of 1e-10, so their minimisers differ only by the solvers' stopping
  tolerances: positions and the offset must agree to 1e-3 of their standard deviations
  (far below the statistical precision the acceptance asks for), the cost must not be
  higher than trf's beyond round-off, and the covariances (computed by the same code at
  the two minimisers) must agree to 1e-3 of each node's trace.
"""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import scipy.sparse

from selfcal.toa.engine.nls import refine_toa
from selfcal.toa.engine.schur_affine import RowPattern, local_blocks, solve_affine_lm


def _random_problem(seed: int, nE: int = 7, mE: int = 3, ng: int = 4, per_node: int = 5):
    """A sparse Jacobian whose every row touches one E node (some slots padded) and globals."""
    rng = np.random.default_rng(seed)
    sizes = rng.integers(1, mE + 1, nE)
    sizes[0] = mE
    p_loc = int(sizes.sum())
    p = p_loc + ng
    perm = rng.permutation(p)  # local and global columns interleaved in x
    loc_cols = perm[:p_loc]
    glob = np.sort(perm[p_loc:])
    blocks = -np.ones((nE, mE), np.intp)
    k = 0
    for e, n in enumerate(sizes):
        blocks[e, :n] = loc_cols[k:k + n]
        k += n
    rows, cols = [], []
    r = 0
    for e in range(nE):
        for _ in range(per_node):
            own = blocks[e][blocks[e] >= 0]
            g = rng.choice(glob, rng.integers(1, ng + 1), replace=False)
            for c in np.concatenate([own, g]):
                rows.append(r)
                cols.append(c)
            r += 1
    for _ in range(3):  # rows with globals only
        for c in rng.choice(glob, 2, replace=False):
            rows.append(r)
            cols.append(c)
        r += 1
    return rng, np.array(rows), np.array(cols), r, p, blocks, glob


def test_local_blocks_partition():
    """Columns touching one E node only are local to it; the rest are global."""
    node = np.array([-1, -1, 0, 0, 1, 1, 2])  # theta entries: two K entries, then E nodes
    T = scipy.sparse.csc_matrix(np.array([
        [1, 0, 0, 0, 0, 0],
        [0, 1, 0, 0, 0, 0],
        [0, 0, 1, 0, 0, 0],
        [0, 0, 0, 1, 0, 1],
        [0, 0, 0, 0, 1, 1],
        [0, 0, 0, 0, 0, 1],
        [0, 0, 0, 0, 0, 1],
    ], float))
    blocks, glob = local_blocks(T, node)
    assert blocks.tolist() == [[2, 3], [4, -1], [-1, -1]]  # node 2 has no local column: all padding
    assert glob.tolist() == [0, 1, 5]  # column 5 spans nodes 0, 1, 2 (a common offset)


@pytest.mark.parametrize("seed", range(4))
def test_systems_equal_dense_normal_equations(seed):
    """D, C, R, g_E, g_G equal the blocks of the dense J^T W J and J^T W f."""
    rng, rows, cols, n_rows, p, blocks, glob = _random_problem(seed)
    pat = RowPattern(rows, cols, n_rows, n_rows - 2, blocks, glob)
    vals = rng.normal(size=rows.size)
    w = rng.uniform(0.2, 2.0, n_rows)
    f = rng.normal(size=n_rows)
    f[-2:] = 0.0  # curvature rows carry no residual
    D, C, R, gE, gG = pat.systems(vals, w, f)
    Jd = np.zeros((n_rows, p))
    Jd[rows, cols] = vals
    N = Jd.T @ (w[:, None] * Jd)
    g = Jd.T @ (w * f)
    np.testing.assert_allclose(R, N[np.ix_(glob, glob)], atol=1e-12)
    np.testing.assert_allclose(gG, g[glob], atol=1e-12)
    for e in range(blocks.shape[0]):
        b = blocks[e]
        v = b >= 0
        np.testing.assert_allclose(D[e][np.ix_(v, v)], N[np.ix_(b[v], b[v])], atol=1e-12)
        np.testing.assert_allclose(C[e][v], N[np.ix_(b[v], glob)], atol=1e-12)
        np.testing.assert_allclose(gE[e][v], g[b[v]], atol=1e-12)
        assert np.all(D[e][~v] == 0) and np.all(C[e][~v] == 0)
    dx = rng.normal(size=p)
    np.testing.assert_allclose(pat.matvec(vals, dx), Jd @ dx, atol=1e-12)


@pytest.mark.parametrize("seed", range(3))
def test_linear_least_squares_solved_exactly(seed):
    """On a linear problem f = J x - y the engine's minimiser is the lstsq solution."""
    rng, rows, cols, n_rows, p, blocks, glob = _random_problem(seed, per_node=6)
    vals = rng.normal(size=rows.size)
    Jd = np.zeros((n_rows, p))
    Jd[rows, cols] = vals
    y = rng.normal(size=n_rows)
    pat = RowPattern(rows, cols, n_rows, n_rows, blocks, glob)
    x, conv, _ = solve_affine_lm(np.zeros(p), lambda x: Jd @ x - y, lambda x, f, w: (vals, np.zeros(0)),
                                 pat, "linear", 1.0, 1e-12)
    ref = np.linalg.lstsq(Jd, y, rcond=None)[0]
    assert conv
    np.testing.assert_allclose(x, ref, atol=1e-8)


def _flight(seed: int, kind: str, n: int = 130, start: str = "truth"):
    from selfcal.experiments.lps import simulate_uwb_flight

    sim = simulate_uwb_flight(seed, n, layout="lps", bias_std=0.0, spike_rate=0.0, noise=0.03,
                              sparse_positions=0)
    A, T, Y = sim["anchors"], sim["tag"], sim["ranges"]
    rng = np.random.default_rng(seed)
    r0 = A + rng.normal(0, 0.05, A.shape)
    s0 = T + rng.normal(0, 0.05, T.shape)
    if start == "free":  # as the recipe's test: from the offsets-free fit (c = 0, scale shrunk)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            free = refine_toa(Y, r0, s0, covariance=False)
        r0, s0 = free.receivers, free.sources
    kw: dict = dict(offsets="receivers", common_offsets="receivers")
    if kind == "known":  # three anchors at known positions (--known)
        fr = np.zeros(6, bool)
        fr[:3] = True
        r0[:3] = A[:3]
        kw["fixed_receivers"] = fr
    elif kind == "heights":  # known anchor heights, per-anchor offsets
        fz = np.zeros((6, 3), bool)
        fz[:, 2] = True
        r0[:, 2] = A[:, 2]
        kw = dict(offsets="receivers", fixed_receivers=fz)
    elif kind == "prior":  # four anchors known to 2 cm, the noise estimated
        mu = np.full((6, 3), np.nan)
        mu[:4] = A[:4] + rng.normal(0, 0.02, (4, 3))
        kw["receiver_prior"] = (mu, np.full(6, 0.02))
    return Y, r0, s0, kw


def _compare(seed: int, kind: str, start: str = "truth"):
    Y, r0, s0, kw = _flight(seed, kind, start=start)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        a = refine_toa(Y, r0, s0, solver="auto", **kw)
        b = refine_toa(Y, r0, s0, solver="trf", **kw)
    assert a.solver == "schur-lm-constrained" and b.solver == "trf-constrained"
    assert a.converged
    assert a.cost <= b.cost * (1 + 1e-9)
    for est, ref, cov in ((a.receivers, b.receivers, b.receiver_cov), (a.sources, b.sources, b.source_cov)):
        std = np.sqrt(np.einsum("naa->n", cov))
        moved = np.linalg.norm(est - ref, axis=1)
        fixed = std == 0  # known coordinates: held exactly by both
        assert np.all(moved[fixed] == 0)
        assert np.all(moved[~fixed] <= 1e-3 * std[~fixed])
    if a.receiver_offset_std is not None:
        se = b.receiver_offset_std
        assert np.all(np.abs(a.receiver_offsets - b.receiver_offsets) <= 1e-3 * se)
    # the same covariance code at minimisers 1e-3 std apart: each node's block to 1e-3 of its trace
    tr = np.einsum("naa->n", b.source_cov)[:, None, None]
    assert np.all(np.abs(a.source_cov - b.source_cov) <= 1e-3 * tr)


@pytest.mark.parametrize("kind", ["common", "known", "heights", "prior"])
def test_constrained_flight_matches_trf(kind):
    """Reduced default: one seed per constraint kind (see the module docstring)."""
    _compare(0, kind)


def test_common_offset_from_the_offsets_free_fit_matches_trf():
    """The recipe's case: the common-offset refit started from the offsets-free minimum (the
    offset moves from 0 to ~-0.17 m and the geometry rescales). A Newton step from there can
    land in another basin (measured on data5 before the Gauss-Newton-first rule: cost 8.4951
    against trf's 8.4671, c 0.4 se away); the engine must reach trf's minimum or a lower one."""
    _compare(1, "common", start="free")


@pytest.mark.slow
@pytest.mark.parametrize("kind", ["common", "known", "heights", "prior", "free-start"])
@pytest.mark.parametrize("seed", range(1, 13))
def test_constrained_flight_matches_trf_many_seeds(kind, seed):
    if kind == "free-start":
        _compare(seed + 100, "common", start="free")
    else:
        _compare(seed, kind)


def test_huber_flight_reaches_a_minimum():
    """Robust loss with 2 % gross errors at a given scale: "auto" keeps SciPy trf for robust
    losses (see constrained._engine_partition); the forced engine ends at a stationary point
    of the same cost: trf started from it lowers the cost by less than 1e-9 relative."""
    Y, r0, s0, kw = _flight(0, "common", n=90)
    rng = np.random.default_rng(5)
    Y = Y.copy()
    Y[rng.random(Y.shape) < 0.02] += 0.5
    hub = dict(loss="huber", f_scale=0.04, **kw)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        assert refine_toa(Y, r0, s0, covariance=False, **hub).solver == "trf-constrained"
        a = refine_toa(Y, r0, s0, solver="schur", covariance=False, **hub)
        b = refine_toa(Y, a.receivers, a.sources, receiver_offsets0=a.receiver_offsets, solver="trf",
                       covariance=False, **hub)
    assert a.solver == "schur-lm-constrained" and a.converged
    assert b.cost >= a.cost * (1 - 1e-9)
