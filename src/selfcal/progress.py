"""Progress of long stages on a terminal: one shared helper for every command.

A stage longer than about two seconds (detection, calibration, a constrained refit, a Monte-Carlo
sweep) shows one line on standard error: the stage name, ``done/total`` when the count is known
and the elapsed time, refreshed once a second even while the stage sits in one long step.
Nothing is drawn when standard error is not a terminal (logs, pipes, CliRunner) or under
``selfcal -q`` (:func:`set_quiet`), so scripted output is unchanged.

Examples
--------
>>> from selfcal.progress import stage
>>> with stage("detect", total=3, unit="rx") as bar:   # silent here: not a terminal
...     for _ in range(3):
...         bar.update()
>>> [x for x in stage.iterate(range(3), "sweep")]
[0, 1, 2]
"""

from __future__ import annotations

import sys
import threading
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from typing import Any, TypeVar

__all__ = ["stage", "set_quiet", "enabled", "note", "report", "Stage"]

T = TypeVar("T")

#: Set by ``selfcal -q`` (and by library users who want silence).
_QUIET = {"quiet": False}
#: The stages running now, innermost last (:func:`note` writes on the innermost).
_ACTIVE: list[Stage] = []
#: Seconds between redraws of a stage whose count does not move (elapsed time keeps ticking).
REFRESH_S = 1.0


def set_quiet(quiet: bool) -> None:
    """Silence (``True``) or allow (``False``) every progress line of this process.

    Parameters
    ----------
    quiet : bool
        ``selfcal -q`` sets it.
    """
    _QUIET["quiet"] = bool(quiet)


def note(text: str) -> None:
    """Show ``text`` on the innermost running stage's line (nothing when none is drawn).

    For code deep inside a stage (a solver's rounds) that does not hold the bar.

    Parameters
    ----------
    text : str
        A few words, e.g. ``"outlier round 2"``.
    """
    if _ACTIVE:
        _ACTIVE[-1].note(text)


def report(done: int, total: int | None = None) -> None:
    """Tell the innermost running stage how far it is, in absolute counts (nothing when none).

    For code deep inside a stage that counts its own work (the search's refinements, the
    held-out folds) without holding the bar.

    Parameters
    ----------
    done : int
        Items done so far.
    total : int, optional
        The stage's number of items, when it is known only now.
    """
    if _ACTIVE:
        _ACTIVE[-1](done, total)


def enabled(stream: Any = None) -> bool:
    """Whether a progress line would be drawn: not quiet and ``stream`` (stderr) a terminal.

    Parameters
    ----------
    stream : file-like, optional
        Default ``sys.stderr``.

    Returns
    -------
    bool
    """
    s = sys.stderr if stream is None else stream
    try:
        return not _QUIET["quiet"] and bool(s.isatty())
    except (AttributeError, ValueError):
        return False


class Stage:
    """One stage's line (a ``tqdm`` bar on stderr, or nothing when not :func:`enabled`).

    Use :func:`stage`. ``update(n)`` adds ``n`` done; ``set_total(n)`` sets the count once it
    is known; ``note(text)`` shows a short postfix (e.g. the current round).
    """

    def __init__(self, name: str, total: int | None = None, unit: str = "", show: bool | None = None) -> None:
        self.name = name
        self._bar: Any = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        if show is None:
            show = enabled()
        if not show:
            return
        from tqdm import tqdm

        fmt = ("{desc}: {n_fmt}/{total_fmt} {unit} [{elapsed}]{postfix}" if total is not None
               else "{desc}: {n_fmt} {unit} [{elapsed}]{postfix}")
        self._bar = tqdm(total=total, desc=name, unit=unit or "", file=sys.stderr, leave=False,
                         bar_format=fmt, dynamic_ncols=True, mininterval=0.2)
        self._thread = threading.Thread(target=self._tick, daemon=True)
        self._thread.start()

    def _tick(self) -> None:
        while not self._stop.wait(REFRESH_S):
            bar = self._bar
            if bar is not None:
                bar.refresh()

    def update(self, n: int = 1) -> None:
        """Count ``n`` more items done."""
        if self._bar is not None:
            self._bar.update(n)

    def set_total(self, total: int) -> None:
        """Set (or change) the number of items of this stage."""
        if self._bar is not None:
            self._bar.total = total
            self._bar.bar_format = "{desc}: {n_fmt}/{total_fmt} {unit} [{elapsed}]{postfix}"
            self._bar.refresh()

    def __call__(self, done: int, total: int | None = None) -> None:
        """Set the count to ``done`` (absolute), and the number of items to ``total`` if given."""
        if self._bar is None:
            return
        if total is not None and total != self._bar.total:
            self.set_total(int(total))
        self._bar.update(max(int(done) - self._bar.n, 0))

    def note(self, text: str) -> None:
        """Show ``text`` after the count (e.g. ``round 2``)."""
        if self._bar is not None:
            self._bar.set_postfix_str(text, refresh=True)

    def close(self) -> None:
        """Stop the refresh and erase the line."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2 * REFRESH_S)
        if self._bar is not None:
            self._bar.close()
            self._bar = None


class _StageFactory:
    """:func:`stage` is a context manager; ``stage.iterate`` wraps an iterable."""

    @contextmanager
    def __call__(self, name: str, total: int | None = None, *, unit: str = "",
                 show: bool | None = None) -> Iterator[Stage]:
        bar = Stage(name, total, unit, show)
        _ACTIVE.append(bar)
        try:
            yield bar
        finally:
            _ACTIVE.remove(bar)
            bar.close()

    def iterate(self, items: Iterable[T], name: str, total: int | None = None, *, unit: str = "",
                show: bool | None = None) -> Iterator[T]:
        if total is None:
            try:
                total = len(items)  # type: ignore[arg-type]
            except TypeError:
                total = None
        with self(name, total, unit=unit, show=show) as bar:
            for item in items:
                yield item
                bar.update()


#: ``with stage("calibrate", total=None) as bar: ...`` -- see the module docstring.
stage = _StageFactory()
