"""ToaOptions: solve_toa's options named once, typed, and followed by name (issue 30)."""

from __future__ import annotations

import dataclasses
import inspect

import numpy as np
import pytest

from selfcal.toa import solve_toa, toa_model
from selfcal.toa.options import ToaOptions


def test_fields_are_solve_toas_keywords_without_defaults_of_their_own():
    """Every field is a keyword of solve_toa, whose signature alone holds the default."""
    params = inspect.signature(inspect.unwrap(solve_toa)).parameters
    for f in dataclasses.fields(ToaOptions):
        assert f.name in params and params[f.name].kind is inspect.Parameter.KEYWORD_ONLY, f.name
        assert f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING, f.name


def test_frozen_and_replaced_not_copied():
    opts = ToaOptions(speed=None, loss="auto", method="auto", rng=np.random.default_rng(0), f_scale=None,
                      max_nfev=None, covariance=True, sweep=True, noise=0.5, budget=None)
    with pytest.raises(dataclasses.FrozenInstanceError):
        opts.noise = 1.0  # type: ignore[misc]
    nls = dataclasses.replace(opts, method="nls")
    assert (nls.method, nls.noise, opts.method) == ("nls", 0.5, "auto")
    assert nls.rng is opts.rng  # one generator stream through the model choice's fits


@pytest.mark.parametrize("seed", range(4))
def test_noise_reaches_the_chi_square_test(seed):
    """``noise`` given to solve_toa is the noise of the result's chi-square test: its statistic
    is the residual sum of squares over noise^2 (an independent computation from the residuals)."""
    g = np.random.default_rng(seed)
    r, s = g.uniform(-5, 5, (6, 3)), g.uniform(-5, 5, (8, 3))
    Y = toa_model(r, s) + g.normal(0, 0.01, (6, 8))
    for noise in (0.01, 0.02):
        res = solve_toa(Y, rng=seed, noise=noise, covariance=False)
        assert res.fit is not None and res.geometry is None and res.fit.noise == noise
        e = res.residuals[np.isfinite(res.residuals) & ~res.outliers]
        np.testing.assert_allclose(res.fit.chi2, float(e @ e) / noise**2, rtol=1e-9)
    assert solve_toa(Y, rng=seed, covariance=False).fit is None
