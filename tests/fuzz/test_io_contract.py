"""Nothing a run reads is ever destroyed, and no call ends in a raw exception (issue 28).

Classes, not instances:

* every command's every output option against every one of its inputs, walked from the
  click tree (a new command or option is covered without editing this file): the output
  names the input itself, a symlink to it, a hard link to it, or (for a folder input) a
  file inside it -> exit 2, one line naming both, every file unchanged;
* ``simulate --out`` replaces a folder only when it holds just what an earlier simulate
  wrote (its manifest), never deleting anything else;
* standard output that cannot be written (closed) is exit 2;
* the table reader decides header / names from the whole first row / column: one
  non-number anywhere among numbers is refused by its cell, never turns numbers into names;
* every public function refuses wrong types with an InputError naming the argument;
* structural observability of a TOA matrix is decided from its pattern up front (a matrix
  mostly of empty nodes refused; the time-order test unchanged by rows without pairs).
"""

from __future__ import annotations

import inspect
import os
import subprocess
import sys
from pathlib import Path

import click
import numpy as np
import pytest
from click.testing import CliRunner

import selfcal
from selfcal.cli import main
from selfcal.commands._common import OUTPUT_PARAMS, is_input_param
from selfcal.errors import DegenerateGeometryError, InputError, SelfcalError
from selfcal.io import read_table, write_json

from .test_cli import check_contract, snapshot
from .test_options import COMMANDS

SRC = str(Path(selfcal.__file__).resolve().parents[1])


# ----------------------------------------------------------------------------- the click tree

def _outputs(cmd: click.Command) -> list[click.Parameter]:
    return [p for p in cmd.params if p.name in OUTPUT_PARAMS]


def _inputs(cmd: click.Command) -> list[click.Parameter]:
    return [p for p in cmd.params if is_input_param(p)]


def _dir_only(p: click.Parameter) -> bool:
    return isinstance(p.type, click.Path) and not p.type.file_okay


def _file_ok(p: click.Parameter) -> bool:
    return not _dir_only(p)


def _dir_ok(p: click.Parameter) -> bool:
    return isinstance(p.type, click.Path) and p.type.dir_okay


def _flag(p: click.Parameter) -> str:
    assert isinstance(p, click.Option)
    return next(o for o in p.opts if o.startswith("--"))


def _label(p: click.Parameter) -> str:
    return _flag(p) if isinstance(p, click.Option) else (p.name or "").upper()


MODES = ("same", "symlink", "hardlink", "inside", "folder")
CLASH_CASES = [
    (path, o.name, i.name, mode)
    for path, cmd in COMMANDS for o in _outputs(cmd) for i in _inputs(cmd) for mode in MODES
    if (mode not in ("inside", "folder") or _dir_ok(i)) and (mode != "hardlink" or _file_ok(i))
]


def test_the_walk_covers_the_commands_of_the_issue() -> None:
    """The clash cases include the ones the issue found (so the walk really reaches them)."""
    have = {(" ".join(p), o, i) for p, o, i, _ in CLASH_CASES}
    for case in [("calibrate toa", "out", "matrix"), ("calibrate toa", "csv_out", "known"),
                 ("locate aoa", "out", "beacons"), ("calibrate tdoa-farfield", "out", "matrix"),
                 ("pipeline", "out", "directory"), ("calibrate tdoa-farfield", "csv_out", "directions")]:
        assert case in have, case
    assert len(CLASH_CASES) >= 80


def test_every_command_runs_inside_the_contract() -> None:
    """Each command callback is wrapped by handle_errors (outputs checked against inputs)."""
    missing = [" ".join(p) for p, cmd in COMMANDS if not getattr(cmd.callback, "__selfcal_contract__", False)]
    assert missing == []


def test_no_path_parameter_is_unclassified() -> None:
    """A parameter that takes a path is either an output (by name) or an input: none is neither."""
    for path, cmd in COMMANDS:
        for p in cmd.params:
            metavar = (getattr(p, "metavar", None) or "").upper()
            takes_path = isinstance(p.type, click.Path) or any(w in metavar for w in ("FILE", "DIR", "PATH"))
            if takes_path:
                assert p.name in OUTPUT_PARAMS or is_input_param(p), (path, p.name)


