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

__all__ = ["KNOWN_ALPHA", "KnownTest", "candidate_mirror", "choose_side", "frame_mirror", "judge_known", "known_test"]

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
               alpha: float = KNOWN_ALPHA) -> KnownTest:
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
        lim = float(chi2.ppf(1.0 - alpha / max(len(names), 1), d))
        sel = np.flatnonzero(disc > lim)
        if sel.size == 0 and disc.size:
            sel = np.array([int(np.nanargmax(disc))])
        bad = tuple(names[i] for i in sel[np.argsort(-disc[sel])])
    return KnownTest(float(stat), q, dn, p, alpha, passed, bad)


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
                noise: float | None, mirror_stated: bool = False) -> tuple[Any, Any]:
    """Test a constrained fit of :func:`selfcal.toa.frame.known.fit_known` and apply the rule.

    The known test (:func:`known_test`) and the uniqueness test
    (:func:`selfcal.toa.verdict.uniqueness.uniqueness_test`: flips of the free nodes, and the
    mirror :func:`frame_mirror` that known nodes of rank < d leave) on the constrained fit
    ``sol``; either failing makes ``out`` FAILED_TEST with their messages. The blind fit's
    own uniqueness verdict is replaced (the known nodes may resolve its flips); its other
    tests stand. Returns ``(out, info)`` with ``info.known_test`` set.
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
    used = np.isfinite(Ysub) & np.isfinite(sol.residuals)
    rss_known = float(np.sum(np.where(used, sol.residuals, 0.0) ** 2))
    rb = None if blind.residuals is None else np.asarray(blind.residuals, float)[np.ix_(ok_r, ok_s)] * c
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
        for k, a in zip(usable, aligned, strict=True):
            pos = np.asarray((out.receivers if k.kind == "receiver" else out.sources)[k.index], float)
            if k.std is not None:
                prior += float(np.sum((pos - k.position) ** 2)) / k.std**2
            C = np.asarray((blind.receiver_cov if k.kind == "receiver" else blind.source_cov)[k.index], float)
            sd_blind = float(blind.sigma) * c if np.isfinite(blind.sigma) else float("nan")
            if noise2 is not None and np.isfinite(sd_blind) and sd_blind > 0:
                C = C * noise2 / sd_blind**2
            C = rotate_covariances(C[None], rotation)[0] if np.isfinite(C).all() else np.full((d, d), np.nan)
            if not np.isfinite(C).all():
                C = (s2 if np.isfinite(s2) else 0.0) * np.eye(d)
            C = C + ((k.std or 0.0) ** 2 + 1e-12 * (1.0 + float(np.abs(k.position).max())) ** 2) * np.eye(d)
            e = a - np.asarray(k.position, float)
            names.append(k.name)
            disc.append(float(e @ np.linalg.solve(C, e)))
        kt = known_test(rss_known, rss_blind, prior, n_known=len(usable), d=d, rank=rank, noise2=noise2,
                        dof_blind=dof_blind, names=names, discrepancy=np.asarray(disc))
    # the uniqueness test on the constrained fit: exact known nodes are held, the rest may flip,
    # and a known set of rank < d leaves the mirror of the whole free network

    ref = np.array([k.position for k in usable], float)
    exact_r = np.zeros(I, bool)
    exact_s = np.zeros(J, bool)
    exact_r[:] = np.asarray(fixed_r).all(1) if np.ndim(fixed_r) == 2 else np.asarray(fixed_r, bool)
    exact_s[:] = np.asarray(fixed_s).all(1) if np.ndim(fixed_s) == 2 else np.asarray(fixed_s, bool)
    n_exact = int(exact_r.sum() + exact_s.sum())
    n_par = n_blind + gauge_fixed(d, rank) - d * n_exact
    u = uniqueness_test(Ysub, sol.receivers, sol.sources, sol.receiver_offsets, sol.source_offsets,
                        n_params=n_par, noise=None if noise is None else float(noise) * c,
                        receiver_cov=sol.receiver_cov, source_cov=sol.source_cov,
                        fixed_receivers=exact_r[ok_r], fixed_sources=exact_s[ok_s], mirror=None if mirror_stated and rank >= d - 1 else candidate_mirror(ref, rank))
    u = u.relabel(ok_r, ok_s, np.arange(I), np.arange(J))
    bu = getattr(blind, "uniqueness", None)
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
    info = dataclasses.replace(info, known_test=None if kt is None else kt.to_dict())
    return out, info


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
