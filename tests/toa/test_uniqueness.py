"""Unique or honest (issue 27): no confident answer the data do not single out.

Specification, over many random draws per family (``uniqueness_families.py``):

- flip families (2-D collinear receivers, 3-D coplanar receivers, parallel planes,
  collinear receivers in 3-D, minimal 2-D 3 x 3 and 3-D 4 x 6 noise-free, a tag walked at
  one height under ceiling anchors): every draw is either right within 3 of its own error
  bars (sqrt of the trace of its covariance, after the rigid alignment onto the truth) or
  flagged (not a success);
- generic well-posed networks (2-D / 3-D 8 x 10, with the noise given, with receiver
  offsets): the result is flagged in at most 1 % of the draws. Why 1 %: the uniqueness test
  flags an alternative only when a likelihood-ratio test at level 1e-3 cannot reject it;
  on a generic network every flip misfits by many noise units, so the flags left are the
  other tests' (chi-square / geometry at 1e-3, 0.05 for the permutation test with its
  cross-validated companion) plus chance -- 1 % is what the issue asks, and a rate above it
  would make exit 1 uninformative;
- contradicting known nodes (positions x 2, collinear anchors the ranges contradict) and
  forced models (``dim=2`` on 3-D data, ``offsets="none"`` on data with delays) are caught.

The default run takes a reduced number of draws (deterministic seeds); the ``slow`` ones
take 200 per family (``pytest -m slow``).

Measured (200 draws a family, ``solve_toa`` defaults, noise unknown unless stated; "wrong" =
exit 0 with a node outside 3 of its error bars; loaded 2-core machine, CPU s):

=====================  =======  =====  ====
family                 flagged  wrong  s
=====================  =======  =====  ====
collinear-2d           200      0      85
coplanar-3d            200      0      92
parallel-planes        200      0      83
collinear-3d           199      0      101
tag-one-height         200      0      80
minimal-2d (3 x 3)     200      0      10
minimal-3d (4 x 6)     200      0      21
generic-2d (8 x 10)    0        3      54
generic-3d (8 x 10)    0        5      67
generic-3d, noise      2        1      15
generic-3d, offsets    0        5      162
=====================  =======  =====  ====

The 2 flags of "generic-3d, noise" are the chi-square test's (p = 1.6e-4, 8.2e-4), none the
uniqueness test's. The "wrong" draws of the generic families are nodes at 3.1-3.7 of their
error bars (generic-2d: 3.2-3.3 with the noise estimated 13-20 % low; generic-3d: 3.1-3.7,
the noise estimated 0.64-1.04 cm for 1 cm): the tails of the local error bars, not a second
solution (no alternative within the test's reach); they are not asserted here.
"""

from __future__ import annotations

import json
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from selfcal.cli import main
from selfcal.toa import solve_toa, toa_model
from selfcal.toa.frame.frame import calibrate_in_frame
from selfcal.toa.verdict.model_test import forced_model_test
from selfcal.toa.verdict.uniqueness import uniqueness_test

sys.path.insert(0, str(Path(__file__).resolve().parent))
from uniqueness_families import FAMILIES, GENERIC, draw  # noqa: E402

REDUCED = 6  # draws per family in the default run
FULL = 200  # draws per family in the slow run


def _sweep(family, seeds):
    wrong = []
    flagged = 0
    for seed in seeds:
        out = draw(family, seed)
        flagged += out["flagged"]
        if not out["flagged"] and not out["right"]:
            wrong.append(seed)
    return flagged, wrong


# ----------------------------------------------------------------------------- the test itself


def test_collinear_receivers_leave_every_source_its_mirror_image():
    """Exact data, receivers on a line: each source's reflection fits exactly (a flip)."""
    for seed in range(10):
        g = np.random.default_rng(seed)
        r = np.c_[np.sort(g.uniform(-4, 4, 5)), np.zeros(5)]
        s = g.uniform(-4, 4, (6, 2))
        s[:, 1] += np.sign(s[:, 1]) * 0.5  # off the line: their mirror images are distinct
        u = uniqueness_test(toa_model(r, s), r, s, n_params=2 * 11 - 3, noise=0.01)
        assert not u.passed
        assert u.ambiguous_sources.all() and not u.ambiguous_receivers.any()
        # the alternative of each source is its reflection through the line y = 0
        assert np.allclose(u.source_alternatives, s * [1, -1], atol=1e-6)


def test_a_generic_network_has_no_alternative():
    for seed in range(10):
        g = np.random.default_rng(seed)
        r, s = g.uniform(0, 10, (8, 3)), g.uniform(0, 10, (10, 3))
        u = uniqueness_test(toa_model(r, s) + g.normal(0, 0.01, (8, 10)), r, s, n_params=3 * 18 - 6, noise=0.01)
        assert u.passed, u.message()


