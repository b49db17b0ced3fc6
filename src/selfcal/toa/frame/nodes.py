"""The user's nodes for a TOA frame: names, known-position files, result records.

What :mod:`selfcal.toa.frame.frame` (reference frames) and :mod:`selfcal.toa.frame.known` (known
positions) share: :class:`KnownNode`, :class:`FrameInfo` (what the references fixed and
what they left undetermined), :class:`FramedToaResult`, the node names
(:func:`resolve_node`: ``r<i>``, ``s<j>``, a bare receiver index, or a name from the
node-name lists), the parsers of ``--known FILE.csv`` (:func:`read_known_csv`,
:func:`parse_known`) and of ``--frame origin=A,x=B,xy=C[,z=D]`` (:func:`parse_frame`), and
small helpers on result objects. The public names are re-exported by
:mod:`selfcal.toa.frame.frame`.
"""

from __future__ import annotations

import csv
import dataclasses
import os
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..._result import WrappedResult, replace_fields
from ...errors import InputError

__all__ = ["FrameInfo", "FramedToaResult", "KnownNode", "check_frame", "check_known_scale", "node_names",
           "node_positions", "offsets_of",
           "parse_frame", "parse_known",
           "read_known_csv", "RefitData", "refit_data", "replace_fields", "resolve_node", "units"]

Array = NDArray[np.float64]


@dataclass(frozen=True)
class KnownNode:
    """One node with a known position, or some known coordinates of it.

    Attributes
    ----------
    name: the name it was given by.
    kind: "receiver" or "source".
    index: row (receiver) or column (source) index of the range matrix.
    position: (d,) metres in the user's frame; NaN where the coordinate is not known
        (``A3,,,2.41``: only the height known).
    std: isotropic standard deviation of each known coordinate (m), or None for exact ones.
    """

    name: str
    kind: str
    index: int
    position: Array
    std: float | None = None

    @property
    def mask(self) -> NDArray[np.bool_]:
        """(d,) bool: which coordinates are known."""
        return np.isfinite(np.asarray(self.position, float))

    @property
    def full(self) -> bool:
        """Every coordinate known."""
        return bool(self.mask.all())


@dataclass(frozen=True)
class FrameInfo:
    """How the result was put in the user's frame, and what stayed undetermined.

    Attributes
    ----------
    kind: "canonical" (no frame asked), "known" or "reference".
    references: names of the nodes that define the frame.
    rank: affine rank of the references (0 = one point, d = full); where known nodes give
        only some coordinates, the number of frame axes they fix (``axes_fixed``).
    determined: True when rotation, translation and mirror are all fixed by them.
    residual_gauge: continuous freedoms the references leave (0 when determined or only
        the mirror is left); those are held at the blind solution's canonical gauge.
    mirror_resolved: whether the mirror image is fixed by the references.
    message: one line saying what was fixed, and what choice was taken where not.
    known_rms: RMS (m) of known-minus-estimated positions over the known nodes after the
        rigid alignment of the blind solution (before the constrained fit): a check of
        the known coordinates against the ranges; None for kind != "known". Where some
        nodes give only some coordinates: the RMS over the known coordinates.
    known_rms_fit: the same after the constrained fit (0 for exact nodes).
    known_test: the test of the known positions against the ranges
        (:class:`selfcal.toa.verdict.known_test.KnownTest` as a dict), None for kind != "known".
    axes_fixed: the frame axes whose direction and origin the known coordinates fix
        (``("z",)`` when only heights are known: the room's z, horizontal axes canonical);
        None where not computed (kind != "known").
    error_scale: the block jackknife's scale of the receivers' covariances
        (:meth:`selfcal.toa.verdict.jackknife.JackknifeScale.to_dict`), None when not run.
    """

    kind: str
    references: tuple[str, ...] = ()
    rank: int = 0
    determined: bool = False
    residual_gauge: int = 0
    mirror_resolved: bool = False
    message: str = ""
    known_rms: float | None = None
    known_rms_fit: float | None = None
    known_test: dict[str, Any] | None = None
    axes_fixed: tuple[str, ...] | None = None
    error_scale: dict[str, Any] | None = None

    def to_dict(self) -> dict[str, Any]:
        """JSON-safe dictionary."""
        return dataclasses.asdict(self) | {"references": list(self.references),
                                           "axes_fixed": None if self.axes_fixed is None else list(self.axes_fixed)}


