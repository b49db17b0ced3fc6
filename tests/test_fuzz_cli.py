"""The command-line contract under malformed inputs and hostile output paths (issue 13).

Contract (DESIGN.md, "Inputs and outputs"): every run ends with exit 0 (a result), 1 (a
``FAIL:`` line on stdout) or 2 (exactly one ``selfcal: error:`` line on stderr); never a
traceback; a run that fails writes nothing, leaves an existing output byte-identical and
never touches a FIFO / device / directory at an output path. Named cases cover each class
of the issue; hypothesis cases draw random bytes, matrices and options for every command.
FIFOs and device-like nodes are ones created here in a temporary folder (never the
system's): a symlink to ``/dev/full`` stands for a full disk.
"""

from __future__ import annotations

import errno
import os
import stat
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from selfcal.cli import main

hypothesis = pytest.importorskip("hypothesis")
from hypothesis import HealthCheck, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

FAST = settings(max_examples=12, deadline=None, suppress_health_check=list(HealthCheck), derandomize=True)
SLOW = settings(max_examples=300, deadline=None, suppress_health_check=list(HealthCheck))


# ----------------------------------------------------------------------------- helpers

def snapshot(folder: Path) -> dict[str, tuple[str, bytes | None]]:
    """Kind and bytes of every entry under ``folder`` (without following links)."""
    out: dict[str, tuple[str, bytes | None]] = {}
    for root, dirs, files in os.walk(folder):
        for n in dirs + files:
            p = Path(root) / n
            m = os.lstat(p).st_mode
            if stat.S_ISLNK(m):
                out[str(p)] = ("link:" + os.readlink(p), None)
            elif stat.S_ISREG(m):
                out[str(p)] = ("file", p.read_bytes())
            elif stat.S_ISFIFO(m):
                out[str(p)] = ("fifo", None)
            elif stat.S_ISDIR(m):
                out[str(p)] = ("dir", None)
            else:
                out[str(p)] = ("other", None)
    return out


def invoke(args: list[str], stdin: bytes | str | None = None):  # type: ignore[no-untyped-def]
    return CliRunner().invoke(main, [str(a) for a in args], input=stdin, catch_exceptions=True)


def check_contract(res, before=None, after=None):  # type: ignore[no-untyped-def]
    """Assert the exit-status contract on one CliRunner result; return (code, stdout, stderr)."""
    out, err = res.stdout, res.stderr
    assert res.exception is None or isinstance(res.exception, SystemExit), repr(res.exception)
    assert "Traceback" not in out + err
    assert res.exit_code in (0, 1, 2), (res.exit_code, err)
    if res.exit_code == 2:
        lines = [ln for ln in err.splitlines() if ln.strip()]
        assert len(lines) == 1 and lines[0].startswith("selfcal: error:"), err
        assert "internal error" not in lines[0], lines[0]
        if before is not None:
            assert after == before, "a failed run changed the files"
    if res.exit_code == 1:
        assert any(ln.startswith("FAIL") for ln in out.splitlines()), out
    return res.exit_code, out, err


def toa_matrix(rng: np.random.Generator, I: int = 6, J: int = 8, noise: float = 0.01) -> np.ndarray:
    R = rng.uniform(0, 10, (I, 3))
    S = rng.uniform(0, 10, (J, 3))
    return np.linalg.norm(R[:, None] - S[None], axis=2) + noise * rng.normal(size=(I, J))


@pytest.fixture
def matrix_file(tmp_path: Path) -> Path:
    p = tmp_path / "in" / "m.csv"
    p.parent.mkdir()
    np.savetxt(p, toa_matrix(np.random.default_rng(3)), delimiter=",")
    return p


# ----------------------------------------------------------------------------- outputs

