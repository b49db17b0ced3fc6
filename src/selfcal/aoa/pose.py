"""``solve_aoa``: receiver position and orientation from bearings to known beacons (paper 001).

Methods (3-D unless stated):

``"sol1"``  paper Solution 1: Newton on the torus equations (eq. 7-8), orientation eq. 14/15-18.
``"sol2"``  paper Solution 2: Newton on the cosine-rule ranges (eq. 19-20), orientation eq. 23/25,
            location eq. 27.
``"p3p"``   every solution of the three-beacon problem in closed form (quartic), each
            candidate's pose by a rigid fit; a fourth beacon (if any) picks among them.
``"ml"``    the P3P candidates refined by maximum likelihood over all beacons (rotation on
            SO(3)), with covariance; the candidate of least cost wins.
``"linear"`` (2-D) the closed-form linear resection; ``"ml"`` refines it.
``"auto"``  ``"ml"``.

The shared pieces live in :mod:`.result` (result types) and :mod:`.checks` (validation,
degeneracy checks, the residual test); the methods in their own modules (:mod:`.solution1`,
:mod:`.solution2`, :mod:`.p3p`, :mod:`.ml`, :mod:`.planar2d`), named in
:data:`METHODS_3D` / :data:`METHODS_2D`; public names are re-exported here as before.
"""

from __future__ import annotations

from dataclasses import replace
from itertools import combinations
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .._checks import as_points, check_choice, entry
from ..errors import DegenerateGeometryError, InputError
from .checks import (
    _area,
    _best_triple,
    _check_determined,
    _count_distinct,
    _fit,
    _rms,
    _validate,
)
from .ml import refine_ml
from .orientation import nearest_rotation
from .p3p import p3p
from .planar2d import DANGER_TOL, linear_pose_2d
from .result import AoaCandidate, AoaResult
from .solution1 import solution1
from .solution2 import solution2

Array = NDArray[Any]

__all__ = ["AoaResult", "AoaCandidate", "solve_aoa", "METHODS_3D", "METHODS_2D"]

METHODS_3D = ("auto", "sol1", "sol2", "p3p", "ml")
METHODS_2D = ("auto", "linear", "ml")
#: relative tolerance on a candidate's cost to call two candidates equally good (ambiguous)
TIE_TOL = 1e-6

# ----------------------------------------------------------------------------- solver


@entry(beacons="array", bearings="array", sigma="positive?", max_iter="count", position_hint="array",
       orthonormalize="bool", sign_z_unknown="bool")
