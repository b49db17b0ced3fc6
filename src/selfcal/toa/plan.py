"""Planning a UWB anchor installation before it is made: predicted error bars and ambiguities.

Given candidate anchor positions, a planned tag path and the range noise,
:func:`plan_layout` predicts what a self-calibration (``calibrate toa`` on the ranges the
tag would log) can reach, from the same machinery as the solver:

- each anchor's error bar: the gauge-free Cramér-Rao bound of the self-calibration
  (:func:`selfcal.toa.engine.crlb.toa_crlb`, 003 eq. 17 at the planned geometry) with the offset
  model the data will be fitted with (``offsets="receivers"``: a per-anchor ranging bias);
  the NLS covariances the solver reports converge to it;
- the tag's positioning error over the room: at each point of a horizontal grid at the
  tag's height, ``sqrt(tr (sigma^2 (G^T G)^-1))`` with ``G`` the unit vectors from the
  anchors (the positioning bound with the anchors and their biases known; the anchors'
  own calibration error adds to it);
- ambiguities the layout will have, which no local error bar shows
  (:func:`layout_ambiguities`): a tag path in one plane (one height) leaves each anchor
  determined only up to its mirror image through that plane; coplanar anchors leave each
  tag position determined only up to its mirror image through theirs. Planarity is the
  solver's own test (:func:`selfcal.toa.verdict.planarity.planarity`): a set is planar when its
  thickness is not resolved by its Cramér-Rao bounds at the planned geometry (chi-square of
  the out-of-plane coordinates at level 1e-3, the statistic the calibration's test will
  see, less its noise); an exactly planar set, whose bound is singular, is planar.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .._checks import as_points, check_choice, check_positive
from ..errors import DegenerateGeometryError, InputError

__all__ = ["Ambiguity", "LayoutPlan", "layout_ambiguities", "plan_layout", "positioning_std"]

Array = NDArray[np.float64]


@dataclass(frozen=True)
class Ambiguity:
    """A discrete ambiguity of a layout.

    Attributes
    ----------
    kind : str
        ``"anchor-mirror"`` (tag path in one plane) or ``"tag-mirror"`` (coplanar anchors).
    plane_point, plane_normal : (3,) arrays
        The mirror plane.
    message : str
        What it means and how to remove it.
    """

    kind: str
    plane_point: Array
    plane_normal: Array
    message: str

    def to_dict(self) -> dict[str, Any]:
        """JSON-safe dictionary."""
        return {"kind": self.kind, "plane_point": np.asarray(self.plane_point).tolist(),
                "plane_normal": np.asarray(self.plane_normal).tolist(), "message": self.message}


@dataclass(frozen=True)
class LayoutPlan:
    """What :func:`plan_layout` predicts.

    Attributes
    ----------
    anchor_std : (I,) array
        Predicted RMS position error of each anchor, ``sqrt(trace)`` of its CRLB block (m).
    anchor_bounds : (I, 3, 3) array
        The CRLB blocks (m^2).
    path_std : (J,) array
        Predicted error of each tag position of the calibration flight (m).
    grid_x, grid_y : (nx,), (ny,) arrays
        The map's grid (m).
    height : float
        The map's height (m).
    tag_std_map : (ny, nx) array
        Tag positioning error bound at each grid point (m); NaN where the anchors do not
        determine a position.
    ambiguities : list of Ambiguity
    noise : float
    offsets : str
    determined : bool
        False when the layout's Fisher information is singular beyond the gauge (e.g. a tag
        path in one plane): no finite error bar, ``anchor_std`` NaN.
    """

    anchor_std: Array
    anchor_bounds: Array
    path_std: Array
    grid_x: Array
    grid_y: Array
    height: float
    tag_std_map: Array
    ambiguities: list[Ambiguity] = field(default_factory=list)
    noise: float = 0.0
    offsets: str = "receivers"
    determined: bool = True

    def to_dict(self) -> dict[str, Any]:
        """JSON-safe dictionary (the map as nested lists, NaN as None)."""
        def tl(a: Array) -> Any:
            return [[None if not np.isfinite(v) else float(v) for v in row] for row in np.atleast_2d(a)]

        p_rms = float(np.sqrt(np.mean(self.path_std**2)))
        return {"noise": self.noise, "offsets": self.offsets, "determined": self.determined,
                "anchor_std": tl(self.anchor_std)[0], "anchor_bounds": [tl(b) for b in self.anchor_bounds],
                "path_std_rms": p_rms if np.isfinite(p_rms) else None,
                "map": {"x": self.grid_x.tolist(), "y": self.grid_y.tolist(), "height": self.height,
                        "tag_std": tl(self.tag_std_map)},
                "ambiguities": [a.to_dict() for a in self.ambiguities]}


def _plane(P: Array, cov: Array | None) -> tuple[bool, Array, Array]:
    from .verdict.planarity import planarity

    pl = planarity(P, cov)
    return pl.near_planar, P.mean(axis=0), np.asarray(pl.normal, float)


def layout_ambiguities(anchors: Any, path: Any, *, anchor_cov: Any = None, path_cov: Any = None) -> list[Ambiguity]:
    """Mirror ambiguities of a 3-D layout: a planar tag path, coplanar anchors.

    A set is planar by the solver's own test (:func:`selfcal.toa.verdict.planarity.planarity`):
    its thickness not resolved by its covariances, the chi-square of the out-of-plane
    coordinates at level ``PLANAR_ALPHA`` = 1e-3. Given the Cramér-Rao bounds of the planned
    layout (what :func:`plan_layout` passes), the statistic is the noncentrality the
    calibration's own test will see; without covariances (or where the bound is singular:
    an exactly planar path) a set thinner than 1 % of its extent is planar.

    Parameters
    ----------
    anchors : (I, 3) array
    path : (J, 3) array
    anchor_cov, path_cov : (I, 3, 3), (J, 3, 3) arrays, optional
        Position covariances (m^2), e.g. the CRLB blocks of the self-calibration.

    Returns
    -------
    list of Ambiguity (empty when neither set is planar).

    Examples
    --------
    >>> import numpy as np
    >>> A = np.array([[0, 0, 2.8], [6, 0, 2.7], [6, 5, 2.9], [0, 5, 2.8], [3, 0, 1.0]])
    >>> t = np.linspace(0, 6, 50)
    >>> P = np.c_[1 + 4 * np.cos(t) ** 2, 1 + 3 * np.sin(t) ** 2, np.full(50, 1.2)]
    >>> [a.kind for a in layout_ambiguities(A, P)]
    ['anchor-mirror']
    """
    A = as_points(anchors, "anchors", dim=3)
    P = as_points(path, "path", dim=3)
    out: list[Ambiguity] = []
    flat, c, n = _plane(P, None if path_cov is None else np.asarray(path_cov, float))
    if flat:
        out.append(Ambiguity(
            "anchor-mirror", c, n,
            "the tag path lies in one plane: every anchor's mirror image through it fits the ranges "
            "equally, so each anchor is determined only up to that reflection (the solver picks one side "
            "per anchor); fly or carry the tag at several heights, or give --known anchors on both sides"))
    flat_a, ca, na = _plane(A, None if anchor_cov is None else np.asarray(anchor_cov, float))
    if flat_a:
        out.append(Ambiguity(
            "tag-mirror", ca, na,
            "the anchors lie in one plane: a tag position and its mirror image through that plane have the "
            "same ranges, so positioning cannot tell the two sides apart (and heights near the plane are "
            "poorly determined); mount at least one anchor well off the plane"))
    return out


def positioning_std(anchors: Any, points: Any, noise: float) -> Array:
    """Position error bound ``sqrt(tr(noise^2 (G^T G)^-1))`` of a tag at each point, anchors known (m).

    ``G`` holds the unit vectors from the anchors to the point (the Jacobian of the
    ranges). NaN where ``G`` has rank below 3 (fewer than 3 anchors in independent
    directions).

    Examples
    --------
    >>> import numpy as np
    >>> A = np.array([[0, 0, 0], [4, 0, 0], [0, 4, 0], [0, 0, 4.0]])
    >>> bool(positioning_std(A, [[1, 1, 1]], 0.1)[0] < 0.3)
    True
    """
    A = as_points(anchors, "anchors", dim=3)
    X = np.atleast_2d(np.asarray(points, float))
    diff = X[:, None, :] - A[None]
    dist = np.linalg.norm(diff, axis=2)
    G = diff / np.maximum(dist, 1e-12)[..., None]
    F = np.einsum("kia,kib->kab", G, G)
    out = np.full(len(X), np.nan)
    ok = np.linalg.matrix_rank(F, tol=1e-9) == 3
    if ok.any():
        out[ok] = noise * np.sqrt(np.trace(np.linalg.inv(F[ok]), axis1=1, axis2=2))
    return out


def plan_layout(anchors: Any, path: Any, *, noise: float = 0.05, offsets: str = "receivers",
                room: Any = None, height: float | None = None, grid: int = 41,
                max_range: float | None = None) -> LayoutPlan:
    """Predict a calibration's anchor error bars and the tag's positioning error over the room.

    Parameters
    ----------
    anchors : (I, 3) array
        Candidate anchor positions (m).
    path : (J, 3) array
        Planned tag positions of the calibration flight / walk (m), one per range epoch.
    noise : float
        Range noise std (m); UWB two-way ranging: 0.03-0.1.
    offsets : str
        Offset model the ranges will be fitted with: "none", "receivers" (per-anchor
        biases, default) or "both".
    room : (3,) sequence, optional
        Room size L, W, H (m; origin at a corner): the map covers the floor plan; default
        the bounding box of anchors and path.
    height : float, optional
        Height of the map (default the path's median height).
    grid : int
        Map points per side.
    max_range : float, optional
        Ranges longer than this are not measured (default: every anchor hears every position).

    Returns
    -------
    LayoutPlan

    Raises
    ------
    InputError
        Fewer than 4 anchors, too few tag positions, non-finite coordinates.

    Examples
    --------
    >>> import numpy as np
    >>> A = np.array([[0.2, 0.2, 2.8], [5.8, 0.3, 2.7], [5.7, 4.8, 2.9], [0.3, 4.7, 2.8], [3, 0.2, 0.5],
    ...               [3, 4.8, 1.5]])
    >>> t = np.linspace(0, 1, 200)
    >>> P = np.c_[3 + 2 * np.sin(7 * t), 2.5 + 1.8 * np.sin(11 * t), 1.2 + 0.6 * np.sin(5 * t)]
    >>> plan = plan_layout(A, P, noise=0.05, room=(6, 5, 3))
    >>> np.round(plan.anchor_std, 2).tolist(), plan.ambiguities
    ([0.17, 0.16, 0.18, 0.2, 0.07, 0.07], [])

    Per-anchor biases are nearly confounded with the radial positions of anchors on the
    walls and ceiling (the tag stays inside): without them the bound is 0.02-0.06 m.
    """
    check_choice(offsets, "offsets", ("none", "receivers", "both"))
    sd = check_positive(noise, "noise")
    assert sd is not None
    A = as_points(anchors, "anchors", dim=3)
    P = as_points(path, "path", dim=3)
    if len(A) < 4:
        raise InputError(f"anchors: {len(A)} given; a 3-D self-calibration needs at least 4")
    if len(P) < 10:
        raise InputError(f"path: {len(P)} tag positions; plan at least 10 (a real flight logs hundreds)")
    from .engine.crlb import toa_crlb

    mask = None
    if max_range is not None:
        mask = np.linalg.norm(A[:, None] - P[None], axis=2) <= float(max_range)
    try:
        crlb = toa_crlb(A, P, sd, offsets=offsets, mask=mask)
        a_std, a_bounds, p_std = np.sqrt(crlb.receiver_trace), np.asarray(crlb.receiver_bounds), np.sqrt(crlb.source_trace)
        p_bounds = np.asarray(crlb.source_bounds)
        determined = bool(np.isfinite(a_std).all())
    except DegenerateGeometryError:  # singular beyond the gauge: no finite error bar at all
        a_std, a_bounds, p_std = np.full(len(A), np.nan), np.full((len(A), 3, 3), np.nan), np.full(len(P), np.nan)
        p_bounds = np.full((len(P), 3, 3), np.nan)
        determined = False
    lo = np.minimum(A.min(0), P.min(0))
    hi = np.maximum(A.max(0), P.max(0))
    if room is not None:
        box = np.asarray(room, float).ravel()
        if box.shape != (3,) or not (np.isfinite(box).all() and (box > 0).all()):
            raise InputError(f"room: expected three positive sizes L, W, H in metres, got {room!r}")
        lo, hi = np.zeros(3), box
    z = float(np.median(P[:, 2])) if height is None else float(height)
    gx = np.linspace(lo[0], hi[0], int(grid))
    gy = np.linspace(lo[1], hi[1], int(grid))
    X, Y = np.meshgrid(gx, gy)
    pts = np.c_[X.ravel(), Y.ravel(), np.full(X.size, z)]
    smap = positioning_std(A, pts, sd).reshape(X.shape)
    amb = layout_ambiguities(A, P, anchor_cov=a_bounds, path_cov=p_bounds)
    return LayoutPlan(a_std, a_bounds, p_std, gx, gy, z, smap, amb, float(sd), offsets, determined)