@dataclass(frozen=True, repr=False)
class FramedToaResult(WrappedResult):
    """A :class:`selfcal.toa.solve.ToaResult` in the user's frame plus its :class:`FrameInfo`.

    Every attribute of the wrapped result (``receivers``, ``sources``, covariances, ...)
    is available directly; ``to_dict()`` adds the key ``"frame"``. A
    :class:`~selfcal._result.WrappedResult`: status, summary and dict follow the
    :class:`~selfcal._result.Result` convention.
    """

    frame: FrameInfo = field(default_factory=lambda: FrameInfo("canonical"))

    def to_dict(self) -> dict[str, Any]:
        """The wrapped result's dictionary with ``"frame"`` added."""
        out = dict(self.result.to_dict())
        out["frame"] = self.frame.to_dict()
        return out


def resolve_node(token: Any, I: int, J: int, receiver_names: Sequence[str] | None = None,
                 source_names: Sequence[str] | None = None) -> tuple[str, int]:
    """Map a node reference to ``("receiver" | "source", index)``.

    Accepted: a name of ``receiver_names`` / ``source_names``; ``r<i>`` / ``s<j>``
    (0-based); a bare integer (receiver index).
    """
    t = str(token).strip()
    for names in (receiver_names, source_names):
        if names is not None and list(names).count(t) > 1:
            raise InputError(f"node name {t!r} names {list(names).count(t)} nodes of the input; "
                             "names must be unique to be used")
    if receiver_names is not None and t in receiver_names:
        if source_names is not None and t in source_names:
            raise InputError(f"node name {t!r} is both a receiver and a source name")
        return "receiver", list(receiver_names).index(t)
    if source_names is not None and t in source_names:
        return "source", list(source_names).index(t)
    m = re.fullmatch(r"([rs]?)(\d+)", t, flags=re.IGNORECASE)
    if m is None:
        given = [n for names in (receiver_names, source_names) if names is not None for n in names]
        shown = ", ".join(given[:8]) + (", ..." if len(given) > 8 else "")
        raise InputError(f"unknown node {t!r}: use r<i> (receiver i), s<j> (source j), a receiver "
                         "index" + (f", or a node name of the input ({shown})" if given else
                                    " (the input names no nodes)"))
    kind = "source" if m.group(1).lower() == "s" else "receiver"
    k = int(m.group(2))
    n = J if kind == "source" else I
    if k >= n:
        raise InputError(f"node {t!r}: {kind} index {k} out of range (there are {n} {kind}s, 0-based)")
    return kind, k


def node_names(row_names: Sequence[str] | None, col_names: Sequence[str] | None, I: int, J: int
               ) -> dict[str, tuple[str, ...]]:
    """The names of a range matrix's nodes: its own, else 0-based ``r<i>`` / ``s<j>``.

    Parameters
    ----------
    row_names, col_names : names read with the matrix (first column / header row), or None.
    I, J : number of receivers (rows) and sources (columns).

    Returns
    -------
    ``{"receiver_names": (...), "source_names": (...)}``, the keyword arguments of
    :func:`parse_known`, :func:`resolve_node` and :func:`selfcal.toa.frame.frame.apply_frame`,
    and the keys the result JSON and CSV carry, so that a node has one name everywhere.

    Examples
    --------
    >>> node_names(("A0", "A1"), None, 2, 3)["source_names"]
    ('s0', 's1', 's2')
    """
    rn = tuple(row_names) if row_names is not None and len(row_names) == I else tuple(f"r{i}" for i in range(I))
    cn = tuple(col_names) if col_names is not None and len(col_names) == J else tuple(f"s{j}" for j in range(J))
    return {"receiver_names": rn, "source_names": cn}


def check_frame(frame: str | Mapping[str, Any], I: int, J: int, *, receiver_names: Sequence[str] | None = None,
                source_names: Sequence[str] | None = None) -> dict[str, tuple[str, int]]:
    """Parse ``--frame`` and resolve its nodes before any work: ``{role: (kind, index)}``.

    Raises
    ------
    InputError
        A malformed frame or a node the input does not have (named in the message).
    """
    roles = parse_frame(frame)
    return {k: resolve_node(v, I, J, receiver_names, source_names) for k, v in roles.items()}


