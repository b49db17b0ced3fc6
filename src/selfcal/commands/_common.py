"""Shared command-line plumbing: the top-level error contract, output checks, unit options.

Contract (DESIGN.md, "Inputs and outputs"): exit 0 = trustworthy result, 1 = the result
failed its own test (a ``FAIL:`` line), 2 = bad input or an unwritable output, with exactly
one line on stderr and no traceback (``--verbose`` adds the traceback of an internal error).
Outputs are checked before any work is done and written all together at the end
(:func:`selfcal.io.staged_outputs`).
"""

from __future__ import annotations

import contextlib
import io
import os
import sys
import traceback
import warnings
from collections.abc import Callable, Iterator, Mapping
from pathlib import Path
from typing import Any

import click

from ..errors import SelfcalError

__all__ = [
    "SelfcalGroup",
    "OUTPUT_PARAMS",
    "IMAGE_FORMATS",
    "check_command_outputs",
    "command_context",
    "error_line",
    "UNITS",
    "unit_options",
    "to_metres",
]

#: Parameter names that are outputs of a command (checked before the command runs).
OUTPUT_PARAMS = ("out", "out_dir", "plot", "report", "csv", "csv_out")

#: Figure formats matplotlib writes (``--plot FILE.pdf`` writes a PDF); no suffix = PNG.
IMAGE_FORMATS = ("png", "pdf", "svg", "svgz", "eps", "ps", "jpg", "jpeg", "tif", "tiff", "webp")

_STATE: dict[str, bool] = {"quiet": False, "verbose": False}


def error_line(message: object) -> str:
    """One stderr line for ``message`` (whitespace collapsed, capped at 400 characters)."""
    text = " ".join(str(message).split())
    if len(text) > 400:
        text = text[:397] + "..."
    return f"selfcal: error: {text}"


def _emit_error(message: object) -> None:
    click.echo(error_line(message), err=True)


class SelfcalGroup(click.Group):
    """The ``selfcal`` group with a last-resort handler around every command.

    * click usage errors -> one line + exit 2 (instead of click's multi-line usage block);
    * :class:`~selfcal.errors.SelfcalError` / ``OSError`` -> one line + exit 2;
    * any other exception -> one line ``internal error: ...`` + exit 2 (traceback only with
      ``--verbose``);
    * warnings (numpy, tqdm, convergence) are collected: on exit 0 / 1 selfcal's own warnings
      are printed as ``selfcal: warning:`` lines, numpy's only with ``--verbose``; on exit 2
      none, so that the error is the only line.
    """

    def main(self, args: Any = None, prog_name: str | None = None, complete_var: str | None = None,
             standalone_mode: bool = True, **extra: Any) -> Any:
        argv = [os.fspath(a) for a in (sys.argv[1:] if args is None else args)]
        # -q/--quiet and -v/--verbose are accepted anywhere on the line (no command uses them)
        if "--" in argv:
            k = argv.index("--")
            flags, rest = argv[:k], argv[k:]
        else:
            flags, rest = argv, []
        quiet = any(a in ("-q", "--quiet") for a in flags)
        verbose = any(a in ("-v", "--verbose") for a in flags)
        argv = [a for a in flags if a not in ("-q", "--quiet", "-v", "--verbose")] + rest
        if prog_name is None:
            prog_name = "selfcal"
        _add_short_out(self)
        _STATE.update(quiet=quiet, verbose=verbose)
        code: int = 0
        real_stdout = sys.stdout
        captured = io.StringIO()
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            try:
                with contextlib.ExitStack() as stack:
                    if quiet:
                        from ..io import stdout_target

                        stack.enter_context(stdout_target(real_stdout))
                        stack.enter_context(contextlib.redirect_stdout(captured))
                    rv = super().main(argv, prog_name, complete_var, standalone_mode=False, **extra)
                code = rv if isinstance(rv, int) and not isinstance(rv, bool) else 0
            except SystemExit as exc:
                c = exc.code
                code = c if isinstance(c, int) else (0 if c is None else 2)
                if not isinstance(c, int) and c is not None:
                    _emit_error(c)
            except click.exceptions.Exit as exc:
                code = exc.exit_code
            except click.exceptions.NoArgsIsHelpError as exc:  # pragma: no cover - click >= 8.2
                click.echo(exc.ctx.get_help() if exc.ctx else str(exc))
                code = 2
            except click.ClickException as exc:
                ctx = getattr(exc, "ctx", None)
                where = f"{ctx.command_path}: " if ctx is not None else ""
                hint = f" (see '{ctx.command_path} --help')" if ctx is not None else ""
                _emit_error(f"{where}{exc.format_message()}{hint}")
                code = 2
            except click.Abort:
                _emit_error("aborted")
                code = 130
            except (KeyboardInterrupt, EOFError):
                _emit_error("interrupted")
                code = 130
            except SelfcalError as exc:
                _emit_error(exc)
                code = 2
            except MemoryError:
                _emit_error("out of memory: the input or the requested sizes are too large for this machine")
                code = 2
            except OSError as exc:
                name = f"{exc.filename}: " if getattr(exc, "filename", None) else ""
                _emit_error(f"{name}{exc.strerror or exc}")
                code = 2
            except Exception as exc:  # the last resort: never a traceback by default
                if verbose:
                    traceback.print_exc()
                _emit_error(f"internal error: {type(exc).__name__}: {exc}")
                code = 2
        if quiet:
            fails = [ln for ln in captured.getvalue().splitlines() if ln.startswith("FAIL")]
            for ln in fails:
                real_stdout.write(ln + "\n")
        if code in (0, 1):
            _report_warnings(caught, verbose=verbose, quiet=quiet)
        if standalone_mode:
            sys.exit(code)
        return code


