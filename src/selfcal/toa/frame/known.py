"""Known node positions for a TOA calibration: constrain the fit and set the frame.

``known=`` (``--known FILE.csv``, ``name,x,y,z[,std]``): the blind solution is moved onto
the known nodes by a weighted least-squares rigid motion (Kabsch), then refined by
:func:`selfcal.toa.engine.nls.refine_toa` with the exact nodes as fixed rows and the others as
Gaussian priors. A node may give only some coordinates (an empty field, ``A3,,,2.41``):
those are fixed entries (or per-coordinate priors) and the rigid motion is fitted to the
known coordinates alone (:func:`_fit_partial`). ``k`` affinely independent known nodes fix a rigid motion in ``d``
dimensions only when ``k >= d + 1``; what they leave open (a mirror, a rotation about a
line, every rotation) is held at the blind solution's canonical gauge and reported in
:class:`selfcal.toa.frame.nodes.FrameInfo`. Re-exported by :mod:`selfcal.toa.frame.frame`.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ...errors import DegenerateGeometryError
from ..verdict.known_test import gauge_left as _axes_fixed
from .error_scale import jackknife_scaled
from .nodes import FramedToaResult, FrameInfo, KnownNode, node_positions, refit_data, replace_fields

__all__ = ["fit_known", "align_known"]

Array = NDArray[np.float64]

_RANK_TOL = 1e-6  # relative singular value below which known nodes are called degenerate


def _affine_rank(P: Array) -> tuple[int, float]:
    if P.shape[0] < 2:
        return 0, 0.0
    sv = np.linalg.svd(P - P.mean(0), compute_uv=False)
    return int((sv > _RANK_TOL * max(sv[0], 1e-300)).sum()), float(sv[0])


def _rigid(X: Array, Y: Array, w: Array, allow_reflection: bool) -> tuple[Array, Array]:
    """Weighted least-squares rigid motion ``y = R x + t`` (Kabsch, Umeyama 1991)."""
    from ...geometry import align

    if X.shape[0] == 1:
        return np.eye(X.shape[1]), Y[0] - X[0]
    al = align(X, Y, reflection=allow_reflection, weights=w)
    return al.rotation, al.translation


@dataclass(frozen=True)
class _Refit:
    """The model and options of :func:`fit_known`'s refits (its arguments; ``f_scale`` and
    ``noise`` in the matrix's units, scaled to metres by ``c`` at each refit)."""

    offsets: str  # the refits' offsets mode ("receivers" for a common offset)
    common: str  # "receivers": one offset common to every receiver, else "none"
    loss: str
    f_scale: float | None
    noise: float | None
    max_nfev: int | None

    def metres(self, value: float | None, c: float) -> float | None:
        """``f_scale`` or ``noise`` in metres (``c``: metres per matrix unit)."""
        return None if value is None else value * c


