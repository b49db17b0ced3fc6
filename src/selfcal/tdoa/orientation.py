"""Orientation check of a far-field matrix: rows must be receivers, columns transmitters."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from ..errors import InputError
from ..robust import mad_std
from .degeneracy import top_svd

__all__ = ["check_orientation"]

Array = NDArray[np.float64]


def _noise_from_double_centred(D: Array, rank: int) -> float:
    """Robust per-entry noise level of a complete matrix from its double-centred rank-r residual.

    Both orientations of far-field data (``Z N^T + 1 c^T`` and its transpose) are of rank
    ``r`` once row and column means are removed, so this estimate does not depend on the
    orientation: 1.4826 median |R| x sqrt(entries / dof), dof = (m-1-r)(k-1-r).
    """
    X = D - D.mean(axis=0, keepdims=True)
    X = X - X.mean(axis=1, keepdims=True)
    U, s, Vt = top_svd(X, rank)
    R = X - (U[:, :rank] * s[:rank]) @ Vt[:rank]
    dof = (D.shape[0] - 1 - rank) * (D.shape[1] - 1 - rank)
    return float(mad_std(R, centre=False) * np.sqrt(R.size / max(dof, 1)))


def check_orientation(D: Array, *, noise_std: float | None = None, rank: int = 3,
                      rank_factor: float = 1.5) -> None:
    """Refuse a far-field matrix that looks transposed (rows = transmitters): ``InputError``.

    Far-field data ``D = Z N^T + 1 c^T`` carry one offset per *column*: removing the column
    means leaves a matrix of rank <= ``rank`` (3 in space), while its transpose
    ``N Z^T + c 1^T`` keeps the rank-1 offset term after column centring (rank ``rank + 1``)
    and loses it only after row centring. The (rank+1)-th singular value of each centred
    matrix is compared with the Marchenko-Pastur edge ``sigma (sqrt(rows - 1) + sqrt(cols))``
    of an i.i.d. noise matrix, times ``rank_factor`` (the same noise-aware threshold as
    :func:`~selfcal.tdoa.analyse_degeneracy`; sigma = ``noise_std`` or the robust estimate
    of the double-centred rank-r residual, valid in both orientations). Significant after
    column centring but not after row centring -> transposed. A column that is exactly
    constant while no row is (a reference receiver gives a constant *row*: the Pyramic
    layout) is named too: in the far-field model it would be a transmitter orthogonal to
    the whole array.

    Only complete matrices with at least ``rank + 2`` rows and columns are tested (the test
    needs a (rank+1)-th singular value); others pass silently.

    Parameters
    ----------
    D : (m, k) relative distances (metres), NaN = missing.
    noise_std : known per-entry noise standard deviation (metres) or None.
    rank : rank of the position/direction factorisation (3 in space, 2 in a plane).

    Raises
    ------
    InputError
        When the matrix looks transposed; the message says "transposed?".

    Examples
    --------
    >>> import numpy as np
    >>> rng = np.random.default_rng(0)
    >>> Z, N = rng.normal(size=(10, 3)), rng.normal(size=(30, 3))
    >>> N /= np.linalg.norm(N, axis=1, keepdims=True)
    >>> D = Z @ N.T + rng.normal(size=30)
    >>> check_orientation(D)          # fine
    >>> check_orientation(D.T)        # doctest: +IGNORE_EXCEPTION_DETAIL
    Traceback (most recent call last):
    InputError: ... transposed? ...
    """
    D = np.asarray(D, dtype=float)
    m, k = D.shape
    if not np.isfinite(D).all():
        return
    scale = float(np.max(np.abs(D - D.mean(axis=0)))) + 1e-300
    const_col = np.ptp(D, axis=0) <= 1e-12 * scale
    const_row = np.ptp(D, axis=1) <= 1e-12 * scale
    if const_col.any() and not const_row.any() and not const_col.all():
        j = int(np.flatnonzero(const_col)[0])
        raise InputError(
            f"matrix ({m} x {k}): column {j} is constant, which in the far-field model is a transmitter "
            "orthogonal to the whole array, while a reference receiver gives a constant row: is the matrix "
            f"transposed? (rows must be receivers, columns transmitters; try the {k} x {m} transpose)")
    if min(m, k) < rank + 2:
        return
    sigma = noise_std if noise_std is not None else _noise_from_double_centred(D, rank)
    sigma = max(float(sigma), 1e-14 * scale)
    sc = top_svd(D - D.mean(axis=0, keepdims=True), rank + 1)[1]
    sr = top_svd(D - D.mean(axis=1, keepdims=True), rank + 1)[1]
    thr_c = rank_factor * sigma * (np.sqrt(m - 1) + np.sqrt(k))
    thr_r = rank_factor * sigma * (np.sqrt(m) + np.sqrt(k - 1))
    if sc[rank] > thr_c and sr[rank] <= thr_r:
        raise InputError(
            f"matrix ({m} x {k}) does not have the far-field structure with one offset per column "
            f"(singular value {rank + 1} after removing column means {sc[rank]:.3g} > noise threshold "
            f"{thr_c:.3g}) but has it with one offset per row ({sr[rank]:.3g} <= {thr_r:.3g}): is it "
            f"transposed? Rows must be receivers, columns transmitters (try the {k} x {m} transpose)")
