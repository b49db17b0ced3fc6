"""The user's frame: known node positions and reference-node frames for TOA calibration.

Anchor-free calibration determines the network up to a rigid motion and a mirror image
(003 sec. II; the solver reports it in the canonical principal-axes gauge). Installers
want coordinates in their room. Two ways to get there:

- **Known nodes** (``known=``, ``--known FILE.csv``): some nodes have known positions,
  exact or with a standard deviation. They *constrain* the fit (exact ones are fixed
  coordinates, the others Gaussian priors of :func:`selfcal.toa.nls.refine_toa`) and put
  the result in their frame. The blind solution is first moved onto them by a least-squares
  rigid motion (Kabsch), then refined with the constraints.
- **Reference frame** (``frame="origin=A,x=B,xy=C[,z=D]"``, as UWB anchor set-up tools
  do): node A at the origin, B on the +x axis, C in the xy half-plane with y > 0, and in
  3-D optionally D on the z > 0 side. These only fix the gauge: the fit is unchanged and
  the covariances are re-expressed in that frame (A's position has zero variance, B's y
  and z, C's z too), computed by the engine with exactly those coordinates fixed.

What the references leave undetermined is reported, never silently chosen: ``k`` affinely
independent known nodes fix a rigid motion in ``d`` dimensions only when ``k >= d + 1``.
In 3-D, three known nodes (a plane) leave the mirror image through their plane; two (a
line) also leave the rotation about that line; one leaves every rotation. In 2-D, two
known nodes leave the mirror through their line. The free part is then held at the
blind solution's canonical gauge (a proper rotation, i.e. the blind solution's
handedness) and :class:`FrameInfo` says so; add a reference off the plane / line (or
``z=D`` with ``--frame``) to resolve it.

Node names. A node is named ``r<i>`` (receiver i, 0-based) or ``s<j>`` (source j), by a
bare integer (a receiver index: receivers are usually the anchors), or by a name from
the ``receiver_names`` / ``source_names`` lists when given.

Length (745 lines, above the ~600 guideline): known nodes and every reference-frame
convention, each with its undetermined part.
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

from ..errors import DegenerateGeometryError, InputError

__all__ = [
    "FrameInfo",
    "FramedToaResult",
    "KnownNode",
    "apply_frame",
    "calibrate_in_frame",
    "fit_known",
    "parse_frame",
    "parse_known",
    "read_known_csv",
]

Array = NDArray[np.float64]

_RANK_TOL = 1e-6  # relative singular value below which known nodes are called degenerate


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

    def to_dict(self) -> dict[str, Any]:
        """JSON-safe dictionary."""
        return dataclasses.asdict(self) | {"references": list(self.references)}


@dataclass(frozen=True)
class FramedToaResult:
    """A :class:`selfcal.toa.solve.ToaResult` in the user's frame plus its :class:`FrameInfo`.

    Every attribute of the wrapped result (``receivers``, ``sources``, covariances, ...)
    is available directly; ``to_dict()`` adds the key ``"frame"``.
    """

    result: Any
    frame: FrameInfo = field(default_factory=lambda: FrameInfo("canonical"))

    def __getattr__(self, name: str) -> Any:
        if name in ("result", "frame") or name.startswith("__"):
            raise AttributeError(name)
        return getattr(self.result, name)

    def to_dict(self) -> dict[str, Any]:
        """The wrapped result's dictionary with ``"frame"`` added."""
        out = dict(self.result.to_dict())
        out["frame"] = self.frame.to_dict()
        return out


# ---------------------------------------------------------------------------
# names
# ---------------------------------------------------------------------------


def resolve_node(token: Any, I: int, J: int, receiver_names: Sequence[str] | None = None,
                 source_names: Sequence[str] | None = None) -> tuple[str, int]:
    """Map a node reference to ``("receiver" | "source", index)``.

    Accepted: a name of ``receiver_names`` / ``source_names``; ``r<i>`` / ``s<j>``
    (0-based); a bare integer (receiver index).
    """
    t = str(token).strip()
    if receiver_names is not None and t in receiver_names:
        if source_names is not None and t in source_names:
            raise InputError(f"node name {t!r} is both a receiver and a source name")
        return "receiver", list(receiver_names).index(t)
    if source_names is not None and t in source_names:
        return "source", list(source_names).index(t)
    m = re.fullmatch(r"([rs]?)(\d+)", t, flags=re.IGNORECASE)
    if m is None:
        raise InputError(f"unknown node {t!r}: use r<i> (receiver i), s<j> (source j), a receiver "
                         "index, or a name from the node names")
    kind = "source" if m.group(1).lower() == "s" else "receiver"
    k = int(m.group(2))
    n = J if kind == "source" else I
    if k >= n:
        raise InputError(f"node {t!r}: {kind} index {k} out of range (there are {n} {kind}s, 0-based)")
    return kind, k


