"""Writers: atomic writes that never destroy anything, all-or-nothing staging, JSON / CSV / NPY outputs.

* **Outputs never destroy anything.** :func:`atomic_write_bytes` writes a temporary file
  beside the target and ``os.replace``-s it, but only over a regular file or a new path.
  A symlink is written through (its target is replaced, the link stays); a directory,
  device, FIFO or socket at the path is refused with :class:`OutputError`. ``"-"`` means
  standard output. Any failure (parent is a file, disk full, read-only, name too long) is an
  :class:`OutputError` and leaves no new file behind.
* **All or nothing.** Inside :func:`staged_outputs` every write is buffered and the whole set
  is committed when the block ends without an exception (temporary files first, then the
  renames), or nothing is written.
"""

from __future__ import annotations

import contextlib
import contextvars
import csv
import errno
import io as _io
import json
import math
import os
import stat
import sys
import tempfile
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any

import numpy as np
from numpy.typing import NDArray

from .._checks import entry
from .._result import jsonable
from ..errors import InputError
from ._paths import _is_dash, _kind_name, _oserror_text, input_named_by

#: Every path committed since the last ``written_files(reset=True)`` (``"-"`` = standard output), in
#: order: the CLI's last line lists them (:class:`selfcal.commands._common.SelfcalGroup`).
_WRITTEN: list[str] = []


def written_files(*, reset: bool = False) -> list[str]:
    """The paths written (committed) so far, as given; ``reset`` empties the record afterwards.

    Examples
    --------
    >>> import tempfile, pathlib
    >>> _ = written_files(reset=True)
    >>> p = pathlib.Path(tempfile.mkdtemp()) / "a.json"
    >>> write_json(p, {"x": 1})
    >>> written_files() == [str(p)]
    True
    """
    out = list(_WRITTEN)
    if reset:
        _WRITTEN.clear()
    return out


def moved_written(old: str | os.PathLike[str], new: str | os.PathLike[str]) -> None:
    """Rename the recorded written paths under folder ``old`` to folder ``new`` (a folder
    staged under a temporary name and then moved into place).

    Examples
    --------
    >>> _ = written_files(reset=True)
    >>> _WRITTEN.append("/tmp/.rec.x1/a.wav")
    >>> moved_written("/tmp/.rec.x1", "/tmp/rec")
    >>> written_files(reset=True)
    ['/tmp/rec/a.wav']
    """
    o, n = os.fspath(old).rstrip(os.sep), os.fspath(new).rstrip(os.sep)
    for k, p in enumerate(_WRITTEN):
        if p == o or p.startswith(o + os.sep):
            _WRITTEN[k] = n + p[len(o):]


_TMP_PREFIX = ".selfcal-"  # constant-length temporary names: a long target name still fits


class OutputError(InputError):
    """An output path cannot be written (a directory, device, FIFO, read-only, disk full, ...)."""


class SerializationError(InputError, TypeError):
    """An object handed to a writer has no JSON form (an InputError naming it; also a TypeError)."""


# --------------------------------------------------------------------------------------
# outputs
# --------------------------------------------------------------------------------------

_STAGE: contextvars.ContextVar[_Stage | None] = contextvars.ContextVar("selfcal_stage", default=None)
_STDOUT: contextvars.ContextVar[IO[Any] | None] = contextvars.ContextVar("selfcal_stdout", default=None)


