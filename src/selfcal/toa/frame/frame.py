"""The user's frame: known node positions and reference-node frames for TOA calibration.

Anchor-free calibration determines the network up to a rigid motion and a mirror image
(003 sec. II; the solver reports it in the canonical principal-axes gauge). Installers
want coordinates in their room. Two ways to get there:

- **Known nodes** (``known=``, ``--known FILE.csv``): some nodes have known positions,
  exact or with a standard deviation. They *constrain* the fit (exact ones are fixed
  coordinates, the others Gaussian priors of :func:`selfcal.toa.engine.nls.refine_toa`) and put
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

Layout (one job per file): this module holds the reference frames (:func:`apply_frame`)
and the entry :func:`calibrate_in_frame`; known positions are fitted in
:mod:`selfcal.toa.frame.known`; node names, parsers and the result records are in
:mod:`selfcal.toa.frame.nodes`. Every public name is re-exported here.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ...errors import DegenerateGeometryError, InputError
from ...geometry import rotate_covariances
from ..result import ToaResult
from .known import align_known, fit_known
from .nodes import (
    FramedToaResult,
    FrameInfo,
    KnownNode,
    node_positions,
    offsets_of,
    parse_frame,
    parse_known,
    read_known_csv,
    refit_data,
    replace_fields,
    resolve_node,
)

__all__ = [
    "FrameInfo",
    "FramedToaResult",
    "KnownNode",
    "align_known",
    "apply_frame",
    "calibrate_in_frame",
    "fit_known",
    "parse_frame",
    "parse_known",
    "read_known_csv",
    "resolve_node",
]

Array = NDArray[np.float64]


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
        :func:`selfcal.toa.engine.nls.refine_toa` with A fixed, B's off-axis and C's
        out-of-plane coordinates fixed (the gauge of this frame); otherwise the
        gauge-free covariances are only rotated.
    offsets, loss: the model of ``result`` (for the covariance refit); ``"common"`` = one
        offset shared by every receiver.
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
    >>> from selfcal.toa.engine.nls import toa_model
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
        p = node_positions(result, kind)[idx]
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
    rc = rotate_covariances(np.asarray(result.receiver_cov, float), Rm)
    scv = rotate_covariances(np.asarray(result.source_cov, float), Rm)
    out = replace_fields(result, receivers=Rn, sources=Sn, receiver_cov=rc, source_cov=scv,
                   method=f"{result.method}+frame")
    if isinstance(result, ToaResult) and result.uniqueness is not None:  # the alternatives in the same frame
        out = replace_fields(out, uniqueness=result.uniqueness.moved(Rm, t))
    # (dropped nodes have NaN positions and covariances: the refit is over the located ones)
    loc_r, loc_s = np.isfinite(Rn).all(1), np.isfinite(Sn).all(1)
    if matrix is not None and np.isfinite(rc[loc_r]).all() and np.isfinite(scv[loc_s]).all():
        out = _frame_covariance(out, matrix, refs, offsets, loss)
    if mirror:
        msg.insert(0, "frame fully determined by " + ", ".join(f"{k}={v}" for k, v in roles.items()))
    info = FrameInfo(kind="reference", references=tuple(roles[k] for k in roles), rank=len(roles) - 1,
                     determined=mirror, residual_gauge=0, mirror_resolved=mirror, message="; ".join(msg))
    return FramedToaResult(out, info)


def _frame_covariance(result: Any, matrix: Any, refs: dict[str, tuple[str, int]], offsets: str,
                      loss: str) -> Any:
    """Covariances in the reference frame: refit with exactly the frame's gauge fixed."""
    from ..engine.nls import refine_toa

    data = refit_data(result, matrix)
    R, S, ok_r, ok_s = data.receivers, data.sources, data.ok_r, data.ok_s
    I, d = R.shape
    J = S.shape[0]
    fr = np.zeros((I, d), bool)
    fs = np.zeros((J, d), bool)
    for role, axes in (("origin", range(d)), ("x", range(1, d)), ("xy", range(2, d))):
        if role in refs:
            kind, idx = refs[role]
            (fr if kind == "receiver" else fs)[idx, list(axes)] = True
    # "common": one offset shared by every receiver (the moving-tag recipe's kept model)
    off, common = ("receivers", "receivers") if offsets == "common" else (offsets, "none")
    sol = refine_toa(data.Y[np.ix_(ok_r, ok_s)], R[ok_r], S[ok_s], offsets=off, common_offsets=common,
                     receiver_offsets0=data.receiver_offsets, source_offsets0=data.source_offsets,
                     loss=loss, fixed_receivers=fr[ok_r], fixed_sources=fs[ok_s])
    rc = np.full((I, d, d), np.nan)
    scv = np.full((J, d, d), np.nan)
    rc[ok_r], scv[ok_s] = sol.receiver_cov, sol.source_cov
    # the refit starts at the minimum; keep the positions of the blind fit (the gauge
    # constraints do not change the minimum, only round-off)
    return replace_fields(result, receiver_cov=rc, source_cov=scv)


def calibrate_in_frame(
    matrix: Any,
    *,
    known: Any = None,
    frame: str | Mapping[str, Any] | None = None,
    receiver_names: Sequence[str] | None = None,
    source_names: Sequence[str] | None = None,
    side: str | None = None,
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
    side: with ``known``: "below" / "above" -- the other nodes lie below / above the plane of
        coplanar known nodes (3-D), which resolves the mirror they leave (:func:`fit_known`).
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
    >>> from selfcal.toa.engine.nls import toa_model
    >>> rng = np.random.default_rng(1)
    >>> r, s = rng.uniform(0, 5, (6, 3)), rng.uniform(0, 5, (9, 3))
    >>> Y = toa_model(r, s) + 0.01 * rng.standard_normal((6, 9))
    >>> res = calibrate_in_frame(Y, known={f"r{i}": r[i] for i in range(4)}, rng=0)
    >>> bool(np.allclose(res.receivers[:4], r[:4]))
    True
    """
    from ..solve import solve_toa

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
        offsets = offsets_of(blind)
    loss = solve_kw.get("loss", "linear")
    if loss not in ("linear", "huber", "soft_l1", "cauchy"):  # "auto": least squares on the inliers
        loss = "linear"
    if frame is not None:
        return apply_frame(blind, frame, matrix=M if solve_kw.get("covariance", True) else None,
                           offsets=offsets, loss=loss, receiver_names=receiver_names,
                           source_names=source_names)
    nodes = parse_known(known, I, J, dim, receiver_names=receiver_names, source_names=source_names)
    return fit_known(M, blind, nodes, offsets=offsets, loss=loss, f_scale=solve_kw.get("f_scale"),
                     noise=solve_kw.get("noise"), max_nfev=solve_kw.get("max_nfev"),
                     covariance=solve_kw.get("covariance", True), side=side)