def _build(tmp: Path, path: tuple[str, ...], out_name: str, in_name: str, mode: str
           ) -> tuple[list[str], click.Parameter, click.Parameter]:
    cmd = dict(COMMANDS)[path]
    o = next(p for p in cmd.params if p.name == out_name)
    i = next(p for p in cmd.params if p.name == in_name)
    # the input under test: a small file, or a folder with a file in it
    if mode in ("inside", "folder"):
        target_in = tmp / "in_folder"
        target_in.mkdir()
        (target_in / "setup.json").write_text('{"x": 1}\n')
        victim = target_in / "setup.json" if mode == "inside" else target_in
    else:
        target_in = tmp / "in_file.csv"
        target_in.write_text("1,2,3\n4,5,6\n")
        victim = target_in
    if mode in ("same", "inside", "folder"):
        target_out = victim
    elif mode == "symlink":
        target_out = tmp / "link_out"
        target_out.symlink_to(victim)
    else:
        target_out = tmp / "hard_out"
        os.link(victim, target_out)
    values: dict[str, Path] = {in_name: target_in, out_name: target_out}
    for p in cmd.params:  # every other required path: a fresh input file / a new output path
        if p.required and p.name not in values:
            if p.name in OUTPUT_PARAMS:
                values[p.name or ""] = tmp / (f"new_{p.name}" + ("" if _dir_only(p) else ".json"))
            else:
                f = tmp / f"other_{p.name}.csv"
                f.write_text("1,2\n3,4\n")
                values[p.name or ""] = f
    args = list(path)
    for p in cmd.params:  # arguments in order, then options
        if isinstance(p, click.Argument) and p.name in values:
            args.append(str(values[p.name]))
    for p in cmd.params:
        if isinstance(p, click.Option) and p.name in values:
            args += [_flag(p), str(values[p.name])]
    return args, o, i


@pytest.mark.parametrize("path,out_name,in_name,mode", CLASH_CASES,
                         ids=[f"{' '.join(c[0])}:{c[1]}={c[2]}:{c[3]}" for c in CLASH_CASES])
def test_an_output_never_names_an_input(tmp_path: Path, monkeypatch, path: tuple[str, ...],  # type: ignore[no-untyped-def]
                                        out_name: str, in_name: str, mode: str) -> None:
    monkeypatch.chdir(tmp_path)
    args, o, i = _build(tmp_path, path, out_name, in_name, mode)
    before = snapshot(tmp_path)
    res = CliRunner().invoke(main, args, catch_exceptions=True)
    code, _, err = check_contract(res, before, snapshot(tmp_path))
    assert code == 2, (args, err)
    if _dir_only(o) != (mode == "folder"):  # a kind mismatch: click may refuse it first (nothing touched)
        assert ("is the input" in err and _label(i) in err) or "is a file" in err or "is a directory" in err, err
        assert _label(o) in err, err
        return
    assert "is the input" in err and _label(o) in err and _label(i) in err, err


# ----------------------------------------------------------------------------- simulate --out

SIM = ["simulate", "conference", "--units", "5", "--sample-rate", "8000", "--max-order", "0", "--room", "4x4x3"]


def test_simulate_replaces_only_its_own_folder(tmp_path: Path) -> None:
    out = tmp_path / "rec"
    res = CliRunner().invoke(main, [*SIM, "--out", str(out)])
    assert res.exit_code == 0, res.output
    assert (out / "simulate-manifest.json").is_file()
    res = CliRunner().invoke(main, [*SIM, "--seed", "1", "--out", str(out)])  # its own folder: replaced
    assert res.exit_code == 0, res.output
    # anything it did not write, or a file changed since, blocks the replacement; nothing is deleted
    for name, change in (("notes.txt", "new"), (".hidden", "new"), ("truth.json", "edit"), ("sub", "dir")):
        target = out / name
        if change == "new":
            target.write_text("mine\n")
        elif change == "dir":
            target.mkdir()
        else:
            target.write_bytes(target.read_bytes() + b" ")
        before = snapshot(tmp_path)
        res = CliRunner().invoke(main, [*SIM, "--out", str(out)])
        code, _, err = check_contract(res, before, snapshot(tmp_path))
        assert code == 2 and name in err, err
        if change == "dir":
            target.rmdir()
        elif change == "new":
            target.unlink()
        else:
            target.write_bytes(target.read_bytes()[:-1])
    res = CliRunner().invoke(main, [*SIM, "--out", str(out)])  # restored: its own folder again
    assert res.exit_code == 0, res.output


