"""Shared command-line plumbing: the top-level error contract, output checks, unit options.

Contract (DESIGN.md, "Inputs and outputs"): exit 0 = trustworthy result, 1 = the result
failed its own test (a ``FAIL:`` line), 2 = bad input or an unwritable output, with exactly
one line on stderr and no traceback (``--verbose`` adds the traceback of an internal error).
Outputs are checked before any work is done and written all together at the end
(:func:`selfcal.io.staged_outputs`).

Why this file is long (~690 lines): it is every command's shared plumbing (the error
contract, output checks, unit and clock options, payload enrichment, node CSVs), each piece
used by several command modules; the command modules themselves stay thin.
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
from ._options import JITTER_S, JITTER_US, SAMPLE_RATE_HZ

__all__ = [
    "SelfcalGroup",
    "OUTPUT_PARAMS",
    "IMAGE_FORMATS",
    "check_command_outputs",
    "command_inputs",
    "is_input_param",
    "command_context",
    "error_line",
    "UNITS",
    "unit_options",
    "to_metres",
]

#: Parameter names that are outputs of a command (checked before the command runs).
OUTPUT_PARAMS = ("out", "out_dir", "plot", "report", "csv", "csv_out", "csv_path", "tum_path", "anchors_out",
                 "anchor_plot")

#: Figure formats matplotlib writes (``--plot FILE.pdf`` writes a PDF); no suffix = PNG.
IMAGE_FORMATS = ("png", "pdf", "svg", "svgz", "eps", "ps", "jpg", "jpeg", "tif", "tiff", "webp")

_STATE: dict[str, bool] = {"quiet": False, "verbose": False}
#: The process's standard output as the group found it (None when it was closed at start-up),
#: before ``--quiet`` or ``--out -`` redirect ``sys.stdout``.
_REAL_STDOUT: dict[str, Any] = {}


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
        if prog_name is None or prog_name == self.name:  # click's test runner passes the function's name
            prog_name = "selfcal"
        _add_short_out(self)
        _STATE.update(quiet=quiet, verbose=verbose)
        from ..progress import set_quiet

        set_quiet(quiet)  # progress lines (selfcal.progress) only on a terminal, never under -q
        from ..io.outputs import written_files

        written_files(reset=True)
        code: int = 0
        real_stdout = sys.stdout
        _REAL_STDOUT["stream"] = real_stdout
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
        if code in (0, 1) and not quiet:
            _report_written(written_files(reset=True))
        if code in (0, 1):
            _report_warnings(caught, verbose=verbose, quiet=quiet)
        if standalone_mode:
            sys.exit(code)
        return code


def wrote_line(paths: list[str], *, max_per_folder: int = 4) -> str:
    """``wrote a.json, a.csv, map.png`` naming every file written; a folder holding more than
    ``max_per_folder`` of them is named once with its count (``rec/ (22 files)``).

    Examples
    --------
    >>> wrote_line(["out/r.json", "out/r.csv", "-"])
    'wrote out/r.json, out/r.csv, standard output'
    >>> wrote_line([f"rec/rx_{i}.wav" for i in range(9)] + ["r.json"])
    'wrote rec/ (9 files), r.json'
    """
    seen: list[str] = []
    for p in paths:
        if p not in seen:
            seen.append(p)
    per: dict[str, int] = {}
    for p in seen:
        if p != "-":
            per[os.path.dirname(p)] = per.get(os.path.dirname(p), 0) + 1
    out: list[str] = []
    for p in seen:
        if p == "-":
            out.append("standard output")
            continue
        d = os.path.dirname(p)
        if per[d] > max_per_folder:
            item = f"{d}{os.sep} ({per[d]} files)"
            if item not in out:
                out.append(item)
        else:
            out.append(p)
    return "wrote " + ", ".join(out)


def _report_written(paths: list[str]) -> None:
    """The console's last line: every file the command wrote (stderr when stdout held one)."""
    if paths:
        click.echo(wrote_line(paths), err="-" in paths)


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


def _opt_name(param: click.Parameter) -> str:
    """``--out`` for an option (its long form), ``MATRIX`` for an argument."""
    if isinstance(param, click.Option) and param.opts:
        return next((o for o in param.opts if o.startswith("--")), param.opts[0])
    return (param.name or "ARG").upper()


