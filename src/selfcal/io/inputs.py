"""Readers: CSV / NPY matrices with their names, JSON, NPZ logs (never pickle).

Readers take real files. :func:`read_table` sniffs the delimiter (comma, semicolon, tab,
whitespace), a header row and a first column of names, a UTF-8 BOM, CRLF line ends, ``#``
comments (``np.savetxt`` output loads), and refuses what Python's ``float`` would misread
(``1_0``); errors name the row and the column.
"""

from __future__ import annotations

import csv
import io as _io
import json
import math
import os
import re
import stat
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .._checks import entry
from ..errors import InputError
from ._paths import _is_dash, _kind_name, _oserror_text, note_input

#: Cell texts read as a missing value (case-insensitive), besides the empty field.
MISSING_TOKENS = frozenset({"", "na", "nan", "n/a", "#n/a", "null", "none", "-nan", "+nan"})  # #N/A: Excel

# strict decimal number: no underscores, no hex, no "infinity" spelled out
_NUMBER = re.compile(r"[+-]?(?:\d+(?:\.\d*)?|\.\d+)(?:[eE][+-]?\d+)?\Z", re.ASCII)  # linear time
_INF = re.compile(r"[+-]?inf\Z", re.IGNORECASE | re.ASCII)
_DECIMAL_COMMA = re.compile(r"[+-]?\d+,\d+(?:[eE][+-]?\d+)?\Z", re.ASCII)



# --------------------------------------------------------------------------------------
# inputs
# --------------------------------------------------------------------------------------

def _read_input_bytes(path: str | os.PathLike[str], label: str) -> bytes:
    if _is_dash(path):
        stream = sys.stdin
        buf = getattr(stream, "buffer", None)
        data = buf.read() if buf is not None else stream.read()
        return data if isinstance(data, bytes) else data.encode()
    p = Path(path)
    try:
        st = os.stat(p)
    except FileNotFoundError:
        raise InputError(f"{label}: file not found") from None
    except OSError as exc:
        raise InputError(f"{label}: cannot read ({_oserror_text(exc)})") from None
    if stat.S_ISDIR(st.st_mode):
        raise InputError(f"{label}: is a directory, not a file")
    if not stat.S_ISREG(st.st_mode):
        raise InputError(f"{label}: is {_kind_name(st.st_mode)}; give a regular file (or '-' for standard input)")
    note_input(p, label)
    try:
        return p.read_bytes()
    except OSError as exc:
        raise InputError(f"{label}: cannot read ({_oserror_text(exc)})") from None
    except MemoryError:
        raise InputError(f"{label}: too large to read into memory ({st.st_size} bytes)") from None


@dataclass(frozen=True)
class Table:
    """A numeric matrix read from a file, with the names it carried.

    Attributes
    ----------
    values:
        (rows, cols) float array, NaN = missing.
    row_names:
        Names from a first column of labels (one per row), or None.
    col_names:
        Names from a header row (one per value column), or None.
    """

    values: NDArray[np.float64]
    row_names: tuple[str, ...] | None = None
    col_names: tuple[str, ...] | None = None


def _cell_kind(cell: str) -> str:
    c = cell.strip().strip('"').strip("'").strip()
    if c.lower() in MISSING_TOKENS:
        return "missing"
    if _NUMBER.match(c) or _INF.match(c):
        return "number"
    return "text"


def _short(cell: str) -> str:
    c = cell.strip()
    return repr(c if len(c) <= 24 else c[:20] + "...")


def _layout(kinds: list[list[str]]) -> tuple[bool, bool]:
    """(header row?, names column?) decided from the whole first row and the whole first column.

    The first row is a header when no cell of it is a number (at least one text, the others
    empty: a blank corner above the names) and more rows follow. The first column is names
    when more columns follow and every cell of it below the header is text. A single text
    cell among numbers (``1_0``, ``0x1A``, a stray word) makes neither, so no row or column of
    numbers is ever taken for names; the reader then names that cell.
    """
    nrow, ncol = len(kinds), len(kinds[0])
    first = kinds[0]
    header = nrow > 1 and "number" not in first and "text" in first
    body = kinds[1:] if header else kinds
    names_col = ncol > 1 and bool(body) and all(r[0] == "text" for r in body)
    return header, names_col


