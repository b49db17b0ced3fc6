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

from ..._result import WrappedResult
from ...errors import InputError

__all__ = ["FrameInfo", "FramedToaResult", "KnownNode", "check_frame", "node_names", "node_positions",
           "parse_frame", "parse_known",
           "read_known_csv", "RefitData", "refit_data", "replace_fields", "resolve_node", "units"]

Array = NDArray[np.float64]


@dataclass(frozen=True)
class KnownNode:
    """One node with a known position.

    Attributes
    ----------
    name: the name it was given by.
    kind: "receiver" or "source".
    index: row (receiver) or column (source) index of the range matrix.
    position: (d,) metres in the user's frame.
    std: isotropic standard deviation per coordinate (m), or None for an exact position.
    """

    name: str
    kind: str
    index: int
    position: Array
    std: float | None = None


@dataclass(frozen=True)
class FrameInfo:
    """How the result was put in the user's frame, and what stayed undetermined.

    Attributes
    ----------
    kind: "canonical" (no frame asked), "known" or "reference".
    references: names of the nodes that define the frame.
    rank: affine rank of the references (0 = one point, d = full).
    determined: True when rotation, translation and mirror are all fixed by them.
    residual_gauge: continuous freedoms the references leave (0 when determined or only
        the mirror is left); those are held at the blind solution's canonical gauge.
    mirror_resolved: whether the mirror image is fixed by the references.
    message: one line saying what was fixed, and what choice was taken where not.
    known_rms: RMS (m) of known-minus-estimated positions over the known nodes after the
        rigid alignment of the blind solution (before the constrained fit): a check of
        the known coordinates against the ranges; None for kind != "known".
    known_rms_fit: the same after the constrained fit (0 for exact nodes).
    known_test: the test of the known positions against the ranges
        (:class:`selfcal.toa.verdict.known_test.KnownTest` as a dict), None for kind != "known".
    error_scale: the block jackknife's scale of the receivers' covariances
        (:meth:`selfcal.toa.verdict.crossval.JackknifeScale.to_dict`), None when not run.
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
    error_scale: dict[str, Any] | None = None

    def to_dict(self) -> dict[str, Any]:
        """JSON-safe dictionary."""
        return dataclasses.asdict(self) | {"references": list(self.references)}


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


def read_known_csv(path: str | os.PathLike[str], dim: int = 3) -> dict[str, tuple[float, ...]]:
    """Read known node positions from a CSV file ``name,x,y,z[,std]`` (metres).

    One node per line. An optional header line names the columns (``name,x,y,z,std``;
    ``z`` absent in 2-D). Without a header the columns are ``name`` then ``dim``
    coordinates then an optional ``std``; an empty or absent ``std`` means exact.
    Lines starting with ``#`` and blank lines are skipped.

    Returns
    -------
    ``{name: (x, y[, z][, std])}`` suitable for ``known=`` of :func:`calibrate_in_frame`
    (a tuple of ``dim + 1`` values carries a std).

    Raises
    ------
    InputError: unreadable file, wrong number of columns, non-numeric or non-finite
        values, negative std, duplicated names.
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
            raise InputError(f"{p}: header {rows[0]} lacks one of {','.join(axes)}")
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
            xyz = [float(rec[a]) for a in axes]
            std = float(rec["std"]) if rec.get("std", "") != "" else None
        except ValueError:
            raise InputError(f"{p}: line {ln}: non-numeric value in {row}") from None
        if not np.all(np.isfinite(xyz)) or (std is not None and not (np.isfinite(std) and std >= 0)):
            raise InputError(f"{p}: line {ln}: coordinates must be finite and std >= 0")
        out[name] = tuple(xyz) + (() if std is None or std == 0 else (std,))
    return out


def parse_known(known: Any, I: int, J: int, dim: int, *, receiver_names: Sequence[str] | None = None,
                source_names: Sequence[str] | None = None) -> list[KnownNode]:
    """Validate ``known=`` into :class:`KnownNode` records.

    ``known``: a mapping ``{node: (x, y[, z][, std])}`` (std in metres; absent or 0 =
    exact), a path to a CSV file (:func:`read_known_csv`), or a list of
    :class:`KnownNode`.
    """
    if isinstance(known, (str, os.PathLike)):
        known = read_known_csv(known, dim)
    if isinstance(known, Sequence) and all(isinstance(k, KnownNode) for k in known):
        nodes = list(known)
    elif isinstance(known, Mapping):
        nodes = []
        for name, value in known.items():
            v = np.asarray(value, dtype=float).ravel()
            if v.size not in (dim, dim + 1) or not np.isfinite(v).all():
                raise InputError(f"known node {name!r}: expected {dim} finite coordinates and an "
                                 f"optional std, got {value!r}")
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
    if not nodes:
        raise InputError("known: no nodes given")
    return nodes


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


def replace_fields(result: Any, **kw: Any) -> Any:
    """dataclasses.replace with only the fields the result type has."""
    names = {f.name for f in dataclasses.fields(result)}
    return dataclasses.replace(result, **{k: v for k, v in kw.items() if k in names})


def node_positions(result: Any, kind: str) -> Array:
    """The (n, d) receivers or sources of a result (``kind`` "receiver" / "source")."""
    return np.asarray(result.receivers if kind == "receiver" else result.sources, float)
