"""Offset (ranging-bias) models chosen by held-out prediction: K-fold cross-validation over sources.

The question "does this matrix support per-receiver offsets?" (a per-anchor UWB ranging
bias; ``offsets="receivers"`` when the anchors are the rows) is answered by how well each
candidate model *predicts ranges it was not fitted to*, not by an in-sample test. On real
ranges every in-sample test (F, BIC, likelihood ratio) accepts any extra parameter: the
residuals are serially correlated and partly systematic (the measured LPS flights give a
nested F of ~1e3 for a single common offset), so the test's null distribution is wrong.
Held-out prediction needs no null distribution.

Procedure (:func:`cross_validate`):

1. The sources (columns: tag positions, in time order for a moving tag) are cut into
   ``K`` contiguous blocks (folds). Contiguous blocks, not random columns: neighbouring
   positions of a moving tag share their errors (multipath, NLOS stretches, AR noise), so
   a random split would let the training fold see the held-out errors. For independent
   sources contiguous blocks are as valid as any split.
2. For each candidate model and fold ``k``: the model is refitted on the other ``K - 1``
   blocks (:func:`selfcal.toa.engine.nls.refine_toa`, warm-started from the model's fit on all
   columns; the start is only a start, the refit minimises the training cost alone).
3. Every held-out source is located from its own ranges with the fitted receivers and
   receiver offsets held fixed (:func:`locate_sources`: Gauss-Newton per column, plus the
   column's own offset for models with source offsets).
4. Each held-out range is scored by its leave-one-range-out prediction residual
   ``e_ij / (1 - h_ij)`` (PRESS; ``h_ij`` the leverage of the range in its column's
   location). The column's position is fitted from its own ranges, so its plain residuals
   are deflated by the 3 (or 4) parameters of the location; the PRESS residual is the
   error of predicting the range from the position located *without* it, which makes
   models with and without per-source offsets comparable.
5. ``cv_score[model]`` = mean squared prediction residual over all held-out ranges
   (m^2); per-fold means give the paired standard error of the difference between two
   models (``std(diff_k) / sqrt(K)``).

Choice (:func:`one_se_choice`): the *one-standard-error rule* (Breiman et al. 1984;
Hastie, Tibshirani & Friedman, *Elements of Statistical Learning*, sec. 7.10): the
simplest model whose CV score exceeds the best one's by no more than one standard error
of their paired per-fold difference. A model with more parameters is adopted only when
it predicts held-out positions better by more than the fold-to-fold noise of that
comparison. Every candidate is scored on the same entries.

The standard error is the fold-to-fold noise only when the per-fold differences are
roughly exchangeable with a moderate spread. Fold scores are mean *squared* errors: one
fold where a wrong model mispredicts badly (a held-out block its wrong offsets cannot
reach) dominates both the mean difference and its standard deviation, and the rule then
sits on a knife-edge (one dominant difference ``x`` among ``K`` gives a mean ``x / K`` and an
SE ``x / K``), decided by the other folds and by the weighting: the scores pool the entries,
so a one-column fold counts half as much in the score difference as in the SE. Measured
(``benchmarks/cli_audit.py``, family ``gen-3d-offauto-10x14``, seed 23: both offsets in
the truth): "both" better than "sources" in 10 of 10 folds, held-out RMS 0.021 against
0.33 m, fold-mean difference 0.132 m^2, pooled 0.106, SE 0.109 from one one-column fold at
1.1 m^2: "sources" was chosen, 1.5 m off. So a simpler model also counts as within reach
of the best only if a one-sided *sign test* on the folds (the distribution-free test of
"the two predict equally well": the differences' signs, no variance estimate) does not
reject it at :data:`SIGN_ALPHA`. This keeps the one-SE rule's purpose (no model adopted on
a difference within the CV noise: the sign test is a test of exactly that) and adds
nothing where the SE is sound: the sign test rejects only when the best model wins every
one of ``K >= 7`` folds, and ``K`` positive differences always have their mean above their
SE (their coefficient of variation is below ``sqrt(K)``, reached only when one fold carries
the whole sum), so the rule alone could keep the simpler model there only through the
knife-edge above.

Anchor check (:func:`choose_receiver_offsets`, :func:`selfcal.toa.verdict.focused.anchor_mse`): held-out prediction
judges ranges; a per-receiver offset that trades against the receiver's radial position
can predict better and place the receivers worse (LPS data4). Per-receiver offsets are
kept only when the receivers' mean squared error estimated from the same folds' refits
(focused criterion, Claeskens & Hjort 2003) is lower too.

Folds: ``K = min(MAX_FOLDS, J // L)`` with ``L`` the residual correlation length along
the columns (:func:`selfcal.toa.verdict.offset_fit.residual_correlation_length` on the
simplest model's residuals), at least :data:`MIN_FOLDS`; so a held-out block is longer
than the span over which its errors are correlated with the training blocks next to it.
"""

