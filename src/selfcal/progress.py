"""Progress on a terminal for the stages of a long computation (tqdm on stderr).

A stage's bar appears only once the stage has run :data:`DELAY` seconds, only when
stderr is a terminal, and never after the CLI's ``-q`` (:func:`set_quiet`); otherwise
every call here is a no-op, so library code reports progress unconditionally. A bar shows
the stage's name, done / total and the elapsed time.

Code that runs a stage wraps it in :func:`stage`; code deeper down that knows how far it
is (a search counting its refinements) calls :func:`report`, which updates the innermost
open stage, whoever opened it.
"""

from __future__ import annotations

import sys
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any

__all__ = ["DELAY", "enabled", "report", "set_quiet", "stage"]

#: seconds a stage runs before its bar is drawn (issue 29: any stage over ~2 s shows progress)
DELAY = 2.0

_STATE: dict[str, Any] = {"quiet": False}
_STACK: list[Callable[..., None]] = []


def set_quiet(quiet: bool) -> None:
    """Silence (True) or allow (False) every progress bar of this process (the CLI's ``-q``)."""
    _STATE["quiet"] = bool(quiet)


def enabled() -> bool:
    """Whether a bar may be drawn now: stderr is a terminal and not quiet."""
    isatty = getattr(sys.stderr, "isatty", None)
    try:
        tty = bool(isatty and isatty())
    except ValueError:  # a closed stream
        tty = False
    return not _STATE["quiet"] and tty


def report(done: int, total: int | None = None) -> None:
    """Tell the innermost open :func:`stage` how far it is (absolute counts); no-op without one."""
    if _STACK:
        _STACK[-1](done, total)


@contextmanager
def stage(name: str, total: int = 0, unit: str = "step") -> Iterator[Callable[..., None]]:
    """A progress bar for one stage; yields ``update(done, total=None)`` (absolute counts).

    Examples
    --------
    >>> with stage("refits", 3) as update:
    ...     for k in range(3):
    ...         update(k + 1)
    """
    bar: Any = None
    if enabled():
        from tqdm.auto import tqdm

        bar = tqdm(total=int(total) or None, desc=name, unit=unit, leave=False, file=sys.stderr,
                   dynamic_ncols=True, delay=DELAY, bar_format="{desc}: {n_fmt}/{total_fmt} {unit} [{elapsed}]")

    def update(done: int, new_total: int | None = None) -> None:
        if bar is None:
            return
        if new_total is not None and new_total != bar.total:
            bar.total = int(new_total)
        bar.update(max(int(done) - bar.n, 0))

    _STACK.append(update)
    try:
        yield update
    finally:
        _STACK.pop()
        if bar is not None:
            bar.close()
