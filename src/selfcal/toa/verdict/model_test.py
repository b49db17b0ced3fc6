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
Networks with more than :data:`SUBSAMPLE_SIDE` receivers or sources are tested on a random
sub-block of that side, both models refitted there (the F test is exact on any subset of the
entries; it keeps its level and loses only the power a few thousand entries do not need).
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
    """

    forced: str
    better: str | None
    statistic: float
    dof: int
    dof_noise: int
    p_value: float
    alpha: float
    passed: bool

    def message(self) -> str:
        """One line for a failed test."""
        if self.passed:
            return ""
        return (f"the forced model ({self.forced}) fits far worse than {self.better} "
                f"({'F' if self.dof_noise else 'chi2'} = {self.statistic:.4g} on {self.dof} extra parameters, "
                f"p = {self.p_value:.2g} < {self.alpha:g}): use {self.better}")

    def to_dict(self) -> dict[str, Any]:
        """JSON-safe dictionary."""
        return {"forced": self.forced, "better": self.better, "statistic": _num(self.statistic), "dof": int(self.dof),
                "dof_noise": int(self.dof_noise), "p_value": _num(self.p_value), "alpha": float(self.alpha),
                "passed": bool(self.passed)}


def _n_par(I: int, J: int, dim: int, offsets: str) -> int:
    return n_parameters(I, J, dim, offsets)


def _ftest(rss0: float, rss1: float, k: int, dof1: int, noise2: float | None, floor2: float) -> tuple[float, float, int]:
    from scipy.stats import chi2
    from scipy.stats import f as fdist

    drop = max(rss0 - rss1, 0.0)
    if noise2 is not None:
        t = drop / noise2
        return t, float(chi2.sf(t, k)), 0
    if dof1 < 1:
        return 0.0, 1.0, 0
    var = max(rss1 / dof1, floor2)
    t = drop / k / var
    return t, float(fdist.sf(t, k, dof1)), dof1


def forced_model_test(ranges: Any, receivers: Any, sources: Any, receiver_offsets: Any = None,
                      source_offsets: Any = None, *, offsets: str, noise: float | None = None,
                      test_dim: bool = True, test_offsets: bool = True, alpha: float = MODEL_ALPHA,
                      seed: int = 0) -> ModelTest:
    """Test a fitted model (dimension, offsets) against the larger ones (module docstring).

    Parameters
    ----------
    ranges: (I, J) the entries the fit used (metres), NaN elsewhere.
    receivers, sources, receiver_offsets, source_offsets: the fit (metres).
    offsets: its offsets model ("none" | "receivers" | "sources" | "both").
    noise: range noise std (metres) when known.
    test_dim: test a 2-D fit against 3-D; test_offsets: test offsets other than "both" against "both".
    alpha: level; seed: the lift's random heights.

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

    def fit(r: Array, s: Array, off: str) -> float | None:
        has_r, has_s = off in ("receivers", "both"), off in ("sources", "both")
        dd = (d0 if d0 is not None else np.zeros(I)) if has_r else None
        oo = (o0 if o0 is not None else np.zeros(J)) if has_s else None
        try:
            sol = refine_toa(Y, r, s, offsets=off, receiver_offsets0=dd, source_offsets0=oo, max_nfev=MODEL_NFEV,
                             covariance=False)
        except (DegenerateGeometryError, np.linalg.LinAlgError, ValueError):
            return None
        f = sol.residuals[np.isfinite(sol.residuals)]
        return float(f @ f)

    best = ModelTest(label, None, 0.0, 0, 0, 1.0, alpha, True)
    # 2-D -> 3-D: lifted off the plane (heights of 1 % of the extent, both signs)
    if test_dim and dim == 2:
        g = np.random.default_rng(seed)
        ext = float(np.ptp(np.vstack([R, S]), axis=0).max()) or 1.0
        r3 = np.c_[R, g.normal(0, 0.01 * ext, I)]
        s3 = np.c_[S, g.normal(0, 0.01 * ext, J)]
        rss3 = fit(r3, s3, offsets)
        if rss3 is not None:
            k = _n_par(I, J, 3, offsets) - _n_par(I, J, 2, offsets)
            t, p, dn = _ftest(rss0, rss3, k, m - _n_par(I, J, 3, offsets), noise2, floor2)
            best = ModelTest(label, f"dim=3 (offsets={offsets})" if p < alpha else None, t, k, dn, p, alpha,
                             not p < alpha)
    if test_offsets and offsets != "both" and best.passed:
        rssb = fit(R, S, "both")
        if rssb is not None and m - _n_par(I, J, dim, "both") >= 1:
            kb = _n_par(I, J, dim, "both") - _n_par(I, J, dim, offsets)
            dofb = m - _n_par(I, J, dim, "both")
            t, p, dn = _ftest(rss0, rssb, kb, dofb, noise2, floor2)
            best = ModelTest(label, None, t, kb, dn, p, alpha, True)
            if p < alpha:
                name = "offsets=both"
                # the smallest model between the forced one and "both" that "both" does not beat
                for mid in ("receivers", "sources"):
                    if mid == offsets or (offsets != "none"):
                        continue
                    rm = fit(R, S, mid)
                    if rm is None:
                        continue
                    km = _n_par(I, J, dim, "both") - _n_par(I, J, dim, mid)
                    _, pm, _ = _ftest(rm, rssb, km, dofb, noise2, floor2)
                    if not pm < alpha:
                        name = f"offsets={mid}"
                        break
                best = ModelTest(label, name, t, kb, dn, p, alpha, False)
    return best