from __future__ import annotations

import dataclasses
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ...errors import ConvergenceWarning, DegenerateGeometryError, InputError
from .focused import AnchorMse, anchor_mse

__all__ = ["MAX_FOLDS", "MIN_FOLDS", "MODELS", "SIGN_ALPHA", "CvChoice",
           "choose_receiver_offsets", "cross_validate", "locate_sources", "one_se_choice", "sign_test_p"]

Array = NDArray[np.float64]

#: most folds (each is one refit per candidate); 10 is the usual K of K-fold CV
MAX_FOLDS = 10
#: fewest folds (fewer gives a standard error from too few differences to be useful)
MIN_FOLDS = 4
#: level of the one-sided sign test on the folds (:func:`one_se_choice`): a simpler model the
#: best one beats in significantly many folds is not "within one SE"; at 0.01 that takes
#: every fold of K >= 7 (2^-7 = 0.0078), so with fewer folds the one-SE rule acts alone
SIGN_ALPHA = 0.01
#: offset models, simplest first; "common": one offset shared by every receiver (an antenna delay)
MODELS = ("none", "common", "receivers", "sources", "both")

_REFIT = {
    "none": {"offsets": "none"},
    "common": {"offsets": "receivers", "common_offsets": "receivers"},
    "receivers": {"offsets": "receivers"},
    "sources": {"offsets": "sources"},
    "both": {"offsets": "both"},
}
_MAX_LEVERAGE = 0.99  # a range its column's location fits exactly carries no prediction


@dataclass(frozen=True)
class CvChoice:
    """The offset model chosen by :func:`cross_validate` and its evidence.

    Attributes
    ----------
    chosen : str
        One of :data:`MODELS`.
    scores : dict
        Model -> mean squared held-out prediction residual (m^2, or the matrix's units^2).
    se : dict
        Model -> standard error of its paired per-fold difference from the best model.
    best : str
        The model with the lowest score (the one-SE rule may choose a simpler one).
    folds : int
        K.
    correlation_length : int
        Residual correlation length (columns) behind K.
    entries : int
        Held-out ranges scored (the same for every model).
    fold_scores : dict
        Model -> per-fold mean squared prediction residual.
    failed : dict
        Model -> reason, for candidates whose fits failed (not scored).
    refits : dict
        Model -> the receivers (I, d) of its K fold refits, in their own gauges.
    anchors : AnchorMse, optional
        The receivers' estimated MSE under the two models (set by
        :func:`choose_receiver_offsets`, which then may keep the simpler model).
    """

    chosen: str
    scores: dict[str, float]
    se: dict[str, float]
    best: str
    folds: int
    correlation_length: int
    entries: int
    fold_scores: dict[str, list[float]] = field(default_factory=dict)
    failed: dict[str, str] = field(default_factory=dict)
    refits: dict[str, list[Array]] = field(default_factory=dict, repr=False, compare=False)
    anchors: AnchorMse | None = None

    def to_dict(self) -> dict[str, Any]:
        """JSON-safe dictionary (scores as RMS prediction errors too)."""
        return {"criterion": "held-out prediction (K-fold over sources, one-SE rule with a sign test)"
                             + ("; anchor MSE by the folds' refits" if self.anchors is not None else ""),
                "chosen": self.chosen,
                "best": self.best, "folds": self.folds, "correlation_length": self.correlation_length,
                "entries": self.entries, "cv_mse": dict(self.scores),
                "cv_rmse": {k: float(np.sqrt(v)) for k, v in self.scores.items()},
                "se": dict(self.se), "fold_mse": {k: list(v) for k, v in self.fold_scores.items()},
                "failed": dict(self.failed),
                **({"anchor_mse": self.anchors.to_dict()} if self.anchors is not None else {})}

    def line(self, unit: str = "m") -> str:
        """One line for the CLI: the choice and the held-out RMS prediction error of every model."""
        parts = ", ".join(f"{k} {np.sqrt(v):.4g}" for k, v in self.scores.items())
        text = (f"offsets model {self.chosen} by held-out prediction ({self.folds}-fold over tag positions, "
                f"one-SE rule with a sign test): RMS prediction error {parts} {unit}")
        if self.anchors is not None:
            est = ", ".join(f"{k} {v:.3g}" for k, v in self.anchors.rmse.items())
            text += f"; estimated anchor RMS error {est} {unit}"
        return text


