"""What a run says it wrote, how it names nodes, which paths it refuses (issue 32), through the CLI."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from selfcal.cli import main


def invoke(*args: object):
    return CliRunner().invoke(main, [str(a) for a in args])


def _matrix(tmp_path: Path, seed: int) -> Path:
    rng = np.random.default_rng(seed)
    r, s = rng.uniform(0, 6, (7, 3)), rng.uniform(0, 6, (9, 3))
    D = np.linalg.norm(r[:, None] - s[None], axis=2) + rng.normal(0, 0.01, (7, 9))
    p = tmp_path / "m.csv"
    np.savetxt(p, D, delimiter=",")
    return p


@pytest.mark.parametrize("seed", range(3))
def test_last_line_lists_every_file_and_csv_names_are_0_based(tmp_path: Path, seed: int) -> None:
    m = _matrix(tmp_path, seed)
    files = [tmp_path / "r.json", tmp_path / "r.csv", tmp_path / "fig.png"]
    res = invoke("calibrate", "toa", m, "-o", files[0], "--csv", files[1], "--plot", files[2])
    assert res.exit_code == 0, res.output
    last = res.stdout.strip().splitlines()[-1]
    assert last.startswith("wrote ") and all(str(f) in last for f in files) and all(f.is_file() for f in files)
    rows = list(csv.reader(files[1].open()))
    names = [r[1] for r in rows[1:]]
    # one numbering everywhere: the CSV's names are --known / --frame's r<i> / s<j> and the JSON's
    assert names[:7] == [f"r{i}" for i in range(7)] and names[7] == "s0"
    assert json.loads(files[0].read_text())["receiver_names"][:2] == ["r0", "r1"]
    P = json.loads(files[0].read_text())["receivers"]
    assert np.allclose([float(v) for v in rows[1][2:5]], P[0])


def test_output_in_a_missing_folder_is_refused_and_nothing_is_created(tmp_path: Path) -> None:
    m = _matrix(tmp_path, 0)
    target = tmp_path / "no" / "such" / "x.json"
    res = invoke("calibrate", "toa", m, "-o", target)
    assert res.exit_code == 2 and res.stderr.count("\n") == 1 and "does not exist" in res.stderr
    assert not (tmp_path / "no").exists()


def test_excel_na_cells_are_missing_entries(tmp_path: Path) -> None:
    m = _matrix(tmp_path, 1)
    rows = m.read_text().splitlines()
    cells = [r.split(",") for r in rows]
    cells[0][0] = "#N/A"  # first cell of a line: not a comment line either
    cells[3][5] = "#N/A"
    m.write_text("\n".join(",".join(c) for c in cells) + "\n")
    res = invoke("calibrate", "toa", m, "-o", tmp_path / "r.json")
    assert res.exit_code == 0, res.output
    assert "7 receivers x 9 sources" in res.stdout and "2 missing" in res.stdout


def test_help_states_the_levels_the_tests_use() -> None:
    from selfcal.toa.recipes.common_offset import COMMON_OFFSET_ALPHA
    from selfcal.toa.recipes.recipes import TIME_ORDER_ALPHA

    text = " ".join(invoke("calibrate", "toa", "--help").stdout.split())
    assert f"finds it (p < {COMMON_OFFSET_ALPHA:g})" in text
    assert f"in time order (p < {TIME_ORDER_ALPHA:.0e})".replace("e-03", "e-3") in text


def test_output_folder_in_a_missing_folder_is_refused(tmp_path: Path) -> None:
    """One new output folder is made (``demo --out DIR``), never a chain of them (a typo)."""
    res = invoke("demo", "--out", tmp_path / "no" / "such" / "demo")
    assert res.exit_code == 2 and "does not exist" in res.stderr and not (tmp_path / "no").exists()
