"""Malformed ``calibrate toa`` / ``reproduce lps`` inputs found by the fuzz pass of this stop:
each is refused with one named line and exit 2, before any costly work or any file written."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from selfcal.cli import main


def _run(args: list[str]):  # type: ignore[no-untyped-def]
    return CliRunner().invoke(main, [str(a) for a in args], catch_exceptions=True)


def _network(path: Path) -> Path:
    g = np.random.default_rng(0)
    r, s = g.uniform(0, 5, (8, 3)), g.uniform(0, 5, (10, 3))
    np.savetxt(path, np.linalg.norm(r[:, None] - s[None], axis=-1) + g.normal(0, 0.01, (8, 10)), delimiter=",")
    return path


@pytest.mark.parametrize("case,match", [
    # one receiver and 200000 columns: refused by the count check, not after the time-order test
    ("one-row-wide", "too-few-receivers"),
    # a noise whose square overflows the chi-square sums (was a leaked OverflowError)
    ("noise-1e308", "noise: 1e+308"),
    # a sample rate beyond any timing hardware (was exit 0 on a network of 1e-17 m)
    ("sample-rate-1e20", "beyond any timing hardware"),
])
def test_calibrate_toa_refuses_by_name(tmp_path: Path, case: str, match: str) -> None:
    out = tmp_path / "r.json"
    if case == "one-row-wide":
        f = tmp_path / "w.csv"
        f.write_text(",".join(["1"] * 200000) + "\n")
        args = ["calibrate", "toa", f, "-o", out]
    else:
        f = _network(tmp_path / "m.csv")
        extra = ["--noise", "1e308"] if case == "noise-1e308" else ["--unit", "samples", "--speed", "343",
                                                                    "--sample-rate", "1e20"]
        args = ["calibrate", "toa", f, *extra, "-o", out]
    res = _run(args)
    assert res.exit_code == 2, res.output
    assert match in res.output, res.output
    assert "Traceback" not in res.output
    assert not out.exists()


def test_reproduce_lps_on_a_device_file_names_it(tmp_path: Path) -> None:
    res = _run(["reproduce", "lps", "--data", "/dev/null", "--out", tmp_path / "o"])
    assert res.exit_code == 2, res.output
    assert "not a regular file" in res.output
    assert not (tmp_path / "o").exists()
