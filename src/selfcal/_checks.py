"""Input validation shared by every entry point.

These helpers raise :class:`~selfcal.errors.InputError` (malformed data) or
:class:`~selfcal.errors.DegenerateGeometryError` (data that cannot determine the
unknowns) with messages that name the argument and the fix.

Why this file is long (~880 lines): it is the one place every entry point takes its input
checks from, so a rule and its message are written once; its sections (arrays and scalars,
identifiability counts, the :func:`entry` decorator, plausibility of units, size guards) are
independent of each other. Split, each importer's one line would become several or the
pieces would come back through re-export shims (the plausibility checks need
:func:`check_float`, the counts :func:`guard_size`).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from .errors import DegenerateGeometryError, InputError

__all__ = [
    "as_array",
    "check_int",
    "check_magnitude",
    "check_runs",
    "check_float",
    "entry",
    "plausible_matrix_scale",
    "plausible_jitter",
    "plausible_angles",
    "plausible_angle_unit",
    "guard_size",
    "as_matrix",
    "as_points",
    "check_dim",
    "check_choice",
    "check_positive",
    "as_rng",
    "check_toa_counts",
    "check_toa_observable",
    "check_path",
    "instance_of",
    "has_attributes",
    "check_pairs",
    "gauge_freedoms",
    "n_parameters",
]


#: Largest magnitude of an entry the least-squares solvers can process (:func:`check_magnitude`):
#: they form squares, products and sums of up to ~1e12 such terms, which must stay below the
#: float64 maximum (1.8e308), so |entry| <= sqrt(1.8e308 / 1e12) ~ 1.3e148.
MAX_ABS_ENTRY = float(np.sqrt(np.finfo(np.float64).max / 1e12))


def as_matrix(
    value: Any,
    name: str = "matrix",
    *,
    allow_nan: bool = True,
    nonnegative: bool = False,
    min_shape: tuple[int, int] = (1, 1),
    huge: str = "scale",
) -> NDArray[np.float64]:
    """Convert ``value`` to a float (rows, cols) matrix and validate it.

    NaN is allowed only as "missing" (``allow_nan``); +-inf is always refused.
    With ``nonnegative`` every finite entry must be >= 0 (ranges, times of flight).
    Magnitudes beyond :data:`MAX_ABS_ENTRY`: with ``huge="scale"`` (default) the matrix is
    refused when its median finite magnitude is beyond it (a unit mistake or corrupt data);
    single absurd entries in an otherwise plausible matrix are left to the solver, whose
    robust fit flags them as gross outliers (the TOA solver, issue 12). ``huge="entry"``
    refuses any such entry (solvers without a gross-error model for them).
    """
    arr = as_array(value, name)
    if arr.ndim != 2:
        raise InputError(f"{name}: expected a 2-D matrix (rows = receivers, columns = transmitters), got shape {arr.shape}")
    if arr.shape[0] < min_shape[0] or arr.shape[1] < min_shape[1]:
        raise InputError(f"{name}: shape {arr.shape} is too small; need at least {min_shape[0]} x {min_shape[1]}")
    if np.isinf(arr).any():
        i, j = np.argwhere(np.isinf(arr))[0]
        raise InputError(f"{name}: entry ({i}, {j}) is infinite; use NaN (or an empty field) for a missing value")
    nan = np.isnan(arr)
    if nan.any() and not allow_nan:
        i, j = np.argwhere(nan)[0]
        raise InputError(f"{name}: entry ({i}, {j}) is NaN but missing values are not allowed here")
    if nan.all():
        raise InputError(f"{name}: every entry is missing (NaN)")
    mag = np.abs(arr[~nan])
    if (mag > MAX_ABS_ENTRY).any() and (huge == "entry" or np.median(mag) > MAX_ABS_ENTRY):
        check_magnitude(arr, name)  # names the first such entry
    if nonnegative and (arr[~nan] < 0).any():
        i, j = np.argwhere(np.where(nan, 0.0, arr) < 0)[0]
        raise InputError(f"{name}: entry ({i}, {j}) = {arr[i, j]:g} is negative; ranges and times of flight must be >= 0")
    return arr


def as_points(value: Any, name: str = "points", *, dim: int | None = None, allow_nan: bool = False) -> NDArray[np.float64]:
    """Convert ``value`` to an (n, d) float array of points, d in {2, 3} (or ``dim``)."""
    arr = as_array(value, name)
    if arr.ndim != 2:
        raise InputError(f"{name}: expected an (n, d) array of points (one point per row), got shape {arr.shape}")
    d = arr.shape[1]
    if d not in (2, 3) and arr.shape[0] in (2, 3) and (dim is None or arr.shape[0] == dim):
        raise InputError(f"{name}: shape {arr.shape} looks transposed; give one point per row "
                         f"({arr.shape[1]} x {arr.shape[0]}), not one coordinate per row")
    if dim is not None and d != dim:
        raise InputError(f"{name}: points have {d} coordinates, expected {dim}")
    if d not in (2, 3):
        raise InputError(f"{name}: points must have 2 or 3 coordinates, got {d}")
    if np.isinf(arr).any() or (not allow_nan and np.isnan(arr).any()):
        raise InputError(f"{name}: contains NaN or inf")
    return arr


def check_magnitude(arr: NDArray[np.float64], name: str) -> NDArray[np.float64]:
    """Refuse finite entries beyond :data:`MAX_ABS_ENTRY`, where least-squares sums overflow.

    For arrays of any shape (points, logs) of solvers without a gross-error model for such
    entries; matrices use ``as_matrix(huge="entry")`` (or ``huge="scale"`` for the TOA solver,
    whose robust fit flags a single 1e300 typo).

    Raises
    ------
    InputError
        Naming the first such entry and the fix (another unit).
    """
    a = np.asarray(arr, dtype=float)
    big = np.abs(np.where(np.isfinite(a), a, 0.0)) > MAX_ABS_ENTRY
    if big.any():
        idx = tuple(int(v) for v in np.argwhere(big)[0])
        raise InputError(f"{name}: entry {idx} = {a[idx]:.3g} is beyond {MAX_ABS_ENTRY:.2g}, where the "
                         f"least-squares sums overflow double precision; give the data in another unit")
    return a


def non_number_leaf(value: Any) -> str | None:
    """The first leaf of a nested JSON list that is not a number or ``null``, as a short repr
    (None when every leaf is one). Strings and booleans are not numbers, although numpy reads
    ``"1e-3"`` as 0.001 and ``true`` as 1 when it converts the list.

    Examples
    --------
    >>> non_number_leaf([[1, 2.5], [None, 3]]) is None, non_number_leaf([[1, "2"]])
    (True, "'2'")
    """
    stack = [value]
    while stack:
        v = stack.pop()
        if isinstance(v, (list, tuple)):
            stack.extend(v)
        elif v is None or (isinstance(v, (int, float)) and not isinstance(v, bool)):
            continue
        else:
            return repr(v)[:40]
    return None


def check_dim(dim: int) -> int:
    """Return ``dim`` if it is 2 or 3, else raise :class:`InputError`."""
    if isinstance(dim, (bool, np.bool_)) or not isinstance(dim, (int, np.integer, float, np.floating)) \
            or dim not in (2, 3):
        raise InputError(f"dim must be 2 or 3, got {type(dim).__name__} {dim!r}"[:120])
    return int(dim)


def check_choice(value: str, name: str, choices: tuple[str, ...] | list[str]) -> str:
    """Return ``value`` if it is one of ``choices``, else raise :class:`InputError`."""
    if value not in choices:
        raise InputError(f"{name} must be one of {', '.join(map(repr, choices))}; got {value!r}")
    return value


def check_positive(value: float | None, name: str, *, allow_none: bool = True) -> float | None:
    """Return ``value`` as float if it is finite and > 0 (or None when allowed)."""
    if value is None:
        if allow_none:
            return None
        raise InputError(f"{name} is required")
    v = float(value)
    if not np.isfinite(v) or v <= 0:
        raise InputError(f"{name} must be a finite positive number, got {value!r}")
    return v


def as_rng(rng: np.random.Generator | int | None) -> np.random.Generator:
    """Normalise an ``rng`` argument (Generator, seed >= 0 or None) to a Generator."""
    if isinstance(rng, np.random.Generator):
        return rng
    if rng is None:
        return np.random.default_rng()
    if isinstance(rng, (int, np.integer)) and not isinstance(rng, (bool, np.bool_)):
        if rng < 0:
            raise InputError(f"rng: a seed must be >= 0, got {int(rng)}")
        return np.random.default_rng(int(rng))
    raise InputError(f"rng must be a numpy Generator, an int seed >= 0 or None, got {type(rng).__name__}")


def check_toa_counts(shape: tuple[int, int], n_observed: int, dim: int, offsets: str) -> None:
    """Raise :class:`DegenerateGeometryError` when an I x J TOA problem is under-determined.

    The condition is ``I >= d+1``, ``J >= d+1`` (the positions must span the space) and
    ``observed entries >= unknowns`` where ``unknowns = d(I+J) - d(d+1)/2 + [I] + [J] - [both]``
    (coordinates less the rigid motions, plus the offsets less one common shift). The classical
    minimal configurations for ``offsets="none"`` (Kuang, Burgess, Torstensson & Astrom 2013)
    are 3 x 3 in 2-D and 4 x 6 / 6 x 4 in 3-D.
    """
    I, J = shape
    r_min = s_min = dim + 1
    if I < r_min:
        raise DegenerateGeometryError(
            f"{I} receivers cannot determine a {dim}-D geometry; at least {r_min} are needed "
            f"(they must span {dim}-D space)",
            kind="too-few-receivers",
        )
    if J < s_min:
        raise DegenerateGeometryError(
            f"{J} transmitters cannot determine a {dim}-D geometry; at least {s_min} are needed "
            f"(they must span {dim}-D space)",
            kind="too-few-sources",
        )
    unknowns = n_parameters(I, J, dim, offsets)
    if n_observed < unknowns + 1 and offsets != "none":
        raise DegenerateGeometryError(
            f"{n_observed} observed entries for {unknowns} unknowns ({I} receivers x {J} transmitters, "
            f"{dim}-D, offsets={offsets!r}); add receivers or transmitters until "
            f"I*J > d(I+J) - d(d+1)/2 + offsets",
            kind="too-few-measurements",
        )
    if n_observed < unknowns:
        raise DegenerateGeometryError(
            f"{n_observed} observed entries for {unknowns} unknowns ({I} receivers x {J} transmitters, "
            f"{dim}-D, offsets={offsets!r}); add receivers, transmitters or measurements",
            kind="too-few-measurements",
        )



# --------------------------------------------------------------------------------------
# scalar and array validators shared by the entry points
# --------------------------------------------------------------------------------------

def check_toa_observable(matrix: NDArray[np.float64], dim: int, offsets: str = "none",
                         name: str = "matrix") -> None:
    """Refuse, in time linear in the entries, a TOA matrix whose pattern cannot be solved.

    :func:`check_toa_counts` on the whole matrix, then the empty nodes: rows / columns with
    no observed entry say nothing about the network. When they are more than half of the
    nodes the result would fail its determinacy test anyway (more than half of the nodes
    undetermined, :mod:`selfcal.toa.verdict.determinacy`), so the matrix is refused up front, before
    work that grows with its size. (Pruning the nodes with at most ``dim`` ranges adds
    nothing here: the entries such nodes carry are at most ``dim`` per node, fewer than
    their unknowns, so a matrix that passes the whole count leaves a core that passes it.)

    Raises
    ------
    DegenerateGeometryError
        The count's kinds, or ``unobservable-node`` naming the empty rows and columns.
    """
    obs = np.isfinite(np.asarray(matrix))
    I, J = obs.shape
    check_toa_counts((I, J), int(obs.sum()), dim, offsets)
    empty_r = int((~obs.any(axis=1)).sum())
    empty_c = int((~obs.any(axis=0)).sum())
    if 2 * (empty_r + empty_c) > I + J:
        raise DegenerateGeometryError(
            f"{name}: {empty_r} of {I} rows (receivers) and {empty_c} of {J} columns (transmitters) have no "
            f"observed entry: more than half of the nodes say nothing; remove the empty rows / columns",
            kind="unobservable-node")


def as_array(value: Any, name: str = "array") -> NDArray[np.float64]:
    """Convert ``value`` to a float array: masked entries -> NaN; complex, text, objects refused.

    Raises
    ------
    InputError
        Complex, strings / bytes, booleans-as-objects, ragged nesting, or non-numbers.
    """
    if isinstance(value, (str, bytes)):
        raise InputError(f"{name}: expected numbers, got a {type(value).__name__}")
    if np.ma.isMaskedArray(value):
        m = np.ma.getmaskarray(value)
        data = np.ma.getdata(value)
        if data.dtype.kind == "c":
            raise InputError(f"{name}: complex values; give real numbers")
        if data.dtype.kind == "b":
            raise InputError(f"{name}: holds booleans (True / False), not measurements; give the measured numbers")
        try:
            arr = np.array(data, dtype=np.float64)
        except (TypeError, ValueError) as exc:
            raise InputError(f"{name}: cannot be read as numbers ({exc})") from None
        arr[m] = np.nan  # the mask means missing
        return arr
    try:
        raw = np.asarray(value)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{name}: cannot be read as a numeric array ({str(exc).splitlines()[0]})") from None
    kind = raw.dtype.kind
    if kind == "c":
        raise InputError(f"{name}: complex values; give real numbers")
    if kind == "b":  # a mask passed by mistake: True / False are not ranges, times or angles
        raise InputError(f"{name}: holds booleans (True / False), not measurements; give the measured numbers")
    if kind in "USaV":
        raise InputError(f"{name}: holds text ({raw.dtype}); give numbers (read files with selfcal.io.read_matrix)")
    if kind in "mM":
        raise InputError(f"{name}: holds dates / durations; give numbers")
    if kind == "O":
        flat = raw.ravel()
        for v in flat[: 10_000]:
            if v is None or isinstance(v, (str, bytes, complex, np.complexfloating, bool, np.bool_)) \
                    or not np.isscalar(v):
                raise InputError(f"{name}: holds {type(v).__name__} values; give a rectangular array of numbers")
    try:
        return np.array(raw, dtype=np.float64)
    except (TypeError, ValueError, OverflowError) as exc:
        raise InputError(f"{name}: cannot be read as numbers ({exc})") from None


def check_int(value: Any, name: str, *, minimum: int | None = None, allow_none: bool = False) -> int | None:
    """Return ``value`` as int; refuse bools, non-integral numbers, text and values < ``minimum``."""
    if value is None:
        if allow_none:
            return None
        raise InputError(f"{name} is required")
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer, float, np.floating)):
        raise InputError(f"{name} must be an integer, got {type(value).__name__} {value!r}")
    if isinstance(value, (float, np.floating)):
        if not np.isfinite(value) or float(value) != int(value):
            raise InputError(f"{name} must be an integer, got {value!r}")
    v = int(value)
    if minimum is not None and v < minimum:
        raise InputError(f"{name} must be >= {minimum}, got {v}")
    return v


def check_float(value: Any, name: str, *, positive: bool = False, nonnegative: bool = False,
                allow_none: bool = True, finite: bool = True, maximum: float | None = None) -> float | None:
    """Return ``value`` as a finite float; refuse text, complex, bools, NaN/inf, sign violations."""
    if value is None:
        if allow_none:
            return None
        raise InputError(f"{name} is required")
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise InputError(f"{name} must be a real number, got {type(value).__name__} {value!r}")
    v = float(value)
    if np.isnan(v) or (finite and not np.isfinite(v)):
        raise InputError(f"{name} must be a finite number, got {value!r}")
    if positive and not v > 0:
        raise InputError(f"{name} must be > 0, got {v:g}")
    if nonnegative and not v >= 0:
        raise InputError(f"{name} must be >= 0, got {v:g}")
    if maximum is not None and v > maximum:
        raise InputError(f"{name} must be <= {maximum:g}, got {v:g}")
    return v


_SPECS: dict[str, Any] = {
    "positive": lambda v, n: check_float(v, n, positive=True, allow_none=False),
    "positive?": lambda v, n: check_float(v, n, positive=True),
    "nonnegative?": lambda v, n: check_float(v, n, nonnegative=True),
    "count": lambda v, n: check_int(v, n, minimum=1),
    "count?": lambda v, n: check_int(v, n, minimum=1, allow_none=True),
    "count0": lambda v, n: check_int(v, n, minimum=0),
    "count0?": lambda v, n: check_int(v, n, minimum=0, allow_none=True),
    "rng": lambda v, n: as_rng(v) and None,
    "bool": lambda v, n: _check_bool(v, n),
    "str": lambda v, n: _check_str(v, n),
    "str?": lambda v, n: None if v is None else _check_str(v, n),
    "dim": lambda v, n: check_dim(v),
    "path": lambda v, n: check_path(v, n),
    "path?": lambda v, n: check_path(v, n, allow_none=True),
    "paths": lambda v, n: _check_paths(v, n),
    "indices": lambda v, n: _check_indices(v, n),
    "callable": lambda v, n: _check_callable(v, n),
    "array": lambda v, n: None,
}


def check_path(value: Any, name: str, *, allow_none: bool = False) -> None:
    """Refuse anything but a ``str`` / ``os.PathLike`` path (bytes, numbers, arrays, '' and NUL)."""
    import os

    if value is None and allow_none:
        return
    if isinstance(value, (bytes, bytearray)):
        raise InputError(f"{name} must be a path (str or pathlib.Path), got bytes {bytes(value)[:40]!r}; "
                         f"decode it first")
    if not isinstance(value, (str, os.PathLike)):
        raise InputError(f"{name} must be a path (str or pathlib.Path), got {type(value).__name__}")
    raw = os.fspath(value)
    if not isinstance(raw, str):
        raise InputError(f"{name} must be a path (str or pathlib.Path), got a bytes path")
    if raw == "" or "\x00" in raw:
        raise InputError(f"{name} {raw!r} is not a usable path")


def _check_paths(value: Any, name: str) -> None:
    if isinstance(value, (list, tuple)):
        if not value:
            raise InputError(f"{name} is an empty list; give at least one path")
        for k, v in enumerate(value):
            check_path(v, f"{name}[{k}]")
        return
    check_path(value, name)


def _check_indices(value: Any, name: str) -> None:
    """A non-empty 1-D array of integer indices >= 0 (booleans and floats refused)."""
    if isinstance(value, (str, bytes)) or value is None or isinstance(value, (dict, set)):
        raise InputError(f"{name} must be a 1-D array of integer indices, got {type(value).__name__}")
    try:
        arr = np.asarray(value)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{name} must be a 1-D array of integer indices ({str(exc).splitlines()[0]})") from None
    if arr.ndim != 1:
        raise InputError(f"{name} must be a 1-D array of integer indices, got shape {arr.shape}")
    if arr.size == 0:
        raise InputError(f"{name} is empty: give at least one observed pair")
    if arr.dtype.kind not in "iu":
        raise InputError(f"{name} must hold integer indices, got dtype {arr.dtype}")
    if arr.min() < 0:
        raise InputError(f"{name}: indices must be >= 0, got {int(arr.min())}")


def _check_callable(v: Any, n: str) -> None:
    if not callable(v):
        raise InputError(f"{n} must be a callable, got {type(v).__name__}")


def instance_of(get_class: Any, what: str) -> Any:
    """An :func:`entry` spec: the argument is an instance of ``get_class()`` (imported lazily)."""

    def check(v: Any, n: str) -> None:
        cls = get_class()
        if not isinstance(v, cls):
            raise InputError(f"{n} must be a {what}, got {type(v).__name__}")

    return check


def has_attributes(*names: str, what: str) -> Any:
    """An :func:`entry` spec: the argument carries every attribute in ``names`` (duck typing)."""

    def check(v: Any, n: str) -> None:
        missing = [a for a in names if not hasattr(v, a)]
        if missing:
            raise InputError(f"{n} must be a {what}, got {type(v).__name__} (no attribute {missing[0]!r})")

    return check


def _check_bool(v: Any, n: str) -> None:
    if not isinstance(v, (bool, np.bool_)):
        raise InputError(f"{n} must be True or False, got {type(v).__name__} {v!r}")


def _check_str(v: Any, n: str) -> None:
    if not isinstance(v, str):
        raise InputError(f"{n} must be a string, got {type(v).__name__} {v!r}")


_LEAKS = (ValueError, TypeError, IndexError, KeyError, ZeroDivisionError, OverflowError, FloatingPointError,
          np.linalg.LinAlgError, AttributeError)


def entry(**specs: str) -> Any:
    """Decorator for a public entry point: validate named arguments, name any leftover failure.

    Parameters
    ----------
    **specs:
        ``argument="spec"`` with spec one of ``positive``, ``positive?`` (None allowed),
        ``nonnegative?``, ``count`` (int >= 1), ``count?``, ``count0`` (int >= 0), ``count0?``,
        ``rng`` (Generator / seed >= 0 / None), ``bool``, ``str``, ``str?``, ``path`` / ``path?``
        (str or os.PathLike; bytes refused), ``paths`` (a path or a non-empty list of them),
        ``indices`` (non-empty 1-D integer array >= 0), ``callable``, ``array`` (masked entries ->
        NaN; complex, text, booleans and non-arrays refused), or a callable ``(value, name)``
        raising :class:`~selfcal.errors.InputError` (:func:`instance_of`, :func:`has_attributes`).

    Notes
    -----
    Arguments are checked before the function runs. A ``ValueError``, ``TypeError``,
    ``IndexError``, ``KeyError``, ``ZeroDivisionError``, ``OverflowError``, ``LinAlgError``
    that still escapes the function becomes an :class:`~selfcal.errors.InputError` naming the
    function (a ``MemoryError`` too, saying that the input is too large), so that a caller
    only ever sees :class:`~selfcal.errors.SelfcalError` subclasses.

    Examples
    --------
    >>> @entry(speed="positive?")
    ... def f(x, speed=None):
    ...     return speed
    >>> f(1, speed="fast")
    Traceback (most recent call last):
    ...
    selfcal.errors.InputError: speed must be a real number, got str 'fast'
    """
    import functools
    import inspect

    from .errors import SelfcalError

    def deco(func: Any) -> Any:
        sig = inspect.signature(func)
        for k, spec in specs.items():
            if k not in sig.parameters or not (callable(spec) or spec in _SPECS):
                raise TypeError(f"entry(): {func.__name__} has no argument {k!r} or spec {spec!r} is unknown")

        @functools.wraps(func)
        def wrapper(*args: Any, **kwargs: Any) -> Any:
            try:
                bound = sig.bind(*args, **kwargs)
            except TypeError as exc:
                raise InputError(f"{func.__name__}: {exc}") from None
            for k, spec in specs.items():
                if k not in bound.arguments:
                    continue
                v = bound.arguments[k]
                if callable(spec):
                    spec(v, k)
                    continue
                if spec == "array":
                    if v is None and sig.parameters[k].default is inspect.Parameter.empty:
                        raise InputError(f"{k} is required: give an array of numbers")
                    if isinstance(v, (str, bytes, bytearray, dict, set)) or (v is not None and not (
                            np.isscalar(v) or hasattr(v, "__array__") or hasattr(v, "__len__"))):
                        raise InputError(f"{k}: expected an array of numbers, got {type(v).__name__}")
                    if v is not None and not np.isscalar(v):
                        bound.arguments[k] = as_array(v, k)
                    continue
                _SPECS[spec](v, k)
            try:
                return func(*bound.args, **bound.kwargs)
            except SelfcalError:
                raise
            except MemoryError:
                raise InputError(f"{func.__name__}: the input needs more memory than this machine has") from None
            except RecursionError:
                raise InputError(f"{func.__name__}: the input is nested too deeply") from None
            except _LEAKS as exc:
                msg = " ".join(str(exc).split())[:200]
                raise InputError(f"{func.__name__}: could not use the input ({type(exc).__name__}: {msg})") from None

        wrapper.__selfcal_entry__ = True  # type: ignore[attr-defined]  # tests: every public function has it
        return wrapper

    return deco


# --------------------------------------------------------------------------------------
# plausibility: the mistakes people make, named
# --------------------------------------------------------------------------------------

#: Largest finite entry (m) below which a "range" matrix looks like seconds given without --speed.
#: The networks selfcal calibrates (rooms, halls, UWB, radio) span more than 10 cm; acoustic times
#: of flight across a 30 m hall are < 0.1 s, so sub-0.1 values in metres are far likelier seconds.
TIMES_AS_METRES_MAX = 0.1
#: The same for far-field TDOA (relative distances across a microphone array): arrays are
#: larger than 5 mm (a 1 m array gives times of flight of ~3 ms = 0.003 "m").
FARFIELD_TIMES_AS_METRES_MAX = 0.005
#: Largest distance (m) a TOA / TDOA self-calibration is expected to span; beyond it the likely
#: mistake is milliseconds (or samples) read as seconds with --speed.
MAX_PLAUSIBLE_SPAN_M = 1000.0
#: Largest clock jitter (s) that is not a unit mistake: detection windows are milliseconds, 004's
#: units are synchronised within 100 us; a jitter >= 10 ms is microseconds given as seconds.
MAX_PLAUSIBLE_JITTER_S = 0.01
#: Largest distance (m) of an indoor network (rooms, halls, UWB in a building): a range matrix
#: spanning more (without ``--unit``) gets a warning naming centimetres / millimetres; one
#: spanning more than :data:`MAX_PLAUSIBLE_SPAN_M` is refused (no ranging hardware selfcal
#: calibrates -- acoustic, UWB -- measures a kilometre; 8000 "m" is an 8 m room in millimetres).
ROOM_SPAN_M = 100.0


def _length_unit_mistake(top: float, name: str) -> None:
    """Refuse (beyond :data:`MAX_PLAUSIBLE_SPAN_M`) or warn (beyond :data:`ROOM_SPAN_M`) about
    a range matrix in metres whose scale only makes sense in millimetres or centimetres."""
    import warnings

    alts = [f"{w} (--unit {u}: {top * f:.3g} m)" for w, u, f in (("millimetres", "mm", 1e-3),
                                                                    ("centimetres", "cm", 1e-2))
            if TIMES_AS_METRES_MAX <= top * f <= ROOM_SPAN_M]
    guess = " or ".join(alts) if alts else "millimetres (--unit mm) or centimetres (--unit cm)"
    if top > MAX_PLAUSIBLE_SPAN_M:
        raise InputError(
            f"{name}: the largest range is {top:.4g}, {top / 1000:.3g} km if these are metres -- beyond any "
            f"ranging network ({MAX_PLAUSIBLE_SPAN_M / 1000:g} km); are they in another unit, {guess}? "
            f"Confirm metres with --unit m")
    warnings.warn(
        f"{name}: the largest range is {top:.4g} m, beyond a room or hall ({ROOM_SPAN_M:g} m); if these are "
        f"{guess} say so, or confirm metres with --unit m", UserWarning, stacklevel=3)


def plausible_matrix_scale(matrix: NDArray[np.float64], *, speed: float | None, explicit_unit: bool,
                           name: str = "matrix", option: str = "--speed",
                           min_span: float = TIMES_AS_METRES_MAX) -> None:
    """Refuse a range / time matrix whose scale points at a unit mistake (unless the unit was explicit).

    Raises
    ------
    InputError
        Ranges whose largest entry is below :data:`TIMES_AS_METRES_MAX` without ``--speed``
        (times in seconds), or distances ``speed * t`` beyond :data:`MAX_PLAUSIBLE_SPAN_M`
        (milliseconds or samples read as seconds), or ranges in metres beyond
        :data:`MAX_PLAUSIBLE_SPAN_M` (millimetres / centimetres read as metres).

    Warns
    -----
    UserWarning
        Ranges in metres beyond :data:`ROOM_SPAN_M` (likely centimetres), printed by the CLI
        as a ``selfcal: warning:`` line after the result.
    """
    if explicit_unit:
        return
    M = np.asarray(matrix, dtype=float)
    finite = np.abs(M[np.isfinite(M)])
    if finite.size == 0:
        return
    top = float(finite.max())
    if speed is None:
        if 0 < top < min_span:
            raise InputError(
                f"{name}: the largest entry is {top:.3g}, a network under {min_span * 100:g} cm "
                f"if these are metres; if they are times in seconds give {option} (343 for sound in air), "
                f"if kilometres --unit km, or confirm metres with --unit m")
        if top > ROOM_SPAN_M:
            _length_unit_mistake(top, name)
        return
    span = top * speed
    if span > MAX_PLAUSIBLE_SPAN_M:
        raise InputError(
            f"{name}: with {option} {speed:g} the largest entry {top:.3g} s is {span / 1000:.3g} km; "
            f"are the times milliseconds (--unit ms), microseconds (--unit us) or samples "
            f"(--unit samples --sample-rate HZ)? Confirm seconds with --unit s")


def plausible_jitter(jitter: float | None, option: str = "--jitter") -> float | None:
    """Refuse a negative / non-finite jitter or one of 10 ms or more (microseconds given as seconds)."""
    if jitter is None:
        return None
    j = check_float(jitter, option, nonnegative=True)
    assert j is not None
    if j >= MAX_PLAUSIBLE_JITTER_S:
        raise InputError(f"{option} {j:g} s is not a clock jitter; {option} is in seconds "
                         f"(did you mean {option}-us {j:g}, i.e. {j * 1e-6:g} s?)")
    return j


def plausible_angles(values: NDArray[np.float64], unit: str, option: str = "--angles") -> None:
    """Refuse radians beyond 2 pi (likely degrees) with the fix named."""
    a = np.asarray(values, dtype=float)
    finite = np.abs(a[np.isfinite(a)])
    if unit == "rad" and finite.size and finite.max() > 2 * np.pi + 1e-9:
        raise InputError(f"{option} rad: values up to {finite.max():.4g} exceed 2 pi; are they degrees "
                         f"({option} deg)?")


#: A receiver located from bearings stands among its beacons (in the room they span). Read as
#: degrees, radians (every value within 2 pi) squeeze every bearing into a cone of ~12 deg, which
#: the fit explains by a receiver far outside: more than this many beacon extents (largest
#: beacon-beacon distance) from the beacons' centre is "outside" ...
AOA_OUTSIDE_EXTENTS = 2.0
#: ... and within this many extents is "among the beacons" (the radians reading's position).
AOA_INSIDE_EXTENTS = 1.0


def plausible_angle_unit(values: NDArray[np.float64], beacons: NDArray[np.float64],
                         position_deg: NDArray[np.float64] | None, position_rad: NDArray[np.float64] | None,
                         *, rad_fits: bool, option: str = "--unit", degrees_error: str | None = None) -> None:
    """Refuse / warn about bearing angles read as degrees whose spread only makes sense in radians.

    Called only when the degrees were the default (not given). Every value within 2 pi and the
    degrees reading putting the receiver more than :data:`AOA_OUTSIDE_EXTENTS` beacon
    extents from the beacons' centre: when the radians reading fits (``rad_fits``) and puts
    the receiver among the beacons (:data:`AOA_INSIDE_EXTENTS`) the evidence is strong
    (refused, exit 2); otherwise a warning. ``position_deg`` None: the degrees reading gave
    no pose (``degrees_error``, e.g. an angle pair no direction makes); refused when the
    radians reading fits among the beacons, else nothing is said here (the caller reports
    the degrees reading's error).

    Raises
    ------
    InputError
        Naming ``--unit rad`` (and ``--unit deg`` to confirm).

    Examples
    --------
    >>> import numpy as np
    >>> b = np.array([[0.0, 0, 0], [8, 0, 0], [8, 6, 0], [0, 6, 3]])
    >>> plausible_angle_unit(np.zeros((4, 2)), b, np.array([4.0, 3, 1]), None, rad_fits=False)
    """
    import warnings

    v = np.abs(np.asarray(values, dtype=float))
    v = v[np.isfinite(v)]
    B = np.asarray(beacons, dtype=float)
    B = B[np.isfinite(B).all(axis=1)]
    if v.size == 0 or v.max() > 2 * np.pi or len(B) < 2:
        return
    centre = B.mean(axis=0)
    extent = float(np.max(np.linalg.norm(B[:, None] - B[None], axis=2)))
    far_deg = np.inf if position_deg is None else float(np.linalg.norm(np.asarray(position_deg, float) - centre))
    if not extent > 0 or not far_deg > AOA_OUTSIDE_EXTENTS * extent:
        return
    far_rad = np.inf if position_rad is None else float(np.linalg.norm(np.asarray(position_rad, float) - centre))
    among = rad_fits and far_rad <= AOA_INSIDE_EXTENTS * extent
    if position_deg is None:
        if among:
            why = " ".join(str(degrees_error).split())[:120]
            raise InputError(f"bearings: are they radians ({option} rad)? Every angle is within 2 pi "
                             f"({v.max():.3g}); read as radians they fit with the receiver {far_rad:.3g} m from the "
                             f"beacons' centre, read as degrees they give no pose ({why}). Confirm degrees with "
                             f"{option} deg")
        return
    what = (f"bearings: every angle is within 2 pi ({v.max():.3g}); read as degrees they put the receiver "
            f"{far_deg:.3g} m from the beacons' centre ({far_deg / extent:.0f} x the beacons' extent of "
            f"{extent:.3g} m)")
    if among:
        raise InputError(f"{what}, read as radians {far_rad:.3g} m; are they radians ({option} rad)? "
                         f"Confirm degrees with {option} deg")
    warnings.warn(f"{what}; if they are radians give {option} rad (or confirm degrees with {option} deg)",
                  UserWarning, stacklevel=2)


def guard_size(n_bytes: float, what: str, *, limit: float | None = None) -> None:
    """Refuse up front an allocation of ``n_bytes`` beyond ``limit`` (default: half the RAM).

    Raises
    ------
    InputError
        Naming ``what`` and the memory it would need.
    """
    if limit is None:
        try:
            import os

            limit = 0.5 * os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
        except (ValueError, OSError, AttributeError):
            limit = 8e9
    if not np.isfinite(n_bytes) or n_bytes > limit:
        need = "an unbounded amount of" if not np.isfinite(n_bytes) else f"{n_bytes / 1e9:.3g} GB of"
        raise InputError(f"{what} would need {need} memory (limit {limit / 1e9:.3g} GB); choose smaller sizes")


#: Memory one Monte-Carlo trial holds until its sweep ends (its task tuple, spawned
#: ``SeedSequence`` and tidy result row): at least 1 kB, so a run count is bounded by memory.
TRIAL_BYTES = 1024.0


def check_runs(value: Any, name: str = "--runs", *, minimum: int = 1, settings: int = 1) -> int:
    """Return a Monte-Carlo run count, refusing non-integers, values < ``minimum`` and counts
    whose trials (``value * settings``, :data:`TRIAL_BYTES` each) could not be held in memory.

    Raises
    ------
    InputError
        Naming the option (before anything is written or run).
    """
    v = check_int(value, name, minimum=minimum)
    assert v is not None
    guard_size(float(v) * max(int(settings), 1) * TRIAL_BYTES, f"{name} {v}")
    return v


def guard_recording_setup(sample_rate: float, event_times: Any, probe: Any, n_receivers: int = 1,
                          where: str = "setup.json") -> None:
    """Refuse, before any signal is read or synthesised, a setup whose sizes cannot be real.

    A chirp probe of ``duration`` s is ``duration * sample_rate`` float64 samples; an event at
    time ``t`` needs every receiver's recording to be at least ``t * sample_rate`` samples
    long. Either beyond the memory limit of :func:`guard_size` is named with what it needs.

    Raises
    ------
    InputError
        Naming the field and the memory.
    """
    fs = float(sample_rate)
    times = np.asarray(event_times, dtype=float)
    if times.size:
        t = float(np.max(times))
        guard_size(t * fs * 4.0 * max(int(n_receivers), 1),
                   f"{where}: field 'events' (latest time {t:g} s at {fs:g} Hz, {t * fs:.3g} samples per receiver)")
    if isinstance(probe, dict) and "duration" in probe:
        d = probe["duration"]
        if isinstance(d, bool) or not isinstance(d, (int, float)) or not np.isfinite(d) or d <= 0:
            raise InputError(f"{where}: field 'probe.duration' must be a positive number of seconds, got {d!r}")
        guard_size(float(d) * fs * 8.0 * 4, f"{where}: field 'probe.duration' ({float(d):g} s at {fs:g} Hz)")


def gauge_freedoms(dim: int) -> int:
    """Degrees of freedom of a rigid motion in ``dim`` dimensions: ``dim (dim + 1) / 2`` (3 in 2-D, 6 in 3-D)."""
    return int(dim) * (int(dim) + 1) // 2


def n_parameters(n_receivers: int, n_sources: int, dim: int, offsets: str = "none") -> int:
    """Free parameters of the TOA / range model up to the gauge (003 eq. 2, 004 eq. 3.1).

    The one parameter count of the package (residual chi-square tests, the identifiability
    check of the entry points, the pipeline's noise test, the 2-D / 3-D model comparison).

    Parameters
    ----------
    n_receivers, n_sources : int
        I and J (``n_sources = 0`` counts the coordinates of ``n_receivers`` points only).
    dim : int
        2 or 3.
    offsets : {"none", "receivers", "sources", "both"}
        Unknown offsets: none; one per receiver (I); one per source (J); both (``I + J - 1``:
        a common shift between delays and onsets is not observable).

    Returns
    -------
    int
        ``dim (I + J) - dim (dim + 1) / 2`` coordinates (a rigid motion removed) plus the offsets;
        ``4 (I + J) - 7`` in 3-D with both offsets.

    Examples
    --------
    >>> n_parameters(12, 6, 3, "both")   # 3 * 18 - 6 + 12 + 6 - 1
    65
    >>> n_parameters(8, 10, 2)           # 2 * 18 - 3
    33
    """
    I, J = int(n_receivers), int(n_sources)
    n_off = {"none": 0, "receivers": I, "sources": J, "both": I + J - 1}.get(offsets)
    if n_off is None:
        raise InputError(f"offsets must be one of none, receivers, sources, both; got {offsets!r}")
    return int(dim) * (I + J) - gauge_freedoms(dim) + n_off


def check_pairs(i: object, j: object, ranges: object, I: int | None, J: int | None
                ) -> tuple[NDArray[np.intp], NDArray[np.intp], NDArray[np.float64], int, int]:
    """Validate observed pairs ``(i[k], j[k], ranges[k])`` of a sparse range network.

    Returns ``(i, j, ranges, I, J)`` (indices as ``intp``; ``I`` / ``J`` from the largest
    index when None). Raises :class:`~selfcal.errors.InputError` for malformed, duplicate or
    out-of-range pairs, :class:`~selfcal.errors.DegenerateGeometryError` when fewer than
    half of the nodes appear in any pair (they could not be located).
    """
    ii = np.asarray(i)
    jj = np.asarray(j)
    y = np.asarray(ranges, dtype=float)
    if ii.ndim != 1 or jj.shape != ii.shape or y.shape != ii.shape:
        raise InputError(f"i, j and ranges must be 1-D arrays of one length, got shapes "
                         f"{ii.shape}, {jj.shape}, {y.shape}")
    if ii.size and not (np.issubdtype(ii.dtype, np.integer) and np.issubdtype(jj.dtype, np.integer)):
        raise InputError("i and j must be integer node indices")
    if not np.isfinite(y).all():
        raise InputError("ranges must be finite (list only the observed pairs)")
    if ii.size and (ii.min() < 0 or jj.min() < 0):
        raise InputError("node indices must be >= 0")
    if ii.size == 0:
        raise InputError("i, j and ranges are empty: give the observed pairs")
    if y.dtype.kind == "b" or np.asarray(ranges).dtype.kind == "b":
        raise InputError("ranges holds booleans (True / False), not measured ranges")
    I = int(ii.max()) + 1 if I is None else int(I)
    J = int(jj.max()) + 1 if J is None else int(J)
    if ii.size and (ii.max() >= I or jj.max() >= J):
        raise InputError(f"node index out of range for {I} receivers and {J} sources")
    # ~64 float64 per node: positions, offsets, the growth's bookkeeping and the normal blocks
    guard_size(float(I + J) * 8.0 * 64, f"a sparse network of {I} receivers and {J} sources")
    # nodes without a range are never located, and a fit reaching less than half of the
    # nodes is refused (solve_toa_sparse): refuse it before anything the size of I + J is made
    seen = np.unique(ii).size + np.unique(jj).size
    if I + J > 2 * seen:
        raise DegenerateGeometryError(
            f"{I} receivers and {J} sources, but only {seen} of them appear in the {ii.size} pairs: less than "
            f"half of the nodes could be located (check n_receivers / n_sources)", kind="unobservable-node")
    key = ii.astype(np.int64) * J + jj
    if np.unique(key).size != key.size:
        raise InputError("a (receiver, source) pair is listed twice; average repeated ranges first")
    return ii.astype(np.intp), jj.astype(np.intp), y, I, J
