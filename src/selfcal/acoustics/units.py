"""A start for the TOA search from the units: a microphone and a loudspeaker in one housing.

A conference unit (004 sec. 2.2) holds microphone ``i`` and loudspeaker ``j`` a few
centimetres apart (5-15 cm; a gooseneck 30-50 cm). The recording directory says which:
a receiver and a sender with the same name. The blind search does not know it; the
pipeline does, and it gives a start that needs no search at all:

with ``r_k ~ s_k = p_k`` for the K units, the two-way sum of a pair of units cancels all
offsets (two-way ranging),

    c (t_kl + t_lk - t_kk - t_ll) / 2 = |p_k - p_l| + O(unit size),

(004 eq. 3.1 twice; ``t_kk`` is a unit hearing its own loudspeaker: ``delta_k + tau_k`` plus
a few centimetres). Classical MDS of these distances
(:func:`selfcal.toa.init.mds.classical_mds`) places the units up to a rigid motion and a
reflection, both gauge freedoms of the TOA model; the offsets follow by least squares
(:func:`selfcal.toa.engine.model.least_squares_offsets`). The start is wrong by about the unit
size, far inside the basin of the truth, and goes to :func:`selfcal.toa.solve_toa` as the
first start of its search (which keeps the lowest cost of all its starts).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

__all__ = ["unit_pairs", "unit_start"]

Array = NDArray[np.float64]


def unit_pairs(receivers: tuple[str, ...] | list[str], senders: tuple[str, ...] | list[str]) -> NDArray[np.intp]:
    """(K, 2) indices ``(receiver, sender)`` of the units: a receiver and a sender with the same name.

    Parameters
    ----------
    receivers, senders : sequences of str
        Names from setup.json.

    Returns
    -------
    (K, 2) int array
        Empty (0, 2) when no name is shared.
    """
    where = {n: j for j, n in enumerate(senders)}
    pairs = [(i, where[n]) for i, n in enumerate(receivers) if n in where]
    return np.array(pairs, dtype=np.intp).reshape(-1, 2)


def unit_start(T: Array, pairs: NDArray[np.intp], speed: float, dim: int, *,
               rng: int = 0) -> tuple[Array, Array, Array, Array] | None:
    """Start ``(receivers, sources, receiver_offsets, source_offsets)`` from two-way unit distances.

    Parameters
    ----------
    T : (I, J) array
        TOA matrix, s (NaN = missing).
    pairs : (K, 2) int array
        ``(receiver, sender)`` of every unit (:func:`unit_pairs`).
    speed : float
        m/s.
    dim : int
        2 or 3.
    rng : int
        Unused (the microphone is split from its loudspeaker, where the model's gradient is
        undefined, along a direction the geometry fixes; kept for the signature).

    Returns
    -------
    tuple or None
        Positions (I, dim) and (J, dim) in metres, offsets (I,), (J,) in seconds; None when
        the units do not cover every receiver and sender, or fewer than ``dim + 2`` of their
        two-way sums are observed.

    Examples
    --------
    >>> import numpy as np
    >>> g = np.random.default_rng(0)
    >>> p = g.uniform(0, 8, (8, 3)); q = p + g.normal(0, 0.05, (8, 3))
    >>> T = np.linalg.norm(q[:, None] - p[None], axis=-1) / 343.0 + g.uniform(0, 0.02, (8, 1))
    >>> r0, s0, dr, ds = unit_start(T, np.column_stack([np.arange(8)] * 2), 343.0, 3)
    >>> r0.shape, s0.shape
    ((8, 3), (8, 3))
    """
    from ..toa.engine.model import least_squares_offsets
    from ..toa.init.mds import classical_mds, complete_distances

    T = np.asarray(T, float)
    I, J = T.shape
    pairs = np.asarray(pairs, dtype=np.intp).reshape(-1, 2)
    K = len(pairs)
    if K < dim + 2 or len(set(pairs[:, 0])) != I or len(set(pairs[:, 1])) != J:
        return None
    A = T[np.ix_(pairs[:, 0], pairs[:, 1])]
    diag = np.diag(A)
    two_way = 0.5 * speed * (A + A.T - diag[:, None] - diag[None, :])
    D = np.abs(two_way)
    np.fill_diagonal(D, 0.0)
    if np.isfinite(D[~np.eye(K, dtype=bool)]).sum() < 2 * (dim + 2):
        return None
    if not np.isfinite(D).all():
        D = complete_distances(np.where(np.isfinite(D), D, np.nan))
        if not np.isfinite(D).all():
            return None
    P = classical_mds(D, dim)
    # each microphone 5 cm (the smallest unit of 004) from its loudspeaker, away from the units'
    # centroid: a direction fixed by the geometry, not by the units' numbering, so the start (and
    # the fit) is equivariant under relabelling and rigid motions
    out = P - P.mean(axis=0)
    norm = np.linalg.norm(out, axis=1, keepdims=True)
    axis = np.eye(dim)[0]  # a unit at the centroid itself: any fixed direction will do
    split = 0.05 * np.where(norm > 0, out / np.where(norm > 0, norm, 1.0), axis)
    r = np.empty((I, dim))
    s = np.empty((J, dim))
    r[pairs[:, 0]] = P + split
    s[pairs[:, 1]] = P
    a, b = least_squares_offsets(speed * T, r, s, "both")
    assert a is not None and b is not None
    return r, s, a / speed, b / speed
