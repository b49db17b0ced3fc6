"""The 004 initialiser of ``solve_toa(offsets="both")``: rank-d offsets, then positions.

Multistart of :func:`selfcal.toa.init.rank3.fast_offsets` with its stopping rules, distinct
candidates, and with missing entries the complete core + growth start.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..._checks import as_matrix, as_rng, check_dim
from ...errors import DegenerateGeometryError
from .offset_positions import _locate_with_offset, _range_rms, offset_free_positions
from .rank3 import fast_offsets
from .rank3_model import Array, Rank3Result, check_rank_identifiable

__all__ = ["complete_core", "initialize_offsets", "initialize_offsets_candidates"]


def _start_from_offsets(R: Array, res: Rank3Result, dim: int,
                        gen: np.random.Generator) -> tuple[Array, Array, Array, Array]:
    """(receivers, sources, receiver_offsets, source_offsets) from one rank-d offset estimate.

    Positions come from the offset-free ranges (completed by the rank-d fit where ``R`` is
    missing) through :func:`offset_free_positions`.
    """
    full = res.extra.get("completed", R)
    D = full - res.receiver_offsets[:, None] - res.source_offsets[None, :]
    receivers, sources = offset_free_positions(D, np.isnan(R), dim, rng=gen)
    return receivers, sources, res.receiver_offsets.copy(), res.source_offsets.copy()


def initialize_offsets(
    ranges: Any,
    dim: int = 3,
    *,
    rng: np.random.Generator | int | None = None,
    n_starts: int = 8,
) -> tuple[Array, Array, Array, Array]:
    """Starting geometry and offsets for ``solve_toa(offsets="both")`` (the NLS refinement).

    Fast rank-d estimate of the offsets (:func:`fast_offsets`, exact model, from p = 0 and then
    up to ``n_starts - 1`` thesis random initialisations, keeping the smallest F and stopping
    early at a noise-free fit or, where p is identifiable with margin, once the two best
    starts agree (:func:`_two_agree`)), then positions from the offset-free ranges
    (:func:`positions_from_ranges`). Missing (NaN) entries are completed inside the rank-d
    fit (:func:`rank3_lm`, alternating projection, no dense unknowns).

    Parameters
    ----------
    ranges : (I, J) metres (times times c), NaN = missing; rows = receivers.
    dim : 2 or 3.
    rng : seed or Generator for the random restarts.
    n_starts : maximal number of starts.

    Returns
    -------
    receivers (I, d), sources (J, d), receiver_offsets (I,), source_offsets (J,) with
    ``source_offsets[0] == 0`` (the common shift lives in the receiver offsets), metres.
    """
    dim = check_dim(dim)
    R = as_matrix(ranges, "ranges", allow_nan=True, min_shape=(2, 2))
    check_rank_identifiable(R.shape[0], R.shape[1], dim)
    gen = as_rng(rng)
    K = R.shape[0] + R.shape[1] - 1
    best = fast_offsets(R, dim=dim, p0=np.zeros(K))
    level = 1e-9 * float(np.nansum(R * R))
    stop_ok = _early_stop_ok(R.shape[0], R.shape[1], dim)
    runs = [best]
    for _ in range(max(1, int(n_starts)) - 1):
        if best.frobenius <= level:
            break  # a noise-free fit: the global minimum
        if stop_ok and _two_agree(runs, R):
            break  # the best basin was reached from two starts
        res = fast_offsets(R, dim=dim, rng=gen, abort_above=_abort_level(runs) if stop_ok else None)
        runs.append(res)
        if res.frobenius < best.frobenius:
            best = res
    start = _start_from_offsets(R, best, dim, gen)
    if np.isnan(R).any():
        # Missing entries as free unknowns of the rank-d fit widen its non-convex landscape:
        # from p = 0 or thesis random starts it lands in a wrong basin in most runs once
        # ~10 % of the entries are missing (measured: 0-2 of 8 starts on 20 x 20 and 12-unit
        # layouts). The complete core + growth start has no completion unknowns at all.
        grown = _core_and_grow(R, dim, gen, n_starts)
        if grown is not None and _model_rms(R, *grown) < _model_rms(R, *start):
            start = grown
    return start


def _same_p(a: Rank3Result, b: Rank3Result, R: Array) -> bool:
    """Two offset estimates are the same: ``||p_a - p_b|| <= 1e-6 rms(t) sqrt(K)`` (metres).

    The threshold is the one that tells distinct candidates apart
    (:func:`initialize_offsets_candidates`): far above the convergence tolerance of
    :func:`rank3_lm` (1e-12 relative), far below any offset difference that matters.
    """
    scale = float(np.sqrt(np.nanmean(R * R))) or 1.0
    return bool(np.linalg.norm(a.p - b.p) <= 1e-6 * scale * np.sqrt(a.p.size))


def _abort_level(runs: list[Rank3Result]) -> float | None:
    """Objective of the best converged run so far: later starts abort above it (thesis sec. 6.2)."""
    ok = [float(r.extra.get("objective", np.inf)) for r in runs if r.converged and np.isfinite(r.frobenius)]
    return min(ok) if ok else None


def _two_agree(runs: list[Rank3Result], R: Array) -> bool:
    """Stopping rule of the multistart: the two runs with the smallest F reached the same p.

    A basin reached from two independent starts and better than every other basin found is
    taken as the global one; further thesis random starts only re-find it (measured: all 8
    starts land on the same p at 500 units). Applied only where a noise-free F = 0
    identifies p (:func:`_early_stop_ok`).
    """
    ok = [r for r in runs if np.isfinite(r.frobenius)]
    if len(ok) < 2:
        return False
    a, b = sorted(ok, key=lambda r: r.frobenius)[:2]
    return _same_p(a, b, R)


def _early_stop_ok(I: int, J: int, dim: int) -> bool:
    """Whether a noise-free rank-d fit (F ~ 0) identifies the offsets, so the starts may stop.

    Double-centred, the corrected matrix is (I-1) x (J-1) and must have rank d: that is
    (I-1-d)(J-1-d) equations for the I+J-1 unknowns of p (3.5). With few units they barely
    outnumber the unknowns (8 units in 3-D: 16 vs 15) and F = 0 has spurious solutions besides
    the true offsets; we trust a zero F only with at least twice as many equations as unknowns
    (12 units and more in 3-D).
    """
    return (I - 1 - dim) * (J - 1 - dim) >= 2 * (I + J - 1)


def initialize_offsets_candidates(
    ranges: Any,
    dim: int = 3,
    *,
    rng: np.random.Generator | int | None = None,
    n_starts: int = 8,
    max_candidates: int = 4,
) -> list[tuple[Array, Array, Array, Array]]:
    """Several distinct starting geometries + offsets for ``solve_toa`` (the 004 rank-d initialiser).

    Runs :func:`fast_offsets` (exact model) from p = 0 and from up to ``n_starts - 1`` thesis
    random initialisations (004 sec. 3.5.1, 6.2) and keeps the *distinct* offset estimates
    (relative difference of p above 1e-6), ordered by the Frobenius norm F (3.17); each
    becomes a start through :func:`offset_free_positions`. F is the distance of the
    offset-corrected matrix to rank d, not the fit of the model ``|r_i - s_j| + delta_i +
    tau_j``: with few units (8 in 3-D) a wrong basin can have the smallest F, even F = 0 on
    exact data. The caller ranks the candidates by the fit of the full model (``solve_toa``
    after a short NLS refinement). The starts stop early at a noise-free F, or once the two
    best starts agree (:func:`_two_agree`), only when the rank-d equations clearly outnumber
    the unknowns (:func:`_early_stop_ok`).

    Parameters
    ----------
    ranges : (I, J) metres (times times c), NaN = missing; rows = receivers.
    dim : 2 or 3.
    rng : seed or Generator for the random restarts.
    n_starts : maximal number of rank-d starts (>= 1).
    max_candidates : at most this many candidates are returned (>= 1), the smallest F first.

    Returns
    -------
    list of (receivers (I, d), sources (J, d), receiver_offsets (I,), source_offsets (J,)),
    metres, ``source_offsets[0] == 0``; at least one entry. With missing entries the
    complete-core start (:func:`_core_and_grow`) is added when it fits better than the first;
    when only one candidate is asked for (``max_candidates=1``, the large-network search) and
    that start fits every observed entry at the noise level of its core
    (:data:`CORE_LEVEL_RATIO`), it is returned alone and the full-size multistart, whose
    unknowns include every missing entry, is not run (500 units, 5 % missing: 0.65 s instead
    of 17.4 s CPU, the same final cost; ``benchmarks/bench_toa.py``).
    """
    dim = check_dim(dim)
    R = as_matrix(ranges, "ranges", allow_nan=True, min_shape=(2, 2))
    check_rank_identifiable(R.shape[0], R.shape[1], dim)
    gen = as_rng(rng)
    I, J = R.shape
    K = I + J - 1
    grown: tuple[Array, Array, Array, Array] | None = None
    if np.isnan(R).any():
        # see initialize_offsets: the complete core + growth start has no completion unknowns
        core: dict[str, Any] = {}
        grown = _core_and_grow(R, dim, gen, n_starts, core)
        if grown is not None and int(max_candidates) == 1 and _fits_at_core_level(R, grown, core):
            # the one start asked for explains every entry as well as the core's own fit: the
            # full-size multistart (with the missing entries as unknowns) could only replace it
            # by a start of lower misfit than the noise level of the core
            return [grown]
    level = 1e-9 * float(np.nansum(R * R))
    stop_ok = _early_stop_ok(I, J, dim)
    runs: list[Rank3Result] = []
    for k in range(max(1, int(n_starts))):
        res = fast_offsets(R, dim=dim, p0=np.zeros(K) if k == 0 else None, rng=None if k == 0 else gen,
                           abort_above=_abort_level(runs) if stop_ok else None)
        if np.isfinite(res.frobenius):
            runs.append(res)
        if stop_ok and runs and min(r.frobenius for r in runs) <= level:
            break  # a noise-free fit that identifies p: the global minimum
        if stop_ok and _two_agree(runs, R):
            break  # the best basin was reached from two starts
    if not runs:
        raise DegenerateGeometryError("the rank-d offset estimation diverged from every start", kind="init-failed")
    runs.sort(key=lambda r: r.frobenius)
    scale = float(np.sqrt(np.nanmean(R * R))) or 1.0
    distinct: list[Rank3Result] = []
    for res in runs:
        if all(np.linalg.norm(res.p - q.p) > 1e-6 * scale * np.sqrt(K) for q in distinct):
            distinct.append(res)
        if len(distinct) >= max(1, int(max_candidates)):
            break
    out: list[tuple[Array, Array, Array, Array]] = []
    for res in distinct:
        try:
            out.append(_start_from_offsets(R, res, dim, gen))
        except DegenerateGeometryError:
            continue
    if not out:
        raise DegenerateGeometryError("no position initialiser produced a finite geometry from the "
                                      "offset-corrected ranges", kind="init-failed")
    if grown is not None and _model_rms(R, *grown) < _model_rms(R, *out[0]):
        out.insert(0, grown)
    return out


#: a grown start is "at the core's level" when its RMS misfit over every observed entry is at
#: most this multiple of its RMS over the core's entries. The core is fitted by the rank-d
#: method itself, the other nodes by linear multilateration from it, so at the right basin the
#: two RMS are both noise-level (measured ratios 0.99-1.18 at 60-1000 units, 1 mm noise); a wrong
#: basin misfits by the scale of the geometry, orders of magnitude above the noise.
CORE_LEVEL_RATIO = 3.0


def _fits_at_core_level(R: Array, start: tuple[Array, Array, Array, Array], core: dict[str, Any]) -> bool:
    """Whether a grown start fits all observed entries at the noise level of its complete core."""
    rows, cols = core.get("rows"), core.get("cols")
    if rows is None or cols is None:
        return False
    r, s, d, o = start
    sub = R[np.ix_(rows, cols)]
    rms_core = _range_rms(sub - d[rows, None] - o[None, cols], ~np.isnan(sub), r[rows], s[cols])
    rms_all = _model_rms(R, r, s, d, o)
    return bool(np.isfinite(rms_all) and rms_all <= CORE_LEVEL_RATIO * max(rms_core, 1e-12 * float(np.nanmax(np.abs(R)))))



def _model_rms(R: Array, receivers: Array, sources: Array, d: Array, o: Array) -> float:
    """RMS of ``t_ij - |r_i - s_j| - delta_i - tau_j`` over the observed entries (inf if not finite)."""
    return _range_rms(R - d[:, None] - o[None, :], ~np.isnan(R), receivers, sources)


def complete_core(missing: NDArray[np.bool_], dim: int) -> tuple[NDArray[np.intp], NDArray[np.intp]] | None:
    """Rows and columns of a complete sub-matrix on which the rank-d method is identifiable.

    Greedy: drop the row or column with the largest fraction of missing entries until
    none is missing (ties: the first such row / column). Returns (row indices, column
    indices), or None when the complete part left is too small for
    :func:`check_rank_identifiable`. The missing counts are updated incrementally:
    O(I + J) per dropped row or column, O((I + J)^2) in all.
    """
    miss = np.asarray(missing, bool)
    I, J = miss.shape
    alive_r = np.ones(I, bool)
    alive_c = np.ones(J, bool)
    rc = miss.sum(axis=1).astype(float)
    cc = miss.sum(axis=0).astype(float)
    nr, nc = I, J
    while nr and nc and (rc[alive_r] > 0).any():
        fr = np.where(alive_r, rc / nc, -np.inf)
        fc = np.where(alive_c, cc / nr, -np.inf)
        if fr.max() >= fc.max():
            k = int(np.argmax(fr))
            alive_r[k] = False
            cc -= miss[k] & alive_c
            nr -= 1
        else:
            k = int(np.argmax(fc))
            alive_c[k] = False
            rc -= miss[:, k] & alive_r
            nc -= 1
    rows, cols = np.flatnonzero(alive_r), np.flatnonzero(alive_c)
    d = dim
    if nr < d + 2 or nc < d + 2 or (nr - 1 - d) * (nc - 1 - d) < nr + nc - 1:
        return None
    return rows, cols



def _core_and_grow(
    R: Array, dim: int, rng: np.random.Generator, n_starts: int, info: dict[str, Any] | None = None
) -> tuple[Array, Array, Array, Array] | None:
    """Start with missing entries: rank-d on a complete core, then add the other nodes one by one.

    The core (:func:`complete_core`) is solved by :func:`initialize_offsets`; each node outside
    it is then placed, with its offset, from its measurements to the nodes already placed
    (:func:`_locate_with_offset`: receiver i from ``t_ij - tau_j = |r_i - s_j| + delta_i``,
    sender j likewise), alternating sides until nothing more can be placed. ``info`` (optional dict)
    receives the core's ``rows`` and ``cols``.
    """
    missing = np.isnan(R)
    core = complete_core(missing, dim)
    if core is None:
        return None
    rows, cols = core
    if info is not None:
        info["rows"], info["cols"] = rows, cols
    try:
        rc, sc, dc, oc = initialize_offsets(R[np.ix_(rows, cols)], dim, rng=rng, n_starts=n_starts)
    except DegenerateGeometryError:
        return None
    I, J = R.shape
    r = np.full((I, dim), np.nan)
    s = np.full((J, dim), np.nan)
    d = np.full(I, np.nan)
    o = np.full(J, np.nan)
    r[rows], s[cols], d[rows], o[cols] = rc, sc, dc, oc
    progress = True
    while progress and (np.isnan(d).any() or np.isnan(o).any()):
        progress = False
        for i in np.flatnonzero(np.isnan(d)):
            use = ~missing[i] & ~np.isnan(o)
            got = _locate_with_offset(s[use], R[i, use] - o[use])
            if got is not None:
                r[i], d[i] = got
                progress = True
        for j in np.flatnonzero(np.isnan(o)):
            use = ~missing[:, j] & ~np.isnan(d)
            got = _locate_with_offset(r[use], R[use, j] - d[use])
            if got is not None:
                s[j], o[j] = got
                progress = True
    if np.isnan(d).any() or np.isnan(o).any():
        return None
    # the gauge of the result: source_offsets[0] == 0, the common shift in the receiver offsets
    d, o = d + o[0], o - o[0]
    return r, s, d, o


