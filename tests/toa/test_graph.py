"""The measurement-graph input (issue 29): anchor-to-anchor ranges alone or with tag ranges,
repeated measurements, solved in the user's frame with error bars that cover the truth.

Coverage is checked by the normalised error ``e' C^-1 e / k`` of each node's free
coordinates (k of them): for a Gaussian estimate with the stated covariance it is
chi-square(k) / k, so the fraction of nodes inside the 95 % region must be ~0.95 and the
mean ~1. Nodes of one draw are correlated, so the tolerances are wider than binomial
(stated at each assertion).
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import chi2

from selfcal.errors import DegenerateGeometryError, InputError, Status
from selfcal.io.graph import read_range_graph
from selfcal.toa.graph.graph import collapse_repeats, simulate_range_graph, solve_range_graph

ANCHORS = np.array([[0, 0, 2.8], [5, 0, 2.9], [5, 4, 2.7], [0, 4, 2.9], [2.5, 0, 0.3], [2.5, 4, 0.4],
                    [0, 2, 1.5]])


def _tags(rng, n):
    return np.column_stack([rng.uniform(0.5, 4.5, n), rng.uniform(0.5, 3.5, n), rng.uniform(0.3, 2.0, n)])


def _frame_coords(X, o, x, xy, z):
    """Independent construction of the reference frame: o at 0, x on +x, xy in the xy plane, z above."""
    e1 = X[x] - X[o]
    e1 /= np.linalg.norm(e1)
    v = X[xy] - X[o]
    v -= (v @ e1) * e1
    e2 = v / np.linalg.norm(v)
    e3 = np.cross(e1, e2)
    if (X[z] - X[o]) @ e3 < 0:
        e3 = -e3
    return (X - X[o]) @ np.vstack([e1, e2, e3]).T


def _normalised_errors(est, truth, cov):
    out = []
    for e, C in zip(est - truth, cov, strict=True):
        free = np.diag(C) > 1e-14
        if free.any():
            k = int(free.sum())
            out.append((e[free] @ np.linalg.solve(C[np.ix_(free, free)], e[free]) / k, k))
    return out


def _coverage(samples):
    inside = [q * k <= chi2.ppf(0.95, k) for q, k in samples]
    return float(np.mean(inside)), float(np.mean([q for q, _ in samples]))


# ---------------------------------------------------------------------------------------
# reader
# ---------------------------------------------------------------------------------------

def test_reader_keeps_names_repeats_and_std(tmp_path):
    p = tmp_path / "g.csv"
    p.write_text("# UWB log\nFrom;To;Range;Std;time\nA0;A1;4.1;0.02;1\nA1;A0;4.12;0.02;2\nA1;t0;2.5;0.05;3\n")
    g = read_range_graph(p)
    assert g.names == ("A0", "A1", "t0")
    assert g.a.tolist() == [0, 1, 1] and g.b.tolist() == [1, 0, 2]
    assert g.std is not None and g.std.tolist() == [0.02, 0.02, 0.05]
    pa, pb, mean, w, k = collapse_repeats(g.a, g.b, g.ranges, g.std)
    assert pa.tolist() == [0, 1] and pb.tolist() == [1, 2] and np.isclose(mean[0], 4.11) and k.tolist() == [0, 0, 1]


@pytest.mark.parametrize("text, word", [
    ("a,b,range\nA,B,1\n", "lacks"), ("from,to,range\nA,A,1\n", "itself"),
    ("from,to,range\nA,B,1_0\n", "not a number"), ("from,to,range\nA,B,nan\n", "not a number"),
    ("from,to,range,std\nA,B,1,0\n", "std"), ("from,to,range\n", "no measurements"),
])
def test_reader_refuses_with_one_clear_line(tmp_path, text, word):
    p = tmp_path / "g.csv"
    p.write_text(text)
    with pytest.raises(InputError, match=word):
        read_range_graph(p)


# ---------------------------------------------------------------------------------------
# anchor-only graphs
# ---------------------------------------------------------------------------------------

def test_anchor_only_known_nodes_right_and_covered_over_draws():
    """7 anchors, all pairs ranged 5 times at 3 cm; A0-A2 known exactly, A3 with a 5 cm std.

    Right in the frame: every anchor within 6 sigma of its stated std (a wrong frame or
    mirror is metres off). Coverage over 60 draws x 4 free anchors: the 95 % inside-rate
    within [0.88, 0.99] (binomial sd 0.014 widened for the correlation within a draw) and
    the mean normalised error within [0.75, 1.3].
    """
    samples = []
    for seed in range(60):
        a, b, y = simulate_range_graph(ANCHORS, None, noise=0.03, repeats=5, rng=seed)
        known = {str(i): ANCHORS[i] for i in range(3)} | {"3": (*ANCHORS[3], 0.05)}
        res = solve_range_graph(a, b, y, known=known, rng=seed)
        assert res.success, res.message
        assert res.frame.determined
        std = np.sqrt(np.clip(np.diagonal(res.position_cov, axis1=1, axis2=2), 1e-12, None))
        assert np.all(np.abs(res.positions - ANCHORS) <= 6 * std + 1e-9)
        samples += _normalised_errors(res.positions, ANCHORS, res.position_cov)
    rate, mean = _coverage(samples)
    assert 0.88 <= rate <= 0.99, rate
    assert 0.75 <= mean <= 1.3, mean


def test_anchor_only_reference_frame_right_and_covered_over_draws():
    """--frame origin=A0,x=A1,xy=A3,z=A4: the anchors in that frame (built independently here)."""
    samples = []
    truth = _frame_coords(ANCHORS, 0, 1, 3, 4)
    for seed in range(60):
        a, b, y = simulate_range_graph(ANCHORS, None, noise=0.03, repeats=3, rng=100 + seed)
        names = [f"A{i}" for i in range(7)]
        res = solve_range_graph(a, b, y, names=names, frame="origin=A0,x=A1,xy=A3,z=A4", rng=seed)
        assert res.success and res.frame.mirror_resolved
        assert np.allclose(res.positions[0], 0) and np.allclose(res.positions[1, 1:], 0)
        assert np.max(np.abs(res.positions - truth)) < 0.3
        samples += _normalised_errors(res.positions, truth, res.position_cov)
    rate, mean = _coverage(samples)
    assert 0.88 <= rate <= 0.99, rate
    assert 0.75 <= mean <= 1.3, mean


def test_coplanar_anchors_alone_are_reported_undetermined_in_3d():
    """Ceiling anchors (one plane) ranging only to each other: the out-of-plane coordinates
    are free to first order; the result says so (DEGENERATE), never a confident answer."""
    flat = ANCHORS.copy()
    flat[:, 2] = 2.8
    for seed in range(5):
        a, b, y = simulate_range_graph(flat, None, noise=0.02, repeats=3, rng=seed)
        res = solve_range_graph(a, b, y, rng=seed)
        assert res.status == Status.DEGENERATE and len(res.undetermined_nodes) == 7


def test_coplanar_anchors_are_determined_in_2d():
    """The same ranges in 2-D determine the layout (a plane configuration is its own mirror)."""
    flat = ANCHORS[:, :2]
    a, b, y = simulate_range_graph(flat, None, noise=0.02, repeats=3, rng=0)
    res = solve_range_graph(a, b, y, dim=2, known={"0": flat[0], "1": flat[1], "3": flat[3]})
    assert res.success and np.max(np.abs(res.positions - flat)) < 0.1


def test_node_with_too_few_ranges_is_refused():
    a, b, y = simulate_range_graph(ANCHORS, None, noise=0.02, rng=0)
    other = np.where(a == 6, b, a)
    keep = ~(((a == 6) | (b == 6)) & (other > 1))  # node 6 ranges to 0 and 1 only
    with pytest.raises(DegenerateGeometryError, match="needs at least"):
        solve_range_graph(a[keep], b[keep], y[keep])


# ---------------------------------------------------------------------------------------
# mixed graphs: anchor-to-anchor and anchor-to-tag ranges
# ---------------------------------------------------------------------------------------

@pytest.mark.parametrize("anchor_pairs", [True, False])
def test_mixed_graph_anchors_and_tags_right_and_covered(anchor_pairs):
    """7 anchors + 25 tag positions, 2 cm noise, repeats 2; 4 anchors known exactly.

    With and without anchor-anchor ranges (without: a bipartite graph, the sparse blind
    start). Anchors and tags within 6 sigma; coverage over 8 draws x 28 free nodes in
    [0.88, 0.99], mean normalised error in [0.75, 1.3].
    """
    samples = []
    for seed in range(8):
        rng = np.random.default_rng(seed)
        T = _tags(rng, 25)
        X = np.vstack([ANCHORS, T])
        a, b, y = simulate_range_graph(ANCHORS, T, noise=0.02, repeats=2, anchor_pairs=anchor_pairs, rng=seed)
        res = solve_range_graph(a, b, y, known={str(i): ANCHORS[i] for i in range(4)}, rng=seed)
        assert res.success, res.message
        std = np.sqrt(np.clip(np.diagonal(res.position_cov, axis1=1, axis2=2), 1e-12, None))
        assert np.all(np.abs(res.positions - X) <= 6 * std + 1e-9)
        samples += _normalised_errors(res.positions, X, res.position_cov)
    rate, mean = _coverage(samples)
    assert 0.88 <= rate <= 0.99, rate
    assert 0.75 <= mean <= 1.3, mean


def test_anchor_ranges_tighten_the_anchors():
    """Adding anchor-to-anchor ranges to the same tag ranges shrinks the anchors' error bars
    (more information: the covariance can only decrease)."""
    rng = np.random.default_rng(3)
    T = _tags(rng, 25)
    known = {str(i): ANCHORS[i] for i in range(4)}
    a1, b1, y1 = simulate_range_graph(ANCHORS, T, noise=0.02, anchor_pairs=False, rng=1)
    a2, b2, y2 = simulate_range_graph(ANCHORS, T, noise=0.02, anchor_pairs=True, rng=1)
    r1 = solve_range_graph(a1, b1, y1, known=known)
    r2 = solve_range_graph(a2, b2, y2, known=known)
    t1 = np.trace(r1.position_cov[4:7], axis1=1, axis2=2) / r1.noise_estimate**2
    t2 = np.trace(r2.position_cov[4:7], axis1=1, axis2=2) / r2.noise_estimate**2
    assert np.all(t2 < t1)


# ---------------------------------------------------------------------------------------
# repeats: pure error and lack of fit
# ---------------------------------------------------------------------------------------

def test_repeats_estimate_the_noise_and_the_lack_of_fit_test_holds_its_level():
    """Unbiased ranges: the repeats' spread estimates the noise (within 15 % at 210 dof and
    more), and the lack-of-fit test rejects at most ~its level (0 or 1 of 40 draws at 1e-3)."""
    rejections = 0
    for seed in range(40):
        a, b, y = simulate_range_graph(ANCHORS, None, noise=0.04, repeats=10, rng=seed)
        res = solve_range_graph(a, b, y, rng=seed)
        assert res.pure_error_sigma is not None and abs(res.pure_error_sigma / 0.04 - 1) < 0.15
        rejections += res.lack_of_fit_p < 1e-3
    assert rejections <= 1


def test_lack_of_fit_finds_pair_biases_the_repeats_do_not_show():
    """A constant 15 cm excess on 3 of the 21 anchor pairs (NLOS), repeats at 1 cm: the misfit
    exceeds the pure error in every draw (F test p < 1e-3), with or without the outlier
    flagging (an anchor-only graph has too little redundancy to locate biased pairs: the
    test says that the error bars from the repeats would be too small)."""
    for seed in range(10):
        a, b, y = simulate_range_graph(ANCHORS, None, noise=0.01, repeats=10, rng=seed)
        g = np.random.default_rng(seed)
        pa, pb, _, _, k = collapse_repeats(a, b, y)
        bad = g.choice(pa.size, 3, replace=False)
        y = y + 0.15 * np.isin(k, bad)
        for flag in (False, True):
            res = solve_range_graph(a, b, y, rng=seed, outliers=flag)
            assert res.lack_of_fit_p is not None and res.lack_of_fit_p < 1e-3


def test_spikes_in_a_mixed_graph_are_flagged():
    """Multipath spikes: +0.5 to +2 m on 4 anchor-tag ranges of a 7-anchor, 25-tag graph with
    anchor ranges (2 cm noise; a tag has 7 ranges for 3 unknowns, so a spike also pulls its
    tag's other residuals). Measured over these 8 draws: 23 of 32 spikes flagged, 5 of 28
    flags wrong, the anchors' error 0.235 -> 0.101 m on average, better in 6 of 8 draws.
    Asserted with margin: >= 60 % of the spikes flagged, <= 25 % of the flags wrong, the
    mean anchor error at most 0.6 x plain least squares'."""
    hit = wrong = n_flags = 0
    errs = []
    for seed in range(8):
        rng = np.random.default_rng(seed)
        T = _tags(rng, 25)
        a, b, y = simulate_range_graph(ANCHORS, T, noise=0.02, rng=seed)
        tag_edges = np.flatnonzero(np.maximum(a, b) >= 7)
        spiked = rng.choice(tag_edges, 4, replace=False)
        y[spiked] += rng.uniform(0.5, 2.0, 4)
        known = {str(i): ANCHORS[i] for i in range(4)}
        plain = solve_range_graph(a, b, y, known=known, outliers=False, rng=seed)
        res = solve_range_graph(a, b, y, known=known, rng=seed)
        flags = set(np.flatnonzero(res.outliers))
        hit += len(flags & set(spiked))
        wrong += len(flags - set(spiked))
        n_flags += len(flags)
        errs.append([np.linalg.norm(r.positions[4:7] - ANCHORS[4:7]) for r in (plain, res)])
    assert hit >= 0.6 * 32 and wrong <= 0.25 * max(n_flags, 1)
    e = np.mean(errs, axis=0)
    assert e[1] <= 0.6 * e[0]


def test_std_column_gives_a_chi_square_test():
    """With the true std the chi-square test passes (p > 1e-3 in 19 of 20 draws at least);
    with a std 3 x too small it fails in every draw."""
    passed = 0
    for seed in range(20):
        a, b, y = simulate_range_graph(ANCHORS, None, noise=0.02, repeats=4, rng=seed)
        ok = solve_range_graph(a, b, y, std=np.full(y.size, 0.02), rng=seed)
        passed += ok.success
        bad = solve_range_graph(a, b, y, std=np.full(y.size, 0.02 / 3), rng=seed)
        assert bad.status == Status.FAILED_TEST
    assert passed >= 19


def test_unknown_known_node_is_refused_before_the_solve(monkeypatch):
    import selfcal.toa.graph.graph as graph

    monkeypatch.setattr(graph, "_initial", lambda *a, **k: (_ for _ in ()).throw(AssertionError("solved")))
    a, b, y = simulate_range_graph(ANCHORS, None, rng=0)
    with pytest.raises(InputError, match="'B3'.*A0, A1"):
        solve_range_graph(a, b, y, names=[f"A{i}" for i in range(7)], known={"B3": (0, 0, 0)})


@pytest.mark.slow
def test_coverage_over_many_draws():
    """The long version (~2 CPU-minutes): 200 anchor-only draws with known nodes and 30 mixed
    draws (7 anchors + 25 tags, anchor-anchor ranges), 95 % inside-rate in [0.91, 0.98] and
    mean normalised error in [0.9, 1.15] (binomial sd ~0.008 at 800 nodes, widened for the
    correlation within a draw; measured with outlier flagging on: 0.930 / 1.03 over the 200
    anchor-only draws, 0.933 / 1.07 over the 30 mixed ones)."""
    samples = []
    for seed in range(200):
        a, b, y = simulate_range_graph(ANCHORS, None, noise=0.03, repeats=5, rng=seed)
        res = solve_range_graph(a, b, y, known={str(i): ANCHORS[i] for i in range(3)} | {"3": (*ANCHORS[3], 0.05)})
        samples += _normalised_errors(res.positions, ANCHORS, res.position_cov)
    for seed in range(30):
        rng = np.random.default_rng(seed)
        T = _tags(rng, 25)
        a, b, y = simulate_range_graph(ANCHORS, T, noise=0.02, repeats=2, rng=seed)
        res = solve_range_graph(a, b, y, known={str(i): ANCHORS[i] for i in range(4)})
        samples += _normalised_errors(res.positions, np.vstack([ANCHORS, T]), res.position_cov)
    rate, mean = _coverage(samples)
    assert 0.91 <= rate <= 0.98, rate
    assert 0.9 <= mean <= 1.15, mean


def test_tags_under_coplanar_anchors_are_named_ambiguous():
    """7 anchors all at 2.8 m, tags below ranging only to them: each tag fits its ranges as
    well mirrored above the ceiling (its partners are coplanar), whatever the frame: status
    AMBIGUOUS naming tags, never the anchors. With A6 lowered to 1.5 m the same tags
    are unique (success) in every draw."""
    flat = ANCHORS.copy()
    flat[:, 2] = 2.8
    for seed in range(3):
        rng = np.random.default_rng(seed)
        T = _tags(rng, 15)
        a, b, y = simulate_range_graph(flat, T, noise=0.02, anchor_pairs=False, rng=seed)
        res = solve_range_graph(a, b, y, known={str(i): flat[i] for i in range(4)}, rng=seed)
        assert res.status == Status.AMBIGUOUS
        assert set(res.mirror_ambiguous_nodes) <= {str(k) for k in range(7, 22)}
        # the fitted anchors A4-A6 leave the plane by the noise, and the mirror is compared with
        # them held there: a conservative test, so not every tag is named (9-15 of 15 here)
        assert len(res.mirror_ambiguous_nodes) >= 5
        a, b, y = simulate_range_graph(ANCHORS, T, noise=0.02, anchor_pairs=False, rng=seed)
        ok = solve_range_graph(a, b, y, known={str(i): ANCHORS[i] for i in range(4)}, rng=seed)
        assert ok.success and not ok.mirror_ambiguous_nodes


def test_grown_start_stays_within_the_bound_its_ranges_set():
    """A node placed by multilateration obeys the triangle inequality of its own ranges:
    ``|x - c| <= min_k |c - p_k| + y_k`` (c = its partners' centroid), so gross range errors
    cannot send it hundreds of metres out (on LPS data4 they sent five tags 10-225 m away and
    the refinement stalled). Checked on 50 draws of 6 anchors and 40 tags whose ranges carry
    errors of up to 20 m on a third of them (the bound holds whatever the ranges); and that
    clean ranges keep the exact position (the bound is never active at the truth)."""
    from selfcal.toa.graph.graph_fit import _pairs
    from selfcal.toa.graph.graph_start import _grow

    A = ANCHORS[:6]
    for seed in range(50):
        rng = np.random.default_rng(seed)
        T = _tags(rng, 40)
        a, b, y = simulate_range_graph(A, T, noise=0.0, anchor_pairs=True, rng=seed)
        tag = b >= 6
        clean = y.copy()
        hit = tag & (rng.random(y.size) < 1 / 3)
        y[hit] += rng.uniform(-20, 20, int(hit.sum()))
        y = np.abs(y)
        for ranges, exact in ((y, False), (clean, True)):
            P = _pairs(a.astype(np.intp), b.astype(np.intp), ranges, None)
            X = np.full((46, 3), np.nan)
            X[:6] = A
            G = _grow(P, X, 3)
            assert np.isfinite(G).all()
            for k in range(6, 46):
                m = (P.b == k) & (P.a < 6)
                p, r = A[P.a[m]], P.mean[m]
                c = p.mean(0)
                assert np.linalg.norm(G[k] - c) <= np.min(np.linalg.norm(p - c, axis=1) + r) * (1 + 1e-9) + 1e-12
            if exact:
                assert np.allclose(G[6:], T, atol=1e-6)
