"""Known node positions for a TOA calibration: constrain the fit and set the frame.

``known=`` (``--known FILE.csv``, ``name,x,y,z[,std]``): the blind solution is moved onto
the known nodes by a weighted least-squares rigid motion (Kabsch), then refined by
:func:`selfcal.toa.engine.nls.refine_toa` with the exact nodes as fixed rows and the others as
Gaussian priors. ``k`` affinely independent known nodes fix a rigid motion in ``d``
dimensions only when ``k >= d + 1``; what they leave open (a mirror, a rotation about a
line, every rotation) is held at the blind solution's canonical gauge and reported in
:class:`selfcal.toa.frame.nodes.FrameInfo`. Re-exported by :mod:`selfcal.toa.frame.frame`.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ...errors import DegenerateGeometryError
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
    known: from :func:`parse_known`.
    offsets, loss, f_scale, max_nfev, covariance: as for :func:`selfcal.toa.engine.nls.refine_toa`
        (``f_scale`` / ``noise`` in the matrix's units); ``offsets="common"``: one offset
        shared by every receiver (``common_offsets="receivers"``), the model the moving-tag
        recipe keeps (:func:`selfcal.toa.recipes.common_offset.choose_common_offset`).
    noise: range noise std in the matrix's units, weighting the priors.
    side: "below" | "above": in 3-D, the other nodes lie below / above the plane of coplanar
        known nodes (along the known frame's z): resolves the mirror they leave
        (:func:`selfcal.toa.verdict.known_test.choose_side`); None = the mirror is tested and reported.
    jackknife: scale each free receiver's covariance by the block jackknife's evidence
        (:func:`selfcal.toa.verdict.crossval.block_jackknife_scale`: the constrained fit
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
    from ..engine.nls import refine_toa

    data = refit_data(result, matrix)
    c, R0, S0, ok_r, ok_s = data.c, data.receivers, data.sources, data.ok_r, data.ok_s
    I, d = R0.shape
    J = S0.shape[0]
    usable, dropped, est, ref, w, rank = _matched(
        result, known, lambda k: bool((ok_r if k.kind == "receiver" else ok_s)[k.index]))
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
    # "common": one offset shared by every receiver (the moving-tag recipe's kept model)
    off, common = ("receivers", "receivers") if offsets == "common" else (offsets, "none")
    sol = refine_toa(data.Y[np.ix_(ok_r, ok_s)], Ra[ok_r], Sa[ok_s], offsets=off, common_offsets=common,
                     receiver_offsets0=data.receiver_offsets, source_offsets0=data.source_offsets, loss=loss, f_scale=None if f_scale is None else f_scale * c,
                     noise=None if noise is None else noise * c, max_nfev=max_nfev,
                     covariance=covariance, **kw)
    scaled = None
    if jackknife and covariance:
        sol, scaled = _jackknife(sol, data.Y[np.ix_(ok_r, ok_s)], dict(
            offsets=off, common_offsets=common, loss=loss, f_scale=None if f_scale is None else f_scale * c,
            noise=None if noise is None else noise * c, max_nfev=max_nfev, **kw))
    out = _embed(result, sol, ok_r, ok_s, c, f"{result.method}+known({len(usable)})")
    fitted = np.array([node_positions(out, k.kind)[k.index] for k in usable])
    after = float(np.sqrt(np.mean(np.sum((fitted - ref) ** 2, axis=1))))
    info = _known_info(usable, rank, d, before, after, dropped)
    # the known positions tested against the ranges, the frame's mirror against the data
    from ..verdict.known_test import judge_known

    out, info = judge_known(out, info, result, sol, data, usable, est @ Rm.T + t, Rm, rank, fr, fs, off, noise,
                            mirror_stated=side is not None)
    if scaled is not None:
        names = [f"r{i}" for i in np.nonzero(ok_r)[0]]
        info = dataclasses.replace(info, error_scale=scaled.to_dict(names))
    return FramedToaResult(out, info)


def _jackknife(sol: Any, Y: Array, kw: dict[str, Any]) -> tuple[Any, Any]:
    """``sol`` with its receivers' covariances scaled by the block jackknife, and the scale (or None)."""
    from ..engine.nls import refine_toa
    from ..verdict.crossval import block_jackknife_scale

    if sol.receiver_cov is None or sol.residuals is None or not np.isfinite(sol.receiver_cov).all():
        return sol, None
    per_source = {"fixed_sources", "source_prior"}

    def cols_of(v: Any, cols: NDArray[np.bool_]) -> Any:
        return tuple(a[cols] for a in v) if isinstance(v, tuple) else np.asarray(v)[cols]

    def refit(cols: NDArray[np.bool_]) -> Array:
        fkw = {k: (cols_of(v, cols) if k in per_source else v) for k, v in kw.items()}
        so = None if sol.source_offsets is None else np.asarray(sol.source_offsets)[cols]
        return refine_toa(Y[:, cols], sol.receivers, sol.sources[cols], receiver_offsets0=sol.receiver_offsets,
                          source_offsets0=so, covariance=False, **fkw).receivers

    js = block_jackknife_scale(sol.residuals, sol.receivers, sol.receiver_cov, refit)
    if js is None:
        return sol, None
    cov = sol.receiver_cov * js.scale[:, None, None]
    if kw.get("offsets") == "receivers" and kw.get("common_offsets") == "receivers":
        extra = _bias_effect(sol, Y, kw)
        if extra is not None:
            tau, add = extra
            cov = cov + add
            js = dataclasses.replace(js, bias_tau=tau)
    return dataclasses.replace(sol, receiver_cov=cov), js


