"""Known nodes are tested, not imposed: the constrained fit against the blind one.

:func:`selfcal.toa.frame.known.fit_known` constrains a blind TOA fit by known node positions.
Known positions that contradict the ranges (a typo, a node at twice its coordinates, the
wrong node named) would otherwise bend the whole network onto them and inflate the noise
estimate until the result "passes". The test here (:func:`known_test`):

- ``T = (RSS_known - RSS_blind) / sigma^2 + sum_k |p_k - mu_k|^2 / std_k^2`` (the second term
  over nodes given with a standard deviation: their prior's misfit), on the same entries;
- under correct known positions ``T`` is chi-square with ``q = d k - f`` degrees of freedom
  (``k`` known nodes, ``f`` the rigid-motion freedoms they fix: ``d (d + 1) / 2`` less the
  rotations about their affine hull, ``(d - r)(d - r - 1) / 2`` for affine rank ``r``); the
  blind fit is the same model without those ``q`` constraints (nested, Wilks);
- noise given: ``chi2(q)`` test; noise estimated from the blind fit's residuals with its
  ``dof``: ``(T / q) ~ F(q, dof)``; rejected at :data:`KNOWN_ALPHA`;
- the known nodes that disagree: the blind fit, moved onto the known nodes by the
  weighted rigid motion, against each known position, standardised by the node's own
  covariance and its stated std (Bonferroni over the known nodes); the worst one when
  none alone is significant.

Known nodes that give only some coordinates (heights): ``q`` is the known coordinates
less the rigid freedoms they fix (:func:`gauge_left`), the blind fit is the blind model
refitted from the constrained one (:func:`judge_known`), and each node's discrepancy is
chi-square with as many dof as its known coordinates.

:func:`frame_mirror` gives the isometry a known set of affine rank ``r < d`` leaves (the
mirror through their plane, the half-turn about their line, the point reflection), which
:func:`selfcal.toa.verdict.uniqueness.uniqueness_test` then tests as an alternative of the free nodes.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..._result import json_float as _num

__all__ = ["KNOWN_ALPHA", "KnownTest", "candidate_mirror", "choose_side", "frame_mirror", "gauge_left", "judge_known",
           "known_test"]

Array = NDArray[np.float64]

#: level of the known-node test (the residual test's, selfcal.toa.verdict.trust.RESIDUAL_ALPHA)
KNOWN_ALPHA = 1e-3


@dataclass(frozen=True)
class KnownTest:
    """The test of known node positions against the ranges (:func:`known_test`).

    Attributes
    ----------
    statistic: ``T`` (chi-square form) or ``T / q`` (F form, noise estimated).
    dof: ``q``, the constraints beyond the gauge; dof_noise: the blind fit's residual dof
        (F form), else 0.
    p_value, alpha, passed: the test (``passed = not p < alpha``; True when ``q = 0``).
    disagreeing: names of the known nodes that contradict the ranges (empty when passed).
    """

    statistic: float
    dof: int
    dof_noise: int
    p_value: float
    alpha: float
    passed: bool
    disagreeing: tuple[str, ...] = ()

    def message(self) -> str:
        """One line for a failed test."""
        if self.passed:
            return ""
        return (f"the known positions contradict the ranges: the constrained fit is worse than the blind one "
                f"beyond the noise ({'F' if self.dof_noise else 'chi2'} = {self.statistic:.4g} on {self.dof} "
                f"constraint dof, p = {self.p_value:.2g} < {self.alpha:g}); disagreeing known node(s): "
                f"{', '.join(self.disagreeing)} (check their coordinates, units and names)")

    def to_dict(self) -> dict[str, Any]:
        """JSON-safe dictionary."""
        return {"test": "F" if self.dof_noise else "chi2", "statistic": _num(self.statistic), "dof": int(self.dof),
                "dof_noise": int(self.dof_noise), "p_value": _num(self.p_value), "alpha": float(self.alpha),
                "passed": bool(self.passed), "disagreeing": list(self.disagreeing)}


def gauge_fixed(d: int, rank: int) -> int:
    """Rigid-motion freedoms fixed by known nodes of affine rank ``rank`` in ``d`` dimensions."""
    r = min(max(int(rank), 0), d)
    return d * (d + 1) // 2 - (d - r) * (d - r - 1) // 2


def known_test(rss_known: float, rss_blind: float, prior_misfit: float, *, n_known: int, d: int, rank: int,
               noise2: float | None, dof_blind: int, names: Sequence[str], discrepancy: Array,
               alpha: float = KNOWN_ALPHA, q: int | None = None, node_dof: Sequence[int] | None = None) -> KnownTest:
    """Likelihood-ratio test of known positions (module docstring).

    Parameters
    ----------
    rss_known, rss_blind: residual sums of squares (m^2) of the constrained and the blind
        fit over the same entries.
    prior_misfit: ``sum_k |p_k - mu_k|^2 / std_k^2`` over the nodes given with a std.
    n_known, d, rank: the known nodes' count, the dimension, their affine rank.
    noise2: range noise variance (m^2) when given, else None (estimated from the blind fit).
    dof_blind: the blind fit's residual degrees of freedom.
    names: the known nodes' names; discrepancy: (k,) each node's standardised squared
        distance from its known position after the rigid alignment (chi-square, d dof).
    alpha: level.
    q: the constraints beyond the gauge when some nodes give only some coordinates (known
        coordinates less the rigid-motion freedoms they fix, :func:`gauge_left`); default
        ``d n_known - gauge_fixed(d, rank)``.
    node_dof: (k,) the known coordinates of each node (the chi-square dof of its
        ``discrepancy``); default ``d`` each.

    Returns
    -------
    KnownTest

    Examples
    --------
    >>> t = known_test(1.0, 1.0, 0.0, n_known=4, d=3, rank=3, noise2=1e-4, dof_blind=30,
    ...                names=["r0", "r1", "r2", "r3"], discrepancy=[0.1, 0.2, 0.3, 0.1])
    >>> t.dof, t.passed
    (6, True)
    """
    from scipy.stats import chi2
    from scipy.stats import f as fdist

    if q is None:
        q = d * int(n_known) - gauge_fixed(d, rank)
    if q <= 0:
        return KnownTest(0.0, 0, 0, 1.0, alpha, True)
    delta = max(float(rss_known) - float(rss_blind), 0.0)
    if noise2 is not None and noise2 > 0:
        T = delta / noise2 + float(prior_misfit)
        p = float(chi2.sf(T, q))
        stat, dn = T, 0
    elif dof_blind > 0 and rss_blind > 0:
        s2 = float(rss_blind) / dof_blind
        stat = (delta / s2 + float(prior_misfit)) / q
        p = float(fdist.sf(stat, q, dof_blind))
        dn = int(dof_blind)
    else:  # no spare measurement in the blind fit: nothing to test against
        return KnownTest(float("nan"), q, 0, float("nan"), alpha, True)
    passed = not p < alpha
    bad: tuple[str, ...] = ()
    if not passed:
        disc = np.asarray(discrepancy, float)
        nd = np.full(disc.size, d) if node_dof is None else np.asarray(node_dof, int)
        lim = chi2.ppf(1.0 - alpha / max(len(names), 1), nd)
        sel = np.flatnonzero(disc > lim)
        if sel.size == 0 and disc.size:
            sel = np.array([int(np.nanargmax(disc))])
        bad = tuple(names[i] for i in sel[np.argsort(-disc[sel])])
    return KnownTest(float(stat), q, dn, p, alpha, passed, bad)


def gauge_left(points: Array, mask: NDArray[np.bool_]) -> tuple[tuple[str, ...], int]:
    """The frame axes known coordinates fix, and the rigid-motion freedoms they leave.

    The small rigid motions ``p -> p + omega x p + u`` that leave every known coordinate of
    ``points`` unchanged (the null space of their Jacobian) are the freedoms left (a gauge);
    axis ``c`` is fixed (direction and origin) when none of them translates along it or
    turns it (rotations about ``c`` itself only).

    Parameters
    ----------
    points: (k, d) the known nodes' positions in the known frame (metres; any value where
        not known, e.g. the aligned estimate).
    mask: (k, d) bool, which coordinates are known.

    Returns
    -------
    ``(axes, n)``: the names of the fixed axes (``"x"``, ``"y"``, ``"z"``) and ``n``, the
    freedoms left (0 = every rigid motion fixed; the mirror is not a freedom).

    Examples
    --------
    Heights of three nodes not on a line fix z; the rotation about z and the horizontal
    translations stay free:

    >>> import numpy as np
    >>> P = np.array([[0.0, 0, 2.4], [5, 0, 2.4], [0, 4, 0.3]])
    >>> gauge_left(P, np.array([[False, False, True]] * 3))
    (('z',), 3)
    """
    P = np.asarray(points, float)
    k, d = P.shape
    M = np.asarray(mask, bool)
    nrot = 3 if d == 3 else 1
    if k == 0 or not M.any():
        return (), nrot + d
    scale = float(np.max(np.abs(P - P.mean(0)))) or 1.0
    Q = (P - P.mean(0)) / scale
    rows = []
    for i in range(k):
        for c in range(d):
            if not M[i, c]:
                continue
            if d == 3:
                x, y, z = Q[i]
                rot = [[0.0, z, -y], [-z, 0.0, x], [y, -x, 0.0]][c]
            else:
                rot = [[-Q[i, 1]], [Q[i, 0]]][c]
            rows.append(list(rot) + list(np.eye(d)[c]))
    G = np.array(rows, float)
    _, sv, vt = np.linalg.svd(G, full_matrices=True)
    rank = int((sv > 1e-6 * max(float(sv[0]), 1e-300)).sum())
    N = vt[rank:]  # the null space (freedoms left), rows [omega, u]
    fixed = []
    for c in range(d):
        cols = [j for j in range(nrot) if not (d == 3 and j == c)] + [nrot + c]
        if N.size == 0 or float(np.max(np.abs(N[:, cols]))) < 1e-6:
            fixed.append("xyz"[c])
    return tuple(fixed), int(N.shape[0])


def frame_mirror(points: Array, rank: int) -> tuple[Array, Array] | None:
    """The isometry ``(centre, Q)`` known points of affine rank ``rank < d`` leave; None at full rank.

    Rank ``d - 1`` (a plane in 3-D, a line in 2-D): the mirror through it. A line in 3-D:
    the half-turn about it (one of the rotations it leaves). One point: the point reflection.
    """
    P = np.asarray(points, float)
    d = P.shape[1]
    if rank >= d:
        return None
    c = P.mean(axis=0)
    if P.shape[0] < 2 or rank == 0:
        return c, -np.eye(d)
    _, _, vt = np.linalg.svd(P - c, full_matrices=True)
    if rank == d - 1:
        n = vt[-1]
        return c, np.eye(d) - 2.0 * np.outer(n, n)
    u = vt[0]  # a line in 3-D
    return c, 2.0 * np.outer(u, u) - np.eye(d)


def candidate_mirror(points: Array, rank: int) -> tuple[Array, Array] | None:
    """The mirror the known nodes leave, or, when they span the space, the mirror through their
    best-fitting plane (line in 2-D): the alternative to test, not to assume.

    Known anchors a few centimetres off one plane (ceiling anchors) span the space numerically
    but leave the mirror through that plane nearly open at the noise level: the likelihood-ratio
    test of :func:`selfcal.toa.verdict.uniqueness.uniqueness_test` decides, at the cost of one refit.
    """
    P = np.asarray(points, float)
    d = P.shape[1]
    if rank < d:
        return frame_mirror(P, rank)
    return frame_mirror(P, d - 1) if P.shape[0] >= d else None


def judge_known(out: Any, info: Any, blind: Any, sol: Any, data: Any, usable: Sequence[Any], aligned: Array,
                rotation: Array, rank: int, fixed_r: NDArray[np.bool_], fixed_s: NDArray[np.bool_], offsets: str,
                noise: float | None, mirror_stated: bool = False, mirror_fit: Any = None,
                local_blind: Any = None) -> tuple[Any, Any]:
    """Test a constrained fit of :func:`selfcal.toa.frame.known.fit_known` and apply the rule.

    The known test (:func:`known_test`) and the uniqueness test
    (:func:`selfcal.toa.verdict.uniqueness.uniqueness_test`: flips of the free nodes, and the
    mirror :func:`frame_mirror` that known nodes of rank < d leave) on the constrained fit
    ``sol``; either failing makes ``out`` FAILED_TEST with their messages. The blind fit's
    own uniqueness verdict is replaced (the known nodes may resolve its flips); its other
    tests stand. Returns ``(out, info)`` with ``info.known_test`` set.

    Known nodes that give only some coordinates (``KnownNode.mask``; e.g. heights): the
    alternatives of the uniqueness test that move a known coordinate beyond its error bar
    are not alternatives of the constrained fit (dropped), and the mirror candidate is
    ``mirror_fit``, the constrained fit from the other handedness
    (:func:`selfcal.toa.frame.known.fit_known`), compared by the same likelihood-ratio test
    (``Delta`` = its RSS plus ``sigma^2`` times its prior misfit, less the fit's).

    ``local_blind``: the blind model refitted from the constrained fit (an NlsSolution over the
    located nodes, any gauge). When given, the known test compares with it rather than with
    the blind fit: the nested models of the likelihood-ratio test at the same minimum. Where
    the data leave distant minima (a tag at one height: every anchor's flip), the blind
    search may return one that fits the noise better than the truth does (measured on the
    tag-one-height family: 0.024 against 0.036 m^2, ``F`` = 8-15 on 3 dof with the true
    heights), which the test would blame on the known coordinates.
    """
    import dataclasses

    from ..._result import replace_fields
    from ...errors import Status
    from ...geometry import n_parameters, rotate_covariances
    from .uniqueness import apply_rule, uniqueness_test

    c, ok_r, ok_s = data.c, data.ok_r, data.ok_s
    Ysub = data.Y[np.ix_(ok_r, ok_s)]
    I, d = np.asarray(blind.receivers).shape
    J = np.asarray(blind.sources).shape[0]
    partial = not all(bool(np.isfinite(np.asarray(k.position, float)).all()) for k in usable)
    masks = np.array([np.isfinite(np.asarray(k.position, float)) for k in usable])
    ref = np.array([k.position for k in usable], float)
    if partial:
        n_gauge = (3 if d == 3 else 1) + d
        n_fixed_gauge = n_gauge - gauge_left(np.asarray(aligned, float), masks)[1]
    else:
        n_fixed_gauge = gauge_fixed(d, rank)
    used = np.isfinite(Ysub) & np.isfinite(sol.residuals)
    rss_known = float(np.sum(np.where(used, sol.residuals, 0.0) ** 2))
    rb = None if blind.residuals is None else np.asarray(blind.residuals, float)[np.ix_(ok_r, ok_s)] * c
    if local_blind is not None:
        rb = np.asarray(local_blind.residuals, float)
    base_off = "none" if offsets == "common" else offsets
    n_blind = n_parameters(int(ok_r.sum()), int(ok_s.sum()), d, base_off) + (1 if offsets == "common" else 0)
    m = int(used.sum())
    dof_blind = m - n_blind
    noise2 = None if noise is None else (float(noise) * c) ** 2
    kt = None
    if rb is not None:
        both = used & np.isfinite(rb)
        rss_blind = float(np.sum(np.where(both, rb, 0.0) ** 2))
        rss_known = float(np.sum(np.where(both, sol.residuals, 0.0) ** 2))
        prior = 0.0
        names, disc = [], []
        s2 = noise2 if noise2 is not None else (rss_blind / dof_blind if dof_blind > 0 else float("nan"))
        if local_blind is not None:  # its positions moved onto the constrained fit (any rigid motion)
            from ...geometry import align

            X = np.vstack([sol.receivers, sol.sources])
            Xl = np.vstack([local_blind.receivers, local_blind.sources])
            Xl = align(Xl, X, reflection=True).apply(Xl)
            Rl, Sl = np.full((I, d), np.nan), np.full((J, d), np.nan)
            Rl[ok_r], Sl[ok_s] = Xl[:int(ok_r.sum())], Xl[int(ok_r.sum()):]
            aligned = np.array([(Rl if k.kind == "receiver" else Sl)[k.index] for k in usable])
        for k, a, mk in zip(usable, aligned, masks, strict=True):
            pos = np.asarray((out.receivers if k.kind == "receiver" else out.sources)[k.index], float)
            if k.std is not None:
                prior += float(np.sum((pos[mk] - k.position[mk]) ** 2)) / k.std**2
            C = np.asarray((blind.receiver_cov if k.kind == "receiver" else blind.source_cov)[k.index], float)
            sd_blind = float(blind.sigma) * c if np.isfinite(blind.sigma) else float("nan")
            if noise2 is not None and np.isfinite(sd_blind) and sd_blind > 0:
                C = C * noise2 / sd_blind**2
            if local_blind is not None:  # another gauge: the blind block's isotropic part
                C = np.trace(C) / d * np.eye(d)
            else:
                C = rotate_covariances(C[None], rotation)[0] if np.isfinite(C).all() else np.full((d, d), np.nan)
            if not np.isfinite(C).all():
                C = (s2 if np.isfinite(s2) else 0.0) * np.eye(d)
            big = np.abs(np.asarray(k.position, float)[mk]).max()
            C = C + ((k.std or 0.0) ** 2 + 1e-12 * (1.0 + float(big)) ** 2) * np.eye(d)
            e = (a - np.where(mk, np.asarray(k.position, float), 0.0))[mk]
            names.append(k.name)
            disc.append(float(e @ np.linalg.solve(C[np.ix_(mk, mk)], e)))
        kt = known_test(rss_known, rss_blind, prior, n_known=len(usable), d=d, rank=rank, noise2=noise2,
                        dof_blind=dof_blind, names=names, discrepancy=np.asarray(disc),
                        q=int(masks.sum()) - n_fixed_gauge if partial else None,
                        node_dof=masks.sum(1) if partial else None)
    # the uniqueness test on the constrained fit: exact known nodes are held, the rest may flip,
    # and a known set of rank < d leaves the mirror of the whole free network

    exact_r = np.zeros(I, bool)
    exact_s = np.zeros(J, bool)
    fr2, fs2 = np.asarray(fixed_r, bool), np.asarray(fixed_s, bool)
    exact_r[:] = fr2.all(1) if fr2.ndim == 2 else fr2
    exact_s[:] = fs2.all(1) if fs2.ndim == 2 else fs2
    n_fixed = int(fr2.sum() + fs2.sum()) if fr2.ndim == 2 else d * int(exact_r.sum() + exact_s.sum())
    n_par = n_blind + n_fixed_gauge - n_fixed
    mirror = None
    if not partial and not (mirror_stated and rank >= d - 1):
        mirror = candidate_mirror(ref, rank)
    u = uniqueness_test(Ysub, sol.receivers, sol.sources, sol.receiver_offsets, sol.source_offsets,
                        n_params=n_par, noise=None if noise is None else float(noise) * c,
                        receiver_cov=sol.receiver_cov, source_cov=sol.source_cov,
                        fixed_receivers=exact_r[ok_r], fixed_sources=exact_s[ok_s], mirror=mirror)
    u = u.relabel(ok_r, ok_s, np.arange(I), np.arange(J))
    mirror_note = ""
    if partial:
        u = _admissible(u, usable, out)
        if mirror_fit is not None and not mirror_stated:
            u, mirror_note = _partial_mirror(u, out, sol, mirror_fit, usable, ok_r, ok_s, aligned, masks)
    bu = blind.uniqueness
    base = bu.base_verdict if bu is not None and bu.base_verdict is not None else (int(blind.verdict),
                                                                                   str(blind.verdict_message))
    status, message = Status(base[0]), base[1]
    if kt is not None and not kt.passed:
        if status != Status.FAILED_TEST:
            status, message = Status.FAILED_TEST, kt.message()
        else:
            message = f"{message}; {kt.message()}"
    out = replace_fields(out, verdict=int(status), verdict_message=message)
    out = apply_rule(out, dataclasses.replace(u, base_verdict=base), base_off)
    if mirror_note and int(out.verdict) == int(Status.FAILED_TEST):
        out = replace_fields(out, verdict_message=f"{out.verdict_message}; {mirror_note}")
    info = dataclasses.replace(info, known_test=None if kt is None else kt.to_dict(),
                               mirror_resolved=bool(info.mirror_resolved or (partial and not mirror_note)))
    return out, info


def _admissible(u: Any, usable: Sequence[Any], out: Any) -> Any:
    """The uniqueness test less the alternatives that move a known coordinate beyond its error bar
    (``3 std`` of the stated std and of the constrained fit's covariance, at least 1e-6 of the scale)."""
    import dataclasses

    R = np.asarray(out.receivers, float)
    S = np.asarray(out.sources, float)
    scale = float(np.nanmax(np.abs(np.vstack([R, S])))) or 1.0
    known: dict[tuple[str, int], Any] = {(k.kind, k.index): k for k in usable}

    def bad_node(kind: str, i: int, pos: Array) -> bool:
        k = known.get((kind, int(i)))
        if k is None:
            return False
        mk = np.isfinite(np.asarray(k.position, float))
        C = np.asarray((out.receiver_cov if kind == "receiver" else out.source_cov)[int(i)], float)
        var = np.where(np.isfinite(np.diag(C)), np.diag(C), 0.0)
        tol = 3.0 * np.sqrt(var + (k.std or 0.0) ** 2) + 1e-6 * scale
        return bool(np.any(np.abs(np.asarray(pos, float) - np.asarray(k.position, float))[mk] > tol[mk]))

    keep = []
    for a in u.alternatives:
        bad = any(bad_node("receiver", i, p) for i, p in zip(a.receivers, a.receiver_positions, strict=True)) or \
            any(bad_node("source", j, p) for j, p in zip(a.sources, a.source_positions, strict=True))
        if not bad:
            keep.append(a)
    if len(keep) == len(u.alternatives):
        return u
    amb_r, amb_s = np.zeros_like(u.ambiguous_receivers), np.zeros_like(u.ambiguous_sources)
    alt_r, alt_s = np.full_like(u.receiver_alternatives, np.nan), np.full_like(u.source_alternatives, np.nan)
    for a in keep:
        for i, p in zip(a.receivers, a.receiver_positions, strict=True):
            if not amb_r[i]:
                amb_r[i], alt_r[i] = True, p
        for j, p in zip(a.sources, a.source_positions, strict=True):
            if not amb_s[j]:
                amb_s[j], alt_s[j] = True, p
    note = f"{len(u.alternatives) - len(keep)} alternative(s) contradicting known coordinates dropped"
    return dataclasses.replace(u, alternatives=tuple(keep), ambiguous_receivers=amb_r, ambiguous_sources=amb_s,
                               receiver_alternatives=alt_r, source_alternatives=alt_s,
                               note="; ".join(x for x in (u.note, note) if x))


def _partial_mirror(u: Any, out: Any, sol: Any, alt: Any, usable: Sequence[Any], ok_r: NDArray[np.bool_],
                    ok_s: NDArray[np.bool_], aligned: Array, masks: NDArray[np.bool_]) -> tuple[Any, str]:
    """The likelihood-ratio test of the other-handedness constrained fit ``alt`` against ``sol``.

    ``Delta`` = (RSS + sigma^2 prior misfit) of ``alt`` less that of ``sol``; ``k = d`` times the
    nodes it moves beyond 3 error bars (after the rigid motions the known coordinates leave);
    chi-square (noise given) or F (estimated, the uniqueness test's ``sigma`` and dof) at the
    uniqueness test's level. Returns the test with the alternative added when not rejected,
    and a line naming the remedy ("" when rejected).
    """
    import dataclasses

    from scipy.stats import chi2
    from scipy.stats import f as fdist

    from ...geometry import align
    from .uniqueness import MAX_LISTED, Alternative

    d = np.asarray(out.receivers).shape[1]
    s2 = float(u.noise) ** 2

    def full(P: Any, ok: NDArray[np.bool_]) -> Array:
        X = np.full((ok.size, d), np.nan)
        X[ok] = np.asarray(P, float)
        return X

    def cost(fit: Any) -> float:
        R, S = full(fit.receivers, ok_r), full(fit.sources, ok_s)
        prior = 0.0
        for k, mk in zip(usable, masks, strict=True):
            if k.std is not None:
                p = (R if k.kind == "receiver" else S)[k.index]
                prior += float(np.sum((p[mk] - np.asarray(k.position, float)[mk]) ** 2)) / k.std**2
        return float(np.nansum(np.asarray(fit.residuals, float) ** 2)) + s2 * prior

    delta = cost(alt) - cost(sol)
    if not np.isfinite(delta):
        return u, ""
    R0, S0 = full(sol.receivers, ok_r), full(sol.sources, ok_s)
    Ra, Sa = full(alt.receivers, ok_r), full(alt.sources, ok_s)
    ok = np.concatenate([ok_r, ok_s])
    X0, Xa = np.vstack([R0, S0]), np.vstack([Ra, Sa])
    axes, n_free = gauge_left(np.asarray(aligned, float), masks)
    if n_free:  # the freedoms the known coordinates leave: align over them (a reflection of
        # axes the user did not fix is a gauge too: heights alone leave x -> -x)
        cols = [c for c in range(d) if "xyz"[c] not in axes] if axes else list(range(d))
        if len(cols) >= 2:
            al = align(Xa[ok][:, cols], X0[ok][:, cols], reflection=len(cols) < d)
            Xa[:, cols] = al.apply(Xa[:, cols])
        elif cols:
            Xa[:, cols] += np.nanmean(X0[ok][:, cols] - Xa[ok][:, cols], axis=0)
    Cr, Cs = np.asarray(out.receiver_cov, float), np.asarray(out.source_cov, float)
    with np.errstate(invalid="ignore"):
        bar = np.sqrt(np.maximum(np.concatenate([np.trace(Cr, axis1=1, axis2=2), np.trace(Cs, axis1=1, axis2=2)]),
                                 0.0))
    tol = np.where(np.isfinite(bar), 3.0 * bar, 3.0 * np.sqrt(s2))
    moved = ok & (np.linalg.norm(Xa - X0, axis=1) > tol)
    if not moved.any():
        return u, ""
    I = R0.shape[0]
    k = d * int(moved.sum())
    if u.noise_source == "estimated" and u.spare > 0:
        t = (max(delta, 0.0) / k) / s2
        crit, p = float(fdist.ppf(1.0 - u.alpha, k, u.spare)), float(fdist.sf(t, k, u.spare))
    else:
        t = max(delta, 0.0) / s2
        crit, p = float(chi2.ppf(1.0 - u.alpha, k)), float(chi2.sf(t, k))
    if t > crit:
        return u, ""
    ir, js = np.flatnonzero(moved[:I]), np.flatnonzero(moved[I:])
    amb_r, amb_s = u.ambiguous_receivers.copy(), u.ambiguous_sources.copy()
    alt_r, alt_s = u.receiver_alternatives.copy(), u.source_alternatives.copy()
    amb_r[ir], alt_r[ir] = True, Xa[:I][ir]
    amb_s[js], alt_s[js] = True, Xa[I:][js]
    a = Alternative("mirror", tuple(int(i) for i in ir), tuple(int(j) for j in js), Xa[:I][ir], Xa[I:][js], t,
                    crit, p)
    alts = u.alternatives + ((a,) if len(u.alternatives) < MAX_LISTED else ())
    u = dataclasses.replace(u, alternatives=alts, ambiguous_receivers=amb_r, ambiguous_sources=amb_s,
                            receiver_alternatives=alt_r, source_alternatives=alt_s, candidates=u.candidates + 1,
                            refits=u.refits + 1)
    zk = [float(kk.position[d - 1]) for kk, mk in zip(usable, masks, strict=True) if mk[d - 1]]
    level = (len(zk) and float(np.ptp(zk)) <= 1e-6 * (1.0 + max(abs(z) for z in zk)))
    if level and d == 3:
        note = (f"the known heights are all at one level (z = {zk[0]:.4g} m): the mirror z -> {2 * zk[0]:.4g} - z "
                "of the other nodes fits as well; remedy: a known height off that level (or --side below/above)")
    else:
        note = ("the known coordinates leave the mirror image of the network open (it fits as well); remedy: "
                "known coordinates of a node off the plane they fix (or --side below/above)")
    return u, note


def choose_side(receivers: Array, sources: Array, known: Sequence[Any], ref: Array, rank: int,
                side: str) -> tuple[Array, Array]:
    """Put the free nodes on the ``side`` ("below" / "above", along z) of the coplanar known nodes' plane.

    The mirror through the plane of coplanar known nodes fits every range exactly (only the
    user can choose it): the free nodes (all but the known ones) are reflected through that
    plane when most of them lie on the other side. Applies in 3-D to known nodes of affine
    rank 2 whose plane is not vertical (its normal within 60 degrees of z); known nodes that
    span the space have no mirror (``side`` is then ignored).

    Raises
    ------
    InputError: ``side`` not "below" / "above"; a 2-D fit; a vertical plane (say which side
        along z is meaningless there).
    """
    from ...errors import InputError

    if side not in ("below", "above"):
        raise InputError(f"side must be 'below' or 'above', got {side!r}")
    R, S = np.array(receivers, float), np.array(sources, float)
    d = R.shape[1]
    if d != 3:
        raise InputError("side (below / above the known nodes' plane) applies to 3-D fits only")
    P = np.asarray(ref, float)
    sv = np.linalg.svd(P - P.mean(0), compute_uv=False) if len(P) >= d else np.zeros(d)
    # coplanar, or nearly: thinner than a tenth of their extent (ceiling anchors a few cm apart in z)
    if rank < d - 1 or (rank == d and not sv[-1] < 0.1 * sv[0]):
        return R, S
    c, Q = frame_mirror(ref, d - 1)  # type: ignore[misc]
    n = np.linalg.eigh(np.eye(d) - Q)[1][:, -1]  # the plane's normal (Q = I - 2 n n^T)
    if abs(n[2]) < 0.5:
        raise InputError("the known nodes' plane is not horizontal (normal > 60 degrees from z): "
                         "'below' / 'above' does not say which mirror image; add a known node off the plane")
    n = n if n[2] > 0 else -n
    free_r = np.ones(len(R), bool)
    free_s = np.ones(len(S), bool)
    for k in known:
        (free_r if k.kind == "receiver" else free_s)[k.index] = False
    h = np.concatenate([(R[free_r] - c) @ n, (S[free_s] - c) @ n])
    if h.size and (np.median(h) > 0) == (side == "below"):
        R[free_r] = R[free_r] - 2.0 * np.outer((R[free_r] - c) @ n, n)
        S[free_s] = S[free_s] - 2.0 * np.outer((S[free_s] - c) @ n, n)
    return R, S
