"""Reproducers of the defects found by the fuzz sweep over every command (this stop): each was a
hang, an internal error or an output checked only after the work. Contract: exit 2, one
``selfcal: error:`` line naming the option, nothing written, no work started."""

from __future__ import annotations

import os
from pathlib import Path

import pytest
from click.testing import CliRunner

from selfcal.cli import main

from .test_cli import check_contract, snapshot


@pytest.mark.parametrize("args,match", [
    # an iteration cap of 1e20 started a reproduction that never ends
    (["reproduce", "delays", "--max-iter", "99999999999999999999", "--out", "{d}/o"], "--max-iter"),
    (["reproduce", "delays", "--cap-120", "2000000", "--out", "{d}/o"], "--cap-120"),
    # 1e20 rounds: an OverflowError (internal error); 1e5 rounds: 15 GB of signals not guarded
    (["simulate", "conference", "--rounds", "99999999999999999999", "--units", "5", "--out", "{d}/rec"], "rounds"),
    (["simulate", "conference", "--rounds", "100000", "--units", "5", "--sample-rate", "8000", "--out", "{d}/rec"],
     "rounds"),
    # 1e20 simulated LPS flights: never ended
    (["reproduce", "lps", "--data", "{d}", "--simulate", "99999999999999999999", "--out", "{d}/o"], "--simulate"),
    # a negative image-source order: pyroomacoustics' ValueError (internal error)
    (["simulate", "conference", "--max-order", "-1", "--units", "5", "--out", "{d}/rec"], "--max-order"),
    # a grid step of 1e-4 m: 2.5e9 grid points (a hang); 1e-300: an internal error
    (["reproduce", "aoa", "--step", "0.0001", "--out", "{d}/o"], "grid points"),
    (["reproduce", "aoa", "--step", "1e-300", "--out", "{d}/o"], "grid points"),
    # shorter than Fig. 4's 50-step moving average: an internal error of the plot
    (["reproduce", "slac", "--minutes", "0.05", "--out", "{d}/o"], "moving average"),
    (["reproduce", "slac", "--minutes", "1e-300", "--out", "{d}/o"], "moving average"),
])
def test_sweep_findings_refused_up_front(tmp_path: Path, args: list[str], match: str) -> None:
    before = snapshot(tmp_path)
    res = CliRunner().invoke(main, [a.format(d=tmp_path) for a in args], catch_exceptions=True)
    code, _, err = check_contract(res, before, snapshot(tmp_path))
    assert code == 2 and match in err, err


@pytest.mark.parametrize("opt", ["--csv", "--tum"])
@pytest.mark.parametrize("kind", ["dir", "devnull-link"])
def test_slac_plaza_trajectory_outputs_checked_before_the_run(tmp_path: Path, opt: str, kind: str) -> None:
    """--csv / --tum of slac plaza were checked only when written, after the whole run."""
    target = tmp_path / "t"
    if kind == "dir":
        target.mkdir()
    else:
        os.symlink("/dev/null", target)
    missing = tmp_path / "no-such.mat"  # would be named if the outputs were not checked first
    before = snapshot(tmp_path)
    res = CliRunner().invoke(main, ["slac", "plaza", str(missing), opt, str(target), "-o", str(tmp_path / "r.json")])
    code, _, err = check_contract(res, before, snapshot(tmp_path))
    assert code == 2 and opt in err and "no-such" not in err, err


@pytest.mark.parametrize("hint,match", [("1_0,1,1", "decimal"), ("0x1,1,1", "decimal"), ("nan,1,1", "decimal"),
                                        ("1e308,1,1", "another unit"), ("1e400,1,1", "finite")])
def test_aoa_hint_strict_numbers(tmp_path: Path, hint: str, match: str) -> None:
    """--hint took Python's float(): 1_0 read as 10, and a hint of 1e308 gave a (failed) pose."""
    import numpy as np

    g = np.random.default_rng(0)
    np.savetxt(tmp_path / "b.csv", g.uniform(-5, 5, (5, 3)), delimiter=",")
    u = g.normal(size=(5, 3))
    np.savetxt(tmp_path / "u.csv", u / np.linalg.norm(u, axis=1, keepdims=True), delimiter=",")
    before = snapshot(tmp_path)
    res = CliRunner().invoke(main, ["locate", "aoa", str(tmp_path / "b.csv"), str(tmp_path / "u.csv"), "--hint", hint,
                                    "-o", str(tmp_path / "r.json")])
    code, _, err = check_contract(res, before, snapshot(tmp_path))
    assert code == 2 and match in err, err


@pytest.mark.parametrize("max_order", [-1, 1.5, True])
def test_simulate_conference_api_refuses_bad_max_order(max_order: object) -> None:
    import numpy as np

    from selfcal.acoustics.room import simulate_conference
    from selfcal.errors import InputError
    from selfcal.scenarios.conference import conference_scene

    scene = conference_scene(5, (6.0, 6.0, 3.0), rng=np.random.default_rng(0))
    with pytest.raises(InputError, match="max_order"):
        simulate_conference(scene, max_order=max_order, sample_rate=8000, progress=False)  # type: ignore[arg-type]