# ---------------------------------------------------------------------------
# parsing
# ---------------------------------------------------------------------------


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


# ---------------------------------------------------------------------------
# helpers on ToaResult-like objects
# ---------------------------------------------------------------------------


def _units(result: Any) -> float:
    spd = getattr(result, "speed", None)
    return 1.0 if spd is None else float(spd)


def _replace(result: Any, **kw: Any) -> Any:
    """dataclasses.replace with only the fields the result type has."""
    names = {f.name for f in dataclasses.fields(result)}
    return dataclasses.replace(result, **{k: v for k, v in kw.items() if k in names})


def _rotate_cov(C: Array, R: Array) -> Array:
    return np.einsum("ab,nbc,dc->nad", R, C, R)


def _node_positions(result: Any, kind: str) -> Array:
    return np.asarray(result.receivers if kind == "receiver" else result.sources, float)


# ---------------------------------------------------------------------------
# reference frame
# ---------------------------------------------------------------------------


def apply_frame(result: Any, frame: str | Mapping[str, Any], *, matrix: Any = None,
                offsets: str = "none", loss: str = "linear",
                receiver_names: Sequence[str] | None = None,
                source_names: Sequence[str] | None = None) -> FramedToaResult:
    """Express a calibration in the frame of reference nodes (origin=A, x=B, xy=C, z=D).

    A is moved to the origin, B onto the +x axis, C into the xy half-plane with y > 0
    (in 2-D: the upper half-plane). In 3-D the z sign is fixed by D (z > 0) when given;
    otherwise the frame is right-handed with respect to the blind solution (its
    handedness is kept: a proper rotation) and :class:`FrameInfo` reports that the mirror
    through the plane of A, B, C was not determined by the frame. In 2-D without ``xy``
    the mirror through the x axis is likewise reported.

    Parameters
    ----------
    result: a :class:`selfcal.toa.solve.ToaResult` (canonical gauge).
    frame: ``"origin=A,x=B,xy=C[,z=D]"`` or a mapping (see :func:`parse_frame`).
    matrix: the range / TOA matrix the result was fitted to. When given (and the result
        has covariances), the covariances are recomputed in the new frame by
        :func:`selfcal.toa.nls.refine_toa` with A fixed, B's off-axis and C's
        out-of-plane coordinates fixed (the gauge of this frame); otherwise the
        gauge-free covariances are only rotated.
    offsets, loss: the model of ``result`` (for the covariance refit).
    receiver_names, source_names: optional node names.

    Returns
    -------
    :class:`FramedToaResult`.

    Raises
    ------
    InputError: bad frame string, unknown node, missing ``xy`` in 3-D.
    DegenerateGeometryError: A and B coincide, C on the line AB, D in the plane ABC.

    Examples
    --------
    >>> import numpy as np
    >>> from selfcal.toa.nls import toa_model
    >>> from selfcal.toa import solve_toa
    >>> rng = np.random.default_rng(0)
    >>> r, s = rng.uniform(0, 5, (6, 3)), rng.uniform(0, 5, (8, 3))
    >>> res = apply_frame(solve_toa(toa_model(r, s), rng=0), "origin=r0,x=r1,xy=r2")
    >>> bool(np.allclose(res.receivers[0], 0))
    True
    """
    roles = parse_frame(frame)
    R0 = np.asarray(result.receivers, float)
    S0 = np.asarray(result.sources, float)
    I, d = R0.shape
    J = S0.shape[0]
    if d == 3 and "xy" not in roles:
        raise InputError("frame: in 3-D the xy=C reference is required (it fixes the rotation about x)")
    if d == 2 and "z" in roles:
        raise InputError("frame: z= is a 3-D reference; the calibration is 2-D")
    refs = {k: resolve_node(v, I, J, receiver_names, source_names) for k, v in roles.items()}

    def pos(role: str) -> Array:
        kind, idx = refs[role]
        p = _node_positions(result, kind)[idx]
        if not np.isfinite(p).all():
            raise DegenerateGeometryError(f"frame: reference {roles[role]!r} has no estimated position "
                                          "(dropped)", kind="degenerate-frame")
        return p

    A, B = pos("origin"), pos("x")
    scale = float(np.nanmax(np.abs(np.vstack([R0, S0]) - A))) or 1.0
    e1 = B - A
    if np.linalg.norm(e1) <= 1e-9 * scale:
        raise DegenerateGeometryError("frame: origin and x references coincide", kind="degenerate-frame")
    e1 = e1 / np.linalg.norm(e1)
    mirror = True
    msg = []
    if "xy" in roles:
        v = pos("xy") - A
        v = v - (v @ e1) * e1
        if np.linalg.norm(v) <= 1e-6 * scale:
            raise DegenerateGeometryError("frame: the xy reference lies on the line through origin and x",
                                          kind="degenerate-frame")
        e2 = v / np.linalg.norm(v)
    else:  # 2-D only: the proper rotation; the mirror through the x axis is open
        e2 = np.array([-e1[1], e1[0]])
        mirror = False
        msg.append("the side of the x axis is not fixed (no xy= reference): kept the blind "
                   "solution's handedness")
    if d == 3:
        e3 = np.cross(e1, e2)
        if "z" in roles:
            h = float((pos("z") - A) @ e3)
            if abs(h) <= 1e-6 * scale:
                raise DegenerateGeometryError("frame: the z reference lies in the plane of origin, x, xy",
                                              kind="degenerate-frame")
            if h < 0:
                e3 = -e3  # a reflection: the blind solution was the mirror image
        else:
            mirror = False
            msg.append("the z sign is not fixed by origin/x/xy (mirror through their plane): kept the "
                       "blind solution's handedness (a proper rotation); add z=D to fix it")
        Rm = np.vstack([e1, e2, e3])
    else:
        Rm = np.vstack([e1, e2])
    t = -Rm @ A
    Rn, Sn = R0 @ Rm.T + t, S0 @ Rm.T + t
    # by construction these coordinates are zero; remove the round-off
    for role, axes in (("origin", range(d)), ("x", range(1, d)), ("xy", range(2, d))):
        if role in refs:
            kind, idx = refs[role]
            (Rn if kind == "receiver" else Sn)[idx, list(axes)] = 0.0
    rc = _rotate_cov(np.asarray(result.receiver_cov, float), Rm)
    scv = _rotate_cov(np.asarray(result.source_cov, float), Rm)
    out = _replace(result, receivers=Rn, sources=Sn, receiver_cov=rc, source_cov=scv,
                   method=f"{result.method}+frame")
    if matrix is not None and np.isfinite(rc).all() and np.isfinite(scv).all():
        out = _frame_covariance(out, matrix, refs, offsets, loss)
    if mirror:
        msg.insert(0, "frame fully determined by " + ", ".join(f"{k}={v}" for k, v in roles.items()))
    info = FrameInfo(kind="reference", references=tuple(roles[k] for k in roles), rank=len(roles) - 1,
                     determined=mirror, residual_gauge=0, mirror_resolved=mirror, message="; ".join(msg))
    return FramedToaResult(out, info)


