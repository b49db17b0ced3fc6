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

FAST = settings(max_examples=int(os.environ.get("SELFCAL_FUZZ_EXAMPLES", "12")), deadline=None, suppress_health_check=list(HealthCheck), derandomize=True)
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
    res = invoke(["calibrate", "toa", matrix_file, "--out", d / "r.json", "--plot", d / "r.png"])
    code, _, err = check_contract(res, {}, {})
    assert code == 2 and "no space left" in err
    assert list(d.iterdir()) == []  # no JSON, no PNG, no temporary (a missing folder is refused up front)


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
    import selfcal.io as sio

    def boom(*a, **k):  # type: ignore[no-untyped-def]
        raise ZeroDivisionError("boom")

    monkeypatch.setattr(sio, "read_table", boom)  # any unexpected exception inside a command
    res = invoke(["calibrate", "toa", matrix_file, "-o", tmp_path / "r.json"])
    assert res.exit_code == 2 and res.stderr.strip() == "selfcal: error: internal error: ZeroDivisionError: boom"
    assert not (tmp_path / "r.json").exists()
    res = invoke(["--verbose", "calibrate", "toa", matrix_file, "-o", tmp_path / "r.json"])
    assert res.exit_code == 2 and "Traceback" in res.stderr


# ----------------------------------------------------------------------------- readers, units, results

def test_names_units_std_and_csv_round_trip(tmp_path: Path) -> None:
    import csv
    import json

    D = toa_matrix(np.random.default_rng(5))
    p = tmp_path / "m.csv"
    rows = ["name;" + ";".join(f"spk{j}" for j in range(D.shape[1]))]
    rows += [f"mic{i};" + ";".join(f"{v:.6f}".replace(".", ",") for v in D[i]) for i in range(D.shape[0])]
    p.write_bytes(("\ufeff" + "\r\n".join(rows) + "\r\n").encode())
    res = invoke(["calibrate", "toa", p, "-o", tmp_path / "r.json", "--csv", tmp_path / "r.csv"])
    assert check_contract(res)[0] == 0
    doc = json.loads((tmp_path / "r.json").read_text())
    assert doc["receiver_names"] == [f"mic{i}" for i in range(6)] and doc["source_names"][0] == "spk0"
    assert "units" in doc and len(doc["receiver_std"]) == 6 and len(doc["receiver_ellipse95"][0]) == 3
    # std = sqrt(diag(cov)); 95 % semi-axes = sqrt(chi2_3(0.95) * eig(cov)), largest first
    from scipy.stats import chi2

    C = np.array(doc["receiver_cov"][1])
    np.testing.assert_allclose(doc["receiver_std"][1], np.sqrt(np.diag(C)), rtol=1e-9)
    np.testing.assert_allclose(doc["receiver_ellipse95"][1], np.sqrt(chi2.ppf(0.95, 3) * np.linalg.eigvalsh(C))[::-1],
                               rtol=1e-6)
    table = list(csv.reader((tmp_path / "r.csv").open()))
    assert table[0] == ["kind", "name", "x", "y", "z", "x_std", "y_std", "z_std"]
    assert table[1][:2] == ["receiver", "mic0"] and table[7][:2] == ["source", "spk0"] and len(table) == 15


@pytest.mark.parametrize("args,match", [
    (["--speed", "343"], None),                                 # times in seconds: fine
    ([], "--speed"),                                            # seconds without --speed: the 1 cm array
    (["--unit", "m"], None),                                    # explicitly metres: trusted
    (["--speed", "343", "--unit", "ms"], "__ms__"),             # the same data scaled as ms
    (["--unit", "s"], "--speed"),                               # a time unit without a speed
    (["--unit", "samples", "--speed", "343"], "sample-rate"),
    (["--speed", "0"], "speed"), (["--speed", "nan"], "speed"), (["--sample-rate", "48000"], "samples"),
])
def test_units_and_plausibility(tmp_path: Path, args: list[str], match: str | None) -> None:
    D = toa_matrix(np.random.default_rng(6)) / 343.0  # seconds of flight
    p = tmp_path / "t.csv"
    np.savetxt(p, D * (1e3 if match == "__ms__" else 1.0), delimiter=",")
    res = invoke(["calibrate", "toa", p, "-o", tmp_path / "r.json", *args])
    code, _, err = check_contract(res, {}, {})
    if match is None:
        assert code == 0, err
    elif match == "__ms__":
        assert code == 0, err  # --unit ms turns them back into seconds
        res = invoke(["calibrate", "toa", p, "-o", tmp_path / "r2.json", "--speed", "343"])
        code, _, err = check_contract(res)
        assert code == 2 and "milliseconds" in err and not (tmp_path / "r2.json").exists()
    else:
        assert code == 2 and match in err, err