def _layout_hint(kinds: list[list[str]], r: int, c: int) -> str:
    """Why a text cell was not read as a name or a header (a typo is the likelier cause)."""
    if c == 0 and len(kinds[0]) > 1:
        n = sum(k[0] == "number" for k in kinds)
        if n:
            return f" (not a names column: {n} other cells of column 1 are numbers)"
    if r == 0 and len(kinds) > 1:
        n = sum(k == "number" for k in kinds[0])
        if n:
            return f" (not a header: {n} other cells of the first row are numbers)"
    return ""


def _sniff_delimiter(lines: list[str]) -> str | None:
    """Pick ',', ';' or tab when every line has the same positive count; None = whitespace."""
    best = None
    for d in (";", ",", "\t", "|"):  # ";" first: a semicolon file with decimal commas has both
        counts = {ln.count(d) for ln in lines}
        if min(counts) > 0 and (best is None or len(counts) == 1):
            if best is None or len(counts) == 1 and best[1] > 1:
                best = (d, len(counts))
    if best is not None:
        return best[0]
    # a delimiter missing from some lines (e.g. a one-column file) -> the most frequent one
    total = {d: sum(ln.count(d) for ln in lines) for d in (",", ";", "\t")}
    d, n = max(total.items(), key=lambda kv: kv[1])
    return d if n > 0 else None


def _split(lines: list[str], delim: str | None) -> list[list[str]]:
    if delim is None:
        return [ln.split() for ln in lines]
    old = csv.field_size_limit()
    csv.field_size_limit(min(sys.maxsize, 2**31 - 1))  # cells of any size, no _csv.Error
    try:
        return [next(csv.reader([ln], delimiter=delim, skipinitialspace=True), []) for ln in lines]
    except csv.Error as exc:
        raise InputError(f"unreadable CSV ({exc})") from None
    finally:
        csv.field_size_limit(old)


def _is_comment(line: str) -> bool:
    """A ``#`` comment line -- but not a data row whose first cell is Excel's ``#N/A``."""
    t = line.lstrip()
    return t.startswith("#") and not t[:4].upper() == "#N/A"


