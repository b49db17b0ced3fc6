"""Measured data that are not clean: gross entries, outliers, nodes with too few ranges.

The rules here are statistical or counting arguments, never tuned on a data set:

- :func:`gross_entries`: entries so far from a robust two-way (median-polish) fit of the
  matrix that no initialiser should see them (Tukey's "far out" fence, 3 IQR beyond the
  quartiles). A 1e300 typo is one; they are excluded from the search and re-judged by
  :func:`outlier_mask` against the fitted model at the end.
- :func:`noise_scale`: normal-consistent MAD of residuals
  (:func:`scipy.stats.median_abs_deviation`).
- :func:`outlier_mask`: ``|t_ij| > k s`` for the studentized residuals
  ``t = r / sqrt(1 - h)`` (:func:`selfcal.toa.verdict.leverage.leverages`,
  :func:`selfcal.toa.verdict.leverage.studentized`), ``s`` the given noise
  or the MAD of t, ``k = Phi^-1(1 - alpha / (2 m))`` (Bonferroni over the m measurements:
  under Gaussian noise the probability that any inlier is flagged is at most ``alpha``).
- :func:`drop_unidentifiable`: nodes with fewer ranges than their unknowns + 1, removed
  iteratively (removing a source lowers its receivers' counts).

The leverages and the one linearisation the checks share are in
:mod:`selfcal.toa.verdict.leverage`; the high-breakdown start of the outlier rule in
:mod:`selfcal.toa.verdict.high_breakdown`.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..._checks import check_toa_counts
from ...errors import DegenerateGeometryError

__all__ = ["OUTLIER_ALPHA", "TUKEY_FAR", "canonical_order", "drop_unidentifiable", "gross_entries", "noise_scale",
           "outlier_mask", "outlier_threshold", "required_ranges", "screened"]

Array = NDArray[np.float64]
Mask = NDArray[np.bool_]

#: family-wise probability of flagging any inlier as an outlier (Gaussian noise)
OUTLIER_ALPHA = 0.01
#: Tukey's "far out" fence in interquartile ranges beyond the quartiles
TUKEY_FAR = 3.0


def _nanmedian_rows(R: Array) -> Array:
    """Row medians ignoring NaN, equal to ``np.nanmedian(R, axis=1)`` (NaN for an all-NaN row).

    One vectorised sort of the rows (NaN sort last) and the middle one or two finite
    entries of each: ``np.nanmedian`` loops over the rows in Python above 600 columns
    (``apply_along_axis``; 2.6 s of the 1000 x 1000 median polish, 20 calls).
    """
    S = np.sort(R, axis=1)
    n = R.shape[1] - np.isnan(R).sum(axis=1)
    lo = np.take_along_axis(S, np.maximum((n - 1) // 2, 0)[:, None], axis=1)[:, 0]
    hi = np.take_along_axis(S, (n // 2)[:, None], axis=1)[:, 0]  # n // 2 <= n - 1 when n >= 1
    with np.errstate(invalid="ignore"):
        med = (lo + hi) / 2
    med[n == 0] = np.nan
    return med


def _median_polish(Y: Array, iterations: int = 10) -> Array:
    """Residuals of Tukey's median polish ``y_ij ~ m + a_i + b_j`` over the observed entries.

    Stops early at a fixed point (every row and column median exactly 0: further sweeps
    would change nothing), so the result equals that of all ``iterations`` sweeps.
    """
    R = np.array(Y, dtype=float)
    if R.size == 0:
        return R
    with np.errstate(all="ignore"):
        for _ in range(iterations):
            a = _nanmedian_rows(R)
            a = np.where(np.isfinite(a), a, 0.0)
            R = R - a[:, None]
            b = _nanmedian_rows(R.T)
            b = np.where(np.isfinite(b), b, 0.0)
            R = R - b[None, :]
            if not a.any() and not b.any():
                break
    return R


def gross_entries(Y: Array) -> Mask:
    """Entries beyond Tukey's far-out fence of the median-polish residuals (I, J) bool.

    The additive part ``a_i + b_j`` absorbs offsets and the typical range of each node;
    what is left has the geometric spread of the network. An entry more than 3 IQR beyond
    the quartiles of those residuals (a typo, 1e300, a reflection many times longer than
    the room) is excluded before any initialiser runs. The spread used is the IQR of the
    residuals plus that of the entries (the residuals' quartiles collapse on small
    matrices, where median polish zeroes a large share of them; over 2000 clean draws of
    5-9 nodes the largest clean entry reached 2.5 of the 3 spreads). The rule is deliberately loose: the
    final :func:`outlier_mask` re-judges every entry against the fitted model.
    """
    obs = np.isfinite(Y)
    if obs.sum() < 4:
        return np.zeros(Y.shape, bool)
    # scale down first so that 1e300 entries cannot overflow in the medians' arithmetic
    big = float(np.nanmax(np.abs(Y)))
    Z = Y / big if big > 0 else Y
    R = _median_polish(Z)
    v = R[obs]
    q1, q3 = np.percentile(v, [25, 75])
    # median polish zeroes at least one residual per row and column, so on a small matrix
    # the quartiles of its residuals collapse (5 x 5: 9 exact zeros of 25) and clean
    # entries fell outside the fence (half of 2000 clean 5-9 node draws); the spread of the
    # entries themselves, which bounds what a geometry leaves in the residuals, is added
    z1, z3 = np.percentile(Z[obs], [25, 75])
    iqr = (q3 - q1) + (z3 - z1)
    if not iqr > 0:
        return np.zeros(Y.shape, bool)
    lo, hi = q1 - TUKEY_FAR * iqr, q3 + TUKEY_FAR * iqr
    return obs & ((R < lo) | (R > hi))


def noise_scale(residuals: Array, floor: float = 0.0) -> float:
    """Normal-consistent MAD of the finite residuals (``scipy.stats.median_abs_deviation(f,
    scale="normal")``: ``median|f - median f| / Phi^-1(3/4)``, the same operations without its
    array-API dispatch)."""
    f = np.asarray(residuals, float)
    f = f[np.isfinite(f)]
    if f.size == 0:
        return float("nan")
    mad = np.median(np.abs(f - np.median(f))) / _NORMAL_MAD
    return max(float(mad), float(floor))


#: ``scipy.special.ndtri(0.75)``, the constant of ``median_abs_deviation(scale="normal")``
_NORMAL_MAD = 0.6744897501960817


def outlier_threshold(m: int, alpha: float = OUTLIER_ALPHA, dof: int | None = None) -> float:
    """``k = Phi^-1(1 - alpha / (2 m))``: Bonferroni two-sided normal quantile for m measurements.

    With ``dof`` (the scale was estimated from residuals with that many degrees of freedom)
    Student's t quantile with ``dof`` degrees of freedom instead: a studentized residual over
    an estimated scale is t-distributed under Gaussian noise (the normal quantile for dof -> oo).
    """
    from scipy.stats import norm, t

    a = alpha / (2.0 * max(int(m), 1))
    return float(norm.isf(a) if dof is None else t.isf(a, max(int(dof), 1)))


def outlier_mask(residuals: Array, scale: float, alpha: float = OUTLIER_ALPHA, dof: int | None = None) -> Mask:
    """Entries with ``|r_ij| > k scale``, ``k`` from :func:`outlier_threshold` (NaN -> False)."""
    R = np.asarray(residuals, float)
    fin = np.isfinite(R)
    k = outlier_threshold(int(fin.sum()), alpha, dof)
    with np.errstate(invalid="ignore"):
        return fin & (np.abs(np.where(fin, R, 0.0)) > k * scale)


def required_ranges(dim: int, own_offset: bool) -> int:
    """Ranges a node needs: its ``dim (+1)`` unknowns plus one redundant range.

    With exactly ``dim`` ranges (``dim + 1`` with an offset) a node sits at one of the
    (generically two) intersections of its spheres: locally determined but with a mirror
    ambiguity and no redundancy to test it; one more range resolves both.
    """
    return int(dim) + int(own_offset) + 1


def drop_unidentifiable(observed: Mask, dim: int, offsets: str) -> tuple[Mask, Mask]:
    """Receivers and sources kept after iteratively removing nodes with too few ranges.

    Returns boolean keep-masks (I,), (J,). A node is removed while its count of observed
    ranges to kept partners is below :func:`required_ranges`.
    """
    has_r, has_s = offsets in ("receivers", "both"), offsets in ("sources", "both")
    need_r, need_s = required_ranges(dim, has_r), required_ranges(dim, has_s)
    keep_r = np.ones(observed.shape[0], bool)
    keep_s = np.ones(observed.shape[1], bool)
    while True:
        sub = observed & keep_r[:, None] & keep_s[None, :]
        bad_r = keep_r & (sub.sum(axis=1) < need_r)
        bad_s = keep_s & (sub.sum(axis=0) < need_s)
        if not bad_r.any() and not bad_s.any():
            return keep_r, keep_s
        keep_r &= ~bad_r
        keep_s &= ~bad_s


def canonical_order(Y: Array) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
    """Permutations (rows, columns) that sort a matrix into an order independent of numbering.

    Key of a row: its median over the observed entries, then its sorted entries (NaN last),
    lexicographically; columns alike. Rows that tie on the whole key are identical up to
    the order of their entries; the stable sort keeps their given order.

    Examples
    --------
    >>> import numpy as np
    >>> Y = np.array([[3.0, 1.0], [1.0, 2.0], [2.0, 2.0]])
    >>> [int(i) for i in canonical_order(Y)[0]]  # medians 2, 1.5, 2; rows 0 and 2 tie, then [1, 3] < [2, 2]
    [1, 0, 2]
    """
    def order(M: Array) -> NDArray[np.intp]:
        med = _nanmedian_rows(M)  # = np.nanmedian(M, axis=1), vectorised above 600 columns
        srt = np.sort(M, axis=1)  # NaN sort last
        # the keys as rows of one array, the last row the primary key: the median, then the
        # sorted entries from the first (lexsort sorts by the last key first)
        keys = np.vstack([np.where(np.isfinite(srt), srt, np.inf)[:, ::-1].T, np.where(np.isfinite(med), med, np.inf)])
        return np.lexsort(keys).astype(np.intp)

    return order(Y), order(Y.T)


def screened(Y: Array, dim: int, offsets: str) -> tuple[Any, ...]:
    """Steps 1-3 of :func:`selfcal.toa.fit.finish` on ranges ``Y`` (metres): ``(pr, pc, Yc, gross, used, keep_r, keep_s)``.

    ``Yc`` is ``Y`` in canonical order (rows ``pr``, columns ``pc``), ``gross`` its
    numerically absurd entries, ``used`` the observed ones less those, ``keep_r`` /
    ``keep_s`` the identifiable nodes; the search's matrix is ``Yc`` on ``used``, those nodes.
    """
    pr, pc = canonical_order(Y)
    Yc = Y[np.ix_(pr, pc)]
    obs = np.isfinite(Yc)
    # gross entries (numerically absurd for any initialiser), then the identifiable nodes
    gross = gross_entries(Yc)
    used = obs & ~gross
    keep_r, keep_s = drop_unidentifiable(used, dim, offsets)
    if gross.any():
        try:
            _check_kept(used, keep_r, keep_s, dim, offsets)
        except DegenerateGeometryError:
            # the screen must not make an identifiable network unidentifiable: screen nothing
            # (the robust loss and the outlier rule still judge every entry)
            gross = np.zeros_like(gross)
            used = obs.copy()
            keep_r, keep_s = drop_unidentifiable(used, dim, offsets)
    _check_kept(used, keep_r, keep_s, dim, offsets)
    return pr, pc, Yc, gross, used, keep_r, keep_s


def _check_kept(used: NDArray[np.bool_], kr: NDArray[np.bool_], ks: NDArray[np.bool_], dim: int, offsets: str) -> None:
    """Raise when the nodes left after dropping cannot determine the geometry."""
    sub = used[np.ix_(kr, ks)]
    dropped = f" after dropping {int((~kr).sum())} receivers and {int((~ks).sum())} sources with too few ranges" \
        if (~kr).any() or (~ks).any() else ""
    try:
        check_toa_counts(sub.shape, int(sub.sum()), dim, offsets)
    except DegenerateGeometryError as exc:
        raise DegenerateGeometryError(f"{exc.args[0]}{dropped}", kind=exc.kind) from None
