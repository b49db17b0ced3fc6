"""Path helpers shared by the readers and the writers ('-' is a standard stream; error texts)."""

from __future__ import annotations

import contextlib
import contextvars
import os
import stat
from collections.abc import Iterator


def _is_dash(path: str | os.PathLike[str]) -> bool:
    return os.fspath(path) == "-"


def _kind_name(mode: int) -> str:
    if stat.S_ISDIR(mode):
        return "a directory"
    if stat.S_ISCHR(mode):
        return "a character device"
    if stat.S_ISBLK(mode):
        return "a block device"
    if stat.S_ISFIFO(mode):
        return "a FIFO"
    if stat.S_ISSOCK(mode):
        return "a socket"
    return "not a regular file"


def _oserror_text(exc: OSError) -> str:
    return exc.strerror or type(exc).__name__


# --------------------------------------------------------------------------------------
# the run's inputs: no output may be one of them (same file = same device and inode)
# --------------------------------------------------------------------------------------

#: Files a run reads, by (device, inode) -> the label that names the input (active inside
#: :func:`run_inputs`; outside a run, e.g. from the Python API, nothing is registered).
_INPUTS: contextvars.ContextVar[dict[tuple[int, int], str] | None] = contextvars.ContextVar(
    "selfcal_inputs", default=None)

#: Entries of an input folder registered one by one (a recording folder holds tens of files);
#: past this count the folder itself still counts, the files beyond it are not listed.
MAX_FOLDER_ENTRIES = 100_000


def file_identity(path: str | os.PathLike[str]) -> tuple[int, int] | None:
    """(device, inode) of what ``path`` names, symlinks followed; None if it does not exist."""
    try:
        st = os.stat(path)
    except (OSError, ValueError):
        return None
    return (st.st_dev, st.st_ino)


def input_identities(path: str | os.PathLike[str], label: str) -> dict[tuple[int, int], str]:
    """Identities of an input path: the file, or a folder and every entry under it.

    A folder is walked (links followed to their targets, never into linked folders), so
    that an output naming any file the run may read from it is found.
    """
    out: dict[tuple[int, int], str] = {}
    raw = os.fspath(path)
    if _is_dash(raw):
        return out
    ident = file_identity(raw)
    if ident is None:
        return out
    out[ident] = label
    if not os.path.isdir(raw):
        return out
    count = 0
    for root, dirs, files in os.walk(raw):
        for n in files + dirs:
            count += 1
            if count > MAX_FOLDER_ENTRIES:
                return out
            p = os.path.join(root, n)
            sub = file_identity(p)
            if sub is not None:
                out.setdefault(sub, f"{label} ({p})")
    return out


@contextlib.contextmanager
def run_inputs(identities: dict[tuple[int, int], str]) -> Iterator[dict[tuple[int, int], str]]:
    """Within the block every file read through :mod:`selfcal.io` joins ``identities``, and
    every write refuses a target among them (:func:`selfcal.io.outputs.atomic_write_bytes`)."""
    tok = _INPUTS.set(identities)
    try:
        yield identities
    finally:
        _INPUTS.reset(tok)


def note_input(path: str | os.PathLike[str], label: str | None = None) -> None:
    """Register a file the running command reads (no-op outside :func:`run_inputs`)."""
    reg = _INPUTS.get()
    if reg is None or _is_dash(path):
        return
    ident = file_identity(path)
    if ident is not None:
        reg.setdefault(ident, label or os.fspath(path))


def input_named_by(path: str | os.PathLike[str]) -> str | None:
    """The label of the run's input that ``path`` resolves to, or None."""
    reg = _INPUTS.get()
    if not reg or _is_dash(path):
        return None
    ident = file_identity(path)
    return None if ident is None else reg.get(ident)
