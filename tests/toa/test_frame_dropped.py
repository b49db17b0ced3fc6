"""apply_frame with nodes the solver dropped: the covariances are still those of the frame."""

from __future__ import annotations

import numpy as np
import pytest

from selfcal.toa import solve_toa
from selfcal.toa.engine.nls import toa_model
from selfcal.toa.frame.frame import apply_frame


@pytest.mark.parametrize("seed", range(3))
def test_frame_covariance_with_a_dropped_source(seed):
    """A source with 2 ranges is dropped (NaN); the frame's references still get exactly the
    zero variances the frame defines (origin: all, x: y and z, xy: z), the others positive.
    (Before, one NaN block made the frame keep the rotated gauge-free covariances: the
    origin anchor of an LPS flight had a 3 cm std.)"""
    rng = np.random.default_rng(seed)
    r, s = rng.uniform(0, 5, (6, 3)), rng.uniform(0, 5, (30, 3))
    Y = toa_model(r, s) + rng.normal(0, 0.01, (6, 30))
    Y[:4, 7] = np.nan
    res = solve_toa(Y, rng=0)
    assert np.isnan(res.sources[7]).all()
    f = apply_frame(res, "origin=r0,x=r1,xy=r2", matrix=Y)
    var = np.diagonal(f.receiver_cov, axis1=1, axis2=2)
    zero = np.zeros((6, 3), bool)
    zero[0], zero[1, 1:], zero[2, 2] = True, True, True
    assert np.all(np.abs(var[zero]) < 1e-12) and np.all(var[~zero] > 0)
