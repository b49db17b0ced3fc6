"""An incremental start of the offsets-free range model for matrices with structured gaps.

The MDS-type initialisers of :mod:`selfcal.toa.init.mds` are built on receiver-receiver
distances estimated from the sources both receivers observe (003 eq. 11). A pair of
receivers that shares fewer than ``dim + 1`` observed sources has no such estimate: the
relative geometry of the pair is not identified through common sources, only through
a chain of other nodes, and the completed distance matrix (shortest paths) is then far
from Euclidean. A UWB flight where one anchor is unseen over the first half and another
over the second half is the case that motivated it (``benchmarks/lps_faults.py``,
``two-gaps``): every MDS-type start landed in a minimum 0.4 m from the truth.

:func:`block_start` places the network incrementally instead:

1. **Core block**: the largest complete bipartite sub-matrix found by a greedy rule on
   the shorter side (rows if ``I <= J``): start with every row, and repeatedly remove
   the row whose removal adds the most complete columns, down to ``dim + 1`` rows;
   of the blocks visited, the one with the most entries among those whose counts
   identify a geometry (:func:`selfcal._checks.check_toa_counts`). It is solved by the
   search's engine and race (:func:`selfcal.toa.search.search`, no moves) over the starts
   of every registry initialiser (a large network's search would run one).
2. **Growth**: alternately, every unplaced column with at least ``dim + 1`` ranges to
   placed rows is multilaterated from them, and every unplaced row with at least
   ``dim + 1`` ranges to placed columns from those (linear least squares,
   :func:`selfcal.toa.init.mds_core.multilaterate`, then Gauss-Newton steps on the ranges).
   ``dim + 1`` links place a point up to no discrete ambiguity in general position.
3. Nodes the growth cannot reach with ``dim + 1`` links are placed from what links they
   have (least-norm solution), or at the centroid of the placed nodes of the other kind.

The start is a start, not a fit: the caller's search refines it with every other start
and keeps the lower cost (:func:`selfcal.toa.fit._nested_start`).

Permutation equivariance: the rows and columns are put in
:func:`selfcal.toa.search.canonical_order` first and every choice (the greedy removal,
ties included) is made in that order, so permuting the input permutes the start.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from .._checks import check_toa_counts
from ..errors import DegenerateGeometryError, InputError
from .engine.nls import refine_toa
from .init.mds_core import multilaterate
from .search import INITIALISERS, RACE_RUNGS, canonical_order, search

__all__ = ["block_start", "grown_starts", "needs_block_start"]

Array = NDArray[np.float64]
Start = tuple[Array, Array, "Array | None", "Array | None"]

#: Gauss-Newton steps of the point placement after the linear multilateration (each step a
#: batched d x d solve; the linear solution is within the noise of the minimum in a few)
PLACE_STEPS = 8


def needs_block_start(observed: NDArray[np.bool_], dim: int) -> bool:
    """Does the missing pattern call for :func:`block_start`?

    True when some pair of rows (receivers) shares fewer than ``dim + 1`` observed columns
    (sources): that pair's relative geometry is not identified through common sources,
    so the receiver-receiver distances of the MDS-type starts are missing for it.

    Parameters
    ----------
    observed: (I, J) bool, True where a range is observed.
    dim: 2 or 3.

    Returns
    -------
    bool

    Examples
    --------
    >>> import numpy as np
    >>> obs = np.ones((5, 40), bool)
    >>> needs_block_start(obs, 3)
    False
    >>> obs[0, :20] = obs[1, 20:] = False  # rows 0 and 1 share no column
    >>> needs_block_start(obs, 3)
    True
    """
    O = np.asarray(observed, bool).astype(float)  # counts exact in floating point; BLAS, not numpy's integer loop
    if O.shape[0] < 2:
        return False
    C = O @ O.T
    np.fill_diagonal(C, dim + 1)
    return bool(C.min() < dim + 1)


def _cores(obs: NDArray[np.bool_], dim: int) -> list[tuple[NDArray[np.bool_], NDArray[np.bool_]]]:
    """One core block per row: the greedy largest identifiable complete block that keeps it.

    From every row, the row whose removal completes the most columns is removed (the first
    in canonical order on ties; never the kept row), down to ``dim + 1`` rows; of the blocks
    visited, the one with the most entries whose counts identify a geometry. Distinct
    blocks only, in the order of their first row.
    """
    I, J = obs.shape
    miss = (~obs).astype(np.int64)
    out: list[tuple[NDArray[np.bool_], NDArray[np.bool_]]] = []
    seen: set[bytes] = set()
    for keep in range(I):
        rows = np.ones(I, bool)
        n_miss = miss.sum(axis=0)  # per column: rows of the current set that miss it
        best: tuple[int, NDArray[np.bool_], NDArray[np.bool_]] | None = None
        while True:
            cols = n_miss == 0
            n_r, n_c = int(rows.sum()), int(cols.sum())
            try:
                check_toa_counts((n_r, n_c), n_r * n_c, dim, "none")
                if best is None or n_r * n_c > best[0]:
                    best = (n_r * n_c, rows.copy(), cols)
            except DegenerateGeometryError:
                pass
            if n_r <= dim + 1:
                break
            # columns completed by removing row i: those whose one missing row of the set is i
            gains = ((n_miss == 1)[None, :] & (miss == 1)).sum(axis=1)
            gains[~rows] = -1
            gains[keep] = -1
            i = int(np.argmax(gains))
            rows[i] = False
            n_miss = n_miss - miss[i]
        if best is not None and best[1].tobytes() not in seen:
            seen.add(best[1].tobytes())
            out.append((best[1], best[2]))
    return out


def _place(anchors: Array, ranges: Array) -> Array:
    """Points from their ranges (m, n) to ``anchors`` (n, d), NaN = missing: linear, then Gauss-Newton."""
    X = multilaterate(anchors, ranges)
    obs = np.isfinite(ranges)
    Y = np.where(obs, ranges, 0.0)
    W = obs.astype(float)

    def cost(P: Array) -> Array:
        D = np.linalg.norm(P[:, None, :] - anchors[None], axis=2)
        return np.sum(W * (D - Y) ** 2, axis=1)

    c = cost(X)
    d = anchors.shape[1]
    for _ in range(PLACE_STEPS):
        V = X[:, None, :] - anchors[None]  # (m, n, d)
        D = np.maximum(np.linalg.norm(V, axis=2), 1e-12)
        U = V / D[..., None] * W[..., None]
        F = W * (D - Y)
        N = np.einsum("mnd,mne->mde", U, U)
        g = np.einsum("mnd,mn->md", U, F)
        lam = 1e-9 * np.maximum(np.trace(N, axis1=1, axis2=2), 1e-12)[:, None, None]
        try:
            step = np.linalg.solve(N + lam * np.eye(d), g[..., None])[..., 0]
        except np.linalg.LinAlgError:
            break
        Xn = X - step
        cn = cost(Xn)
        ok = np.isfinite(cn) & (cn < c)
        if not ok.any():
            break
        X[ok], c[ok] = Xn[ok], cn[ok]
    return X


def _refit(Y: Array, r: Array, s: Array, pr: NDArray[np.bool_], pc: NDArray[np.bool_]) -> None:
    """The engine on the placed nodes, in place (skipped where it degenerates)."""
    try:
        sol = refine_toa(Y[np.ix_(pr, pc)], r[pr], s[pc], offsets="none", covariance=False)
    except DegenerateGeometryError:
        return
    if np.isfinite(sol.receivers).all() and np.isfinite(sol.sources).all():
        r[pr], s[pc] = sol.receivers, sol.sources


def _grow(Y: Array, dim: int, r: Array, s: Array, pr: NDArray[np.bool_], pc: NDArray[np.bool_]) -> None:
    """Place every row and column from the placed ones, in place (module docstring, 2. and 3.)."""
    obs = np.isfinite(Y)
    while not (pr.all() and pc.all()):
        lc = obs[pr].sum(axis=0) * ~pc  # links of the unplaced columns to placed rows
        lr = obs[:, pc].sum(axis=1) * ~pr  # ... of the unplaced rows to placed columns
        need = dim + 1
        if lc.max(initial=0) < need and lr.max(initial=0) < need:
            # stalled: the nodes with the most links, from what links they have
            need = max(int(lc.max(initial=0)), int(lr.max(initial=0)))
            if need == 0:  # unlinked to anything placed: at the centroid of the other kind
                s[~pc] = r[pr].mean(axis=0)
                r[~pr] = s[pc].mean(axis=0)
                pc[:] = True
                pr[:] = True
                break
        if lc.max(initial=0) >= need:
            new = lc >= need
            s[new] = _place(r[pr], Y[np.ix_(pr, new)].T)
            pc |= new
        else:
            new = lr >= need
            r[new] = _place(s[pc], Y[np.ix_(new, pc)])
            pr |= new
        _refit(Y, r, s, pr, pc)


def _core_starts(Y: Array, dim: int, rng: np.random.Generator) -> list[tuple[str, Start]]:
    """Every registry initialiser's start on the core block (raced by the caller's search).

    The core is complete but has fewer rows than the whole matrix (4 of 6 anchors on the
    two-gaps flights), where no one 003 initialiser reaches the truth-started basin on every
    draw (measured: each failed on some of 6 seeds, the lowest cost of the three on none);
    a large network's search would run only one of them.
    """
    out: list[tuple[str, Start]] = []
    for name, init in INITIALISERS.items():
        try:
            got = init(Y, dim, "none", rng)
        except (DegenerateGeometryError, InputError, np.linalg.LinAlgError, ValueError, FloatingPointError):
            continue
        out += [(name, st) for st in got if all(p is None or np.isfinite(p).all() for p in st)]
    return out


def grown_starts(Y: Array, dim: int, *, rng: np.random.Generator) -> list[tuple[str, Start]]:
    """Every core block's grown start (module docstring, 1.-3.), in the caller's numbering.

    Parameters
    ----------
    Y: (I, J) ranges in metres, NaN = missing.
    dim: 2 or 3.
    rng: Generator for the core blocks' searches.

    Returns
    -------
    list of (name, (receivers (I, dim), sources (J, dim), None, None)), one per distinct core
    block whose search succeeded (possibly empty). Each is refined on the whole matrix.
    """
    Y = np.asarray(Y, float)
    I, J = Y.shape
    p_r, p_c = canonical_order(Y)
    Yc = Y[np.ix_(p_r, p_c)]
    flip = I > J  # the greedy removal runs on the shorter side
    if flip:
        Yc = Yc.T
    obs = np.isfinite(Yc)
    grown: list[tuple[str, Start]] = []
    for k, (kr, kc) in enumerate(_cores(obs, dim)):
        Yb = Yc[np.ix_(kr, kc)]
        starts = _core_starts(Yb, dim, rng)
        if not starts:
            continue
        try:
            out = search(Yb, dim, "none", rng=rng, starts=starts, budget=len(starts) * (1 + RACE_RUNGS),
                         use_moves=False)
        except (DegenerateGeometryError, InputError):
            continue
        n, m = Yc.shape
        r, s = np.zeros((n, dim)), np.zeros((m, dim))
        r[kr], s[kc] = out.solution.receivers, out.solution.sources
        _grow(Yc, dim, r, s, kr.copy(), kc.copy())
        if not (np.isfinite(r).all() and np.isfinite(s).all()):
            continue
        if flip:
            r, s = s, r
        rec, src = np.empty_like(r), np.empty_like(s)
        rec[p_r], src[p_c] = r, s
        grown.append((f"block{k}", (rec, src, None, None)))
    return grown


def block_start(Y: Array, dim: int, *, rng: np.random.Generator) -> Start | None:
    """A start of the offsets-free model grown from the largest complete blocks (module docstring).

    The grown starts of :func:`grown_starts` (one per core block), raced on the whole matrix
    by :func:`selfcal.toa.search.search` when there are several.

    Parameters
    ----------
    Y: (I, J) ranges in metres, NaN = missing.
    dim: 2 or 3.
    rng: Generator for the core blocks' searches (their randomised initialisers).

    Returns
    -------
    (receivers (I, dim), sources (J, dim), None, None), or None when no complete block
    identifies a geometry (or every core's search fails).

    Notes
    -----
    Intended for matrices where :func:`needs_block_start` holds; on any matrix it returns
    a finite start or None. Cost: per core block (at most one per row of the shorter side),
    one race of the registry initialisers on it and one refinement per growth step.

    Examples
    --------
    >>> import numpy as np
    >>> g = np.random.default_rng(0)
    >>> R, S = g.uniform(0, 3, (6, 3)), g.uniform(0, 3, (80, 3))
    >>> Y = np.linalg.norm(R[:, None] - S[None], axis=2)
    >>> Y[0, :40] = np.nan; Y[1, 40:] = np.nan
    >>> r, s, _, _ = block_start(Y, 3, rng=np.random.default_rng(1))
    >>> bool(np.nanmax(np.abs(np.linalg.norm(r[:, None] - s[None], axis=2) - Y)) < 1e-6)
    True
    """
    Y = np.asarray(Y, float)
    grown = grown_starts(Y, dim, rng=rng)
    if not grown:
        return None
    if len(grown) == 1:
        return grown[0][1]
    # the race on the whole matrix in canonical order (the order of the candidates too)
    p_r, p_c = canonical_order(Y)
    inv_r, inv_c = np.argsort(p_r), np.argsort(p_c)
    cands: list[tuple[str, Start]] = [(name, (st[0][p_r], st[1][p_c], None, None)) for name, st in grown]
    try:
        win = search(Y[np.ix_(p_r, p_c)], dim, "none", rng=rng, starts=cands,
                     budget=len(cands) * (1 + RACE_RUNGS), use_moves=False).solution
    except (DegenerateGeometryError, InputError):
        return grown[0][1]
    if not (np.isfinite(win.receivers).all() and np.isfinite(win.sources).all()):
        return grown[0][1]
    return win.receivers[inv_r], win.sources[inv_c], None, None