def fit_known(
    matrix: Any, result: Any, known: Sequence[KnownNode], *, offsets: str = "none",
    loss: str = "linear", f_scale: float | None = None, noise: float | None = None,
    max_nfev: int | None = None, covariance: bool = True, side: str | None = None,
    jackknife: bool = True,
) -> FramedToaResult:
    """Constrain a calibration by known node positions and express it in their frame.

    1. Move the blind ``result`` onto the known nodes by the weighted least-squares rigid
       motion (weights ``1 / std^2``, exact nodes weighted as the most certain ones;
       reflection allowed only when the known nodes span the space, ``rank = d``).
    2. Refine with :func:`selfcal.toa.engine.nls.refine_toa`: exact nodes are fixed rows, the
       others Gaussian priors ``N(position, std^2 I)``; the noise that weights the priors
       is ``noise`` when given, else estimated by the fit.

    Parameters
    ----------
    matrix: the (I, J) ranges (metres) or times (seconds with the result's ``speed``).
    result: the blind :class:`selfcal.toa.solve.ToaResult`.
    known: from :func:`parse_known`. Nodes may give only some coordinates (NaN elsewhere,
        ``A3,,,2.41`` a known height): those are fixed entries / per-coordinate priors, the
        frame's axes they fix are the user's and the others canonical (:func:`_fit_partial`).
    offsets, loss, f_scale, max_nfev, covariance: as for :func:`selfcal.toa.engine.nls.refine_toa`
        (``f_scale`` / ``noise`` in the matrix's units); ``offsets="common"``: one offset
        shared by every receiver (``common_offsets="receivers"``), the model the moving-tag
        recipe keeps (:func:`selfcal.toa.recipes.common_offset.choose_common_offset`).
    noise: range noise std in the matrix's units, weighting the priors.
    side: "below" | "above": in 3-D, the other nodes lie below / above the plane of coplanar
        known nodes (along the known frame's z): resolves the mirror they leave
        (:func:`selfcal.toa.verdict.known_test.choose_side`); None = the mirror is tested and reported.
    jackknife: scale each free receiver's covariance by the block jackknife's evidence
        (:func:`selfcal.toa.verdict.jackknife.block_jackknife_scale`: the constrained fit
        repeated without each of K contiguous column blocks; a receiver's covariance is
        multiplied by ``max(1, tr(C^-1 V) / d)``, ``V`` the jackknife covariance), so that the
        stated error bars hold where range errors are serially correlated or depend on the
        tag's position (measured UWB ranges). With ``offsets="common"`` (per-anchor biases
        not in the model: the held-out choice did not adopt them) their effect is added as
        a random effect, which the jackknife cannot see (a bias is the same in every block):
        per-anchor biases ``b_i ~ N(c, tau^2)``, ``tau^2`` by the method of moments from the
        per-anchor refit (``(sum (d_i - mean d)^2 - (1 - 1/I) sum var d_i) / (I - 1)``, at
        least 0; 0 unless the offsets' weighted spread exceeds the chi-square 0.95 quantile
        with I - 1 dof), their effect on the receivers by the delta method, ``C_i += tau^2 G_i G_i^T``
        with ``G = d receivers / d b`` of the common-offset fit (finite differences, one refit
        per receiver). Reported in ``frame.error_scale`` (``bias_tau``, m).

    Returns
    -------
    :class:`FramedToaResult` whose positions are in the known frame.
    """
    data = refit_data(result, matrix)
    c, R0, S0, ok_r, ok_s = data.c, data.receivers, data.sources, data.ok_r, data.ok_s
    I, d = R0.shape
    usable, dropped, est, ref, w, rank = _matched(
        result, known, lambda k: bool((ok_r if k.kind == "receiver" else ok_s)[k.index]))
    # "common": one offset shared by every receiver (the moving-tag recipe's kept model)
    off, common = ("receivers", "receivers") if offsets == "common" else (offsets, "none")
    spec = _Refit(off, common, loss, f_scale, noise, max_nfev)
    if not all(k.full for k in usable):
        return _fit_partial(result, data, usable, dropped, est, ref, w, spec, covariance, side)
    full = rank == d
    # (a) align on the known nodes; the undetermined part stays at the canonical gauge
    # (reflection is a choice only when the references span the space)
    Rm, t = _rigid(est, ref, w, allow_reflection=full)
    before = float(np.sqrt(np.mean(np.sum((est @ Rm.T + t - ref) ** 2, axis=1))))
    Ra, Sa = R0 @ Rm.T + t, S0 @ Rm.T + t
    if side is not None:  # the user's statement picks the mirror image coplanar known nodes leave
        from ..verdict.known_test import choose_side

        Ra, Sa = choose_side(Ra, Sa, usable, ref, rank, side)
    # (b) the constrained refit
    sol, fr, fs, extra = _refit(data, Ra, Sa, usable, spec, covariance)
    scaled = None
    if jackknife and covariance:
        sol, scaled = jackknife_scaled(sol, data.Y[np.ix_(ok_r, ok_s)], dict(
            offsets=off, common_offsets=common, loss=loss, f_scale=None if f_scale is None else f_scale * c,
            noise=None if noise is None else noise * c, max_nfev=max_nfev, **extra))
    out = _embed(result, sol, ok_r, ok_s, c, f"{result.method}+known({len(usable)})")
    fitted = np.array([node_positions(out, k.kind)[k.index] for k in usable])
    after = float(np.sqrt(np.mean(np.sum((fitted - ref) ** 2, axis=1))))
    info = _known_info(usable, rank, d, before, after, dropped)
    info = replace(info, axes_fixed=_axes_fixed(est @ Rm.T + t, np.isfinite(ref))[0])
    # the known positions tested against the ranges, the frame's mirror against the data
    from ..verdict.known_test import judge_known

    out, info = judge_known(out, info, result, sol, data, usable, est @ Rm.T + t, Rm, rank, fr, fs, off, noise,
                            mirror_stated=side is not None)
    if scaled is not None:
        names = [f"r{i}" for i in np.nonzero(ok_r)[0]]
        info = dataclasses.replace(info, error_scale=scaled.to_dict(names))
    return FramedToaResult(out, info)