def _complexity(model: str, I: int, J: int) -> int:
    return {"none": 0, "common": 1, "receivers": I, "sources": J, "both": I + J - 1}[model]


def locate_sources(Y: Array, receivers: Array, receiver_offsets: Array | None = None, *,
                   source_offset: bool = False, start: Array | None = None,
                   iterations: int = 30) -> tuple[Array, Array, Array, Array]:
    """Locate every column's source from its ranges with the receivers (and their offsets) fixed.

    Minimises ``sum_i (|r_i - s_j| + d_i + o_j - y_ij)^2`` over ``s_j`` (and ``o_j`` when
    ``source_offset``) for each column ``j`` separately, by damped Gauss-Newton
    (all columns at once, step halved per column until its cost decreases).

    Parameters
    ----------
    Y : (I, n) array
        Ranges (m), NaN = missing.
    receivers : (I, d) array
    receiver_offsets : (I,) array, optional
        ``d_i`` (m); zero when omitted.
    source_offset : bool
        Fit one offset ``o_j`` per column too.
    start : (n, d) array, optional
        Starting positions; default the receivers' centroid shifted by the column's
        linear multilateration where it exists.
    iterations : int

    Returns
    -------
    positions : (n, d) array
        NaN for columns with fewer ranges than parameters + 1.
    offsets : (n,) array
        ``o_j`` (zeros without ``source_offset``).
    residuals : (I, n) array
        ``y - model``, NaN where missing or not located.
    leverage : (I, n) array
        Diagonal of each column's hat matrix ``J (J^T J)^-1 J^T``.

    Examples
    --------
    >>> import numpy as np
    >>> g = np.random.default_rng(0)
    >>> R, S = g.uniform(0, 5, (6, 3)), g.uniform(1, 4, (20, 3))
    >>> Y = np.linalg.norm(R[:, None] - S[None], axis=2)
    >>> X, o, e, h = locate_sources(Y, R)
    >>> bool(np.allclose(X, S, atol=1e-6)), bool(np.allclose(h.sum(0), 3))
    (True, True)
    """
    Y = np.asarray(Y, float)
    R = np.asarray(receivers, float)
    I, n = Y.shape
    d = R.shape[1]
    doff = np.zeros(I) if receiver_offsets is None else np.nan_to_num(np.asarray(receiver_offsets, float))
    obs = np.isfinite(Y)
    p = d + int(source_offset)
    ok = obs.sum(axis=0) >= p + 1
    Z = np.where(obs, Y - doff[:, None], 0.0)
    W = obs.astype(float)
    X = np.repeat(R.mean(0)[None], n, axis=0) if start is None else np.array(start, float)
    if start is None:
        X = _linear_start(Z, W, R, X, ok)
    X = np.where(np.isfinite(X), X, R.mean(0))
    o = np.zeros(n)

    def cost_of(Xc: Array, oc: Array) -> Array:
        f = np.linalg.norm(Xc[None] - R[:, None], axis=2) + oc[None] - Z
        return np.sum(W * f * f, axis=0)

    cost = cost_of(X, o)
    for _ in range(iterations):
        diff = X[None] - R[:, None]  # (I, n, d)
        dist = np.maximum(np.linalg.norm(diff, axis=2), 1e-12)
        f = W * (dist + o[None] - Z)
        Jx = diff / dist[..., None]
        Jm = np.concatenate([Jx, np.ones((I, n, 1))], axis=2) if source_offset else Jx
        Jm = Jm * W[..., None]
        G = np.einsum("inp,inq->npq", Jm, Jm) + 1e-9 * np.eye(p)
        g = np.einsum("inp,in->np", Jm, f)
        try:
            step = -np.linalg.solve(G, g[..., None])[..., 0]
        except np.linalg.LinAlgError:
            step = -np.einsum("npq,nq->np", np.linalg.pinv(G), g)
        t = np.ones(n)
        newX, newo = X.copy(), o.copy()
        todo = np.ones(n, bool)
        for _half in range(8):
            cand_X = X + t[:, None] * step[:, :d]
            cand_o = o + t * step[:, d] if source_offset else o
            c = cost_of(cand_X, cand_o)
            good = todo & (c <= cost)
            newX[good], newo[good] = cand_X[good], cand_o[good]
            cost = np.where(good, c, cost)
            todo &= ~good
            if not todo.any():
                break
            t = np.where(todo, t / 2, t)
        moved = float(np.max(np.abs(newX - X))) if n else 0.0
        X, o = newX, newo
        if moved < 1e-10:
            break
    diff = X[None] - R[:, None]
    dist = np.maximum(np.linalg.norm(diff, axis=2), 1e-12)
    E = np.where(obs, Z - dist - o[None], np.nan)
    Jx = diff / dist[..., None]
    Jm = np.concatenate([Jx, np.ones((I, n, 1))], axis=2) if source_offset else Jx
    Jw = Jm * W[..., None]
    G = np.einsum("inp,inq->npq", Jw, Jw)
    Ginv = np.linalg.pinv(G)
    H = np.einsum("inp,npq,inq->in", Jm, Ginv, Jm)
    H = np.where(obs, H, np.nan)
    X[~ok] = np.nan
    o[~ok] = np.nan
    E[:, ~ok] = np.nan
    H[:, ~ok] = np.nan
    return X, o, E, H