def solve_aoa(
    beacons: ArrayLike,
    bearings: ArrayLike,
    *,
    method: str = "auto",
    noise: str = "sphere",
    sigma: float | None = None,
    orthonormalize: bool = True,
    max_iter: int = 50,
    position_hint: ArrayLike | None = None,
    sign_z_unknown: bool = False,
) -> AoaResult:
    """Receiver position and orientation from bearings to known beacons (paper 001).

    Parameters
    ----------
    beacons : (N, d) known beacon positions in metres, d in {2, 3}, N >= 3, not collinear.
    bearings : (N, d) or batched (B, N, d) direction of each beacon in the receiver frame
        (normalised here; a NaN row marks a missing beacon for a single receiver). In 3-D
        the model is ``bearing_k = R^T (b_k - m) / |b_k - m|`` (paper eq. 2, 11).
    method : 3-D ``"auto" | "sol1" | "sol2" | "p3p" | "ml"``; 2-D ``"auto" | "linear" | "ml"``
        (see the module notes; ``"auto"`` is ``"ml"``).
    noise : ML noise model, ``"sphere"`` (isotropic angular) or ``"angles"`` (Gaussian on the
        angles alpha, beta with the local x and y axes, the paper's simulation model).
    sigma : angular noise std (rad) for the ML covariance; None estimates it when N > 3 (3-D)
        or N > 3 (2-D) and leaves it NaN otherwise.
    orthonormalize : project the paper solutions' rotation (eq. 14/17-18/23/25) onto SO(3).
    max_iter : iteration cap for Newton / Levenberg-Marquardt.
    position_hint : (d,) or None
        Side information for ambiguous problems (three beacons in 3-D): among the candidates
        that explain the bearings equally well, return the one nearest to this point. It never
        enters the cost; without it ties go to the first candidate (all are in ``candidates``).
    sign_z_unknown : bool
        The bearings came from the angles with the receiver's x and y axes (paper eq. 2-4,
        ``--angles axes``), which do not tell on which side of the receiver's xy plane a
        beacon is (eq. 4 takes the front hemisphere). Then every method is followed by the
        maximum-likelihood refinement under the ``"angles"`` noise model (which depends only
        on those two angles), started from the method's solutions for every sign pattern of
        the beacons' z components (all 2^N for N <= 8, else those of the best-conditioned
        triple), and the least-cost pose is returned (``method`` = ``"<method>+ml"``); the
        reported bearings' z signs are the ones this pose predicts. 3-D, one receiver.

    Returns
    -------
    AoaResult

    Raises
    ------
    InputError
        Wrong shapes, inf, zero-length bearings, unknown method.
    DegenerateGeometryError
        ``too-few-beacons``, ``collinear-beacons``, ``receiver-on-beacon-plane`` (3-D, all
        bearings coplanar), ``danger-cylinder`` (3-D, every method) / ``danger-circle``
        (2-D): the pose Jacobian is singular at the solution.

    Notes
    -----
    ``success`` comes from :func:`~selfcal.aoa.checks.residual_test` (chi-square on the angular residuals).

    Examples
    --------
    Noise-free bearings from a receiver at ``m`` (axes aligned with the global frame) to
    six beacons:

    >>> import numpy as np
    >>> import selfcal
    >>> rng = np.random.default_rng(5)
    >>> beacons = rng.uniform(-5, 5, (6, 3))
    >>> m = np.array([0.3, -0.2, 0.1])
    >>> bearings = (beacons - m) / np.linalg.norm(beacons - m, axis=1, keepdims=True)
    >>> res = selfcal.solve_aoa(beacons, bearings)
    >>> res.success, np.allclose(res.position, m), np.allclose(res.rotation, np.eye(3))
    (True, True, True)
    """
    if sign_z_unknown:
        return _solve_sign_ambiguous(beacons, bearings, method=method, sigma=sigma,
                                     orthonormalize=orthonormalize, max_iter=max_iter,
                                     position_hint=position_hint)
    b, U, batched = _validate(beacons, bearings)
    N, d = b.shape
    check_choice(method, "method", METHODS_3D if d == 3 else METHODS_2D)
    check_choice(noise, "noise", ("sphere", "angles"))
    if d == 2 and noise != "sphere":
        raise InputError("noise='angles' is a 3-D model; in 2-D the residual is the bearing angle")
    if method == "auto":
        method = "ml"
    hint = None
    if position_hint is not None:
        hint = np.asarray(position_hint, float).reshape(-1)
        if hint.shape != (d,) or not np.isfinite(hint).all():
            raise InputError(f"position_hint must be {d} finite numbers, got {position_hint!r}")
    B = U.shape[0]
    cov: Array | None = None
    cand: tuple[AoaCandidate, ...] = ()
    if d == 2:
        m, R, cond = linear_pose_2d(b, U)
        if (cond <= DANGER_TOL).any():
            k = int(np.argmax(cond <= DANGER_TOL))
            raise DegenerateGeometryError(
                f"receiver {k} lies on the circle through the beacons: every point of that arc sees "
                "the same bearing differences; add a beacon off that circle",
                kind="danger-circle",
            )
        iters = np.zeros(B, int)
        conv = np.ones(B, bool)
        ncand = np.ones(B, int)
        if method == "ml":
            out = refine_ml(b, U, m, R, sigma=sigma, max_iter=max_iter)
            m, R, cov = out["position"], out["rotation"], out["covariance"]
            iters, conv = out["iterations"], out["converged"]
        bad = _check_determined(b, U, m, R, "danger-circle", raise_=not batched)
        conv = np.array(conv, bool, copy=True)
        conv[bad] = False
    elif method in ("sol1", "sol2"):
        if method == "sol1":
            out = solution1(b, U, orthonormalize=orthonormalize, max_iter=max(max_iter, 60))
        else:
            out = solution2(b, U, orthonormalize=orthonormalize, max_iter=max_iter)
        m, A = out["position"], out["A"]
        R = np.swapaxes(A, -1, -2)
        iters, conv = out["iterations"], out["converged"]
        ncand = np.ones(B, int)
        if method == "sol1":
            ncand = _count_distinct(out["roots"], out["root_ok"])
            if not batched:
                cand = _sol1_candidates(b, U, out, orthonormalize)
        # the paper's solutions are as undetermined on the danger cylinder as P3P is
        bad = _check_determined(b, U, m, R, "danger-cylinder", raise_=not batched)
        conv = np.array(conv, bool, copy=True)
        conv[bad] = False
        if not conv.all():
            import warnings

            from ..errors import ConvergenceWarning

            warnings.warn(
                f"{method}: Newton did not converge for {int(np.sum(~np.asarray(conv, bool)))} of {B} receivers",
                ConvergenceWarning,
                stacklevel=2,
            )
    else:
        tri = _best_triple(b)
        pos, rot, valid = p3p(b[tri], U[:, tri])  # (B, 4, 3), (B, 4, 3, 3)
        if not batched and not valid.any() and N > 3:
            # noise can make one triple's cosines inconsistent; the others still start the ML
            for alt in sorted(combinations(range(min(N, 12)), 3), key=lambda t: -_area(b, t)):
                pos, rot, valid = p3p(b[list(alt)], U[:, list(alt)])
                if valid.any():
                    break
        if not batched and not valid.any():
            k = int(np.argmin(valid.any(axis=1)))
            raise DegenerateGeometryError(
                f"receiver {k}: the bearings admit no pose for beacons {tri.tolist()} (measurements "
                "inconsistent with the beacon triangle, or too noisy)",
                kind="no-solution",
            )
        S = pos.shape[1]
        flat_valid = valid.reshape(-1)
        Uc = np.repeat(U, S, axis=0)
        mc = np.where(flat_valid[:, None], pos.reshape(-1, 3), np.nan)
        Rc = np.where(flat_valid[:, None, None], rot.reshape(-1, 3, 3), np.eye(3))
        cost = np.full(B * S, np.inf)
        itc, convc = np.zeros(B * S, int), flat_valid.copy()
        covc = np.full((B * S, 6, 6), np.nan)
        v = flat_valid
        if method == "ml":
            out = refine_ml(b, Uc[v], mc[v], Rc[v], noise=noise, sigma=sigma, max_iter=max_iter)
            mc[v], Rc[v] = out["position"], out["rotation"]
            cost[v] = out["residual_rms"]
            covc[v] = out["covariance"]
            itc[v], convc[v] = out["iterations"], out["converged"]
        else:
            cost[v] = _rms(b, Uc[v], mc[v], Rc[v])
        cost = np.where(flat_valid, cost, np.inf).reshape(B, S)
        best = np.argmin(cost, axis=1)
        rows = np.arange(B)
        pick = rows * S + best
        m, R = mc[pick], Rc[pick]
        iters, conv = itc[pick], convc[pick]
        if method == "ml":
            cov = covc[pick]
        tie = cost <= cost[rows, best][:, None] * (1 + TIE_TOL) + 1e-9
        tie &= valid
        mcs = mc.reshape(B, S, 3)
        if hint is not None:
            # equally good candidates: the side information decides (nearest to the hint)
            dist = np.where(tie, np.linalg.norm(mcs - hint, axis=-1), np.inf)
            best = np.argmin(dist, axis=1)
            pick = rows * S + best
            m, R = mc[pick], Rc[pick]
            iters, conv = itc[pick], convc[pick]
            if method == "ml":
                cov = covc[pick]
        # distinct candidates among the ties (several P3P roots may refine to one optimum)
        ncand = _count_distinct(mcs, tie)
        if not batched:
            kept: list[AoaCandidate] = []
            for s_ in [int(best[0]), *np.argsort(cost[0]).tolist()]:
                p_ = mc[s_]
                if tie[0, s_] and all(np.linalg.norm(p_ - c.position) > 1e-6 * (1 + np.linalg.norm(p_)) for c in kept):
                    kept.append(AoaCandidate(p_.copy(), Rc[s_].copy(), float(cost[0, s_])))
            cand = tuple(kept)
        # a degenerate candidate among the equally good ones (the double root of the danger
        # cylinder comes with a regular twin) means the bearings do not determine the pose
        tb, ts = np.nonzero(tie)
        bad = _check_determined(
            b, U[tb], mcs[tb, ts], Rc.reshape(B, S, 3, 3)[tb, ts], "danger-cylinder", tb, raise_=not batched
        )
        conv = np.array(conv, bool, copy=True)
        conv[bad] = False  # batched: an undetermined receiver is flagged, not fatal
    rms = _rms(b, U, m, R)
    fit = _fit(rms, N, d, sigma, batched)
    if not batched:
        return AoaResult(
            position=m[0], rotation=R[0], residual_rms=float(rms[0]), method=method,
            converged=bool(conv[0]), iterations=int(iters[0]),
            covariance=None if cov is None else cov[0], candidates=cand, n_candidates=int(ncand[0]), fit=fit,
        )
    return AoaResult(
        position=m, rotation=R, residual_rms=rms, method=method, converged=conv,
        iterations=iters, covariance=cov, candidates=(), n_candidates=ncand, fit=fit,
    )