def _refit(data: Any, Ra: Array, Sa: Array, usable: Sequence[KnownNode], spec: _Refit, covariance: Any,
           max_nfev: int | None = None) -> tuple[Any, NDArray[np.bool_], NDArray[np.bool_], dict[str, Any]]:
    """The constrained refit from ``(Ra, Sa)`` in the known frame: exact known coordinates fixed
    (set to their values), known coordinates with a std Gaussian priors. Returns ``(sol, fixed_r,
    fixed_s, constraints)`` ((I, d), (J, d) masks of the fixed coordinates; the constraint
    keywords of :func:`selfcal.toa.engine.nls.refine_toa` on the located nodes)."""
    from ..engine.nls import refine_toa

    c, ok_r, ok_s = data.c, data.ok_r, data.ok_s
    Ra, Sa = np.array(Ra, float), np.array(Sa, float)
    I, d = Ra.shape
    J = Sa.shape[0]
    fr = np.zeros((I, d), bool)
    fs = np.zeros((J, d), bool)
    pr_m, pr_s = np.full((I, d), np.nan), np.full((J, d), np.nan)
    pr_sd, ps_sd = np.ones((I, d)), np.ones((J, d))
    for k in usable:
        pts, mask, mu, sd = (Ra, fr, pr_m, pr_sd) if k.kind == "receiver" else (Sa, fs, pr_s, ps_sd)
        m = k.mask
        if k.std is None:
            pts[k.index, m] = k.position[m]
            mask[k.index, m] = True
        else:
            mu[k.index, m] = k.position[m]
            sd[k.index, m] = k.std
    extra: dict[str, Any] = {}
    if fr.any():
        extra["fixed_receivers"] = fr[ok_r]
    if fs.any():
        extra["fixed_sources"] = fs[ok_s]
    if np.isfinite(pr_m).any():
        extra["receiver_prior"] = (pr_m[ok_r], pr_sd[ok_r])
    if np.isfinite(pr_s).any():
        extra["source_prior"] = (pr_s[ok_s], ps_sd[ok_s])
    sol = refine_toa(data.Y[np.ix_(ok_r, ok_s)], Ra[ok_r], Sa[ok_s], offsets=spec.offsets,
                     common_offsets=spec.common, receiver_offsets0=data.receiver_offsets,
                     source_offsets0=data.source_offsets, loss=spec.loss, f_scale=spec.metres(spec.f_scale, c),
                     noise=spec.metres(spec.noise, c), max_nfev=spec.max_nfev if max_nfev is None else max_nfev,
                     covariance=covariance, **extra)
    return sol, fr, fs, extra


#: iterations of the refit from the other handedness (the mirror candidate of partial known coordinates)
MIRROR_NFEV = 50