def _param_label(param: click.Parameter, value: Any) -> str:
    return f"{_opt_name(param)} {os.fspath(value)}"


def is_input_param(param: click.Parameter) -> bool:
    """Whether ``param`` names something the command reads.

    Every :class:`click.Path` parameter that is not an output (:data:`OUTPUT_PARAMS`) is an
    input, and so is a text option whose metavar says ``FILE`` (``--directions FILE|sources``):
    a new command's path parameters are inputs unless they are named as outputs, so none
    can be forgotten.
    """
    if param.name in OUTPUT_PARAMS:
        return False
    if isinstance(param.type, click.Path):
        return True
    metavar = getattr(param, "metavar", None) or ""
    return isinstance(param.type, click.types.StringParamType) and "FILE" in metavar.upper()


def _values(value: Any) -> list[Any]:
    if value is None:
        return []
    if isinstance(value, (tuple, list)):
        return [v for v in value if v is not None]
    return [value]


def _stream_identity(stream: Any) -> tuple[int, int] | None:
    """(device, inode) of the regular file behind a standard stream, or None (a terminal, a pipe)."""
    import stat as _stat

    try:
        st = os.fstat(stream.fileno())
    except (OSError, ValueError, AttributeError):
        return None
    return (st.st_dev, st.st_ino) if _stat.S_ISREG(st.st_mode) else None


def command_inputs(ctx: click.Context | None, kwargs: Mapping[str, Any]) -> dict[tuple[int, int], str]:
    """(device, inode) -> label of every file and folder the command reads (folders walked).

    Inputs are the command's parameters selected by :func:`is_input_param`; a folder counts
    with every entry under it (a recording folder: setup.json, the WAV files, ...).
    """
    from ..io._paths import input_identities

    found: dict[tuple[int, int], str] = {}
    if ctx is None:
        return found
    for param in ctx.command.params:
        if not is_input_param(param):
            continue
        for v in _values(kwargs.get(param.name or "")):
            if isinstance(v, (str, os.PathLike)) and os.fspath(v) == "-":  # the file behind a `< file`
                ident = _stream_identity(sys.stdin)
                if ident is not None:
                    found.setdefault(ident, f"{_opt_name(param)} - (standard input)")
                continue
            if not isinstance(v, (str, os.PathLike)) or os.fspath(v) == "":
                continue
            for ident, label in input_identities(v, _param_label(param, v)).items():
                found.setdefault(ident, label)
    return found