@entry(path="path", name="str?")
def read_table(path: str | os.PathLike[str], name: str | None = None) -> Table:
    """Read a numeric matrix from ``.npy`` or delimited text, keeping row/column names.

    Parameters
    ----------
    path:
        ``.npy`` (no pickle) or text; ``"-"`` reads text from standard input.
    name:
        Label used in error messages (default: the path).

    Returns
    -------
    Table
        The values (NaN = missing) and any names.

    Notes
    -----
    Text dialects: comma, semicolon (with decimal commas), tab, ``|`` or whitespace separated
    (sniffed; ``np.savetxt`` output loads), UTF-8 with or without BOM, LF or CRLF, blank and
    ``#`` comment lines skipped (not a line starting with Excel's ``#N/A``). Missing: empty,
    ``NA``, ``NaN``, ``nan``, ``N/A``, ``#N/A`` (Excel), ``null``.
    The layout is decided from whole rows and columns: the first row is a header when none of
    its cells is a number; the first column is names when every cell of it (below a header) is
    text. A single non-number among numbers (``1_0``, ``0x1A``, a stray word in the corner) is
    refused by its line and column, never taken as a sign of names, so no numeric row or column
    is ever dropped. Numbers are strict decimals: ``1_0``, ``0x10`` and
    the like are refused with the row and column named. A 1-D input becomes one column.

    Raises
    ------
    InputError
        Not found, unreadable, not text, ragged rows, a non-number (row and column named).

    Examples
    --------
    >>> import tempfile, pathlib
    >>> p = pathlib.Path(tempfile.mkdtemp()) / "m.csv"
    >>> _ = p.write_text("name;s1;s2\\nrx1;1,5;NA\\n")
    >>> t = read_table(p)
    >>> t.row_names, t.col_names, t.values.tolist()
    (('rx1',), ('s1', 's2'), [[1.5, nan]])
    """
    label = name or os.fspath(path)
    if not _is_dash(path) and Path(path).suffix.lower() in (".npy", ".npz"):
        return Table(_read_npy(path, label))
    data = _read_input_bytes(path, label)
    if data[:6] == b"\x93NUMPY":
        return Table(_read_npy(data, label))
    if data[:2] == b"PK":
        raise InputError(f"{label}: looks like an .npz archive; give a .csv or .npy matrix")
    if b"\x00" in data[:65536]:
        raise InputError(f"{label}: not a text file (binary data)")
    # parsing holds each cell as a Python string and its kind: ~28 bytes per byte of text for
    # one-character cells (a 9.1 MB 3000 x 3000 CSV peaks at 250 MB), so refuse what cannot fit
    from .._checks import guard_size

    guard_size(32.0 * len(data), f"{label}: parsing a {len(data) / 1e6:.3g} MB text table "
                                 f"(save large matrices as .npy)")
    try:
        text = data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise InputError(f"{label}: not UTF-8 text (byte {exc.start})") from None
    numbered = [(i + 1, ln) for i, ln in enumerate(text.splitlines())]
    numbered = [(i, ln) for i, ln in numbered if ln.strip() and not _is_comment(ln)]
    if not numbered:
        raise InputError(f"{label}: the file is empty")
    lines = [ln for _, ln in numbered]
    delim = _sniff_delimiter(lines)
    try:
        rows = _split(lines, delim)
    except InputError as exc:
        raise InputError(f"{label}: {exc}") from None
    decimal_comma = delim == ";" and any(_DECIMAL_COMMA.match(c.strip()) for r in rows for c in r)
    if decimal_comma:
        rows = [[c.replace(",", ".") if _DECIMAL_COMMA.match(c.strip()) else c for c in r] for r in rows]
    widths = {len(r) for r in rows}
    if len(widths) != 1:
        w0 = len(rows[0])
        k = next(k for k, r in enumerate(rows) if len(r) != w0)
        raise InputError(
            f"{label}: rows have different numbers of fields {sorted(widths)[:6]}: line {numbered[k][0]} has "
            f"{len(rows[k])}, line {numbered[0][0]} has {w0}"
        )
    ncol = widths.pop()
    kinds = [[_cell_kind(c) for c in r] for r in rows]
    header, names_col = _layout(kinds)
    body = range(1 if header else 0, len(rows))
    c0 = 1 if names_col else 0
    values = np.empty((len(body), ncol - c0), dtype=float)
    for out_r, r in enumerate(body):
        for c in range(c0, ncol):
            cell = rows[r][c].strip().strip('"').strip("'").strip()
            kind = kinds[r][c]
            if kind == "missing":
                values[out_r, c - c0] = math.nan
            elif kind == "number":
                values[out_r, c - c0] = float(cell)
            else:
                raise InputError(f"{label}: row {numbered[r][0]}, column {c + 1}: {_short(cell)} is not a "
                                 f"number{_layout_hint(kinds, r, c)}")
    if values.size == 0:
        raise InputError(f"{label}: no numeric values (only a header or names)")
    row_names = tuple(rows[r][0].strip().strip('"') for r in body) if names_col else None
    col_names = tuple(c.strip().strip('"') for c in rows[0][c0:]) if header else None
    return Table(values, row_names, col_names)