def test_angles_in_degrees_given_as_radians(tmp_path: Path) -> None:
    b, a = tmp_path / "b.csv", tmp_path / "a.csv"
    np.savetxt(b, [[0, 0, 0], [4, 0, 0], [0, 4, 0], [4, 4, 1]], delimiter=",")
    np.savetxt(a, [[30, 10], [60, 5], [120, -3], [200, 8]], delimiter=",")
    res = invoke(["locate", "aoa", b, a, "--angles", "rad", "-o", tmp_path / "r.json"])
    code, _, err = check_contract(res, {}, {})
    assert code == 2 and "degrees" in err


@pytest.mark.parametrize("args,match", [
    (["pipeline", "{d}", "-o", "{o}", "--jitter", "20"], "jitter-us"),
    (["simulate", "conference", "--jitter", "5", "--out", "{o}"], "jitter-us"),
    (["simulate", "conference", "--sample-rate", "1000000000", "--out", "{o}"], "memory"),
    (["demo", "--jitter", "5", "--out", "{o}"], "jitter-us"),
    (["slac", "simulate", "--snr-db", "nan", "-o", "{o}"], "snr"),
    (["slac", "simulate", "--minutes", "1e6", "-o", "{o}"], "memory"),
    (["slac", "simulate", "--subcarriers", "100000000", "-o", "{o}"], "memory"),
    (["reproduce", "toa-mds-nls", "--runs", "0", "--out", "{o}"], "runs"),
    (["reproduce", "aoa", "--step", "nan", "--out", "{o}"], "step"),
    (["reproduce", "slac", "--minutes", "-1", "--out", "{o}"], "minutes"),
    (["reproduce", "delays", "--runs", "0", "--out", "{o}"], "runs"),
    (["reproduce", "farfield", "--runs", "0", "--out", "{o}"], "runs"),
    (["reproduce", "lps", "--data", "{d}/nothing", "--out", "{o}"], None),
    (["slac", "plaza", "{d}/nothing.mat", "-o", "{o}"], None),
])
def test_commands_refuse_up_front(tmp_path: Path, args: list[str], match: str | None) -> None:
    """Every command: bad values -> exit 2, one line, nothing written (named mistakes)."""
    d = tmp_path / "in"
    d.mkdir()
    o = tmp_path / "out"
    before = snapshot(tmp_path)
    res = invoke([a.format(d=d, o=o) for a in args])
    code, _, err = check_contract(res, before, snapshot(tmp_path))
    assert code == 2
    if match:
        assert match in err.lower(), err


# ----------------------------------------------------------------------------- hypothesis at every command

_CELLS = st.one_of(st.floats(-50, 50).map(lambda v: f"{v:.4g}"), st.sampled_from(["", "NA", "nan", "1_0", "inf", "x"]))


@given(rows=st.lists(st.lists(_CELLS, min_size=1, max_size=8), min_size=1, max_size=8),
       sep=st.sampled_from([",", ";", "\t", " "]),
       extra=st.lists(st.sampled_from([["--speed", "343"], ["--unit", "mm"], ["--dim", "2"], ["--offsets", "both"],
                                       ["--offsets", "receivers"], ["--loss", "huber"], ["--method", "nls"],
                                       ["--unit", "m"], ["--seed", "-1"], ["--speed", "-3"]]), max_size=3))