def _fit_partial(result: Any, data: Any, usable: Sequence[KnownNode], dropped: Sequence[str], est: Array,
                 ref: Array, w: Array, spec: _Refit, covariance: Any, side: str | None) -> FramedToaResult:
    """:func:`fit_known` where some known nodes give only some coordinates (``A3,,,2.41``).

    The blind fit is moved onto the known coordinates by the best rigid motion
    (:func:`_masked_rigid`) and refitted with them. The axes they fix (:func:`gauge_left`)
    may still be mirrored: known heights all at one level leave ``z -> 2h - z``, heights on
    several levels do not. That mirror (:func:`_mirror_start`) is refitted too, with at
    most :data:`MIRROR_NFEV` iterations; the better of the two fits is the result and
    :func:`selfcal.toa.verdict.known_test.judge_known` tests the other against it.
    """
    from ..verdict.known_test import judge_known

    c, R0, S0, ok_r, ok_s = data.c, data.receivers, data.sources, data.ok_r, data.ok_s
    d = R0.shape[1]
    mask = np.isfinite(ref)
    scale = float(np.nanmax(np.ptp(np.vstack([R0[ok_r], S0[ok_s]]), axis=0))) or 1.0
    motions = _masked_rigid(est, ref, w, scale)
    Rm, t, _ = motions[0]
    aligned = est @ Rm.T + t
    axes, n_free = _axes_fixed(aligned, mask)
    sol, fr, fs, _ = _refit(data, R0 @ Rm.T + t, S0 @ Rm.T + t, usable, spec, covariance)
    other = None
    start = _mirror_start(sol, data, usable, axes, n_free, motions[1])
    if start is not None:
        other = _refit(data, start[0], start[1], usable, spec, False, MIRROR_NFEV)[0]
    s_m = spec.metres(spec.noise, c)
    s2 = None if s_m is None else s_m**2

    def total(fit: Any) -> float:  # the constrained cost: RSS + noise^2 x prior misfit
        rss = float(np.nansum(np.asarray(fit.residuals, float) ** 2))
        sig2 = s2 if s2 is not None else float(sol.sigma) ** 2
        return rss + sig2 * _prior_misfit(fit, usable, ok_r, ok_s)

    swap = other is not None and total(other) < total(sol) * (1.0 - 1e-9)
    if other is not None and side is not None:  # the user's statement picks the mirror image
        swap = not _on_side(sol, usable, ok_r, ok_s, side) and _on_side(other, usable, ok_r, ok_s, side)
    if swap:  # the mirror fits better (or is the side stated): it is the result, with its covariance
        assert other is not None
        sol, other = _refit(data, _full(other.receivers, ok_r), _full(other.sources, ok_s), usable, spec,
                            covariance)[0], sol
    out = _embed(result, sol, ok_r, ok_s, c, f"{result.method}+known({len(usable)}, partial)")
    before = float(np.sqrt(np.nanmean(np.where(mask, aligned - ref, np.nan) ** 2)))  # per known coordinate
    fitted = np.array([node_positions(out, k.kind)[k.index] for k in usable])
    after = float(np.sqrt(np.nanmean(np.where(mask, fitted - ref, np.nan) ** 2)))
    info = _partial_info(usable, d, axes, n_free, before, after, dropped)
    out, info = judge_known(out, info, result, sol, data, usable, aligned, Rm, d, fr, fs, spec.offsets,
                            spec.noise, mirror_stated=side is not None, mirror_fit=other,
                            local_blind=_local_blind(data, sol, spec))
    return FramedToaResult(out, info)


def _local_blind(data: Any, sol: Any, spec: _Refit) -> Any:
    """The blind model refitted from the constrained fit ``sol`` (no constraint, no covariance):
    the nested model of the known test at the same minimum; None when the refit fails."""
    from ...errors import DegenerateGeometryError
    from ..engine.nls import refine_toa

    c, ok_r, ok_s = data.c, data.ok_r, data.ok_s
    try:
        return refine_toa(data.Y[np.ix_(ok_r, ok_s)], sol.receivers, sol.sources, offsets=spec.offsets,
                          common_offsets=spec.common, receiver_offsets0=sol.receiver_offsets,
                          source_offsets0=sol.source_offsets, loss=spec.loss,
                          f_scale=spec.metres(spec.f_scale, c), covariance=False)
    except (DegenerateGeometryError, np.linalg.LinAlgError, ValueError):
        return None


