"""Robust scale: the one home of the normalised median absolute deviation.

``1.4826 MAD`` estimates the standard deviation of Gaussian data with a 50 % breakdown
point (Hampel 1974; Rousseeuw & Croux 1993). Every solver that needs a robust noise level
calls :func:`mad_std`, which is :func:`scipy.stats.median_abs_deviation` with
``scale="normal"`` (the constant ``1 / Phi^-1(3/4) = 1.482602...``) and NaN omitted.
"""

from __future__ import annotations

import warnings
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.stats import median_abs_deviation

__all__ = ["mad_std"]


def _zero(x: NDArray[Any], axis: int | None = None) -> Any:
    return np.zeros(()) if axis is None else np.zeros(np.delete(np.shape(x), axis))


def mad_std(
    x: ArrayLike,
    axis: int | None = None,
    *,
    centre: bool = True,
    keepdims: bool = False,
) -> Any:
    """Normalised median absolute deviation ``1.4826 median|x - median(x)|``, NaN ignored.

    Parameters
    ----------
    x : array_like
        Data (any shape). NaN entries are left out.
    axis : int, optional
        Axis along which to compute; None (default) uses every entry.
    centre : bool
        Subtract the median first (default). ``False`` gives ``1.4826 median|x|``, the
        scale of residuals that are already centred by a fit.
    keepdims : bool
        Keep the reduced axis with length one (for broadcasting against ``x``).

    Returns
    -------
    float or ndarray
        The robust standard deviation (x's units); NaN where a slice has no finite entry.

    Examples
    --------
    >>> import numpy as np
    >>> from selfcal.robust import mad_std
    >>> float(mad_std([1.0, 2.0, 3.0, 4.0, 100.0]))  # 1.4826 x median(|x - 3|) = 1.4826
    1.482602218505602
    >>> mad_std(np.array([[1.0, -1.0, np.nan], [2.0, -2.0, 0.0]]), axis=1, centre=False)
    array([1.48260222, 2.96520444])
    """
    a = np.asarray(x, dtype=float)
    with warnings.catch_warnings():  # an all-NaN slice gives NaN, as documented
        warnings.simplefilter("ignore", RuntimeWarning)
        out = median_abs_deviation(a, axis=axis, center=np.median if centre else _zero, scale="normal",
                                   nan_policy="omit")
    if keepdims and axis is not None:
        out = np.expand_dims(out, axis)
    return float(out) if np.ndim(out) == 0 and not keepdims else out