def check_command_outputs(ctx: click.Context | None, kwargs: Mapping[str, Any],
                          inputs: Mapping[tuple[int, int], str] | None = None) -> list[Any]:
    """Check every output parameter of the running command before it does any work.

    Returns the output values that are ``"-"`` (standard output).

    Raises
    ------
    selfcal.io.OutputError
        An output is a directory, device, FIFO, socket, read-only, or under a file; it is one
        of the run's inputs (``inputs``: the same device and inode, symlinks followed, so a
        link or a hard link to the input is found too); two outputs name one file; ``-``
        (standard output) is closed.
    """
    from ..errors import InputError
    from ..io import OutputError, check_output_path
    from ..io._paths import file_identity
    from ..io.outputs import stream_problem

    dashes: list[Any] = []
    if ctx is None:
        return dashes
    inputs = {} if inputs is None else inputs
    seen: dict[str, str] = {}
    dash_opt = "--out"
    for param in ctx.command.params:
        if param.name not in OUTPUT_PARAMS:
            continue
        value = kwargs.get(param.name)
        if value is None:
            continue
        kind = _param_kind(param)
        if param.name == "report" and os.fspath(value) != "-" and not os.fspath(value).lower().endswith(".html"):
            kind = "dir"  # pipeline --report: a path not ending in .html is a folder of report files
        opt = _opt_name(param)
        if os.fspath(value) == "-":
            dashes.append(value)
            dash_opt = opt
        if os.fspath(value) not in ("-", ""):  # first: the clash is the message, whatever else is wrong
            ident = file_identity(value)
            if ident is not None and ident in inputs:
                raise OutputError(f"{_param_label(param, value)} is the input {inputs[ident]} (the same file); "
                                  f"an output never replaces an input, choose another {opt}")
        real = check_output_path(value, kind=kind, label=f"{opt} {os.fspath(value)}")
        parent = Path(os.fspath(value)).parent
        missing = parent if kind != "file" else parent.parent  # a folder output is itself the new folder
        if os.fspath(value) != "-" and not parent.exists() and not missing.exists():
            # a chain of missing folders is a typo far more often than a wish for new folders:
            # one new output folder is made (``-o out/r.json`` next to the data), never a chain
            raise InputError(f"{opt} {os.fspath(value)}: the folder {missing} does not exist (create it first)")
        if param.name == "plot" and kind == "file" and os.fspath(value) != "-":
            suffix = Path(os.fspath(value)).suffix.lower().lstrip(".")
            if suffix and suffix not in IMAGE_FORMATS:
                raise InputError(f"{opt} {os.fspath(value)}: unknown figure format '.{suffix}' "
                                 f"(use one of {', '.join(IMAGE_FORMATS[:4])}, ...)")
        ident_out = file_identity(real) if os.fspath(real) != "-" else None
        key = os.fspath(real) if ident_out is None else f"{ident_out[0]}:{ident_out[1]}"  # hard links too
        if key != "-" and key in seen:
            raise InputError(f"{opt} and {seen[key]} name the same file {os.fspath(value)}")
        seen[key] = opt
    if len(dashes) > 1:
        raise InputError("only one output can be '-' (standard output)")
    if dashes:
        real_stdout = _REAL_STDOUT.get("stream", sys.stdout)
        why = stream_problem(real_stdout)
        if why is not None:
            raise OutputError(f"{dash_opt} -: {why}; give a file name")
        ident = _stream_identity(real_stdout)  # `--out - >> input.csv`
        if ident is not None and ident in inputs:
            raise OutputError(f"{dash_opt} -: standard output is the input {inputs[ident]} (the same file); "
                              f"an output never replaces an input")
    return dashes


@contextlib.contextmanager
def command_context(kwargs: Mapping[str, Any]) -> Iterator[None]:
    """Check outputs against the run's inputs; with ``--out -`` send the summary to stderr.

    Inside the block every file the command reads through :mod:`selfcal.io` joins the inputs
    and every write refuses a target among them (:func:`selfcal.io._paths.run_inputs`): a
    folder output whose files are only named while the command runs is checked there.
    """
    from ..io import stdout_target
    from ..io._paths import run_inputs

    ctx = click.get_current_context(silent=True)
    inputs = command_inputs(ctx, kwargs)
    dashes = check_command_outputs(ctx, kwargs, inputs)
    with contextlib.ExitStack() as stack:
        stack.enter_context(run_inputs(inputs))
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
        "--sample-rate", "sample_rate", type=SAMPLE_RATE_HZ, default=None, metavar="HZ",
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
    # no timing hardware samples faster than ~1e11 Hz (UWB timestamps: 15.65 ps ticks, 64 GHz);
    # 1e13 Hz (100 fs) leaves two decades and catches a rate in the wrong unit (a network of 1e-17 m)
    if sample_rate is not None and sample_rate > 1e13:
        raise InputError(f"--sample-rate {sample_rate:g} Hz is beyond any timing hardware (1e13 Hz); give it in Hz")
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


# --------------------------------------------------------------------------------------
# result payloads: per-point std, 95 % ellipse semi-axes, names, units, CSV
# --------------------------------------------------------------------------------------

