"""Blind start of a range graph: MDS of a complete group, the dense or sparse blind
solvers on a bipartite part, multilateration growth (used by :mod:`selfcal.toa.graph.graph`)."""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from ...errors import DegenerateGeometryError
from .graph_fit import _Pairs

Array = NDArray[np.float64]
Index = NDArray[np.intp]


__all__: list[str] = []


# ---------------------------------------------------------------------------------------
# initial positions
# ---------------------------------------------------------------------------------------

def _clique(P: _Pairs, n: int) -> Index:
    """A greedy complete group of nodes (all mutual ranges measured), best connected first."""
    adj = np.zeros((n, n), bool)
    adj[P.a, P.b] = adj[P.b, P.a] = True
    order = np.argsort(-adj.sum(1), kind="stable")
    best: list[int] = []
    for start in order[: min(n, 8)]:
        group = [int(start)]
        for v in order:
            if v != start and adj[v, group].all():
                group.append(int(v))
        if len(group) > len(best):
            best = group
    return np.array(sorted(best), np.intp)


def _initial(P: _Pairs, n: int, d: int, rng: Any) -> tuple[Array, str]:
    """Start positions of every node (canonical-ish gauge) and the route taken."""
    from ..init.mds_core import classical_mds

    K = _clique(P, n)
    inK = np.zeros(n, bool)
    inK[K] = True
    X = np.full((n, d), np.nan)
    route = ""
    if K.size >= d + 2:
        D = np.zeros((K.size, K.size))
        pos = -np.ones(n, np.intp)
        pos[K] = np.arange(K.size)
        m = inK[P.a] & inK[P.b]
        D[pos[P.a[m]], pos[P.b[m]]] = D[pos[P.b[m]], pos[P.a[m]]] = np.maximum(P.mean[m], 0.0)
        XK = classical_mds(D, d)
        sv = np.linalg.svd(XK - XK.mean(0), compute_uv=False)
        if K.size == n:
            return XK, f"mds({K.size})"
        if sv[-1] > 0.05 * sv[0]:  # the clique spans the space: multilaterate the rest from it
            X[K] = XK
            route = f"mds({K.size})+multilateration"
    if not route:
        X, route = _bipartite_start(P, n, d, K, rng)
    X = _grow(P, X, d)
    lost = np.flatnonzero(~np.isfinite(X).all(1))
    if lost.size:
        raise DegenerateGeometryError(
            f"{lost.size} node(s) have fewer than {d + 1} ranges to the nodes placed so far and cannot be placed "
            f"(first: node {int(lost[0])}); add ranges to them", kind="unobservable-node")
    return X, route


def _bipartite_start(P: _Pairs, n: int, d: int, K: Index, rng: Any) -> tuple[Array, str]:
    """Start from the bipartite part: the clique (or one colour class) x the other nodes."""
    colour = _two_colouring(P, n)
    if colour is not None:
        from ..sparse import solve_toa_sparse

        R, S = np.flatnonzero(colour == 0), np.flatnonzero(colour == 1)
        if R.size > S.size:
            R, S = S, R
        if P.mean.size >= 0.5 * R.size * S.size:
            # a dense bipartite graph is a range matrix: the dense blind solver (its search)
            return _matrix_start(P, n, d, R, S, rng)
        ri, si = -np.ones(n, np.intp), -np.ones(n, np.intp)
        ri[R], si[S] = np.arange(R.size), np.arange(S.size)
        a_is_r = colour[P.a] == 0
        i = np.where(a_is_r, ri[P.a], ri[P.b])
        j = np.where(a_is_r, si[P.b], si[P.a])
        sol = solve_toa_sparse(i, j, P.mean, R.size, S.size, dim=d, rng=rng)
        X = np.full((n, d), np.nan)
        X[R], X[S] = sol.receivers, sol.sources
        return X, "sparse-bipartite"
    if K.size < d + 1:
        raise DegenerateGeometryError(
            f"no group of {d + 1} nodes with all their mutual ranges and the graph is not bipartite: no "
            "blind start for it; measure the ranges among a few anchors", kind="too-few-measurements")
    return _matrix_start(P, n, d, K, np.setdiff1d(np.arange(n), K), rng)