def check_output_path(path: str | os.PathLike[str], *, kind: str = "file",
                      label: str | None = None) -> Path:
    """Validate an output path before anything is computed; return the real target.

    Parameters
    ----------
    path:
        The path given by the user. ``"-"`` (standard output) is returned unchanged for
        ``kind="file"`` and refused for ``kind="dir"``.
    kind:
        ``"file"``: the target must be a regular file or not exist (a symlink is followed
        to its target). ``"dir"``: the target must be a directory or not exist.
    label:
        Name used in the message (default: the path).

    Returns
    -------
    pathlib.Path
        The resolved target (symlinks followed).

    Raises
    ------
    OutputError
        The target is a directory / device / FIFO / socket (or a file for ``kind="dir"``), an
        ancestor is not a directory, the location is not writable, or a name is too long.

    Examples
    --------
    >>> check_output_path("-")
    PosixPath('-')
    """
    raw = os.fspath(path)
    name = label or raw
    if raw == "-":
        if kind == "dir":
            raise OutputError(f"{name}: '-' (standard output) cannot hold a folder of files")
        return Path("-")
    if raw == "" or "\x00" in raw:
        raise OutputError(f"{name!r}: not a usable path")
    if kind == "file" and raw.endswith(os.sep):
        raise OutputError(f"{name}: ends with '{os.sep}' (a folder); give a file name")
    real = Path(os.path.realpath(raw))
    try:
        st = os.stat(real)
    except FileNotFoundError:
        st = None
    except OSError as exc:  # ENOTDIR (an ancestor is a file), ENAMETOOLONG, ELOOP, EACCES
        raise OutputError(f"{name}: cannot write here ({_oserror_text(exc)})") from None
    if st is not None:
        if kind == "file" and not stat.S_ISREG(st.st_mode):
            what = _kind_name(st.st_mode)
            hint = "; give a file name" if stat.S_ISDIR(st.st_mode) else "; refusing to replace it"
            raise OutputError(f"{name}: is {what}{hint}")
        if kind == "dir" and not stat.S_ISDIR(st.st_mode):
            raise OutputError(f"{name}: exists and is not a directory")
        if kind == "file" and not os.access(real, os.W_OK):
            raise OutputError(f"{name}: the existing file is read-only")
        if kind == "dir" and not os.access(real, os.W_OK | os.X_OK):
            raise OutputError(f"{name}: the directory is not writable")
        return real
    # walk up to the first existing ancestor: it must be a writable directory
    missing = [real.name]
    anc = real.parent
    while True:
        try:
            ast = os.stat(anc)
            break
        except FileNotFoundError:
            missing.append(anc.name)
            anc = anc.parent
        except OSError as exc:
            raise OutputError(f"{name}: cannot write here ({_oserror_text(exc)})") from None
    if not stat.S_ISDIR(ast.st_mode):
        raise OutputError(f"{name}: {anc} is not a directory")
    if not os.access(anc, os.W_OK | os.X_OK):
        raise OutputError(f"{name}: {anc} is not writable")
    try:
        name_max = os.pathconf(anc, "PC_NAME_MAX")
    except (OSError, ValueError):
        name_max = 255
    for part in missing:
        if len(os.fsencode(part)) > name_max:
            raise OutputError(f"{name}: a file name is longer than {name_max} bytes")
    return real


@dataclass
class _Stage:
    items: list[tuple[str, bytes]]


@contextlib.contextmanager
def stdout_target(stream: IO[Any] | None) -> Iterator[None]:
    """Make ``"-"`` write to ``stream`` (binary or text) within the block (CLI plumbing)."""
    tok = _STDOUT.set(stream)
    try:
        yield
    finally:
        _STDOUT.reset(tok)


def stream_problem(stream: IO[Any] | None) -> str | None:
    """Why ``stream`` (standard output) cannot take a result (None = closed), or None when it can."""
    if stream is None:
        return "standard output is closed"
    if getattr(stream, "closed", False):
        return "standard output is closed"
    try:
        fd = stream.fileno()
    except (OSError, ValueError, AttributeError):  # an in-memory stream (tests, redirection)
        return None
    try:
        os.fstat(fd)
    except OSError as exc:
        return f"standard output is not open ({_oserror_text(exc)})"
    try:
        import fcntl

        if fcntl.fcntl(fd, fcntl.F_GETFL) & os.O_ACCMODE == os.O_RDONLY:
            return "standard output is open for reading only"
    except (ImportError, OSError):  # no fcntl (Windows): the write itself will tell
        pass
    return None


def _refuse_input(raw: str, real: Path | None = None) -> None:
    """Refuse a write whose target is a file the running command reads."""
    label = input_named_by(real if real is not None else raw)
    if label is not None:
        raise OutputError(f"{raw}: is the input {label} (the same file); refusing to overwrite it, "
                          f"choose another output")


