"""The installer's HTML report (issue 15): self-contained, complete, and loads in a real browser."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from selfcal.cli import main
from tests.acoustics.test_pipeline_faults import _make


@pytest.fixture(scope="module")
def report(tmp_path_factory) -> tuple[Path, str]:
    """A report of a recording with one occluded pair (so it has an outlier) and its CLI output."""
    d = tmp_path_factory.mktemp("report")
    rec = d / "rec"
    _make(rec, "occluded")
    out = d / "report.html"
    res = CliRunner().invoke(main, ["pipeline", str(rec), "--out", str(d / "r.json"), "--heights",
                                    str(rec / "heights.json"), "--report", str(out)])
    assert res.exit_code == 0, res.output
    return out, res.output


def test_report_is_one_self_contained_file_with_every_part(report):
    path, _ = report
    text = path.read_text()
    assert text.startswith("<!DOCTYPE html>")
    # nothing fetched: every image is embedded, no script, no external link
    assert not re.search(r'(src|href)="(?!data:)', text) and "<script" not in text
    assert len(re.findall(r'src="data:image/png;base64,', text)) == 2  # map + residual heat map
    assert 'id="verdict"' in text and "PASS" in text
    assert 'id="units"' in text and text.count("<tr>") >= 10 + 1  # 10 units + the header
    for name in [f"u{k:03d}" for k in range(10)]:
        assert name in text
    assert 'id="outliers"' in text and "re-detected" in text  # the occluded pair
    assert "magnified x" in text and "speed of sound" in text and "lands in the onsets" in text


def test_report_refuses_a_non_regular_file(tmp_path):
    rec = tmp_path / "rec"
    _make(rec, "dead")
    bad = tmp_path / "x.html"
    bad.mkdir()
    res = CliRunner().invoke(main, ["pipeline", str(rec), "--out", str(tmp_path / "r.json"), "--heights",
                                    str(rec / "heights.json"), "--report", str(bad)])
    assert res.exit_code == 2 and ("not a regular file" in res.output or "is a directory" in res.output)
    assert not (tmp_path / "r.json").exists()  # all or nothing: no result either


def test_magnification_makes_ellipses_visible():
    from selfcal.acoustics.report import ellipse_magnification

    for std, extent in ((2e-4, 5.0), (3e-3, 30.0), (0.5, 10.0)):
        m = ellipse_magnification(np.array([std]), extent)
        radius = m * np.sqrt(5.991) * std
        assert m >= 1 and (radius <= 0.04 * extent or m == 1) and (radius > 0.015 * extent or m == 1)


def _chromium() -> str | None:
    exe = shutil.which("chromium") or shutil.which("chromium-browser")
    if exe is None and os.geteuid() == 0 and shutil.which("apt-get"):
        env = dict(os.environ, DEBIAN_FRONTEND="noninteractive")
        try:
            subprocess.run(["apt-get", "install", "-y", "-qq", "chromium"], env=env, check=False,
                           capture_output=True, timeout=600)
        except (OSError, subprocess.TimeoutExpired):
            return None
        exe = shutil.which("chromium")
    return exe


def _load(exe: str, path: Path) -> tuple[str, list[str]]:
    """DOM after load and the console lines of headless Chromium."""
    run = subprocess.run([exe, "--headless", "--no-sandbox", "--disable-gpu", "--enable-logging=stderr", "--v=0",
                          "--dump-dom", path.resolve().as_uri()], capture_output=True, text=True, timeout=120)
    return run.stdout, [ln for ln in run.stderr.splitlines() if ":CONSOLE" in ln]


@pytest.mark.slow
def test_report_loads_in_headless_chromium_without_console_errors(report, tmp_path):
    exe = _chromium()
    if exe is None:
        pytest.skip("Debian package 'chromium' is not installed and could not be installed with apt-get")
    # control: the harness sees a console error when there is one
    ctl = tmp_path / "control.html"
    ctl.write_text('<!DOCTYPE html><html><body><script>console.error("control-error")</script></body></html>')
    _, lines = _load(exe, ctl)
    assert any("control-error" in ln for ln in lines)
    dom, lines = _load(exe, report[0])
    assert not lines, lines
    assert 'id="units"' in dom and dom.count("<tr") >= 11 and "u009" in dom
