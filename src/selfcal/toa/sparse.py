"""Sparse TOA networks: only the observed pairs ``(i, j, range)`` are stored.

Large radio and acoustic networks measure ranges only between nearby nodes: with 10,000
receivers and 10,000 sources and 1 % of the pairs observed, the dense I x J matrix
(800 MB of mostly NaN) is never formed here. Everything works on the list of the m
observed pairs:

- :func:`refine_toa_sparse` is the engine of :func:`selfcal.toa.engine.nls.refine_toa` (the
  Levenberg-Marquardt of :mod:`selfcal.toa.engine.schur_lm`, Schur complement onto the smaller
  node set, matrix-free conjugate gradients with the Schur-Jacobi preconditioner) on the
  pairs: each product is a few ``bincount`` sums over the m pairs, O(m) time and memory.
  On the same observed set it reaches the same minimum as the dense engine (tested).
- :func:`initialize_toa_sparse` is a blind initialiser for sparse data, by *multilateration
  growth from a dense seed patch*: a greedy near-complete bipartite block of the
  observation graph (receivers that share most of their sources) is solved blind by the
  dense pipeline (:func:`selfcal.toa.solve.solve_toa`), then every node with at least
  d + 2 ranges to located nodes is multilaterated (linearised least squares, then
  Gauss-Newton; batched over all candidate nodes of a round), the located set refined by
  the sparse engine each time it has doubled, until no node can be added.
- :func:`solve_toa_sparse` chains the two.

Nodes left with at most d + 1 ranges in the final fit are *weakly placed* (one redundant
range: a placement mirrored across their partners' hyperplane fits almost as well when the
partners are nearly coplanar); the blind solve re-checks each against its mirror after the
final fit, moves it when the mirror fits its ranges better, refits, and lists them in
``weakly_placed_receivers`` / ``weakly_placed_sources``.

Model and gauge are those of :mod:`selfcal.toa.engine.nls` (003 eq. 2 without offsets; the result
is in the canonical gauge of :func:`selfcal.geometry.canonical_gauge`). Offsets and robust
losses are not offered on this path (the dense path has them); exact covariance blocks of
selected nodes (``covariance=`` of :func:`refine_toa_sparse` / :func:`solve_toa_sparse`) come
from :func:`selfcal.toa.engine.sparse_covariance.sparse_covariance_blocks` (d matrix-free CG solves
per node).

The file is above 600 lines because the result type, the engine wrapper, the growth, its
mirror re-check and the covariance request share the pair bookkeeping (index maps, batched
multilateration); the covariance arithmetic itself lives in :mod:`selfcal.toa.engine.sparse_covariance`.

Cost. A CG product is O(m); the number of CG iterations grows with the graph diameter
(hops across the network), the growth initialiser is O(m) per round and needs about
diameter rounds. Memory is O(m + I + J).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .._checks import check_pairs, entry
from .._result import Result
from ..errors import DegenerateGeometryError, InputError
from .engine.model import _check_counts
from .engine.sparse_covariance import sparse_covariance_blocks

__all__ = ["SparseToaResult", "refine_toa_sparse", "initialize_toa_sparse", "solve_toa_sparse",
           "simulate_sparse_network"]

Array = NDArray[np.float64]
Index = NDArray[np.intp]


@dataclass(frozen=True, repr=False)
class SparseToaResult(Result):
    """Result of :func:`refine_toa_sparse` / :func:`solve_toa_sparse` (lengths in metres).

    Attributes
    ----------
    receivers, sources : (I, d), (J, d) positions in the canonical gauge.
    residuals : (m,) measured minus modelled range of each observed pair.
    residual_rms : root mean square of the residuals.
    noise_estimate : ``sqrt(RSS / (m - n + g))`` (n unknowns, g gauge freedoms).
    converged, iterations, cost : solver status, LM iterations, ``0.5 RSS``.
    located : fraction of the nodes the initialiser reached (1.0 after a plain refine).
    seed_shape : (receivers, sources) of the initialiser's dense seed patch, (0, 0) if none.
    unlocated_receivers, unlocated_sources : indices of the nodes the blind growth never
        reached (too few ranges to the located part): NaN positions, their pairs unused.
    weakly_placed_receivers, weakly_placed_sources : located nodes with at most d + 1 ranges
        in the final fit (one redundant range: a placement mirrored across their partners'
        hyperplane fits almost as well when the partners are nearly coplanar). The blind
        solve re-checks each against its mirror after the final fit (:func:`solve_toa_sparse`);
        their positions deserve less trust than the noise level suggests.
    mirrors_taken : how many weakly placed nodes that re-check moved to their mirror side.
    receiver_cov, source_cov : (I, d, d), (J, d, d) gauge-free covariance blocks (m^2, the
        canonical frame, ``noise_estimate**2`` times :func:`selfcal.toa.engine.sparse_covariance.
        sparse_covariance_blocks`) of the nodes asked for with ``covariance=``, NaN for the
        others; None when none was asked for.
    """

    receivers: Array
    sources: Array
    residuals: Array
    residual_rms: float
    noise_estimate: float
    converged: bool
    iterations: int
    cost: float
    located: float = 1.0
    seed_shape: tuple[int, int] = (0, 0)
    unlocated_receivers: Index = dataclasses.field(default_factory=lambda: np.zeros(0, np.intp))
    unlocated_sources: Index = dataclasses.field(default_factory=lambda: np.zeros(0, np.intp))
    weakly_placed_receivers: Index = dataclasses.field(default_factory=lambda: np.zeros(0, np.intp))
    weakly_placed_sources: Index = dataclasses.field(default_factory=lambda: np.zeros(0, np.intp))
    mirrors_taken: int = 0
    receiver_cov: Array | None = None
    source_cov: Array | None = None


def _lm(i: Index, j: Index, y: Array, r0: Array, s0: Array, max_nfev: int | None, xtol: float
        ) -> tuple[Array, Array, bool, int]:
    from .engine.model import _make_layout, _pack, _unpack
    from .engine.schur_lm import solve_schur_lm

    I, d = r0.shape
    J = s0.shape[0]
    lay = _make_layout(r0, s0, "none")
    theta, conv, it = solve_schur_lm(_pack(r0, s0, None, None), y, lay, "linear", 1.0, max_nfev, xtol, pairs=(i, j))
    r, s, _, _ = _unpack(theta, I, J, d, "none")
    return r.copy(), s.copy(), conv, it


def _result(i: Index, j: Index, y: Array, r: Array, s: Array, conv: bool, it: int,
            located: float = 1.0, seed_shape: tuple[int, int] = (0, 0),
            cov: tuple[Index, Index] | None = None) -> SparseToaResult:
    """The result in the canonical gauge; ``cov`` = (receiver, source) indices whose blocks to compute."""
    from ..geometry import canonical_gauge, rotate_covariances

    f = y - np.linalg.norm(r[i] - s[j], axis=1)
    d = r.shape[1]
    n = (r.shape[0] + s.shape[0]) * d
    g = d * (d + 1) // 2
    dof = f.size - n + g
    noise = float(np.sqrt(f @ f / dof)) if dof > 0 else float("nan")
    rc, sc, al = canonical_gauge(r, s)
    assert sc is not None
    Cr = Cs = None
    if cov is not None and (cov[0].size or cov[1].size):
        Br, Bs = sparse_covariance_blocks(i, j, r, s, covariance=cov)
        Cr, Cs = (rotate_covariances(B * noise**2, al.rotation) for B in (Br, Bs))
    return SparseToaResult(
        receivers=rc, sources=sc, residuals=f, residual_rms=float(np.sqrt(np.mean(f**2))),
        noise_estimate=noise, converged=conv, iterations=it, cost=0.5 * float(f @ f), located=located,
        seed_shape=seed_shape, receiver_cov=Cr, source_cov=Cs)


def refine_toa_sparse(
    i: NDArray[np.integer], j: NDArray[np.integer], ranges: Array, receivers0: Array, sources0: Array,
    *, max_nfev: int | None = None, xtol: float = 1e-10, covariance: Any = "none",
) -> SparseToaResult:
    """Refine receivers and sources from the observed pairs only (003 eq. 2, 16; sparse path).

    Parameters
    ----------
    i, j : (m,) int receiver and source index of each observed range.
    ranges : (m,) measured ranges, metres (``y_m = |r_i - s_j| + e``).
    receivers0, sources0 : (I, d), (J, d) starting positions, d in {2, 3}.
    max_nfev : cap on LM iterations (default 100).
    xtol : relative step tolerance.
    covariance : which nodes' covariance blocks (``(receiver_idx, source_idx)``,
        ``{"receivers": idx, "sources": idx}``, "receivers" / "sources" / "all", default
        "none"): d CG solves per node (:mod:`selfcal.toa.engine.sparse_covariance`), so ask for the
        nodes you need on a large network.

    Returns
    -------
    SparseToaResult in the canonical gauge (:func:`selfcal.geometry.canonical_gauge`).

    Raises
    ------
    InputError
        Malformed pairs (shapes, indices out of range, repeated pairs, non-finite ranges).
    DegenerateGeometryError
        A node with fewer than d ranges, or a geometry whose gauge cannot be fixed.

    Notes
    -----
    The engine of :mod:`selfcal.toa.engine.schur_lm` on the :class:`selfcal.toa.engine.schur_lm.Pairs`
    pattern: O(m) per CG product, O(m + I + J) memory. The same minimum as
    :func:`selfcal.toa.engine.nls.refine_toa` on the dense matrix with the same observed entries.

    Examples
    --------
    >>> import numpy as np
    >>> rng = np.random.default_rng(0)
    >>> r, s = rng.uniform(0, 5, (8, 3)), rng.uniform(0, 5, (9, 3))
    >>> i, j = np.nonzero(rng.random((8, 9)) < 0.8)
    >>> y = np.linalg.norm(r[i] - s[j], axis=1) + rng.normal(0, 0.01, i.size)
    >>> sol = refine_toa_sparse(i, j, y, r + 0.05, s - 0.05)
    >>> bool(sol.converged), bool(sol.noise_estimate < 0.02)
    (True, True)
    """
    from .._checks import as_points

    r0 = as_points(receivers0, "receivers0")
    d = r0.shape[1]
    s0 = as_points(sources0, "sources0", dim=d)
    ii, jj, y, I, J = check_pairs(i, j, ranges, r0.shape[0], s0.shape[0])
    cov = _sparse_request(covariance, I, J)
    _check_counts(np.bincount(ii, minlength=I), np.bincount(jj, minlength=J), d, d)
    r, s, conv, it = _lm(ii, jj, y, r0, s0, max_nfev, xtol)
    return _result(ii, jj, y, r, s, conv, it, cov=cov)


def _sparse_request(covariance: Any, I: int, J: int) -> tuple[Index, Index]:
    """Receiver and source indices of a covariance request (``"local"`` refused on this path)."""
    from .engine.covariance import is_local, normalize_covariance, resolve_covariance

    if is_local(normalize_covariance(covariance)):
        raise InputError("covariance='local' is not offered on the sparse path (its error ~(d+1) / fewest ranges "
                         "per node is large there); ask for indices")
    return resolve_covariance(covariance, I, J)


# ---------------------------------------------------------------------------
# blind initialiser: dense seed patch + multilateration growth
# ---------------------------------------------------------------------------


def _seed_patch(i: Index, j: Index, I: int, J: int, size: int, rng: np.random.Generator, d: int
                ) -> tuple[Index, Index]:
    """A locally dense block of the observation graph (missing entries allowed).

    A well-connected receiver r0 and its sources S0; the ``size`` receivers sharing most of
    S0; then alternately the sources seen by half of those receivers and the receivers that
    see half of those sources (at least d + 2 each), until the block stops changing.
    """
    import scipy.sparse

    A = scipy.sparse.csr_matrix((np.ones(i.size), (i, j)), shape=(I, J))
    AT = A.T.tocsr()
    deg = np.asarray(A.sum(1)).ravel()
    top = np.flatnonzero(deg >= np.quantile(deg, 0.9))
    r0 = int(rng.choice(top))
    S = A[r0].indices
    overlap = np.asarray(A[:, S].sum(1)).ravel()
    R = np.argsort(-overlap, kind="stable")[:size]
    for _ in range(10):
        seen = np.asarray(AT[:, R].sum(1)).ravel()
        S_new = np.flatnonzero(seen >= max(d + 2, 0.5 * R.size))
        cnt = np.asarray(A[:, S_new].sum(1)).ravel()
        R_new = np.flatnonzero(cnt >= max(d + 2, 0.5 * S_new.size))
        if R_new.size > 2 * size:
            R_new = R_new[np.argsort(-cnt[R_new], kind="stable")[: 2 * size]]
        if np.array_equal(R_new, np.sort(R)) and np.array_equal(S_new, np.sort(S)):
            break
        R, S = np.sort(R_new), S_new
    return np.sort(R), np.sort(S)


def _multilaterate(node: Index, anc: Array, dist: Array, n: int, d: int) -> tuple[Array, Array]:
    """Batched multilateration of ``n`` nodes from anchors; returns positions (n, d) and rms."""
    # linearised: -2 (p - pbar) . x = (rho^2 - |p|^2) - mean(rho^2 - |p|^2)
    cnt = np.bincount(node, minlength=n).astype(float)
    pbar = np.stack([np.bincount(node, anc[:, a], minlength=n) for a in range(d)], 1) / cnt[:, None]
    q = dist**2 - (anc**2).sum(1)
    qbar = np.bincount(node, q, minlength=n) / cnt
    A = -2.0 * (anc - pbar[node])
    c = q - qbar[node]
    M = np.zeros((n, d, d))
    v = np.zeros((n, d))
    for a in range(d):
        v[:, a] = np.bincount(node, A[:, a] * c, minlength=n)
        for b in range(a, d):
            M[:, a, b] = M[:, b, a] = np.bincount(node, A[:, a] * A[:, b], minlength=n)
    scale = np.einsum("npp->n", M)[:, None, None] + 1e-300
    x = np.linalg.solve(M + 1e-12 * scale * np.eye(d), v[:, :, None])[:, :, 0]
    return _gauss_newton(node, anc, dist, x, n, d, 5)


def _gauss_newton(node: Index, anc: Array, dist: Array, x: Array, n: int, d: int, steps: int
                  ) -> tuple[Array, Array]:
    """``steps`` lightly damped Gauss-Newton steps on the ranges of ``n`` nodes from ``x`` (anchors fixed).

    Returns the positions (n, d) and each node's residual rms.
    """
    cnt = np.bincount(node, minlength=n).astype(float)
    for _ in range(steps):
        diff = x[node] - anc
        nrm = np.linalg.norm(diff, axis=1)
        u = diff / np.maximum(nrm, 1e-12)[:, None]
        res = nrm - dist
        G = np.zeros((n, d, d))
        gr = np.zeros((n, d))
        for a in range(d):
            gr[:, a] = np.bincount(node, u[:, a] * res, minlength=n)
            for b in range(a, d):
                G[:, a, b] = G[:, b, a] = np.bincount(node, u[:, a] * u[:, b], minlength=n)
        G += 1e-9 * np.einsum("npp->n", G)[:, None, None] * np.eye(d)
        x = x - np.linalg.solve(G, gr[:, :, None])[:, :, 0]
    res = np.linalg.norm(x[node] - anc, axis=1) - dist
    rms = np.sqrt(np.bincount(node, res**2, minlength=n) / cnt)
    return x, rms


def _mirror_recheck(i: Index, j: Index, y: Array, r: Array, s: Array, d: int
                    ) -> tuple[Array, Array, Index, Index, int]:
    """Weakly placed nodes (at most d + 1 ranges) against their mirror placement.

    With d + 1 ranges a node has one redundant range: when its partners lie close to a
    hyperplane, the reflection of the node across it fits its ranges almost as well, and a
    growth that placed it on the wrong side leaves no large residual to notice. Each such
    node is reflected across the least-squares hyperplane of its partners, refined by
    Gauss-Newton with the partners fixed, and moved there when that fits its ranges better.

    Returns (r, s, weak receiver indices, weak source indices, number of nodes moved);
    ``r`` and ``s`` are copies when a node moved.
    """
    moved = 0
    weak = []
    for side in ("r", "s"):
        node_all, pos, anc_pos = (i, r, s[j]) if side == "r" else (j, s, r[i])
        cnt = np.bincount(node_all, minlength=pos.shape[0])
        w = np.flatnonzero(cnt <= d + 1)
        weak.append(w)
        if not w.size:
            continue
        loc = -np.ones(pos.shape[0], np.intp)
        loc[w] = np.arange(w.size)
        keep = loc[node_all] >= 0
        node, anc, dist = loc[node_all[keep]], anc_pos[keep], y[keep]
        # both placements re-optimised with the partners fixed (the joint fit's point is not the
        # node-only optimum, so an unrefined comparison would favour any refined start)
        x, _ = _gauss_newton(node, anc, dist, pos[w], w.size, d, 10)
        res = np.linalg.norm(x[node] - anc, axis=1) - dist
        rss = np.bincount(node, res**2, minlength=w.size)
        # the partners' least-squares hyperplane: centroid and the normal (smallest singular vector)
        c = np.stack([np.bincount(node, anc[:, a], minlength=w.size) for a in range(d)], 1) / cnt[w][:, None]
        D = anc - c[node]
        Cov = np.einsum("ka,kb->kab", D, D)
        Cn = np.zeros((w.size, d, d))
        np.add.at(Cn, node, Cov)
        nrm = np.linalg.eigh(Cn)[1][:, :, 0]
        xm = x - 2.0 * np.einsum("na,na->n", x - c, nrm)[:, None] * nrm
        xm, _ = _gauss_newton(node, anc, dist, xm, w.size, d, 10)
        res_m = np.linalg.norm(xm[node] - anc, axis=1) - dist
        rss_m = np.bincount(node, res_m**2, minlength=w.size)
        # better beyond round-off (with d ranges both sides fit exactly: keep the node where it is)
        tol = 1e-20 * np.bincount(node, dist**2, minlength=w.size)
        apart = np.linalg.norm(xm - x, axis=1) > 1e-6 * (1.0 + np.linalg.norm(x - c, axis=1))
        better = np.isfinite(rss_m) & (rss_m + tol < rss) & apart
        if better.any():
            pos = pos.copy()
            pos[w[better]] = xm[better]
            moved += int(better.sum())
            if side == "r":
                r = pos
            else:
                s = pos
    return r, s, weak[0], weak[1], moved


def initialize_toa_sparse(
    i: NDArray[np.integer], j: NDArray[np.integer], ranges: Array, n_receivers: int | None = None,
    n_sources: int | None = None, *, dim: int = 3, rng: int | np.random.Generator | None = 0,
    seed_size: int = 20, n_seeds: int = 3,
) -> tuple[Array, Array, float, tuple[int, int], float]:
    """Blind start for a sparse network by multilateration growth from a dense seed patch.

    Parameters
    ----------
    i, j, ranges : (m,) observed pairs (receiver index, source index, range in metres).
    n_receivers, n_sources : I and J (default: the largest index + 1).
    dim : 2 or 3.
    rng : seed or generator (the seed patch's first receiver among the best connected 10 %).
    seed_size : number of receivers the seed patch aims at.
    n_seeds : patches tried (around different well-connected receivers); the one whose blind
        dense solve has the smallest noise estimate is grown (a wrong basin fits worse).

    Returns
    -------
    (receivers (I, d), sources (J, d), fraction of nodes located, seed patch shape, the
    seed's noise estimate in metres). Nodes never reached are NaN.

    Raises
    ------
    DegenerateGeometryError
        When the seed patch is too small or its blind solve fails.

    Notes
    -----
    See the module docstring. A node needs d + 2 ranges to located nodes (one more than
    the d + 1 of a unique fix, so its own residual can be checked); once none is left, nodes
    with d + 1 are added (their fix is unique but unchecked); after each round the
    located set is refined by :func:`refine_toa_sparse`'s engine when it has doubled since
    the last refinement, so the multilateration error does not accumulate along the growth.
    """
    from .solve import solve_toa

    ii, jj, y, I, J = check_pairs(i, j, ranges, n_receivers, n_sources)
    gen = np.random.default_rng(rng)
    d = int(dim)
    best = None
    for _ in range(n_seeds):
        R, S = _seed_patch(ii, jj, I, J, seed_size, gen, d)
        if R.size < d + 2 or S.size < d + 2:
            continue
        ridx = -np.ones(I, np.intp)
        ridx[R] = np.arange(R.size)
        sidx = -np.ones(J, np.intp)
        sidx[S] = np.arange(S.size)
        sel = (ridx[ii] >= 0) & (sidx[jj] >= 0)
        Ys = np.full((R.size, S.size), np.nan)
        Ys[ridx[ii[sel]], sidx[jj[sel]]] = y[sel]
        try:
            seed = solve_toa(Ys, dim=d, rng=gen, covariance="none")
        except DegenerateGeometryError:
            continue
        # a wrong basin fits worse: keep the patch with the smallest noise estimate
        if best is None or seed.sigma < best[2].sigma:
            best = (R, S, seed)
    if best is None:
        raise DegenerateGeometryError(
            f"no patch of at least {d + 2} receivers x {d + 2} sources sharing most of their ranges "
            "was found and solved: the network is too sparse for a blind start", kind="too-few-measurements")
    R, S, seed = best
    r = np.full((I, d), np.nan)
    s = np.full((J, d), np.nan)
    r[R], s[S] = seed.receivers, seed.sources
    noise = max(float(seed.sigma), 1e-12)
    need = d + 2
    last_refine = R.size + S.size
    while True:
        grew = _place_once(ii, jj, y, r, s, d, need, noise) > 0
        n_loc = int(np.isfinite(r[:, 0]).sum() + np.isfinite(s[:, 0]).sum())
        if grew and n_loc >= 2 * last_refine and n_loc < I + J:
            r, s = _refine_located(ii, jj, y, r, s, d)
            last_refine = n_loc
        if not grew:
            if need > d + 1:  # the rest: d + 1 ranges fix a node uniquely (no own check left)
                need = d + 1
                continue
            break
    located = float((np.isfinite(r[:, 0]).sum() + np.isfinite(s[:, 0]).sum()) / (I + J))
    return r, s, located, (int(R.size), int(S.size)), noise


def _second_chance(i: Index, j: Index, y: Array, r: Array, s: Array, d: int, noise: float) -> int:
    """Multilaterate the unlocated nodes with >= d + 2 ranges to located ones (in place); count added."""
    return _place_once(i, j, y, r, s, d, d + 2, noise)


def _place_once(i: Index, j: Index, y: Array, r: Array, s: Array, d: int, need: int, noise: float) -> int:
    """One placement pass (in place): every unlocated node with >= ``need`` ranges to located ones.

    Receivers first, then sources against the receivers located so far. A fix whose own
    residual is far above the noise is postponed (more anchors later): a right fix has
    rms <= ~noise, so it is kept only below 4 x noise. Returns the number of nodes placed.
    """
    added = 0
    for side in ("r", "s"):
        lr, ls = np.isfinite(r[:, 0]), np.isfinite(s[:, 0])
        if side == "r":
            m = ~lr[i] & ls[j]
            node_all, anc_all, pos = i[m], s[j[m]], r
        else:
            m = lr[i] & ~ls[j]
            node_all, anc_all, pos = j[m], r[i[m]], s
        if not node_all.size:
            continue
        cnt = np.bincount(node_all, minlength=pos.shape[0])
        cand = np.flatnonzero(cnt >= need)
        if not cand.size:
            continue
        loc = -np.ones(pos.shape[0], np.intp)
        loc[cand] = np.arange(cand.size)
        keep = loc[node_all] >= 0
        x, rms = _multilaterate(loc[node_all[keep]], anc_all[keep], y[m][keep], cand.size, d)
        ok = np.isfinite(rms) & (rms <= 4.0 * noise)
        pos[cand[ok]] = x[ok]
        added += int(ok.sum())
    return added


def _refine_located(i: Index, j: Index, y: Array, r: Array, s: Array, d: int) -> tuple[Array, Array]:
    """A few LM iterations on the located nodes and the pairs among them."""
    lr, ls = np.isfinite(r[:, 0]), np.isfinite(s[:, 0])
    m = lr[i] & ls[j]
    R, S = np.flatnonzero(lr), np.flatnonzero(ls)
    ridx = -np.ones(r.shape[0], np.intp)
    ridx[R] = np.arange(R.size)
    sidx = -np.ones(s.shape[0], np.intp)
    sidx[S] = np.arange(S.size)
    ci, cj = np.bincount(ridx[i[m]], minlength=R.size), np.bincount(sidx[j[m]], minlength=S.size)
    if ci.min() < d or cj.min() < d:
        return r, s
    rr, ss, _, _ = _lm(ridx[i[m]], sidx[j[m]], y[m], r[R], s[S], 10, 1e-8)
    r, s = r.copy(), s.copy()
    r[R], s[S] = rr, ss
    return r, s


@entry(i="indices", j="indices", ranges="array", n_receivers="count?", n_sources="count?", rng="rng",
       max_nfev="count?", tries="count", dim="dim")
def solve_toa_sparse(
    i: NDArray[np.integer], j: NDArray[np.integer], ranges: Array, n_receivers: int | None = None,
    n_sources: int | None = None, *, dim: int = 3, rng: int | np.random.Generator | None = 0,
    max_nfev: int | None = None, tries: int = 3, covariance: Any = "none",
) -> SparseToaResult:
    """Blind self-calibration of a sparse TOA network from its observed pairs.

    Parameters
    ----------
    i, j, ranges : (m,) observed pairs (receiver index, source index, range in metres).
    n_receivers, n_sources : I and J (default: the largest index + 1).
    dim : 2 or 3.
    rng : seed or generator of the initialiser.
    max_nfev : cap on the final LM iterations.
    tries : growths from different seed patches at most; the first whose final noise estimate
        is within 1.5x its seed patch's (and that reached 90 % of the nodes) is returned,
        else the best fit (smallest noise estimate) of all tries.
    covariance : which nodes' covariance blocks, in the caller's numbering (as in
        :func:`refine_toa_sparse`; default "none"); computed once, for the returned fit;
        unlocated nodes' blocks are NaN.

    Returns
    -------
    SparseToaResult (canonical gauge); ``located`` says which fraction the initialiser
    reached, the nodes it never reached (too few ranges to the located part, e.g. d + 1
    nearly coplanar partners at the edge of the network) are listed in
    ``unlocated_receivers`` / ``unlocated_sources`` with NaN positions.

    Raises
    ------
    InputError, DegenerateGeometryError
        Malformed pairs; a network the growth cannot cover (less than half of the nodes
        reached). Nodes with at most d ranges are not determined: they are reported as
        unlocated, not an error.

    Examples
    --------
    >>> r, s, i, j, y = simulate_sparse_network(60, 60, 0.4, size=20.0, rng=1)
    >>> sol = solve_toa_sparse(i, j, y, 60, 60, rng=0)
    >>> bool(sol.converged), bool(sol.noise_estimate < 0.02)
    (True, True)
    """
    ii, jj, y, I, J = check_pairs(i, j, ranges, n_receivers, n_sources)
    want_r, want_s = _sparse_request(covariance, I, J)
    d = int(dim)
    gen = np.random.default_rng(rng)
    best: SparseToaResult | None = None
    for _ in range(max(1, int(tries))):
        try:
            sol, seed_noise = _grow_and_fit(ii, jj, y, I, J, d, gen, max_nfev)
        except DegenerateGeometryError:
            if best is None and _ == tries - 1:
                raise
            continue
        if best is None or sol.noise_estimate < best.noise_estimate:
            best = sol
        # a growth that went astray leaves a fit far worse than its own seed patch's
        if sol.noise_estimate <= 1.5 * seed_noise and sol.located >= 0.9:
            break
    assert best is not None
    if want_r.size or want_s.size:
        best = _with_covariance(best, ii, jj, y, want_r, want_s)
    return best


def _with_covariance(sol: SparseToaResult, ii: Index, jj: Index, y: Array, want_r: Index, want_s: Index
                     ) -> SparseToaResult:
    """The blind fit with the requested nodes' covariance blocks (on its located part and pairs)."""
    lr, ls = np.isfinite(sol.receivers[:, 0]), np.isfinite(sol.sources[:, 0])
    m = np.isfinite(sol.residuals)
    ridx, sidx = np.cumsum(lr) - 1, np.cumsum(ls) - 1
    sub_r, sub_s = ridx[want_r[lr[want_r]]], sidx[want_s[ls[want_s]]]
    # the fit's positions are in the canonical frame already: the gauge-free blocks there are too
    Br, Bs = sparse_covariance_blocks(ridx[ii[m]], sidx[jj[m]], sol.receivers[lr], sol.sources[ls],
                                      covariance=(sub_r, sub_s))
    d = sol.receivers.shape[1]
    Cr = np.full((lr.size, d, d), np.nan)
    Cs = np.full((ls.size, d, d), np.nan)
    Cr[lr], Cs[ls] = Br * sol.noise_estimate**2, Bs * sol.noise_estimate**2
    return dataclasses.replace(sol, receiver_cov=Cr, source_cov=Cs)


def _grow_and_fit(ii: Index, jj: Index, y: Array, I: int, J: int, d: int, gen: np.random.Generator,
                  max_nfev: int | None) -> tuple[SparseToaResult, float]:
    r0, s0, located, seed, seed_noise = initialize_toa_sparse(ii, jj, y, I, J, dim=d, rng=gen)
    lr, ls = np.isfinite(r0[:, 0]), np.isfinite(s0[:, 0])
    if located < 0.5:
        raise DegenerateGeometryError(
            f"the multilateration growth reached only {located:.1%} of the nodes: the network is not "
            "rigidly connected enough for a blind solve", kind="too-few-measurements")
    # the nodes never reached stay NaN; the fit is on the located part and the pairs inside it.
    # After the fit, nodes left out with >= d + 2 ranges to it get a second chance from the
    # fitted (more accurate) positions, checked against the fitted noise, then one refit.
    mirrors = 0
    for final in (False, True):
        m = lr[ii] & ls[jj]
        R, S = np.flatnonzero(lr), np.flatnonzero(ls)
        ridx = -np.ones(I, np.intp)
        ridx[R] = np.arange(R.size)
        sidx = -np.ones(J, np.intp)
        sidx[S] = np.arange(S.size)
        si, sj = ridx[ii[m]], sidx[jj[m]]
        _check_counts(np.bincount(si, minlength=R.size), np.bincount(sj, minlength=S.size), d, d)
        r, s, conv, it = _lm(si, sj, y[m], r0[R], s0[S], max_nfev, 1e-10)
        # the nodes with one redundant range against their mirror placement; one refit if any moved
        r, s, weak_r, weak_s, moved = _mirror_recheck(si, sj, y[m], r, s, d)
        if moved:
            r, s, conv, it2 = _lm(si, sj, y[m], r, s, max_nfev, 1e-10)
            it += it2
        mirrors += moved
        sub = _result(si, sj, y[m], r, s, conv, it, located, seed)
        if final or (lr.all() and ls.all()):
            break
        r0, s0 = np.full((I, d), np.nan), np.full((J, d), np.nan)
        r0[R], s0[S] = r, s
        added = _second_chance(ii, jj, y, r0, s0, d, sub.noise_estimate)
        if not added:
            break
        lr, ls = np.isfinite(r0[:, 0]), np.isfinite(s0[:, 0])
    rf = np.full((I, d), np.nan)
    sf = np.full((J, d), np.nan)
    rf[R], sf[S] = sub.receivers, sub.sources
    res = np.full(ii.size, np.nan)
    res[m] = sub.residuals
    out = dataclasses.replace(sub, receivers=rf, sources=sf, residuals=res,
                              unlocated_receivers=np.flatnonzero(~lr), unlocated_sources=np.flatnonzero(~ls),
                              weakly_placed_receivers=R[weak_r], weakly_placed_sources=S[weak_s],
                              mirrors_taken=mirrors)
    return out, seed_noise


def simulate_sparse_network(
    n_receivers: int, n_sources: int, fraction: float, *, dim: int = 3, noise: float = 0.01,
    size: float = 100.0, rng: int | np.random.Generator | None = 0,
) -> tuple[Array, Array, Index, Index, Array]:
    """A sparse network: nodes uniform in a cube, ranges only between nearby nodes.

    Parameters
    ----------
    n_receivers, n_sources : I and J.
    fraction : target fraction of the I J pairs observed (0 < fraction <= 1): a pair is observed
        when the nodes are closer than the radius R at which that fraction of pairs lies
        (the R-quantile of a sample of pair distances).
    dim : 2 or 3; noise : range noise std (m); size : cube edge (m).
    rng : seed or generator.

    Returns
    -------
    (receivers (I, d), sources (J, d), i (m,), j (m,), ranges (m,)).

    Examples
    --------
    >>> r, s, i, j, y = simulate_sparse_network(200, 300, 0.05, rng=0)
    >>> r.shape, s.shape, abs(i.size / (200 * 300) - 0.05) < 0.01
    ((200, 3), (300, 3), True)
    """
    import scipy.spatial

    if not 0 < fraction <= 1:
        raise InputError(f"fraction must be in (0, 1], got {fraction}")
    g = np.random.default_rng(rng)
    r = g.uniform(0, size, (n_receivers, dim))
    s = g.uniform(0, size, (n_sources, dim))
    a = g.integers(0, n_receivers, 200_000)
    b = g.integers(0, n_sources, 200_000)
    R = float(np.quantile(np.linalg.norm(r[a] - s[b], axis=1), fraction))
    tree = scipy.spatial.cKDTree(s)
    Mx = tree.sparse_distance_matrix(scipy.spatial.cKDTree(r), R, output_type="coo_matrix")
    j_, i_ = Mx.row.astype(np.intp), Mx.col.astype(np.intp)
    order = np.lexsort((j_, i_))
    i_, j_ = i_[order], j_[order]
    y = np.linalg.norm(r[i_] - s[j_], axis=1) + g.normal(0, noise, i_.size)
    return r, s, i_, j_, y
