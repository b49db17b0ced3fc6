"""Known coordinates, not only known positions: ``A3,,,2.41`` (a known height) in --known.

The FAIL message of an ambiguous layout (issue 27: a tag walked at one height under
ceiling anchors) names "a known height" as a remedy; these tests check that following it
works, over random draws of that family (``uniqueness_families.tag_one_height``):

- blind, every draw is flagged (exit 1);
- with the anchors' true heights (two levels: ceiling and low anchors), x and y left
  empty, the result passes (exit 0) with every node within 3 of its own error bars of the
  truth *in the room frame*: z as given, only the horizontal gauge (rotation about z,
  translation, mirror through a vertical plane) aligned;
- wrong heights (two anchors' heights swapped, a 1 m typo) are caught by the known test;
- known heights all at one level leave the mirror ``z -> 2h - z`` open: reported, exit 1.

The default run takes a few draws (deterministic seeds); the ``slow`` ones 100 per case
(``pytest -m slow``). Measured with this code (``_remedy`` / ``_wrong`` over seeds 0-49,
``_level`` over 0-32): tag-one-height blind flagged 50 / 50, with the true heights 49 / 50
pass (seed 10: the blind fit's determinacy verdict stands) and 50 / 50 right, wrong
heights caught 50 / 50 (the culprit named in 29); one level: the mirror reported 33 / 33;
two levels: 33 / 33 pass, 32 / 33 right (seed 13, see ``_level``).
"""

from __future__ import annotations

import sys
import warnings
from pathlib import Path

import numpy as np
import pytest

from selfcal.errors import InputError
from selfcal.geometry import align
from selfcal.toa import solve_toa
from selfcal.toa.engine.nls import toa_model
from selfcal.toa.frame.frame import calibrate_in_frame, parse_known, read_known_csv
from selfcal.toa.verdict.known_test import gauge_left

sys.path.insert(0, str(Path(__file__).parent))
from uniqueness_families import tag_one_height  # noqa: E402

FEW = 3  # draws per case in the default run
FULL = 100  # draws per case in the slow run


def _room_ok(res, r: np.ndarray, s: np.ndarray, k: float = 3.0) -> bool:
    """Every node within ``k`` of its own error bar (sqrt trace) of the truth, z as fitted:
    only the horizontal gauge the known heights leave is aligned (reflection allowed)."""
    est = np.vstack([res.receivers, res.sources])
    ref = np.vstack([r, s])
    C = np.concatenate([res.receiver_cov, res.source_cov])
    al = align(est[:, :2], ref[:, :2], reflection=True)
    X = np.c_[al.apply(est[:, :2]), est[:, 2]]
    bar = np.sqrt(np.trace(C, axis1=1, axis2=2))
    return bool(np.all(np.linalg.norm(X - ref, axis=1) <= k * bar + 1e-9))


def _heights(z: np.ndarray, idx) -> dict[str, tuple[float, float, float]]:
    return {f"r{i}": (np.nan, np.nan, float(z[i])) for i in idx}


def _calibrate(Y, known, seed, **kw):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return calibrate_in_frame(Y, known=known, rng=seed, **kw)


# --- the file format -----------------------------------------------------------------


def test_empty_coordinates_read_as_not_known(tmp_path):
    f = tmp_path / "k.csv"
    f.write_text("name,x,y,z,std\nA0,0,0,2.4,\nA3,,,2.41,\nA4,1,2,,0.05\n")
    got = read_known_csv(f)
    assert got["A0"] == (0.0, 0.0, 2.4)
    assert np.isnan(got["A3"][:2]).all() and got["A3"][2] == 2.41
    assert np.isnan(got["A4"][2]) and got["A4"][3] == 0.05  # a std on the coordinates given
    nodes = parse_known(got, 5, 3, 3, receiver_names=["A0", "A1", "A2", "A3", "A4"])
    assert [k.mask.tolist() for k in nodes] == [[True] * 3, [False, False, True], [True, True, False]]
    assert nodes[2].std == 0.05


@pytest.mark.parametrize("text, what", [
    ("name,x,y,z\nA0,,,\n", "no coordinate"),
    ("name,x,y,z\nA0,,,abc\n", "non-numeric"),
    ("name,x,y\nA0,1,2\n", "lacks"),
])
def test_bad_known_files_are_one_line_errors(tmp_path, text, what):
    f = tmp_path / "k.csv"
    f.write_text(text)
    with pytest.raises(InputError, match=what):
        read_known_csv(f)


def test_whole_positions_only_where_the_fit_needs_them():
    with pytest.raises(InputError, match="only some coordinates"):
        parse_known({"r0": (np.nan, np.nan, 2.0)}, 3, 3, 3, partial=False)
    with pytest.raises(InputError, match="at least"):
        parse_known({"r0": (np.nan, np.nan, np.nan)}, 3, 3, 3)


def test_gauge_left_by_heights_and_by_positions():
    g = np.random.default_rng(0)
    P = g.uniform(0, 5, (4, 3))
    z_only = np.zeros((4, 3), bool)
    z_only[:, 2] = True
    # heights of nodes not on a vertical plane: z fixed; rotation about z and x, y translation left
    assert gauge_left(P, z_only) == (("z",), 3)
    assert gauge_left(P, np.ones((4, 3), bool)) == (("x", "y", "z"), 0)
    # two heights cannot fix the up direction
    assert gauge_left(P[:2], z_only[:2])[0] == ()


# --- the remedy of the tag-one-height family ---------------------------------------------


