"""load_lps on flights exported differently from data4 / data5 (other flights of the set).

Each variant is written with ``scipy.io.savemat`` from a seeded synthetic flight and read
back: the ranges must come back exactly, comparison-only fields may be absent (NaN, a
warning), and layouts that cannot be read say why in one line (InputError), never a bare
NumPy error or a silently cast value.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pytest
import scipy.io

from selfcal.datasets.lps import LpsFormatWarning, load_lps
from selfcal.errors import InputError


def _flight(seed: int, n: int = 40, m: int = 6) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    G = rng.uniform(-4, 4, (3, m))
    T = rng.uniform(-2, 2, (3, n))
    d = np.linalg.norm(G[:, :, None] - T[:, None, :], axis=0) - 0.15 + 0.05 * rng.standard_normal((m, n))
    d[rng.random((m, n)) < 0.1] = np.nan
    return {"d": d, "Gtr": G, "GTs_resamp": T, "ropt": G + 0.1, "sopt": T + 0.1,
            "GTs_resamp_ok": np.ones((1, n), bool)}


def _save(tmp: Path, fields: dict[str, np.ndarray], struct: bool = True) -> Path:
    p = tmp / "flight.mat"
    scipy.io.savemat(p, {"data": fields} if struct else fields)
    return p


@pytest.mark.parametrize("seed", range(3))
@pytest.mark.parametrize("drop", ["ropt", "sopt", "GTs_resamp", "GTs_resamp_ok"])
def test_comparison_fields_are_optional(tmp_path: Path, seed: int, drop: str) -> None:
    f = _flight(seed)
    kept = {k: v for k, v in f.items() if k != drop}
    with warnings.catch_warnings(record=True) as w:
        warnings.simplefilter("always")
        data = load_lps(_save(tmp_path, kept))
    np.testing.assert_array_equal(data.ranges, f["d"])  # the measurements, bit for bit
    np.testing.assert_array_equal(data.anchors_true, f["Gtr"].T)
    absent = {"ropt": data.authors_anchors, "sopt": data.authors_tag, "GTs_resamp": data.tag_true}
    if drop in absent:
        assert np.isnan(absent[drop]).all()
        assert any(issubclass(x.category, LpsFormatWarning) and drop in str(x.message) for x in w)


def test_top_level_variables_read_like_the_struct(tmp_path: Path) -> None:
    f = _flight(7)
    a = load_lps(_save(tmp_path, f, struct=True))
    b = load_lps(_save(tmp_path, f, struct=False))
    for x, y in [(a.ranges, b.ranges), (a.anchors_true, b.anchors_true), (a.tag_true, b.tag_true),
                 (a.authors_anchors, b.authors_anchors)]:
        np.testing.assert_array_equal(x, y)


def test_complex_ranges_are_refused_not_cast(tmp_path: Path) -> None:
    f = _flight(1)
    f["d"] = f["d"] + 1j
    with pytest.raises(InputError, match="complex"):
        load_lps(_save(tmp_path, f))


def test_transposed_ranges_are_named(tmp_path: Path) -> None:
    f = _flight(2)
    f["d"] = f["d"].T.copy()
    with pytest.raises(InputError, match="transposed"):
        load_lps(_save(tmp_path, f))


def test_required_fields_are_named(tmp_path: Path) -> None:
    f = _flight(3)
    del f["Gtr"]
    with pytest.raises(InputError, match="Gtr"):
        load_lps(_save(tmp_path, f))


def test_reproduce_scores_a_flight_without_the_authors_estimate(tmp_path: Path) -> None:
    """A flight without ropt / sopt is calibrated and scored; the authors' columns are null."""
    import json

    from click.testing import CliRunner

    from selfcal.cli import main
    from selfcal.experiments.lps import RECOMMENDED, simulate_uwb_flight

    sim = simulate_uwb_flight(4, n_positions=150)  # smooth trajectory, biases, spikes
    f = {"d": sim["ranges"], "Gtr": sim["anchors"].T, "GTs_resamp": sim["tag"].T}
    scipy.io.savemat(tmp_path / "data9.mat", {"data": f})
    r = CliRunner().invoke(main, ["reproduce", "lps", "--data", str(tmp_path / "data9.mat"), "-o",
                                  str(tmp_path / "out"), "--simulate", "0", "--variants", RECOMMENDED])
    assert r.exit_code == 0, r.output
    entry = json.loads((tmp_path / "out" / "lps.json").read_text())["flights"]["data9"]
    assert entry["authors_anchor_rmse"] is None and entry["authors_tag_rmse"] is None
    # scored against the motion capture all the same (finite; its size is the recipe's business)
    assert np.isfinite(entry["variants"][RECOMMENDED]["anchor_rmse"])
    assert np.isfinite(entry["variants"][RECOMMENDED]["tag_rmse"])
