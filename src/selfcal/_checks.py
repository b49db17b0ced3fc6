"""Input validation shared by every entry point.

These helpers raise :class:`~selfcal.errors.InputError` (malformed data) or
:class:`~selfcal.errors.DegenerateGeometryError` (data that cannot determine the
unknowns) with messages that name the argument and the fix.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from .errors import DegenerateGeometryError, InputError

__all__ = [
    "as_matrix",
    "as_points",
    "check_dim",
    "check_choice",
    "check_positive",
    "as_rng",
    "min_counts_toa",
    "check_toa_counts",
]


def as_matrix(
    value: Any,
    name: str = "matrix",
    *,
    allow_nan: bool = True,
    nonnegative: bool = False,
    min_shape: tuple[int, int] = (1, 1),
) -> NDArray[np.float64]:
    """Convert ``value`` to a float (rows, cols) matrix and validate it.

    NaN is allowed only as "missing" (``allow_nan``); +-inf is always refused.
    With ``nonnegative`` every finite entry must be >= 0 (ranges, times of flight).
    """
    try:
        arr = np.array(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{name}: cannot be read as a numeric matrix ({exc})") from None
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
    if nonnegative and (arr[~nan] < 0).any():
        i, j = np.argwhere(np.where(nan, 0.0, arr) < 0)[0]
        raise InputError(f"{name}: entry ({i}, {j}) = {arr[i, j]:g} is negative; ranges and times of flight must be >= 0")
    return arr


def as_points(value: Any, name: str = "points", *, dim: int | None = None, allow_nan: bool = False) -> NDArray[np.float64]:
    """Convert ``value`` to an (n, d) float array of points, d in {2, 3} (or ``dim``)."""
    try:
        arr = np.array(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{name}: cannot be read as points ({exc})") from None
    if arr.ndim != 2:
        raise InputError(f"{name}: expected an (n, d) array of points, got shape {arr.shape}")
    d = arr.shape[1]
    if dim is not None and d != dim:
        raise InputError(f"{name}: points have {d} coordinates, expected {dim}")
    if d not in (2, 3):
        raise InputError(f"{name}: points must have 2 or 3 coordinates, got {d}")
    if np.isinf(arr).any() or (not allow_nan and np.isnan(arr).any()):
        raise InputError(f"{name}: contains NaN or inf")
    return arr


def check_dim(dim: int) -> int:
    """Return ``dim`` if it is 2 or 3, else raise :class:`InputError`."""
    if dim not in (2, 3):
        raise InputError(f"dim must be 2 or 3, got {dim!r}")
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
    """Normalise an ``rng`` argument (Generator, seed or None) to a Generator."""
    if isinstance(rng, np.random.Generator):
        return rng
    if rng is None or isinstance(rng, (int, np.integer)):
        return np.random.default_rng(rng)
    raise InputError(f"rng must be a numpy Generator, an int seed or None, got {type(rng).__name__}")


def min_counts_toa(dim: int, offsets: str) -> tuple[int, int]:
    """Minimal (receivers, transmitters) for anchor-free TOA self-calibration.

    Counting argument: an I x J range matrix gives at most I*J equations; unknowns
    are d*(I+J) coordinates minus the d(d+1)/2 gauge freedoms of a rigid motion,
    plus I and/or J offsets (minus one common shift when both kinds are present).
    The classical minimal configurations (Kuang, Burgess, Torstensson & Astrom
    2013) for ``offsets="none"`` are 3 x 3 in 2D (with one more row or column for
    a finite solution set in practice) and 4 x 6 / 6 x 4 in 3D. We require at
    least d+1 nodes on each side so that the positions span the space, and then
    the count of equations >= unknowns.
    """
    base = dim + 1
    return base, base


def _toa_unknowns(I: int, J: int, dim: int, offsets: str) -> int:
    gauge = dim * (dim + 1) // 2
    n = dim * (I + J) - gauge
    if offsets in ("receivers", "both"):
        n += I
    if offsets in ("sources", "both"):
        n += J
    if offsets == "both":
        n -= 1  # a common shift between the two kinds of offsets is unobservable
    return n


def check_toa_counts(shape: tuple[int, int], n_observed: int, dim: int, offsets: str) -> None:
    """Raise :class:`DegenerateGeometryError` when an I x J TOA problem is under-determined.

    The condition is ``I >= d+1``, ``J >= d+1`` and ``observed entries >= unknowns``
    where ``unknowns = d(I+J) - d(d+1)/2 + [I] + [J] - [both]`` (see
    :func:`min_counts_toa`).
    """
    I, J = shape
    r_min, s_min = min_counts_toa(dim, offsets)
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
    unknowns = _toa_unknowns(I, J, dim, offsets)
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