def _matrix_start(P: _Pairs, n: int, d: int, K: Index, E: Index, rng: Any) -> tuple[Array, str]:
    """Blind start from the K x E range matrix (rows K) by :func:`selfcal.toa.solve.solve_toa`."""
    from ..solve import solve_toa

    kpos, epos = -np.ones(n, np.intp), -np.ones(n, np.intp)
    kpos[K], epos[E] = np.arange(K.size), np.arange(E.size)
    M = np.full((K.size, E.size), np.nan)
    for u, v, y in zip(P.a, P.b, P.mean, strict=True):
        if kpos[u] >= 0 and epos[v] >= 0:
            M[kpos[u], epos[v]] = y
        elif kpos[v] >= 0 and epos[u] >= 0:
            M[kpos[v], epos[u]] = y
    ok = np.isfinite(M).sum(0) >= d + 1
    res = solve_toa(np.maximum(M[:, ok], 0.0), dim=d, rng=rng, covariance="none")
    X = np.full((n, d), np.nan)
    X[K] = res.receivers
    X[E[ok]] = res.sources
    return X, f"toa({K.size}x{int(ok.sum())})"


def _two_colouring(P: _Pairs, n: int) -> NDArray[np.int8] | None:
    """0/1 colours when the graph is bipartite (every edge joins the two classes), else None."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import breadth_first_order

    A = coo_matrix((np.ones(P.a.size), (P.a, P.b)), shape=(n, n)).tocsr()
    A = A + A.T
    colour = -np.ones(n, np.int8)
    for s in range(n):
        if colour[s] >= 0:
            continue
        order, pred = breadth_first_order(A, s, directed=False, return_predecessors=True)
        colour[s] = 0
        for v in order[1:]:
            colour[v] = 1 - colour[pred[v]]
    if np.any(colour[P.a] == colour[P.b]):
        return None
    return colour


def _grow(P: _Pairs, X: Array, d: int) -> Array:
    """Multilaterate unplaced nodes with >= d + 1 ranges to placed ones (batched, repeated)."""
    from ..sparse import _multilaterate

    X = X.copy()
    a = np.concatenate([P.a, P.b])
    b = np.concatenate([P.b, P.a])
    y = np.concatenate([P.mean, P.mean])
    while True:
        placed = np.asarray(np.isfinite(X).all(axis=1), dtype=bool)
        m = ~placed[a] & placed[b]
        cnt = np.bincount(a[m], minlength=X.shape[0])
        cand = np.flatnonzero(cnt >= d + 1)
        if not cand.size:
            return X
        loc = -np.ones(X.shape[0], np.intp)
        loc[cand] = np.arange(cand.size)
        k = m & (loc[a] >= 0)
        node, part = loc[a[k]], X[b[k]]
        x, _ = _multilaterate(node, part, y[k], cand.size, d)
        # the triangle inequality bounds a node's distance from its partners' centroid c by
        # min_k |c - p_k| + y_k; a point beyond it contradicts its own ranges (gross errors
        # sent the Gauss-Newton steps there, hundreds of metres out on a real flight, where
        # the refinement's single damping factor then crawls): pulled back onto the bound
        cnt_k = np.bincount(node, minlength=cand.size)[:, None]
        c = np.stack([np.bincount(node, part[:, j], minlength=cand.size) for j in range(d)], 1) / cnt_k
        bound = np.full(cand.size, np.inf)
        np.minimum.at(bound, node, np.linalg.norm(part - c[node], axis=1) + np.abs(y[k]))
        r = np.linalg.norm(x - c, axis=1)
        out = r > bound
        x[out] = c[out] + (x[out] - c[out]) * (bound[out] / r[out])[:, None]
        X[cand] = x


