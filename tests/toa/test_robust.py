"""selfcal.toa.verdict.robust: the vectorised median polish equals NumPy's nanmedian sweeps."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from selfcal.toa.verdict import robust


def _polish_reference(Y: np.ndarray, iterations: int = 10) -> np.ndarray:
    """Tukey's median polish with ``np.nanmedian`` (the independent computation)."""
    R = np.array(Y, dtype=float)
    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN rows / columns
        for _ in range(iterations):
            a = np.nanmedian(R, axis=1)
            R = R - np.where(np.isfinite(a), a, 0.0)[:, None]
            b = np.nanmedian(R, axis=0)
            R = R - np.where(np.isfinite(b), b, 0.0)[None, :]
    return R


def test_nanmedian_rows_equals_numpy() -> None:
    rng = np.random.default_rng(0)
    for _ in range(200):
        I, J = rng.integers(1, 30, 2)
        R = rng.normal(size=(I, J))
        R[rng.random((I, J)) < rng.uniform(0, 0.7)] = np.nan
        if rng.random() < 0.3:
            R[rng.integers(I)] = np.nan
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            ref = np.nanmedian(R, axis=1)
        np.testing.assert_array_equal(robust._nanmedian_rows(R), ref)


def test_median_polish_equals_nanmedian_sweeps() -> None:
    # bitwise equal (same arithmetic on the same middle entries), ties, empty rows and
    # columns, and the early stop at a fixed point included; one matrix above NumPy's
    # 600-column switch to its per-row loop
    rng = np.random.default_rng(1)
    shapes = [tuple(rng.integers(1, 40, 2)) for _ in range(60)] + [(20, 700)]
    for I, J in shapes:
        Y = rng.uniform(0, 10, (I, J)) + rng.normal(size=I)[:, None]
        Y[rng.random((I, J)) < rng.uniform(0, 0.6)] = np.nan
        if rng.random() < 0.2:
            Y[:, rng.integers(J)] = np.nan
        if rng.random() < 0.3:
            Y = np.round(Y)  # ties
        np.testing.assert_array_equal(robust._median_polish(Y), _polish_reference(Y))


def test_outlier_threshold_with_an_estimated_scale_is_students_t():
    """With the scale estimated from ``dof`` residual degrees of freedom the Bonferroni cut
    is Student's t quantile: above the normal one (a scale from 7 degrees of freedom, the
    12 x 6 both-offsets case, is often half the true one, and the normal cut then flagged
    clean entries, throwing 14 of 175 blind solves out of their basin), decreasing in dof,
    and the normal quantile in the limit."""
    from selfcal.toa.verdict.robust import outlier_threshold

    m = 72
    k_norm = outlier_threshold(m)
    ks = [outlier_threshold(m, dof=d) for d in (1, 3, 7, 30, 300, 10**7)]
    assert (np.diff(ks) < 0).all()
    assert ks[2] > 1.5 * k_norm  # 7 dof: the cut is far wider than the normal one
    assert ks[-1] == pytest.approx(k_norm, rel=1e-5)
