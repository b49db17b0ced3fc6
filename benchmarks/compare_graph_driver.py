"""The range-graph fit: SciPy's TRF (old) against the one Levenberg-Marquardt driver (issue 30).

Loads the tree of an old commit (default ``b6893af``, the last one whose
:func:`selfcal.toa.graph.graph_fit._fit` ran ``scipy.optimize.least_squares(method="trf")``) as the
package ``selfcal_old`` next to the working tree's ``selfcal`` (the loader of
``benchmarks/compare_driver.py``), runs every case on both in this one process (old and new
alternately, the better of ``--repeat`` CPU times each) and prints one row per case:

* ``rel_cost``: ``(c_new - c_old) / c_old`` (negative: the driver's minimum is lower), both costs computed here by one formula
  (``0.5 sum rho`` of the weighted pair residuals and the prior rows, at the returned
  positions);
* ``pos_diff``: largest distance between the two solutions' positions after a rigid alignment
  (reflection allowed), relative to the extent of the old solution;
* ``cov_diff`` (end-to-end rows): largest ``|std_new - std_old| / std_old`` over the
  coordinates with a finite, nonzero std;
* ``t_ratio``: new / old CPU seconds per call (``time.process_time``).

Cases: the graphs of ``tests/toa/test_graph.py`` -- 7 anchors alone (known nodes, one of them
with a std; a reference frame; blind), 7 anchors + 25 tags with and without anchor-anchor
ranges, 2-D, the soft-L1 fit of a graph with spikes -- fitted from the same start and the same
pair means by the two ``_fit``; then ``solve_range_graph`` end to end on some of them, a
large graph (8 anchors + 300 / 3000 tags, 924 / 9012 unknowns: the sparse step), and the LPS flight
``data4`` in long form when the shared data are there (its start differs: the new tree's
multilateration keeps grossly wrong tags inside their ranges' bound, see
:mod:`selfcal.toa.graph.graph_start`; the minimum must not).

Usage::

    PYTHONPATH=src python benchmarks/compare_graph_driver.py [--old b6893af] [--repeat 3]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from compare_driver import ROOT, align_diff, load_old, timed_pair, tree  # noqa: E402

ANCHORS = np.array([[0, 0, 2.8], [5, 0, 2.9], [5, 4, 2.7], [0, 4, 2.9], [2.5, 0, 0.3], [2.5, 4, 0.4],
                    [0, 2, 1.5]])


def _tags(rng: np.random.Generator, n: int, d: int = 3) -> Any:
    T = np.column_stack([rng.uniform(0.5, 4.5, n), rng.uniform(0.5, 3.5, n), rng.uniform(0.3, 2.0, n)])
    return T[:, :d]


def _cost(X: Any, P: Any, prior: Any, free: Any, loss: str, f_scale: float) -> float:
    from selfcal.robust import loss_rho

    r = np.sqrt(P.weight) * (np.linalg.norm(X[P.a] - X[P.b], axis=1) - P.mean)
    if prior is not None:
        mu, isd = prior
        pm = np.isfinite(mu) & free
        r = np.concatenate([r, (X[pm] - mu[pm]) * isd[pm]])
    if loss == "linear":
        return 0.5 * float(r @ r)
    rho, _ = loss_rho((r / f_scale) ** 2, loss)
    return 0.5 * f_scale**2 * float(np.sum(rho))


def fit_case(anchors: Any, tags: Any, *, noise: float, repeats: int, seed: int, anchor_pairs: bool = True,
             known: int = 0, prior_node: int | None = None, frame: bool = False, loss: str = "linear",
             spikes: int = 0) -> Callable[[Any], tuple[float, Any]]:
    """One ``_fit`` call from one start on one graph (the problem built once, by the new tree)."""
    from selfcal.toa.graph.graph import simulate_range_graph
    from selfcal.toa.graph.graph_fit import _pairs
    from selfcal.toa.graph.graph_start import _initial

    a, b, y = simulate_range_graph(
        anchors, tags, noise=noise, repeats=repeats, anchor_pairs=anchor_pairs, rng=seed)
    g = np.random.default_rng(seed + 1000)
    if spikes:
        k = g.choice(y.size, spikes, replace=False)
        y[k] += g.uniform(0.5, 1.5, spikes)
    P = _pairs(a.astype(np.intp), b.astype(np.intp), y, None)
    n = int(max(a.max(), b.max())) + 1
    d = anchors.shape[1]
    truth = anchors if tags is None else np.vstack([anchors, tags])
    X0, _ = _initial(P, n, d, 0)
    free = np.ones((n, d), bool)
    prior = None
    if known or frame:  # start in the truth's frame (as solve_range_graph's rigid alignment would)
        X0 = truth + g.normal(0, 0.05, truth.shape)
    if known:
        X0[:known] = truth[:known]
        free[:known] = False
    if frame:  # origin = 0, x = 1, xy = 2 (the coordinates the references fix)
        Xf = truth - truth[0]
        X0 = Xf + g.normal(0, 0.05, truth.shape)
        X0[0] = 0.0
        X0[1, 1:] = 0.0
        X0[2, 2:] = 0.0
        free[0] = False
        free[1, 1:] = False
        free[2, 2:] = False
    if prior_node is not None:
        mu, isd = np.full((n, d), np.nan), np.full((n, d), np.nan)
        mu[prior_node], isd[prior_node] = truth[prior_node], 1.0 / 0.05 * noise  # scaled as solve_range_graph does
        prior = (mu, isd)
    f_scale = noise * np.sqrt(repeats) if loss != "linear" else 1.0

    def run(m: Any) -> tuple[float, Any]:
        X, _, _ = m("toa.graph.graph_fit")._fit(X0.copy(), P, free, prior, loss=loss, f_scale=f_scale)
        return _cost(X, P, prior, free, loss, f_scale), X

    return run


def solve_case(anchors: Any, tags: Any, *, noise: float, repeats: int, seed: int, known: int = 4,
               **kw: Any) -> Callable[[Any], tuple[float, Any]]:
    """``solve_range_graph`` end to end (the blind start, the fits, the outlier pass, the covariances)."""
    from selfcal.toa.graph.graph import simulate_range_graph

    a, b, y = simulate_range_graph(anchors, tags, noise=noise, repeats=repeats, rng=seed, **kw)
    kn = {str(i): anchors[i] for i in range(known)}

    def run(m: Any) -> tuple[float, Any]:
        res = m("toa.graph.graph").solve_range_graph(a, b, y, known=kn, dim=anchors.shape[1])
        e = y - np.linalg.norm(res.positions[a] - res.positions[b], axis=1)
        e = e[~res.outliers]
        return 0.5 * float(e @ e), (res.positions, res.position_std)

    return run


def lps_case(path: Path) -> Callable[[Any], tuple[float, Any]]:
    """The LPS flight's anchor-tag log in long form (6 anchors x 626 positions, 3739 ranges),
    A0-A3 known at their motion-capture positions (the UWB page's ``calibrate graph`` row)."""
    from selfcal.datasets import load_lps

    f = load_lps(str(path))
    R, A = f.ranges, f.anchors_true
    i, j = np.nonzero(np.isfinite(R))
    a, b, y = i, R.shape[0] + j, np.round(R[i, j], 4)
    names = [f"A{k}" for k in range(R.shape[0])] + [f"t{k:04d}" for k in range(R.shape[1])]
    kn = {f"A{k}": np.round(A[k], 3) for k in range(4)}

    def run(m: Any) -> tuple[float, Any]:
        res = m("toa.graph.graph").solve_range_graph(a, b, y, len(names), names=names, known=kn)
        e = y - np.linalg.norm(res.positions[a] - res.positions[b], axis=1)
        e = e[~res.outliers]
        return 0.5 * float(e @ e), (res.positions, res.position_std)

    return run


def cases() -> list[tuple[str, Callable[[Any], tuple[float, Any]]]]:
    g = np.random.default_rng(7)
    T25, T300 = _tags(g, 25), _tags(g, 300)
    A8 = np.vstack([ANCHORS, [[5, 2, 1.2]]])
    A2 = ANCHORS[:, :2]
    out: list[tuple[str, Callable[[Any], tuple[float, Any]]]] = []
    for seed in (0, 1):
        out += [
            (f"fit anchors 7, known 3 + prior, s{seed}", fit_case(ANCHORS, None, noise=0.03, repeats=5, seed=seed,
                                                                  known=3, prior_node=3)),
            (f"fit anchors 7, frame refs, s{seed}", fit_case(ANCHORS, None, noise=0.03, repeats=5, seed=seed,
                                                             frame=True)),
            (f"fit anchors 7, blind, s{seed}", fit_case(ANCHORS, None, noise=0.03, repeats=5, seed=seed)),
            (f"fit 7 + 25 tags, known 4, s{seed}", fit_case(ANCHORS, T25, noise=0.02, repeats=2, seed=seed, known=4)),
            (f"fit 7 + 25 tags, no anchor pairs, s{seed}", fit_case(ANCHORS, T25, noise=0.02, repeats=2, seed=seed,
                                                                     known=4, anchor_pairs=False)),
            (f"fit 7 + 25 tags, blind, s{seed}", fit_case(ANCHORS, T25, noise=0.02, repeats=2, seed=seed)),
            (f"fit 2-D 7 + 25, known 3, s{seed}", fit_case(A2, T25[:, :2], noise=0.02, repeats=2, seed=seed,
                                                           known=3)),
            (f"fit soft_l1 7 + 25, 8 spikes, s{seed}", fit_case(ANCHORS, T25, noise=0.02, repeats=2, seed=seed,
                                                                known=4, loss="soft_l1", spikes=8)),
        ]
    out += [
        ("fit 8 + 300 tags, known 4 (sparse)", fit_case(A8, T300, noise=0.02, repeats=1, seed=0, known=4)),
        ("fit 8 + 300 tags, blind (sparse)", fit_case(A8, T300, noise=0.02, repeats=1, seed=0)),
        ("fit 8 + 3000 tags, known 4 (sparse)", fit_case(A8, _tags(g, 3000), noise=0.02, repeats=1, seed=0,
                                                         known=4)),
        ("solve anchors 7, known 4", solve_case(ANCHORS, None, noise=0.03, repeats=5, seed=0)),
        ("solve 7 + 25 tags, known 4", solve_case(ANCHORS, T25, noise=0.02, repeats=2, seed=0)),
        ("solve 7 + 25 tags, no anchor pairs", solve_case(ANCHORS, T25, noise=0.02, repeats=2, seed=1,
                                                          anchor_pairs=False)),
        ("solve 8 + 300 tags, known 4 (sparse)", solve_case(A8, T300, noise=0.02, repeats=1, seed=0)),
    ]
    for where in (base / "shared" / "data" / "lps" / "data4.mat" for base in (ROOT, ROOT.parent)):
        if where.exists():
            out.append(("solve LPS data4 long form, A0-A3 known", lps_case(where)))
            break
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--old", default="b6893af", help="commit of the TRF graph fit")
    ap.add_argument("--repeat", type=int, default=3, help="timings per case and tree (the better counts)")
    ap.add_argument("--min-seconds", type=float, default=0.2, help="CPU seconds each timing runs for")
    ap.add_argument("--only", default="", help="run the cases whose name contains this text")
    a = ap.parse_args()
    import warnings

    warnings.simplefilter("ignore")
    sys.path.insert(0, str(ROOT / "src"))
    with tempfile.TemporaryDirectory() as tmp:
        old, new = tree(load_old(a.old, Path(tmp))), tree("selfcal")
        rows = []
        print(f"{'case':42s} {'cost_old':>11s} {'rel_cost':>9s} {'pos_diff':>9s} {'cov_diff':>9s} "
              f"{'t_old s':>8s} {'t_ratio':>7s}")
        for name, f in cases():
            if a.only not in name:
                continue
            (c_old, p_old, t_old), (c_new, p_new, t_new) = timed_pair(f, old, new, a.repeat, a.min_seconds)
            rel = (c_new - c_old) / max(abs(c_old), 1e-300)
            cov = float("nan")
            if isinstance(p_old, tuple):
                (p_old, s_old), (p_new, s_new) = p_old, p_new
                ok = np.isfinite(s_old) & (s_old > 0) & np.isfinite(s_new)
                cov = float(np.max(np.abs(s_new[ok] - s_old[ok]) / s_old[ok])) if ok.any() else float("nan")
            pos = align_diff(p_new, p_old)
            rows.append((rel, t_new / max(t_old, 1e-9)))
            print(f"{name:42s} {c_old:11.6g} {rel:9.1e} {pos:9.2e} {cov:9.2e} {t_old:8.4f} {rows[-1][1]:7.2f}",
                  flush=True)
        rels, ratios = np.array([r[0] for r in rows]), np.array([r[1] for r in rows])
        print(f"\n{int(np.sum(np.abs(rels) <= 1e-8))} of {len(rows)} rows with rel_cost <= 1e-8; time ratio median "
              f"{np.median(ratios):.2f}, geometric mean {np.exp(np.mean(np.log(ratios))):.2f}, max {ratios.max():.2f}")


if __name__ == "__main__":
    main()