def _frame_covariance(result: Any, matrix: Any, refs: dict[str, tuple[str, int]], offsets: str,
                      loss: str) -> Any:
    """Covariances in the reference frame: refit with exactly the frame's gauge fixed."""
    from .nls import refine_toa

    c = _units(result)
    Y = np.asarray(matrix, float) * c
    R = np.asarray(result.receivers, float)
    S = np.asarray(result.sources, float)
    I, d = R.shape
    J = S.shape[0]
    fr = np.zeros((I, d), bool)
    fs = np.zeros((J, d), bool)
    for role, axes in (("origin", range(d)), ("x", range(1, d)), ("xy", range(2, d))):
        if role in refs:
            kind, idx = refs[role]
            (fr if kind == "receiver" else fs)[idx, list(axes)] = True
    ok_r, ok_s = np.isfinite(R).all(1), np.isfinite(S).all(1)
    Ysub = Y[np.ix_(ok_r, ok_s)]
    do = None if result.receiver_offsets is None else np.asarray(result.receiver_offsets, float)[ok_r] * c
    so = None if result.source_offsets is None else np.asarray(result.source_offsets, float)[ok_s] * c
    sol = refine_toa(Ysub, R[ok_r], S[ok_s], offsets=offsets, receiver_offsets0=do, source_offsets0=so,
                     loss=loss, fixed_receivers=fr[ok_r], fixed_sources=fs[ok_s])
    rc = np.full((I, d, d), np.nan)
    scv = np.full((J, d, d), np.nan)
    rc[ok_r], scv[ok_s] = sol.receiver_cov, sol.source_cov
    # the refit starts at the minimum; keep the positions of the blind fit (the gauge
    # constraints do not change the minimum, only round-off)
    return _replace(result, receiver_cov=rc, source_cov=scv)