def test_json_carries_the_ambiguous_nodes_and_their_alternatives():
    Y, r, s, kw = FAMILIES["collinear-2d"](0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        res = solve_toa(Y, rng=0, **kw)
    d = json.loads(json.dumps(res.to_dict()))
    assert not res.success
    assert d["ambiguous_sources"] == [int(j) for j in np.flatnonzero(res.ambiguous_sources)]
    assert d["ambiguous_sources"]
    alt = np.array(d["uniqueness"]["source_alternatives"], dtype=float)
    assert np.isfinite(alt[d["ambiguous_sources"]]).all()
    assert d["uniqueness"]["alpha"] == 1e-3


def test_minimal_problem_is_never_a_success():
    for fam in ("minimal-2d", "minimal-3d"):
        for seed in range(5):
            out = draw(FAMILIES[fam], seed)
            assert out["flagged"], (fam, seed)
            assert out["result"].uniqueness.minimal
            # a given noise does not make a minimal problem testable
            Y, r, s, kw = FAMILIES[fam](seed)
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                res = solve_toa(Y, rng=seed, noise=0.01, **kw)
            assert not res.success and res.uniqueness.minimal


# ----------------------------------------------------------------------------- the families


@pytest.mark.parametrize("name", sorted(FAMILIES))
def test_flip_family_is_right_or_flagged_reduced(name):
    flagged, wrong = _sweep(FAMILIES[name], range(REDUCED))
    assert not wrong, f"{name}: exit 0 with a node outside 3 error bars at seeds {wrong}"


@pytest.mark.parametrize("name", sorted(GENERIC))
def test_generic_networks_are_not_flagged_reduced(name):
    """At most 1 of the reduced draws (the 1 % bound cannot be resolved on 6 draws; the slow test does)."""
    flagged, _ = _sweep(GENERIC[name], range(REDUCED))
    assert flagged <= 1, f"{name}: {flagged} of {REDUCED} well-posed draws flagged"


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(FAMILIES))
def test_flip_family_is_right_or_flagged(name):
    flagged, wrong = _sweep(FAMILIES[name], range(FULL))
    assert not wrong, f"{name}: exit 0 with a node outside 3 error bars at seeds {wrong}"


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(GENERIC))
def test_generic_networks_false_alarms_at_most_one_percent(name):
    flagged, _ = _sweep(GENERIC[name], range(FULL))
    assert flagged <= 0.01 * FULL, f"{name}: {flagged} of {FULL} well-posed draws flagged"


# ----------------------------------------------------------------------------- known nodes, models


def _room(seed):
    g = np.random.default_rng([27, seed])
    r = np.array([[0.5, 0.5, 2.9], [7.5, 0.5, 2.9], [7.5, 5.5, 2.9], [0.5, 5.5, 2.9], [0.5, 3, 0.3], [7.5, 3, 0.4]])
    s = np.c_[g.uniform(1, 7, 30), g.uniform(1, 5, 30), g.uniform(0.5, 2.0, 30)]
    return r, s, toa_model(r, s) + g.normal(0, 0.01, (6, 30))


def _framed(Y, known):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return calibrate_in_frame(Y, known=known, rng=0)


def test_right_known_nodes_pass_and_wrong_ones_are_named():
    for seed in range(4):
        r, s, Y = _room(seed)
        good = _framed(Y, {f"r{i}": r[i] for i in range(6)})
        assert good.frame.known_test["passed"]
        assert good.success, good.message
        doubled = _framed(Y, {f"r{i}": 2 * r[i] for i in range(5)})
        assert not doubled.success and not doubled.frame.known_test["passed"]
        assert "contradict" in doubled.message
        # four anchors declared on a line the ranges contradict
        line = _framed(Y, {f"r{i}": np.array([2.0 * i, 0.0, 2.9]) for i in range(4)})
        assert not line.success and line.frame.known_test["disagreeing"]


def test_one_wrong_known_node_is_the_one_named():
    for seed in range(4):
        r, s, Y = _room(seed)
        known = {f"r{i}": r[i].copy() for i in range(6)}
        known["r2"] = r[2] + [1.5, 0.0, 0.0]
        res = _framed(Y, known)
        assert not res.success
        assert res.frame.known_test["disagreeing"][0] == "r2"


