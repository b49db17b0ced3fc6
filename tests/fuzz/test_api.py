"""Public functions under malformed input (issue 13): only SelfcalError subclasses escape.

Named cases for the readers (CSV dialects, names, BOM, CRLF, missing tokens, ``1_0``, huge
cells), the writers (non-regular targets, all-or-nothing staging), the shared validators
(wrong types, NaN, complex, masked arrays) at every solver entry, SLAC log validation and the
resource guards; hypothesis draws random text / arrays / arguments for each public entry.
"""

from __future__ import annotations

import errno
import io
import os
from pathlib import Path

import numpy as np
import pytest

from selfcal.errors import InputError, SelfcalError
from selfcal.io import (
    OutputError,
    atomic_write_bytes,
    read_json,
    read_matrix,
    read_table,
    staged_outputs,
    write_json,
    write_matrix,
)

hypothesis = pytest.importorskip("hypothesis")
from hypothesis import HealthCheck, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

FAST = settings(max_examples=int(os.environ.get("SELFCAL_FUZZ_EXAMPLES", "25")), deadline=None, suppress_health_check=list(HealthCheck), derandomize=True)
SLOW = settings(max_examples=500, deadline=None, suppress_health_check=list(HealthCheck))
LEAKS = (ValueError, TypeError, IndexError, KeyError, ZeroDivisionError, OverflowError, MemoryError,
         np.linalg.LinAlgError, AttributeError, UnicodeError)


def only_selfcal_errors(fn, *args, **kwargs):  # type: ignore[no-untyped-def]
    """Call ``fn``; a failure must be a SelfcalError (InputError and friends), never a bare one."""
    try:
        return fn(*args, **kwargs)
    except SelfcalError:
        return None
    except LEAKS as exc:  # pragma: no cover - the assertion reports it
        raise AssertionError(f"{fn.__name__} leaked {type(exc).__name__}: {exc}") from exc


# ----------------------------------------------------------------------------- readers

M = np.array([[1.0, 2.5, np.nan], [4.0, 5.0, 6.0]])


@pytest.mark.parametrize("text", [
    "1,2.5,\n4,5,6\n",
    "1;2,5;NA\r\n4;5;6\r\n",                    # semicolons, decimal comma, CRLF
    "\ufeff1\t2.5\tnan\n4\t5\t6\n",              # BOM, tab
    "1 2.5 NaN\n4   5 6\n",                      # whitespace
    "# comment\n\n1,2.5,N/A\n4,5,6\n",           # comments / blank lines
    "s1,s2,s3\n1,2.5,\n4,5,6\n",                 # header row
    "name,s1,s2,s3\nrx1,1,2.5,\nrx2,4,5,6\n",    # header + names column
    "rx1,1,2.5,NA\nrx2,4,5,6\n",                 # names column only
    '"rx1","1","2.5",""\n"rx2","4","5","6"\n',   # quoted cells
])
def test_csv_dialects(tmp_path: Path, text: str) -> None:
    p = tmp_path / "m.csv"
    p.write_bytes(text.encode("utf-8"))
    t = read_table(p)
    np.testing.assert_array_equal(t.values, M)
    if "rx1" in text:
        assert t.row_names == ("rx1", "rx2")
    if "s1" in text:
        assert t.col_names == ("s1", "s2", "s3")


def test_savetxt_default_output_loads(tmp_path: Path) -> None:
    X = np.random.default_rng(0).normal(size=(5, 4))
    p = tmp_path / "m.txt"
    np.savetxt(p, X)
    np.testing.assert_array_equal(read_matrix(p), X)
    np.savetxt(p, X, delimiter=",", header="a,b,c,d")
    np.testing.assert_array_equal(read_matrix(p), X)


@pytest.mark.parametrize("cell", ["1_0", "0x10", "1e", "--1", "inf_", "1.2.3", "١"])
def test_strict_numbers_name_row_and_column(tmp_path: Path, cell: str) -> None:
    p = tmp_path / "m.csv"
    p.write_text(f"1,2,3\n4,{cell},6\n")
    with pytest.raises(InputError, match=r"row 2, column 2"):
        read_matrix(p)


def test_huge_cell_no_csv_error_and_no_echo(tmp_path: Path) -> None:
    p = tmp_path / "m.csv"
    p.write_text("1,2\n3," + "9" * 300_000 + "x\n")
    with pytest.raises(InputError) as exc:
        read_matrix(p)
    assert "row 2, column 2" in str(exc.value) and len(str(exc.value)) < 200
    p.write_text("1,2\n3," + "9" * 300_000 + "\n")  # a huge number is a number (inf is refused later)
    assert read_matrix(p).shape == (2, 2)