# ---------------------------------------------------------------------------
# known nodes
# ---------------------------------------------------------------------------


def _affine_rank(P: Array) -> tuple[int, float]:
    if P.shape[0] < 2:
        return 0, 0.0
    sv = np.linalg.svd(P - P.mean(0), compute_uv=False)
    return int((sv > _RANK_TOL * max(sv[0], 1e-300)).sum()), float(sv[0])


def _rigid(X: Array, Y: Array, w: Array, allow_reflection: bool) -> tuple[Array, Array]:
    """Weighted least-squares rigid motion ``y = R x + t`` (Kabsch, Umeyama 1991)."""
    from ..geometry import align

    if X.shape[0] == 1:
        return np.eye(X.shape[1]), Y[0] - X[0]
    al = align(X, Y, reflection=allow_reflection, weights=w)
    return al.rotation, al.translation


def fit_known(
    matrix: Any, result: Any, known: Sequence[KnownNode], *, offsets: str = "none",
    loss: str = "linear", f_scale: float | None = None, noise: float | None = None,
    max_nfev: int | None = None, covariance: bool = True,
) -> FramedToaResult:
    """Constrain a calibration by known node positions and express it in their frame.

    1. Move the blind ``result`` onto the known nodes by the weighted least-squares rigid
       motion (weights ``1 / std^2``, exact nodes weighted as the most certain ones;
       reflection allowed only when the known nodes span the space, ``rank = d``).
    2. Refine with :func:`selfcal.toa.nls.refine_toa`: exact nodes are fixed rows, the
       others Gaussian priors ``N(position, std^2 I)``; the noise that weights the priors
       is ``noise`` when given, else estimated by the fit.

    Parameters
    ----------
    matrix: the (I, J) ranges (metres) or times (seconds with the result's ``speed``).
    result: the blind :class:`selfcal.toa.solve.ToaResult`.
    known: from :func:`parse_known`.
    offsets, loss, f_scale, max_nfev, covariance: as for :func:`selfcal.toa.nls.refine_toa`
        (``f_scale`` / ``noise`` in the matrix's units).
    noise: range noise std in the matrix's units, weighting the priors.

    Returns
    -------
    :class:`FramedToaResult` whose positions are in the known frame.
    """
    from .nls import refine_toa

    c = _units(result)
    Y = np.asarray(matrix, float) * c
    R0 = np.asarray(result.receivers, float)
    S0 = np.asarray(result.sources, float)
    I, d = R0.shape
    J = S0.shape[0]
    ok_r, ok_s = np.isfinite(R0).all(1), np.isfinite(S0).all(1)
    usable = [k for k in known if (ok_r if k.kind == "receiver" else ok_s)[k.index]]
    dropped = [k.name for k in known if k not in usable]
    if not usable:
        raise DegenerateGeometryError("none of the known nodes has an estimated position", kind="degenerate-frame")
    est = np.array([_node_positions(result, k.kind)[k.index] for k in usable])
    ref = np.array([k.position for k in usable], float)
    stds = np.array([k.std if k.std is not None else 0.0 for k in usable])
    rank, spread = _affine_rank(ref)
    tiny = max(1e-3 * spread, 1e-9) if spread > 0 else 1e-3
    w = 1.0 / np.maximum(stds, tiny * 1e-3) ** 2
    full = rank == d
    # (a) align on the known nodes; the undetermined part stays at the canonical gauge
    # (reflection is a choice only when the references span the space)
    Rm, t = _rigid(est, ref, w, allow_reflection=full)
    before = float(np.sqrt(np.mean(np.sum((est @ Rm.T + t - ref) ** 2, axis=1))))
    Ra, Sa = R0 @ Rm.T + t, S0 @ Rm.T + t
    # (b) the constrained refit
    fr = np.zeros((I, d), bool)
    fs = np.zeros((J, d), bool)
    pr_m, pr_s = np.full((I, d), np.nan), np.full((J, d), np.nan)
    pr_sd, ps_sd = np.ones(I), np.ones(J)
    for k in usable:
        pts, mask, mu, sd = (Ra, fr, pr_m, pr_sd) if k.kind == "receiver" else (Sa, fs, pr_s, ps_sd)
        if k.std is None:
            pts[k.index] = k.position
            mask[k.index] = True
        else:
            mu[k.index] = k.position
            sd[k.index] = k.std
    kw: dict[str, Any] = {}
    if fr.any():
        kw["fixed_receivers"] = fr[ok_r]
    if fs.any():
        kw["fixed_sources"] = fs[ok_s]
    if np.isfinite(pr_m).any():
        kw["receiver_prior"] = (pr_m[ok_r], pr_sd[ok_r])
    if np.isfinite(pr_s).any():
        kw["source_prior"] = (pr_s[ok_s], ps_sd[ok_s])
    do = None if result.receiver_offsets is None else np.asarray(result.receiver_offsets, float)[ok_r] * c
    so = None if result.source_offsets is None else np.asarray(result.source_offsets, float)[ok_s] * c
    sol = refine_toa(Y[np.ix_(ok_r, ok_s)], Ra[ok_r], Sa[ok_s], offsets=offsets, receiver_offsets0=do,
                     source_offsets0=so, loss=loss, f_scale=None if f_scale is None else f_scale * c,
                     noise=None if noise is None else noise * c, max_nfev=max_nfev,
                     covariance=covariance, **kw)
    out = _embed(result, sol, ok_r, ok_s, c, f"{result.method}+known({len(usable)})")
    fitted = np.array([_node_positions(out, k.kind)[k.index] for k in usable])
    after = float(np.sqrt(np.mean(np.sum((fitted - ref) ** 2, axis=1))))
    info = _known_info(usable, rank, d, before, after, dropped)
    return FramedToaResult(out, info)