@FAST
def test_fuzz_calibrate_toa(tmp_path_factory, rows, sep: str, extra) -> None:  # type: ignore[no-untyped-def]
    d = tmp_path_factory.mktemp("toa")
    p = d / "m.csv"
    p.write_text("\n".join(sep.join(r) for r in rows) + "\n")
    (d / "old.json").write_bytes(b"keep")
    before = snapshot(d)
    args = ["calibrate", "toa", p, "-o", d / "old.json", "--csv", d / "r.csv"] + [a for e in extra for a in e]
    res = invoke(args)
    code, out, err = check_contract(res, before, snapshot(d))
    if code != 2:
        import json

        doc = json.loads((d / "old.json").read_text())
        assert len(doc["receivers"]) >= 1 and "units" in doc


@given(m=st.integers(1, 12), k=st.integers(1, 8), scale=st.sampled_from([1e-4, 0.01, 1.0, 1e4]),
       holes=st.floats(0, 0.6), seed=st.integers(0, 3),
       extra=st.lists(st.sampled_from([["--speed", "343"], ["--method", "alternating"], ["--ransac"],
                                       ["--allow-degenerate"], ["--loss", "cauchy"], ["--unit", "mm"],
                                       ["--noise-std", "0"], ["--noise-std", "0.01"]]), max_size=2))