#: Longest .npy header parsed (bytes): numpy's own limit (``max_header_size``), so that a hostile
#: header cannot make the literal parser work for long.
_NPY_MAX_HEADER = 10_000


def _npy_header(data: bytes, label: str) -> tuple[np.dtype[Any], tuple[int, ...], bool, int]:
    """Parse an .npy header without loading anything: (dtype, shape, fortran order, data offset).

    Raises
    ------
    InputError
        Not an .npy file, an unknown version, a malformed or over-long header.
    """
    import ast

    if data[:6] != b"\x93NUMPY":
        if data[:2] == b"PK":
            raise InputError(f"{label}: is an .npz archive (zip), not a single .npy array; give one .npy matrix")
        if data[:1] == b"\x80":
            raise InputError(f"{label}: is a Python pickle, not an .npy array; refused (pickles are never loaded)")
        raise InputError(f"{label}: not an .npy file (no NUMPY header; starts with {data[:8]!r}); "
                         f"a text matrix needs a .csv or .txt name")
    if len(data) < 10:
        raise InputError(f"{label}: truncated .npy header")
    major = data[6]
    if major == 1:
        n, start = int.from_bytes(data[8:10], "little"), 10
    elif major in (2, 3):
        n, start = int.from_bytes(data[8:12], "little"), 12
    else:
        raise InputError(f"{label}: .npy format version {major}.{data[7]} is not supported (1.0-3.0)")
    if n > _NPY_MAX_HEADER or start + n > len(data):
        raise InputError(f"{label}: malformed .npy header ({n} bytes declared, {len(data) - start} present)")
    try:
        text = data[start:start + n].decode("latin1" if major < 3 else "utf8")
        hdr = ast.literal_eval(text)
    except (ValueError, SyntaxError, TypeError, MemoryError, RecursionError, UnicodeDecodeError):
        raise InputError(f"{label}: malformed .npy header (not a Python literal)") from None
    if not isinstance(hdr, dict) or set(hdr) != {"descr", "fortran_order", "shape"}:
        raise InputError(f"{label}: malformed .npy header (keys descr, fortran_order, shape expected)")
    shape, fortran = hdr["shape"], hdr["fortran_order"]
    if not isinstance(shape, tuple) or not all(isinstance(k, int) and not isinstance(k, bool) and k >= 0
                                               for k in shape) or not isinstance(fortran, bool):
        raise InputError(f"{label}: malformed .npy header (shape {shape!r}, fortran_order {fortran!r})")
    try:
        dtype = np.lib.format.descr_to_dtype(hdr["descr"])
    except (ValueError, TypeError, KeyError, IndexError):
        raise InputError(f"{label}: malformed .npy header (descr {str(hdr['descr'])[:40]!r})") from None
    return dtype, shape, fortran, start + n


