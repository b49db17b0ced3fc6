"""The one search of the TOA solver: initialisers, moves, one engine, one acceptance rule, one budget.

1. **Canonical order** (:func:`canonical_order`): rows and columns are sorted by a key that
   does not depend on their numbering (the median of the row / column, ties broken by its
   sorted entries). :func:`selfcal.toa.solve_toa` solves the sorted matrix and undoes the
   sort, so its answer is equivariant under permutations of receivers and of sources
   (exactly: the sorted matrix, and so every later step, is the same bit for bit).
2. **Starts** from a registry of initialisers (:data:`INITIALISERS`, in that order): the
   004 rank-3 iteration (:mod:`selfcal.toa.init.offsets_init`, with offsets and when it identifies
   them) and the 003 family (:mod:`selfcal.toa.init.mds`: rank factorisation, MDS +
   multilateration, Algorithm 2). Starting offsets are the least-squares offsets of the
   start geometry. The initialisers run in that order and stop at a start that already
   passes the search's stopping rule (5.): residuals at the solver's precision, or, with
   the linear loss, the chi-square test at the given noise (level
   :data:`selfcal.toa.result.RESIDUAL_ALPHA`). The race ends at the first start in order
   whose first rung passes it, and a rung only lowers the cost (the linear loss: the sum of
   squares), so no later start can win: they are not computed (noise-free 120 units with
   both offsets: the 004 start is exact, Algorithm 2 and the other 003 starts, 90 ms of a
   110 ms search, are skipped).
3. **Moves** (:mod:`selfcal.toa.moves`): reflect or lift subsets of nodes through fitted planes.
   A move of one or two nodes is ranked by a *partial refit* (the one engine with every
   other node and offset fixed, on the entries that touch the moved nodes, at most
   :data:`MOVE_NFEV` iterations): its full cost after that refit bounds what a full
   refinement from it reaches. The improving ones (lower cost than the current best), best
   first and with disjoint nodes, are applied together -- a move of the union of their
   subsets -- and refined in full; the best alone if the union does not improve. The
   collective moves (half the network or more) are refined in full directly.
4. **One engine**: every candidate is refined by :func:`selfcal.toa.engine.nls.refine_toa`.
5. **One acceptance rule**: a candidate replaces the best one when its ML cost (the
   robust cost with one fixed scale for the whole search) is lower. With a known noise,
   the chi-square test of :func:`selfcal.toa.result.residual_test` is the stopping rule.
6. **One budget**: at most ``budget`` refinements (default :func:`default_budget` plus
   :data:`RACE_RUNGS` per start). The starts share it by a *race*: every start refined
   :data:`MOVE_NFEV` iterations, then in rungs that double its iterations every start that
   may still beat the best current cost ``U`` goes on. A start still descending is dropped
   once ``c - RACE_FACTOR (c_prev - c) > U`` (``c_prev`` its cost before the rung): under an
   O(1/k) descent (``c_k = c* + b / k``) what is left after a doubling is what the doubling
   removed, so ``c - (c_prev - c)`` is its optimistic limit. A converged start stays only as
   the leader (duplicates of a converged minimum drop out). The last one standing is refined
   to the end. Successive halving (Jamieson & Talwalkar 2016), the rule before, ranked by the
   cost after 10, 30, 70 ... iterations and dropped starts whose basin was the right one but
   which descended slowly through a far-field valley: replaying both on every start refined
   to convergence (12 x 6 with both offsets, seeds 0-188, the nested and 24 scaled starts),
   the race lands in the truth-started basin in all 180 draws where some start does (at
   3982 iterations median against 8672 for running every start to the end), the halving in
   168 (1110 iterations). Rungs run
   the engine's dense step (:func:`selfcal.toa.engine.dense_lm.solve_dense_lm`) directly on small
   problems without a stopping rule; the winner's full refinement is :func:`refine_toa`'s.

Why this file is long (~600 lines): :func:`search` is one function whose stages (race,
moves) share the refinement count, the robust scale and the best candidate; split by stage
they would pass that state through a dozen closures. The starts' registry, which has a seam,
is :mod:`selfcal.toa.init.starts` (re-exported here).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from ..errors import DegenerateGeometryError, InputError
from ..optim.lm import irls
from ..optim.structure import lm_step
from ..progress import report
from ..robust import TUNING
from .engine.batch_lm import solve_batch_lm
from .engine.dense_lm import solve_dense_lm
from .engine.model import _pack, _unpack, least_squares_offsets
from .engine.nls import NlsSolution, refine_toa, toa_model
from .init.starts import _LARGE, INITIALISERS, MOVES_MAX_NODES, SCALED_STARTS  # noqa: F401
from .moves import Move, Start, moves
from .verdict.robust import canonical_order  # noqa: F401  (the search's order; fit, block_start use it)

__all__ = ["INITIALISERS", "MOVES_MAX_NODES", "SearchOutcome", "canonical_order", "default_budget",
           "least_squares_offsets", "search"]

Array = NDArray[np.float64]

#: iteration cap of the short refinements that rank the moves (the accepted one is finished)
MOVE_NFEV = 10
#: relative cost decrease a candidate must bring to be accepted (round-off guard)
ACCEPT_REL = 1e-9
#: ... and, in units of the noise variance of the current best fit, the decrease of the sum of
#: squares a move must bring: a chi-square difference of 0.01 is below anything a test can
#: see, and on flat valleys (12 x 6 with both offsets) moves of smaller gain are the engine's
#: unfinished iterations, accepted again and again (measured: 18 accepted moves, the same ten
#: twice, on one draw)
ACCEPT_CHI2 = 0.01


#: whether the race advances its starts in lockstep (:mod:`selfcal.toa.engine.batch_lm`); False runs
#: them one at a time through the dense LM (the same iterates, the baseline of the benchmark)
BATCH_RACE = True


def _sane(start: Start, Y: Array) -> bool:
    """Finite and within 100x the scale of the data."""
    lim = 100.0 * (float(np.nanmax(np.abs(Y))) + 1.0)
    return all(p is None or (np.isfinite(p).all() and np.abs(p).max() <= lim) for p in start)


def default_budget(n_receivers: int, n_sources: int) -> int:
    """Refinements the search may run: about one round of node-wise moves (24 nodes), at least 16."""
    n = int(n_receivers) + int(n_sources)
    return 1 if n > MOVES_MAX_NODES else max(16, min(n, 24) + 8)


# ------------------------------------------------------------------ the search


@dataclass(frozen=True)
class SearchOutcome:
    """What :func:`search` found.

    Attributes
    ----------
    solution: the best refinement (no covariances).
    start: name of the initialiser whose start led to it.
    moves: names of the accepted moves, in order.
    refinements: refinements run; iterations: summed over them.
    f_scale: the fixed robust-loss scale of the search (metres; 1 for the linear loss).
    stopped: why the search ended: "test" (the chi-square test passed), "exact" (residuals at
        the solver's precision: no candidate can do better), "budget", "exhausted".
    history: (candidate name, cost) of every start and accepted move.
    minima: converged starts the race dropped behind the winner (lowest cost first, at most
        :data:`MINIMA_KEPT`): other minima, for :func:`selfcal.toa.verdict.uniqueness.uniqueness_test`.
    """

    solution: NlsSolution
    start: str
    moves: tuple[str, ...]
    refinements: int
    iterations: int
    f_scale: float
    stopped: str
    history: list[tuple[str, float]] = field(default_factory=list)
    minima: list[Start] = field(default_factory=list)


def _cost(sol: NlsSolution, loss: str, fs: float) -> float:
    return _cost_of(sol.residuals, loss, fs)


def _cost_of(residuals: Array, loss: str, fs: float) -> float:
    """The ML cost of the search: ``sum rho`` of the finite residuals at the search's one scale."""
    return irls(residuals[np.isfinite(residuals)], loss, fs)[0]


def _as_start(sol: NlsSolution) -> Start:
    return sol.receivers, sol.sources, sol.receiver_offsets, sol.source_offsets


def _pack_start(st: Start) -> Array:
    return _pack(*st)


def _unpack_start(theta: Array, I: int, J: int, dim: int, offsets: str) -> Start:
    r, s, d, o = _unpack(theta, I, J, dim, offsets)
    return r.copy(), s.copy(), None if d is None else d.copy(), None if o is None else o.copy()


#: a move is "local" (ranked by a partial refit) when it moves at most this many nodes
LOCAL_MAX_NODES = 2


def _is_local(mv: Move, I: int, J: int) -> bool:
    n = len(mv.receivers) + len(mv.sources)
    return n <= LOCAL_MAX_NODES and n < I + J


def _combine(base: Start, found: list[tuple[Move, Start]]) -> tuple[str, Start]:
    """One start with the refitted nodes of every move of ``found`` (best first) that moves no
    node an earlier one moved: a move of the union of their subsets."""
    r, s = base[0].copy(), base[1].copy()
    d = None if base[2] is None else base[2].copy()
    o = None if base[3] is None else base[3].copy()
    used_r: set[int] = set()
    used_s: set[int] = set()
    names: list[str] = []
    for mv, st in found:
        if used_r & set(mv.receivers) or used_s & set(mv.sources):
            continue
        used_r |= set(mv.receivers)
        used_s |= set(mv.sources)
        names.append(mv.name)
        ir, js = list(mv.receivers), list(mv.sources)
        r[ir], s[js] = st[0][ir], st[1][js]
        if d is not None and st[2] is not None:
            d[ir] = st[2][ir]
        if o is not None and st[3] is not None:
            o[js] = st[3][js]
    return "+".join(names), (r, s, d, o)


#: a start of the race: (cost, start, converged, the full refinement when it ran through refine_toa)
_State = tuple[float, Start, bool, "NlsSolution | None"]
#: an entry of the race: (cost, index of the start, name, state, cost before the last rung)
_Entry = tuple[float, int, str, _State, float]
#: iteration cap of a rung without an explicit cap (the dense engine's default, schur_lm.DEFAULT_MAX_IT)
DENSE_MAX_IT = 100
#: rungs a start may run in the race, the start allowance of the default budget: its
#: iterations double from MOVE_NFEV, so 8 rungs are 10 (2^8 - 1) = 2550 iterations, more than
#: any start needs (measured at 12 x 6 with both offsets: at most 5.2 rungs per start on average)
RACE_RUNGS = 8

#: the race's bound (module docstring, 6.): a start still descending may go on to lose as much
#: as it lost over its last rung (the rungs double its iterations; for an O(1/k) descent,
#: c_k = c* + b / k, the rest after k iterations, b / k, is what the last doubling removed)
RACE_FACTOR = 1.0
#: converged losers of the race kept as other minima (SearchOutcome.minima)
MINIMA_KEPT = 4


def _race_survivors(pool: list[_Entry], best_only: bool = False) -> list[_Entry]:
    """The starts of the race that may still beat the best one (its lowest cost ``U``).

    Entries ``(cost, index, name, state, cost before the last rung)``, ``state[2]`` whether the
    start converged. A converged start survives only as the leader (converged starts at a
    higher cost, and duplicates of a converged minimum behind the first, are out); a start
    still descending when ``cost - RACE_FACTOR (previous - cost) <= U``: its optimistic limit
    under an O(1/k) descent can still reach the best. ``best_only`` (the budget is spent):
    the leader alone. Sorted by (cost, index), so the order depends on the canonical
    numbering only.
    """
    pool = sorted(pool, key=lambda e: (e[0], e[1]))
    if best_only:
        return pool[:1]
    U = pool[0][0]
    return pool[:1] + [e for e in pool[1:] if not e[3][2] and e[0] - RACE_FACTOR * max(e[4] - e[0], 0.0) <= U]


def search(
    Y: Array,
    dim: int,
    offsets: str,
    *,
    rng: np.random.Generator,
    loss: str = "linear",
    f_scale: float | None = None,
    starts: list[tuple[str, Start]] | None = None,
    first: tuple[str, Start] | None = None,
    stop: Callable[[Array], bool] | None = None,
    budget: int | None = None,
    max_nfev: int | None = None,
    use_moves: bool = True,
    solver: str = "auto",
) -> SearchOutcome:
    """Best refinement of the range model over the registry's starts and the plane moves.

    Parameters
    ----------
    Y: (I, J) ranges in metres (canonical order, see :func:`canonical_order`), NaN = missing
        or excluded.
    dim, offsets: the model.
    rng: Generator for the randomised initialisers.
    loss: loss of every refinement; the robust ones use one scale ``f_scale`` for the whole
        search (default: the tuning constant times the noise estimate of the first refinement)
        so that costs are comparable.
    starts: explicit starts (name, start) instead of the registry.
    first: a start tried before the registry's (an explicit ``init``).
    stop: called on the (I, J) residuals of every new best (and of every start, below); True ends the
        search (the chi-square test with a known noise).
    budget: maximal refinements (default :func:`default_budget`).
    max_nfev: iteration cap of the full refinements.
    use_moves: run the moves after the starts (only up to :data:`MOVES_MAX_NODES` nodes).
    solver: passed to :func:`selfcal.toa.engine.nls.refine_toa`.

    Returns
    -------
    SearchOutcome

    Raises
    ------
    DegenerateGeometryError: no start refined to a non-degenerate solution.
    """
    I, J = Y.shape
    large = I + J > MOVES_MAX_NODES
    nb_given = None if budget is None else max(1, int(budget))
    fs: float | None = f_scale if loss != "linear" else 1.0
    count = 0
    iters = 0
    history: list[tuple[str, float]] = []
    last_err: Exception | None = None
    # residuals at this level are the solver's precision (sqrt of machine eps, relative)
    exact_level = np.sqrt(np.finfo(float).eps) * float(np.nanmedian(np.abs(Y)))

    def done_res(R: Array) -> str | None:
        f = R[np.isfinite(R)]
        if f.size and float(np.max(np.abs(f))) <= exact_level:
            return "exact"
        if stop is not None and stop(R):
            return "test"
        return None

    def done(sol: NlsSolution) -> str | None:
        return done_res(sol.residuals)

    def refine(start: Start, nfev: int | None) -> NlsSolution | None:
        nonlocal count, iters, fs, last_err
        count += 1
        report(count)
        r0, s0, d0, o0 = start
        try:
            sol = refine_toa(Y, r0, s0, offsets=offsets, receiver_offsets0=d0, source_offsets0=o0, loss=loss,
                             f_scale=fs if loss != "linear" else None, max_nfev=nfev, covariance=False,
                             solver=solver)
        except DegenerateGeometryError as exc:
            last_err = exc
            return None
        iters += sol.iterations
        if fs is None:  # the first robust refinement sets the search's scale (95 % efficiency, selfcal.robust)
            fs = max(TUNING[loss] * float(sol.sigma), 1e-12 * (1.0 + float(np.nanmax(np.abs(Y)))))
            return refine(_as_start(sol), nfev)
        return sol

    has_r, has_s = offsets in ("receivers", "both"), offsets in ("sources", "both")
    observed = np.isfinite(Y)

    def refine_part(mv: Move) -> tuple[float, Start] | None:
        """Refit only the moved nodes (and their offsets) on the entries that touch them.

        The engine's dense Levenberg-Marquardt step (:func:`selfcal.toa.engine.dense_lm.solve_dense_lm`)
        with every other parameter held: the fixed nodes hold the frame, so no gauge is
        projected; a few free unknowns on a few entries (4 on 6 at 12 x 6 with both offsets).
        """
        nonlocal iters
        r0, s0, d0, o0 = mv.start
        ir, js = list(mv.receivers), list(mv.sources)
        touch = np.zeros((I, J), bool)
        touch[ir, :] = True
        touch[:, js] = True
        ii, jj = np.nonzero(touch & observed)
        theta0 = _pack_start(mv.start)
        free = np.zeros(theta0.size, bool)
        for i in ir:
            free[i * dim:(i + 1) * dim] = True
        for j in js:
            free[(I + j) * dim:(I + j + 1) * dim] = True
        k = (I + J) * dim
        if has_r:
            free[k + np.asarray(ir, np.intp)] = True
            k += I
        if has_s:
            free[k + np.asarray(js, np.intp)] = True
        try:
            theta, _, nit = solve_dense_lm(theta0, Y[ii, jj], ii, jj, I, J, dim, offsets, loss,
                                           fs if loss != "linear" and fs is not None else 1.0, MOVE_NFEV,
                                           1e-10, free=free)
        except (np.linalg.LinAlgError, ValueError):
            return None
        iters += nit
        if not np.isfinite(theta).all():
            return None
        st = _unpack_start(theta, I, J, dim, offsets)
        with np.errstate(all="ignore"):
            R = np.where(observed, Y - toa_model(*st), np.nan)
        return _cost_of(R, loss, fs or 1.0), st

    def final_start(st: Start) -> bool:
        """Whether a start ends the search before any refinement (module docstring, 2.): it passes
        the search's stopping rule as it stands -- residuals at the solver's precision, or (the
        linear loss, whose every step only lowers the sum of squares) the chi-square test."""
        with np.errstate(all="ignore"):
            why = done_res(np.where(np.isfinite(Y), Y - toa_model(*st), np.nan))
        return why == "exact" or (why == "test" and loss == "linear")

    # ---- starts
    if starts is None:
        reg = _LARGE if large else INITIALISERS
        starts = [] if first is None else [first]
        ended = first is not None and final_start(first[1])
        shared: dict[str, object] = {}  # what two initialisers compute from Y, computed once (init.starts)
        for name, init in reg.items():
            if ended:
                break  # an earlier start ends the race at or before it: the later ones cannot win
            try:
                got = init(Y, dim, offsets, rng, shared)
            except (DegenerateGeometryError, InputError, np.linalg.LinAlgError, ValueError, FloatingPointError):
                continue  # an initialiser that does not apply here is skipped
            new = [(name, st) for st in got if _sane(st, Y)]
            starts += new
            if large and new:
                break
            ended = any(final_start(st) for _, st in new)
    # the default budget: the moves' allowance plus the race's (RACE_RUNGS rungs per start)
    nb = nb_given if nb_given is not None else default_budget(I, J) + (0 if large else RACE_RUNGS * len(starts))
    report(count, nb)  # progress on a terminal: refinements run / the budget
    best: NlsSolution | None = None
    best_cost = np.inf
    best_name = ""
    stopped = "exhausted"
    # the race over the starts (module docstring, 6.): each refined MOVE_NFEV iterations, then
    # in rungs of twice the iterations every start that may still beat the best one; the
    # winner is refined to the end. A lone start, and the first one when the robust scale is
    # still unknown (it sets the scale), are refined to the end at once.
    n_unknowns = (I + J) * dim + (I if has_r else 0) + (J if has_s else 0)
    # the rungs run the engine's dense step directly (what refine_toa runs at this size, without
    # its layout, gauge and covariance round trip per call) unless a stopping rule needs each
    # rung's full solution
    fast = solver == "auto" and stop is None and lm_step(n_unknowns) == "dense" and len(starts) > 1
    ii_obs, jj_obs = np.nonzero(observed)
    y_obs = Y[ii_obs, jj_obs]

    def advance(st: Start, nfev: int | None) -> _State | None:
        """One rung of a start: (cost, start, converged, full solution or None)."""
        nonlocal count, iters
        if not fast or fs is None:
            sol = refine(st, nfev)
            return None if sol is None else (_cost(sol, loss, fs or 1.0), _as_start(sol), bool(sol.converged), sol)
        count += 1
        report(count)
        try:
            theta, conv, nit = solve_dense_lm(_pack_start(st), y_obs, ii_obs, jj_obs, I, J, dim, offsets, loss,
                                              fs if loss != "linear" else 1.0, nfev, 1e-10, max_it=DENSE_MAX_IT)
        except (np.linalg.LinAlgError, ValueError):
            return None
        iters += nit
        if not np.isfinite(theta).all():
            return None
        nxt = _unpack_start(theta, I, J, dim, offsets)
        with np.errstate(all="ignore"):
            c = _cost_of(np.where(observed, Y - toa_model(*nxt), np.nan), loss, fs or 1.0)
        return (c, nxt, bool(conv), None) if np.isfinite(c) else None

    def advance_many(sts: list[Start], nfev: int | None) -> list[_State | None]:
        """One rung of several starts, in lockstep (:func:`selfcal.toa.engine.batch_lm.solve_batch_lm`:
        each start's iterates are those of its own dense LM, to round-off)."""
        nonlocal count, iters
        if not (fast and BATCH_RACE) or fs is None or len(sts) < 2:
            return [advance(st, nfev) for st in sts]
        count += len(sts)
        Th, conv, nit, fin = solve_batch_lm(np.stack([_pack_start(st) for st in sts]), Y, dim, offsets, loss,
                                            fs if loss != "linear" else 1.0, nfev, 1e-10, max_it=DENSE_MAX_IT)
        iters += int(nit.sum())
        out: list[_State | None] = []
        for k in range(len(sts)):
            if not (fin[k] and np.isfinite(Th[k]).all()):
                out.append(None)
                continue
            nxt = _unpack_start(Th[k], I, J, dim, offsets)
            with np.errstate(all="ignore"):
                c = _cost_of(np.where(observed, Y - toa_model(*nxt), np.nan), loss, fs or 1.0)
            out.append((c, nxt, bool(conv[k]), None) if np.isfinite(c) else None)
        return out

    def state_done(state: _State) -> str | None:
        if state[3] is not None:
            return done(state[3])
        with np.errstate(all="ignore"):
            R = np.where(observed, Y - toa_model(*state[1]), np.nan)
        f = R[np.isfinite(R)]
        return "exact" if f.size and float(np.max(np.abs(f))) <= exact_level else None

    pool: list[_Entry] = []
    nfev = MOVE_NFEV if len(starts) > 1 else max_nfev

    def cap(n: int | None) -> int | None:
        return n if max_nfev is None or n is None else min(n, max_nfev)

    # the first rung of every start (in one batch when the scale is known; the first robust
    # refinement alone, since it sets the scale)
    states: list[_State | None] = []
    if fast and fs is not None:
        states = advance_many([st for _, st in starts], cap(nfev))
    for k, (name, st) in enumerate(starts):
        if count >= nb and pool and not states:
            stopped = "budget"
            break
        state = states[k] if states else advance(st, max_nfev if fs is None else cap(nfev))
        if state is None:
            continue
        history.append((name, state[0]))
        with np.errstate(all="ignore"):
            c_start = _cost_of(np.where(observed, Y - toa_model(*st), np.nan), loss, fs or 1.0)
        pool.append((state[0], k, name, state, c_start if np.isfinite(c_start) else np.inf))
        why = state_done(state)
        if why is not None:
            pool = [pool[-1]]
            stopped = why
            break
    settled: list[tuple[float, int, Start]] = []  # converged starts the race dropped: other minima
    while len(pool) > 1 and stopped == "exhausted":
        if count >= nb:
            stopped = "budget"
        kept = _race_survivors(pool, best_only=count >= nb)
        settled += [(e[0], e[1], e[3][1]) for e in pool if e[3][2] and all(e[1] != k[1] for k in kept)]
        pool = kept
        if all(e[3][2] for e in pool):
            break
        nfev = None if nfev is None else 2 * nfev
        todo = [idx for idx, e in enumerate(pool) if not e[3][2]]
        rung = advance_many([pool[idx][3][1] for idx in todo], cap(nfev))
        for idx, more in zip(todo, rung, strict=True):
            c_old, k, name, state, _ = pool[idx]
            if more is None:  # no further progress: judged as it is
                pool[idx] = (c_old, k, name, (state[0], state[1], True, state[3]), c_old)
                continue
            pool[idx] = (more[0], k, name, more, c_old)
            why = state_done(more)
            if why is not None:
                pool = [pool[idx]]
                stopped = why
                break
    # the winner (lowest cost; the next ones if its full refinement degenerates) refined to the end
    for _c, _, name, state, _ in sorted(pool, key=lambda e: (e[0], e[1])):
        sol = state[3]
        if sol is None or (not sol.converged and stopped not in ("test", "exact")):
            sol = refine(state[1], max_nfev)
        if sol is None:
            continue
        best, best_cost, best_name = sol, _cost(sol, loss, fs or 1.0), name
        why = done(best)
        if why is not None:
            stopped = why
        elif stopped == "budget":
            stopped = "exhausted" if count < nb else "budget"
        break
    if best is None:
        msg = str(last_err.args[0]) if last_err is not None else "no initialiser applies"
        kind = getattr(last_err, "kind", "init-failed")
        raise DegenerateGeometryError(
            f"{msg} (reached from every start tried: {', '.join(n for n, _ in starts) or 'none'}; if the geometry "
            "is fine, the initialisation failed: pass init=(receivers, sources[, offsets]) or add measurements)",
            kind=kind)
    accepted: list[str] = []

    def gain() -> float:
        """Cost decrease a move must bring (ML cost units: half a sum of squares)."""
        sig2 = float(best.sigma) ** 2 if best is not None and np.isfinite(best.sigma) else 0.0
        return max(ACCEPT_REL * best_cost, 0.5 * ACCEPT_CHI2 * sig2)

    if use_moves and not large and stopped == "exhausted":
        obs = np.isfinite(Y)
        improved = True
        while improved and stopped == "exhausted":
            improved = False
            round_best: tuple[float, str, NlsSolution] | None = None
            base = _as_start(best)
            local: list[Move] = []
            for mv in moves(base, obs):
                if _is_local(mv, I, J):
                    local.append(mv)
                    continue
                if count >= nb:
                    stopped = "budget"
                    break
                sol = refine(mv.start, MOVE_NFEV)
                if sol is None:
                    continue
                c = _cost(sol, loss, fs or 1.0)
                if c < best_cost - gain() and (round_best is None or c < round_best[0]):
                    round_best = (c, mv.name, sol)
            # the moves of a few nodes: ranked by a partial refit, the improving ones (disjoint,
            # best first) applied together and refined in full; the best alone if that fails
            screened: list[tuple[float, int, Move, Start]] = []
            for k, mv in enumerate(local if stopped == "exhausted" else []):
                part = refine_part(mv)
                if part is not None and part[0] < best_cost - gain():
                    screened.append((part[0], k, mv, part[1]))
            screened.sort(key=lambda t: (t[0], t[1]))
            tries: list[tuple[str, Start]] = []
            if screened:
                union = _combine(base, [(mv, st) for _, _, mv, st in screened])
                tries.append(union)
                if union[0] != screened[0][2].name:
                    tries.append((screened[0][2].name, screened[0][3]))
            for mname, st in tries:
                if count >= nb:
                    stopped = "budget"
                    break
                sol = refine(st, MOVE_NFEV)
                if sol is None:
                    continue
                c = _cost(sol, loss, fs or 1.0)
                if c < best_cost - gain() and (round_best is None or c < round_best[0]):
                    round_best = (c, mname, sol)
                    break  # the union improved: no need to try the best move alone
            if round_best is not None:
                c, mname, sol = round_best
                if not sol.converged:
                    full = refine(_as_start(sol), max_nfev)
                    if full is not None:
                        c, sol = _cost(full, loss, fs or 1.0), full
                if c < best_cost - gain():
                    best, best_cost = sol, c
                    accepted.append(mname)
                    history.append((mname, c))
                    improved = True
                    why = done(best)
                    if why is not None:
                        stopped = why
    settled.sort(key=lambda e: (e[0], e[1]))
    return SearchOutcome(best, best_name, tuple(accepted), count, iters, float(fs or 1.0), stopped, history,
                         [st for _, _, st in settled[:MINIMA_KEPT]])
