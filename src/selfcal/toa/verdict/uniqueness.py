"""Unique or honest: is the fitted TOA geometry the only one the data allow?

The covariance of a fit (003 eq. 17) is local: it says how well the data pin the geometry
*near* the minimum found. Range data also admit distant alternatives that fit as well --
a node whose partners span less than the space reflected through them (:mod:`.flips`),
another minimum of the cost, the mirror image a frame of coplanar known nodes leaves.
:func:`uniqueness_test` builds those candidates, refits each (the flipped node alone
first: an upper bound of the alternative's cost; then, for a few, a warm-started refit of
everything) and compares each with the best fit by a likelihood-ratio test:

- ``Delta = RSS_alt - RSS_best`` (metres^2) over the entries the fit used;
- noise given (``sigma``): reject the alternative when ``Delta / sigma^2 > chi2_{1-a}(k)``;
- noise estimated (``s^2 = RSS_best / dof``): reject when ``(Delta / k) / s^2 > F_{1-a}(k, dof)``;
- ``k = d`` times the number of nodes the alternative moves beyond 3 of their error bars.

Under the hypothesis that the alternative is the truth, ``Delta`` is (to first order, Wilks)
chi-square with ``k`` degrees of freedom (the alternative differs from the best only in the
coordinates of the ``k / d`` nodes it moves; every other parameter is refitted), so an
alternative that is in fact the truth is rejected with probability ``alpha`` at most: a
result that passes is right within its error bars, or wrong with probability <= alpha per
candidate. Alternatives not rejected are *indistinguishable*; the nodes they move are
``ambiguous`` and carry their alternative positions.

With no spare measurement (``dof <= 0``) the test says ``minimal`` (never a pass) and lists
what it found (at the solver's precision when the noise is not given).

Cost: the candidate screen is one product of the observation mask with the partners'
moments (O(I J d^2)); flipped nodes are refitted alone, vectorised; at most
:data:`MAX_REFITS` full refits of :data:`REFIT_NFEV` iterations each, warm-started, only for
candidates the one-node refit could not settle (``benchmarks/bench_uniqueness.py``).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..._result import json_float as _num
from ..._result import jsonable
from .flips import flip_candidates, refit_nodes

__all__ = ["UNIQUE_ALPHA", "Alternative", "UniquenessTest", "apply_rule", "judge_fit", "uniqueness_test"]

Array = NDArray[np.float64]
Start = tuple[Array, Array, "Array | None", "Array | None"]

#: level of the likelihood-ratio test: an alternative that is the truth is rejected with at
#: most this probability (the residual test's level, selfcal.toa.verdict.trust.RESIDUAL_ALPHA)
UNIQUE_ALPHA = 1e-3
#: full warm-started refits per test (candidates the one-node refit leaves open), and their
#: iteration cap: each costs a fraction of one refinement of the search
MAX_REFITS = 4
REFIT_NFEV = 10
#: alternatives listed per test (the ambiguous masks gather every one found)
MAX_LISTED = 20
#: isolated one-node flips on at most this fraction of the nodes are named, not failed
#: (:func:`apply_rule`): so few cannot carry the rest of the network with them
ISOLATED_FRACTION = 0.01


@dataclass(frozen=True)
class Alternative:
    """One alternative solution the data do not reject.

    Attributes
    ----------
    kind: "flip" (nodes reflected through their partners' span), "minimum" (another minimum
        the search found), "mirror" (the mirror image a frame of coplanar / collinear known
        nodes leaves), "better" (a flip that fits better than the result).
    receivers, sources: the nodes it moves beyond 3 error bars (indices).
    receiver_positions, source_positions: (len, d) their alternative positions (m).
    statistic: ``Delta / sigma^2`` (noise given) or ``(Delta / k) / s^2`` (estimated).
    critical: the test's critical value at ``alpha``; p_value: the alternative's p-value.
    """

    kind: str
    receivers: tuple[int, ...]
    sources: tuple[int, ...]
    receiver_positions: Array
    source_positions: Array
    statistic: float
    critical: float
    p_value: float

    def to_dict(self) -> dict[str, Any]:
        """JSON-safe dictionary."""
        return {"kind": self.kind, "receivers": list(self.receivers), "sources": list(self.sources),
                "receiver_positions": jsonable(self.receiver_positions),
                "source_positions": jsonable(self.source_positions), "statistic": _num(self.statistic),
                "critical": _num(self.critical), "p_value": _num(self.p_value)}


@dataclass(frozen=True)
class UniquenessTest:
    """Whether the data single out the fitted geometry (:func:`uniqueness_test`).

    Attributes
    ----------
    alpha: level of the likelihood-ratio test.
    noise: the range noise std the test used (metres); noise_source: "given" | "estimated" |
        "precision" (no spare measurement: the solver's precision).
    spare: residual degrees of freedom ``m - n`` of the fit.
    minimal: no spare measurement (``dof <= 0``): the fit is exact whatever the geometry, so
        nothing can be rejected (a given noise still judges the alternatives found).
    candidates: alternatives examined; refits: full refits run.
    alternatives: those not rejected (at most :data:`MAX_LISTED`).
    ambiguous_receivers, ambiguous_sources: (I,), (J,) bool, nodes moved by some alternative.
    receiver_alternatives, source_alternatives: (I, d), (J, d) an alternative position of
        each ambiguous node (NaN elsewhere), metres, in the result's frame.
    note: what was not examined, or why not.
    near_minimal: at most ``d`` spare measurements (fewer than one node's coordinates and
        its offset): the test is run but has little power.
    base_verdict: the result's (status, message) before this test (:func:`judge_fit`), so a
        later constrained fit (known nodes) can judge again; None elsewhere.
    failed: the rule of :func:`apply_rule` failed the result (minimal, or too many nodes
        ambiguous); a test that did not pass but did not fail it names its nodes only.
    """

    alpha: float
    noise: float
    noise_source: str
    spare: int
    minimal: bool
    candidates: int
    refits: int
    alternatives: tuple[Alternative, ...]
    ambiguous_receivers: NDArray[np.bool_]
    ambiguous_sources: NDArray[np.bool_]
    receiver_alternatives: Array
    source_alternatives: Array
    note: str = ""
    near_minimal: bool = field(default=False)
    base_verdict: tuple[int, str] | None = None
    failed: bool = False

    @property
    def passed(self) -> bool:
        """No indistinguishable alternative and at least one spare measurement."""
        return not self.minimal and not (self.ambiguous_receivers.any() or self.ambiguous_sources.any())

    def names(self, receiver_names: Sequence[str] | None = None, source_names: Sequence[str] | None = None,
              limit: int = 12) -> str:
        """The ambiguous nodes, e.g. ``"r3, s0, s5"`` (at most ``limit``, then a count)."""
        rn = [receiver_names[int(i)] if receiver_names else f"r{i}" for i in np.flatnonzero(self.ambiguous_receivers)]
        sn = [source_names[int(j)] if source_names else f"s{j}" for j in np.flatnonzero(self.ambiguous_sources)]
        allv = rn + sn
        more = f" and {len(allv) - limit} more" if len(allv) > limit else ""
        return ", ".join(allv[:limit]) + more

    def message(self) -> str:
        """One line: what the test found (empty when it passed)."""
        if self.passed:
            return ""
        kinds = sorted({a.kind for a in self.alternatives})
        if self.ambiguous_receivers.any() or self.ambiguous_sources.any():
            why = {"flip": "reflected through the span of their partners",
                   "minimum": "at another minimum of the fit",
                   "mirror": "mirrored through the known nodes' plane / line",
                   "better": "at a flip that fits better than the result"}
            what = "; ".join(why[k] for k in kinds if k in why)
            out = (f"the data do not single out the solution: {self.names()} fit as well {what} "
                   f"(likelihood-ratio test, level {self.alpha:g}); remedy: a measurement off the plane of "
                   "their partners (a tag position off the plane), a known height, or a known node off the plane")
        else:
            out = ""
        if self.minimal:
            out = ("no spare measurement: the fit is exact whatever the geometry, so no alternative solution "
                   "can be rejected (a minimal problem is not a determined one); add measurements"
                   + ("; " + out if out else ""))
        return out

    def to_dict(self) -> dict[str, Any]:
        """JSON-safe dictionary."""
        return {"test": "likelihood-ratio", "alpha": float(self.alpha), "noise": _num(self.noise),
                "noise_source": self.noise_source, "spare": int(self.spare), "minimal": bool(self.minimal),
                "near_minimal": bool(self.near_minimal), "passed": bool(self.passed),
                "candidates": int(self.candidates), "refits": int(self.refits),
                "ambiguous_receivers": [int(i) for i in np.flatnonzero(self.ambiguous_receivers)],
                "ambiguous_sources": [int(j) for j in np.flatnonzero(self.ambiguous_sources)],
                "receiver_alternatives": jsonable(self.receiver_alternatives),
                "source_alternatives": jsonable(self.source_alternatives),
                "alternatives": [a.to_dict() for a in self.alternatives], "note": self.note}

    def moved(self, rotation: Array, translation: Array) -> UniquenessTest:
        """The test with every alternative position moved by ``p -> rotation p + translation`` (a new frame)."""
        import dataclasses

        Rm, t = np.asarray(rotation, float), np.asarray(translation, float)

        def mv(P: Array) -> Array:
            return np.asarray(P, float) @ Rm.T + t

        alts = tuple(dataclasses.replace(a, receiver_positions=mv(a.receiver_positions),
                                         source_positions=mv(a.source_positions)) for a in self.alternatives)
        return dataclasses.replace(self, receiver_alternatives=mv(self.receiver_alternatives),
                                   source_alternatives=mv(self.source_alternatives), alternatives=alts)

    def relabel(self, keep_r: NDArray[np.bool_], keep_s: NDArray[np.bool_], perm_r: NDArray[np.intp],
                perm_c: NDArray[np.intp]) -> UniquenessTest:
        """The test in the caller's numbering: kept nodes ``keep_*`` of the canonical order ``perm_*``."""
        import dataclasses

        kr_idx = np.asarray(perm_r)[np.flatnonzero(keep_r)]  # kept position -> caller index
        ks_idx = np.asarray(perm_c)[np.flatnonzero(keep_s)]
        I, J = len(perm_r), len(perm_c)
        d = self.receiver_alternatives.shape[1]

        def grow(mask: NDArray[np.bool_], pos: Array, idx: NDArray[np.intp], n: int) -> tuple[NDArray[np.bool_], Array]:
            m = np.zeros(n, bool)
            p = np.full((n, d), np.nan)
            m[idx] = mask
            p[idx] = pos
            return m, p

        ar, pr_ = grow(self.ambiguous_receivers, self.receiver_alternatives, kr_idx, I)
        as_, ps_ = grow(self.ambiguous_sources, self.source_alternatives, ks_idx, J)
        alts = tuple(dataclasses.replace(a, receivers=tuple(int(kr_idx[i]) for i in a.receivers),
                                         sources=tuple(int(ks_idx[j]) for j in a.sources)) for a in self.alternatives)
        return dataclasses.replace(self, ambiguous_receivers=ar, ambiguous_sources=as_, receiver_alternatives=pr_,
                                   source_alternatives=ps_, alternatives=alts)


def _model(r: Array, s: Array, d: Array | None, o: Array | None) -> Array:
    D = np.linalg.norm(r[:, None, :] - s[None, :, :], axis=-1)
    if d is not None:
        D = D + np.asarray(d)[:, None]
    if o is not None:
        D = D + np.asarray(o)[None, :]
    return D


def _std(cov: Any, n: int) -> Array:
    if cov is None:
        return np.full(n, np.nan)
    C = np.asarray(cov, float)
    with np.errstate(invalid="ignore"):
        return np.sqrt(np.maximum(np.trace(C, axis1=1, axis2=2), 0.0))


def uniqueness_test(
    ranges: Any,
    receivers: Any,
    sources: Any,
    receiver_offsets: Any = None,
    source_offsets: Any = None,
    *,
    n_params: int,
    noise: float | None = None,
    receiver_cov: Any = None,
    source_cov: Any = None,
    minima: Sequence[Start] = (),
    fixed_receivers: Any = None,
    fixed_sources: Any = None,
    mirror: tuple[Array, Array] | None = None,
    refine: Callable[[Start], Start | None] | None = None,
    alpha: float = UNIQUE_ALPHA,
    max_refits: int = MAX_REFITS,
) -> UniquenessTest:
    """Test whether a TOA fit is the only solution the data allow (module docstring).

    Parameters
    ----------
    ranges: (I, J) the ranges the fit used (metres), NaN elsewhere (missing, outliers).
    receivers, sources: (I, d), (J, d) the fit (metres); receiver_offsets, source_offsets:
        (I,), (J,) or None (metres).
    n_params: the fit's free parameters (:func:`selfcal.geometry.n_parameters`), for its
        residual degrees of freedom.
    noise: range noise std (metres) when known; else estimated from the residuals.
    receiver_cov, source_cov: (I, d, d), (J, d, d) the fit's covariances (m^2), NaN where
        unknown: the error bars that say whether a node moved and whether partners are coplanar.
    minima: other minima of the fit (starts ``(r, s, d, o)`` on the same nodes), e.g. the
        search's converged losers.
    fixed_receivers, fixed_sources: (I,), (J,) bool, nodes held by the fit (known nodes):
        never flipped, and alternatives are compared without re-alignment.
    mirror: ``(centre, Q)``: the isometry ``p -> centre + Q (p - centre)`` that the frame leaves
        (mirror through coplanar known nodes): tested as an alternative of every free node.
    refine: warm-started refit of a start (few iterations) returning the refitted start in
        any frame (it is aligned onto the fit); None = one-node refits only.
    alpha: test level; max_refits: cap on full refits.

    Returns
    -------
    UniquenessTest

    Examples
    --------
    Receivers on a line in 2-D: every source has a mirror image through it.

    >>> import numpy as np
    >>> from selfcal.toa.engine.nls import toa_model
    >>> g = np.random.default_rng(0)
    >>> r = np.c_[np.linspace(-4, 4, 5), np.zeros(5)]
    >>> s = g.uniform(-4, 4, (6, 2))
    >>> u = uniqueness_test(toa_model(r, s), r, s, n_params=2 * 11 - 3, noise=0.01)
    >>> u.passed, int(u.ambiguous_sources.sum())
    (False, 6)
    """
    from scipy.stats import chi2
    from scipy.stats import f as fdist

    Y = np.asarray(ranges, float)
    R0 = np.asarray(receivers, float)
    S0 = np.asarray(sources, float)
    d0 = None if receiver_offsets is None else np.asarray(receiver_offsets, float)
    o0 = None if source_offsets is None else np.asarray(source_offsets, float)
    I, d = R0.shape
    J = S0.shape[0]
    obs = np.isfinite(Y)
    m = int(obs.sum())
    with np.errstate(all="ignore"):
        E = np.where(obs, Y - _model(R0, S0, d0, o0), 0.0)
    rss = float(np.sum(E**2))
    dof = m - int(n_params)
    floor2 = (np.sqrt(np.finfo(float).eps) * float(np.nanmedian(np.abs(Y)) if m else 1.0)) ** 2
    if noise is not None:
        s2, src = float(noise) ** 2, "given"
    elif dof > 0:
        s2, src = max(rss / dof, floor2), "estimated"
    else:
        s2, src = floor2, "precision"
    s2 = max(s2, floor2)
    minimal = dof <= 0  # a given noise judges the alternatives, but cannot test the fit itself

    def crit(k: int) -> float:
        """The critical RSS increase for an alternative moving k / d nodes."""
        if src == "estimated":
            return s2 * k * float(fdist.ppf(1.0 - alpha, k, dof))
        return s2 * float(chi2.ppf(1.0 - alpha, k))

    def stat(delta: float, k: int) -> tuple[float, float, float]:
        if src == "estimated":
            t = (delta / k) / s2
            return t, float(fdist.ppf(1.0 - alpha, k, dof)), float(fdist.sf(max(t, 0.0), k, dof))
        t = delta / s2
        return t, float(chi2.ppf(1.0 - alpha, k)), float(chi2.sf(max(t, 0.0), k))

    std_r, std_s = _std(receiver_cov, I), _std(source_cov, J)
    tol_r = np.where(np.isfinite(std_r), 3.0 * std_r, 3.0 * np.sqrt(s2))
    tol_s = np.where(np.isfinite(std_s), 3.0 * std_s, 3.0 * np.sqrt(s2))
    fix_r = np.zeros(I, bool) if fixed_receivers is None else np.asarray(fixed_receivers, bool)
    fix_s = np.zeros(J, bool) if fixed_sources is None else np.asarray(fixed_sources, bool)
    anchored = bool(fix_r.any() or fix_s.any())

    amb_r, amb_s = np.zeros(I, bool), np.zeros(J, bool)
    alt_r, alt_s = np.full((I, d), np.nan), np.full((J, d), np.nan)
    found: list[Alternative] = []
    n_cand = 0
    n_refit = 0
    notes: list[str] = []

    def accept(kind: str, ir: NDArray[np.intp], js: NDArray[np.intp], pr: Array, ps: Array, delta: float) -> None:
        k = d * max(1, ir.size + js.size)
        t, c, p = stat(delta, k)
        if t > c:
            return
        if delta < -crit(k):
            kind = "better"
        for i, pos in zip(ir, pr, strict=True):
            if not amb_r[i]:
                amb_r[i], alt_r[i] = True, pos
        for j, pos in zip(js, ps, strict=True):
            if not amb_s[j]:
                amb_s[j], alt_s[j] = True, pos
        if len(found) < MAX_LISTED:
            found.append(Alternative(kind, tuple(int(i) for i in ir), tuple(int(j) for j in js),
                                     np.asarray(pr, float).reshape(-1, d), np.asarray(ps, float).reshape(-1, d),
                                     t, c, p))

    def compare(kind: str, st: Start, align: bool) -> None:
        """An alternative start: aligned onto the fit, its moved nodes, the LR test."""
        r, s, dd, oo = (np.asarray(st[0], float), np.asarray(st[1], float), st[2], st[3])
        if r.shape != R0.shape or s.shape != S0.shape or not (np.isfinite(r).all() and np.isfinite(s).all()):
            return
        with np.errstate(all="ignore"):
            Ea = np.where(obs, Y - _model(r, s, dd, oo), 0.0)
        delta = float(np.sum(Ea**2)) - rss
        if not np.isfinite(delta):
            return
        if align:  # onto the fit, then again on the nodes that did not move (a flip must not drag the rest)
            from ...geometry import align as _align

            ref, tol = np.vstack([R0, S0]), np.concatenate([tol_r, tol_s])
            flip = np.ones(d)
            flip[-1] = -1.0
            best_X, best_n = None, -1
            for X0 in (np.vstack([r, s]), np.vstack([r, s]) * flip):  # both handednesses
                w = np.ones(I + J)
                for it in range(4):  # all nodes, the nearer half, then the nodes within their error bars
                    X = _align(X0, ref, reflection=False, weights=w).apply(X0)
                    dist = np.linalg.norm(X - ref, axis=1)
                    still = dist <= tol
                    if still.sum() < d + 1:
                        still = dist <= np.median(dist)
                    if it and np.array_equal(still, w > 0):
                        break
                    w = still.astype(float)
                n_still = int((np.linalg.norm(X - ref, axis=1) <= tol).sum())
                if n_still > best_n:
                    best_X, best_n = X, n_still
            assert best_X is not None
            r, s = best_X[:I], best_X[I:]
        ir = np.flatnonzero(np.linalg.norm(r - R0, axis=1) > tol_r)
        js = np.flatnonzero(np.linalg.norm(s - S0, axis=1) > tol_s)
        if ir.size + js.size:
            accept(kind, ir, js, r[ir], s[js], delta)

    bound = crit(d)
    quantile = float(chi2.ppf(1.0 - alpha, 1))
    queue: list[tuple[float, str, int, Array, float | None]] = []
    for kind_r, P, Q, W, off_self, off_part, cov_part, std_self, fixed in (
            (True, R0, S0, obs, d0, o0, source_cov, std_r, fix_r),
            (False, S0, R0, obs.T, o0, d0, receiver_cov, std_s, fix_s)):
        fc = flip_candidates(P, Q, W, noise2=s2, partner_var=cov_part, point_std=std_self, quantile=quantile,
                             bound=bound, skip=fixed)
        if fc.index.size == 0:
            continue
        n_cand += fc.index.size
        y = (Y if kind_r else Y.T)[fc.index]
        w = W[fc.index]
        part_off = np.zeros(Q.shape[0]) if off_part is None else np.asarray(off_part, float)
        own = None if off_self is None else np.asarray(off_self, float)[fc.index]
        X, b, rss_alt = refit_nodes(fc.flipped, Q, y, w, part_off, own)
        Eb = (E if kind_r else E.T)[fc.index]
        delta = rss_alt - np.sum(Eb**2, axis=1)
        tol = tol_r if kind_r else tol_s
        for q, idx in enumerate(fc.index):
            if np.linalg.norm(X[q] - P[idx]) <= tol[idx]:
                continue  # the one-node refit slid back: no distinct alternative from this node
            one = np.array([idx])
            none = np.zeros(0, np.intp)
            if delta[q] <= crit(d):
                if kind_r:
                    accept("flip", one, none, X[q:q + 1], np.zeros((0, d)), float(delta[q]))
                else:
                    accept("flip", none, one, np.zeros((0, d)), X[q:q + 1], float(delta[q]))
            else:
                queue.append((float(delta[q]), "r" if kind_r else "s", int(idx), X[q], None if b is None else float(b[q])))
    # candidates the one-node refit could not settle: a few full refits, warm-started
    if refine is not None and max_refits > 0:
        queue.sort(key=lambda t: t[0])
        done_r, done_s = amb_r.copy(), amb_s.copy()
        for _delta, kind, idx, pos, off in queue:
            if n_refit >= max_refits:
                notes.append(f"{len(queue) - n_refit} flip candidates beyond {max_refits} full refits judged by "
                             "their one-node refit only")
                break
            if (done_r if kind == "r" else done_s)[idx]:
                continue
            r, s = R0.copy(), S0.copy()
            dd = None if d0 is None else d0.copy()
            oo = None if o0 is None else o0.copy()
            if kind == "r":
                r[idx] = pos
                if dd is not None and off is not None:
                    dd[idx] = off
            else:
                s[idx] = pos
                if oo is not None and off is not None:
                    oo[idx] = off
            n_refit += 1
            try:
                got = refine((r, s, dd, oo))
            except Exception as exc:  # noqa: BLE001 - a refit that fails is no alternative
                notes.append(f"a refit failed ({type(exc).__name__})")
                continue
            if got is not None:
                compare("flip", got, align=not anchored)
    for st in minima:
        n_cand += 1
        compare("minimum", st, align=not anchored)
    if mirror is not None:
        n_cand += 1
        c, Qm = np.asarray(mirror[0], float), np.asarray(mirror[1], float)
        r = np.where(fix_r[:, None], R0, c + (R0 - c) @ Qm.T)
        s = np.where(fix_s[:, None], S0, c + (S0 - c) @ Qm.T)
        compare("mirror", (r, s, d0, o0), align=False)
    if minimal and src == "precision":
        notes.append("no spare measurement: alternatives are judged at the solver's precision only")
    return UniquenessTest(float(alpha), float(np.sqrt(s2)), src, int(dof), minimal, n_cand, n_refit, tuple(found),
                          amb_r, amb_s, alt_r, alt_s, "; ".join(notes),
                          near_minimal=bool(0 < dof <= d))


def judge_fit(res: Any, Yf: Array, sol: Any, offsets: str, noise: float | None, n_params: int,
              keep: tuple[NDArray[np.bool_], NDArray[np.bool_]], perm: tuple[NDArray[np.intp], NDArray[np.intp]],
              minima: Sequence[Start] = ()) -> Any:
    """Run :func:`uniqueness_test` on a fit of :func:`selfcal.toa.fit.finish` and apply its rule.

    ``Yf`` (kept, canonical order, metres) holds the entries the fit ``sol``
    (:class:`selfcal.toa.engine.nls.NlsSolution`) used; ``noise`` in metres or None. A result that
    is not singled out (an indistinguishable alternative, or no spare measurement) becomes
    FAILED_TEST with the test's message; an already failed one keeps its message with the
    test's appended. The test is attached in the caller's numbering.
    """
    import dataclasses

    from ...errors import DegenerateGeometryError
    from ..engine.nls import refine_toa

    def refine(st: Start) -> Start | None:
        try:
            got = refine_toa(Yf, st[0], st[1], offsets=offsets, receiver_offsets0=st[2], source_offsets0=st[3],
                             max_nfev=REFIT_NFEV, covariance=False)
        except (DegenerateGeometryError, np.linalg.LinAlgError, ValueError):
            return None
        return got.receivers, got.sources, got.receiver_offsets, got.source_offsets

    Cr, Cs = sol.receiver_cov, sol.source_cov
    sig = float(sol.sigma)
    if noise is not None and np.isfinite(sig) and sig > 0:  # the fit's blocks are at its own estimate
        k = (noise / sig) ** 2
        Cr, Cs = np.asarray(Cr) * k, np.asarray(Cs) * k
    try:
        u = uniqueness_test(Yf, sol.receivers, sol.sources, sol.receiver_offsets, sol.source_offsets,
                            n_params=n_params, noise=noise, receiver_cov=Cr, source_cov=Cs, minima=minima,
                            refine=refine)
    except (np.linalg.LinAlgError, ValueError, FloatingPointError) as exc:  # said, never silently passed
        return dataclasses.replace(res, verdict_message=f"{res.verdict_message}; uniqueness test not run "
                                                        f"({type(exc).__name__}: {exc})")
    u = dataclasses.replace(u.relabel(keep[0], keep[1], perm[0], perm[1]),
                            base_verdict=(int(res.verdict), str(res.verdict_message)))
    return apply_rule(res, u, offsets)


def apply_rule(res: Any, u: UniquenessTest, offsets: str) -> Any:
    """The verdict of a uniqueness test on a result (caller's numbering), as the determinacy rule.

    The result fails (FAILED_TEST) when the problem is minimal, or when any node is ambiguous
    unless the ambiguity is *isolated*: every alternative a flip of one node alone, at most
    :data:`ISOLATED_FRACTION` of the nodes, the other nodes an identifiable network
    (``check_toa_counts``) and at most half of the nodes ambiguous or undetermined (the
    determinacy rule). Only then does the status stay, the message naming the nodes (a long
    flight with a few tag positions of four or five ranges), whose covariance is widened by
    ``delta delta^T`` (``delta`` the way to their alternative) so their error bar covers it; a
    failed result keeps its local covariances (the alternatives are in the test). Why so strict: where several
    nodes flip (receivers on a line or a plane), the truth may be a *combination* of flips
    that moves every node, and the nodes no single flip moves are then metres off too
    (measured on 2-D collinear and 3-D coplanar receivers, 200 draws each: 3 and 1 draws exit 0
    with other nodes outside 3 error bars under the half-of-the-nodes rule alone).
    """
    import dataclasses

    from ..._checks import check_toa_counts
    from ...errors import DegenerateGeometryError, Status
    from .determinacy import UNDETERMINED_FAIL_FRACTION

    amb_r, amb_s = u.ambiguous_receivers, u.ambiguous_sources
    R, S = np.asarray(res.receivers, float), np.asarray(res.sources, float)
    ok_r, ok_s = np.isfinite(R).all(1), np.isfinite(S).all(1)
    Cr, Cs = np.array(res.receiver_cov, float), np.array(res.source_cov, float)
    open_r = amb_r | np.asarray(res.undetermined_receivers, bool)
    open_s = amb_s | np.asarray(res.undetermined_sources, bool)
    n_nodes = int(ok_r.sum() + ok_s.sum())
    n_open = int((open_r & ok_r).sum() + (open_s & ok_s).sum())
    n_amb = int(amb_r.sum() + amb_s.sum())
    core = None
    if n_amb and res.residuals is not None:
        kr, ks = ok_r & ~open_r, ok_s & ~open_s
        used = np.isfinite(res.residuals) & (~res.outliers if res.outliers is not None else True)
        try:
            check_toa_counts((int(kr.sum()), int(ks.sum())), int(used[np.ix_(kr, ks)].sum()), R.shape[1], offsets)
        except DegenerateGeometryError as exc:
            core = f"the other nodes alone are not identifiable: {exc.args[0]}"
    isolated = all(a.kind == "flip" and len(a.receivers) + len(a.sources) == 1 for a in u.alternatives)
    fails = u.minimal or (n_amb and (not isolated or n_amb > ISOLATED_FRACTION * n_nodes
                                     or n_open > UNDETERMINED_FAIL_FRACTION * n_nodes or core is not None))
    status, message = Status(res.verdict), res.verdict_message
    if fails:
        why = u.message() + (f"; {core}" if core else "")
        if status != Status.FAILED_TEST:
            status, message = Status.FAILED_TEST, why
        else:
            message = f"{message}; {why}"
    elif n_amb:  # isolated: named, their error bars widened to cover the alternative
        for C, amb, P, alt in ((Cr, amb_r, R, u.receiver_alternatives), (Cs, amb_s, S, u.source_alternatives)):
            for i in np.flatnonzero(amb):
                dlt = alt[i] - P[i]
                C[i] = C[i] + np.outer(dlt, dlt)
        message += (f"; but {n_amb} of {n_nodes} nodes are ambiguous ({u.names()}: an alternative position fits "
                    f"as well, likelihood-ratio test at {u.alpha:g}; their error bars cover it)")
    elif u.near_minimal:
        message += f"; only {u.spare} spare measurement(s): the uniqueness test has little power"
    u = dataclasses.replace(u, failed=bool(fails))
    return dataclasses.replace(res, uniqueness=u, verdict=int(status), verdict_message=message,
                               receiver_cov=Cr, source_cov=Cs)