def _add_short_out(group: click.Group) -> None:
    """Give every command's ``--out`` the short form ``-o`` (where ``-o`` is free)."""
    for cmd in group.commands.values():
        if isinstance(cmd, click.Group):
            _add_short_out(cmd)
            continue
        taken = {o for p in cmd.params for o in (*p.opts, *p.secondary_opts)}
        if "-o" in taken:
            continue
        for p in cmd.params:
            if isinstance(p, click.Option) and p.opts and "--out" in p.opts:
                p.opts.insert(0, "-o")
                break


def _report_warnings(caught: list[warnings.WarningMessage], *, verbose: bool, quiet: bool) -> None:
    if quiet and not verbose:
        return
    seen: set[str] = set()
    for w in caught:
        mod = getattr(w, "filename", "") or ""
        ours = issubclass(w.category, UserWarning) and f"{os.sep}selfcal{os.sep}" in mod
        if not (ours or verbose):
            continue
        text = " ".join(str(w.message).split())
        if text in seen:
            continue
        seen.add(text)
        click.echo(f"selfcal: warning: {text}", err=True)


def _param_kind(param: click.Parameter) -> str:
    t = param.type
    if isinstance(t, click.Path) and not t.file_okay:
        return "dir"
    return "file"


def check_command_outputs(ctx: click.Context | None, kwargs: Mapping[str, Any]) -> list[Any]:
    """Check every output parameter of the running command before it does any work.

    Returns the output values that are ``"-"`` (standard output).

    Raises
    ------
    selfcal.io.OutputError
        An output is a directory, device, FIFO, socket, read-only, or under a file.
    """
    from ..errors import InputError
    from ..io import check_output_path

    dashes = []
    if ctx is None:
        return dashes
    seen: dict[str, str] = {}
    for param in ctx.command.params:
        if param.name not in OUTPUT_PARAMS:
            continue
        value = kwargs.get(param.name)
        if value is None:
            continue
        kind = _param_kind(param)
        opt = param.opts[0] if param.opts else param.name
        if os.fspath(value) == "-":
            dashes.append(value)
        real = check_output_path(value, kind=kind, label=f"{opt} {os.fspath(value)}")
        if param.name == "plot" and kind == "file" and os.fspath(value) != "-":
            suffix = Path(os.fspath(value)).suffix.lower().lstrip(".")
            if suffix and suffix not in IMAGE_FORMATS:
                raise InputError(f"{opt} {os.fspath(value)}: unknown figure format '.{suffix}' "
                                 f"(use one of {', '.join(IMAGE_FORMATS[:4])}, ...)")
        key = os.fspath(real)
        if key != "-" and key in seen:
            raise InputError(f"{opt} and {seen[key]} name the same file {os.fspath(value)}")
        seen[key] = opt
    if len(dashes) > 1:
        raise InputError("only one output can be '-' (standard output)")
    return dashes


