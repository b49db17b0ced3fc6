"""The cheaper post-solve computations of issue 27 give the same numbers / decisions.

- leverages from the lifted normal matrix (Cholesky with the gauge basis) against the
  eigendecomposition of ``J^T J`` with the relative cut (the former computation);
- the additive model's leverages from its small normal matrix against the SVD of the dense
  design (the former computation);
- the time-order test's sequential stop: the same decision as all 999 random orders;
- the bipartite generalised inverse (:class:`~selfcal.toa.verdict.bipartite.BipartiteInverse`)
  against the dense lifted inverse: the same leverages (fitted and held-out entries) and the
  same Fisher blocks;
- the linearisation kept between the outlier rule, the trust test and the determinacy test
  (:func:`~selfcal.toa.verdict.leverage.normal_equations`): reused only on the same entries
  within the solver's step tolerance, and then equal to a fresh one;
- the permutation test's statistic of the data and its copies refined in lockstep
  (:func:`~selfcal.toa.verdict.trust.geometry_statistics`) against one ``refine_toa`` call per
  matrix (the former computation): the same statistic, so the same level and power.

Speed itself is measured in ``benchmarks/bench_postsolve.py``, never asserted here.
"""

from __future__ import annotations

import numpy as np
import pytest

from selfcal.errors import DegenerateGeometryError
from selfcal.robust import mad_std
from selfcal.toa import toa_model
from selfcal.toa.engine.nls import _pack, toa_jacobian
from selfcal.toa.recipes.recipes import TIME_ORDER_PERMUTATIONS, _total_variation, detect_time_order
from selfcal.toa.verdict.leverage import leverages
from selfcal.toa.verdict.trust import _additive_leverages


def _eigh_leverages(Y, r, s, d, o, offsets):
    J = toa_jacobian(_pack(r, s, d, o), Y, r.shape[1], offsets).tocsr()
    N = (J.T @ J).toarray()
    lam, V = np.linalg.eigh(N)
    keep = lam > lam[-1] * 1e-12
    P = (V[:, keep] / lam[keep]) @ V[:, keep].T
    return np.asarray(J.multiply(J @ P).sum(axis=1)).ravel()


@pytest.mark.parametrize("seed", range(4))
def test_leverages_equal_the_eigendecomposition(seed):
    """Random networks, every offsets mode, 2-D and 3-D, 0-30 % missing, 60 draws a seed: the
    lifted Cholesky leverages equal the cut eigendecomposition's to 1e-8 on generic networks,
    and sum to the rank (trace of the hat matrix). Near-degenerate draws (coplanar receivers,
    collinear sources) fall back to the eigendecomposition or agree to its own noise, 1e-5."""
    g = np.random.default_rng(seed)
    for k in range(60):
        dim = int(g.choice([2, 3]))
        I, J = (int(v) for v in g.integers(dim + 3, 16, 2))
        off = str(g.choice(["none", "receivers", "sources", "both"]))
        r, s = g.uniform(0, 10, (I, dim)), g.uniform(0, 10, (J, dim))
        degenerate = k % 5 == 0
        if degenerate:
            r[:, -1] = 0.0
        d = g.uniform(0, 3, I) if off in ("receivers", "both") else None
        o = g.uniform(0, 3, J) if off in ("sources", "both") else None
        Y = toa_model(r, s, d, o)
        Y[g.random(Y.shape) < g.uniform(0, 0.3)] = np.nan
        h = leverages(Y, r, s, d, o, off)[np.isfinite(Y)]
        h0 = _eigh_leverages(Y, r, s, d, o, off)
        assert np.max(np.abs(h - h0)) < (1e-5 if degenerate else 1e-8), (seed, k, off, dim)
        if not degenerate:  # the trace of the hat matrix is the rank of the Jacobian
            rank = np.linalg.matrix_rank(toa_jacobian(_pack(r, s, d, o), Y, dim, off).toarray())
            assert abs(h.sum() - rank) < 1e-6 * rank


def _svd_additive(obs, rows, cols):
    I, J = obs.shape
    ii, jj = np.nonzero(obs)
    H = np.full(obs.shape, np.nan)
    X = [np.ones((ii.size, 1))]
    if rows:
        X.append(np.eye(I)[ii][:, 1:])
    if cols:
        X.append(np.eye(J)[jj][:, 1:])
    U, sv, _ = np.linalg.svd(np.hstack(X), full_matrices=False)
    H[obs] = np.sum(U[:, : int(np.sum(sv > sv[0] * 1e-10))] ** 2, axis=1)
    return H


