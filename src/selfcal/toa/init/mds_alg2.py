"""003 Algorithm 2: MDS on the eq. 11 receiver distances, then one extended MDS per source.

Each source's extended MDS (eq. 13) is aligned to the receivers by Procrustes (eq. 14-15);
sources with the same observation pattern are batched. One of the initialisers of
:func:`selfcal.toa.init.mds.initialize_toa`.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from ..._checks import check_dim
from ...geometry import align
from .mds_core import (
    _double_centre,
    _top_eig_coords,
    _validated_ranges,
    classical_mds,
    complete_distances,
    estimate_receiver_distances,
    multilaterate,
)

__all__ = ["mds_alg2"]

Array = NDArray[np.float64]


# ---------------------------------------------------------------------------------------
# Algorithm 2
# ---------------------------------------------------------------------------------------


def _procrustes_stack(X: Array, Y: Array) -> tuple[Array, Array]:
    """Batched orthogonal Procrustes (reflection allowed), 003 eq. 14.

    X, Y: (B, n, d). Returns R (B, d, d), t (B, d) minimising ``sum |Y - (X R^T + t)|^2``.
    """
    a = align(X, Y, reflection=True)  # the one Procrustes (selfcal.geometry)
    return a.rotation, a.translation


def _alg2_sources(D_hat: Array, receivers: Array, Y: Array, dim: int) -> Array:
    """Steps 3-7 of 003 Algorithm 2 for every source, batched by observation pattern."""
    I, J = Y.shape
    obs = ~np.isnan(Y)
    sources = np.full((J, dim), np.nan)
    patterns, inverse = np.unique(obs.T, axis=0, return_inverse=True)
    inverse = np.asarray(inverse).ravel()
    for p, pattern in enumerate(patterns):
        cols = np.flatnonzero(inverse == p)
        rows = np.flatnonzero(pattern)
        n = rows.size
        if n < dim + 1:
            continue  # located afterwards by multilateration (or not at all)
        # eq. 13: extended distance matrix, the source as the last point
        Dk = np.zeros((cols.size, n + 1, n + 1))
        Dk[:, :n, :n] = D_hat[np.ix_(rows, rows)]
        Dk[:, :n, n] = Y[np.ix_(rows, cols)].T
        Dk[:, n, :n] = Dk[:, :n, n]
        coords = _top_eig_coords(_double_centre(Dk**2), dim)  # (B, n+1, d)
        ref = np.broadcast_to(receivers[rows], (cols.size, n, dim))
        R, t = _procrustes_stack(coords[:, :n], ref)
        sources[cols] = np.einsum("bij,bj->bi", R, coords[:, n]) + t  # eq. 15
    return sources


def mds_alg2(ranges: Array, dim: int, *, receiver_distances: Array | None = None) -> tuple[Array, Array]:
    """003 Algorithm 2: MDS initialisation of receivers and sources.

    1. ``D_hat`` from eq. 11 (:func:`estimate_receiver_distances`); pairs that share no
       source are completed by shortest paths (:func:`complete_distances`).
    2. Receivers ``s_MDS`` = :func:`classical_mds` of ``D_hat``.
    3.-7. For each source k: MDS of the extended matrix ``D_hat_k`` (eq. 13) that appends the
       measured ranges ``y_k``; align its receiver part to ``s_MDS`` (eq. 14, reflection
       allowed since MDS is defined up to an isometry) and map the source with it (eq. 15).

    Sources with missing ranges use only the receivers that observed them; sources seen by
    fewer than ``dim + 1`` receivers are placed by linear multilateration (least norm).

    Parameters
    ----------
    ranges: (I, J) metres, rows = receivers, NaN = missing.
    dim: 2 or 3.
    receiver_distances: ``D_hat`` of step 1 when the caller already has it (I, I).

    Returns
    -------
    receivers (I, dim), sources (J, dim), in the frame of ``s_MDS``.
    """
    dim = check_dim(dim)
    Y = _validated_ranges(ranges, dim)
    D_hat = complete_distances(estimate_receiver_distances(Y)) if receiver_distances is None \
        else np.asarray(receiver_distances, float)
    receivers = classical_mds(D_hat, dim)
    sources = _alg2_sources(D_hat, receivers, Y, dim)
    lost = np.isnan(sources).any(axis=1)
    if lost.any():
        sources[lost] = multilaterate(receivers, Y[:, lost].T)
    return receivers, sources
