"""The estimated-scale outlier cut says when it has no power (``toa.verdict.leverage.outlier_rule_has_power``).

With few residual degrees of freedom a gross error inflates the MAD scale it is judged
against, so Student's t cut at that dof can flag nothing, whatever the error's size. The
result must say so instead of reporting zero outliers silently; where the rule has power a
gross error is flagged. Networks: uniform 10 m cubes, 1 cm noise, 5 seeds each.
"""

from __future__ import annotations

import numpy as np
import pytest

from selfcal.toa import solve_toa
from selfcal.toa.verdict.leverage import outlier_rule_has_power


def _net(seed: int, I: int, J: int) -> np.ndarray:
    g = np.random.default_rng(seed)
    R, S = g.uniform(0, 10, (I, 3)), g.uniform(0, 10, (J, 3))
    return np.linalg.norm(R[:, None] - S[None], axis=2) + 0.01 * g.normal(size=(I, J))


@pytest.mark.parametrize("seed", range(5))
def test_no_power_is_said_and_the_gross_error_is_indeed_not_flagged(seed: int) -> None:
    # 5 x 6 without offsets: 30 entries for 27 unknowns, 3 residual dof
    Y = _net(seed, 5, 6)
    Y[1, 2] += 5.0  # 500 noise stds
    res = solve_toa(Y, offsets="none", rng=seed)
    assert "outlier detection has no power at 3 residual dof" in res.message
    assert not np.asarray(res.outliers).any()


@pytest.mark.parametrize("seed", range(5))
def test_where_the_rule_has_power_the_gross_error_is_flagged(seed: int) -> None:
    # 8 x 10 without offsets: 80 entries for 48 unknowns, 32 residual dof
    Y = _net(seed, 8, 10)
    Y[3, 4] += 0.5  # 50 noise stds
    res = solve_toa(Y, offsets="none", rng=seed)
    assert "no power" not in res.message
    assert bool(np.asarray(res.outliers)[3, 4])


def test_power_check_against_the_sqrt_dof_bound_of_rms_studentized_residuals() -> None:
    """At 1 residual dof every residual vector is a multiple of one vector: no cut can separate one entry."""
    g = np.random.default_rng(0)
    R, S = g.uniform(0, 10, (4, 2)), g.uniform(0, 10, (5, 2))
    # 2-D, no offsets: 8 + 10 - 3 = 15 unknowns; 16 entries -> 1 dof
    Y = np.linalg.norm(R[:, None] - S[None], axis=2)
    assert not outlier_rule_has_power(Y, R, S, None, None, "none", dof=1)
    Yb = np.linalg.norm(g.uniform(0, 10, (30, 2))[:, None] - S[None], axis=2)
    assert outlier_rule_has_power(Yb, g.uniform(0, 10, (30, 2)), S, None, None, "none", dof=150 - 67)