@FAST
def test_fuzz_tdoa_farfield(tmp_path_factory, m: int, k: int, scale: float, holes: float, seed: int, extra) -> None:  # type: ignore[no-untyped-def]
    d = tmp_path_factory.mktemp("ff")
    rng = np.random.default_rng(seed)
    Z, n = rng.normal(size=(m, 3)), rng.normal(size=(k, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    D = scale * (Z @ n.T + rng.normal(size=k))
    D[rng.random(D.shape) < holes] = np.nan
    np.savetxt(d / "m.csv", D, delimiter=",")
    before = snapshot(d)
    args = ["calibrate", "tdoa-farfield", d / "m.csv", "-o", d / "r.json"] + [a for e in extra for a in e]
    res = invoke(args)
    code, _, _ = check_contract(res)
    if code == 2:
        assert snapshot(d) == before


@given(nb=st.integers(1, 6), dim=st.sampled_from([2, 3]), angles=st.sampled_from([None, "deg", "rad"]),
       method=st.sampled_from(["auto", "sol1", "sol2", "p3p", "ml", "linear"]), seed=st.integers(0, 5),
       ncol=st.integers(1, 4), hint=st.sampled_from([None, "1,2", "1,2,3", "x", "nan,1,1"]))
@FAST
def test_fuzz_locate_aoa(tmp_path_factory, nb: int, dim: int, angles, method: str, seed: int, ncol: int, hint) -> None:  # type: ignore[no-untyped-def]
    d = tmp_path_factory.mktemp("aoa")
    rng = np.random.default_rng(seed)
    np.savetxt(d / "b.csv", rng.uniform(-5, 5, (nb, dim)), delimiter=",")
    np.savetxt(d / "u.csv", rng.normal(size=(nb, ncol)), delimiter=",")
    before = snapshot(d)
    args = ["locate", "aoa", d / "b.csv", d / "u.csv", "-o", d / "r.json", "--method", method]
    args += ["--angles", angles] if angles else []
    args += ["--hint", hint] if hint else []
    code, _, _ = check_contract(invoke(args))
    if code == 2:
        assert snapshot(d) == before


@given(data=st.binary(max_size=300), name=st.sampled_from(["log.npz", "log.npy", "log"]))
@FAST
def test_fuzz_slac_run_bytes(tmp_path_factory, data: bytes, name: str) -> None:  # type: ignore[no-untyped-def]
    d = tmp_path_factory.mktemp("slac")
    (d / name).write_bytes(data)
    before = snapshot(d)
    assert check_contract(invoke(["slac", "run", d / name, "-o", d / "r.json"]), before, snapshot(d))[0] == 2


@given(setup=st.recursive(st.none() | st.booleans() | st.floats() | st.integers() | st.text(max_size=4),
                          lambda c: st.lists(c, max_size=3) | st.dictionaries(
                              st.sampled_from(["sample_rate", "receivers", "senders", "probe", "events", "time",
                                               "sender", "duration", "clock_jitter", "type"]), c, max_size=5),
                          max_leaves=12))
@FAST
def test_fuzz_pipeline_setup(tmp_path_factory, setup) -> None:  # type: ignore[no-untyped-def]
    import json

    d = tmp_path_factory.mktemp("pipe")
    (d / "rec").mkdir()
    (d / "rec" / "setup.json").write_text(json.dumps(setup))
    before = snapshot(d)
    assert check_contract(invoke(["pipeline", d / "rec", "-o", d / "r.json"]), before, snapshot(d))[0] == 2


_NUM = st.sampled_from(["0", "-1", "nan", "inf", "-inf", "1e300", "x", "", "1e-300", "2.5"])


@given(opt=st.sampled_from(["--minutes", "--subcarriers", "--snr-db", "--seed"]), value=_NUM)
@FAST
def test_fuzz_slac_simulate_options(tmp_path_factory, opt: str, value: str) -> None:  # type: ignore[no-untyped-def]
    d = tmp_path_factory.mktemp("sim")
    args = ["slac", "simulate", opt, value, "-o", d / "log.npz"]
    if opt != "--minutes":
        args += ["--minutes", "0.02"]
    code, _, _ = check_contract(invoke(args))
    if code == 0:
        from selfcal.slac.run import SlacLog

        assert SlacLog.from_npz(d / "log.npz").n_steps >= 1
    else:
        assert not any(d.iterdir())


@given(opt=st.sampled_from(["--units", "--rt60", "--snr", "--sample-rate", "--max-order", "--jitter", "--jitter-us",
                            "--room"]), value=_NUM)
@FAST
def test_fuzz_simulate_conference_options(tmp_path_factory, opt: str, value: str) -> None:  # type: ignore[no-untyped-def]
    d = tmp_path_factory.mktemp("conf")
    args = ["simulate", "conference", opt, value, "--out", d / "rec", "--units", "4", "--max-order", "0",
            "--sample-rate", "16000"]
    if opt in ("--units", "--max-order", "--sample-rate"):
        args = ["simulate", "conference", "--units", "4", "--max-order", "0", "--sample-rate", "16000",
                opt, value, "--out", d / "rec"]
    code, _, _ = check_contract(invoke(args))
    if code == 2:
        assert not any(d.iterdir())


@pytest.mark.slow
@given(rows=st.lists(st.lists(_CELLS, min_size=1, max_size=10), min_size=1, max_size=10))
@SLOW
def test_fuzz_calibrate_toa_slow(tmp_path_factory, rows) -> None:  # type: ignore[no-untyped-def]
    d = tmp_path_factory.mktemp("toa")
    p = d / "m.csv"
    p.write_text("\n".join(",".join(r) for r in rows) + "\n")
    check_contract(invoke(["calibrate", "toa", p, "-o", d / "r.json"]))


def test_transposed_inputs_are_named(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    Z, n = rng.normal(size=(10, 3)), rng.normal(size=(5, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    np.savetxt(tmp_path / "ff.csv", Z @ n.T, delimiter=",")  # 10 positions x 5 transmitters (needs 6)
    res = invoke(["calibrate", "tdoa-farfield", tmp_path / "ff.csv", "-o", tmp_path / "r.json"])
    code, _, err = check_contract(res)
    assert code == 2 and "transposed" in err
    np.savetxt(tmp_path / "b.csv", rng.uniform(0, 4, (5, 3)).T, delimiter=",")  # beacons as columns
    np.savetxt(tmp_path / "u.csv", rng.normal(size=(5, 3)), delimiter=",")
    res = invoke(["locate", "aoa", tmp_path / "b.csv", tmp_path / "u.csv", "-o", tmp_path / "p.json"])
    code, _, err = check_contract(res)
    assert code == 2 and "transposed" in err


# ----------------------------------------------------------------------------- malformed inputs found by hand (hygiene)

def _tiny_recording(d: Path, *, wav: bytes | None = None, setup_extra: dict | None = None) -> Path:  # type: ignore[type-arg]
    """A two-unit recording folder written by hand (no simulation): valid unless told otherwise."""
    import json

    from scipy.io import wavfile

    rec = d / "rec"
    rec.mkdir()
    setup = {"sample_rate": 16000, "receivers": ["a", "b"], "senders": ["a", "b"],
             "probe": {"type": "chirp", "f0": 500.0, "f1": 4000.0, "duration": 0.02},
             "events": [{"sender": "a", "time": 0.05}, {"sender": "b", "time": 0.15}], **(setup_extra or {})}
    (rec / "setup.json").write_text(json.dumps(setup))
    x = (0.01 * np.random.default_rng(0).normal(size=4000) * 32767).astype(np.int16)
    for n in ("a", "b"):
        wavfile.write(rec / f"rx_{n}.wav", 16000, x)
    if wav is not None:
        (rec / "rx_b.wav").write_bytes(wav)
    return rec


_BIG_INT_JSON = '{"delays": [[0.001, 0.002]], "sound_speed_mps": ' + "9" * 5000 + "}"


@pytest.mark.parametrize("case", [
    "ff-json-huge-int", "heights-json-huge-int", "toa-1e308", "ff-1e308", "ff-one-1e308", "aoa-beacons-1e300",
    "wav-corrupt-header", "wav-is-dir", "setup-is-dir",
    "setup-speed-1e6", "pipeline-speed-1e308", "jitter-us-1e308", "demo-rt60-1e308", "demo-snr-minus-1e308",
    "demo-seed-negative", "farfield-runs-1e20", "toa-mds-nls-runs-1e20", "delays-runs-1e20",
    "delays-noise-runs-1e20", "aoa-runs-1e20", "slac-runs-1e20", "slac-minutes-1e308", "slac-minutes-1e20",
    "lps-bad-mat", "plaza-dir", "plaza-fifo",
])
def test_malformed_inputs_exit_2_with_one_line(tmp_path: Path, case: str) -> None:
    """Each case is a reproducer of a defect found by hand: an internal error (a 5000-digit JSON
    integer, a corrupt WAV header, 1e20 runs, 1e308 lengths), LAPACK noise on stdout (entries
    near 1e308), an output folder created by a failed run, or a misleading message. Contract:
    exit 2, one ``selfcal: error:`` line (no internal error), nothing written."""
    d = tmp_path / "w"
    d.mkdir()
    o = d / "r.json"
    rng = np.random.default_rng(1)
    Z, n = rng.normal(size=(8, 3)), rng.normal(size=(10, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    ff = Z @ n.T
    match = None
    if case in ("ff-json-huge-int", "heights-json-huge-int"):
        (d / "x.json").write_text(_BIG_INT_JSON if case.startswith("ff") else
                                  '{"receivers": [' + "1" * 5000 + '], "senders": [1, 2]}')
        args = (["calibrate", "tdoa-farfield", d / "x.json", "-o", o] if case.startswith("ff") else
                ["pipeline", _tiny_recording(d), "--heights", d / "x.json", "-o", o])
        match = "malformed json"
    elif case in ("toa-1e308", "ff-1e308", "ff-one-1e308"):  # toa: a whole matrix in an overflowing unit
        M = np.full((6, 8), 1e308) if case != "ff-one-1e308" else np.where(np.arange(80).reshape(8, 10) == 7, 1e308, ff)
        np.savetxt(d / "m.csv", M, delimiter=",")
        args = ["calibrate", "toa" if case == "toa-1e308" else "tdoa-farfield", d / "m.csv", "-o", o]
        match = "another unit"
    elif case == "aoa-beacons-1e300":
        np.savetxt(d / "b.csv", 1e300 * rng.uniform(-5, 5, (5, 3)), delimiter=",")
        np.savetxt(d / "u.csv", n[:5], delimiter=",")
        args, match = ["locate", "aoa", d / "b.csv", d / "u.csv", "-o", o], "another unit"
    elif case in ("wav-corrupt-header", "wav-is-dir", "setup-is-dir"):
        rec = _tiny_recording(d, wav=b"RIFF\x00\x00\x00\x00WAVEfmt " if case == "wav-corrupt-header" else None)
        if case == "wav-is-dir":
            (rec / "rx_b.wav").unlink()
            (rec / "rx_b.wav").mkdir()
        if case == "setup-is-dir":
            (rec / "setup.json").unlink()
            (rec / "setup.json").mkdir()
        args = ["pipeline", rec, "-o", o]
        match = {"wav-corrupt-header": "rx_b.wav: not a readable wav", "wav-is-dir": "rx_b.wav: not a regular file",
                 "setup-is-dir": "setup.json: is a directory"}[case]
    elif case == "setup-speed-1e6":
        args, match = ["pipeline", _tiny_recording(d, setup_extra={"speed_of_sound": 1e6}), "-o", o], "physical bound"
    elif case == "pipeline-speed-1e308":
        args, match = ["pipeline", _tiny_recording(d), "--speed-of-sound", "1e308", "-o", o], "physical bound"
    elif case == "jitter-us-1e308":
        args, match = ["pipeline", _tiny_recording(d), "--jitter-us", "1e308", "-o", o], "--jitter-us 1e+308 us"
    elif case.startswith("demo-"):
        opt = {"demo-rt60-1e308": ["--rt60", "1e308"], "demo-snr-minus-1e308": ["--snr", "-1e308"],
               "demo-seed-negative": ["--seed", "-1"]}[case]
        args, match = ["demo", "--units", "6", *opt, "--out", d / "demo"], opt[0].lstrip("-")
    elif case.endswith("-runs-1e20"):
        sub = case[: -len("-runs-1e20")]
        opt = "--runs"
        if sub == "delays-noise":
            sub, opt = "delays", "--noise-runs"
        args, match = ["reproduce", sub, opt, "99999999999999999999", "--out", d / "out"], "memory"
    elif case.startswith("slac-minutes"):
        args = ["reproduce", "slac", "--minutes", "1e308" if case.endswith("1e308") else "1e20", "--out", d / "out"]
        match = "memory"
    elif case == "lps-bad-mat":
        (d / "data4.mat").write_bytes(b"MATLAB 5.0 garbage")
        args, match = ["reproduce", "lps", "--data", d / "data4.mat", "--simulate", "0", "--out", d / "out"], "matlab"
    else:  # plaza on a folder / FIFO: named as such, not "file not found"
        p = d / "p.mat"
        p.mkdir() if case == "plaza-dir" else os.mkfifo(p)
        args = ["slac", "plaza", p, "-o", o]
        match = "is a directory" if case == "plaza-dir" else "not a regular file"
    before = snapshot(d)
    res = invoke(args)
    code, out, err = check_contract(res, before, snapshot(d))
    assert code == 2, err
    assert match.lower() in err.lower(), err


def test_output_file_path_ending_in_a_separator_is_refused(tmp_path: Path) -> None:
    """``write_json("out/")`` names a folder: refused, nothing created (the CLI's click paths
    drop the trailing separator before selfcal sees them, so this is the library's check)."""
    from selfcal.io import check_output_path, write_json
    from selfcal.io.outputs import OutputError

    with pytest.raises(OutputError, match="give a file name"):
        check_output_path(str(tmp_path / "zz") + os.sep)
    with pytest.raises(OutputError):
        write_json(str(tmp_path / "zz") + os.sep, {"a": 1})
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("args,match", [
    # sigma**2 underflowed (ZeroDivisionError after the JSON was written)
    (["calibrate", "tdoa-farfield", "{ff}", "--noise-std", "1e-308", "-o", "{o}"], None),
    (["locate", "aoa", "{b}", "{u}", "--sigma-deg", "99999999999999999999", "-o", "{o}"], "below 180"),
    (["reproduce", "aoa", "--sigma-deg", "nan", "--out", "{d}/out"], "below 180"),
    (["simulate", "conference", "--units", "3", "--out", "{d}/rec"], "--units must be >= 5"),
])
def test_more_malformed_options(tmp_path: Path, args: list[str], match: str | None) -> None:
    rng = np.random.default_rng(2)
    Z, n = rng.normal(size=(8, 3)), rng.normal(size=(10, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    np.savetxt(tmp_path / "ff.csv", Z @ n.T + 1e-3 * rng.normal(size=(8, 10)), delimiter=",")
    np.savetxt(tmp_path / "b.csv", rng.uniform(-5, 5, (5, 3)), delimiter=",")
    np.savetxt(tmp_path / "u.csv", n[:5], delimiter=",")
    d = tmp_path / "w"
    d.mkdir()
    fmt = {"ff": tmp_path / "ff.csv", "b": tmp_path / "b.csv", "u": tmp_path / "u.csv", "o": d / "r.json", "d": d}
    before = snapshot(d)
    code, out, err = check_contract(invoke([a.format(**fmt) for a in args]), before, snapshot(d))
    if match is None:  # a result failing its own test at that noise: exit 1, written
        assert code == 1 and (d / "r.json").is_file(), err
    else:
        assert code == 2 and match in err, err


@pytest.fixture(scope="module")
def slac_log_arrays(tmp_path_factory) -> dict[str, np.ndarray]:  # type: ignore[no-untyped-def,type-arg]
    """The arrays of a short simulated SLAC log (N = 8 subcarriers): mutated one field at a time."""
    from selfcal.scenarios.rovers import make_rover_scenario
    from selfcal.slac.run import SlacLog

    p = tmp_path_factory.mktemp("slaclog") / "log.npz"
    SlacLog.from_scenario(make_rover_scenario(0.02, n_subcarriers=8, rng=3), seed=3).to_npz(p)
    return dict(np.load(p))


@pytest.mark.parametrize("field,value,code", [
    ("version", "x", 2),         # a text version: ValueError inside int() before
    ("signals", "zeros", 1),     # nothing to range with: was TypeError (mean of None), now FAIL
    ("controls", "huge", 1),     # an odometry step of 1e308 m: was TypeError, now FAIL
])
def test_slac_run_on_corrupt_logs(tmp_path: Path, slac_log_arrays, field: str, value: str, code: int) -> None:  # type: ignore[no-untyped-def]
    z = dict(slac_log_arrays)
    if value == "x":
        z[field] = np.array("x")
    elif value == "zeros":
        z[field] = np.zeros_like(z[field])
    else:
        z[field] = z[field].copy()
        z[field].flat[0] = 1e308
    np.savez(tmp_path / "log.npz", **z)
    before = snapshot(tmp_path)
    c, out, err = check_contract(invoke(["slac", "run", tmp_path / "log.npz", "-o", tmp_path / "r.json"]),
                                 before, snapshot(tmp_path))
    assert c == code, err
    assert code == 2 or (tmp_path / "r.json").is_file(), out + err
    if code == 1:  # the result is written, JSON-safe, and says it failed
        import json

        doc = json.loads((tmp_path / "r.json").read_text())
        assert doc["success"] is False and "FAIL" in out


@pytest.mark.parametrize("field,value,match", [
    ("speaker", 1e308, "integer ids"),                 # OverflowError converting it to int64 before
    ("sound_speed_mps", True, "must be a number"),     # a bool was read as 1 m/s (exit 0 with --directions sources)
    ("mic_ref", True, "must be a number"),
])
def test_pyramic_json_field_types(tmp_path: Path, field: str, value: object, match: str) -> None:
    import json

    rng = np.random.default_rng(4)
    mics = rng.normal(scale=0.1, size=(8, 3))
    az = np.linspace(0, 2 * np.pi, 12, endpoint=False)
    src = np.column_stack([np.cos(az), np.sin(az), np.full(12, 0.3)])
    src /= np.linalg.norm(src, axis=1, keepdims=True)
    delays = ((mics[1:] - mics[0]) @ -src.T) / 343.0
    doc = {"sound_speed_mps": 343.0, "mic_ref": 0, "microphones": mics.T.tolist(), "delays": delays.tolist(),
           "sources": src.tolist(), field: value}
    p = tmp_path / "pyramic_tdoa_x.json"
    p.write_text(json.dumps(doc))
    before = snapshot(tmp_path)
    res = invoke(["calibrate", "tdoa-farfield", p, "--directions", "sources", "-o", tmp_path / "r.json"])
    code, _, err = check_contract(res, before, snapshot(tmp_path))
    assert code == 2 and match in err.lower(), err


def test_pipeline_report_folder_that_is_a_file_is_refused_up_front(tmp_path: Path) -> None:
    """``--report PATH`` without .html is a folder: an existing file there is refused before the
    pipeline runs (it failed only when the figures were written, after the whole calibration)."""
    rec = _tiny_recording(tmp_path)
    (tmp_path / "rep").write_text("keep")
    before = snapshot(tmp_path)
    res = invoke(["pipeline", rec, "-o", tmp_path / "r.json", "--report", tmp_path / "rep"])
    code, _, err = check_contract(res, before, snapshot(tmp_path))
    assert code == 2 and "not a directory" in err, err


@pytest.mark.parametrize("kind,angles,match", [
    ("azel", [[10.0, 95.0]] * 5, "within +-90"),        # an elevation of 95 deg was read as a direction
    ("azel", [[10.0, 1e308]] * 5, "within +-90"),       # ... and 1e308 deg gave 'receiver on the beacon plane'
    ("axes", [[-30.0, 60.0]] * 5, "within [0, 180]"),   # an angle to an axis is never negative
    ("vectors", [[1e300, 1e300, 1e300]] * 5, "not a unit vector"),  # the norm overflowed and skipped the check
])
def test_bearing_angles_out_of_range(tmp_path: Path, kind: str, angles: list, match: str) -> None:  # type: ignore[type-arg]
    np.savetxt(tmp_path / "b.csv", np.random.default_rng(0).uniform(-5, 5, (5, 3)), delimiter=",")
    np.savetxt(tmp_path / "a.csv", np.array(angles), delimiter=",")
    before = snapshot(tmp_path)
    res = invoke(["locate", "aoa", tmp_path / "b.csv", tmp_path / "a.csv", "--angles", kind, "-o", tmp_path / "r.json"])
    code, _, err = check_contract(res, before, snapshot(tmp_path))
    assert code == 2 and match in err, err


@pytest.mark.parametrize("field", ["TL", "DR"])
def test_plaza_values_beyond_double_precision(tmp_path: Path, field: str) -> None:
    """A beacon at 1e308 m raised ValueError inside the range solver; an odometry step of 1e308
    gave exit 0. Every numeric variable of the log is bounded like the matrices (MAX_ABS_ENTRY)."""
    import scipy.io as sio

    t = np.arange(20.0)
    m = {"TL": np.array([[1, 0.0, 0.0], [2, 10.0, 0.0], [3, 0.0, 10.0], [4, 10.0, 10.0]]),
         "TD": np.column_stack([t, np.zeros(20), 1 + t % 4, np.full(20, 5.0)]),
         "GT": np.column_stack([t, np.full(20, 5.0), np.full(20, 5.0), np.zeros(20)]),
         "DR": np.column_stack([t, np.full(20, 0.1), np.zeros(20)]), "init_heading_offset": np.array([[0]])}
    m[field] = m[field].astype(float)
    m[field][-1, -1] = 1e308
    sio.savemat(tmp_path / "p.mat", m)
    before = snapshot(tmp_path)
    res = invoke(["slac", "plaza", tmp_path / "p.mat", "-o", tmp_path / "r.json"])
    code, _, err = check_contract(res, before, snapshot(tmp_path))
    assert code == 2 and f"{field} row" in err and "beyond" in err, err