@pytest.mark.parametrize("content,match", [
    (b"", "empty"), (b"\x00\x01\x02", "not a text"), (b"\xff\xfe1,2", "UTF-8"), (b"1,2\n3\n", "different numbers"),
    (b"PK\x03\x04", "npz"), (b"a,b\n", "not a number"),
])
def test_unreadable_files(tmp_path: Path, content: bytes, match: str) -> None:
    p = tmp_path / "m.csv"
    p.write_bytes(content)
    with pytest.raises(InputError, match=match):
        read_matrix(p)


def test_inputs_that_are_not_files(tmp_path: Path) -> None:
    os.mkfifo(tmp_path / "fifo")
    for p, match in ((tmp_path, "directory"), (tmp_path / "fifo", "FIFO"), (tmp_path / "none.csv", "not found")):
        with pytest.raises(InputError, match=match):
            read_matrix(p)
    with pytest.raises(InputError):
        read_json(tmp_path / "fifo")


def test_npy_inputs(tmp_path: Path) -> None:
    p = tmp_path / "m.npy"
    np.save(p, M)
    np.testing.assert_array_equal(read_matrix(p), M)
    np.save(p, M + 1j)
    with pytest.raises(InputError, match="complex"):
        read_matrix(p)
    p.write_bytes(b"\x93NUMPY garbage")
    with pytest.raises(InputError):
        read_matrix(p)


def test_stdin_dash(monkeypatch) -> None:  # type: ignore[no-untyped-def]
    class Stdin:
        buffer = io.BytesIO(b"1,2\n3,4\n")

    monkeypatch.setattr("sys.stdin", Stdin())
    np.testing.assert_array_equal(read_matrix("-"), [[1, 2], [3, 4]])


# ----------------------------------------------------------------------------- writers

def test_writer_refuses_non_regular_and_leaves_nothing(tmp_path: Path) -> None:
    os.mkfifo(tmp_path / "fifo")
    os.symlink("/dev/full", tmp_path / "full")
    (tmp_path / "d").mkdir()
    (tmp_path / "f").write_text("x")
    for target in ("fifo", "full", "d", "f/x.json", "n" * 300):
        with pytest.raises(OutputError):
            write_json(tmp_path / target, {"a": 1})
    assert sorted(p.name for p in tmp_path.iterdir()) == ["d", "f", "fifo", "full"]
    assert os.path.islink(tmp_path / "full") and (tmp_path / "f").read_text() == "x"


def test_staged_outputs_all_or_nothing(tmp_path: Path, monkeypatch) -> None:  # type: ignore[no-untyped-def]
    (tmp_path / "a.json").write_text("old")
    with pytest.raises(RuntimeError):
        with staged_outputs():
            write_json(tmp_path / "a.json", {"new": 1})
            write_matrix(tmp_path / "b.csv", M)
            raise RuntimeError("late failure")
    assert (tmp_path / "a.json").read_text() == "old" and not (tmp_path / "b.csv").exists()
    import selfcal.io as sio

    real = sio.os.replace
    calls = {"n": 0}

    def fail_second_write(fd: int) -> None:
        calls["n"] += 1
        if calls["n"] == 2:
            raise OSError(errno.EROFS, "Read-only file system")

    monkeypatch.setattr(sio.os, "fsync", fail_second_write)
    with pytest.raises(OutputError, match="Read-only"):
        with staged_outputs():
            write_json(tmp_path / "a.json", {"new": 1})
            write_json(tmp_path / "sub" / "c.json", {"new": 1})
    assert (tmp_path / "a.json").read_text() == "old" and not (tmp_path / "sub").exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.json"]
    assert sio.os.replace is real


def test_write_json_strict_and_masked(tmp_path: Path) -> None:
    import json

    p = tmp_path / "r.json"
    write_json(p, {"m": np.ma.array([1.0, 2.0], mask=[False, True]), "c": [np.nan, np.inf]})
    assert json.loads(p.read_text()) == {"m": [1.0, None], "c": [None, None]}
    with pytest.raises(SelfcalError):
        write_json(p, {"z": 1j})


