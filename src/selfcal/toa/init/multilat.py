"""MDS + multilateration: receivers by MDS on the eq. 11 distances (003), then every source
by linear multilateration. One of the initialisers of :func:`selfcal.toa.init.mds.initialize_toa`.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..._checks import as_rng, check_dim
from .mds_core import (
    _validated_ranges,
    classical_mds,
    complete_distances,
    estimate_receiver_distances,
    multilaterate,
)

__all__ = ["EQ11_MAX_FLOPS", "mds_multilateration"]

Array = NDArray[np.float64]

# Above this size the O(I^2 J) reverse-triangle estimate stops being cheap next to the rank method.
_EQ11_MAX_FLOPS = 5e7
EQ11_MAX_FLOPS = _EQ11_MAX_FLOPS


def mds_multilateration(ranges: Array, dim: int, *, rng: Any = None,
                        receiver_distances: Array | None = None) -> tuple[Array, Array]:
    """Receivers by MDS on eq. 11, then every source by linear multilateration.

    The reverse-triangle estimate costs ``O(I^2 J)``; above a size cap it uses a random
    subset of the transmitters (the max in eq. 11 only needs a few well-aligned ones).
    Two alternations (receivers multilaterated from the sources, then the sources again)
    remove most of the eq. 11 under-estimation bias. ``receiver_distances``: the completed
    eq. 11 estimate of ``ranges`` over every transmitter (:func:`complete_distances` of
    :func:`estimate_receiver_distances`), when the caller already has it; used below the
    size cap, where it is what this function would compute.

    Returns receivers (I, dim), sources (J, dim).
    """
    dim = check_dim(dim)
    Y = _validated_ranges(ranges, dim)
    I, J = Y.shape
    gen = as_rng(rng)
    cols = np.arange(J)
    max_cols = max(dim + 1, int(_EQ11_MAX_FLOPS // max(1, I * I)))
    if J > max_cols:
        cols = np.sort(gen.choice(J, size=max_cols, replace=False))
    if receiver_distances is not None and cols.size == J:
        D_hat = np.asarray(receiver_distances, float)
    else:
        D_hat = complete_distances(estimate_receiver_distances(Y[:, cols]))
    receivers = classical_mds(D_hat, dim)
    sources = multilaterate(receivers, Y.T)
    for _ in range(2):
        receivers = multilaterate(sources, Y)
        sources = multilaterate(receivers, Y.T)
    return receivers, sources