def _write_stdout(data: bytes) -> None:
    stream = _STDOUT.get() or sys.stdout
    why = stream_problem(stream)
    if why is not None:
        raise OutputError(f"-: cannot write the result: {why}")
    buf = getattr(stream, "buffer", None)
    try:
        if buf is not None:
            buf.write(data)
            buf.flush()
        else:
            stream.write(data.decode("utf-8", errors="replace"))
            stream.flush()
    except BrokenPipeError:
        pass
    except OSError as exc:
        raise OutputError(f"-: cannot write to standard output ({_oserror_text(exc)})") from None


def _commit(items: Sequence[tuple[str, bytes]]) -> None:
    """Write every (path, data) or none: all temporaries first, then the renames."""
    files: dict[Path, tuple[str, bytes]] = {}
    to_stdout: list[bytes] = []
    for raw, data in items:
        if _is_dash(raw):
            to_stdout.append(data)
        else:
            real = check_output_path(raw)
            _refuse_input(raw, real)
            files[real] = (raw, data)  # the last write of a path wins
    if to_stdout:
        why = stream_problem(_STDOUT.get() or sys.stdout)
        if why is not None:
            raise OutputError(f"-: cannot write the result: {why}; nothing was written")
    created: list[Path] = []
    temps: list[tuple[str, Path]] = []
    current = ""
    umask = os.umask(0)
    os.umask(umask)
    try:
        for real, (raw, data) in files.items():
            current = raw
            parents = []
            d = real.parent
            while not d.exists():
                parents.append(d)
                d = d.parent
            for d in reversed(parents):
                os.mkdir(d)
                created.append(d)
            fd, tmp = tempfile.mkstemp(prefix=_TMP_PREFIX, suffix=".tmp", dir=real.parent)
            temps.append((tmp, real))
            with os.fdopen(fd, "wb") as fh:
                fh.write(data)
                fh.flush()
                os.fsync(fh.fileno())
            try:
                mode = stat.S_IMODE(os.stat(real).st_mode)  # keep an existing file's permissions
            except FileNotFoundError:
                mode = 0o666 & ~umask  # what a plain open() would give
            os.chmod(tmp, mode)
        for tmp, real in temps:
            current = str(real)
            os.replace(tmp, real)
    except OSError as exc:
        _cleanup(temps, created)
        if exc.errno == errno.ENOSPC:
            why = "no space left on the device"
        else:
            why = _oserror_text(exc)
        raise OutputError(f"{current}: cannot write ({why}); nothing was written") from None
    except BaseException:
        _cleanup(temps, created)
        raise
    _WRITTEN.extend(raw for raw, _ in files.values())
    for data in to_stdout:
        _write_stdout(data)
    if to_stdout:
        _WRITTEN.append("-")


def _cleanup(temps: list[tuple[str, Path]], created: list[Path]) -> None:
    for tmp, _ in temps:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
    for d in reversed(created):
        with contextlib.suppress(OSError):
            os.rmdir(d)


def atomic_write_bytes(path: str | os.PathLike[str], data: bytes) -> None:
    """Write ``data`` to ``path`` atomically, never replacing anything but a regular file.

    Parameters
    ----------
    path:
        Target file; ``"-"`` = standard output. A symlink is written through to its target.
    data:
        The bytes.

    Raises
    ------
    OutputError
        The path is a directory / device / FIFO, or writing failed; no new file is left.

    Notes
    -----
    Inside :func:`staged_outputs` the write is buffered until the block ends.
    """
    stage = _STAGE.get()
    if stage is not None:
        real = check_output_path(path)  # fail early, before more work is done
        if not _is_dash(path):
            _refuse_input(os.fspath(path), real)
        stage.items.append((os.fspath(path), bytes(data)))
        return
    _commit([(os.fspath(path), bytes(data))])


@contextlib.contextmanager
def staged_outputs() -> Iterator[None]:
    """Buffer every :func:`atomic_write_bytes` in the block and commit them all at its end.

    When the block raises, nothing is written. Nested blocks join the outermost one.

    Examples
    --------
    >>> import tempfile, pathlib
    >>> d = pathlib.Path(tempfile.mkdtemp())
    >>> with staged_outputs():
    ...     write_json(d / "a.json", {"x": 1})
    ...     (d / "a.json").exists()
    False
    >>> (d / "a.json").exists()
    True
    """
    if _STAGE.get() is not None:
        yield
        return
    stage = _Stage(items=[])
    tok = _STAGE.set(stage)
    try:
        yield
    finally:
        _STAGE.reset(tok)
    _commit(stage.items)


