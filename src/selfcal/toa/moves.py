"""The one family of moves of the TOA search: reflect or lift a subset of nodes through a fitted plane.

Local minima of range-only calibration are, almost always, nodes on the wrong side of a
plane that their partners (nearly) span: reflecting a node through that plane changes
its ranges little, so a local refinement does not cross back. Every move here takes a
refined solution, fits a least-squares plane to a reference set of nodes and either
reflects a subset of nodes through it or lifts nodes that lie in it (a saddle: the
out-of-plane gradient vanishes by symmetry) off it, on both sides.

Subsets, in this order (node indices are the search's canonical order, see
:func:`selfcal.toa.search.canonical_order`):

1. each node alone, through the plane of all other nodes (and lifted off it when it lies in it);
2. each receiver with its nearest source, through the plane of the ``2 d + 2`` nodes nearest
   to their midpoint (a microphone and its loudspeaker mirrored together);
3. all receivers through the plane of the sources, and all sources through the plane of
   the receivers;
4. every receiver-source pair of 2. at once (reflected, and moved onto its plane).

Each move is a :class:`Move`: its name, the start ``(receivers, sources,
receiver_offsets, source_offsets)`` and the nodes it moved. The search refines it with
the one engine (:func:`selfcal.toa.engine.nls.refine_toa`): a move of a few nodes first by a
partial refit (only the moved nodes and their offsets free, on the entries that touch
them), which ranks it at a small fraction of a full refinement's cost.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

__all__ = ["Move", "Start", "fit_plane", "moves", "reflect"]

Array = NDArray[np.float64]
Start = tuple[Array, Array, "Array | None", "Array | None"]


class Move(NamedTuple):
    """One candidate of the search: ``name`` (e.g. ``"pair-r2s5"``), its ``start`` and the
    receivers / sources it moved (canonical indices; all of a kind for the collective moves)."""

    name: str
    start: Start
    receivers: tuple[int, ...]
    sources: tuple[int, ...]

#: a node counts as "in the plane" of its partners below this relative distance
IN_PLANE = 1e-6
#: a node lifted off its partners' plane moves this fraction of its median range
LIFT_FRACTION = 0.1


def fit_plane(points: Array) -> tuple[Array, Array, float]:
    """Least-squares plane (a line in 2-D) of (n, d) points: centre, unit normal, RMS thickness."""
    P = np.asarray(points, float)
    c = P.mean(axis=0)
    _, sv, vt = np.linalg.svd(P - c, full_matrices=False)
    thick = float(sv[-1] / np.sqrt(len(P))) if sv.size == P.shape[1] else 0.0
    return c, vt[-1], thick


def reflect(points: Array, centre: Array, normal: Array, fraction: float = 1.0) -> Array:
    """Reflect (``fraction=1``) or project (``0.5``) (n, d) points through a plane."""
    h = (np.asarray(points, float) - centre) @ normal
    return points - 2.0 * fraction * h[..., None] * normal


def _pairs(r: Array, s: Array) -> list[tuple[int, int, Array, Array]]:
    """Each receiver, its nearest source and the plane of the 2d+2 nodes nearest to their midpoint."""
    dim = r.shape[1]
    allpts = np.vstack([r, s])
    I = r.shape[0]
    out: list[tuple[int, int, Array, Array]] = []
    if I + s.shape[0] < 2 * dim + 4:
        return out
    for i in range(I):
        j = int(np.argmin(np.linalg.norm(s - r[i], axis=1)))
        mid = 0.5 * (r[i] + s[j])
        others = np.delete(allpts, [i, I + j], axis=0)
        near = others[np.argsort(np.linalg.norm(others - mid, axis=1), kind="stable")[: 2 * dim + 2]]
        c, n, _ = fit_plane(near)
        out.append((i, j, mid, n))
    return out


#: node-wise moves (1. and 2.) only up to this many nodes: their number grows with the nodes (two
#: or three per node, each a partial refit of O(I + J) entries, ~10-20 ms here), so a round costs
#: O((I + J)^2); at 60 nodes it is ~1 s, the cost of a few full refinements (the bound of the
#: dense solver in selfcal.toa.fit as well). The collective moves always run.
NODEWISE_MAX_NODES = 60


def moves(start: Start, observed: NDArray[np.bool_]) -> Iterator[Move]:
    """Candidate starts from a refined solution, in the fixed order of the module docstring.

    Parameters
    ----------
    start: (receivers (I, d), sources (J, d), receiver_offsets (I,) or None, source_offsets (J,) or None).
    observed: (I, J) bool, the entries used by the fit (for each node's typical range).

    Yields
    ------
    Move; ``name`` says the move, e.g. ``"reflect-r3"``, ``"pair-r2s5"``.
    """
    r0, s0, d0, o0 = start
    r0, s0 = np.asarray(r0, float), np.asarray(s0, float)
    I, dim = r0.shape
    allpts = np.vstack([r0, s0])
    n_all = allpts.shape[0]
    D = np.linalg.norm(r0[:, None] - s0[None], axis=-1)

    def pack(r: Array, s: Array) -> Start:
        return r, s, None if d0 is None else d0.copy(), None if o0 is None else o0.copy()

    J = s0.shape[0]
    every_r, every_s = tuple(range(I)), tuple(range(J))
    nodewise = n_all <= NODEWISE_MAX_NODES
    # 1. single nodes
    for k in range(n_all if nodewise else 0):
        rest = np.delete(allpts, k, axis=0)
        c, n, thick = fit_plane(rest)
        p = allpts[k]
        r, s = r0.copy(), s0.copy()
        tgt, idx, name = (r, k, f"r{k}") if k < I else (s, k - I, f"s{k - I}")
        who = ((idx,), ()) if k < I else ((), (idx,))
        h = float((p - c) @ n)
        span = float(np.sqrt(np.mean(np.sum((rest - c) ** 2, axis=1)))) or 1.0
        if abs(h) > IN_PLANE * span:
            tgt[idx] = p - 2.0 * h * n
            yield Move(f"reflect-{name}", pack(r, s), *who)
        # a node in (or next to) the plane of its partners: lift it off on both sides
        partners = s0[observed[idx]] if k < I else r0[observed[:, idx]]
        if partners.shape[0] > dim:
            pc, pn, pthick = fit_plane(partners)
            ph = float((p - pc) @ pn)
            pspan = float(np.sqrt(np.mean(np.sum((partners - pc) ** 2, axis=1)))) or 1.0
            if pthick <= IN_PLANE * pspan and abs(ph) <= IN_PLANE * pspan:
                row = D[idx][observed[idx]] if k < I else D[:, idx][observed[:, idx]]
                lift = LIFT_FRACTION * float(np.median(row)) if row.size else pspan
                for sign, tag in ((1.0, "+"), (-1.0, "-")):
                    r2, s2 = r0.copy(), s0.copy()
                    (r2 if k < I else s2)[idx] = p + sign * lift * pn
                    yield Move(f"lift{tag}-{name}", pack(r2, s2), *who)
    # 2. receiver + nearest source
    pairs = _pairs(r0, s0)
    for i, j, mid, n in pairs if nodewise else []:
        r, s = r0.copy(), s0.copy()
        r[i] = reflect(r0[i], mid, n)
        s[j] = reflect(s0[j], mid, n)
        yield Move(f"pair-r{i}s{j}", pack(r, s), (i,), (j,))
    # 3. one kind through the plane of the other
    c, n, _ = fit_plane(s0)
    yield Move("reflect-receivers", pack(reflect(r0, c, n), s0.copy()), every_r, ())
    c, n, _ = fit_plane(r0)
    yield Move("reflect-sources", pack(r0.copy(), reflect(s0, c, n)), (), every_s)
    # 4. all pairs at once
    if pairs:
        for fraction, tag in ((1.0, "reflect"), (0.5, "project")):
            r, s = r0.copy(), s0.copy()
            for i, j, mid, n in pairs:
                r[i] = reflect(r0[i], mid, n, fraction)
                s[j] = reflect(s0[j], mid, n, fraction)
            yield Move(f"{tag}-pairs", pack(r, s), tuple(sorted({i for i, *_ in pairs})),
                       tuple(sorted({j for _, j, *_ in pairs})))
