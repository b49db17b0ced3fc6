""".npy matrices: every plain numeric layout is read as float64, the rest refused by name
from the header alone (no data is touched before the dtype and the size are checked, and
nothing is ever unpickled: a pickle whose loading would create a file leaves no file).
"""

from __future__ import annotations

import pickle
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from selfcal.cli import main
from selfcal.errors import InputError
from selfcal.io import load_npz, read_table

from .test_cli import check_contract, snapshot


def _toa(seed: int = 0) -> np.ndarray:
    g = np.random.default_rng(seed)
    r, s = g.uniform(0, 5, (8, 3)), g.uniform(0, 5, (10, 3))
    return np.linalg.norm(r[:, None] - s[None], axis=-1) + g.normal(0, 0.01, (8, 10))


class _Trap:
    """Unpickling it creates ``marker``: the proof that a reader loaded a pickle."""

    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self):  # type: ignore[no-untyped-def]
        return (Path.touch, (self.marker,))


@pytest.mark.parametrize("layout", ["fortran", "float16", "float32", "longdouble", "int16", "int64", "uint8",
                                    "big-endian", "1-d", "non-contiguous"])
def test_plain_numeric_layouts_are_read(tmp_path: Path, layout: str) -> None:
    M = _toa()
    arr = {"fortran": np.asfortranarray(M), "float16": M.astype(np.float16), "float32": M.astype(np.float32),
           "longdouble": M.astype(np.longdouble), "int16": np.round(M * 100).astype(np.int16),
           "int64": np.round(M * 1e6).astype(np.int64), "uint8": np.round(M * 10).astype(np.uint8),
           "big-endian": M.astype(">f8"), "1-d": M[:, 0], "non-contiguous": M[::2, ::3]}[layout]
    p = tmp_path / "m.npy"
    np.save(p, arr, allow_pickle=False)
    t = read_table(p)
    ref = np.asarray(arr, dtype=np.float64)
    ref = ref[:, None] if ref.ndim == 1 else ref
    assert t.values.dtype == np.float64 and t.values.flags["C_CONTIGUOUS"]
    np.testing.assert_array_equal(t.values, ref)


def test_fortran_and_c_order_give_the_same_calibration(tmp_path: Path) -> None:
    M = _toa(1)
    np.save(tmp_path / "c.npy", M)
    np.save(tmp_path / "f.npy", np.asfortranarray(M))
    out = {}
    for k in ("c", "f"):
        res = CliRunner().invoke(main, ["calibrate", "toa", str(tmp_path / f"{k}.npy"), "--method", "nls",
                                        "-o", str(tmp_path / f"{k}.json")])
        assert check_contract(res)[0] in (0, 1)
        out[k] = (tmp_path / f"{k}.json").read_text()
    assert out["c"] == out["f"]


def _npy_header(shape: tuple[int, ...], descr: str = "<f8", version: int = 1) -> bytes:
    hdr = f"{{'descr': '{descr}', 'fortran_order': False, 'shape': {shape}, }}"
    hdr += " " * (118 - len(hdr)) + "\n"
    size = len(hdr).to_bytes(2 if version == 1 else 4, "little")
    return b"\x93NUMPY" + bytes([version, 0]) + size + hdr.encode()


CASES: dict[str, tuple[object, str]] = {
    "structured": (np.zeros(3, dtype=[("a", "f8"), ("b", "i4")]), "structured dtype"),
    "sub-array": (np.zeros(3, dtype=[("a", "f8", (2,))]), "structured dtype"),
    "void": (np.zeros(3, dtype="V8"), "structured dtype"),
    "complex": (np.ones((3, 3), dtype=complex), "complex"),
    "bool": (np.ones((3, 3), dtype=bool), "boolean"),
    "text": (np.array([["a", "b"]]), "not numeric"),
    "datetime": (np.array(["2020-01-01"], dtype="M8[D]"), "not numeric"),
    "0-d": (np.array(3.0), "0-d"),
    "3-d": (np.zeros((2, 3, 4)), "2-D matrix"),
    "empty": (np.zeros((0, 4)), "empty"),
    "empty-1d": (np.zeros(0), "empty"),
    "npz-named-npy": (b"npz", "npz archive"),
    "truncated": (_npy_header((10, 10)) + b"\x00" * 80, "truncated"),
    "huge-shape": (_npy_header((10**12, 10**6)) + b"\x00" * 80, "truncated"),
    "negative-shape": (_npy_header((-3, 2)) + b"\x00" * 80, "malformed"),
    "header-code": (b"\x93NUMPY\x01\x00\x20\x00{'descr': __import__('os')}      \n", "malformed"),
    "header-too-long": (b"\x93NUMPY\x02\x00" + (10**6).to_bytes(4, "little") + b"{" * 200, "malformed"),
    "bad-descr": (_npy_header((2,), descr="zz9") + b"\x00" * 16, "malformed"),
    "version-9": (b"\x93NUMPY\x09\x00" + b"\x00" * 40, "version 9"),
    "magic-only": (b"\x93NUMPY", "truncated"),
    "csv-named-npy": (b"1,2\n3,4\n", "not an .npy file"),
    "empty-file": (b"", "empty"),
    "raw-pickle": (b"pickle", "pickle"),
}


