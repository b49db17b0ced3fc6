"""The initialisers' registry of the TOA search: every start the search refines comes from here.

:data:`INITIALISERS` (small networks run all of them, in this order): the 004 rank-3
iteration (:mod:`selfcal.toa.init.offsets_init`, with offsets and when it identifies them), the 003
family (:mod:`selfcal.toa.init.mds`: rank factorisation, MDS + multilateration, Algorithm 2) with
least-squares offsets of the start geometry, and the scaled random starts
(:mod:`selfcal.toa.init.scaled_starts`) where nothing else reliably knows the offsets (both
kinds, the rank-d method not or only barely identifiable: :func:`_offsets_weakly_identified`).
:data:`LARGE_INITIALISERS` are the affordable choice above :data:`MOVES_MAX_NODES` nodes.
The search that races them is :mod:`selfcal.toa.search`.
"""

from __future__ import annotations

import contextlib
import contextvars
import hashlib
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ...errors import DegenerateGeometryError, InputError
from ..engine.model import least_squares_offsets
from ..moves import Start
from .rank3_model import rank_identifiable
from .scaled_starts import scaled_random_starts

__all__ = ["INITIALISERS", "LARGE_INITIALISERS", "MOVES_MAX_NODES", "SCALED_STARTS", "shared_rank3"]

Array = NDArray[np.float64]

#: moves (and more than one initialiser) only up to this many receivers + sources: above it
#: a refinement costs seconds and the initialisers alone reach the basin (003 sec. V)
MOVES_MAX_NODES = 300


#: an initialiser: (ranges, dim, offsets, rng[, shared]) -> starts. ``shared`` (optional) is a dict
#: the caller creates for one matrix (one search) and passes to every initialiser: quantities
#: two of them compute from the same matrix (the eq. 11 distances of the 003 family) are kept
#: there the first time and reused, never across matrices
_Init = Callable[..., list[Start]]

# the rank-d candidates per matrix inside a shared_rank3() block (None outside: nothing kept)
_RANK3_MEMO: contextvars.ContextVar[dict[tuple[Any, ...], Any] | None] = contextvars.ContextVar(
    "rank3_memo", default=None)


@contextlib.contextmanager
def shared_rank3() -> Iterator[None]:
    """Within the block, the rank-d initialiser runs once per matrix (equal bytes) and its candidates are reused.

    For a caller that fits several offsets models of one matrix
    (:func:`selfcal.toa.verdict.select.choose_offsets`): the candidates (both offset kinds,
    before they are collapsed to a model) do not depend on the model, and they cost as much
    as the rest of a search. Outside such a block nothing is kept.

    Examples
    --------
    >>> with shared_rank3():
    ...     pass
    """
    token = _RANK3_MEMO.set({})
    try:
        yield
    finally:
        _RANK3_MEMO.reset(token)


def _rank3(Y: Array, dim: int, offsets: str, rng: np.random.Generator,
           shared: dict[str, Any] | None = None) -> list[Start]:
    """004 rank-3 iteration (selfcal.toa.init.offsets_init): up to 4 distinct starts, offsets collapsed."""
    from .offsets_init import initialize_offsets_candidates

    if offsets == "none":
        return []
    I, J = Y.shape
    if not rank_identifiable(I, J, dim):
        return []
    k = 4 if I + J <= MOVES_MAX_NODES else 1
    memo = _RANK3_MEMO.get()
    key = (dim, k, Y.shape, hashlib.blake2b(np.ascontiguousarray(Y, float).tobytes()).hexdigest())
    if memo is not None and key in memo:
        found = memo[key]
    else:
        try:
            found = initialize_offsets_candidates(Y, dim, rng=rng, max_candidates=k)
        except (DegenerateGeometryError, InputError):
            if not np.isnan(Y).any():
                raise
            # missing entries: complete them by the two-way additive fit for the initialiser only
            Z = np.where(np.isfinite(Y), Y, _additive_fit(Y, True, True))
            found = initialize_offsets_candidates(Z, dim, rng=rng, max_candidates=k)
        if memo is not None:
            memo[key] = found
    out: list[Start] = []
    for r, s, d0, o0 in found:
        r, s = np.asarray(r, float), np.asarray(s, float)
        if offsets == "receivers":  # the other kind's estimate is the common shift c
            out.append((r, s, np.asarray(d0) + np.mean(o0), None))
        elif offsets == "sources":
            out.append((r, s, None, np.asarray(o0) + np.mean(d0)))
        else:
            out.append((r, s, np.asarray(d0, float), np.asarray(o0, float)))
    return out


def _mds(method: str) -> _Init:
    def init(Y: Array, dim: int, offsets: str, rng: np.random.Generator,
             shared: dict[str, Any] | None = None) -> list[Start]:
        from . import mds

        if _offsets_unidentified(Y, dim, offsets):
            return []  # MDS of offset-free ranges knows nothing of offsets of metres: the scaled starts' case
        shift = min(0.0, float(np.nanmin(Y)))  # negative ranges: shift for the initialiser only
        r, s = mds.initialize_toa(Y - shift, dim, method=method, rng=rng,
                                  shared=None if shared is None else shared.setdefault(f"mds{shift!r}", {}))
        r, s = np.asarray(r, float), np.asarray(s, float)
        d0, o0 = least_squares_offsets(Y, r, s, offsets)
        return [(r, s, d0, o0)]

    init.__doc__ = f"003 initialiser {method!r} (selfcal.toa.init.mds.initialize_toa), LS offsets."
    return init


