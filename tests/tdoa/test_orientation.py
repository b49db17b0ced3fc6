"""The transposed-matrix check (``tdoa.orientation``) on the nested rank test: named when the
transposed reading fits the far-field model and the given one does not, never otherwise."""

from __future__ import annotations

import numpy as np
import pytest

from selfcal.errors import InputError
from selfcal.tdoa.orientation import check_orientation, orientation_statistics

SLOW = pytest.mark.slow


def problem(rng: np.random.Generator, m: int, k: int, d: int, sigma: float, layout: str) -> np.ndarray:
    """Far-field matrix of m receivers and k transmitters in d dimensions (unit-scale array).

    ``offsets``: one random offset per column; ``reference``: TDOAs against receiver 0 (zero
    first row, no trace of the offsets after row centring: the layout in which a correct matrix
    can be mistaken for a transposed one at all).
    """
    Z = rng.normal(size=(m, d))
    N = rng.normal(size=(k, d))
    N /= np.linalg.norm(N, axis=1, keepdims=True)
    c = rng.normal(size=k) if layout == "offsets" else -Z[0] @ N.T
    D = Z @ N.T + c + sigma * rng.standard_normal((m, k))
    return D - D[0] if layout == "reference" else D


def named(D: np.ndarray, **kw: object) -> bool:
    try:
        check_orientation(D, **kw)
    except InputError as exc:
        assert "transposed?" in str(exc)
        return True
    return False


# sizes at which both readings leave enough degrees of freedom to estimate the noise under
# their nulls (5 x 7 and 6 x 10 in space do not: there only exact transposition is named)
DECIDABLE = {3: [(8, 12), (10, 30), (20, 8), (16, 24), (8, 60)], 2: [(6, 10), (8, 12), (10, 30), (20, 8), (8, 60)]}


#: the default tests' share of the sizes (each new size costs its Monte-Carlo null quantiles once)
QUICK = {3: [(8, 12), (10, 30)], 2: [(6, 10), (20, 8)]}


def _rates(d: int, draws: int, noise_given: bool, sizes: dict[int, list[tuple[int, int]]] = QUICK
           ) -> tuple[int, int, int]:
    false = missed = total = 0
    for (m, k) in sizes[d]:
        rng = np.random.default_rng(1000 * m + k + d)
        for t in range(draws):
            layout = ("offsets", "reference")[t % 2]
            D = problem(rng, m, k, d, 1e-3, layout)
            kw = {"rank": d, "noise_std": 1e-3 if noise_given else None}
            false += named(D, **kw)
            missed += not named(D.T, **kw)
            total += 1
    return false, missed, total


@pytest.mark.parametrize("d", [3, 2])
@pytest.mark.parametrize("noise_given", [False, True])
def test_transposed_is_named_and_correct_is_not(d, noise_given):
    # Each rank test has false-alarm rate alpha = 1e-3; a correct matrix is named only when its
    # column-centred test is a false alarm AND its row-centred one finds no offsets (possible only
    # in the reference layout), so false alarms have probability <= 1e-3 per matrix: over 100
    # matrices P(>= 2) < 2e-3 (40 here). The transposed matrices carry offsets of unit scale against 1 mm
    # noise: one is missed only when the test of its own (correct) reading is a false alarm,
    # again probability <= 1e-3.
    false, missed, total = _rates(d, 20, noise_given)
    assert false <= 1, (false, total)
    assert missed <= 1, (missed, total)


@SLOW
@pytest.mark.parametrize("d", [3, 2])
def test_transposed_check_false_alarm_rate_slow(d):
    # 1000 matrices per dimension (5 sizes x 200): P(more than 4 false alarms | rate 1e-3) < 4e-3, and the same
    # for misses (a miss is a false alarm of the correct reading's test)
    false, missed, total = _rates(d, 200, False, DECIDABLE)
    assert false <= 4, (false, total)
    assert missed <= 4, (missed, total)


@pytest.mark.parametrize("shape", [(5, 7), (6, 10)])
def test_small_matrices_name_only_exact_transposition(shape):
    # too few degrees of freedom to estimate the noise under both nulls: the numerical rank
    # decides, so exact transposed data are named and noisy correct data never are
    m, k = shape
    for s in range(20):
        rng = np.random.default_rng(s)
        assert named(problem(rng, m, k, 3, 0.0, "offsets").T)
        D = problem(rng, m, k, 3, 1e-3, ("offsets", "reference")[s % 2])
        assert not named(D)


def test_statistics_are_those_of_the_two_readings():
    rng = np.random.default_rng(3)
    D = problem(rng, 10, 30, 3, 1e-3, "offsets")
    st = orientation_statistics(D)
    assert st["decidable"] == 1.0
    assert st["s_given"] <= st["thr_given"] < st["s_transposed"]
    back = orientation_statistics(D.T)
    assert back["s_given"] == pytest.approx(st["s_transposed"])
    assert back["s_transposed"] == pytest.approx(st["s_given"])