def _solve_sign_ambiguous(beacons: ArrayLike, bearings: ArrayLike, *, method: str, sigma: float | None,
                          orthonormalize: bool, max_iter: int, position_hint: ArrayLike | None) -> AoaResult:
    """:func:`solve_aoa` for bearings whose z-signs are unknown (see ``sign_z_unknown``)."""
    b_all = as_points(beacons, "beacons")
    if b_all.shape[1] != 3:
        raise InputError("sign_z_unknown applies to 3-D bearings (angles with the receiver's x and y axes)")
    U0 = np.array(bearings, dtype=float)
    if U0.ndim != 2:
        raise InputError("sign_z_unknown: one receiver at a time (bearings (N, 3))")
    b, U1, _ = _validate(b_all, U0)
    U = U1[0]
    N = len(b)
    check_choice(method, "method", METHODS_3D)
    idx = np.arange(N) if N <= 8 else _best_triple(b)
    pats = np.array(np.meshgrid(*[[1.0, -1.0]] * len(idx), indexing="ij")).reshape(len(idx), -1).T
    Ub = np.repeat(U[None], len(pats), axis=0)
    Ub[:, idx, 2] *= pats
    ms, Rs = [], []
    base = "ml" if method == "auto" else method
    if base in ("sol1", "sol2"):
        import warnings

        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            out = (solution1(b, Ub, orthonormalize=True, max_iter=max(max_iter, 60)) if base == "sol1"
                   else solution2(b, Ub, orthonormalize=True, max_iter=max_iter))
        ms.append(out["position"])
        Rs.append(np.swapaxes(out["A"], -1, -2))
    else:
        tri = _best_triple(b)
        pos, rot, valid = p3p(b[tri], Ub[:, tri])
        ms.append(np.where(valid[..., None], pos, np.nan).reshape(-1, 3))
        Rs.append(rot.reshape(-1, 3, 3))
    mc, Rc = np.concatenate(ms), np.concatenate(Rs)
    ok = np.isfinite(mc).all(axis=1) & np.isfinite(Rc).all(axis=(1, 2))
    if not ok.any():
        raise DegenerateGeometryError("the bearings admit no pose for any side of the receiver plane",
                                      kind="no-solution")
    mc, Rc = mc[ok], nearest_rotation(Rc[ok])
    Uc = np.repeat(U[None], len(mc), axis=0)
    out = refine_ml(b, Uc, mc, Rc, noise="angles", sigma=sigma, max_iter=max(max_iter, 100))
    cost = np.where(np.asarray(out["converged"], bool), out["residual_rms"], np.inf)
    cost = np.where(np.isfinite(cost), cost, np.inf)
    best = int(np.argmin(cost))
    if position_hint is not None:
        hint = np.asarray(position_hint, float).reshape(-1)
        tie = cost <= cost[best] * (1 + TIE_TOL) + 1e-9
        best = int(np.argmin(np.where(tie, np.linalg.norm(out["position"] - hint, axis=1), np.inf)))
    m, R = out["position"][best], out["rotation"][best]
    # the bearings as this pose sees them: the measured x, y angles with the predicted z side
    g = b - m
    pz = (g @ R)[:, 2]
    Ufix = U.copy()
    Ufix[:, 2] = np.abs(U[:, 2]) * np.where(pz < 0, -1.0, 1.0)
    res = solve_aoa(b, Ufix, method="ml", sigma=sigma, max_iter=max_iter, position_hint=m)
    return replace(res, method=f"{base}+ml")


def _sol1_candidates(b: Array, U: Array, out: dict[str, Array], orthonormalize: bool) -> tuple[AoaCandidate, ...]:
    kept: list[AoaCandidate] = []
    for p, A, ok in zip(out["roots"][0], out["root_A"][0], out["root_ok"][0], strict=True):
        if not ok or any(np.linalg.norm(p - c.position) <= 1e-6 * (1 + np.linalg.norm(p)) for c in kept):
            continue
        R = A.T if not orthonormalize else nearest_rotation(A.T[None])[0]
        kept.append(AoaCandidate(p.copy(), R, float(_rms(b, U, p[None], R[None])[0])))
    return tuple(kept)