#: Deepest nesting of containers :func:`write_json` writes (JSON readers, Python's among them,
#: stop near 1000 levels; a result is a few levels deep).
MAX_JSON_DEPTH = 500


def _unserialisable_nesting(obj: Any) -> str | None:
    """Why ``obj`` cannot be written as JSON by its shape (a container holding itself, or nesting
    deeper than :data:`MAX_JSON_DEPTH`), found iteratively (no recursion), else None."""
    stack: list[tuple[Any, int, frozenset[int]]] = [(obj, 0, frozenset())]
    while stack:
        o, depth, path = stack.pop()
        if isinstance(o, dict):
            kids: Any = o.values()
        elif isinstance(o, (list, tuple)):
            kids = o
        else:
            continue
        if id(o) in path:
            return "a container holds itself (a reference cycle)"
        if depth >= MAX_JSON_DEPTH:
            return f"nested deeper than {MAX_JSON_DEPTH} levels"
        inner = path | {id(o)}
        stack.extend((k, depth + 1, inner) for k in kids)
    return None


@entry(path="path", indent="count0")
def write_json(path: str | os.PathLike[str], obj: Any, *, indent: int = 2) -> None:
    """Serialise ``obj`` with :func:`selfcal._result.jsonable` (strict) and write it atomically as strict JSON.

    Raises
    ------
    SerializationError
        ``obj`` holds something without a JSON form (nothing is written).
    OutputError
        The path cannot be written (see :func:`atomic_write_bytes`).
    """
    try:
        text = json.dumps(jsonable(obj, strict=True), indent=indent, allow_nan=False)
    except (TypeError, ValueError) as exc:
        raise SerializationError(f"result has no strict-JSON form ({exc})") from None
    except RecursionError:  # only then is the shape walked (iteratively) to say why
        why = _unserialisable_nesting(obj) or "nested too deeply for JSON"
        raise SerializationError(f"obj has no JSON form: {why}") from None
    atomic_write_bytes(path, (text + "\n").encode())


def write_npz(path: str | os.PathLike[str], arrays: dict[str, NDArray[Any]]) -> None:
    """Write named arrays as one uncompressed ``.npz`` (``numpy.load`` reads it), atomically.

    The binary sidecar of a JSON result whose per-entry arrays are too large for JSON text
    (``calibrate toa --entries``): 8 bytes a float instead of ~20 characters, no conversion.
    """
    buf = _io.BytesIO()
    np.savez(buf, **{k: np.asarray(v) for k, v in arrays.items()})  # type: ignore[arg-type]
    atomic_write_bytes(path, buf.getvalue())


def write_matrix(path: str | os.PathLike[str], matrix: NDArray[Any]) -> None:
    """Write a 2-D matrix as CSV (``nan`` for missing) or ``.npy``, atomically."""
    p = Path(path)
    arr = np.asarray(np.ma.filled(np.ma.asarray(matrix, dtype=float), np.nan), dtype=float)
    if p.suffix.lower() == ".npy":
        buf = _io.BytesIO()
        np.save(buf, arr, allow_pickle=False)
        atomic_write_bytes(p, buf.getvalue())
    else:
        lines = [",".join("nan" if not np.isfinite(v) else repr(float(v)) for v in row) for row in np.atleast_2d(arr)]
        atomic_write_bytes(p, ("\n".join(lines) + "\n").encode())


def write_csv_rows(path: str | os.PathLike[str], header: Sequence[str], rows: Sequence[Sequence[Any]]) -> None:
    """Write a header and rows as comma-separated text (empty field = missing), atomically."""
    buf = _io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(list(header))
    for row in rows:
        out = []
        for v in row:
            if isinstance(v, (float, np.floating)):
                out.append(repr(float(v)) if math.isfinite(float(v)) else "")
            else:
                out.append("" if v is None else str(v))
        w.writerow(out)
    atomic_write_bytes(path, buf.getvalue().encode())