def _read_npy(src: Any, label: str) -> NDArray[np.float64]:
    """An .npy matrix as float64 (C order): the header checked before any data is touched.

    Fortran order, float16 / longdouble, integer and big-endian dtypes are read (cast to
    float64); object (pickled) arrays are refused from the header alone, so nothing is ever
    unpickled; structured, complex, boolean, text and date dtypes, 0-d scalars, empty arrays,
    more than 2 dimensions and data shorter than the shape are refused by name.
    """
    if isinstance(src, (str, os.PathLike)):
        p = Path(src)
        if p.suffix.lower() == ".npz":
            raise InputError(f"{label}: an .npz archive is not a matrix; give a .csv or .npy file")
        data = _read_input_bytes(p, label)
    else:
        data = src.getvalue() if isinstance(src, _io.BytesIO) else bytes(src)
    if not data:
        raise InputError(f"{label}: the file is empty")
    dtype, shape, fortran, offset = _npy_header(data, label)
    if dtype.hasobject:
        raise InputError(f"{label}: .npy array of Python objects (pickled data): refused without loading; "
                         f"save plain numbers (np.save with a float array)")
    if dtype.fields is not None or dtype.subdtype is not None or dtype.kind == "V":
        raise InputError(f"{label}: .npy array has a structured dtype {dtype}; give a plain numeric matrix")
    if dtype.kind == "c":
        raise InputError(f"{label}: complex values; give real numbers")
    if dtype.kind == "b":  # a mask saved by mistake: True / False are not measurements
        raise InputError(f"{label}: .npy array is boolean (a mask?); give the measured values")
    if dtype.kind not in "fiu":
        raise InputError(f"{label}: .npy dtype {dtype} is not numeric")
    if len(shape) == 0:
        raise InputError(f"{label}: .npy holds a single number (0-d), not a matrix")
    if len(shape) > 2:
        raise InputError(f"{label}: expected a 2-D matrix, got shape {shape}")
    count = math.prod(shape)
    if count == 0:
        raise InputError(f"{label}: .npy array is empty (shape {shape})")
    need = count * dtype.itemsize
    if len(data) - offset < need:
        raise InputError(f"{label}: truncated .npy: shape {shape} needs {need} bytes of data, "
                         f"the file holds {len(data) - offset}")
    flat = np.frombuffer(data, dtype=dtype, count=count, offset=offset)
    with np.errstate(over="ignore"):  # float128 beyond float64's range -> inf (refused downstream)
        arr = np.array(flat.reshape(shape, order="F" if fortran else "C"), dtype=np.float64, order="C")
    if arr.ndim == 1:
        arr = arr[:, None]
    return arr


@entry(path="path", name="str?")
def read_matrix(path: str | os.PathLike[str], name: str | None = None) -> NDArray[np.float64]:
    """Read a numeric matrix from delimited text or ``.npy`` (see :func:`read_table`).

    Returns
    -------
    numpy.ndarray
        (rows, cols) float array, NaN = missing; a 1-D file becomes a column.

    Raises
    ------
    InputError
        The file is missing, unreadable or not a numeric matrix (row and column named).
    """
    return read_table(path, name).values


def read_json(path: str | os.PathLike[str], name: str | None = None) -> Any:
    """Read a JSON file (``"-"`` = standard input), raising :class:`InputError` naming the file."""
    label = name or os.fspath(path)
    data = _read_input_bytes(path, label)
    try:
        return json.loads(data.decode("utf-8-sig"))
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise InputError(f"{label}: malformed JSON ({exc})") from None
    except RecursionError:
        raise InputError(f"{label}: JSON nested too deeply") from None
    except ValueError as exc:  # an integer literal beyond Python's 4300-digit conversion limit
        raise InputError(f"{label}: malformed JSON ({' '.join(str(exc).split())[:120]})") from None


def load_npz(path: str | os.PathLike[str], required: tuple[str, ...] = ()) -> dict[str, NDArray[Any]]:
    """Load an ``.npz`` archive without pickle; check that ``required`` keys exist.

    Raises
    ------
    InputError
        Missing, empty, truncated, a ``.npy`` instead, object arrays, or required keys missing.
    """
    p = Path(path)
    label = str(p)
    data = _read_input_bytes(p, label)
    if not data:
        raise InputError(f"{label}: the file is empty")
    if data[:6] == b"\x93NUMPY":
        raise InputError(f"{label}: is a single .npy array; an .npz archive is expected")
    if data[:2] != b"PK":
        raise InputError(f"{label}: not an .npz archive")
    import zipfile

    try:
        with np.load(_io.BytesIO(data), allow_pickle=False) as z:
            out = {k: z[k] for k in z.files}
    except (ValueError, OSError, EOFError, zipfile.BadZipFile, KeyError) as exc:
        raise InputError(f"{label}: not a readable .npz archive without pickle ({exc})") from None
    missing = [k for k in required if k not in out]
    if missing:
        raise InputError(f"{label}: missing arrays {missing}")
    return out
