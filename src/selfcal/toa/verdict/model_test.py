"""The model a user forced, tested against the larger one the data may prefer.

``--dim 2`` on data of a 3-D layout, or ``offsets="none"`` where the devices have delays,
fit badly but consistently: with the noise estimated from the same residuals, every test
of the forced model alone passes. :func:`forced_model_test` fits the nesting model from
the forced fit (warm start: a 2-D fit lifted off its plane, zero offsets added; a few
refinements, not a new search) and compares the two by the nested F test (with a given
noise: the chi-square test of the RSS drop), at :data:`MODEL_ALPHA`:

- ``F = ((RSS_forced - RSS_larger) / k) / (RSS_larger / dof_larger)`` ~ ``F(k, dof_larger)``
  under the forced model (``k`` the extra parameters: one height per node less the three
  extra gauge freedoms of 3-D, :func:`selfcal.toa.verdict.planarity.compare_fits`; or the offsets);
- with ``offsets`` none / receivers / sources the larger model is ``both``; when it wins,
  the smaller models in between are fitted too and the smallest one the data do not reject
  against ``both`` is named.

The warm start can only under-state the larger model's improvement (a local refinement
from the forced fit), so the test never accuses a right model for lack of search.

Heavy tails (the offsets comparisons): the F test is exact for Gaussian noise only. For
independent noise of excess kurtosis ``gamma2`` the RSS drop ``e' P e`` (``P`` the projection
onto the ``k`` extra directions) has mean ``k sigma^2`` and variance
``sigma^4 (2 k + gamma2 sum_i P_ii^2)`` (Box & Watson 1962; Seber & Lee 2003, Thm 1.6):
matching a scaled chi-square to these two moments (Satterthwaite) gives
``drop / sigma^2 ~ c chi2(k / c)``, ``c = 1 + gamma2 sum_i P_ii^2 / (2 k)``, and likewise
``RSS_larger / sigma^2 ~ c_d chi2(dof / c_d)``, ``c_d = 1 + gamma2 sum_i M_ii^2 / (2 dof)``.
So ``F`` is referred to ``F(k / c, dof / c_d)`` (with a given noise: ``chi2 / c`` to
``chi2(k / c)``). ``P_ii = h_ii(larger) - h_ii(smaller)``, the difference of the two
fits' leverages (:func:`selfcal.toa.verdict.leverage.leverages`; far from uniform: at a
10 x 30 2-D network ``sum P_ii^2`` is 2.2 times the ``k^2 / n`` of equal leverages, at
100 x 100 3-D 4 times), ``M_ii = 1 - h_ii(larger)`` (:func:`_excess_kurtosis`).
``gamma2`` is estimated from the larger model's residuals and
clipped at 0, so Gaussian noise keeps the exact F test or a more lenient one (level <= alpha;
platykurtic noise leaves the uncorrected test conservative anyway). The numerator and
denominator are positively correlated under kurtosis (``kappa4 sum P_ii M_ii``), which the
two-moment match ignores and which narrows the ratio: conservative. The 2-D -> 3-D test is
not corrected: at a planar truth the heights enter the ranges at second order, the drop is
no quadratic form of the noise and its null law is not the F's in any case.

Networks with more than :data:`SUBSAMPLE_SIDE` receivers or sources are tested on a random
sub-block of that side, both models refitted there (the F test is exact on any subset of the
entries; it keeps its level and loses only the power a few thousand entries do not need).

References
----------
Box, G. E. P. & Watson, G. S. (1962). Robustness to non-normality of regression tests.
Biometrika 49, 93-106.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..._result import json_float as _num
from ...geometry import n_parameters

__all__ = ["MODEL_ALPHA", "ModelTest", "forced_model_test"]

Array = NDArray[np.float64]

#: level of the forced-model test (the planar F test's, selfcal.toa.verdict.planarity.PLANAR_ALPHA)
MODEL_ALPHA = 1e-3
#: iteration cap of each warm-started refinement of a larger model
MODEL_NFEV = 30
#: networks with more receivers or sources are tested on a random sub-block of this side
#: (both models refitted there): 1e4 entries detect an offset of a few noise units per
#: node with power ~1 at 1e-3, at a few per cent of a 1000 x 1000 solve
SUBSAMPLE_SIDE = 100


@dataclass(frozen=True)
class ModelTest:
    """The forced model against the larger one (:func:`forced_model_test`).

    Attributes
    ----------
    forced: e.g. ``"dim=2, offsets=none"``; better: the model the data prefer (None when
        the forced one stands).
    statistic, dof, dof_noise, p_value: the F test (``dof_noise = 0``: chi-square form with a
        given noise); alpha: level; passed: the forced model stands.
    kurtosis: the excess kurtosis estimated from the larger model's residuals (clipped at 0);
        scale: the heavy-tail factor ``c`` of the offsets test (``dof / c`` numerator degrees of
        freedom; 1: the Gaussian F test; module docstring).
    """

    forced: str
    better: str | None
    statistic: float
    dof: int
    dof_noise: int
    p_value: float
    alpha: float
    passed: bool
    kurtosis: float = 0.0
    scale: float = 1.0

    def message(self) -> str:
        """One line for a failed test."""
        if self.passed:
            return ""
        return (f"the forced model ({self.forced}) fits far worse than {self.better} "
                f"({'F' if self.dof_noise else 'chi2'} = {self.statistic:.4g} on {self.dof} extra parameters, "
                f"p = {self.p_value:.2g} < {self.alpha:g}"
                + (f", heavy tails allowed for: F dof / {self.scale:.3g}" if self.scale > 1 else "")
                + f"): use {self.better}")

    def to_dict(self) -> dict[str, Any]:
        """JSON-safe dictionary."""
        return {"forced": self.forced, "better": self.better, "statistic": _num(self.statistic), "dof": int(self.dof),
                "dof_noise": int(self.dof_noise), "p_value": _num(self.p_value), "alpha": float(self.alpha),
                "passed": bool(self.passed), "kurtosis": _num(self.kurtosis), "scale": _num(self.scale)}


def _n_par(I: int, J: int, dim: int, offsets: str) -> int:
    return n_parameters(I, J, dim, offsets)


def _excess_kurtosis(res: Array, lev: Array, held: NDArray[np.bool_] | None = None) -> float:
    """Excess kurtosis of the noise from a fit's residuals ``res`` and leverages ``lev`` (same shape).

    A residual is ``r_i = sum_j M_ij e_j`` (``M = 1 - H`` the residual projection, ``M_ii =
    1 - h_i``): the studentized ``u_i = r_i / sqrt(M_ii)`` has variance ``sigma^2`` and
    fourth moment ``3 sigma^4 + kappa4 w_i``, ``w_i = sum_j M_ij^4 / M_ii^2 ~ M_ii^2`` (the
    off-diagonal ``M_ij = -H_ij`` are small). So ``gamma2 = (sum u^4 / s^4 - 3 n) / sum w``
    with ``s^2 = mean u^2`` undoes both the fit's shrinkage of the tails and the spread of
    the leverages (which alone makes Gaussian residuals look heavy-tailed on small
    networks). Entries ``held`` out of the fit enter as prediction residuals: variance
    ``sigma^2 (1 + h_i)``, ``w_i ~ 1 / (1 + h_i)^2``. Clipped at 0 (module docstring).
    Small samples: its standard error for Gaussian noise is ``sqrt(24 n) / sum w`` (0.7 at a
    10 x 30 2-D network, ~ 10 at 3-D 8 x 10 with 15 residual dof of 80 entries: there the
    correction is mostly noise: it can cost power, never make the test stricter than the
    Gaussian F test); the sample kurtosis is
    bounded by ``n``, so tails of infinite kurtosis (Student t3) are under-stated and the
    estimate grows with n.
    """
    held = np.zeros(res.shape, bool) if held is None else held
    ok = np.isfinite(res) & np.isfinite(lev) & (held | (lev < 1.0 - 1e-9))
    var = np.where(held, 1.0 + lev, 1.0 - lev)[ok]
    w = np.where(held[ok], 1.0 / var, var) ** 2
    u = res[ok] / np.sqrt(var)
    n = u.size
    s2 = float(np.mean(u ** 2)) if n else 0.0
    sw = float(np.sum(w))
    if n < 4 or s2 <= 0.0 or sw <= 0.0:
        return 0.0
    return max((float(np.sum(u ** 4)) / s2 ** 2 - 3.0 * n) / sw, 0.0)


def _tail_scale(h_big: Array, h_small: Array, k: int, gamma2: float) -> float:
    """``c = 1 + gamma2 sum_i P_ii^2 / (2 k)``, ``P_ii = h_big - h_small`` (module docstring).

    The difference of the nested models' leverages is the diagonal of the projection onto
    the ``k`` extra directions (evaluated at two nearby fits: clipped at 0, scaled to sum to k).
    """
    if gamma2 <= 0.0 or k < 1:
        return 1.0
    P = np.clip(np.nan_to_num(h_big - h_small), 0.0, None)
    tot = float(P.sum())
    if tot <= 0.0:
        return 1.0
    P *= k / tot
    return 1.0 + gamma2 * float(np.sum(P ** 2)) / (2.0 * k)


def _ftest(rss0: float, rss1: float, k: int, dof1: int, noise2: float | None, floor2: float,
           scale: float = 1.0, scale_noise: float = 1.0) -> tuple[float, float, int]:
    """F (chi-square with a given noise) of the RSS drop; ``scale`` / ``scale_noise``: the
    heavy-tail factors ``c``, ``c_d`` of numerator and denominator (module docstring)."""
    from scipy.stats import chi2
    from scipy.stats import f as fdist

    drop = max(rss0 - rss1, 0.0)
    if noise2 is not None:
        t = drop / noise2
        return t, float(chi2.sf(t / scale, k / scale)), 0
    if dof1 < 1:
        return 0.0, 1.0, 0
    var = max(rss1 / dof1, floor2)
    t = drop / k / var
    return t, float(fdist.sf(t, k / scale, dof1 / scale_noise)), dof1


def forced_model_test(ranges: Any, receivers: Any, sources: Any, receiver_offsets: Any = None,
                      source_offsets: Any = None, *, offsets: str, noise: float | None = None,
                      test_dim: bool = True, test_offsets: bool = True, alpha: float = MODEL_ALPHA,
                      seed: int = 0, excluded: Any = None) -> ModelTest:
    """Test a fitted model (dimension, offsets) against the larger ones (module docstring).

    Parameters
    ----------
    ranges: (I, J) the entries the fit used (metres), NaN elsewhere.
    receivers, sources, receiver_offsets, source_offsets: the fit (metres).
    offsets: its offsets model ("none" | "receivers" | "sources" | "both").
    noise: range noise std (metres) when known.
    test_dim: test a 2-D fit against 3-D; test_offsets: test offsets other than "both" against "both".
    alpha: level; seed: the lift's random heights.
    excluded: (I, J) ranges the fit left out as outliers (metres, NaN elsewhere): they enter
        only the kurtosis estimate (as prediction residuals of the larger fit), since trimming
        the tails of heavy-tailed noise lowers the kurtosis of what is left while the F
        statistic keeps its excess (module docstring).

    Returns
    -------
    ModelTest

    Examples
    --------
    >>> import numpy as np
    >>> from selfcal.toa.engine.nls import toa_model
    >>> g = np.random.default_rng(0)
    >>> r, s = g.uniform(0, 10, (8, 3)), g.uniform(0, 10, (10, 3))
    >>> Y = toa_model(r, s, g.uniform(0, 2, 8)) + g.normal(0, 0.01, (8, 10))
    >>> t = forced_model_test(Y, r, s, offsets="none")
    >>> t.passed, t.better
    (False, 'offsets=receivers')
    """
    from ...errors import DegenerateGeometryError
    from ..engine.nls import refine_toa
    from .leverage import leverages

    Y = np.asarray(ranges, float)
    R = np.asarray(receivers, float)
    S = np.asarray(sources, float)
    label = f"dim={R.shape[1]}, offsets={offsets}"
    if not ((test_dim and R.shape[1] == 2) or (test_offsets and offsets != "both")):
        return ModelTest(label, None, 0.0, 0, 0, 1.0, alpha, True)  # nothing larger to test against
    d0 = None if receiver_offsets is None else np.asarray(receiver_offsets, float)
    o0 = None if source_offsets is None else np.asarray(source_offsets, float)
    sub = Y.shape[0] > SUBSAMPLE_SIDE or Y.shape[1] > SUBSAMPLE_SIDE
    if sub:  # a large network: both models refitted on a random sub-block (module docstring)
        g = np.random.default_rng(seed)
        ir = np.sort(g.choice(Y.shape[0], min(Y.shape[0], SUBSAMPLE_SIDE), replace=False))
        js = np.sort(g.choice(Y.shape[1], min(Y.shape[1], SUBSAMPLE_SIDE), replace=False))
        Y, R, S = Y[np.ix_(ir, js)], R[ir], S[js]
        d0 = None if d0 is None else d0[ir]
        o0 = None if o0 is None else o0[js]
        X = None if excluded is None else np.asarray(excluded, float)[np.ix_(ir, js)]
    else:
        X = None if excluded is None else np.asarray(excluded, float)
    I, dim = R.shape
    J = S.shape[0]
    obs = np.isfinite(Y)
    m = int(obs.sum())

    def model(r: Array, s: Array, d: Array | None, o: Array | None) -> Array:
        D = np.linalg.norm(r[:, None] - s[None], axis=-1)
        return D + (0.0 if d is None else d[:, None]) + (0.0 if o is None else o[None, :])

    rss0 = float(np.sum(np.where(obs, Y - model(R, S, d0, o0), 0.0) ** 2))
    if sub:  # the forced model at its own minimum on the sub-block (else its misfit would count)
        try:
            fs = refine_toa(Y, R, S, offsets=offsets, receiver_offsets0=d0, source_offsets0=o0,
                            max_nfev=MODEL_NFEV, covariance=False)
            R, S, d0, o0 = fs.receivers, fs.sources, fs.receiver_offsets, fs.source_offsets
            rss0 = float(np.sum(np.where(obs, Y - model(R, S, d0, o0), 0.0) ** 2))
        except (DegenerateGeometryError, np.linalg.LinAlgError, ValueError):
            pass
    floor2 = (np.sqrt(np.finfo(float).eps) * float(np.nanmedian(np.abs(Y)))) ** 2
    noise2 = None if noise is None else float(noise) ** 2

    def fit(r: Array, s: Array, off: str) -> tuple[float, Any] | None:
        has_r, has_s = off in ("receivers", "both"), off in ("sources", "both")
        dd = (d0 if d0 is not None else np.zeros(I)) if has_r else None
        oo = (o0 if o0 is not None else np.zeros(J)) if has_s else None
        try:
            sol = refine_toa(Y, r, s, offsets=off, receiver_offsets0=dd, source_offsets0=oo, max_nfev=MODEL_NFEV,
                             covariance=False)
        except (DegenerateGeometryError, np.linalg.LinAlgError, ValueError):
            return None
        f = sol.residuals[np.isfinite(sol.residuals)]
        return float(f @ f), sol

    def lev(r: Array, s: Array, d: Array | None, o: Array | None, off: str) -> Array:
        """Leverages of the observed entries (I, J) at a fit; NaN where they cannot be formed."""
        has_r, has_s = off in ("receivers", "both"), off in ("sources", "both")
        d = (d if d is not None else np.zeros(I)) if has_r else None
        o = (o if o is not None else np.zeros(J)) if has_s else None
        try:
            return leverages(Y, r, s, d, o, off)
        except (np.linalg.LinAlgError, ValueError):
            return np.full(Y.shape, np.nan)

    best = ModelTest(label, None, 0.0, 0, 0, 1.0, alpha, True)
    # 2-D -> 3-D: lifted off the plane (heights of 1 % of the extent, both signs)
    if test_dim and dim == 2:
        g = np.random.default_rng(seed)
        ext = float(np.ptp(np.vstack([R, S]), axis=0).max()) or 1.0
        r3 = np.c_[R, g.normal(0, 0.01 * ext, I)]
        s3 = np.c_[S, g.normal(0, 0.01 * ext, J)]
        fit3 = fit(r3, s3, offsets)
        if fit3 is not None:
            rss3 = fit3[0]
            k = _n_par(I, J, 3, offsets) - _n_par(I, J, 2, offsets)
            t, p, dn = _ftest(rss0, rss3, k, m - _n_par(I, J, 3, offsets), noise2, floor2)
            best = ModelTest(label, f"dim=3 (offsets={offsets})" if p < alpha else None, t, k, dn, p, alpha,
                             not p < alpha)
    if test_offsets and offsets != "both" and best.passed:
        fitb = fit(R, S, "both")
        if fitb is not None and m - _n_par(I, J, dim, "both") >= 1:
            rssb = fitb[0]
            kb = _n_par(I, J, dim, "both") - _n_par(I, J, dim, offsets)
            dofb = m - _n_par(I, J, dim, "both")
            sb = fitb[1]
            hb = lev(sb.receivers, sb.sources, sb.receiver_offsets, sb.source_offsets, "both")
            # the kurtosis of the larger model's residuals: the smaller one's misfit kept out
            res, lv = sb.residuals, hb
            held = np.isfinite(X) & ~obs if X is not None and X.shape == Y.shape else np.zeros(Y.shape, bool)
            if X is not None and held.any():  # their prediction residuals at the larger fit
                ho = leverages(Y, sb.receivers, sb.sources, sb.receiver_offsets, sb.source_offsets, "both",
                               held_out=held)
                pr = X - model(sb.receivers, sb.sources, sb.receiver_offsets, sb.source_offsets)
                res, lv = np.where(held, pr, res), np.where(held, ho, hb)
            g2 = _excess_kurtosis(res, lv, held)
            Mb = 1.0 - hb[obs & np.isfinite(hb)]
            sm2 = float(Mb @ Mb)
            cb = _tail_scale(hb, lev(R, S, d0, o0, offsets), kb, g2) if g2 > 0 else 1.0
            cd = 1.0 + g2 * sm2 / (2.0 * dofb)
            t, p, dn = _ftest(rss0, rssb, kb, dofb, noise2, floor2, cb, cd)
            best = ModelTest(label, None, t, kb, dn, p, alpha, True, g2, cb)
            if p < alpha:
                name = "offsets=both"
                # the smallest model between the forced one and "both" that "both" does not beat
                for mid in ("receivers", "sources"):
                    if mid == offsets or (offsets != "none"):
                        continue
                    fm = fit(R, S, mid)
                    if fm is None:
                        continue
                    km = _n_par(I, J, dim, "both") - _n_par(I, J, dim, mid)
                    sm = fm[1]
                    cm = _tail_scale(hb, lev(sm.receivers, sm.sources, sm.receiver_offsets, sm.source_offsets, mid),
                                     km, g2) if g2 > 0 else 1.0
                    _, pm, _ = _ftest(fm[0], rssb, km, dofb, noise2, floor2, cm, cd)
                    if not pm < alpha:
                        name = f"offsets={mid}"
                        break
                best = ModelTest(label, name, t, kb, dn, p, alpha, False, g2, cb)
    return best