def _linear_start(Z: Array, W: Array, R: Array, X0: Array, ok: NDArray[np.bool_]) -> Array:
    """Linear multilateration per column (differences of squared ranges), where it is determined."""
    X = X0.copy()
    d = R.shape[1]
    for j in np.nonzero(ok)[0]:
        k = W[:, j] > 0
        if k.sum() < d + 1:
            continue
        A, z = R[k], np.clip(Z[k, j], 0.0, None)
        a0, z0 = A[0], z[0]
        M = 2 * (A[1:] - a0)
        b = z0**2 - z[1:] ** 2 + np.sum(A[1:] ** 2, axis=1) - a0 @ a0
        sol, _, rank, _ = np.linalg.lstsq(M, b, rcond=None)
        if rank == d and np.isfinite(sol).all():
            X[j] = sol
    return X


def _folds(J: int, L: int) -> NDArray[np.intp]:
    K = int(min(MAX_FOLDS, max(MIN_FOLDS, J // max(L, 1))))
    return np.linspace(0, J, K + 1).round().astype(np.intp)


def cross_validate(
    matrix: Array,
    starts: Mapping[str, tuple[Array, Array, Array | None, Array | None]],
    *,
    solver: str = "auto",
    folds: int | NDArray[np.intp] | None = None,
    progress: Any = None,
) -> CvChoice:
    """Score offset models by K-fold held-out prediction over the columns and choose one.

    Parameters
    ----------
    matrix : (I, J) array
        Ranges in metres (the entries every candidate was fitted to; NaN = missing or
        excluded), columns in time order for a moving tag.
    starts : mapping
        Model name (one of :data:`MODELS`) -> its fit on all columns ``(receivers (I, d),
        sources (J, d), receiver_offsets (I,) or None, source_offsets (J,) or None)``
        in metres: the warm start of every fold's refit.
    solver : str
        Engine of the refits (:func:`selfcal.toa.engine.nls.refine_toa`).
    folds : int or (J,) int array, optional
        K contiguous blocks of columns (default K from the residual correlation length, see
        the module docstring), or the fold of every column (labels ``0 .. K-1``: another
        split, e.g. the spatial folds evaluated in ``benchmarks/lps_bias_choice.py``).
    progress : callable, optional
        Called with ``(done, total)`` after each refit.

    Returns
    -------
    CvChoice

    Raises
    ------
    DegenerateGeometryError
        No candidate could be scored.

    Examples
    --------
    >>> from selfcal.experiments.lps import simulate_uwb_flight
    >>> from selfcal.toa.engine.nls import refine_toa
    >>> sim = simulate_uwb_flight(0, 300, layout="lps", bias_std=0.2, spike_rate=0.0, sparse_positions=0)
    >>> Y = sim["ranges"]
    >>> com = refine_toa(Y, sim["anchors"], sim["tag"], offsets="receivers", common_offsets="receivers")
    >>> rec = refine_toa(Y, com.receivers, com.sources, offsets="receivers", receiver_offsets0=com.receiver_offsets)
    >>> st = {"common": (com.receivers, com.sources, com.receiver_offsets, None),
    ...       "receivers": (rec.receivers, rec.sources, rec.receiver_offsets, None)}
    >>> cross_validate(Y, st).chosen
    'receivers'
    """
    from ..engine.nls import refine_toa
    from .offset_fit import residual_correlation_length

    Y = np.asarray(matrix, float)
    I, J = Y.shape
    models = [m for m in MODELS if m in starts]
    if not models:
        raise InputError(f"cross_validate: no candidate among {MODELS}")
    simplest = models[0]
    R0, S0, d0, o0 = starts[simplest]
    e0 = Y - (np.linalg.norm(np.asarray(R0)[:, None] - np.asarray(S0)[None], axis=2)
              + (0 if d0 is None else np.asarray(d0)[:, None]) + (0 if o0 is None else np.asarray(o0)[None]))
    L = residual_correlation_length(np.where(np.isfinite(Y), e0, np.nan))
    if folds is not None and np.ndim(folds):
        label = np.asarray(folds, np.intp)
    else:
        edges = np.linspace(0, J, int(folds) + 1).round().astype(np.intp) if folds else _folds(J, L)
        label = np.repeat(np.arange(len(edges) - 1), np.diff(edges))
    K = int(label.max()) + 1
    press: dict[str, Array] = {}
    refits: dict[str, list[Array]] = {}
    failed: dict[str, str] = {}
    total, done = len(models) * K, 0
    fails = (DegenerateGeometryError, InputError, np.linalg.LinAlgError, ValueError)
    for m in models:
        R, S, d, o = starts[m]
        P = np.full((I, J), np.nan)
        for k in range(K):
            test = label == k
            # training sources the model can locate (d + 1 ranges, one more with a source offset)
            need = np.asarray(R).shape[1] + 1 + int(m in ("sources", "both"))
            train = ~test & np.isfinite(np.asarray(S, float)).all(axis=1) & (np.isfinite(Y).sum(axis=0) >= need)
            kw: dict[str, Any] = dict(_REFIT[m])
            if d is not None:
                kw["receiver_offsets0"] = np.nan_to_num(np.asarray(d, float))
            if o is not None:
                kw["source_offsets0"] = np.nan_to_num(np.asarray(o, float)[train])
            try:
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore", ConvergenceWarning)
                    sol = refine_toa(np.where(np.isfinite(Y), Y, np.nan)[:, train], np.asarray(R, float),
                                     np.asarray(S, float)[train], covariance=False, solver=solver, **kw)
            except fails as exc:
                failed[m] = f"fold {k}: {exc}"
                break
            refits.setdefault(m, []).append(np.asarray(sol.receivers, float))
            _, _, E, H = locate_sources(Y[:, test], sol.receivers, sol.receiver_offsets,
                                        source_offset=m in ("sources", "both"))
            with np.errstate(all="ignore"):
                P[:, test] = np.where(H < _MAX_LEVERAGE, E / (1 - H), np.nan)
            done += 1
            if progress is not None:
                progress(done, total)
        if m not in failed:
            press[m] = P
    for m in [m for m, P in press.items() if not np.isfinite(P).any()]:
        failed[m] = "no held-out range can be predicted (each is fitted exactly by its own column's location)"
        del press[m]
    if not press:
        raise DegenerateGeometryError("no offsets model could be cross-validated: " + "; ".join(failed.values()),
                                      kind="too-few-measurements")
    common = np.logical_and.reduce([np.isfinite(P) for P in press.values()])
    fold_mse: dict[str, list[float]] = {}
    for m, P in press.items():
        fold_mse[m] = [float(np.mean(P[:, label == k][common[:, label == k]] ** 2))
                       if common[:, label == k].any() else float("nan") for k in range(K)]
    scores = {m: float(np.mean(P[common] ** 2)) if common.any() else float("nan") for m, P in press.items()}
    chosen, best, se = one_se_choice(scores, fold_mse, I, J)
    return CvChoice(chosen, scores, se, best, K, int(L), int(common.sum()), fold_mse, failed, refits)


def one_se_choice(scores: Mapping[str, float], fold_scores: Mapping[str, Sequence[float]],
                  I: int, J: int) -> tuple[str, str, dict[str, float]]:
    """The one-standard-error rule on paired per-fold CV scores, with a sign test: (chosen, best, se).

    ``best`` has the lowest score; ``se[m] = std_k(f_mk - f_bk) / sqrt(K)`` (folds where
    both are finite). The chosen model is the one with the fewest parameters among those
    with ``score[m] - score[best] <= se[m]`` *and* whose fold differences from ``best`` a
    one-sided sign test does not reject at :data:`SIGN_ALPHA` (:func:`sign_test_p`; see the
    module docstring: one fold with a huge difference inflates ``se`` as much as the mean).

    Examples
    --------
    >>> one_se_choice({"none": 1.02, "receivers": 1.0}, {"none": [1.1, 0.9, 1.06], "receivers": [1.0, 1.0, 1.0]},
    ...               6, 300)[0]
    'none'

    A simpler model worse in every one of 10 folds, one of them (a fold of one column, the
    others of two) by far: pooled over the entries its excess 0.062 is below its ``se``
    0.099, but the sign test (p = 2^-10) rejects it.

    >>> fold = {"sources": [0.01] * 9 + [1.0], "both": [0.0005] * 10}
    >>> scores = {m: (2 * sum(v[:9]) + v[9]) / 19 for m, v in fold.items()}
    >>> chosen, best, se = one_se_choice(scores, fold, 10, 14)
    >>> chosen, round(scores["sources"] - scores["both"], 3), round(se["sources"], 3)
    ('both', 0.062, 0.099)
    """
    ok = {m: v for m, v in scores.items() if np.isfinite(v)}
    if not ok:
        m0 = min(scores, key=lambda m: _complexity(m, I, J))
        return m0, m0, {m: float("nan") for m in scores}
    best = min(ok, key=lambda m: (ok[m], _complexity(m, I, J)))
    fb = np.asarray(fold_scores[best], float)
    se: dict[str, float] = {}
    for m in ok:
        diff = np.asarray(fold_scores[m], float) - fb
        diff = diff[np.isfinite(diff)]
        se[m] = float(np.std(diff, ddof=1) / np.sqrt(diff.size)) if diff.size > 1 else 0.0
    within = [m for m in ok if ok[m] - ok[best] <= se[m]
              and sign_test_p(fold_scores[m], fold_scores[best]) > SIGN_ALPHA]
    chosen = min(within, key=lambda m: (_complexity(m, I, J), ok[m]))
    return chosen, best, se


def sign_test_p(worse: Sequence[float], better: Sequence[float]) -> float:
    """One-sided sign test p-value that ``better`` has the lower per-fold score more often than chance.

    Folds where both are finite and differ; p = P(Binomial(n, 1/2) >= wins), ``wins`` the folds
    where ``better`` is lower (1.0 with no such fold).

    Examples
    --------
    >>> sign_test_p([2.0] * 10, [1.0] * 10) == 0.5 ** 10
    True
    >>> sign_test_p([1.0, 2.0], [1.0, 1.0])
    0.5
    """
    from scipy.stats import binomtest

    diff = np.asarray(worse, float) - np.asarray(better, float)
    diff = diff[np.isfinite(diff) & (diff != 0)]
    if not diff.size:
        return 1.0
    return float(binomtest(int((diff > 0).sum()), int(diff.size), 0.5, alternative="greater").pvalue)


def located_block(res: Any, sub: Array, scale: float = 1.0) -> tuple[Any, ...]:
    """A fit's located nodes and the entries it used, in metres, for refits started from it.

    Returns ``(kr, ks, used, Z, R, S, d0)``: (I,) / (J,) masks of the located receivers /
    sources, the (I, J) mask of the entries used (observed, not flagged), ``Z`` the used
    entries of ``sub * scale`` on the located block (NaN elsewhere), the located receivers
    and sources, and the receivers' offsets in metres (None without offsets).
    """
    kr = np.isfinite(res.receivers).all(axis=1)
    ks = np.isfinite(res.sources).all(axis=1)
    used = np.isfinite(res.residuals) & ~np.asarray(res.outliers, bool)
    Z = np.where(used, np.asarray(sub, float) * scale, np.nan)[np.ix_(kr, ks)]
    R, S = np.asarray(res.receivers, float)[kr], np.asarray(res.sources, float)[ks]
    d0 = None if res.receiver_offsets is None else np.asarray(res.receiver_offsets, float)[kr] * scale
    return kr, ks, used, Z, R, S, d0


def choose_receiver_offsets(res: Any, sub: Array, scale: float = 1.0, solver: str = "auto",
                            progress: Any = None) -> tuple[Any, CvChoice | None]:
    """Per-receiver offsets (per-anchor ranging biases) kept when they predict held-out sources
    better and their receivers are expected to be more accurate.

    ``res`` is a fit of ``sub`` without per-receiver offsets (``offsets`` "none" or
    "common"); the per-receiver model is refitted from it (the nested start: its offsets
    all equal to ``res``'s) on the entries ``res`` used, and :func:`cross_validate`
    compares the two on the same entries and folds. The per-receiver model is kept when
    the one-SE rule chooses it *and* :func:`anchor_mse` (from the same folds' refits, no
    extra fit) estimates its receivers' mean squared error below the simple model's:
    held-out prediction alone prefers offsets that trade against the receivers' radial
    positions where the tag stays on one side of them (LPS data4). Both are in ``choice``.

    Parameters
    ----------
    res : ToaResult
        The fit to compare against (receivers (I, d), sources (J, d), residuals, outliers).
    sub : (I, J) array
        The matrix it was fitted on, matrix units (metres, or seconds with ``scale``).
    scale : float
        Metres per matrix unit.
    solver : str
        Engine of the refits (:func:`selfcal.toa.engine.nls.refine_toa`).
    progress : callable, optional
        ``(done, total)`` after each refit.

    Returns
    -------
    (result, choice)
        ``res`` itself, or ``res`` with the per-receiver fit written in
        (``offsets="receivers"``) when it is kept; ``choice`` (its ``chosen`` the final
        model, ``anchors`` the :class:`AnchorMse`) is None when the per-receiver model
        could not be fitted.
    """
    from ..engine.nls import refine_toa
    from .offset_fit import _with_common

    simple = str(res.offsets)
    kr, ks, used, Z, R, S, d0 = located_block(res, sub, scale)
    fails = (DegenerateGeometryError, InputError, np.linalg.LinAlgError, ValueError)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", ConvergenceWarning)
            full = refine_toa(Z, R, S, offsets="receivers", receiver_offsets0=d0, covariance=True, solver=solver)
    except fails:
        return res, None
    starts = {simple: (R, S, d0, None),
              "receivers": (full.receivers, full.sources, full.receiver_offsets, None)}
    choice = cross_validate(Z, starts, solver=solver, progress=progress)
    # kept only where the receivers are expected to be more accurate too (anchor_mse: held-out
    # prediction can prefer offsets that trade against the receivers' radial positions)
    est = anchor_mse(simple, "receivers", starts, choice.refits) if "receivers" in choice.scores else None
    chosen = choice.chosen
    if chosen == "receivers" and est is not None and est.rmse["receivers"] >= est.rmse[simple]:
        chosen = simple
    choice = dataclasses.replace(choice, chosen=chosen, anchors=est)
    if choice.chosen != "receivers":
        return res, choice
    assert full.receiver_offsets is not None
    out = _with_common(res, full, sub, scale, kr, ks, used, np.asarray(full.receiver_offsets, float), "receivers")
    return out, choice