@pytest.mark.parametrize("kind", ["fifo", "dir", "devlink", "fifolink", "under-file", "too-long", "dashdir"])
def test_output_refuses_non_regular_targets(tmp_path: Path, matrix_file: Path, kind: str) -> None:
    """A FIFO, directory or device at --out (or a link to one) is refused, untouched, exit 2."""
    d = tmp_path / "o"
    d.mkdir()
    target = {"fifo": d / "f", "dir": d / "sub", "devlink": d / "full", "fifolink": d / "lf",
              "under-file": d / "plain" / "x.json", "too-long": d / ("x" * 300 + ".json"),
              "dashdir": d / "sub"}[kind]
    if kind in ("fifo", "fifolink"):
        os.mkfifo(d / "f")
    if kind == "fifolink":
        os.symlink(d / "f", d / "lf")
    if kind in ("dir", "dashdir"):
        (d / "sub").mkdir()
    if kind == "devlink":
        os.symlink("/dev/full", d / "full")  # our own link; the system node is never replaced
    if kind == "under-file":
        (d / "plain").write_text("keep")
    before = snapshot(d)
    args = ["calibrate", "toa", matrix_file, "--out", target]
    if kind == "dashdir":
        args = ["calibrate", "toa", matrix_file, "--out", "-", "--plot", target]
    res = invoke(args)
    code, _, err = check_contract(res, before, snapshot(d))
    assert code == 2, err
    assert os.path.exists("/dev/full") and stat.S_ISCHR(os.stat("/dev/full").st_mode)


def test_output_through_symlink_replaces_the_target_not_the_link(tmp_path: Path, matrix_file: Path) -> None:
    real = tmp_path / "real.json"
    real.write_text("old")
    real.chmod(0o640)
    link = tmp_path / "link.json"
    os.symlink(real, link)
    res = invoke(["calibrate", "toa", matrix_file, "-o", link])
    assert check_contract(res)[0] == 0
    assert link.is_symlink() and os.readlink(link) == str(real)
    assert real.read_text().startswith("{")
    assert stat.S_IMODE(real.stat().st_mode) == 0o640  # an existing file keeps its permissions


def test_dangling_symlink_creates_its_target(tmp_path: Path, matrix_file: Path) -> None:
    link = tmp_path / "link.json"
    os.symlink(tmp_path / "new.json", link)
    assert check_contract(invoke(["calibrate", "toa", matrix_file, "-o", link]))[0] == 0
    assert link.is_symlink() and (tmp_path / "new.json").is_file()


def test_failed_run_keeps_existing_outputs_byte_identical(tmp_path: Path) -> None:
    bad = tmp_path / "bad.csv"
    bad.write_text("1,2,3\n4,x,6\n")
    out, plot = tmp_path / "r.json", tmp_path / "r.png"
    out.write_bytes(b"\x00precious")
    plot.write_bytes(b"old png")
    before = snapshot(tmp_path)
    res = invoke(["calibrate", "toa", bad, "--out", out, "--plot", plot])
    code, _, err = check_contract(res, before, snapshot(tmp_path))
    assert code == 2 and "row 2, column 2" in err


def test_plot_and_out_are_committed_together(tmp_path: Path, matrix_file: Path, monkeypatch) -> None:  # type: ignore[no-untyped-def]
    """A disk that fills up while the second artefact is written leaves neither (ENOSPC)."""
    import selfcal.io as sio

    calls = {"n": 0}
    real_fsync = os.fsync

    def fsync(fd: int) -> None:
        calls["n"] += 1
        if calls["n"] == 2:
            raise OSError(errno.ENOSPC, "No space left on device")
        real_fsync(fd)

    monkeypatch.setattr(sio.os, "fsync", fsync)
    d = tmp_path / "o"
    d.mkdir()
    res = invoke(["calibrate", "toa", matrix_file, "--out", d / "r.json", "--plot", d / "new" / "r.png"])
    code, _, err = check_contract(res, {}, {})
    assert code == 2 and "no space left" in err
    assert list(d.iterdir()) == []  # no JSON, no PNG, no temporary, not even the new folder