_BIAS_ALPHA = 0.05  # level of the test that the per-receiver offsets spread beyond their noise
_BIAS_STEP = 0.01  # m, the finite-difference step of a row's bias (the fit is linear in it at this scale)


def _bias_effect(sol: Any, Y: Array, kw: dict[str, Any]) -> tuple[float, Array] | None:
    """Random per-receiver biases around the common offset: ``(tau, tau^2 G_i G_i^T per receiver)``.

    ``sol`` is the common-offset fit of ``Y`` (metres) with the fit options ``kw``; None when
    the per-receiver refit or a shifted refit fails.
    """
    from scipy.stats import chi2

    from ..engine.nls import refine_toa

    I = Y.shape[0]
    base = {k: v for k, v in kw.items() if k not in ("offsets", "common_offsets")}
    try:
        full = refine_toa(Y, sol.receivers, sol.sources, offsets="receivers", receiver_offsets0=sol.receiver_offsets,
                          source_offsets0=sol.source_offsets, covariance=True, **base)
        d = np.asarray(full.receiver_offsets, float)
        var = np.asarray(full.receiver_offset_std, float) ** 2
        if not (np.isfinite(d).all() and np.isfinite(var).all()) or I < 2:
            return None
        tau2 = max(0.0, float(np.sum((d - d.mean()) ** 2) - (1 - 1 / I) * np.sum(var)) / (I - 1))
        # no spread beyond the offsets' own noise (chi-square of their deviations from the
        # precision-weighted mean, level 0.05): no random effect
        w = 1.0 / var
        spread = float(np.sum(w * (d - np.sum(w * d) / np.sum(w)) ** 2))
        if tau2 == 0.0 or spread <= chi2.ppf(1 - _BIAS_ALPHA, I - 1):
            return 0.0, np.zeros_like(sol.receiver_cov)
        G = np.zeros((*sol.receivers.shape, I))
        for k in range(I):
            Yk = Y.copy()
            Yk[k] += _BIAS_STEP
            sk = refine_toa(Yk, sol.receivers, sol.sources, receiver_offsets0=sol.receiver_offsets,
                            source_offsets0=sol.source_offsets, covariance=False, **kw)
            G[:, :, k] = (sk.receivers - sol.receivers) / _BIAS_STEP
    except (DegenerateGeometryError, np.linalg.LinAlgError, ValueError):
        return None
    return float(np.sqrt(tau2)), tau2 * np.einsum("iak,ibk->iab", G, G)


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
    from ...geometry import rotate_covariances

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
    if getattr(result, "uniqueness", None) is not None:  # the alternatives in the same frame
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
    ref = np.array([k.position for k in usable], float)
    stds = np.array([k.std if k.std is not None else 0.0 for k in usable])
    rank, spread = _affine_rank(ref)
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
