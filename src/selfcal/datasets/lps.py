"""Loader for the Lund UWB quadcopter flights (LPS data set, Kalle Astrom, MIT licence).

Each ``dataN.mat`` (MATLAB v5) holds one struct ``data`` with the ranges between 6 fixed
UWB anchors and the positions of a flying tag, motion-capture ground truth, and the data
set authors' own self-calibration. This module only reads and validates; calibration is
:func:`selfcal.toa.solve_toa` (see ``selfcal reproduce lps`` and ``examples/lps_anchors.py``).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..errors import InputError

__all__ = ["LpsData", "load_lps", "lps_files"]

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


def _field(rec: Any, key: str, path: Path) -> Array:
    try:
        return np.asarray(rec[key], dtype=float)
    except (KeyError, ValueError, IndexError):
        raise InputError(f"{path}: field {key!r} missing from the 'data' struct; is this an LPS file?") from None


def lps_files(path: str | os.PathLike[str]) -> list[Path]:
    """The ``data*.mat`` files of an LPS folder, sorted (or ``[path]`` if it is a file)."""
    p = Path(path)
    if p.is_file():
        return [p]
    if not p.is_dir():
        raise FileNotFoundError(2, "No such file or directory", str(p))
    files = sorted(p.glob("data*.mat"))
    if not files:
        raise InputError(f"{p}: no data*.mat files (expected the LPS folder with data4.mat, data5.mat)")
    return files


def load_lps(path: str | os.PathLike[str]) -> LpsData:
    """Read one LPS flight (``data4.mat``, ``data5.mat``, ...).

    Parameters
    ----------
    path: the ``.mat`` file (MATLAB v5, struct ``data`` with fields ``d`` 6 x N,
        ``Gtr`` 3 x 6, ``GTs_resamp`` 3 x N, ``GTs_resamp_ok``, ``ropt``, ``sopt``).

    Returns
    -------
    :class:`LpsData` with points as rows (transposed from the file's column layout).

    Raises
    ------
    InputError: not a MATLAB file of this layout, inconsistent shapes, infinite ranges.
    """
    import scipy.io

    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(2, "No such file or directory", str(p))
    try:
        mat = scipy.io.loadmat(p)
    except Exception as exc:  # scipy raises several types for non-MAT content
        raise InputError(f"{p}: cannot be read as a MATLAB v5 file ({exc})") from None
    if "data" not in mat:
        raise InputError(f"{p}: no 'data' struct; is this an LPS file?")
    rec = mat["data"][0, 0]
    d = _field(rec, "d", p)
    G = _field(rec, "Gtr", p)
    T = _field(rec, "GTs_resamp", p)
    ropt = _field(rec, "ropt", p)
    sopt = _field(rec, "sopt", p)
    m, n = d.shape
    if G.shape != (3, m) or T.shape != (3, n) or ropt.shape != (3, m) or sopt.shape != (3, n):
        raise InputError(
            f"{p}: inconsistent shapes d {d.shape}, Gtr {G.shape}, GTs_resamp {T.shape}, "
            f"ropt {ropt.shape}, sopt {sopt.shape}"
        )
    # a few raw ranges are slightly negative (biased UWB ranges with the tag next to an
    # anchor); they are kept as measured, only inf is refused
    if np.isinf(d).any():
        raise InputError(f"{p}: ranges contain inf")
    tag = T.T.copy()
    try:
        ok = np.asarray(rec["GTs_resamp_ok"]).astype(bool)
        tag[~ok.all(axis=0)] = np.nan
    except (KeyError, ValueError):
        pass
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