def test_plot_format_from_suffix_and_unknown_suffix(tmp_path: Path, matrix_file: Path) -> None:
    res = invoke(["calibrate", "toa", matrix_file, "-o", tmp_path / "r.json", "--plot", tmp_path / "r.pdf"])
    assert check_contract(res)[0] == 0
    assert (tmp_path / "r.pdf").read_bytes()[:5] == b"%PDF-"
    before = snapshot(tmp_path)
    res = invoke(["calibrate", "toa", matrix_file, "-o", tmp_path / "s.json", "--plot", tmp_path / "r.txt"])
    assert check_contract(res, before, snapshot(tmp_path))[0] == 2


def test_dash_is_stdout_and_stdin(tmp_path: Path, matrix_file: Path) -> None:
    import json

    res = invoke(["-q", "calibrate", "toa", "-", "-o", "-"], stdin=matrix_file.read_bytes())
    assert check_contract(res)[0] == 0
    doc = json.loads(res.stdout)
    assert len(doc["receivers"]) == 6 and doc["units"]["positions"] == "m"
    res = invoke(["calibrate", "toa", "-", "-o", "-"], stdin=matrix_file.read_bytes())
    assert json.loads(res.stdout)["converged"] in (True, False)  # the summary went to stderr


def test_same_file_twice_is_refused(tmp_path: Path, matrix_file: Path) -> None:
    p = tmp_path / "r.png"
    res = invoke(["calibrate", "toa", matrix_file, "-o", p, "--plot", p])
    assert check_contract(res, {}, {})[0] == 2 and not p.exists()


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes into read-only folders")
def test_read_only_folder(tmp_path: Path, matrix_file: Path) -> None:
    d = tmp_path / "ro"
    d.mkdir()
    d.chmod(0o500)
    try:
        res = invoke(["calibrate", "toa", matrix_file, "-o", d / "r.json"])
        assert check_contract(res)[0] == 2 and not (d / "r.json").exists()
    finally:
        d.chmod(0o700)


# ----------------------------------------------------------------------------- command line

@pytest.mark.parametrize("args", [
    ["calibrate", "toa"],
    ["calibrate", "toa", "x.csv", "--nope"],
    ["calibrate", "toa", "x.csv", "--dim", "4", "-o", "r.json"],
    ["calibrate", "nothing"],
    ["locate", "aoa", "a", "b"],
    ["slac", "simulate", "--minutes", "abc", "-o", "x.npz"],
    ["simulate", "conference", "--room", "1x2", "--out", "rec"],
])
def test_usage_errors_are_one_line(tmp_path: Path, args: list[str], monkeypatch) -> None:  # type: ignore[no-untyped-def]
    monkeypatch.chdir(tmp_path)
    before = snapshot(tmp_path)
    res = invoke(args)
    assert check_contract(res, before, snapshot(tmp_path))[0] == 2


def test_version_and_help() -> None:
    assert invoke(["-V"]).exit_code == 0 and "version" in invoke(["-V"]).stdout
    res = invoke(["calibrate", "toa", "-h"])
    assert res.exit_code == 0 and "-o, --out" in res.stdout and "rows" in res.stdout.lower()


def test_internal_error_is_one_line(monkeypatch, matrix_file: Path, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    import selfcal.toa as toa

    def boom(*a, **k):  # type: ignore[no-untyped-def]
        raise ZeroDivisionError("boom")

    monkeypatch.setattr(toa, "solve_toa", boom)
    res = invoke(["calibrate", "toa", matrix_file, "-o", tmp_path / "r.json"])
    assert res.exit_code == 2 and res.stderr.strip() == "selfcal: error: internal error: ZeroDivisionError: boom"
    assert not (tmp_path / "r.json").exists()
    res = invoke(["--verbose", "calibrate", "toa", matrix_file, "-o", tmp_path / "r.json"])
    assert res.exit_code == 2 and "Traceback" in res.stderr
