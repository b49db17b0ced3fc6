"""Loader for the Lund UWB quadcopter flights (LPS data set, Kalle Astrom, MIT licence).

Each ``dataN.mat`` (MATLAB v5) holds one struct ``data`` with the ranges between 6 fixed
UWB anchors and the positions of a flying tag, motion-capture ground truth, and the data
set authors' own self-calibration. This module only reads and validates; calibration is
:func:`selfcal.toa.solve_toa` (see ``selfcal reproduce lps`` and ``examples/lps_anchors.py``).
"""

from __future__ import annotations

import os
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .._checks import entry
from ..errors import InputError

__all__ = ["LpsData", "LpsFormatWarning", "load_lps", "lps_files"]

Array = NDArray[np.float64]


@dataclass(frozen=True)
class LpsData:
    """One LPS flight.

    Attributes
    ----------
    ranges: (6, N) measured anchor-tag ranges in metres, rows = anchors (receivers),
        columns = tag positions (transmitters), NaN = missing. The UWB ranges carry a
        per-anchor bias of roughly -0.1 to -0.25 m, so a few raw values are negative.
    anchors_true: (6, 3) motion-capture anchor positions (m).
    tag_true: (N, 3) motion-capture tag positions at the range times (m); rows where the
        data set flags the resampled ground truth as invalid (``GTs_resamp_ok``) are NaN.
    authors_anchors: (6, 3) the data set authors' estimate (``ropt``): comparison only.
    authors_tag: (N, 3) the authors' tag estimate (``sopt``): comparison only.
    name: file stem, e.g. ``"data4"``.
    description: the file's own description string.
    """

    ranges: Array
    anchors_true: Array
    tag_true: Array
    authors_anchors: Array
    authors_tag: Array
    name: str
    description: str

    @property
    def n_positions(self) -> int:
        """Number of tag positions N."""
        return int(self.ranges.shape[1])

    def to_dict(self) -> dict[str, Any]:
        """JSON-safe summary (not the raw arrays)."""
        return {
            "name": self.name,
            "description": self.description,
            "n_anchors": int(self.ranges.shape[0]),
            "n_positions": self.n_positions,
            "missing_fraction": float(np.isnan(self.ranges).mean()),
        }


class LpsFormatWarning(UserWarning):
    """An LPS file deviates from the documented layout in a way the loader can repair."""


def _field(rec: Any, key: str, path: Path) -> Array:
    try:
        raw = np.asarray(rec[key])
    except (KeyError, ValueError, IndexError, TypeError):
        raise InputError(f"{path}: field {key!r} missing from the 'data' struct; is this an LPS file?") from None
    if np.iscomplexobj(raw):
        raise InputError(f"{path}: field {key!r} is complex; ranges and positions must be real numbers")
    try:
        return np.asarray(raw, dtype=float)
    except (ValueError, TypeError):
        raise InputError(f"{path}: field {key!r} is not numeric") from None


def _has(rec: Any, key: str) -> bool:
    names = getattr(getattr(rec, "dtype", None), "names", None)
    return key in names if names is not None else key in rec


def _optional(rec: Any, key: str, shape: tuple[int, int], path: Path, what: str) -> Array:
    """A comparison-only field, or NaN of ``shape`` with a :class:`LpsFormatWarning` if absent."""
    if _has(rec, key):
        return _field(rec, key, path)
    warnings.warn(f"{path}: no {key!r} ({what}); it is NaN in the result and not scored",
                  LpsFormatWarning, stacklevel=3)
    return np.full(shape, np.nan)


def _fit_columns(a: Array, n: int, key: str, path: Path) -> Array:
    """A 3 x k per-position field matched to the n columns of ``d`` (NaN-padded or cut)."""
    if a.ndim != 2 or a.shape[0] != 3:
        raise InputError(f"{path}: field {key!r} must be 3 x N (one column per tag position), got {a.shape}")
    k = a.shape[1]
    if k == n:
        return a
    warnings.warn(
        f"{path}: {key!r} has {k} columns but 'd' has {n}; "
        + (f"the last {n - k} positions have no {key} (NaN)" if k < n else f"the extra {k - n} are ignored"),
        LpsFormatWarning, stacklevel=3)
    out = np.full((3, n), np.nan)
    out[:, : min(k, n)] = a[:, : min(k, n)]
    return out


def _validity(rec: Any, n: int, path: Path) -> NDArray[np.bool_] | None:
    """(n,) validity of the resampled ground truth from ``GTs_resamp_ok`` (None if absent).

    The flag may be 1 x N, 3 x N (per coordinate: valid when all three are) or a vector.
    Positions beyond its length are taken as invalid (their ground truth is NaN), with a
    :class:`LpsFormatWarning`; extra flags are ignored.
    """
    try:
        raw = np.asarray(rec["GTs_resamp_ok"])
    except (KeyError, ValueError, IndexError):
        return None
    try:
        ok = raw.astype(bool)
    except (TypeError, ValueError):
        raise InputError(f"{path}: 'GTs_resamp_ok' is not a logical array") from None
    if ok.ndim == 2 and ok.shape[0] in (1, 3) and not (ok.shape[1] in (1, 3) and ok.shape[0] == n):
        ok = np.asarray(ok.all(axis=0))
    elif ok.ndim == 2 and ok.shape[1] in (1, 3):
        ok = np.asarray(ok.all(axis=1))
    ok = ok.ravel()
    k = ok.size
    if k != n:
        warnings.warn(
            f"{path}: 'GTs_resamp_ok' has {k} entries but 'd' has {n} positions; "
            + (f"the last {n - k} are treated as invalid ground truth" if k < n else f"the extra {k - n} are ignored"),
            LpsFormatWarning, stacklevel=3)
        full = np.zeros(n, bool)
        full[: min(k, n)] = ok[: min(k, n)]
        ok = full
    return ok