@pytest.mark.parametrize("content", ["notes.txt", "setup.json"])
def test_simulate_refuses_a_folder_without_its_manifest(tmp_path: Path, content: str) -> None:
    """A recording made by hand (a setup.json, no manifest) is not simulate's to delete."""
    out = tmp_path / "rec"
    out.mkdir()
    (out / content).write_text("{}\n")
    before = snapshot(tmp_path)
    res = CliRunner().invoke(main, [*SIM, "--out", str(out)])
    code, _, err = check_contract(res, before, snapshot(tmp_path))
    assert code == 2 and "simulate-manifest.json" in err


# ----------------------------------------------------------------------------- standard output

def _matrix_file(tmp: Path, seed: int) -> Path:
    g = np.random.default_rng(seed)
    R, S = g.uniform(0, 10, (8, 3)), g.uniform(0, 10, (10, 3))
    p = tmp / "m.csv"
    np.savetxt(p, np.linalg.norm(R[:, None] - S[None], axis=2), delimiter=",")
    return p


@pytest.mark.parametrize("argv", [["calibrate", "toa", "{m}", "--out", "-"],
                                  ["-q", "calibrate", "toa", "{m}", "--out", "-"],
                                  ["calibrate", "toa", "{m}", "--out", "{d}/r.json", "--csv", "-"]])
@pytest.mark.parametrize("redirect", ["1>&-", "1<{m}"])
def test_closed_stdout_is_exit_2(tmp_path: Path, argv: list[str], redirect: str) -> None:
    """Standard output closed, or open for reading only: refused before any work."""
    m = _matrix_file(tmp_path, 0)
    args = [a.format(m=m, d=tmp_path) for a in argv]
    before = snapshot(tmp_path)
    cmd = " ".join([sys.executable, "-m", "selfcal", *args]) + " " + redirect.format(m=m)
    proc = subprocess.run(["bash", "-c", cmd], capture_output=False, stderr=subprocess.PIPE, timeout=120,
                          env={**os.environ, "PYTHONPATH": SRC, "OPENBLAS_NUM_THREADS": "1"}, text=True)
    assert proc.returncode == 2, proc.stderr
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and "standard output" in lines[0], proc.stderr
    assert snapshot(tmp_path) == before


# ----------------------------------------------------------------------------- the table reader

BAD_CELLS = ["1_0", "0x1A", "foo", "1e", "--1", "1.2.3", "n/a?", "12abc"]


@pytest.mark.parametrize("seed", range(12))
def test_one_non_number_is_named_wherever_it_is(tmp_path: Path, seed: int) -> None:
    """One bad cell anywhere in a numeric table (corner, first row, first column, inside):
    refused naming its line and column, never read as a header or names."""
    g = np.random.default_rng(seed)
    I, J = int(g.integers(2, 9)), int(g.integers(2, 13))
    X = g.uniform(0.5, 20, (I, J)).round(3)
    where = [(0, 0), (0, int(g.integers(0, J))), (int(g.integers(0, I)), 0), (int(g.integers(0, I)), int(g.integers(0, J)))]
    for r, c in where:
        cells = [[repr(float(v)) for v in row] for row in X]
        cells[r][c] = str(g.choice(BAD_CELLS))
        p = tmp_path / "m.csv"
        p.write_text("\n".join(",".join(row) for row in cells) + "\n")
        with pytest.raises(InputError, match=rf"row {r + 1}, column {c + 1}:"):
            read_table(p)


@pytest.mark.parametrize("seed", range(8))
def test_names_and_headers_keep_every_number(tmp_path: Path, seed: int) -> None:
    """Headers, names, semicolons with decimal commas and a BOM: the numbers read are the numbers written."""
    g = np.random.default_rng(seed)
    I, J = int(g.integers(1, 7)), int(g.integers(1, 9))
    X = g.uniform(0.5, 20, (I, J)).round(2)
    rows = [f"rx{i}" for i in range(I)]
    cols = [f"s{j}" for j in range(J)]
    for header in (False, True):
        for names in (False, True):
            for semi in (False, True):
                fmt = (lambda v: repr(float(v)).replace(".", ",")) if semi else (lambda v: repr(float(v)))
                sep = ";" if semi else ","
                lines = []
                if header:
                    lines.append(sep.join(([""] if names else []) + cols))
                for i in range(I):
                    lines.append(sep.join(([rows[i]] if names else []) + [fmt(v) for v in X[i]]))
                if semi and J == 1 and not names:
                    continue  # "1,5" alone: a decimal comma or two columns? no ';' says which
                p = tmp_path / "m.csv"
                p.write_bytes(("\ufeff" if seed % 2 else "").encode() + ("\n".join(lines) + "\n").encode())
                t = read_table(p)
                np.testing.assert_array_equal(t.values, X)
                assert t.col_names == (tuple(cols) if header else None)
                assert t.row_names == (tuple(rows) if names else None)