def _scaled(Y: Array, dim: int, offsets: str, rng: np.random.Generator,
            shared: dict[str, Any] | None = None) -> list[Start]:
    """Random starts at the data's distance bounds (selfcal.toa.init.scaled_starts), only where no
    other initialiser reliably knows the offsets: both kinds, and the rank-d method not
    identifiable or only barely (:func:`_offsets_weakly_identified`)."""
    if not _offsets_weakly_identified(Y, dim, offsets):
        return []
    return scaled_random_starts(Y, dim, offsets, rng, n=SCALED_STARTS)


def _offsets_weakly_identified(Y: Array, dim: int, offsets: str) -> bool:
    """Both offset kinds, and the rank-d equations fewer than twice its unknowns (8 x 10 in 3-D).

    There the 004 initialiser's zero rank residual has spurious solutions besides the true
    offsets (:func:`selfcal.toa.init.offsets_init._early_stop_ok`, the same bound), so its
    candidates can all lie in wrong basins of the full model; the 003 starts know nothing of
    offsets. Measured on the generic 8 x 10 draw (3-D, both offsets, 1 us noise, c = 343
    m/s, an 8 x 7 x 3 m room; seeds 0-199, ``benchmarks/basin_rates.py``): with the 004 and 003 starts
    alone the search ended in a wrong basin (a cost above that of the refinement started at the
    truth; draw 6: 5000x, residual 28 us, nodes 1 m off) in 10 draws, 5 of them exit 0 (a
    search failure, not an ambiguity of the data); with the scaled starts in the race, in
    none, at 1.67x the CPU of ``solve_toa`` there.
    """
    from .offsets_init import _early_stop_ok

    I, J = Y.shape
    return _offsets_unidentified(Y, dim, offsets) or (offsets == "both" and not _early_stop_ok(I, J, dim))


def _offsets_unidentified(Y: Array, dim: int, offsets: str) -> bool:
    """Both offset kinds and the rank-d method not identifiable (12 x 6 in 3-D): no initialiser
    but the scaled starts has information on the offsets.

    There the 003 starts (MDS of the ranges as if offset-free, with least-squares offsets for
    their geometry) are not tried: measured on the 12 x 6 scene (seeds 0-199, every start
    refined to convergence, seeds 0-188) an MDS start reached the truth-started basin in 60 of
    189 draws, never in one where no scaled start did, at a median 600 iterations each (the
    measurement's cap: 27 % of them had converged by then).
    """
    return offsets == "both" and not rank_identifiable(Y.shape[0], Y.shape[1], dim)


#: random starts of the "scaled" initialiser (a share of the search's one budget): three cycles
#: of its 8 scale pairs (selfcal.toa.init.scaled_starts.SCALE_FACTORS). Chosen on seeds 0-199 of
#: the 12 x 6 both-offsets scene (benchmarks/compare_toa_race.py, the race in lockstep): 182 /
#: 190 / 194 / 194 of 200 draws in the truth-started basin for 8 / 16 / 24 / 32 starts at a
#: median CPU 1.00 / 1.25 / 1.48 / 1.76 times that of 8: the smallest count past which more
#: starts gain nothing. Held out, seeds 560-759, against the 8 starts raced one at a time
#: (same run): 192 vs 170 of 200 (96.0 %, exact CI 92.3-98.3 %, against 85.0 %), 22 draws
#: gained and none lost (McNemar p = 5e-7), paired CPU ratio 1.52. What made 24 affordable
#: is :mod:`selfcal.toa.engine.batch_lm` (the race's starts advanced together).
SCALED_STARTS = 24
#: the initialisers, in the order the search runs them (small networks run all of them)
INITIALISERS: dict[str, _Init] = {
    "rank3": _rank3,
    "mds-rank": _mds("rank"),
    "mds-multilat": _mds("mds-multilat"),
    "mds-alg2": _mds("alg2"),
    "scaled": _scaled,
}
#: the one initialiser of large networks (I + J > MOVES_MAX_NODES): the affordable 003 choice
LARGE_INITIALISERS = ("rank3", "mds-auto")
_LARGE = {"rank3": _rank3, "mds-auto": _mds("auto")}


def _additive_fit(Y: Array, rows: bool, cols: bool, iterations: int = 100) -> Array:
    """Least-squares fit of ``a_i + b_j`` (or ``a_i``, ``b_j``, a constant) to the observed entries."""
    obs = np.isfinite(Y)
    Z = np.where(obs, Y, 0.0)
    n_r = np.maximum(obs.sum(axis=1), 1)
    n_c = np.maximum(obs.sum(axis=0), 1)
    if not rows and not cols:
        return np.full(Y.shape, Z.sum() / max(obs.sum(), 1))
    a = np.zeros(Y.shape[0])
    b = np.zeros(Y.shape[1])
    complete = bool(obs.all())
    for _ in range(iterations if rows and cols and not complete else 1):
        if rows:
            a = ((Z - b[None, :]) * obs).sum(axis=1) / n_r
        if cols:
            b = ((Z - a[:, None]) * obs).sum(axis=0) / n_c
    # a complete matrix: one sweep of row then column means is the exact two-way fit
    return a[:, None] + b[None, :]
