"""selfcal.progress: a stage line on a terminal (name, done/total, elapsed), nothing otherwise."""

from __future__ import annotations

import io
import sys
import time

import numpy as np
import pytest
from click.testing import CliRunner

from selfcal import progress
from selfcal.cli import main


class Tty(io.StringIO):
    def isatty(self) -> bool:
        return True


def use_tty(monkeypatch: pytest.MonkeyPatch) -> Tty:
    """A terminal as stderr (set in the test body: pytest re-installs its capture after fixtures)."""
    stream = Tty()
    monkeypatch.setattr(sys, "stderr", stream)
    progress.set_quiet(False)
    return stream


def test_a_stage_on_a_terminal_names_itself_counts_and_times(monkeypatch: pytest.MonkeyPatch) -> None:
    fake_tty = use_tty(monkeypatch)
    with progress.stage("detect", total=3, unit="receivers") as bar:
        for _ in range(3):
            time.sleep(0.25)  # past tqdm's 0.2 s minimum redraw interval
            bar.update()
    text = fake_tty.getvalue()
    assert "detect" in text and "3/3" in text and "00:00" in text


def test_an_opaque_stage_keeps_its_elapsed_time_ticking(monkeypatch: pytest.MonkeyPatch) -> None:
    fake_tty = use_tty(monkeypatch)
    monkeypatch.setattr(progress, "REFRESH_S", 0.05)
    with progress.stage("calibrate"):
        time.sleep(0.3)  # no update(): only the refresh thread redraws
        progress.note("outlier round 2")  # from code that does not hold the bar
        time.sleep(0.1)
    assert fake_tty.getvalue().count("calibrate") >= 3
    assert "outlier round 2" in fake_tty.getvalue()
    progress.note("no stage running")  # nothing to write on: ignored


def test_quiet_and_non_terminals_draw_nothing(monkeypatch: pytest.MonkeyPatch) -> None:
    fake_tty = use_tty(monkeypatch)
    progress.set_quiet(True)
    try:
        assert list(progress.stage.iterate(range(4), "sweep")) == [0, 1, 2, 3]
    finally:
        progress.set_quiet(False)
    assert fake_tty.getvalue() == ""
    pipe = io.StringIO()  # not a terminal
    monkeypatch.setattr(sys, "stderr", pipe)
    assert list(progress.stage.iterate(range(4), "sweep")) == [0, 1, 2, 3]
    assert pipe.getvalue() == ""


def test_selfcal_q_silences_progress(tmp_path) -> None:
    rng = np.random.default_rng(0)
    r, s = rng.uniform(0, 5, (6, 3)), rng.uniform(0, 5, (8, 3))
    np.savetxt(tmp_path / "m.csv", np.linalg.norm(r[:, None] - s[None], axis=2), delimiter=",")
    CliRunner().invoke(main, ["-q", "calibrate", "toa", str(tmp_path / "m.csv"), "-o", str(tmp_path / "r.json")])
    assert not progress.enabled(Tty())
    CliRunner().invoke(main, ["calibrate", "toa", str(tmp_path / "m.csv"), "-o", str(tmp_path / "r.json")])
    assert progress.enabled(Tty())