def ellipse95(cov: Any) -> Any:
    """Semi-axes (largest first) of the 95 % confidence ellipse / ellipsoid of each covariance.

    For a d-dimensional Gaussian point estimate with covariance C the 95 % region is
    ``x' C^-1 x <= q`` with ``q`` the 0.95 quantile of chi-square with d degrees of
    freedom; its semi-axes are ``sqrt(q * lambda_i)`` over the eigenvalues of C.

    Parameters
    ----------
    cov:
        (n, d, d) covariances (NaN allowed: gives NaN axes).

    Returns
    -------
    numpy.ndarray
        (n, d) semi-axes in the unit of the coordinates.
    """
    import numpy as np
    from scipy.stats import chi2

    C = np.asarray(cov, dtype=float)
    n, d = C.shape[0], C.shape[-1]
    out = np.full((n, d), np.nan)
    ok = np.isfinite(C).all(axis=(1, 2))
    if ok.any():
        w = np.linalg.eigvalsh(0.5 * (C[ok] + np.swapaxes(C[ok], 1, 2)))
        out[ok] = np.sqrt(chi2.ppf(0.95, d) * np.clip(w, 0.0, None))[:, ::-1]
    return out


def enrich_payload(payload: dict[str, Any], *, names: Mapping[str, Any] | None = None,
                   units: Mapping[str, str] | None = None) -> dict[str, Any]:
    """Add ``<base>_std`` and ``<base>_ellipse95`` next to every ``<base>_cov``, names and units.

    ``names`` maps a key (``"receiver_names"``) to a sequence of names (skipped when None);
    ``units`` is set as ``payload["units"]`` unless the result already carries one.
    """
    import numpy as np

    for key in list(payload):
        if not key.endswith("_cov") or payload[key] is None:
            continue
        try:
            C = np.asarray(payload[key], dtype=float)
        except (TypeError, ValueError):
            continue
        if C.ndim != 3 or C.shape[1] != C.shape[2] or C.shape[0] == 0:
            continue
        base = key[: -len("_cov")]
        diag = np.diagonal(C, axis1=1, axis2=2)
        payload.setdefault(f"{base}_std", np.sqrt(np.where(diag >= 0, diag, np.nan)).tolist())
        payload.setdefault(f"{base}_ellipse95", ellipse95(C).tolist())
    for key, value in (names or {}).items():
        if value is not None:
            payload[key] = list(value)
    if units is not None:
        payload.setdefault("units", dict(units))
    return payload


def write_nodes_csv(path: Any, payload: Mapping[str, Any],
                    groups: list[tuple[str, str, str | None]]) -> None:
    """Write ``--csv``: one row per node (kind, name, coordinates, std per axis).

    ``groups`` lists (kind, positions key, names key) of the payload; the std comes from
    ``<base>_std`` when :func:`enrich_payload` added it (base = positions key without "s").
    """
    import numpy as np

    from ..io import write_csv_rows

    rows: list[list[Any]] = []
    d = 0
    for _kind, key, _names in groups:
        P = payload.get(key)
        if P is None:
            continue
        P = np.atleast_2d(np.asarray(P, dtype=float))
        d = max(d, P.shape[1])
    axes = "xyz"[:d] if d <= 3 else [f"c{i}" for i in range(d)]
    for kind, key, names_key in groups:
        P = payload.get(key)
        if P is None:
            continue
        P = np.atleast_2d(np.asarray(P, dtype=float))
        base = key[:-1] if key.endswith("s") else key
        S = payload.get(f"{base}_std")
        S = np.full(P.shape, np.nan) if S is None else np.atleast_2d(np.asarray(S, dtype=float))
        names = payload.get(names_key) if names_key else None
        for i in range(P.shape[0]):
            name = names[i] if names is not None and i < len(names) else f"{kind}{i}"  # 0-based, as --known / --frame (r0) and the JSON
            coords = list(P[i]) + [np.nan] * (d - P.shape[1])
            stds = list(S[i]) if S.shape == P.shape else [np.nan] * P.shape[1]
            rows.append([kind, name, *coords, *(stds + [np.nan] * (d - len(stds)))])
    header = ["kind", "name", *axes, *[f"{a}_std" for a in axes]]
    write_csv_rows(path, header, rows)


csv_option = click.option(
    "--csv", "csv_out", type=click.Path(dir_okay=False, path_type=Path), default=None, metavar="FILE",
    help="Also write the nodes as CSV: kind, name, coordinates, std per axis (m).")


# --------------------------------------------------------------------------------------
# clock jitter: one unit (seconds) on every command, --jitter-us spelled out
# --------------------------------------------------------------------------------------