def _mirror_start(sol: Any, data: Any, usable: Sequence[KnownNode], axes: tuple[str, ...], n_free: int,
                  other_motion: tuple[Array, Array, float]) -> tuple[Array, Array] | None:
    """The start of the mirror candidate of a fit to partial known coordinates, or None.

    Every rigid motion the known coordinates fix (no freedom left): the blind fit moved by the
    best motion of the other handedness. Otherwise a reflection of the free axes alone is a
    gauge, not an alternative; the candidate reflects the fixed axes: one axis (heights) through
    the mean known value (``z -> 2 mean(z_known) - z``), several through the best-fitting
    line / plane of the known nodes within them. No fixed axis: None (nothing to mirror).
    """
    from ..verdict.known_test import candidate_mirror

    R0, S0, ok_r, ok_s = data.receivers, data.sources, data.ok_r, data.ok_s
    d = R0.shape[1]
    if n_free == 0:
        Rm, t, _ = other_motion
        return R0 @ Rm.T + t, S0 @ Rm.T + t
    idx = ["xyz".index(a) for a in axes]
    if not idx or len(idx) == d:
        return None
    R, S = _full(np.asarray(sol.receivers), ok_r), _full(np.asarray(sol.sources), ok_s)
    P = np.array([k.position[idx] for k in usable if k.mask[idx].all()], float)
    if P.shape[0] == 0:
        return None
    if len(idx) == 1:
        cen, Q = P.mean(0), -np.eye(1)
    else:
        rank = _affine_rank(P)[0]
        got = candidate_mirror(P, rank)
        if got is None:
            return None
        cen, Q = got
    out = []
    for X in (R, S):
        Y = X.copy()
        Y[:, idx] = cen + (X[:, idx] - cen) @ np.asarray(Q).T
        out.append(Y)
    return out[0], out[1]


def _full(P: Array, ok: NDArray[np.bool_]) -> Array:
    out = np.full((ok.size, P.shape[1]), np.nan)
    out[ok] = P
    return out


def _prior_misfit(sol: Any, usable: Sequence[KnownNode], ok_r: NDArray[np.bool_], ok_s: NDArray[np.bool_]) -> float:
    """``sum |p - mu|^2 / std^2`` over the known coordinates given with a std (sol on the located nodes)."""
    R, S = _full(np.asarray(sol.receivers), ok_r), _full(np.asarray(sol.sources), ok_s)
    tot = 0.0
    for k in usable:
        if k.std is not None:
            p = (R if k.kind == "receiver" else S)[k.index]
            tot += float(np.sum((p[k.mask] - k.position[k.mask]) ** 2)) / k.std**2
    return tot


def _on_side(sol: Any, usable: Sequence[KnownNode], ok_r: NDArray[np.bool_], ok_s: NDArray[np.bool_],
             side: str) -> bool:
    """Whether most free nodes lie ``side`` ("below" / "above") of the known heights' mean level."""
    from ...errors import InputError

    if side not in ("below", "above"):
        raise InputError(f"side must be 'below' or 'above', got {side!r}")
    R, S = _full(np.asarray(sol.receivers), ok_r), _full(np.asarray(sol.sources), ok_s)
    if R.shape[1] != 3:
        raise InputError("side (below / above the known nodes) applies to 3-D fits only")
    zk = [k.position[2] for k in usable if k.mask[2]]
    if not zk:
        raise InputError("side (below / above) needs known heights (a z coordinate in --known)")
    free_r, free_s = np.ones(len(R), bool), np.ones(len(S), bool)
    for k in usable:
        (free_r if k.kind == "receiver" else free_s)[k.index] = False
    z = np.concatenate([R[free_r, 2], S[free_s, 2]])
    z = z[np.isfinite(z)]
    h = float(np.median(z)) - float(np.mean(zk)) if z.size else 0.0
    return (h < 0) == (side == "below")


def _rotation(p: Array, d: int) -> Array:
    """The rotation of a rotation vector (3-D, Rodrigues) or an angle (2-D)."""
    if d == 3:
        th = float(np.linalg.norm(p))
        K = np.array([[0.0, -p[2], p[1]], [p[2], 0.0, -p[0]], [-p[1], p[0], 0.0]])
        if th < 1e-8:
            return np.eye(3) + K
        return np.eye(3) + np.sin(th) / th * K + (1.0 - np.cos(th)) / th**2 * (K @ K)
    cs, sn = np.cos(p[0]), np.sin(p[0])
    return np.array([[cs, -sn], [sn, cs]])


