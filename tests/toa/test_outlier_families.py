"""Gross-error contamination as a specification over random draws (issue 27, outlier breakdown).

Families (``outlier_families.py``): 12 x 40 in 3-D and 10 x 30 in 2-D networks in a 10 m
box, 1 cm noise, a fraction of the ranges drawn in 10-40 % off by U(1, 5) m (100-500 noise
std), one-sided or symmetric, the noise given or unknown, offsets none or per receiver.

The property every draw must have: exit 0 only when right (every located node within 3 of
its own error bars of the truth) with the injected errors between located nodes in the
``outliers`` mask; otherwise a failed result (the CLI's exit 1) that says ``outlier
breakdown``. Why this can hold: a source of 12 ranges and 3 unknowns holds at most
floor((12 - 3) / 2) = 4 gross ranges (the maximal breakdown point of any regression
estimator of its position, Rousseeuw & Leroy 1987, sec. 3.4); the high-breakdown start
(``toa.verdict.high_breakdown.high_breakdown_start``: nodewise least median of squares, per node
that same breakdown point) reaches the majority's basin where most nodes are within it, and
the outlier rule (Bonferroni at family-wise level 0.01) then flags the rest. With the noise
given, the rule also measures the flagged fraction against the noise, so a fit it cannot
hold is a breakdown (more than half flagged).

What does not hold yet, measured (``benchmarks/outlier_sweep.py --families``): with the noise
unknown and 30-40 % of the ranges gross, a third to a half of the sources carry more gross
ranges than they can hold, the sweeps stall in a wrong basin, the noise estimate inflates
(1-2 m against 1 cm) and no entry stands out. The majority-scale test
(``toa.verdict.high_breakdown.majority_scale_test``: a graduated trimmed search for a fit of the
majority of the ranges, breakdown when the final fit's scale exceeds the majority's by the
outlier rule's cut) turns those it reaches into an "outlier breakdown"; it does not reach all:
13 of 200 such draws (0-10 % per family; 24 before the test) end in exit 0 with a node outside
3 error bars. That property is stated below as an expected failure.

False alarms: on clean networks, Gaussian or heavy-tailed (t3-t5, Laplace: real ranging noise,
not gross errors), the breakdown must not be reported in more than 1 % of draws (the rule's
family-wise level is 1 %; measured 0 of 200 clean and 0 of 240 heavy-tailed).
"""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
from outlier_families import CLEAN, CONTAMINATED, HEAVY, classify  # noqa: E402

#: the noise given (any fraction up to 40 %), or unknown with at most 25 % gross ranges
HELD = ("3d-plus-given", "3d-sym-given", "2d-sym-given", "3d-offsets-sym-given", "3d-plus-unknown-25",
        "2d-sym-unknown-25")
#: the noise unknown with up to 40 % gross ranges, and the issue's 30 % of ranges +5 m
BEYOND = ("3d-plus-unknown", "3d-sym-unknown", "2d-plus-unknown", "3d-offsets-plus-unknown",
          "3d-30pct-5m-unknown")


def _held(family: str, draws: int) -> None:
    for seed in range(draws):
        d = classify(CONTAMINATED[family], seed)
        # right: exit 0, within 3 error bars, every injected error between located nodes flagged;
        # breakdown: a failed result that says "outlier breakdown"
        assert d["kind"] in ("right", "breakdown"), (family, seed, d["kind"], d["message"])


@pytest.mark.parametrize("family", HELD)
def test_contamination_the_estimator_holds_is_right_and_flagged_or_a_breakdown(family):
    _held(family, 2)


@pytest.mark.slow
@pytest.mark.parametrize("family", HELD)
def test_contamination_the_estimator_holds_is_right_and_flagged_or_a_breakdown_many_draws(family):
    _held(family, 40)  # 6 families x 40 = 240 draws


def _false_alarms(draws: int, families: dict = CLEAN) -> tuple[int, int]:
    alarms = total = 0
    for family in families.values():
        for seed in range(draws):
            d = classify(family, seed)
            alarms += d["kind"] == "breakdown"
            total += 1
    return alarms, total


def test_clean_networks_report_no_breakdown():
    alarms, total = _false_alarms(2)
    assert alarms == 0, (alarms, total)


def test_heavy_tailed_clean_networks_report_no_breakdown():
    # t3-t5 and Laplace noise of 1 cm std, no gross errors: real ranging noise, not a breakdown
    alarms, total = _false_alarms(1, HEAVY)
    assert alarms == 0, (alarms, total)


@pytest.mark.slow
def test_heavy_tailed_clean_networks_report_a_breakdown_in_at_most_one_percent_of_draws():
    # 6 families x 40 = 240 draws; the bound as for the Gaussian clean networks below
    alarms, total = _false_alarms(40, HEAVY)
    assert alarms <= 0.01 * total, (alarms, total)


@pytest.mark.slow
def test_clean_networks_report_a_breakdown_in_at_most_one_percent_of_draws():
    # 5 families x 40 = 200 draws; at a true rate of 1 % the count exceeds 2 with probability 0.32,
    # at 0 % never: the bound asserts the measured 0 with room for one or two tail draws
    alarms, total = _false_alarms(40)
    assert alarms <= 0.01 * total, (alarms, total)


@pytest.mark.slow
@pytest.mark.xfail(reason="noise unknown and 30-40 % of the ranges gross: where the majority-scale search does not "
                          "reach the majority of the ranges the stalled fit is not caught (13 of 200 draws, 0-10 % per "
                          "family, end in exit 0 with a node outside 3 error bars; 24 before the test; "
                          "benchmarks/outlier_sweep.py --families)", strict=False)
@pytest.mark.parametrize("family", BEYOND)
def test_contamination_beyond_what_the_nodes_hold_never_ends_in_a_confident_wrong_answer(family):
    for seed in range(40):
        d = classify(CONTAMINATED[family], seed)
        assert d["kind"] != "wrong", (family, seed, d["outside"], d["message"])
