"""The heading-unit detection of ``load_plaza`` (convention 5) on synthetic CMU logs.

A log in radians loads as is (no warning); the same log written in degrees (a 0..360
compass column and degree increments) is detected column by column, converted and warned
about (:class:`PlazaFormatWarning`), and loads to the same arrays; ``heading_units=``
states the unit and wins over the detection, silently. The detection's statistics have
wide margins on these logs (mean resultant ~1 for the right unit, near the Rayleigh level
1/sqrt(n) or well below 0.7 - 0.3 for the wrong one; turn ratios 1 or 57.3 against the
factor-2 windows), so every seed and heading offset must decide correctly.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from scipy.io import savemat

from selfcal.cli import main
from selfcal.datasets.plaza import PlazaFormatWarning, heading_units, load_plaza
from selfcal.errors import InputError
from selfcal.geometry import wrap_angle

from .cmu_logs import cmu_log

SEEDS = range(4)
OFFSETS = (0.0, np.pi, -1.0)


def _save(tmp_path: Path, m: dict, name: str = "log.mat") -> Path:  # type: ignore[type-arg]
    p = tmp_path / name
    savemat(p, m)
    return p


def _load(p: Path, **kw: object) -> tuple[object, list[str]]:
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        d = load_plaza(p, **kw)  # type: ignore[arg-type]
    return d, [str(w.message) for w in caught if issubclass(w.category, PlazaFormatWarning)]


@pytest.mark.parametrize("seed", SEEDS)
@pytest.mark.parametrize("offset", OFFSETS)
def test_detection_statistic_decides_both_units(seed: int, offset: float) -> None:
    m_rad, _ = cmu_log(seed, heading_offset=offset, duration=120.0)
    m_deg, _ = cmu_log(seed, heading_offset=offset, duration=120.0, heading_degrees=True)
    gt_u, dr_u, st = heading_units(m_rad["GT"][np.argsort(m_rad["GT"][:, 0])], m_rad["DR"])
    assert (gt_u, dr_u) == ("rad", "rad"), st
    assert st["r_rad"] > 0.9 and abs(np.log(st["turn_ratio"])) < np.log(1.5), st
    gt_u, dr_u, st = heading_units(m_deg["GT"][np.argsort(m_deg["GT"][:, 0])], m_deg["DR"])
    assert (gt_u, dr_u) == ("deg", "deg"), st
    assert st["r_deg"] > 0.9 and abs(np.log(st["turn_ratio"] / np.rad2deg(1.0))) < np.log(1.5), st


@pytest.mark.parametrize("seed", SEEDS)
def test_radians_stay_and_degrees_are_converted_with_a_warning(tmp_path: Path, seed: int) -> None:
    m_rad, tr = cmu_log(seed, heading_offset=np.pi, duration=120.0)
    m_deg, _ = cmu_log(seed, heading_offset=np.pi, duration=120.0, heading_degrees=True)
    d_rad, w_rad = _load(_save(tmp_path, m_rad, "rad.mat"))
    assert w_rad == []
    d_deg, w_deg = _load(_save(tmp_path, m_deg, "deg.mat"))
    assert len(w_deg) == 2 and "GT heading column is in degrees" in w_deg[0] and "DR heading" in w_deg[1], w_deg
    # the same log whatever the unit: headings against the truth, increments against each other
    for d in (d_rad, d_deg):
        assert np.max(np.abs(wrap_angle(d.gt[:, 2] - tr.poses[:, 2]))) < 1e-9  # type: ignore[attr-defined]
    np.testing.assert_allclose(d_deg.odo, d_rad.odo, atol=1e-12)  # type: ignore[attr-defined]
    np.testing.assert_allclose(d_deg.gt[:, :2], d_rad.gt[:, :2])  # type: ignore[attr-defined]


def test_one_column_in_degrees_is_converted_alone(tmp_path: Path) -> None:
    """GT in degrees, DR in radians (two loggers): only GT is converted and warned about."""
    m_rad, tr = cmu_log(5, duration=120.0)
    m_deg, _ = cmu_log(5, duration=120.0, heading_degrees=True)
    m = dict(m_rad, GT=m_deg["GT"])
    d, w = _load(_save(tmp_path, m))
    assert len(w) == 1 and "GT heading column" in w[0], w
    assert np.max(np.abs(wrap_angle(d.gt[:, 2] - tr.poses[:, 2]))) < 1e-9  # type: ignore[attr-defined]
    d_ref, _ = _load(_save(tmp_path, m_rad, "ref.mat"))
    np.testing.assert_allclose(d.odo, d_ref.odo)  # type: ignore[attr-defined]


def test_explicit_heading_units_win(tmp_path: Path) -> None:
    m_rad, tr = cmu_log(6, duration=120.0)
    m_deg, _ = cmu_log(6, duration=120.0, heading_degrees=True)
    p_rad, p_deg = _save(tmp_path, m_rad, "rad.mat"), _save(tmp_path, m_deg, "deg.mat")
    auto_rad, _ = _load(p_rad)
    auto_deg, _ = _load(p_deg)
    # stating the right unit: the detection's result, without its warning
    d, w = _load(p_rad, heading_units="rad")
    assert w == [] and np.array_equal(d.gt, auto_rad.gt) and np.array_equal(d.odo, auto_rad.odo)  # type: ignore[attr-defined]
    d, w = _load(p_deg, heading_units="deg")
    assert w == [] and np.allclose(d.gt, auto_deg.gt) and np.allclose(d.odo, auto_deg.odo)  # type: ignore[attr-defined]
    # stating the wrong unit is obeyed too (the caller's word wins): no conversion / a conversion
    d, w = _load(p_deg, heading_units="rad")
    assert w == []
    gt_sorted = m_deg["GT"][np.argsort(m_deg["GT"][:, 0], kind="stable")]
    np.testing.assert_allclose(d.gt[:, 2], wrap_angle(gt_sorted[:, 3] + float(m_deg["init_heading_offset"][0, 0])))  # type: ignore[attr-defined]
    d, w = _load(p_rad, heading_units="deg")
    assert w == []
    np.testing.assert_allclose(d.odo[:, 1], np.deg2rad(auto_rad.odo[:, 1]))  # type: ignore[attr-defined]
    # None = auto
    d, w = _load(p_deg, heading_units=None)
    assert len(w) == 2 and np.allclose(d.gt, auto_deg.gt)  # type: ignore[attr-defined]


@pytest.mark.parametrize("value", ["degrees", "RAD", "", 1, 1.5])
def test_bad_heading_units_refused(tmp_path: Path, value: object) -> None:
    m, _ = cmu_log(0, duration=60.0)
    with pytest.raises(InputError, match="heading_units must be one of"):
        load_plaza(_save(tmp_path, m), heading_units=value)  # type: ignore[arg-type]


def test_heading_column_in_neither_unit_is_refused(tmp_path: Path) -> None:
    """A heading column unrelated to the motion and beyond one turn fits neither unit: refused."""
    m, _ = cmu_log(7, duration=120.0)
    g = np.random.default_rng(7)
    m["GT"] = m["GT"].copy()
    m["GT"][:, 3] = g.uniform(0, 360, m["GT"].shape[0])
    with pytest.raises(InputError, match="neither as radians"):
        load_plaza(_save(tmp_path, m))
    # stated, it is taken as given (the caller knows the column)
    d = load_plaza(_save(tmp_path, m, "b.mat"), heading_units="deg")
    assert np.all(np.isfinite(d.gt))


def test_cli_heading_units_option(tmp_path: Path) -> None:
    res = CliRunner().invoke(main, ["slac", "plaza", str(tmp_path / "x.mat"), "--heading-units", "grad",
                                    "-o", str(tmp_path / "r.json")])
    assert res.exit_code == 2 and "--heading-units" in res.stderr and len(res.stderr.strip().splitlines()) == 1
    assert list(tmp_path.iterdir()) == []