# ----------------------------------------------------------------------------- the Python API

PUBLIC = sorted(n for n in selfcal._LAZY if inspect.isfunction(getattr(selfcal, n)))
WRONG = [None, b"path", {"a": 1}, True, object(), 3.5, ["a", "b"], np.ones((6, 8), bool), np.zeros((0,))]


def test_every_public_function_validates_at_its_entry() -> None:
    missing = [n for n in PUBLIC if not getattr(getattr(selfcal, n), "__selfcal_entry__", False)]
    assert missing == []


def _first_args(name: str, bad: object) -> tuple[object, ...]:
    ok = {"solve_aoa": (np.ones((5, 3)),), "align": (np.ones((4, 3)),), "aligned_rmse": (np.ones((4, 3)),),
          "write_json": ({},), "run_sweep": ([],), "solve_toa_sparse": (np.array([0, 1]), np.array([1.0, 2.0]))}
    if name == "write_json":
        return (bad, {})
    return (bad, *ok.get(name, ()))


@pytest.mark.parametrize("name", PUBLIC)
def test_wrong_types_are_input_errors(name: str) -> None:
    """Each wrong type as the first argument: a SelfcalError (InputError for a type) in one line."""
    f = getattr(selfcal, name)
    first = next(iter(inspect.signature(f).parameters))
    for bad in WRONG:
        try:
            f(*_first_args(name, bad))
        except SelfcalError as exc:
            text = str(exc)
            assert "\n" not in text and len(text) < 500
            if not isinstance(bad, np.ndarray):  # a type error names the argument
                assert isinstance(exc, (InputError, DegenerateGeometryError)), (name, bad, exc)
        except BaseException as exc:  # noqa: BLE001 - the point of the test
            pytest.fail(f"{name}({type(bad).__name__}) raised {type(exc).__name__}: {exc}")
        else:
            if isinstance(bad, (bool, bytes, dict)) or bad is None:
                pytest.fail(f"{name}({type(bad).__name__}) accepted a wrong {first}")


@pytest.mark.parametrize("seed", range(4))
def test_booleans_are_not_ranges(seed: int) -> None:
    g = np.random.default_rng(seed)
    B = g.random((6, 8)) > 0.5
    for f in (selfcal.solve_toa, selfcal.solve_farfield):
        for value in (B, B.tolist(), np.ma.masked_array(B)):
            with pytest.raises(InputError, match="boolean"):
                f(value)
    with pytest.raises(InputError, match="boolean"):
        selfcal.solve_toa_sparse(np.array([0, 1, 2]), np.array([0, 1, 2]), np.array([True, False, True]))


@pytest.mark.parametrize("i,j,y,I,J,match", [
    ([], [], [], None, None, "empty"),
    (np.array([], int), np.array([], int), np.array([]), 5, 5, "empty"),
    ([0, 1], [0, 1], [1.0, 2.0], 10**12, 10**12, "memory"),
    ([0, 1], [0, 1], [1.0, 2.0], 2, 10**15, "memory"),
    ([0.5, 1], [0, 1], [1.0, 2.0], None, None, "integer"),
    ([-1, 1], [0, 1], [1.0, 2.0], None, None, ">= 0"),
    ([0, 1, 2], [0, 1], [1.0, 2.0], None, None, "one length"),
])
def test_sparse_pairs_refused_up_front(i, j, y, I, J, match) -> None:  # type: ignore[no-untyped-def]
    with pytest.raises(InputError, match=match):
        selfcal.solve_toa_sparse(np.asarray(i), np.asarray(j), np.asarray(y, dtype=float), I, J)


def test_sparse_more_nodes_than_the_pairs_can_reach() -> None:
    with pytest.raises(DegenerateGeometryError, match="less than half"):
        selfcal.solve_toa_sparse(np.arange(10), np.arange(10), np.ones(10), 1000, 1000)


