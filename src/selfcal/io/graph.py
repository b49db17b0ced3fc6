"""Reader of a measurement graph: a long-format range file ``from,to,range[,std]``.

One measured range per line, between two named nodes; any node may range to any other
(anchor to anchor, anchor to tag, tag to tag), and a pair may be measured many times (each
line is one measurement; their spread is evidence of the noise). This is the layout UWB
systems log for auto-positioning, and the general form of a range matrix (a matrix is the
graph of all receiver-source pairs).
"""

from __future__ import annotations

import csv
import math
import os
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from ..errors import InputError
from .inputs import _NUMBER, _read_input_bytes

__all__ = ["RangeGraph", "read_range_graph"]

_COLUMNS = ("from", "to", "range", "std")


@dataclass(frozen=True)
class RangeGraph:
    """Measured ranges between named nodes.

    Attributes
    ----------
    names : tuple of str
        Node names in order of first appearance; node ``k`` is ``names[k]``.
    a, b : (m,) int arrays
        The two nodes of each measurement (indices into ``names``), ``a != b``.
    ranges : (m,) float array
        Measured ranges (metres, or the unit the caller converts).
    std : (m,) float array or None
        Per-measurement standard deviation when the file has a ``std`` column.
    """

    names: tuple[str, ...]
    a: NDArray[np.intp]
    b: NDArray[np.intp]
    ranges: NDArray[np.float64]
    std: NDArray[np.float64] | None = None

    @property
    def n_nodes(self) -> int:
        """Number of nodes."""
        return len(self.names)


def read_range_graph(path: str | os.PathLike[str], name: str | None = None) -> RangeGraph:
    """Read a long-format range file ``from,to,range[,std]`` (header required).

    Parameters
    ----------
    path : path or ``"-"``
        A CSV (comma, semicolon or tab separated, UTF-8, ``#`` comments) whose first line
        names the columns ``from``, ``to``, ``range`` and optionally ``std`` (any order,
        case-insensitive; other columns, e.g. a time stamp, are ignored).
    name : str, optional
        Label for the messages (default: the path).

    Returns
    -------
    RangeGraph

    Raises
    ------
    InputError
        No header or a missing column, a non-number or non-finite range, a std that is not
        > 0, a node ranging to itself, an empty node name, fewer than one measurement.

    Examples
    --------
    >>> import tempfile, pathlib
    >>> p = pathlib.Path(tempfile.mkdtemp()) / "g.csv"
    >>> _ = p.write_text("from,to,range\\nA0,A1,4.1\\nA0,A1,4.12\\nA1,T0,2.5\\n")
    >>> g = read_range_graph(p)
    >>> g.names, g.a.tolist(), g.b.tolist(), g.ranges.tolist()
    (('A0', 'A1', 'T0'), [0, 0, 1], [1, 1, 2], [4.1, 4.12, 2.5])
    """
    label = name or os.fspath(path)
    data = _read_input_bytes(path, label)
    if b"\x00" in data[:65536]:
        raise InputError(f"{label}: not a text file (binary data)")
    try:
        text = data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise InputError(f"{label}: not UTF-8 text (byte {exc.start})") from None
    lines = [(k + 1, ln) for k, ln in enumerate(text.splitlines())
             if ln.strip() and not ln.lstrip().startswith("#")]
    if not lines:
        raise InputError(f"{label}: the file is empty")
    head = lines[0][1]
    delim = max((",", ";", "\t"), key=head.count)
    if head.count(delim) == 0:
        raise InputError(f"{label}: the first line must name the columns from,{delim}to,range[,std]")
    rows = list(csv.reader([ln for _, ln in lines], delimiter=delim, skipinitialspace=True))
    cols = [c.strip().lower() for c in rows[0]]
    missing = [c for c in _COLUMNS[:3] if c not in cols]
    if missing:
        raise InputError(f"{label}: the header {rows[0]} lacks the column(s) {', '.join(missing)} "
                         "(a range graph is from,to,range[,std], one measurement per line)")
    k_from, k_to, k_range = (cols.index(c) for c in _COLUMNS[:3])
    k_std = cols.index("std") if "std" in cols else None
    index: dict[str, int] = {}
    a: list[int] = []
    b: list[int] = []
    y: list[float] = []
    s: list[float] = []
    for (ln, _), row in zip(lines[1:], rows[1:], strict=True):
        if len(row) < len(cols):
            raise InputError(f"{label}: line {ln}: {len(row)} fields, the header has {len(cols)}")
        u, v = row[k_from].strip(), row[k_to].strip()
        if not u or not v:
            raise InputError(f"{label}: line {ln}: empty node name")
        if u == v:
            raise InputError(f"{label}: line {ln}: node {u!r} ranges to itself")
        y.append(_number(row[k_range], label, ln, "range"))
        if k_std is not None:
            sd = _number(row[k_std], label, ln, "std")
            if not sd > 0:
                raise InputError(f"{label}: line {ln}: std must be > 0, got {sd:g}")
            s.append(sd)
        a.append(index.setdefault(u, len(index)))
        b.append(index.setdefault(v, len(index)))
    if not y:
        raise InputError(f"{label}: no measurements after the header")
    return RangeGraph(tuple(index), np.array(a, np.intp), np.array(b, np.intp), np.array(y, float),
                      np.array(s, float) if k_std is not None else None)


def _number(cell: str, label: str, ln: int, what: str) -> float:
    c = cell.strip().strip('"').strip()
    if not _NUMBER.match(c):
        raise InputError(f"{label}: line {ln}: {what} {c[:24]!r} is not a number")
    v = float(c)
    if not math.isfinite(v):
        raise InputError(f"{label}: line {ln}: {what} {c[:24]!r} is not finite")
    return v