def test_stdout_dash(capsysbinary) -> None:  # type: ignore[no-untyped-def]
    atomic_write_bytes("-", b"hello\n")
    assert capsysbinary.readouterr().out == b"hello\n"


@given(name=st.text(min_size=1, max_size=40))
@FAST
def test_writer_any_name(tmp_path_factory, name: str) -> None:  # type: ignore[no-untyped-def]
    d = tmp_path_factory.mktemp("w")
    try:
        write_json(d / name, {"a": 1})
    except SelfcalError:
        pass
    except (OSError, ValueError) as exc:  # pragma: no cover
        raise AssertionError(f"leaked {exc!r}") from exc
    assert not [p for p in d.rglob(".selfcal-*")]  # never a temporary left behind


@given(data=st.binary(max_size=400))
@FAST
def test_reader_random_bytes(tmp_path_factory, data: bytes) -> None:  # type: ignore[no-untyped-def]
    p = tmp_path_factory.mktemp("r") / "m.csv"
    p.write_bytes(data)
    out = only_selfcal_errors(read_table, p)
    if out is not None:
        assert out.values.ndim == 2 and out.values.size > 0


_CELL = st.one_of(st.floats(allow_nan=True, allow_infinity=False, width=32).map(repr),
                  st.sampled_from(["", "NA", "nan", "1_0", "x", '"3"', "1,5", " 7 ", "\ufeff"]),
                  st.text(max_size=6))


@given(rows=st.lists(st.lists(_CELL, min_size=1, max_size=5), min_size=1, max_size=6),
       sep=st.sampled_from([",", ";", "\t", " ", "|"]), eol=st.sampled_from(["\n", "\r\n"]))
@FAST
def test_reader_random_tables(tmp_path_factory, rows, sep: str, eol: str) -> None:  # type: ignore[no-untyped-def]
    p = tmp_path_factory.mktemp("t") / "m.csv"
    p.write_text(eol.join(sep.join(r) for r in rows) + eol, encoding="utf-8")
    out = only_selfcal_errors(read_table, p)
    if out is not None:
        assert out.values.ndim == 2
        assert out.row_names is None or len(out.row_names) == out.values.shape[0]
        assert out.col_names is None or len(out.col_names) == out.values.shape[1]


# ----------------------------------------------------------------------------- entry points

def _toa(rng: np.random.Generator, I: int = 6, J: int = 8) -> np.ndarray:
    R, S = rng.uniform(0, 10, (I, 3)), rng.uniform(0, 10, (J, 3))
    return np.linalg.norm(R[:, None] - S[None], axis=2)


@pytest.mark.parametrize("kwargs", [
    {"speed": "fast"}, {"speed": -1.0}, {"speed": float("nan")}, {"rng": -1}, {"rng": "seed"}, {"rng": 1.5},
    {"max_nfev": -5}, {"max_nfev": 2.5}, {"noise": float("nan")}, {"dim": 2.5}, {"dim": "3"}, {"dim": 4},
    {"offsets": "maybe"}, {"loss": 3}, {"f_scale": 0.0}, {"unknown_argument": 1},
])
def test_solve_toa_refuses_bad_arguments(kwargs) -> None:  # type: ignore[no-untyped-def]
    from selfcal.toa import solve_toa

    with pytest.raises(InputError):
        solve_toa(_toa(np.random.default_rng(0)), **kwargs)


@pytest.mark.parametrize("matrix", [
    "1,2", [[1, 2], [3]], [[1 + 1j] * 8] * 6, [["a"] * 8] * 6, None, 3.0, np.zeros((6, 8, 2)),
    np.full((6, 8), np.nan), np.full((6, 8), np.inf), np.ones((1, 1)), [],  # negative ranges are data (issue 12)
    np.array([[{"a": 1}] * 8] * 6, dtype=object),
])
def test_solvers_refuse_bad_matrices(matrix) -> None:  # type: ignore[no-untyped-def]
    from selfcal.tdoa import solve_farfield
    from selfcal.toa import solve_toa

    for fn in (solve_toa, solve_farfield):
        with pytest.raises(SelfcalError):
            fn(matrix)


def test_masked_entries_are_missing() -> None:
    from selfcal.toa import solve_toa

    rng = np.random.default_rng(4)
    D = _toa(rng)
    mask = np.zeros(D.shape, bool)
    mask[0, 0] = mask[2, 3] = True
    garbage = D.copy()
    garbage[mask] = 1e6  # masked values must not be used
    a = solve_toa(np.ma.array(garbage, mask=mask), rng=0)
    Dn = D.copy()
    Dn[mask] = np.nan
    b = solve_toa(Dn, rng=0)
    assert a.n_missing == b.n_missing == 2
    np.testing.assert_allclose(a.residual_rms, b.residual_rms, atol=1e-9)


