"""The lockstep LM of the search's race (selfcal.toa.engine.batch_lm): the iterates of the one-start
dense LM, every start on its own, for every offset model, loss and missing pattern."""

from __future__ import annotations

import numpy as np
import pytest

from selfcal.toa.engine import nls
from selfcal.toa.engine.batch_lm import solve_batch_lm
from selfcal.toa.engine.dense_lm import full_lm

OFFSETS = ("none", "receivers", "sources", "both")


def _network(seed: int, I: int, J: int, missing: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    g = np.random.default_rng(seed)
    r = g.uniform(0.0, 1.5, (I, 3))
    s = g.normal(0.75, 2.5, (J, 3))
    Y = nls.toa_model(r, s, g.uniform(0, 1, I), g.uniform(0, 3, J)) + g.normal(0, 0.005, (I, J))
    Y[g.random((I, J)) < missing] = np.nan
    return r, s, Y


def _starts(r: np.ndarray, s: np.ndarray, offsets: str, g: np.random.Generator, n: int) -> np.ndarray:
    I, J = len(r), len(s)
    out = []
    for _ in range(n):
        d0 = g.normal(0, 0.5, I) if offsets in ("receivers", "both") else None
        o0 = g.normal(0, 0.5, J) if offsets in ("sources", "both") else None
        out.append(nls._pack(r + g.normal(0, 0.3, r.shape), s + g.normal(0, 0.6, s.shape), d0, o0))
    return np.stack(out)


# 12 x 6 (the receivers eliminated) and 6 x 12 (the problem transposed inside), full and with
# 10 % missing, both losses: the stopping decisions and iteration counts must be those of the
# dense LM start by start, and the iterates equal to round-off amplified by the iterations.
# The tolerance is relative to the network's size (metres) after few iterations (8): the
# two solves of the same damped system differ by ~1e-12 relative, and over a few steps of a
# well-conditioned descent that stays far below 1e-6 (measured: <= 1e-7 over these cases).
# The Cholesky solve of the reduced systems (cholesky=True, the permutation test's) is held to
# the same tolerance: another factorisation of the same positive definite systems.
@pytest.mark.parametrize("shape", [(12, 6), (6, 12)])
@pytest.mark.parametrize("offsets", OFFSETS)
@pytest.mark.parametrize("loss", ["linear", "huber"])
@pytest.mark.parametrize("cholesky", [False, True])
def test_batch_is_the_dense_lm_start_by_start(shape: tuple[int, int], offsets: str, loss: str,
                                              cholesky: bool) -> None:
    for seed in range(4):
        r, s, Y = _network(seed, *shape, missing=0.1 if seed % 2 else 0.0)
        Th0 = _starts(r, s, offsets, np.random.default_rng(100 + seed), 5)
        ii, jj = np.nonzero(np.isfinite(Y))
        Th, conv, nit, fin = solve_batch_lm(Th0, Y, 3, offsets, loss, 0.02, 8, 1e-10, cholesky=cholesky)
        assert fin.all()
        for k in range(len(Th0)):
            th, c, n = full_lm(Th0[k], Y[ii, jj], ii, jj, *shape, 3, offsets, loss, 0.02, 8, 1e-10)
            assert n == nit[k] and c == conv[k]
            assert np.abs(Th[k] - th).max() <= 1e-6 * (1.0 + np.abs(th).max())


def test_exact_data_converge_to_zero_residual() -> None:
    """Noise-free ranges from nearby starts: every start converges to an exact fit."""
    g = np.random.default_rng(7)
    for _ in range(5):
        r = g.uniform(0, 1.5, (10, 3))
        s = g.normal(0.75, 2.0, (7, 3))
        d, o = g.uniform(0, 1, 10), g.uniform(0, 1, 7)
        Y = nls.toa_model(r, s, d, o)
        Th0 = np.stack([nls._pack(r + g.normal(0, 0.02, r.shape), s + g.normal(0, 0.02, s.shape),
                                  d + g.normal(0, 0.02, 10), o + g.normal(0, 0.02, 7)) for _ in range(4)])
        Th, conv, nit, fin = solve_batch_lm(Th0, Y, 3, "both", "linear", 1.0, None, 1e-12)
        assert conv.all() and fin.all()
        for th in Th:
            assert np.abs(nls.toa_residuals(th, Y, 3, "both")).max() < 1e-7


def test_a_non_finite_start_is_flagged_and_the_others_run() -> None:
    r, s, Y = _network(3, 12, 6, 0.0)
    Th0 = _starts(r, s, "both", np.random.default_rng(0), 3)
    Th0[1, 4] = np.nan
    Th, conv, nit, fin = solve_batch_lm(Th0, Y, 3, "both", "linear", 1.0, 20, 1e-10)
    assert fin.tolist() == [True, False, True]
    assert nit[1] == 0 and nit[0] > 0 and nit[2] > 0


def test_steps_stay_off_the_gauge() -> None:
    """The projected steps move neither the centroid nor (with both offsets) the offsets' sum
    difference: the gauge the start fixed is kept."""
    r, s, Y = _network(5, 12, 6, 0.0)
    Th0 = _starts(r, s, "both", np.random.default_rng(1), 4)
    Th, *_ = solve_batch_lm(Th0, Y, 3, "both", "linear", 1.0, 30, 1e-10)
    N = 18
    for a, b in zip(Th0, Th, strict=True):
        assert np.allclose(a[:N * 3].reshape(N, 3).mean(0), b[:N * 3].reshape(N, 3).mean(0), atol=1e-9)
        shift = lambda t: t[N * 3:N * 3 + 12].sum() - t[N * 3 + 12:].sum()  # noqa: E731
        assert abs(shift(a) - shift(b)) < 1e-8 * (1 + abs(shift(a)))
