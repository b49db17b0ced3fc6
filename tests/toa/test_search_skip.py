"""The search's initialisers stop at a start that passes the stopping rule unrefined (search.py, 2.).

Property: skipping the later initialisers never changes what the search returns. Reference: the
same search handed every registry start explicitly (``starts=``), which races them all.
"""

from __future__ import annotations

import numpy as np
import pytest

from selfcal.scenarios.units import make_units
from selfcal.toa.engine.nls import toa_model
from selfcal.toa.result import n_parameters, residual_test
from selfcal.toa.search import INITIALISERS, canonical_order, search


def _every_start(Y: np.ndarray, offsets: str, seed: int) -> list:
    rng = np.random.default_rng(seed)
    out = []
    for name, init in INITIALISERS.items():
        out += [(name, st) for st in init(Y, 3, offsets, rng)]
    return out


def _sorted(Y: np.ndarray) -> np.ndarray:
    pr, pc = canonical_order(Y)
    return Y[np.ix_(pr, pc)]


@pytest.mark.parametrize("seed", range(4))
def test_exact_start_ends_the_starts(seed: int) -> None:
    """Noise-free 20 units with both offsets (004's small setup): the rank-3 start is exact, the
    003 starts are not computed, and the winner is the one the full race returns."""
    Y = _sorted(make_units(20, room="small", rng=seed).ranges)
    got = search(Y, 3, "both", rng=np.random.default_rng(seed))
    ref = search(Y, 3, "both", rng=np.random.default_rng(seed), starts=_every_start(Y, "both", seed))
    assert all(n == "rank3" for n, _ in got.history)
    assert got.stopped == ref.stopped == "exact"
    assert got.start == ref.start
    # both at the solver's precision: residuals below sqrt(eps) x the median range
    level = np.sqrt(np.finfo(float).eps) * float(np.nanmedian(np.abs(Y)))
    assert np.nanmax(np.abs(got.solution.residuals)) <= level


@pytest.mark.parametrize("seed", range(4))
def test_given_noise_start_ends_the_starts(seed: int) -> None:
    """A start that passes the chi-square test at the given noise ends the starts; the search then
    returns what the full race returns.

    1 mm noise, 3 mm stated (a conservative user): the unrefined rank-3 start (RMS 1.4-2 mm here)
    passes the test, the 003 starts (0.4-2.8 m) do not. At the true noise no unrefined start
    passes (its RSS would have to be below the chi-square quantile of the residual dof), so the
    branch is exercised with the stated noise above the true one."""
    sc = make_units(20, room="small", rng=seed)
    sd = 3e-3  # m, stated
    Y = _sorted(sc.ranges + np.random.default_rng([5, seed]).normal(0, 1e-3, sc.ranges.shape))
    n_par = n_parameters(Y.shape[0], Y.shape[1], 3, "both")
    stop = lambda res: residual_test(res, sd, n_par).passed  # noqa: E731
    starts = _every_start(Y, "both", seed)
    passing = [k for k, (_, st) in enumerate(starts) if stop(Y - toa_model(*st))]
    got = search(Y, 3, "both", rng=np.random.default_rng(seed), stop=stop)
    ref = search(Y, 3, "both", rng=np.random.default_rng(seed), stop=stop, starts=starts)
    assert got.start == ref.start
    assert got.stopped == ref.stopped
    np.testing.assert_allclose(got.solution.residuals, ref.solution.residuals, atol=1e-9)
    assert passing, "the rank-3 start at 3x the noise should pass: the test would be vacuous"
    # no initialiser after the first passing start's ran
    last = starts[passing[0]][0]
    names = list(INITIALISERS)
    assert all(names.index(n) <= names.index(last) for n, _ in got.history)
    assert got.stopped == "test"