@pytest.mark.parametrize("kwargs", [{"tol": float("nan")}, {"max_iter": -5}, {"rng": -1}, {"noise_std": "x"},
                                    {"reject_k": 0}, {"method": "nope"}])
def test_solve_farfield_refuses_bad_arguments(kwargs) -> None:  # type: ignore[no-untyped-def]
    from selfcal.tdoa import solve_farfield

    rng = np.random.default_rng(1)
    Z, n = rng.normal(size=(10, 3)), rng.normal(size=(6, 3))
    with pytest.raises(InputError):
        solve_farfield(Z @ (n / np.linalg.norm(n, axis=1, keepdims=True)).T, **kwargs)


@pytest.mark.parametrize("bearings", [
    [[1.0, 0.0], [0.0, 1.0], [1.0, 1.0]],        # degrees given as 2-D vectors for 3-D beacons
    [[1 + 0j, 0, 0]] * 3, [[np.nan] * 3] * 3, "north", [[1, 0, 0]],
])
def test_solve_aoa_refuses_bad_bearings(bearings) -> None:  # type: ignore[no-untyped-def]
    from selfcal.aoa import solve_aoa

    with pytest.raises(SelfcalError):
        solve_aoa([[0, 0, 0], [4, 0, 0], [0, 4, 0]], bearings)


def test_transposed_points_named() -> None:
    from selfcal._checks import as_points

    with pytest.raises(InputError, match="transposed"):
        as_points(np.zeros((3, 8)))


def test_run_pipeline_refuses_bad_arguments(tmp_path: Path) -> None:
    from selfcal.acoustics.pipeline import run_pipeline

    for kwargs in ({"rng": -1}, {"jitter": float("nan")}, {"jitter": -1.0}):
        with pytest.raises(InputError):
            run_pipeline(tmp_path, **kwargs)
    with pytest.raises(SelfcalError):
        run_pipeline(tmp_path / "missing")


@given(args=st.fixed_dictionaries({}, optional={
    "speed": st.one_of(st.none(), st.floats(), st.text(max_size=3), st.integers(-3, 3)),
    "rng": st.one_of(st.none(), st.integers(-5, 5), st.floats(), st.text(max_size=2)),
    "max_nfev": st.one_of(st.none(), st.integers(-5, 5), st.floats()),
    "noise": st.one_of(st.none(), st.floats()),
    "dim": st.one_of(st.integers(0, 5), st.floats(), st.text(max_size=1)),
    "offsets": st.sampled_from(["none", "receivers", "sources", "both", "x", ""]),
}), I=st.integers(1, 7), J=st.integers(1, 8), holes=st.floats(0, 1))
@FAST
def test_solve_toa_fuzz(args, I: int, J: int, holes: float) -> None:  # type: ignore[no-untyped-def]
    from selfcal.toa import solve_toa

    rng = np.random.default_rng(I * 10 + J)
    D = _toa(rng, I, J)
    D[rng.random(D.shape) < holes] = np.nan
    res = only_selfcal_errors(solve_toa, D, **args)
    if res is not None:
        assert np.isfinite(res.residual_rms) or not res.converged


@given(m=st.integers(1, 9), k=st.integers(1, 9), scale=st.floats(-1e6, 1e6), nan=st.floats(0, 1))
@FAST
def test_solve_farfield_fuzz(m: int, k: int, scale: float, nan: float) -> None:
    from selfcal.tdoa import solve_farfield

    rng = np.random.default_rng(m * 10 + k)
    D = scale * rng.normal(size=(m, k))
    D[rng.random(D.shape) < nan] = np.nan
    only_selfcal_errors(solve_farfield, D)


@given(b=st.lists(st.lists(st.floats(-10, 10), min_size=2, max_size=4), min_size=1, max_size=5),
       u=st.lists(st.lists(st.floats(-1, 1) | st.just(float("nan")), min_size=2, max_size=4), min_size=1, max_size=5),
       method=st.sampled_from(["auto", "sol1", "sol2", "p3p", "ml", "linear", "x"]))
