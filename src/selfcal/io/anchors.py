"""The installer's anchor file: the anchor set in the room frame with its error bars.

Two forms, chosen by the suffix: CSV ``name,x,y,z,std_x,std_y,std_z`` (metres; one anchor
per line, an empty std = not determined), and JSON for an anchor configuration tool::

    {"format": "selfcal-anchors/1", "units": "m", "frame": "...",
     "anchors": [{"name": "A0", "position": [x, y, z], "std": [sx, sy, sz]}, ...]}

Positions are in the frame of the calibration (``--known`` / ``--frame``: the room, z up
when the user's coordinates are); a frame that is not the user's (canonical gauge) is
named in ``"frame"``.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..errors import InputError
from .outputs import write_csv_rows, write_json

__all__ = ["ANCHOR_FORMAT", "write_anchors"]

#: the ``"format"`` tag of the JSON form
ANCHOR_FORMAT = "selfcal-anchors/1"

_AXES = "xyz"


def write_anchors(path: str | os.PathLike[str], names: Sequence[str], positions: Any, cov: Any = None, *,
                  frame: str = "") -> None:
    """Write anchors as CSV (``name,x,y,z,std_x,std_y,std_z``) or JSON (suffix ``.json``).

    Parameters
    ----------
    path : path
        ``.json`` writes the JSON form, anything else the CSV form (atomically).
    names : sequence of str
        One name per anchor.
    positions : (k, d) array
        Metres, in the calibration's frame.
    cov : (k, d, d) array, optional
        Covariances (m^2); the std per axis is the square root of the diagonal.
    frame : str
        One line saying which frame the positions are in.

    Raises
    ------
    InputError
        ``names`` and ``positions`` of different lengths.

    Examples
    --------
    >>> import tempfile, pathlib, numpy as np
    >>> p = pathlib.Path(tempfile.mkdtemp()) / "anchors.csv"
    >>> write_anchors(p, ["A0"], np.array([[1.0, 2.0, 3.0]]), np.eye(3)[None] * 1e-4)
    >>> p.read_text().splitlines()
    ['name,x,y,z,std_x,std_y,std_z', 'A0,1.0,2.0,3.0,0.01,0.01,0.01']
    """
    P = np.atleast_2d(np.asarray(positions, float))
    if len(names) != P.shape[0]:
        raise InputError(f"{len(names)} anchor names for {P.shape[0]} positions")
    d = P.shape[1]
    S: NDArray[np.float64]
    if cov is None:
        S = np.full(P.shape, np.nan)
    else:
        diag = np.diagonal(np.asarray(cov, float), axis1=1, axis2=2)
        S = np.sqrt(np.where(diag >= 0, diag, np.nan))
    axes = list(_AXES[:d])
    if Path(os.fspath(path)).suffix.lower() == ".json":
        doc = {"format": ANCHOR_FORMAT, "units": "m", "frame": frame,
               "anchors": [{"name": str(n), "position": [_num(v) for v in p], "std": [_num(v) for v in s]}
                           for n, p, s in zip(names, P, S, strict=True)]}
        write_json(path, doc)
        return
    write_csv_rows(path, ["name", *axes, *[f"std_{a}" for a in axes]],
                   [[str(n), *map(float, p), *map(float, s)] for n, p, s in zip(names, P, S, strict=True)])


def _num(v: float) -> float | None:
    return float(v) if np.isfinite(v) else None