def read_known_csv(path: str | os.PathLike[str], dim: int = 3, *, partial: bool = True
                   ) -> dict[str, tuple[float, ...]]:
    """Read known node positions from a CSV file ``name,x,y,z[,std]`` (metres).

    One node per line. An optional header line names the columns (``name,x,y,z,std``;
    ``z`` absent in 2-D). Without a header the columns are ``name`` then ``dim``
    coordinates then an optional ``std``; an empty or absent ``std`` means exact.
    An empty coordinate is one not known: ``A3,,,2.41`` gives only A3's height (the
    fit holds that coordinate, the others stay free); at least one coordinate per line.
    Lines starting with ``#`` and blank lines are skipped. ``partial=False``: every
    coordinate must be given (for the commands that take whole positions).

    Returns
    -------
    ``{name: (x, y[, z][, std])}`` suitable for ``known=`` of :func:`calibrate_in_frame`
    (a tuple of ``dim + 1`` values carries a std; NaN = coordinate not known).

    Raises
    ------
    InputError: unreadable file, wrong number of columns, non-numeric or non-finite
        values, no coordinate on a line, negative std, duplicated names.

    Examples
    --------
    >>> import tempfile, pathlib
    >>> f = pathlib.Path(tempfile.mkdtemp()) / "known.csv"
    >>> _ = f.write_text("name,x,y,z\\nA0,0,0,2.4\\nA3,,,2.41\\n")
    >>> read_known_csv(f)["A3"]
    (nan, nan, 2.41)
    """
    p = Path(path)
    if not p.is_file():
        raise InputError(f"{p}: known-positions file not found (or not a regular file)")
    try:
        text = p.read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"{p}: cannot be read as a text CSV ({exc})") from None
    rows = [r for r in csv.reader(text.splitlines()) if r and not r[0].lstrip().startswith("#")
            and any(c.strip() for c in r)]
    if not rows:
        raise InputError(f"{p}: no known positions")
    axes = ["x", "y", "z"][:dim]
    cols: list[str] = ["name"] + axes + ["std"]
    first = [c.strip().lower() for c in rows[0]]
    if first and first[0] == "name":
        if any(c not in ("name", "x", "y", "z", "std") for c in first) or len(set(first)) != len(first):
            raise InputError(f"{p}: header {rows[0]} must name columns among name,x,y,z,std")
        if dim == 2 and "z" in first:
            raise InputError(f"{p}: the header has a z column but the calibration is 2-D")
        if any(a not in first for a in axes):
            raise InputError(f"{p}: header {rows[0]} lacks one of {','.join(axes)} (leave a value empty "
                             "for a coordinate that is not known)")
        cols = first
        rows = rows[1:]
        header = True
    else:
        header = False
    out: dict[str, tuple[float, ...]] = {}
    for ln, row in enumerate(rows, start=2 if header else 1):
        vals = [c.strip() for c in row]
        if len(vals) not in (dim + 1, dim + 2) or len(vals) > len(cols):
            raise InputError(f"{p}: line {ln}: expected name,{','.join(axes)}[,std], got {len(vals)} fields")
        if not header and dim == 2 and len(vals) == 4:
            raise InputError(f"{p}: line {ln}: 4 fields in a 2-D calibration are ambiguous (x,y,std or "
                             "x,y,z?); add a header line name,x,y,std")
        rec = dict(zip(cols, vals, strict=False))
        name = rec["name"]
        if not name:
            raise InputError(f"{p}: line {ln}: empty node name")
        if name in out:
            raise InputError(f"{p}: line {ln}: node {name!r} given twice")
        try:
            xyz = [float(rec[a]) if rec.get(a, "") != "" else float("nan") for a in axes]
            std = float(rec["std"]) if rec.get("std", "") != "" else None
        except ValueError:
            raise InputError(f"{p}: line {ln}: non-numeric value in {row}") from None
        given = [a for a in axes if rec.get(a, "") != ""]
        if not given:
            raise InputError(f"{p}: line {ln}: node {name!r} has no coordinate (give at least one of "
                             f"{','.join(axes)}; an empty field is a coordinate not known)")
        if not partial and len(given) < dim:
            raise InputError(f"{p}: line {ln}: node {name!r} lacks a coordinate; this command takes whole "
                             f"positions ({','.join(axes)}); only calibrate toa --known fits partly known nodes")
        if not np.all(np.isfinite([v for v, a in zip(xyz, axes, strict=True) if a in given])) or (
                std is not None and not (np.isfinite(std) and std >= 0)):
            raise InputError(f"{p}: line {ln}: coordinates must be finite and std >= 0")
        out[name] = tuple(xyz) + (() if std is None or std == 0 else (std,))
    return out


