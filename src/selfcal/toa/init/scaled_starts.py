"""Random starts at the scale the data bound, for networks where no initialiser identifies the offsets.

With both kinds of offsets and few nodes (12 receivers x 6 sources in 3-D: 16 rank-d
equations for 17 offsets, see :func:`selfcal.toa.init.rank3_model.check_rank_identifiable`) the
004 rank-d method leaves the offsets a one-parameter family, and the 003 initialisers
(MDS on offset-free ranges) have no information about offsets of metres. What the data do
bound are the distances: for receivers i, l and sources j, k the double difference

    t_ij - t_lj - t_ik + t_lk = (|r_i - s_j| - |r_l - s_j|) - (|r_i - s_k| - |r_l - s_k|)

is free of every offset and at most ``2 |r_i - r_l|`` (triangle inequality), likewise
``2 |s_j - s_k|`` with the roles swapped. :func:`scaled_random_starts` draws Gaussian
positions whose pairwise distances have the RMS of those lower bounds (in d dimensions
``E|x - y|^2 = 2 d std^2``) and least-squares offsets for them; the search refines each
with the one engine and keeps the lowest ML cost.

The same double difference is also at most ``2 |s_j - s_k|``: the bound of one set
saturates at the extent of the other, so the larger of the two sets (sources around a
compact array, or receivers around a few sources) is bounded only from below, by about the
smaller set's size, and nothing in the offset-free data bounds it from above (a distant
node's range is absorbed by its offset: the far-field degeneracy). The starts therefore
spread the scale of one set at a time geometrically, :data:`SCALE_FACTORS` (one octave
apart, both sets in turn since the data do not say which one is the larger): measured on
the 12 x 6 scene (10 starts each, refined to convergence), the share of starts reaching the
truth-started minimum went from 0-3 of 10 at the bounds' scale to 4-7 of 10 with the
sources 4 times larger on four of five hard draws.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from ..engine.model import least_squares_offsets
from ..moves import Start

__all__ = ["SCALE_FACTORS", "distance_lower_bounds", "scaled_random_starts"]

Array = NDArray[np.float64]

#: (receiver factor, source factor) of the successive starts, cycled: the bounds' scale, then
#: one set at a time 2, 4, 8 times larger (module docstring)
SCALE_FACTORS = ((1.0, 1.0), (1.0, 2.0), (2.0, 1.0), (1.0, 4.0), (4.0, 1.0), (1.0, 8.0), (8.0, 1.0), (2.0, 2.0))


def distance_lower_bounds(Y: Array) -> Array:
    """Offset-free lower bounds on the distances between the rows' nodes, (I, I), metres.

    ``B_il = (max_j (y_ij - y_lj) - min_j (y_ij - y_lj)) / 2 <= |r_i - r_l|`` for the model
    ``y_ij = |r_i - s_j| + d_i + o_j`` (noise-free); missing entries are skipped. Apply it
    to ``Y.T`` for the sources.

    Examples
    --------
    >>> import numpy as np
    >>> r = np.array([[0.0, 0.0], [1.0, 0.0]]); s = np.array([[-5.0, 0.0], [5.0, 0.0]])
    >>> Y = np.linalg.norm(r[:, None] - s[None], axis=-1) + 3.0
    >>> float(distance_lower_bounds(Y)[0, 1])
    1.0
    """
    X = Y[:, None, :] - Y[None, :, :]
    with np.errstate(all="ignore"):
        B = (np.nanmax(X, axis=-1) - np.nanmin(X, axis=-1)) / 2.0
    return np.where(np.isfinite(B), B, 0.0)


def _coordinate_std(B: Array, dim: int) -> float:
    n = B.shape[0]
    iu = np.triu_indices(n, 1)
    return float(np.sqrt(np.mean(B[iu] ** 2) / (2 * dim))) if iu[0].size else 0.0


def scaled_random_starts(Y: Array, dim: int, offsets: str, rng: np.random.Generator, n: int = 8) -> list[Start]:
    """``n`` random starts (receivers, sources, offsets) at the scale of the distance bounds.

    Parameters
    ----------
    Y : (I, J) ranges, metres, NaN = missing.
    dim : 2 or 3.
    offsets : the offset model (the starting offsets are its least-squares offsets).
    rng : the search's Generator.
    n : number of starts; start k has the scales of ``SCALE_FACTORS[k % 8]``.

    Returns
    -------
    list of (receivers (I, d), sources (J, d), receiver_offsets, source_offsets) starts;
    empty when the bounds are all zero (no spread in the data).

    Notes
    -----
    The bounds underestimate (measured on the 12 x 6 scene of ``benchmarks/bench_toa_minimal.py``:
    60-80 % of the true receiver distances, 20-30 % of the source distances); every start is
    refined to a local minimum, so the scale only has to put the starts in the right region.
    """
    sr = _coordinate_std(distance_lower_bounds(Y), dim)
    ss = _coordinate_std(distance_lower_bounds(Y.T), dim)
    if not (sr > 0 or ss > 0):
        return []
    sr, ss = sr or ss, ss or sr
    I, J = Y.shape
    out: list[Start] = []
    for k in range(int(n)):
        fr, fs = SCALE_FACTORS[k % len(SCALE_FACTORS)]
        r0 = rng.normal(0.0, sr * fr, (I, dim))
        s0 = rng.normal(0.0, ss * fs, (J, dim))
        d0, o0 = least_squares_offsets(Y, r0, s0, offsets)
        out.append((r0, s0, d0, o0))
    return out