def _masked_rigid(est: Array, ref: Array, w: Array, scale: float) -> list[tuple[Array, Array, float]]:
    """The best rigid motion ``y = R x + t`` of each handedness onto known coordinates.

    Minimises ``sum_k w_k sum_{c known} ((R est_k + t)_c - ref_kc)^2`` over proper rotations
    and over improper ones (``R = Q F``, ``F`` the reflection of the last axis) by SciPy
    ``least_squares`` (trf) from the cube group's 24 rotations (4 in 2-D). The freedoms the
    known coordinates leave (a rotation about z and horizontal translations when only
    heights are known) do not move from their start: the start at ``R = F``, ``t`` zero
    along axes without a known coordinate (the blind fit's canonical gauge) is kept when it
    reaches the best cost (within 1e-9 relative), so those freedoms stay at the blind
    solution's principal axes and centroid. Returns ``[(R, t, cost)]``, the better
    handedness first (the proper one on a tie at round-off).
    """
    from scipy.optimize import least_squares

    k, d = est.shape
    mask = np.isfinite(ref)
    refz = np.where(mask, ref, 0.0)
    sw = np.sqrt(np.asarray(w, float) / float(np.max(w)))
    nr = 3 if d == 3 else 1
    if d == 3:
        from scipy.spatial.transform import Rotation

        starts = list(Rotation.create_group("O").as_rotvec())
        starts.sort(key=lambda v: float(np.linalg.norm(v)))  # the identity first
    else:
        starts = [np.array([a]) for a in (0.0, np.pi / 2, np.pi, -np.pi / 2)]
    out = []
    for H in (np.eye(d), np.diag([1.0] * (d - 1) + [-1.0])):
        def fun(x: Array, H: Array = H) -> Array:
            E = (est @ (_rotation(x[:nr], d) @ H).T + x[nr:] - refz) * sw[:, None]
            return E[mask]

        def run(p0: Array, nfev: int, H: Array = H) -> Any:
            R0 = _rotation(p0, d) @ H
            t0 = np.array([np.mean((refz - est @ R0.T)[mask[:, c], c]) if mask[:, c].any() else 0.0
                           for c in range(d)])
            return least_squares(fun, np.concatenate([p0, t0]), method="trf", x_scale=np.r_[
                np.ones(nr), np.full(d, scale)], xtol=1e-12, ftol=1e-12, gtol=1e-12, max_nfev=nfev)

        # every start a few steps, the identity and the best of the others to convergence
        sols = [run(starts[0], 200)]
        screen = [run(p0, 8) for p0 in starts[1:]]
        if screen:
            top = min(screen, key=lambda r: r.cost)
            sols.append(least_squares(fun, top.x, method="trf", x_scale=np.r_[np.ones(nr), np.full(d, scale)],
                                      xtol=1e-12, ftol=1e-12, gtol=1e-12, max_nfev=200))
        best = min(sols, key=lambda r: r.cost)
        floor = 1e-18 * scale**2 * max(int(mask.sum()), 1)
        if sols[0].cost <= best.cost * (1.0 + 1e-9) + floor:  # the blind gauge reaches the optimum
            best = sols[0]
        R = _rotation(best.x[:nr], d) @ H
        out.append((R, best.x[nr:], 2.0 * float(best.cost)))
    tie = 1e-10 * (scale**2) * max(int(mask.sum()), 1)
    if out[1][2] < out[0][2] * (1.0 - 1e-6) - tie:
        out = out[::-1]
    return out


def _partial_info(usable: Sequence[KnownNode], d: int, axes: tuple[str, ...], n_gauge: int, before: float,
                  after: float, dropped: Sequence[str]) -> FrameInfo:
    names = tuple(k.name for k in usable)
    free = [a for a in "xyz"[:d] if a not in axes]
    given = sorted({a for k in usable for a, m in zip("xyz"[:d], k.mask, strict=False) if m}, key="xyz".index)
    msg = (f"{len(usable)} known node(s), coordinates {','.join(given)} given; frame axes fixed by them: "
           f"{','.join(axes) if axes else 'none'}")
    if free:
        msg += (f"; {','.join(free)} canonical (direction and origin held nearest the blind solution's "
                "principal axes and centroid: a gauge the known coordinates leave)")
    if dropped:
        msg += f"; known node(s) without an estimate ignored: {', '.join(dropped)}"
    return FrameInfo(kind="known", references=names, rank=len(axes), determined=n_gauge == 0,
                     residual_gauge=n_gauge, mirror_resolved=False, message=msg,
                     known_rms=before, known_rms_fit=after, axes_fixed=axes)