def jitter_options(default: float | None, what: str = "") -> Callable[[Callable[..., Any]], Callable[..., Any]]:
    """``--jitter SECONDS`` and ``--jitter-us MICROSECONDS`` (the same quantity, one of the two)."""

    def deco(func: Callable[..., Any]) -> Callable[..., Any]:
        func = click.option(
            "--jitter-us", "jitter_us", type=JITTER_US, default=None, metavar="US",
            help="The clock jitter in microseconds instead of --jitter seconds.")(func)
        func = click.option(
            "--jitter", "jitter", type=JITTER_S, default=default, show_default=default is not None, metavar="S",
            help=f"Clock jitter per (receiver, event), standard deviation in SECONDS {what}".strip() + ".")(func)
        return func

    return deco


def resolve_jitter(jitter: float | None, jitter_us: float | None) -> Any:
    """The jitter in seconds from ``--jitter`` (s) or ``--jitter-us`` (us), plausibility-checked."""
    from .._checks import MAX_PLAUSIBLE_JITTER_S, check_float, plausible_jitter
    from ..errors import InputError

    if jitter_us is not None:
        us = check_float(jitter_us, "--jitter-us", nonnegative=True)
        assert us is not None
        if us * 1e-6 >= MAX_PLAUSIBLE_JITTER_S:
            raise InputError(f"--jitter-us {us:g} us ({us * 1e-6:g} s) is not a clock jitter; it must be below "
                             f"{MAX_PLAUSIBLE_JITTER_S * 1e6:g} us")
        return us * 1e-6
    return plausible_jitter(jitter, "--jitter")


# --------------------------------------------------------------------------------------
# resource guards of the simulators (refused before anything is allocated)
# --------------------------------------------------------------------------------------

def check_simulation_size(*, units: int, sample_rate: float, room: tuple[float, float, float],
                          rt60: float, rounds: int = 1) -> None:
    """Refuse conference simulations whose signals would not fit in memory (named up front).

    Memory: the recordings are ``units x n_total`` float32 samples with ``n_total =
    (0.1 s + (units * rounds + 1) * event_spacing) * sample_rate``
    (:func:`selfcal.acoustics.room.event_spacing`; one event per loudspeaker and round), plus
    ``units^2`` impulse responses of about ``rt60 * sample_rate`` float64 taps.
    """
    import numpy as np

    from .._checks import check_float, check_int, guard_size
    from ..acoustics.room import DEFAULT_PROBE, event_spacing

    check_int(units, "--units", minimum=5)  # conference_scene needs 5
    check_float(sample_rate, "--sample-rate", positive=True)
    check_float(rt60, "--rt60", nonnegative=True)
    check_int(rounds, "--rounds", minimum=1)
    spacing = event_spacing(np.asarray(room, dtype=float), float(DEFAULT_PROBE["duration"]), 343.0)
    n_total = (0.1 + spacing * (float(units) * float(rounds) + 1)) * sample_rate
    need = units * n_total * 4.0 + units**2 * (float(rt60) + spacing) * sample_rate * 8.0
    guard_size(need, f"a {units}-unit recording{f' of {rounds} rounds' if rounds != 1 else ''} at "
                     f"{sample_rate:g} Hz, rt60 {rt60:g} s "
                     f"({n_total / sample_rate:.3g} s per receiver)")


def transposed_hint(exc: Any, shape: tuple[int, int], *, min_rows: int, min_cols: int) -> None:
    """Re-raise a too-few-receivers / too-few-sources error saying the matrix looks transposed.

    Only when the transposed shape would meet the minimum (``min_rows`` receivers, ``min_cols``
    transmitters) and the given one does not; otherwise return and let the caller re-raise.
    """
    from ..errors import DegenerateGeometryError

    m, k = shape
    if getattr(exc, "kind", None) not in ("too-few-receivers", "too-few-sources"):
        return
    if (m >= min_rows and k >= min_cols) or not (k >= min_rows and m >= min_cols):
        return
    msg = exc.args[0] if exc.args else str(exc)
    raise DegenerateGeometryError(
        f"{msg}; the {m} x {k} matrix looks transposed: rows must be receivers, columns transmitters "
        f"(a {k} x {m} matrix would be solvable)", kind=exc.kind) from None