@pytest.mark.parametrize("case", sorted(CASES))
def test_npy_refused_by_name(tmp_path: Path, case: str) -> None:
    obj, match = CASES[case]
    p = tmp_path / "m.npy"
    if isinstance(obj, np.ndarray):
        np.save(p, obj, allow_pickle=False)
    elif obj == b"npz":
        np.savez(tmp_path / "a.npz", a=np.ones((3, 3)))
        p.write_bytes((tmp_path / "a.npz").read_bytes())
    elif obj == b"pickle":
        p.write_bytes(pickle.dumps(_toa()))
    else:
        assert isinstance(obj, bytes)
        p.write_bytes(obj)
    with pytest.raises(InputError, match="m.npy: ") as info:
        read_table(p)
    assert match in str(info.value), str(info.value)
    # the same bytes under a .csv name are sniffed as .npy (or refused as binary) the same way
    q = tmp_path / "m.csv"
    q.write_bytes(p.read_bytes())
    if p.read_bytes()[:6] == b"\x93NUMPY":
        with pytest.raises(InputError, match=match):
            read_table(q)


@pytest.mark.parametrize("suffix", [".npy", ".csv", ".txt"])
def test_pickles_are_never_loaded(tmp_path: Path, suffix: str) -> None:
    """An object .npy (np.save with allow_pickle=True) and a raw pickle: refused, the trap not sprung."""
    marker = tmp_path / "unpickled"
    for k, data in enumerate((None, pickle.dumps(_Trap(marker)))):
        p = tmp_path / f"m{k}{suffix}"
        if data is None:
            with open(p, "wb") as f:
                np.save(f, np.array([_Trap(marker), 1], dtype=object), allow_pickle=True)
        else:
            p.write_bytes(data)
        with pytest.raises(InputError):
            read_table(p)
        res = CliRunner().invoke(main, ["calibrate", "toa", str(p), "-o", str(tmp_path / "r.json")])
        assert check_contract(res)[0] == 2
    assert not marker.exists()


def test_npz_with_a_pickled_array_is_refused_without_loading(tmp_path: Path) -> None:
    marker = tmp_path / "unpickled"
    p = tmp_path / "log.npz"
    np.savez(p, a=np.ones(3), b=np.array([_Trap(marker)], dtype=object))
    with pytest.raises(InputError, match="without pickle"):
        load_npz(p)
    before = snapshot(tmp_path)
    res = CliRunner().invoke(main, ["slac", "run", str(p), "-o", str(tmp_path / "r.json")])
    assert check_contract(res, before, snapshot(tmp_path))[0] == 2
    assert not marker.exists()


@pytest.mark.parametrize("command", [["calibrate", "toa"], ["calibrate", "tdoa-farfield"]])
@pytest.mark.parametrize("case", ["structured", "0-d", "3-d", "npz-named-npy", "truncated", "complex"])
def test_commands_refuse_bad_npy_in_one_line(tmp_path: Path, command: list[str], case: str) -> None:
    test_npy_refused_by_name(tmp_path, case)  # writes m.npy
    before = snapshot(tmp_path)
    res = CliRunner().invoke(main, [*command, str(tmp_path / "m.npy"), "-o", str(tmp_path / "r.json")])
    code, _, err = check_contract(res, before, snapshot(tmp_path))
    assert code == 2 and "m.npy" in err, err
