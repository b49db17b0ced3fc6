"""Readers and writers: CSV / NPY matrices, JSON results (atomic), NPZ logs (no pickle).

Matrices follow the project convention: rows = receivers, columns = transmitters,
``nan`` or an empty CSV field = missing.
"""

from __future__ import annotations

import csv
import json
import math
import os
import tempfile
from collections.abc import Mapping
from dataclasses import fields, is_dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .errors import InputError

__all__ = ["read_matrix", "write_matrix", "to_jsonable", "write_json", "read_json", "atomic_write_bytes", "load_npz"]


def read_matrix(path: str | os.PathLike[str], name: str | None = None) -> NDArray[np.float64]:
    """Read a numeric matrix from ``.csv`` (comma separated, no header) or ``.npy``.

    Empty fields and ``nan`` (any case) are missing values -> NaN. Anything else that is
    not a number is refused with the row/column named. A 1-D file becomes a column.
    """
    p = Path(path)
    label = name or str(p)
    if not p.is_file():
        raise InputError(f"{label}: file not found")
    if p.suffix.lower() == ".npy":
        try:
            arr = np.load(p, allow_pickle=False)
        except (ValueError, OSError) as exc:
            raise InputError(f"{label}: not a readable .npy array without pickle ({exc})") from None
        if arr.dtype.kind not in "fiub":
            raise InputError(f"{label}: .npy dtype {arr.dtype} is not numeric")
        arr = np.asarray(arr, dtype=float)
    else:
        rows: list[list[float]] = []
        try:
            with p.open(newline="") as fh:
                for r, row in enumerate(csv.reader(fh)):
                    if not row or all(not c.strip() for c in row) and len(row) <= 1:
                        continue
                    vals = []
                    for c, cell in enumerate(row):
                        cell = cell.strip()
                        if cell == "" or cell.lower() == "nan":
                            vals.append(math.nan)
                            continue
                        try:
                            vals.append(float(cell))
                        except ValueError:
                            raise InputError(f"{label}: row {r + 1}, column {c + 1}: {cell!r} is not a number") from None
                    rows.append(vals)
        except UnicodeDecodeError:
            raise InputError(f"{label}: not a text CSV file") from None
        if not rows:
            raise InputError(f"{label}: the file is empty")
        widths = {len(r) for r in rows}
        if len(widths) != 1:
            raise InputError(f"{label}: rows have different numbers of fields {sorted(widths)}")
        arr = np.array(rows, dtype=float)
    if arr.ndim == 1:
        arr = arr[:, None]
    if arr.ndim != 2:
        raise InputError(f"{label}: expected a 2-D matrix, got shape {arr.shape}")
    return arr


def write_matrix(path: str | os.PathLike[str], matrix: NDArray[Any]) -> None:
    """Write a 2-D matrix as CSV (``nan`` for missing) or ``.npy``, atomically."""
    p = Path(path)
    arr = np.asarray(matrix, dtype=float)
    if p.suffix.lower() == ".npy":
        import io as _io

        buf = _io.BytesIO()
        np.save(buf, arr, allow_pickle=False)
        atomic_write_bytes(p, buf.getvalue())
    else:
        lines = [",".join("nan" if not np.isfinite(v) else repr(float(v)) for v in row) for row in np.atleast_2d(arr)]
        atomic_write_bytes(p, ("\n".join(lines) + "\n").encode())


def to_jsonable(obj: Any) -> Any:
    """Convert results (dataclasses, arrays, numpy scalars) to JSON-safe Python objects.

    Non-finite floats become ``null`` (strict JSON has no NaN).
    """
    if hasattr(obj, "to_dict") and callable(obj.to_dict):
        return to_jsonable(obj.to_dict())
    if is_dataclass(obj) and not isinstance(obj, type):
        return {f.name: to_jsonable(getattr(obj, f.name)) for f in fields(obj)}
    if isinstance(obj, Mapping):
        return {str(k): to_jsonable(v) for k, v in obj.items()}
    if isinstance(obj, np.ndarray):
        return to_jsonable(obj.tolist())
    if isinstance(obj, (list, tuple)):
        return [to_jsonable(v) for v in obj]
    if isinstance(obj, (np.bool_, bool)):
        return bool(obj)
    if isinstance(obj, (np.integer,)):
        return int(obj)
    if isinstance(obj, (float, np.floating)):
        f = float(obj)
        return f if math.isfinite(f) else None
    if isinstance(obj, Path):
        return str(obj)
    return obj


def atomic_write_bytes(path: str | os.PathLike[str], data: bytes) -> None:
    """Write ``data`` to ``path`` via a temporary file in the same folder + rename.

    A crash or an error never leaves a half-written file at ``path``.
    """
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{p.name}.", suffix=".tmp", dir=p.parent)
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        # mkstemp creates 0600; give the file the permissions a plain open() would have
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)
        os.replace(tmp, p)
    except BaseException:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise


def write_json(path: str | os.PathLike[str], obj: Any, *, indent: int = 2) -> None:
    """Serialise ``obj`` with :func:`to_jsonable` and write it atomically as strict JSON."""
    text = json.dumps(to_jsonable(obj), indent=indent, allow_nan=False)
    atomic_write_bytes(path, (text + "\n").encode())


def read_json(path: str | os.PathLike[str], name: str | None = None) -> Any:
    """Read a JSON file, raising :class:`InputError` naming the file on failure."""
    p = Path(path)
    label = name or str(p)
    if not p.is_file():
        raise InputError(f"{label}: file not found")
    try:
        return json.loads(p.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise InputError(f"{label}: malformed JSON ({exc})") from None


def load_npz(path: str | os.PathLike[str], required: tuple[str, ...] = ()) -> dict[str, NDArray[Any]]:
    """Load an ``.npz`` archive without pickle; check that ``required`` keys exist."""
    p = Path(path)
    if not p.is_file():
        raise InputError(f"{p}: file not found")
    try:
        with np.load(p, allow_pickle=False) as z:
            out = {k: z[k] for k in z.files}
    except (ValueError, OSError) as exc:
        raise InputError(f"{p}: not a readable .npz archive without pickle ({exc})") from None
    missing = [k for k in required if k not in out]
    if missing:
        raise InputError(f"{p}: missing arrays {missing}")
    return out