def align_known(result: Any, known: Sequence[KnownNode]) -> FramedToaResult:
    """Move a calibration onto known node positions by a rigid motion only (no refit).

    Step 1 of :func:`fit_known` on its own, for results without a range matrix to refit
    (the acoustic pipeline, whose model is the event times): the weighted least-squares
    rigid motion (Kabsch; weights ``1 / std^2``; a mirror image only when the known nodes
    span the space) applied to every position, the covariances rotated with it. The fit
    itself is unchanged; :class:`FrameInfo` says what the known nodes leave undetermined.

    Parameters
    ----------
    result : any result with ``receivers``, ``sources`` and their covariances (dataclass).
    known : from :func:`selfcal.toa.frame.frame.parse_known`.

    Returns
    -------
    :class:`FramedToaResult` in the known nodes' frame (``known_rms`` = ``known_rms_fit``:
    the RMS distance, m, of the moved estimates from the known positions).

    Examples
    --------
    >>> import numpy as np
    >>> from selfcal.toa import solve_toa
    >>> from selfcal.toa.frame.frame import parse_known
    >>> from selfcal.toa.engine.nls import toa_model
    >>> rng = np.random.default_rng(0)
    >>> r, s = rng.uniform(0, 5, (6, 3)), rng.uniform(0, 5, (8, 3))
    >>> res = solve_toa(toa_model(r, s), rng=0)
    >>> out = align_known(res, parse_known({f"r{i}": r[i] for i in range(4)}, 6, 8, 3))
    >>> bool(np.allclose(out.receivers, r, atol=1e-6))
    True
    """
    from ...errors import InputError
    from ...geometry import rotate_covariances

    part = [k.name for k in known if not k.full]
    if part:
        raise InputError(f"known node(s) {', '.join(part)}: only some coordinates given; moving a result "
                         "without refitting it takes whole positions")
    R0 = np.asarray(result.receivers, float)
    S0 = np.asarray(result.sources, float)
    d = R0.shape[1]
    usable, dropped, est, ref, w, rank = _matched(
        result, known, lambda k: bool(np.isfinite(node_positions(result, k.kind)[k.index]).all()))
    Rm, t = _rigid(est, ref, w, allow_reflection=rank == d)
    rms = float(np.sqrt(np.mean(np.sum((est @ Rm.T + t - ref) ** 2, axis=1))))
    fields: dict[str, Any] = {"receivers": R0 @ Rm.T + t, "sources": S0 @ Rm.T + t,
                              "method": f"{result.method}+aligned({len(usable)} known)"}
    for key in ("receiver_cov", "source_cov"):
        cov = getattr(result, key)
        if cov is not None:
            fields[key] = rotate_covariances(np.asarray(cov, float), Rm)
    if result.uniqueness is not None:  # the alternatives in the same frame
        fields["uniqueness"] = result.uniqueness.moved(Rm, t)
    out = replace_fields(result, **fields)
    return FramedToaResult(out, _known_info(usable, rank, d, rms, rms, dropped))


def _matched(result: Any, known: Sequence[KnownNode], located: Any) -> tuple[Any, ...]:
    """The known nodes the result located, their estimates, known positions, weights, rank.

    Returns ``(usable, dropped names, est (k, d), ref (k, d), weights (k,), affine rank of ref)``;
    a node without a std is weighted as one known to 1e-6 of the known nodes' spread.
    """
    usable = [k for k in known if located(k)]
    dropped = [k.name for k in known if k not in usable]
    if not usable:
        raise DegenerateGeometryError("none of the known nodes has an estimated position", kind="degenerate-frame")
    est = np.array([node_positions(result, k.kind)[k.index] for k in usable])
    ref = np.array([k.position for k in usable], float)  # NaN: a coordinate not known
    stds = np.array([k.std if k.std is not None else 0.0 for k in usable])
    full = np.isfinite(ref).all(1)
    rank, spread = _affine_rank(ref[full])
    if not full.all():  # the spread of the coordinates given
        spread = max(spread, float(np.nanmax(np.nanmax(ref, 0) - np.nanmin(ref, 0))))
    tiny = max(1e-3 * spread, 1e-9) if spread > 0 else 1e-3
    return usable, dropped, est, ref, 1.0 / np.maximum(stds, tiny * 1e-3) ** 2, rank


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
    return replace_fields(
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