@FAST
def test_solve_aoa_fuzz(b, u, method: str) -> None:  # type: ignore[no-untyped-def]
    from selfcal.aoa import solve_aoa

    only_selfcal_errors(solve_aoa, b, u, method=method)


# ----------------------------------------------------------------------------- SLAC logs, guards

def _tiny_log() -> dict[str, np.ndarray]:
    n, S, N = 2, 3, 8
    rx, tx = np.array([0, 1, 0]), np.array([2, 3, 1])
    ports = np.array([1, 2])
    rows = int(ports[rx].sum())
    G = np.ones((n, 2, 3), complex)
    return dict(version=np.array(1), anchors=np.array([[0.0, 0], [5, 0]]), ports=ports, G_em=G, G_chamber=G,
                controls=np.zeros((S, n, 2)), rx=rx, tx=tx, probe=np.ones(N, complex), T=np.array(0.1),
                bandwidth=np.array(1e6), carrier=np.array(1e9), sigma_v=np.array(0.01),
                sigma_omega=np.array(0.01), init_poses=np.zeros((n, 3)), init_cov=np.stack([np.eye(3)] * n),
                signals=np.ones((S, rows, N), np.complex64))


@pytest.mark.parametrize("change,field", [
    ({"T": np.array(0.0)}, "'T'"), ({"T": np.array(np.nan)}, "'T'"), ({"sigma_v": np.array(-1.0)}, "sigma_v"),
    ({"tx": np.array([2, 3, 0])}, "itself"), ({"ports": np.array([0, 2])}, "ports"),
    ({"bandwidth": np.array(0.0)}, "bandwidth"), ({"G_em": np.ones((2, 2, 4), complex)}, "G_"),
    ({"init_cov": np.stack([-np.eye(3)] * 2)}, "positive definite"), ({"controls": np.zeros((0, 2, 2))}, "controls"),
    ({"anchors": np.array([[0.0, np.nan], [5, 0]])}, "anchors"), ({"rx": np.array([0, 1, 5])}, "'rx'"),
    ({"signals": np.ones((3, 2, 8), np.complex64)}, "signals"), ({"init_poses": np.zeros((2, 2))}, "init_poses"),
])
def test_slac_log_validation_names_the_field(change, field: str) -> None:  # type: ignore[no-untyped-def]
    from selfcal.slac.validate import validate_log_arrays

    validate_log_arrays(_tiny_log(), "log.npz")
    z = _tiny_log()
    z.update(change)
    with pytest.raises(InputError, match=field):
        validate_log_arrays(z, "log.npz")


@pytest.mark.parametrize("content", [b"", b"PK\x03\x04trunc", b"\x93NUMPY\x01\x00", b"text"])
def test_slac_log_files(tmp_path: Path, content: bytes) -> None:
    from selfcal.slac.run import SlacLog

    p = tmp_path / "log.npz"
    p.write_bytes(content)
    with pytest.raises(InputError):
        SlacLog.from_npz(p)


@pytest.mark.parametrize("minutes,subcarriers,snr", [(1e6, 128, 30.0), (1.0, 10**8, 30.0), (1.0, 128, float("nan")),
                                                     (float("inf"), 128, 30.0), (-1.0, 128, 30.0)])
def test_slac_simulation_guard(minutes: float, subcarriers: int, snr: float) -> None:
    from selfcal.slac.validate import check_simulation_request

    with pytest.raises(InputError):
        check_simulation_request(minutes, subcarriers, snr)
    check_simulation_request(1.0, 128, 30.0)


def test_plausibility_names_the_mistake() -> None:
    from selfcal._checks import plausible_angles, plausible_jitter, plausible_matrix_scale

    t = _toa(np.random.default_rng(0)) / 343.0  # seconds
    with pytest.raises(InputError, match="--speed"):
        plausible_matrix_scale(t, speed=None, explicit_unit=False)
    plausible_matrix_scale(t, speed=None, explicit_unit=True)  # --unit m given: trusted
    plausible_matrix_scale(t, speed=343.0, explicit_unit=False)
    with pytest.raises(InputError, match="milliseconds"):
        plausible_matrix_scale(t * 1e3, speed=343.0, explicit_unit=False)
    with pytest.raises(InputError, match="degrees"):
        plausible_angles(np.array([[30.0, 10.0]]), "rad")
    with pytest.raises(InputError, match="jitter-us"):
        plausible_jitter(20.0)
    assert plausible_jitter(5e-6) == 5e-6