def test_additive_leverages_equal_the_svd():
    """400 random masks (some split in two blocks: a disconnected design, some complete: the
    balanced layout's closed form), every model."""
    g = np.random.default_rng(0)
    for k in range(400):
        I, J = (int(v) for v in g.integers(1, 30, 2))
        obs = g.random((I, J)) < g.uniform(0.05, 1)
        if k % 10 == 5:
            obs[:] = True
        if k % 10 == 0:
            obs[: I // 2, J // 2:] = False
            obs[I // 2:, : J // 2] = False
        if not obs.any():
            continue
        for rows in (False, True):
            for cols in (False, True):
                a, b = _additive_leverages(obs, rows, cols), _svd_additive(obs, rows, cols)
                assert np.nanmax(np.abs(a - b)) < 1e-10, (k, rows, cols)


def _full_time_order(Y, rng):
    """The test with all 999 orders (the former computation): its decision."""
    med = np.nanmedian(Y, axis=1, keepdims=True)
    sc = mad_std(Y, axis=1, keepdims=True)
    sc = np.where(np.isfinite(sc) & (sc > 0), sc, 1.0)
    Z = (Y - med) / sc
    gen = np.random.default_rng(rng)
    tv = _total_variation(Z, np.arange(Y.shape[1]))
    perm = np.array([_total_variation(Z, gen.permutation(Y.shape[1])) for _ in range(TIME_ORDER_PERMUTATIONS)])
    return bool((1 + np.sum(perm <= tv)) / (TIME_ORDER_PERMUTATIONS + 1) <= 1e-3)


def test_time_order_stop_keeps_the_decision():
    """Independent sources, a moving tag and borderline (weakly smooth) matrices, 30 draws: the
    sequential stop decides as the full test does, with a valid p-value in (0, 1]."""
    g = np.random.default_rng(0)
    for k in range(30):
        I, J = int(g.integers(3, 8)), int(g.integers(20, 80))
        anchors = g.uniform(0, 10, (I, 3))
        kind = k % 3
        if kind == 0:  # independent sources
            Y = toa_model(anchors, g.uniform(0, 10, (J, 3))) + g.normal(0, 0.05, (I, J))
        else:  # a walk, smooth (kind 1) or drowned in noise (kind 2, near the test's limit)
            tag = np.cumsum(g.normal(0, 0.3, (J, 3)), axis=0) + 5
            Y = toa_model(anchors, tag) + g.normal(0, 0.05 if kind == 1 else 1.5, (I, J))
        Y[g.random(Y.shape) < 0.1] = np.nan
        test = detect_time_order(Y, rng=k)
        assert test.detected == _full_time_order(Y, k), k
        assert 0 < test.p_value <= 1 and 1 <= test.permutations <= TIME_ORDER_PERMUTATIONS


def _one_at_a_time(Y, dim, offsets):
    """The former geometry statistic: best 003 start, then ``refine_toa`` (5 iterations)."""
    from selfcal.toa.engine.nls import refine_toa
    from selfcal.toa.init.mds import mds_alg2, mds_multilateration
    from selfcal.toa.verdict.trust import PERMUTATION_REFINE, _additive_fit

    has_r, has_s = offsets in ("receivers", "both"), offsets in ("sources", "both")
    obs = np.isfinite(Y)
    e0 = (Y - _additive_fit(Y, has_r, has_s))[obs]
    rss0 = e0 @ e0
    best, start = np.inf, None
    for init in (lambda Z: mds_multilateration(Z, dim, rng=0), lambda Z: mds_alg2(Z, dim)):
        try:
            r, s = init(Y - min(0.0, float(np.nanmin(Y))))
        except Exception:  # noqa: BLE001 (an initialiser that does not apply, as in the statistic)
            continue
        E = Y - toa_model(r, s)
        E = E - _additive_fit(E, has_r, has_s) if (has_r or has_s) else E
        if np.isfinite(E[obs]).all() and E[obs] @ E[obs] / rss0 < best:
            best, start = E[obs] @ E[obs] / rss0, (r, s)
    if start is not None:
        try:
            sol = refine_toa(Y, *start, offsets=offsets, max_nfev=PERMUTATION_REFINE, covariance=False)
        except DegenerateGeometryError:  # too few ranges: the start's statistic, as before
            return best
        if np.isfinite(sol.residuals[obs]).all():
            best = min(best, sol.residuals[obs] @ sol.residuals[obs] / rss0)
    return best


def test_lockstep_statistics_equal_one_refinement_at_a_time():
    """24 stacks (every offsets mode, 2-D and 3-D, 5-16 nodes a side, half complete (their starts
    stacked too), half 0-20 % missing, genuine networks and their permuted copies, as the test
    builds them): each matrix's statistic in
    the stack equals the one-at-a-time procedure's to 1e-6 relative (the batched driver's
    iterates are the dense / Schur engine's up to round-off, amplified at most by the few
    accepted-or-refused trials that round-off can flip)."""
    from selfcal.toa.verdict.trust import _additive_fit, geometry_statistics

    g = np.random.default_rng(7)
    for k in range(24):
        dim = int(g.choice([2, 3]))
        I, J = (int(v) for v in g.integers(dim + 3, 17, 2))
        off = ["none", "receivers", "sources", "both"][k % 4]
        has_r, has_s = off in ("receivers", "both"), off in ("sources", "both")
        r, s = g.uniform(0, 10, (I, dim)), g.uniform(0, 10, (J, dim))
        Y = toa_model(r, s, g.uniform(0, 3, I) if has_r else None, g.uniform(0, 3, J) if has_s else None)
        Y = Y + g.normal(0, g.choice([0.0, 0.01, 0.3]), Y.shape)
        if k % 2:  # complete stacks take the stacked starts (trust._complete_starts)
            Y[g.random(Y.shape) < g.uniform(0, 0.2)] = np.nan
        obs = np.isfinite(Y)
        F = _additive_fit(Y, has_r, has_s)
        stack = [Y]
        for _ in range(3):  # copies as permutation_test makes them
            Z = np.full(Y.shape, np.nan)
            Z[obs] = g.permutation((Y - F)[obs])
            stack.append(F + Z)
        T = geometry_statistics(np.stack(stack), dim, off)
        for t, Yk in zip(T, stack, strict=True):
            t0 = _one_at_a_time(Yk, dim, off)
            assert t == pytest.approx(t0, rel=1e-6, abs=1e-12), (k, off, dim)


def test_kept_linearisation_equals_a_fresh_one():
    """40 random networks (every offsets mode, 2-D and 3-D, up to 30 % missing): leverages and
    Fisher blocks at a geometry moved by less than the reuse tolerance (which reuse the kept
    linearisation) equal those computed afresh (leverages to 1e-7 relative, Fisher blocks to
    1e-7 of their largest entry: the move is 3e-11 of the parameters' norm, the rest is the
    round-off of two inversions); a move beyond it, a changed
    entry set or another offsets mode forms a new linearisation (never a stale one)."""
    from selfcal.toa.verdict import leverage
    from selfcal.toa.verdict.determinacy import fisher_blocks

    g = np.random.default_rng(3)
    for k in range(40):
        dim = int(g.choice([2, 3]))
        I, J = (int(v) for v in g.integers(dim + 4, 14, 2))
        off = ["none", "receivers", "sources", "both"][k % 4]
        has_r, has_s = off in ("receivers", "both"), off in ("sources", "both")
        r, s = g.uniform(0, 10, (I, dim)), g.uniform(0, 10, (J, dim))
        d = g.uniform(0, 3, I) if has_r else None
        o = g.uniform(0, 3, J) if has_s else None
        Y = toa_model(r, s, d, o)
        Y[g.random(Y.shape) < g.uniform(0, 0.3)] = np.nan
        leverage._LAST.clear()
        h0 = leverages(Y, r, s, d, o, off)
        kept = leverage._LAST[0]
        theta_norm = np.linalg.norm(kept.theta)
        step = 0.3 * leverage.REUSE_XTOL * theta_norm  # within the tolerance: reused
        r1 = r + step / np.sqrt(r.size + s.size) * g.choice([-1, 1], r.shape)
        s1 = s + step / np.sqrt(r.size + s.size) * g.choice([-1, 1], s.shape)
        h1 = leverages(Y, r1, s1, d, o, off)
        assert leverage._LAST[0] is kept, k
        B1 = fisher_blocks(Y, r1, s1, d, o, off, 0.01)
        leverage._LAST.clear()
        h1_fresh = leverages(Y, r1, s1, d, o, off)
        B1_fresh = fisher_blocks(Y, r1, s1, d, o, off, 0.01)
        ok = np.isfinite(h0)
        assert np.allclose(h1[ok], h1_fresh[ok], rtol=1e-7, atol=1e-10), k
        for a, b in zip(B1, B1_fresh, strict=True):
            fin = np.isfinite(b)
            assert np.allclose(a[fin], b[fin], rtol=1e-7, atol=1e-7 * np.abs(b[fin]).max()), k
        # beyond the tolerance, other entries, another model: a new linearisation
        far = leverages(Y, r + 1e-6, s, d, o, off)
        assert leverage._LAST[0] is not kept and leverage._LAST[0].same(np.isfinite(Y), off, leverage._LAST[0].theta)
        leverage._LAST.clear()
        assert np.allclose(far[ok], leverages(Y, r + 1e-6, s, d, o, off)[ok], rtol=1e-12, atol=1e-14)
        Y2 = Y.copy()
        Y2[np.unravel_index(np.flatnonzero(np.isfinite(Y))[0], Y.shape)] = np.nan
        before = leverage._LAST[0]
        leverages(Y2, r, s, d, o, off)
        assert leverage._LAST[0] is not before


@pytest.mark.parametrize("seed", range(3))
def test_bipartite_inverse_equals_the_dense_lifted_one(seed, monkeypatch):
    """60 random networks a seed (every offsets mode, 2-D and 3-D, sides 5-20 so that either
    side is eliminated, 0-30 % missing, some entries held out): the leverages of fitted and
    held-out entries and the determinacy test's Fisher blocks from the bipartite inverse equal
    those of the dense lifted inverse to 1e-7 (relative to the largest entry of a block: two
    different O(n^3) factorisations of the same matrix, condition up to ~1e4 here)."""
    from selfcal.toa.verdict import leverage
    from selfcal.toa.verdict.determinacy import fisher_blocks

    g = np.random.default_rng(100 + seed)
    used = 0
    for k in range(60):
        dim = int(g.choice([2, 3]))
        I, J = (int(v) for v in g.integers(dim + 3, 21, 2))
        off = ["none", "receivers", "sources", "both"][k % 4]
        has_r, has_s = off in ("receivers", "both"), off in ("sources", "both")
        r, s = g.uniform(0, 10, (I, dim)), g.uniform(0, 10, (J, dim))
        d = g.uniform(0, 3, I) if has_r else None
        o = g.uniform(0, 3, J) if has_s else None
        Y = toa_model(r, s, d, o)
        Y[g.random(Y.shape) < g.uniform(0, 0.3)] = np.nan
        held = np.isfinite(Y) & (g.random(Y.shape) < 0.05)
        Yf = np.where(held, np.nan, Y)
        leverage._LAST.clear()
        h_blk = leverages(Yf, r, s, d, o, off, held_out=held)
        blk = leverage._LAST[0].block()
        B_blk = fisher_blocks(Yf, r, s, d, o, off, 0.01)
        with monkeypatch.context() as m:
            m.setattr(leverage.BipartiteInverse, "build", classmethod(lambda cls, ne: None))
            leverage._LAST.clear()
            h_dense = leverages(Yf, r, s, d, o, off, held_out=held)
            B_dense = fisher_blocks(Yf, r, s, d, o, off, 0.01)
        leverage._LAST.clear()
        if blk is None:
            continue  # the dense path decided (a block too ill-conditioned): nothing to compare
        used += 1
        ok = np.isfinite(h_dense)
        assert np.array_equal(ok, np.isfinite(h_blk))
        assert np.allclose(h_blk[ok], h_dense[ok], rtol=1e-7, atol=1e-9), (seed, k, off, dim)
        if B_dense is None:
            assert B_blk is None
            continue
        for a, b in zip(B_blk, B_dense, strict=True):
            fin = np.isfinite(b)
            assert np.array_equal(fin, np.isfinite(a)), (seed, k)
            scale = np.abs(b[fin]).max() if fin.any() else 1.0
            assert np.allclose(a[fin], b[fin], rtol=1e-7, atol=1e-7 * scale), (seed, k, off, dim)
    assert used >= 40  # the bipartite path is the one taken on generic networks


@pytest.mark.parametrize("seed", range(2))
def test_complete_pattern_leverages_equal_the_gathered_ones(seed):
    """Complete matrices (either side eliminated: sources or receivers the larger set, every
    offsets mode, 2-D and 3-D, 20 draws a seed): the leverages on the (eliminated, kept) grid
    (:meth:`BipartiteInverse.pattern_hat`'s complete path) equal the per-entry gathered
    formula (:meth:`BipartiteInverse.hat`) to 1e-12 (the same four terms summed in another
    order) and the dense lifted inverse's to 1e-7 (as the bipartite test above)."""
    from selfcal.toa.verdict import leverage

    g = np.random.default_rng(300 + seed)
    swaps = []
    for k in range(20):
        dim = int(g.choice([2, 3]))
        I, J = (int(v) for v in g.integers(dim + 3, 25, 2))
        off = ["none", "receivers", "sources", "both"][k % 4]
        has_r, has_s = off in ("receivers", "both"), off in ("sources", "both")
        r, s = g.uniform(0, 10, (I, dim)), g.uniform(0, 10, (J, dim))
        d = g.uniform(0, 3, I) if has_r else None
        o = g.uniform(0, 3, J) if has_s else None
        Y = toa_model(r, s, d, o)
        leverage._LAST.clear()
        h = leverages(Y, r, s, d, o, off)
        blk = leverage._LAST[0].block()
        leverage._LAST.clear()
        if blk is None:
            continue
        swaps.append(blk.swap)
        ii, jj = np.nonzero(np.ones(Y.shape, bool))
        h_gather = blk.hat(ii, jj, blk.rows_r[ii, jj], blk.rows_s[ii, jj])
        assert np.allclose(h.ravel(), h_gather, rtol=1e-12, atol=1e-12), (seed, k, off, dim)
        assert np.allclose(h.ravel(), _eigh_leverages(Y, r, s, d, o, off), rtol=1e-7, atol=1e-9), (seed, k)
    assert len(swaps) >= 15 and any(swaps) and not all(swaps)  # the bipartite path, both sides eliminated


def test_stacked_starts_equal_the_initialisers():
    """30 complete stacks (2-D and 3-D, 4-39 nodes a side: both eigensolvers of the MDS, a
    network with offsets and noise 0-1 m, a permuted copy, a noisy absolute one): the stacked
    starts equal ``mds_multilateration`` and ``mds_alg2`` matrix by matrix to 1e-10 of the
    configuration's size (round-off of the same LAPACK calls in another order)."""
    from selfcal.toa.init.mds import mds_alg2, mds_multilateration
    from selfcal.toa.verdict.trust import _complete_starts

    g = np.random.default_rng(11)
    for k in range(30):
        dim = int(g.choice([2, 3]))
        I, J = (int(v) for v in g.integers(dim + 2, 40, 2))
        r, s = g.uniform(0, 10, (I, dim)), g.uniform(0, 10, (J, dim))
        Y = toa_model(r, s) + g.uniform(0, 3, (I, 1)) + g.normal(0, g.choice([0.0, 0.01, 1.0]), (I, J))
        st = np.stack([Y, g.permutation(Y.ravel()).reshape(I, J), np.abs(Y + g.normal(0, 2, Y.shape))])
        st = st - np.minimum(0.0, st.min(axis=(1, 2)))[:, None, None]
        got = _complete_starts(st, dim)
        assert got is not None, k
        for i in range(3):
            for name, start in (("mds-multilat", mds_multilateration(st[i], dim, rng=0)), ("alg2", mds_alg2(st[i], dim))):
                size = max(1.0, float(np.abs(start[0]).max()))
                assert np.abs(got[name][0][i] - start[0]).max() < 1e-10 * size, (k, i, name)
                assert np.abs(got[name][1][i] - start[1]).max() < 1e-10 * size, (k, i, name)


def test_robust_refit_skipped_only_where_it_cannot_flag(monkeypatch):
    """The outlier rule's robust (soft-L1) refit is not run where no fit it can reach flags
    anything (``fit._refit_cannot_flag``): 80 units (6,400 entries, above the high-breakdown
    start's size), both offsets, complete, over seeds: noise-free (the skip applies), noise-free
    with 1 % of the entries +2 m (gross errors in exact data: the refit must run) and 1 mm
    (it runs). The answer with the skip equals the answer with the refit forced, bit for bit
    (positions, covariances, outliers, verdict): the final refit starts from the same winner
    either way."""
    import warnings

    import selfcal.toa.fit as fit
    import selfcal.toa.verdict.leverage as lev
    from selfcal.scenarios.units import make_units
    from selfcal.toa import solve_toa

    real = fit._refit_cannot_flag
    said: list[bool] = []
    monkeypatch.setattr(fit, "_refit_cannot_flag", lambda *a, **k: said.append(real(*a, **k)) or said[-1])
    for seed in range(4):
        kind = ("exact", "gross", "noise", "exact")[seed]
        sc = make_units(80, room="large", noise_std=1e-3 / 343 if kind == "noise" else 0.0,
                        equal_delays=kind != "noise", rng=seed)
        Y = np.array(sc.ranges, float)
        if kind == "gross":
            Y[np.random.default_rng(seed).random(Y.shape) < 0.01] += 2.0
        out = []
        for skip in (True, False):
            if not skip:
                monkeypatch.setattr(fit, "_refit_cannot_flag", lambda *a, **k: False)
            lev._LAST.clear()
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                out.append(solve_toa(Y, dim=3, offsets="both", rng=seed))
        monkeypatch.setattr(fit, "_refit_cannot_flag", lambda *a, **k: said.append(real(*a, **k)) or said[-1])
        a, b = out
        assert said[-1] == (kind == "exact"), (seed, kind)
        assert (a.verdict, a.verdict_message) == (b.verdict, b.verdict_message)
        assert np.array_equal(a.outliers, b.outliers)
        for x, y in ((a.receivers, b.receivers), (a.sources, b.sources), (a.receiver_cov, b.receiver_cov),
                     (a.source_cov, b.source_cov)):
            assert np.array_equal(x, y, equal_nan=True)
        if kind == "gross":
            assert a.outliers.sum() > 0


@pytest.mark.parametrize("seed", range(3))
def test_covariance_from_the_kept_inverse_equals_the_selected_inversion(seed):
    """40 random networks a seed (every offsets mode, 2-D and 3-D, sides 5-20, 0-30 % missing;
    one in four nearly degenerate: receivers within 1e-4 .. 1e-9 of a plane or a line): where
    ``covariance.blocks_from_inverse`` certifies the geometry, the selected inversion
    (``gauge_free_blocks``) accepts it too and its blocks equal the kept inverse's to 1e-7 of a
    block's largest entry (two factorisations of the same matrix, condition up to ~1e6 here);
    where the selected inversion refuses a geometry, the kept inverse never certifies it."""
    from selfcal.toa.engine.covariance import blocks_from_inverse, gauge_free_blocks
    from selfcal.toa.engine.model import _make_layout
    from selfcal.toa.verdict import leverage

    g = np.random.default_rng(200 + seed)
    certified = 0
    for k in range(40):
        dim = int(g.choice([2, 3]))
        I, J = (int(v) for v in g.integers(dim + 3, 21, 2))
        off = ["none", "receivers", "sources", "both"][k % 4]
        has_r, has_s = off in ("receivers", "both"), off in ("sources", "both")
        r, s = g.uniform(0, 10, (I, dim)), g.uniform(0, 10, (J, dim))
        if k % 4 == 1:  # nearly degenerate: the receivers squeezed onto a plane (3-D) or a line (2-D)
            r[:, -1] = 5.0 + r[:, -1] * 10.0 ** -g.uniform(4, 9)
            s[:, -1] = 5.0 + s[:, -1] * 10.0 ** -g.uniform(4, 9)
        d = g.uniform(0, 3, I) if has_r else None
        o = g.uniform(0, 3, J) if has_s else None
        Y = toa_model(r, s, d, o)
        Y[g.random(Y.shape) < g.uniform(0, 0.3)] = np.nan
        obs = np.isfinite(Y)
        if (obs.sum(axis=1) < dim + has_r + 1).any() or (obs.sum(axis=0) < dim + has_s + 1).any():
            continue
        try:
            lay = _make_layout(r, s, off)
        except DegenerateGeometryError:
            continue
        leverage._LAST.clear()
        ne = leverage.normal_equations(obs, r, s, d, o, off)
        inv = ne.block()
        leverage._LAST.clear()
        theta = _pack(r, s, d, o)
        held = None if inv is None else blocks_from_inverse(inv, theta, lay)
        try:
            ref = gauge_free_blocks(theta, obs.astype(float), lay)
        except DegenerateGeometryError:
            assert held is None, (seed, k)
            continue
        if held is None:
            continue
        certified += 1
        for a, b in zip(held, ref, strict=True):
            scale = np.abs(b).max(axis=(1, 2), keepdims=True)
            assert np.allclose(a, b, rtol=0, atol=1e-7 * scale.max()), (seed, k, off, dim)
    assert certified >= 20  # the kept inverse serves generic networks


@pytest.mark.parametrize("seed", range(2))
def test_covariance_at_a_settled_fit_equals_one_more_refinement(seed):
    """24 random networks a seed (every offsets mode, 2-D and 3-D, 8-30 nodes a side, 0-20 %
    missing, noise-free to 5 cm): at a converged least-squares fit whose Gauss-Newton step is
    below the step tolerance (``leverage.settled``), ``nls.with_covariance`` (what the final fit
    of ``solve_toa`` is when nothing changed since the search) equals one more ``refine_toa``
    from it: positions and offsets within 1e-8 m (the step tolerance is 1e-10 of the parameter
    vector's norm, ~1e-8 m here; measured at most 1.5e-9 m), the noise estimate and the covariance blocks within 1e-6
    relative. Fits that converged on the cost's relative decrease with a larger Gauss-Newton
    step (one more refinement moved them by up to 4e-6 m) are not settled."""
    from selfcal.toa.engine.nls import refine_toa, with_covariance
    from selfcal.toa.verdict import leverage

    g = np.random.default_rng(300 + seed)
    n_settled = 0
    for k in range(24):
        dim = int(g.choice([2, 3]))
        I, J = (int(v) for v in g.integers(8, 31, 2))
        off = ["none", "receivers", "sources", "both"][k % 4]
        has_r, has_s = off in ("receivers", "both"), off in ("sources", "both")
        r, s = g.uniform(0, 10, (I, dim)), g.uniform(0, 10, (J, dim))
        d = g.uniform(0, 3, I) if has_r else None
        o = g.uniform(0, 3, J) if has_s else None
        Y = toa_model(r, s, d, o) + g.normal(0, float(g.choice([0.0, 0.001, 0.05])), (I, J))
        Y[g.random(Y.shape) < g.uniform(0, 0.2)] = np.nan
        try:
            sol = refine_toa(Y, r + g.normal(0, 0.05, r.shape), s + g.normal(0, 0.05, s.shape), offsets=off,
                             receiver_offsets0=d, source_offsets0=o, covariance=False)
        except DegenerateGeometryError:
            continue
        fit = (sol.receivers, sol.sources, sol.receiver_offsets, sol.source_offsets)
        leverage._LAST.clear()
        leverages(Y, *fit, off)  # the linearisation at the fit, as the outlier rule leaves it
        if not (sol.converged and leverage.settled(np.isfinite(Y), *fit, off, Y - toa_model(*fit))):
            continue
        n_settled += 1
        a = with_covariance(sol, Y, offsets=off, normal_inverse=leverage.kept_inverse(off))
        leverage._LAST.clear()
        b = refine_toa(Y, sol.receivers, sol.sources, offsets=off, receiver_offsets0=sol.receiver_offsets,
                       source_offsets0=sol.source_offsets)
        assert a.iterations == 0 and a.converged
        for x, y in ((a.receivers, b.receivers), (a.sources, b.sources), (a.receiver_offsets, b.receiver_offsets),
                     (a.source_offsets, b.source_offsets)):
            if x is not None:
                assert np.abs(x - y).max() < 1e-8, (seed, k, off)
        assert a.sigma == pytest.approx(b.sigma, rel=1e-6, abs=1e-12)
        for x, y in ((a.receiver_cov, b.receiver_cov), (a.source_cov, b.source_cov)):
            assert np.allclose(x, y, rtol=0, atol=1e-6 * np.abs(y).max() + 1e-24), (seed, k, off)
    assert n_settled >= 8