def parse_known(known: Any, I: int, J: int, dim: int, *, receiver_names: Sequence[str] | None = None,
                source_names: Sequence[str] | None = None, partial: bool = True) -> list[KnownNode]:
    """Validate ``known=`` into :class:`KnownNode` records.

    ``known``: a mapping ``{node: (x, y[, z][, std])}`` (std in metres; absent or 0 =
    exact; NaN or None = a coordinate not known, e.g. ``(nan, nan, 2.41)`` a known
    height), a path to a CSV file (:func:`read_known_csv`), or a list of
    :class:`KnownNode`. ``partial=False``: every coordinate must be given (for fits that
    take whole positions only).

    Raises
    ------
    InputError: unknown node names, a node given twice, a node without any coordinate,
        partial coordinates where ``partial=False``.
    """
    if isinstance(known, (str, os.PathLike)):
        known = read_known_csv(known, dim)
    if isinstance(known, Sequence) and all(isinstance(k, KnownNode) for k in known):
        nodes = list(known)
    elif isinstance(known, Mapping):
        nodes = []
        for name, value in known.items():
            try:
                v = np.array([np.nan if x is None else x for x in np.ravel(np.asarray(value, dtype=object))],
                             dtype=float)
            except (TypeError, ValueError):
                raise InputError(f"known node {name!r}: expected {dim} coordinates and an optional std, "
                                 f"got {value!r}") from None
            if v.size not in (dim, dim + 1) or not np.isfinite(v[:dim]).any() or (
                    v.size == dim + 1 and not np.isfinite(v[dim])):
                raise InputError(f"known node {name!r}: expected {dim} coordinates (NaN = not known, at least "
                                 f"one given) and an optional std, got {value!r}")
            std = float(v[dim]) if v.size == dim + 1 else None
            if std is not None and std < 0:
                raise InputError(f"known node {name!r}: std must be >= 0, got {std}")
            kind, idx = resolve_node(name, I, J, receiver_names, source_names)
            nodes.append(KnownNode(str(name), kind, idx, v[:dim].copy(), None if not std else std))
    else:
        raise InputError("known must be a mapping {node: (x, y, z[, std])}, a CSV path or a list of KnownNode")
    seen = set()
    for n in nodes:
        if (n.kind, n.index) in seen:
            raise InputError(f"known node {n.name!r} ({n.kind} {n.index}) given twice")
        seen.add((n.kind, n.index))
        if np.asarray(n.position).shape != (dim,):
            raise InputError(f"known node {n.name!r}: position must have {dim} coordinates")
        if not n.mask.any():
            raise InputError(f"known node {n.name!r}: no coordinate given")
        if not partial and not n.full:
            raise InputError(f"known node {n.name!r}: only some coordinates given; this fit takes whole "
                             f"positions ({dim} coordinates per node)")
    if not nodes:
        raise InputError("known: no nodes given")
    return nodes


#: known coordinates may spread at most this many times the triangle-inequality bound
#: ``2 max range`` (two nodes ranging to a common partner are at most that far apart): the
#: margin leaves offsets and missing partners room; a unit mistake (cm, mm) is 100-1000x
KNOWN_SCALE_MARGIN = 10.0


def check_known_scale(nodes: Sequence[KnownNode], max_range: float) -> None:
    """Refuse known coordinates whose spread points at a unit mistake (the file is metres).

    Parameters
    ----------
    nodes: from :func:`parse_known`.
    max_range: the largest range of the input (metres).

    Raises
    ------
    InputError
        Along some axis the known coordinates spread beyond :data:`KNOWN_SCALE_MARGIN`
        times ``2 max_range``.

    Examples
    --------
    >>> import numpy as np
    >>> n = [KnownNode("A0", "receiver", 0, np.array([np.nan, np.nan, 2900.0])),
    ...      KnownNode("A1", "receiver", 1, np.array([np.nan, np.nan, 300.0]))]
    >>> check_known_scale(n, 8.0)
    Traceback (most recent call last):
    ...
    selfcal.errors.InputError: known coordinates spread 2600 m along z but the largest range is 8 m: the known file is in metres (a unit mistake?)
    """
    if not nodes or not np.isfinite(max_range) or max_range <= 0:
        return
    P = np.array([np.asarray(k.position, float) for k in nodes])
    for c in range(P.shape[1]):
        v = P[:, c][np.isfinite(P[:, c])]
        if v.size >= 2 and float(np.ptp(v)) > KNOWN_SCALE_MARGIN * 2.0 * max_range:
            raise InputError(f"known coordinates spread {float(np.ptp(v)):.4g} m along {'xyz'[c]} but the largest "
                             f"range is {max_range:.4g} m: the known file is in metres (a unit mistake?)")


