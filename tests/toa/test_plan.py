"""``selfcal plan`` / selfcal.toa.plan: predicted error bars and ambiguities of a UWB layout (issue 29)."""

from __future__ import annotations

import json
import warnings

import numpy as np
import pytest

from selfcal.toa.plan import layout_ambiguities, plan_layout, positioning_std

ROOM = np.array([8.0, 6.0, 3.0])


def _layout(seed, flat_path=False, flat_anchors=False):
    g = np.random.default_rng(seed)
    A = np.array([[0.2, 0.2, 2.8], [7.8, 0.3, 2.7], [7.7, 5.8, 2.85], [0.3, 5.7, 2.75], [4.0, 0.2, 2.9],
                  [4.1, 5.8, 1.2], [0.2, 3.0, 0.4]]) + g.uniform(-0.1, 0.1, (7, 3))
    if flat_anchors:
        A[:, 2] = 2.8
    t = np.linspace(0, 1, 150)
    f = g.uniform(1, 3, 3)
    P = np.c_[4 + 3 * np.sin(2 * np.pi * f[0] * t), 3 + 2.3 * np.sin(2 * np.pi * f[1] * t + 1),
              1.2 + 0.6 * np.sin(2 * np.pi * f[2] * t)]
    if flat_path:
        P[:, 2] = 1.2
    return A, P


@pytest.mark.parametrize("seed", range(5))
def test_ambiguities_are_named_exactly_when_a_set_is_planar(seed):
    A, P = _layout(seed)
    assert layout_ambiguities(A, P) == []
    kinds = [a.kind for a in layout_ambiguities(*_layout(seed, flat_path=True))]
    assert kinds == ["anchor-mirror"]
    amb = layout_ambiguities(*_layout(seed, flat_anchors=True))
    assert [a.kind for a in amb] == ["tag-mirror"]
    assert abs(abs(amb[0].plane_normal[2]) - 1) < 1e-9  # the ceiling plane


def test_anchor_mirror_through_a_flat_path_has_the_same_ranges():
    """Why the ambiguity is real: reflecting one anchor through the path's plane changes none of its ranges."""
    A, P = _layout(0, flat_path=True)
    amb = layout_ambiguities(A, P)[0]
    n, c = amb.plane_normal, amb.plane_point
    B = A.copy()
    B[2] = A[2] - 2 * ((A[2] - c) @ n) * n
    D = np.linalg.norm(A[:, None] - P[None], axis=2)
    E = np.linalg.norm(B[:, None] - P[None], axis=2)
    assert np.abs(D - E).max() < 1e-9 and np.abs(A[2] - B[2]).max() > 1.0


def test_positioning_bound_matches_monte_carlo_least_squares():
    """The map's bound against the spread of least-squares positions over 400 noisy draws
    (Gauss-Newton from the truth): within 10 % (the Monte Carlo std of a std estimate from
    400 draws is ~3.5 %)."""
    from selfcal.toa.verdict.crossval import locate_sources

    A, _ = _layout(1)
    g = np.random.default_rng(0)
    x = np.array([3.0, 2.0, 1.0])
    bound = positioning_std(A, [x], 0.05)[0]
    D = np.linalg.norm(A - x, axis=1)
    Y = D[:, None] + 0.05 * g.standard_normal((len(A), 400))
    X, _, _, _ = locate_sources(Y, A, start=np.repeat(x[None], 400, axis=0))
    emp = np.sqrt(np.mean(np.sum((X - x) ** 2, axis=1)))
    assert emp == pytest.approx(bound, rel=0.1)


def test_anchor_error_bars_match_the_solvers_covariance():
    """The plan's anchor std is the CRLB at the plan; the solver's own covariance of a fit
    of simulated ranges of that plan (refined from the truth, per-anchor offsets) reports
    the same error bars to within 15 % (its noise estimate and the fitted geometry differ
    from the truth by the noise)."""
    from selfcal.toa.engine.nls import refine_toa

    A, P = _layout(2)
    plan = plan_layout(A, P, noise=0.05, offsets="receivers", room=ROOM)
    g = np.random.default_rng(2)
    Y = np.linalg.norm(A[:, None] - P[None], axis=2) + g.normal(-0.1, 0.1, 7)[:, None] + 0.05 * g.standard_normal(
        (7, len(P)))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        sol = refine_toa(Y, A, P, offsets="receivers")
    fit_std = np.sqrt(np.trace(sol.receiver_cov, axis1=1, axis2=2))
    np.testing.assert_allclose(fit_std, plan.anchor_std, rtol=0.15)


def test_plan_refuses_too_few_anchors():
    from selfcal.errors import InputError

    A, P = _layout(0)
    with pytest.raises(InputError):
        plan_layout(A[:3], P)


def test_cli_plan_writes_the_map_and_names_the_mirror(tmp_path):
    from click.testing import CliRunner

    from selfcal.cli import main

    for flat, code in ((False, 0), (True, 1)):
        A, P = _layout(3, flat_path=flat)
        a = tmp_path / "a.csv"
        a.write_text("name,x,y,z\n" + "".join(f"A{i},{x},{y},{z}\n" for i, (x, y, z) in enumerate(A)))
        p = tmp_path / "p.csv"
        np.savetxt(p, P, delimiter=",", header="x,y,z", comments="")
        out, png = tmp_path / f"o{flat}.json", tmp_path / f"m{flat}.png"
        res = CliRunner().invoke(main, ["plan", str(a), str(p), "--room", "8x6x3", "--out", str(out),
                                        "--plot", str(png)])
        assert res.exit_code == code, res.output
        data = json.loads(out.read_text())
        assert set(data["anchors"]) == {f"A{i}" for i in range(7)} and png.stat().st_size > 1000
        assert ("anchor-mirror" in res.output) == flat
        assert [x["kind"] for x in data["ambiguities"]] == (["anchor-mirror"] if flat else [])
    bad = CliRunner().invoke(main, ["plan", str(a), str(p), "--room", "8x6", "--out", str(tmp_path / "x.json")])
    assert bad.exit_code == 2 and "Traceback" not in bad.output
