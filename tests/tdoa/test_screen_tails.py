"""Gross-error screen on heavy-tailed residuals (issue 31): the scale and tail fitted to the data keep the
stated family-wise false-alarm rate for Student-t (3, 5 dof) and Laplace noise, where the Gaussian rule
flags most clean matrices; gross errors are still found; the real Pyramic file loses only its two
wrong-peak entries."""

from __future__ import annotations

import numpy as np
import pytest

from selfcal.tdoa.screen import SCREEN_ALPHA, gross_error_screen
from selfcal.tdoa.tails import fit_tail_model

SLOW = pytest.mark.slow
SEEDS = {"t3": 1, "t5": 2, "laplace": 3, "gaussian": 4}


def noise(rng: np.random.Generator, kind: str, shape: tuple[int, ...]) -> np.ndarray:
    """Unit-variance noise of the named law."""
    if kind == "t3":
        return rng.standard_t(3, shape) / np.sqrt(3.0)
    if kind == "t5":
        return rng.standard_t(5, shape) / np.sqrt(5.0 / 3.0)
    if kind == "laplace":
        return rng.laplace(size=shape) / np.sqrt(2.0)
    return rng.standard_normal(shape)


def problem(rng: np.random.Generator, m: int, k: int, kind: str, sigma: float = 1e-4) -> np.ndarray:
    """A 5 cm array, k far-field sources, unit offsets, sigma metres of noise of law ``kind``."""
    Z = rng.uniform(-0.025, 0.025, (m, 3))
    N = rng.normal(size=(k, 3))
    N /= np.linalg.norm(N, axis=1, keepdims=True)
    return Z @ N.T + rng.normal(size=k) + sigma * noise(rng, kind, (m, k))


@pytest.mark.parametrize("seed", range(4))
def test_tail_model_recovers_the_law_of_the_residuals(seed):
    # 20000 draws: the ML dof of a t_nu sample is within a grid step or two of nu, and the lower
    # 95 % bound is below it (conservative); Gaussian data give a light tail (>= 30 dof); 1 % of
    # errors 1000 scales away go to the uniform part and leave the tail alone
    rng = np.random.default_rng(seed)
    for nu in (3.0, 5.0):
        z = 2.0 * rng.standard_t(nu, 20000)
        z[:200] += 2000.0
        tm = fit_tail_model(z)
        assert 0.6 * nu <= tm.dof <= tm.dof_ml <= 1.6 * nu, tm
        assert tm.scale == pytest.approx(2.0, rel=0.1)
        assert tm.outliers == pytest.approx(0.01, rel=0.2)
    tm = fit_tail_model(rng.standard_normal(20000))
    assert tm.dof >= 30


def _false_alarms(m: int, k: int, kind: str, draws: int, seed: int, tail: str = "fitted") -> int:
    rng = np.random.default_rng(seed)
    return sum(bool(gross_error_screen(problem(rng, m, k, kind), tail=tail).mask.any()) for _ in range(draws))


@pytest.mark.parametrize("kind", ["t3", "t5", "laplace"])
def test_heavy_tails_keep_the_stated_false_alarm_rate(kind):
    # family-wise alpha = 1 % per matrix: over 30 clean 12 x 24 matrices (the structure test) and
    # 20 clean 6 x 8 ones (the far-field model's deletion test, t_3 null) P(more than 2 | 1 %) < 2e-3
    assert SCREEN_ALPHA == 0.01
    assert _false_alarms(12, 24, kind, 30, seed=SEEDS[kind]) <= 2
    assert _false_alarms(6, 8, kind, 20, seed=100 + SEEDS[kind]) <= 2


def test_the_gaussian_rule_fails_on_heavy_tails():
    # what issue 31 reported: the Gaussian Bonferroni quantile flags most clean t_3 matrices
    # (measured 85 % at 12 x 24); it is kept only as tail="gaussian" for comparison
    assert _false_alarms(12, 24, "t3", 20, seed=3, tail="gaussian") >= 10


@pytest.mark.parametrize("kind", ["t5", "laplace", "gaussian"])
def test_gross_errors_are_found_under_heavy_tails(kind):
    # two errors of 0.2 and 0.3 x the array's extent (200-300 x the noise) in 30 x 60 matrices:
    # far beyond the t_5 Bonferroni quantile (about 35 scales), so both are flagged and nothing else
    rng = np.random.default_rng(11)
    for _ in range(4):
        D = problem(rng, 30, 60, kind)
        ext = float(np.ptp(D - D.mean(axis=0)))
        cells = [(int(rng.integers(30)), int(rng.integers(60))) for _ in range(2)]
        if cells[0] == cells[1]:
            continue
        for (i, j), f in zip(cells, (0.2, -0.3), strict=True):
            D[i, j] += f * ext
        g = gross_error_screen(D)
        assert sorted(map(tuple, np.argwhere(g.mask).tolist())) == sorted(cells)


def test_the_real_pyramic_file_loses_only_its_two_wrong_peaks(shared_data):
    # speaker 0's 8640 delays: two are off by ~259 m (wrong entries), the rest have a Student-t
    # tail of about 5-8 dof; the Gaussian rule flags 29 (issue 31), the fitted tail the two
    from selfcal.datasets import load_pyramic

    D = load_pyramic(shared_data / "pyramic" / "pyramic_tdoa_speaker0.json").D
    g = gross_error_screen(D)
    assert int(g.mask.sum()) == 2
    # the rule that ran and its false-alarm statement travel with the result
    assert "Student-t tail" in g.rule and "false-alarm rate <= 0.01" in g.rule
    Xc = D - np.nanmedian(D, axis=0)
    assert np.all(np.abs(Xc[g.mask]) > 1.0)  # metres: the two huge ones
    assert int(gross_error_screen(D, tail="gaussian").mask.sum()) > 10


@SLOW
@pytest.mark.parametrize("kind", ["t3", "t5", "laplace", "gaussian"])
def test_false_alarm_rate_slow(kind):
    # 200 clean draws per size at alpha = 1 %: P(more than 6 | 1 %) < 5e-3
    for m, k in ((12, 24), (30, 60), (6, 8)):
        assert _false_alarms(m, k, kind, 200, seed=m * k) <= 6