def lps_files(path: str | os.PathLike[str]) -> list[Path]:
    """The ``data*.mat`` files of an LPS folder, sorted (or ``[path]`` if it is a file)."""
    p = Path(path)
    if p.is_file():
        return [p]
    if not p.is_dir():
        if p.exists():  # /dev/null, a FIFO, a socket
            raise InputError(f"{p}: not a regular file or a folder of data*.mat files")
        raise FileNotFoundError(2, "No such file or directory", str(p))
    files = sorted(p.glob("data*.mat"))
    if not files:
        raise InputError(f"{p}: no data*.mat files (expected the LPS folder with data4.mat, data5.mat)")
    return files


@entry(path="path")
def load_lps(path: str | os.PathLike[str]) -> LpsData:
    """Read one LPS flight (``data4.mat``, ``data5.mat``, ...).

    Parameters
    ----------
    path: the ``.mat`` file (MATLAB v5, struct ``data`` with fields ``d`` 6 x N,
        ``Gtr`` 3 x 6, ``GTs_resamp`` 3 x N, ``GTs_resamp_ok``, ``ropt``, ``sopt``; the same
        fields as top-level variables are read too). Required: ``d`` and ``Gtr``.

    Returns
    -------
    :class:`LpsData` with points as rows (transposed from the file's column layout).

    Raises
    ------
    InputError: not a MATLAB file of this layout, anchor fields (``Gtr``, ``ropt``) that do
        not match the rows of ``d``, infinite ranges. Never a bare ``IndexError``.

    Warns
    -----
    LpsFormatWarning: a comparison field absent (``GTs_resamp``, ``ropt``, ``sopt``: NaN in
        the result, not scored; the ranges are what is calibrated), or a per-position field
        (``GTs_resamp``, ``GTs_resamp_ok``, ``sopt``) whose length differs from the columns
        of ``d``. Only ground truth and the
        authors' estimate are affected, never the ranges: the loader keeps every range,
        marks positions without a validity flag (or ground truth) as NaN ground truth and
        ignores extra entries (decision: a shorter flag array is common in exported
        flights and is not a reason to refuse the measurements).
    """
    import scipy.io

    p = Path(path)
    if not p.is_file():
        if p.exists():
            raise InputError(f"{p}: not a regular file (a .mat flight of the LPS set)")
        raise FileNotFoundError(2, "No such file or directory", str(p))
    try:
        mat = scipy.io.loadmat(p)
    except Exception as exc:  # scipy raises several types for non-MAT content
        raise InputError(f"{p}: cannot be read as a MATLAB v5 file ({exc})") from None
    rec: Any
    if "data" in mat:
        try:
            rec = mat["data"][0, 0]
            rec.dtype.names[0]  # a MATLAB struct (record array)
        except (IndexError, TypeError, AttributeError):
            raise InputError(f"{p}: 'data' is not a 1 x 1 MATLAB struct; is this an LPS file?") from None
    elif "d" in mat and "Gtr" in mat:
        rec = mat  # the same fields saved as top-level variables (save(f, 'd', 'Gtr', ...))
    else:
        raise InputError(f"{p}: no 'data' struct (nor top-level 'd' and 'Gtr'); is this an LPS file?")
    d = _field(rec, "d", p)
    G = _field(rec, "Gtr", p)
    if d.ndim != 2 or d.shape[0] < 1 or d.shape[1] < 1:
        raise InputError(f"{p}: field 'd' must be a (anchors x positions) matrix, got shape {d.shape}")
    m, n = d.shape
    if G.ndim == 2 and G.shape[0] == 3 and G.shape[1] == n and n != m:
        raise InputError(f"{p}: 'd' is {d.shape} but Gtr has {n} anchors: 'd' looks transposed "
                         f"(it must be anchors x positions, {n} x {m})")
    T = _optional(rec, "GTs_resamp", (3, n), p, "ground-truth tag positions")
    ropt = _optional(rec, "ropt", (3, m), p, "the authors' anchor estimate")
    sopt = _optional(rec, "sopt", (3, n), p, "the authors' tag estimate")
    if G.shape != (3, m) or ropt.shape != (3, m):
        raise InputError(
            f"{p}: inconsistent shapes d {d.shape}, Gtr {G.shape}, ropt {ropt.shape} "
            f"(expected Gtr and ropt 3 x {m}, one column per anchor)"
        )
    # per-position comparison fields shorter / longer than d: pad with NaN / cut, and say so
    T = _fit_columns(T, n, "GTs_resamp", p)
    sopt = _fit_columns(sopt, n, "sopt", p)
    # a few raw ranges are slightly negative (biased UWB ranges with the tag next to an
    # anchor); they are kept as measured, only inf is refused
    if np.isinf(d).any():
        raise InputError(f"{p}: ranges contain inf")
    tag = T.T.copy()
    ok = _validity(rec, n, p)
    if ok is not None:
        tag[~ok] = np.nan
    desc = ""
    try:
        desc = str(np.asarray(rec["description"]).ravel()[0])
    except (KeyError, ValueError, IndexError):
        pass
    return LpsData(
        ranges=d.copy(),
        anchors_true=G.T.copy(),
        tag_true=tag,
        authors_anchors=ropt.T.copy(),
        authors_tag=sopt.T.copy(),
        name=p.stem,
        description=desc,
    )