_ROLES = ("origin", "x", "xy", "z")


def parse_frame(spec: str | Mapping[str, Any]) -> dict[str, str]:
    """Parse ``"origin=A,x=B,xy=C[,z=D]"`` (or a mapping) into ``{role: node}``.

    ``origin`` and ``x`` are required; ``xy`` is required in 3-D (checked by
    :func:`apply_frame`); ``z`` is an optional fourth reference fixing the z sign in 3-D.
    """
    if isinstance(spec, Mapping):
        items = {str(k).strip(): str(v).strip() for k, v in spec.items()}
    else:
        items = {}
        for part in str(spec).split(","):
            if not part.strip():
                continue
            if "=" not in part:
                raise InputError(f"frame: {part!r} is not role=node (roles: {', '.join(_ROLES)})")
            k, v = part.split("=", 1)
            k, v = k.strip().lower(), v.strip()
            if k in items:
                raise InputError(f"frame: role {k!r} given twice")
            items[k] = v
    bad = [k for k in items if k not in _ROLES]
    if bad:
        raise InputError(f"frame: unknown role(s) {', '.join(bad)}; use origin=A,x=B,xy=C[,z=D]")
    for k in ("origin", "x"):
        if not items.get(k):
            raise InputError(f"frame: {k}= is required (origin=A,x=B,xy=C[,z=D])")
    if len(set(items.values())) != len(items):
        raise InputError("frame: the reference nodes must be distinct")
    return items


def units(result: Any) -> float:
    """Metres per matrix unit of a result (its ``speed``, else 1)."""
    spd = result.speed
    return 1.0 if spd is None else float(spd)


@dataclass(frozen=True)
class RefitData:
    """What a refit of a TOA result starts from, in metres, over its located nodes.

    Attributes
    ----------
    c : float
        Metres per matrix unit (:func:`units`).
    Y : (I, J) array
        The matrix in metres.
    receivers, sources : (I, d), (J, d) arrays
        The result's positions (NaN rows: not located).
    ok_r, ok_s : (I,), (J,) bool arrays
        Located receivers / sources.
    receiver_offsets, source_offsets : arrays or None
        The result's offsets in metres, of the located nodes only.
    """

    c: float
    Y: Array
    receivers: Array
    sources: Array
    ok_r: NDArray[np.bool_]
    ok_s: NDArray[np.bool_]
    receiver_offsets: Array | None
    source_offsets: Array | None


def refit_data(result: Any, matrix: Any) -> RefitData:
    """The :class:`RefitData` of a result and the matrix it was fitted to."""
    c = units(result)
    R = np.asarray(result.receivers, float)
    S = np.asarray(result.sources, float)
    ok_r, ok_s = np.isfinite(R).all(1), np.isfinite(S).all(1)
    do = None if result.receiver_offsets is None else np.asarray(result.receiver_offsets, float)[ok_r] * c
    so = None if result.source_offsets is None else np.asarray(result.source_offsets, float)[ok_s] * c
    return RefitData(c, np.asarray(matrix, float) * c, R, S, ok_r, ok_s, do, so)


def offsets_of(result: Any) -> str:
    """The offsets mode whose arrays ``result`` carries: "none", "receivers", "sources" or "both"."""
    has_r, has_s = result.receiver_offsets is not None, result.source_offsets is not None
    return {(False, False): "none", (True, False): "receivers", (False, True): "sources",
            (True, True): "both"}[(has_r, has_s)]


def node_positions(result: Any, kind: str) -> Array:
    """The (n, d) receivers or sources of a result (``kind`` "receiver" / "source")."""
    return np.asarray(result.receivers if kind == "receiver" else result.sources, float)