def _known_info(usable: Sequence[KnownNode], rank: int, d: int, before: float, after: float,
                dropped: Sequence[str]) -> FrameInfo:
    names = tuple(k.name for k in usable)
    # continuous freedoms left by k affinely independent points in d dimensions
    rot = d * (d - 1) // 2
    if rank >= d:
        gauge, mirror = 0, True
        msg = f"frame fully determined by {len(usable)} known nodes"
    else:
        mirror = False
        if rank == 0:
            gauge = rot  # translation fixed by the one point, every rotation free
            what = "every rotation about it and the mirror image"
        elif d == 3 and rank == 1:
            gauge = 1
            what = "the rotation about the line through them and the mirror image"
        else:
            gauge = 0
            what = "the mirror image through their " + ("plane" if d == 3 else "line")
        msg = (f"{len(usable)} known node(s) of affine rank {rank} leave {what} undetermined: "
               "held at the blind solution's canonical gauge (proper rotation); add a known node "
               f"off their {'plane' if rank == 2 else 'line' if rank == 1 else 'point'} to fix it")
    if dropped:
        msg += f"; known node(s) without an estimate ignored: {', '.join(dropped)}"
    return FrameInfo(kind="known", references=names, rank=rank, determined=rank >= d, residual_gauge=gauge,
                     mirror_resolved=mirror, message=msg, known_rms=before, known_rms_fit=after)


def _embed(result: Any, sol: Any, ok_r: NDArray[np.bool_], ok_s: NDArray[np.bool_], c: float,
           method: str) -> Any:
    """A copy of ``result`` with the (sub-network) NlsSolution ``sol`` written in."""
    I, d = np.asarray(result.receivers).shape
    J = np.asarray(result.sources).shape[0]

    def put(n: int, ok: NDArray[np.bool_], val: Array | None, shape: tuple[int, ...], k: float = 1.0) -> Array | None:
        if val is None:
            return None
        out = np.full((n,) + shape, np.nan)
        out[ok] = np.asarray(val) * k
        return out

    res = np.full((I, J), np.nan)
    res[np.ix_(ok_r, ok_s)] = sol.residuals / c
    return _replace(
        result,
        receivers=put(I, ok_r, sol.receivers, (d,)), sources=put(J, ok_s, sol.sources, (d,)),
        receiver_offsets=put(I, ok_r, sol.receiver_offsets, (), 1 / c),
        source_offsets=put(J, ok_s, sol.source_offsets, (), 1 / c),
        receiver_cov=put(I, ok_r, sol.receiver_cov, (d, d)), source_cov=put(J, ok_s, sol.source_cov, (d, d)),
        receiver_offset_std=put(I, ok_r, sol.receiver_offset_std, (), 1 / c),
        source_offset_std=put(J, ok_s, sol.source_offset_std, (), 1 / c),
        residual_rms=sol.residual_rms / c, sigma=sol.sigma / c, converged=sol.converged,
        iterations=int(result.iterations) + int(sol.iterations), method=method, residuals=res,
    )


