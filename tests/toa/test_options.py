"""ToaOptions: the options of solve_toa named once (issue 30)."""

from __future__ import annotations

import dataclasses
import inspect

import numpy as np
import pytest

from selfcal.toa import solve_toa, toa_model
from selfcal.toa.options import ToaOptions


def test_defaults_are_solve_toas():
    """Every field of ToaOptions is a keyword of solve_toa with the same default (one definition each)."""
    params = inspect.signature(inspect.unwrap(solve_toa)).parameters
    for f in dataclasses.fields(ToaOptions):
        assert f.name in params, f.name
        if f.name == "rng":  # solve_toa's None means a fresh generator: the field's default factory
            assert params["rng"].default is None and isinstance(ToaOptions().rng, np.random.Generator)
            continue
        assert params[f.name].default == f.default, f.name


def test_frozen_and_with():
    opts = ToaOptions(noise=0.5)
    with pytest.raises(dataclasses.FrozenInstanceError):
        opts.noise = 1.0  # type: ignore[misc]
    nls = opts.with_(method="nls")
    assert (nls.method, nls.noise, opts.method) == ("nls", 0.5, "auto")
    assert nls.rng is opts.rng  # one generator stream through the model choice's fits


@pytest.mark.parametrize("seed", range(4))
def test_noise_reaches_the_trust_test(seed):
    """``noise`` given to solve_toa is the noise the chi-square test of the result uses."""
    g = np.random.default_rng(seed)
    r, s = g.uniform(-5, 5, (6, 3)), g.uniform(-5, 5, (8, 3))
    Y = toa_model(r, s) + g.normal(0, 0.01, (6, 8))
    res = solve_toa(Y, rng=seed, noise=0.01, covariance=False)
    assert res.fit is not None and res.geometry is None
    free = solve_toa(Y, rng=seed, covariance=False)
    assert free.fit is None
