"""Path helpers shared by the readers and the writers ('-' is a standard stream; error texts)."""

from __future__ import annotations

import os
import stat


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