def test_coplanar_known_anchors_leave_the_mirror_reported():
    """Four ceiling anchors known: the mirror through the ceiling fits the ranges exactly."""
    for seed in range(4):
        r, s, Y = _room(seed)
        res = _framed(Y, {f"r{i}": r[i] for i in range(4)})
        assert not res.success
        assert res.ambiguous_sources.all() and res.ambiguous_receivers[4:].all()
        # the alternative of each source is its image through the plane z = 2.9
        alt = res.uniqueness.source_alternatives
        assert np.allclose(alt[:, 2], 2 * 2.9 - res.sources[:, 2], atol=1e-6)


def test_forced_models_are_tested_against_the_larger_one():
    for seed in range(5):
        g = np.random.default_rng([28, seed])
        r, s = g.uniform(0, 10, (8, 3)), g.uniform(0, 10, (10, 3))
        Y3 = toa_model(r, s) + g.normal(0, 0.001, (8, 10))
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            flat = solve_toa(Y3, dim=2, rng=0)
        t = forced_model_test(Y3, flat.receivers, flat.sources, offsets="none")
        assert not t.passed and t.better.startswith("dim=3")
        d = g.uniform(0, 2, 8)
        Yd = toa_model(r, s, d) + g.normal(0, 0.001, (8, 10))
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            plain = solve_toa(Yd, rng=0)
        t = forced_model_test(Yd, plain.receivers, plain.sources, offsets="none")
        assert not t.passed and t.better == "offsets=receivers"
        # the right model stands
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            right = solve_toa(Y3, rng=0)
        assert forced_model_test(Y3, right.receivers, right.sources, offsets="none").passed


# ----------------------------------------------------------------------------- the CLI


def _cli(*args):
    return CliRunner().invoke(main, ["calibrate", "toa", *map(str, args)])


def test_cli_names_the_ambiguous_nodes_and_the_remedy(tmp_path):
    Y, r, s, kw = FAMILIES["coplanar-3d"](1)
    path = tmp_path / "m.csv"
    np.savetxt(path, Y, delimiter=",")
    out = tmp_path / "o.json"
    res = _cli(path, "--out", out)
    assert res.exit_code == 1, res.output
    line = next(x for x in res.output.splitlines() if x.startswith("FAIL: ambiguous"))
    assert "known node off the plane" in line and "s" in line
    data = json.loads(out.read_text())
    assert data["ambiguous_sources"]


def test_cli_minimal_problem_exits_1(tmp_path):
    Y, r, s, kw = FAMILIES["minimal-2d"](0)
    path = tmp_path / "m.csv"
    np.savetxt(path, Y, delimiter=",")
    res = _cli(path, "--dim", 2, "--out", tmp_path / "o.json")
    assert res.exit_code == 1 and "FAIL: minimal problem" in res.output


def test_cli_contradicting_known_nodes_and_forced_dim_exit_1(tmp_path):
    r, s, Y = _room(0)
    path = tmp_path / "m.csv"
    np.savetxt(path, Y, delimiter=",")
    known = tmp_path / "k.csv"
    known.write_text("".join(f"r{i},{2 * float(r[i, 0])!r},{2 * float(r[i, 1])!r},{2 * float(r[i, 2])!r}\n" for i in range(5)))
    res = _cli(path, "--known", known, "--out", tmp_path / "o.json")
    assert res.exit_code == 1 and "contradict" in res.output
    res = _cli(path, "--dim", 2, "--out", tmp_path / "o2.json")
    assert res.exit_code == 1 and "use dim=3" in res.output
    known.write_text("".join(f"r{i},{float(r[i, 0])!r},{float(r[i, 1])!r},{float(r[i, 2])!r}\n" for i in range(6)))
    res = _cli(path, "--known", known, "--out", tmp_path / "o3.json")
    assert res.exit_code == 0, res.output
    # the four ceiling anchors alone: the mirror through the ceiling is reported, never chosen
    known.write_text("".join(f"r{i},{float(r[i, 0])!r},{float(r[i, 1])!r},{float(r[i, 2])!r}\n" for i in range(4)))
    res = _cli(path, "--known", known, "--offsets", "receivers", "--out", tmp_path / "o4.json")
    assert res.exit_code == 1 and "FAIL: ambiguous" in res.output and "mirror" in res.output
    assert json.loads((tmp_path / "o4.json").read_text())["ambiguous_sources"] == list(range(30))
    # ... and resolved by the user's statement: the tags are below the ceiling
    res = _cli(path, "--known", known, "--offsets", "receivers", "--side", "below", "--out", tmp_path / "o5.json")
    assert res.exit_code == 0, res.output
    got = np.array(json.loads((tmp_path / "o5.json").read_text())["sources"], float)
    assert np.abs(got - s).max() < 0.1