def test_write_json_cycles_and_depth(tmp_path: Path) -> None:
    a: list[object] = []
    a.append(a)
    d: dict[str, object] = {"x": [1, {}]}
    d["x"][1]["back"] = d  # type: ignore[index]
    deep: list[object] = []
    for _ in range(100_000):
        deep = [deep]
    for obj, match in ((a, "cycle"), (d, "cycle"), (deep, "nested")):
        with pytest.raises(InputError, match=match):
            write_json(tmp_path / "x.json", obj)
    assert not (tmp_path / "x.json").exists()
    shared = [1, 2]
    write_json(tmp_path / "ok.json", {"a": shared, "b": shared})  # shared, not cyclic: written
    assert (tmp_path / "ok.json").exists()


@pytest.mark.parametrize("path", [b"m.csv", bytearray(b"m.csv"), 3, None, ["m.csv"], "", "a\x00b"])
def test_readers_take_paths_only(path: object) -> None:
    for f in (selfcal.read_table, selfcal.read_matrix, selfcal.load_recording, selfcal.load_lps):
        with pytest.raises(InputError, match="path"):
            f(path)


# ----------------------------------------------------------------------------- observability

@pytest.mark.parametrize("seed", range(5))
def test_time_order_test_ignores_rows_without_pairs(seed: int) -> None:
    """Rows with fewer than two entries add nothing to the statistic: the same test, with or without them."""
    from selfcal.toa.recipes.recipes import detect_time_order

    g = np.random.default_rng(seed)
    t = np.linspace(0, 1, 60)
    M = np.abs(np.sin(np.outer(g.uniform(1, 3, 5), t))) + 1 + 0.01 * g.normal(size=(5, 60))
    padded = np.full((40, 60), np.nan)
    rows = np.sort(g.choice(40, 5, replace=False))
    padded[rows] = M
    padded[[r for r in range(40) if r not in rows][:3], int(g.integers(0, 60))] = 2.0  # single entries
    a, b = detect_time_order(M, rng=seed), detect_time_order(padded, rng=seed)
    assert (a.p_value, a.ratio, a.detected) == (b.p_value, b.ratio, b.detected)


@pytest.mark.parametrize("seed", range(5))
def test_a_matrix_mostly_of_empty_nodes_is_refused(seed: int) -> None:
    from selfcal._checks import check_toa_observable

    g = np.random.default_rng(seed)
    # a 20 x 20 block in a 45-65 x 45-65 matrix: 400 entries pass the whole count (3 (I + J) - 6
    # <= 384 unknowns), yet more than half of the I + J nodes have no entry at all
    I, J = int(g.integers(45, 66)), int(g.integers(45, 66))
    M = np.full((I, J), np.nan)
    rows, cols = g.choice(I, 20, replace=False), g.choice(J, 20, replace=False)
    M[np.ix_(rows, cols)] = g.uniform(1, 10, (20, 20))
    with pytest.raises(DegenerateGeometryError, match="no observed entry"):
        check_toa_observable(M, 3)
    with pytest.raises(DegenerateGeometryError, match="no observed entry"):
        selfcal.solve_toa(M)


def _cheap_calls() -> dict[str, tuple[object, ...]]:
    g = np.random.default_rng(0)
    R, S = g.uniform(0, 10, (8, 3)), g.uniform(0, 10, (10, 3))
    P = g.uniform(-1, 1, (8, 3))
    N = g.normal(size=(10, 3))
    N /= np.linalg.norm(N, axis=1, keepdims=True)
    return {"solve_toa": (np.linalg.norm(R[:, None] - S[None], axis=2),),
            "solve_farfield": (-(P @ N.T) + g.uniform(-1, 1, 10),),
            "solve_aoa": (g.normal(size=(6, 3)), g.normal(size=(6, 3))),
            "align": (R, R), "aligned_rmse": (R, R),
            "solve_toa_sparse": (np.array([0, 1]), np.array([0, 1]), np.array([1.0, 2.0]))}


KEYWORD_CASES = [(n, p) for n in _cheap_calls() for p, par in inspect.signature(getattr(selfcal, n)).parameters.items()
                 if par.default is not inspect.Parameter.empty]


