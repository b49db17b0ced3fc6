"""``dim="auto"`` never reports as a success a 2-D model the data reject (issue 27).

A tag walked at about one height under four ceiling anchors and two low ones
(:func:`tests.toa.uniqueness_families.tag_one_height`): the truth is 3-D (anchors 2.6 m
apart in height) but every anchor's partners (the tag positions) are coplanar, so the 3-D
fit is ambiguous (flips through the tag's plane) and its thickness is not resolved by its own
error bars. The dimension test then dropped z although the F test rejected the plane far
beyond its bootstrap band (F = 28, p = 6e-41 on a CLI draw), and the 2-D answer, anchors
1.6 m off at 7 of their error bars, came back as a success (seed 103 here; 2 of 20 CLI draws in
``benchmarks/cli_audit.py``). Property: every draw is either flagged (``success`` False) or
a 3-D answer within 3 of its own error bars of the truth; a 2-D answer is never a success
here, since no plane holds both anchor levels.
"""

from __future__ import annotations

import warnings

import pytest

from selfcal.errors import DegenerateGeometryError
from selfcal.toa import solve_toa

from .uniqueness_families import tag_one_height, within


def _honest(seed: int) -> bool:
    Y, r, s, _ = tag_one_height(seed)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            res = solve_toa(Y, rng=seed, dim="auto")
        except DegenerateGeometryError:
            return True
    if not res.success:
        return True
    return res.receivers.shape[1] == 3 and within(res, r, s)


def test_tag_at_one_height_is_flagged_or_right_reduced() -> None:
    # 12 draws (about 1 s each); 103 is one the rejected-plane rule turns from a 2-D success
    # 1.6 m off into the failing, named 3-D fit
    bad = [seed for seed in range(100, 112) if not _honest(seed)]
    assert bad == []


@pytest.mark.slow
def test_tag_at_one_height_is_flagged_or_right() -> None:
    bad = [seed for seed in range(100, 160) if not _honest(seed)]
    assert bad == []
