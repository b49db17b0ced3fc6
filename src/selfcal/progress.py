"""Progress on a terminal for the stages of a long computation (tqdm on stderr).

A stage is shown only when stderr is a terminal and the CLI was not given ``-q``
(:func:`set_quiet`); otherwise every call here is a no-op, so library code can report
progress unconditionally. A bar shows the stage's name, done / total and the elapsed time.
"""

from __future__ import annotations

import sys
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any

__all__ = ["enabled", "set_quiet", "stage"]

_STATE = {"quiet": False}


def set_quiet(quiet: bool) -> None:
    """Silence (True) or allow (False) every progress bar of this process (the CLI's ``-q``)."""
    _STATE["quiet"] = bool(quiet)


def enabled() -> bool:
    """Whether a bar would be drawn now: stderr is a terminal and not quiet."""
    isatty = getattr(sys.stderr, "isatty", None)
    return not _STATE["quiet"] and bool(isatty and isatty())


@contextmanager
def stage(name: str, total: int, unit: str = "step") -> Iterator[Callable[..., Any]]:
    """A progress bar for one stage; yields ``update(done, total=None)`` (absolute counts).

    Examples
    --------
    >>> with stage("refits", 3) as update:
    ...     for k in range(3):
    ...         update(k + 1)
    """
    if not enabled():
        yield lambda done, total=None: None
        return
    from tqdm.auto import tqdm

    bar = tqdm(total=int(total), desc=name, unit=unit, leave=False, file=sys.stderr, dynamic_ncols=True,
               bar_format="{desc}: {n_fmt}/{total_fmt} {unit} [{elapsed}]")

    def update(done: int, new_total: int | None = None) -> None:
        if new_total is not None and new_total != bar.total:
            bar.total = int(new_total)
        bar.update(int(done) - bar.n)

    try:
        yield update
    finally:
        bar.close()