@pytest.mark.parametrize("name,param", KEYWORD_CASES, ids=[f"{n}:{p}" for n, p in KEYWORD_CASES])
def test_wrong_keyword_types_name_the_argument(name: str, param: str) -> None:
    """A dict, bytes or a bare object for any keyword: an InputError naming that keyword."""
    f = getattr(selfcal, name)
    args = _cheap_calls()[name]
    for bad in ({"a": 1}, b"x", object()):
        with pytest.raises(SelfcalError) as exc:
            f(*args, **{param: bad})
        assert param in str(exc.value) and "\n" not in str(exc.value), (name, param, str(exc.value))


PAIR_CASES = [(path, a.name, b.name, mode) for path, cmd in COMMANDS
              for k, a in enumerate(_outputs(cmd)) for b in _outputs(cmd)[k + 1:]
              if _file_ok(a) and _file_ok(b) and a.name != "report" and b.name != "report"
              for mode in ("same", "symlink", "hardlink")]


@pytest.mark.parametrize("path,a_name,b_name,mode", PAIR_CASES,
                         ids=[f"{' '.join(c[0])}:{c[1]}={c[2]}:{c[3]}" for c in PAIR_CASES])
def test_two_outputs_never_name_one_file(tmp_path: Path, path: tuple[str, ...], a_name: str, b_name: str,
                                         mode: str) -> None:
    """Two file outputs of one run on one file (by path, symlink or hard link): exit 2, nothing written."""
    cmd = dict(COMMANDS)[path]
    first = tmp_path / "out.png"
    first.write_bytes(b"old")
    second = {"same": first, "symlink": tmp_path / "link.png", "hardlink": tmp_path / "hard.png"}[mode]
    if mode == "symlink":
        second.symlink_to(first)
    elif mode == "hardlink":
        os.link(first, second)
    values: dict[str, Path] = {a_name: first, b_name: second}
    for p in cmd.params:
        if p.required and p.name not in values:
            f = tmp_path / f"in_{p.name}.csv"
            f.write_text("1,2\n3,4\n")
            values[p.name or ""] = f
    args = list(path) + [str(values[p.name]) for p in cmd.params if isinstance(p, click.Argument) and p.name in values]
    for p in cmd.params:
        if isinstance(p, click.Option) and p.name in values:
            args += [_flag(p), str(values[p.name])]
    before = snapshot(tmp_path)
    res = CliRunner().invoke(main, args, catch_exceptions=True)
    code, _, err = check_contract(res, before, snapshot(tmp_path))
    assert code == 2 and "same file" in err, err


@pytest.mark.parametrize("shell", ["{py} calibrate toa - --out {m} < {m}",
                                   "{py} calibrate toa {m} --out - >> {m}",
                                   "{py} calibrate toa - --out - < {m} >> {m}",
                                   "{py} calibrate toa - --out {d}/link.csv < {m}"])
def test_standard_streams_behind_an_input(tmp_path: Path, shell: str) -> None:
    """The file behind `< file` is an input, and `--out - >> file` an output: they never meet."""
    m = _matrix_file(tmp_path, 1)
    (tmp_path / "link.csv").symlink_to(m)
    before = snapshot(tmp_path)
    cmd = shell.format(py=f"{sys.executable} -m selfcal", m=m, d=tmp_path)
    proc = subprocess.run(["bash", "-c", cmd], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, timeout=120,
                          env={**os.environ, "PYTHONPATH": SRC, "OPENBLAS_NUM_THREADS": "1"}, text=True)
    assert proc.returncode == 2 and "standard" in proc.stderr and "is the input" in proc.stderr, proc.stderr
    assert len([ln for ln in proc.stderr.splitlines() if ln.strip()]) == 1
    assert snapshot(tmp_path) == before


def test_a_text_table_beyond_memory_is_refused_before_parsing(tmp_path: Path, monkeypatch) -> None:  # type: ignore[no-untyped-def]
    """The reader's memory guard, on a machine made small (8 kB 'RAM'): a 2 kB CSV would need 64 kB."""
    p = tmp_path / "m.csv"
    p.write_text("\n".join(",".join(["1.5"] * 25) for _ in range(20)) + "\n")
    assert read_table(p).values.shape == (20, 25)
    monkeypatch.setattr(os, "sysconf", lambda name: 4096 if name == "SC_PAGE_SIZE" else 4)
    with pytest.raises(InputError, match="text table"):
        read_table(p)