# ---------------------------------------------------------------------------
# entry point
# ---------------------------------------------------------------------------


def calibrate_in_frame(
    matrix: Any,
    *,
    known: Any = None,
    frame: str | Mapping[str, Any] | None = None,
    receiver_names: Sequence[str] | None = None,
    source_names: Sequence[str] | None = None,
    **solve_kw: Any,
) -> FramedToaResult:
    """Calibrate with :func:`selfcal.toa.solve_toa` and return the result in the user's frame.

    Parameters
    ----------
    matrix: (I, J) ranges in metres (or seconds with ``speed=``), NaN = missing.
    known: known node positions ``{node: (x, y[, z][, std])}``, a CSV path
        (``name,x,y,z[,std]``) or a list of :class:`KnownNode`: they constrain the fit
        (exact = fixed, with std = Gaussian prior) and define the frame (:func:`fit_known`).
    frame: ``"origin=A,x=B,xy=C[,z=D]"``: a frame by reference nodes (:func:`apply_frame`);
        exclusive with ``known``.
    receiver_names, source_names: optional names for the rows / columns.
    **solve_kw: passed to :func:`selfcal.toa.solve_toa` (``dim``, ``offsets``, ``loss``,
        ``speed``, ``noise``, ``rng``, ...).

    Returns
    -------
    :class:`FramedToaResult`; ``.frame`` says what the references fixed and what they
    left undetermined.

    Raises
    ------
    InputError: both ``known`` and ``frame``, malformed known positions or frame.
    DegenerateGeometryError: as :func:`selfcal.toa.solve_toa`, or degenerate references.

    Examples
    --------
    >>> import numpy as np
    >>> from selfcal.toa.nls import toa_model
    >>> rng = np.random.default_rng(1)
    >>> r, s = rng.uniform(0, 5, (6, 3)), rng.uniform(0, 5, (9, 3))
    >>> Y = toa_model(r, s) + 0.01 * rng.standard_normal((6, 9))
    >>> res = calibrate_in_frame(Y, known={f"r{i}": r[i] for i in range(4)}, rng=0)
    >>> bool(np.allclose(res.receivers[:4], r[:4]))
    True
    """
    from .solve import solve_toa

    if known is not None and frame is not None:
        raise InputError("give either known positions or a reference frame, not both "
                         "(known positions already define the frame)")
    blind = solve_toa(matrix, **solve_kw)
    if known is None and frame is None:
        return FramedToaResult(blind, FrameInfo("canonical", message="canonical gauge (no frame given)"))
    M = np.asarray(matrix, float)
    I, J = M.shape
    dim = np.asarray(blind.receivers).shape[1]
    offsets = solve_kw.get("offsets", "none")
    if offsets not in ("none", "receivers", "sources", "both"):  # e.g. "auto": the chosen model
        offsets = _offsets_of(blind)
    loss = solve_kw.get("loss", getattr(blind, "loss", "linear"))
    if loss not in ("linear", "huber", "soft_l1", "cauchy"):
        loss = "linear"
    if frame is not None:
        return apply_frame(blind, frame, matrix=M if solve_kw.get("covariance", True) else None,
                           offsets=offsets, loss=loss, receiver_names=receiver_names,
                           source_names=source_names)
    nodes = parse_known(known, I, J, dim, receiver_names=receiver_names, source_names=source_names)
    return fit_known(M, blind, nodes, offsets=offsets, loss=loss, f_scale=solve_kw.get("f_scale"),
                     noise=solve_kw.get("noise"), max_nfev=solve_kw.get("max_nfev"),
                     covariance=solve_kw.get("covariance", True))


def _offsets_of(result: Any) -> str:
    has_r = result.receiver_offsets is not None
    has_s = result.source_offsets is not None
    return {(False, False): "none", (True, False): "receivers", (False, True): "sources",
            (True, True): "both"}[(has_r, has_s)]