def _remedy(seeds) -> dict[str, int]:
    n = {"blind_flagged": 0, "passed": 0, "right": 0, "wrong_passed": 0}
    for seed in seeds:
        Y, r, s, kw = tag_one_height(seed)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            n["blind_flagged"] += not solve_toa(Y, rng=seed, **kw).success
        res = _calibrate(Y, _heights(r[:, 2], range(6)), seed, **kw)
        n["passed"] += res.success
        n["right"] += _room_ok(res, r, s)
        assert res.frame.axes_fixed == ("z",)
        assert "x,y canonical" in res.frame.message  # the output says which axes are the user's
        n["wrong_passed"] += res.success and not _room_ok(res, r, s)
    return n


def test_known_heights_turn_the_tag_one_height_family_into_a_pass():
    n = _remedy(range(FEW))
    assert n["blind_flagged"] == FEW
    # seed 10 of the 25 measured fails honestly (the blind fit's determinacy verdict stands)
    assert n["passed"] >= FEW - 1
    assert n["right"] == FEW and n["wrong_passed"] == 0


@pytest.mark.slow
def test_known_heights_turn_the_tag_one_height_family_into_a_pass_many_draws():
    n = _remedy(range(FULL))
    assert n["blind_flagged"] == FULL
    assert n["passed"] >= 0.9 * FULL  # measured 24 of 25; the rest fail honestly, never wrongly
    assert n["right"] >= 0.97 * FULL  # 3 error bars per node over 36 nodes: a few draws by chance
    assert n["wrong_passed"] <= 0.03 * FULL  # as the blind solver on well-posed draws (see _level)


def _wrong(seeds) -> tuple[int, int]:
    caught = named = 0
    for seed in seeds:
        Y, r, s, kw = tag_one_height(seed)
        z = r[:, 2].copy()
        a, b = seed % 4, 4 + seed % 2
        if seed % 2:
            z[a], z[b] = z[b], z[a]  # a ceiling and a low anchor's heights swapped
        else:
            z[a] += 1.0  # a 1 m typo
        res = _calibrate(Y, _heights(z, range(6)), seed, **kw)
        kt = res.frame.known_test
        caught += not res.success and not kt["passed"]
        named += f"r{a}" in kt["disagreeing"]
    return caught, named


def test_wrong_known_heights_are_caught():
    caught, _ = _wrong(range(FEW))
    assert caught == FEW


@pytest.mark.slow
def test_wrong_known_heights_are_caught_many_draws():
    caught, named = _wrong(range(FULL))
    assert caught == FULL  # errors of metres against centimetre error bars: never missed
    assert named >= 0.5 * FULL  # measured 15 of 25: naming the culprit is weaker than detecting


# --- known heights all at one level: the mirror z -> 2h - z ------------------------------


def _room(seed: int):
    """Four ceiling anchors at exactly 2.9 m, two low ones, a tag anywhere in the room (well posed)."""
    g = np.random.default_rng([29, seed])
    r = np.array([[0.5, 0.5, 2.9], [7.5, 0.5, 2.9], [7.5, 5.5, 2.9], [0.5, 5.5, 2.9],
                  [0.5, 3.0, 0.3], [7.5, 3.0, 0.6]])
    r[:, :2] += g.normal(0, 0.05, (6, 2))
    s = np.c_[g.uniform(1, 7, 20), g.uniform(1, 5, 20), g.uniform(0.3, 2.2, 20)]
    return toa_model(r, s) + g.normal(0, 0.02, (6, 20)), r, s


def _level(seeds) -> tuple[int, int, int, int]:
    """Counts of: mirror reported with one level, pass with two, right with two, pass but not right.

    A pass that is not right happens at the rate of the blind solver on the same draw (seed
    13: a tag near the low anchors' level 3.4 error bars off with the known heights, 3.0 in
    the blind fit, the same minimum as a refit from the truth): the local error bar's tail,
    not the known heights."""
    mirror = passed = right = wrong = 0
    for seed in seeds:
        Y, r, s = _room(seed)
        one = _calibrate(Y, _heights(r[:, 2], range(4)), seed, dim=3)
        kinds = {a.kind for a in one.uniqueness.alternatives} if one.uniqueness is not None else set()
        mirror += (not one.success) and "mirror" in kinds and "z -> 5.8 - z" in one.verdict_message
        two = _calibrate(Y, _heights(r[:, 2], range(6)), seed, dim=3)
        passed += two.success
        ok = _room_ok(two, r, s)
        right += ok
        wrong += two.success and not ok
    return mirror, passed, right, wrong


def test_heights_at_one_level_leave_the_mirror_two_levels_resolve_it():
    mirror, passed, right, wrong = _level(range(FEW))
    assert mirror == FEW  # an exact isometry of the data: never resolved
    assert passed == FEW and right == FEW and wrong == 0


@pytest.mark.slow
def test_heights_at_one_level_leave_the_mirror_many_draws():
    mirror, passed, right, wrong = _level(range(FULL))
    assert mirror == FULL
    assert passed >= 0.99 * FULL  # false alarms of the mirror / known tests <= 1 % (levels 1e-3)
    assert right >= 0.95 * FULL and wrong <= 0.05 * FULL


def test_side_resolves_the_mirror_heights_at_one_level_leave():
    """``side`` is the user's statement of the mirror image: the other nodes below (above) the level."""
    for seed in range(2):
        Y, r, s = _room(seed)
        below = _calibrate(Y, _heights(r[:, 2], range(4)), seed, dim=3, side="below")
        assert below.success and _room_ok(below, r, s)
        above = _calibrate(Y, _heights(r[:, 2], range(4)), seed, dim=3, side="above")
        assert np.median(above.sources[:, 2]) > 2.9  # the mirror image, as stated
