"""Orientation check of a far-field matrix: rows must be receivers, columns transmitters."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from ..errors import InputError
from .degeneracy import RANK_ALPHA, _sigma_null, rank_threshold, top_svd

__all__ = ["check_orientation", "orientation_statistics"]

Array = NDArray[np.float64]


def orientation_statistics(D: Array, *, rank: int = 3, noise_std: float | None = None,
                           alpha: float = RANK_ALPHA) -> dict[str, float]:
    """The two readings of a complete far-field matrix, each tested at model rank ``rank``.

    Given reading (rows = receivers): the column-centred matrix ``D - 1 mean_i D_ij`` is of
    rank <= ``rank`` under the far-field model; transposed reading (rows = transmitters): the
    row-centred matrix is. For each, ``s_{rank+1}`` and its threshold from the nested rank
    test (:func:`~selfcal.tdoa.degeneracy.rank_threshold`, "rank >= rank + 1" against
    "rank <= rank", false-alarm ``alpha``; degrees of freedom ``(m - 1) x k`` and
    ``m x (k - 1)``).

    Parameters
    ----------
    D : (m, k) complete far-field matrix (metres).
    rank : model rank (3 in space, 2 in a plane); noise_std : known noise (metres) or None;
    alpha : false-alarm rate of each test.

    Returns
    -------
    dict with ``s_given``, ``thr_given``, ``s_transposed``, ``thr_transposed`` (metres) and
    ``decidable`` (1.0, or 0.0 when one reading has too few degrees of freedom to estimate the
    noise under its null and no ``noise_std`` is given: both thresholds are then the numerical
    rank, ``1e-9 s_1``).
    """
    D = np.asarray(D, dtype=float)
    m, k = D.shape
    q = rank + 1
    Xc = D - D.mean(axis=0, keepdims=True)
    Xr = D - D.mean(axis=1, keepdims=True)
    svd_c, svd_r = top_svd(Xc, q), top_svd(Xr, q)
    sc = float(svd_c[1][rank]) if len(svd_c[1]) > rank else 0.0
    sr = float(svd_r[1][rank]) if len(svd_r[1]) > rank else 0.0
    # where one reading has too few degrees of freedom to estimate the noise under its null, the
    # two readings cannot be compared at the same level: both fall back to the numerical rank
    # (only exactly transposed data are then named)
    known = noise_std is not None or (_sigma_null(Xc, *svd_c, q, m - 1, k) is not None
                                      and _sigma_null(Xr, *svd_r, q, m, k - 1) is not None)
    tc = rank_threshold(Xc, q, rows=m - 1, cols=k, noise_std=noise_std, alpha=alpha, svd=svd_c)
    tr = rank_threshold(Xr, q, rows=m, cols=k - 1, noise_std=noise_std, alpha=alpha, svd=svd_r)
    if not known:
        tc = 1e-9 * float(svd_c[1][0])
        tr = 1e-9 * float(svd_r[1][0])
    return {"s_given": sc, "thr_given": tc, "s_transposed": sr, "thr_transposed": tr, "decidable": float(known)}


def check_orientation(D: Array, *, noise_std: float | None = None, rank: int = 3,
                      alpha: float = RANK_ALPHA) -> None:
    """Refuse a far-field matrix that looks transposed (rows = transmitters): ``InputError``.

    Far-field data ``D = Z N^T + 1 c^T`` carry one offset per *column*: removing the column
    means leaves a matrix of rank <= ``rank`` (3 in space), while its transpose
    ``N Z^T + c 1^T`` keeps the rank-1 offset term after column centring (rank ``rank + 1``)
    and loses it only after row centring. The matrix is named transposed when the given
    reading does not fit the far-field model at rank ``rank`` and the transposed reading
    does: ``s_{rank+1}`` of the column-centred matrix is signal and that of the row-centred
    matrix is not, both by the nested rank test of :mod:`~selfcal.tdoa.degeneracy`
    (:func:`orientation_statistics`: noise ``noise_std`` or estimated under the smaller
    model, Tracy-Widom / Monte-Carlo quantile at false-alarm ``alpha``). A correct matrix is
    named only when its column-centred ``s_{rank+1}`` is a false alarm (probability <=
    ``alpha``) *and* its offsets leave no trace after row centring (measured over random
    arrays in the tests). A column that is exactly constant while no row is (a reference
    receiver gives a constant *row*: the Pyramic layout) is named too: in the far-field model
    it would be a transmitter orthogonal to the whole array.

    Only complete matrices are tested (NaN: the check passes); where too few degrees of
    freedom remain to estimate the noise (e.g. 5 x 7 at rank 3), the numerical rank decides,
    so only (nearly) exact transposed data are named there.

    Parameters
    ----------
    D : (m, k) relative distances (metres), NaN = missing.
    noise_std : known per-entry noise standard deviation (metres) or None.
    rank : rank of the position/direction factorisation (3 in space, 2 in a plane).
    alpha : false-alarm rate of each rank test (:data:`~selfcal.tdoa.degeneracy.RANK_ALPHA`).

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
    st = orientation_statistics(D, rank=rank, noise_std=noise_std, alpha=alpha)
    if st["s_given"] > st["thr_given"] and st["s_transposed"] <= st["thr_transposed"]:
        raise InputError(
            f"matrix ({m} x {k}) does not have the far-field structure with one offset per column "
            f"(singular value {rank + 1} after removing column means {st['s_given']:.3g} > noise threshold "
            f"{st['thr_given']:.3g}) but has it with one offset per row ({st['s_transposed']:.3g} <= "
            f"{st['thr_transposed']:.3g}): is it transposed? Rows must be receivers, columns transmitters "
            f"(try the {k} x {m} transpose)")