@contextlib.contextmanager
def command_context(kwargs: Mapping[str, Any]) -> Iterator[None]:
    """Check outputs, and with ``--out -`` send the human summary to stderr (stdout = JSON)."""
    from ..io import stdout_target

    ctx = click.get_current_context(silent=True)
    dashes = check_command_outputs(ctx, kwargs)
    with contextlib.ExitStack() as stack:
        if dashes and not _STATE["quiet"]:  # (with --quiet the group already routes '-' to stdout)
            stack.enter_context(stdout_target(sys.stdout))
            stack.enter_context(contextlib.redirect_stdout(sys.stderr))
        yield


# --------------------------------------------------------------------------------------
# units
# --------------------------------------------------------------------------------------

#: Units accepted by ``--unit``: lengths (metres) and times (seconds), or samples.
UNITS = {"m": ("length", 1.0), "mm": ("length", 1e-3), "cm": ("length", 1e-2), "km": ("length", 1e3),
         "s": ("time", 1.0), "ms": ("time", 1e-3), "us": ("time", 1e-6), "samples": ("time", None)}


def unit_options(func: Callable[..., Any]) -> Callable[..., Any]:
    """``--unit`` and ``--sample-rate`` options of a matrix input (see :func:`to_metres`)."""
    func = click.option(
        "--sample-rate", "sample_rate", type=float, default=None, metavar="HZ",
        help="Sampling rate in Hz, for --unit samples.")(func)
    func = click.option(
        "--unit", "unit", type=click.Choice(list(UNITS)), default=None,
        help="Unit of the matrix entries: m, mm, cm, km (lengths) or s, ms, us, samples (times; need "
             "--speed). Default: metres, or seconds when --speed is given.")(func)
    return func


def to_metres(matrix: Any, unit: str | None, speed: float | None, sample_rate: float | None,
              name: str = "matrix") -> tuple[Any, float | None, str]:
    """Scale a matrix given in ``unit`` to metres (lengths) or seconds (times).

    Returns
    -------
    (matrix, speed, unit)
        The scaled matrix, the speed to pass to the solver (None for lengths), and the unit
        the matrix is now in (``"m"`` or ``"s"``).

    Raises
    ------
    InputError
        A time unit without ``--speed``, a length unit with ``--speed``, ``samples`` without
        a valid ``--sample-rate``, or a non-positive / non-finite speed.
    """
    import math

    from ..errors import InputError

    if speed is not None and not (math.isfinite(speed) and speed > 0):
        raise InputError(f"--speed must be a finite positive number in m/s, got {speed:g}")
    if sample_rate is not None and not (math.isfinite(sample_rate) and sample_rate > 0):
        raise InputError(f"--sample-rate must be a finite positive number in Hz, got {sample_rate:g}")
    if unit is None:
        if sample_rate is not None:
            raise InputError("--sample-rate is only used with --unit samples")
        return matrix, speed, ("s" if speed is not None else "m")
    kind, factor = UNITS[unit]
    if kind == "length":
        if speed is not None:
            raise InputError(f"--unit {unit} is a length; --speed is for a matrix of times (s, ms, us, samples)")
        if sample_rate is not None:
            raise InputError("--sample-rate is only used with --unit samples")
        return matrix * factor, None, "m"
    if speed is None:
        raise InputError(f"--unit {unit} is a time; give the propagation --speed in m/s (343 for sound in air)")
    if unit == "samples":
        if sample_rate is None:
            raise InputError("--unit samples needs --sample-rate HZ")
        factor = 1.0 / sample_rate
    elif sample_rate is not None:
        raise InputError("--sample-rate is only used with --unit samples")
    return matrix * factor, speed, "s"


def all_or_nothing(func: Callable[..., Any]) -> Callable[..., Any]:
    """Decorator: every file the command writes is staged and committed together at its end.

    Put it under ``@handle_errors``. Only for commands that do not read back what they write.
    """
    import functools

    @functools.wraps(func)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        from ..io import staged_outputs

        with staged_outputs():
            return func(*args, **kwargs)

    return wrapper
