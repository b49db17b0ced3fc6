"""The fit of a range graph: pair means of repeats, the weighted least squares on the free
coordinates (a model of the one driver :func:`selfcal.optim.lm.levenberg_marquardt`), its
covariance, and the outlier flags (used by :mod:`selfcal.toa.graph.graph`; see its docstring for
the model)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]
Index = NDArray[np.intp]

__all__ = ["NULL_TOL", "TEST_LEVEL", "collapse_repeats"]

#: level of the residual tests (chi-square with a given std, lack of fit against the repeats)
TEST_LEVEL = 1e-3
#: an information-matrix eigenvalue below this fraction of the largest is a null direction
NULL_TOL = 1e-9


@dataclass(frozen=True)
class _Pairs:
    a: Index
    b: Index
    mean: Array
    weight: Array
    pair_of: Index
    pe_ss: float
    pe_dof: int


def collapse_repeats(a: Any, b: Any, ranges: Any, std: Any = None) -> tuple[Index, Index, Array, Array, Index]:
    """Pair means of repeated measurements (an unordered pair is one pair).

    Parameters
    ----------
    a, b : (m,) int
        Nodes of each measurement.
    ranges : (m,) float
    std : (m,) float, optional
        Per-measurement std (weights ``1 / std^2``); unit weights when None.

    Returns
    -------
    (pa, pb, mean, weight, pair_of)
        Per pair the nodes (``pa < pb``), the weighted mean range and the summed weight;
        ``pair_of[m]`` is the pair of measurement ``m``.

    Examples
    --------
    >>> pa, pb, mu, w, k = collapse_repeats([0, 1, 0], [1, 0, 2], [4.0, 4.2, 3.0])
    >>> pa.tolist(), pb.tolist(), mu.round(6).tolist(), w.tolist(), k.tolist()
    ([0, 0], [1, 2], [4.1, 3.0], [2.0, 1.0], [0, 0, 1])
    """
    a, b = np.asarray(a, np.intp), np.asarray(b, np.intp)
    y = np.asarray(ranges, float)
    w = np.ones_like(y) if std is None else 1.0 / np.asarray(std, float) ** 2
    lo: Index = np.minimum(a, b)
    hi: Index = np.maximum(a, b)
    key = lo.astype(np.int64) * (int(max(a.max(initial=0), b.max(initial=0))) + 1) + hi
    uniq, first, pair_of = np.unique(key, return_index=True, return_inverse=True)
    W = np.bincount(pair_of, w, minlength=uniq.size)
    mean = np.bincount(pair_of, w * y, minlength=uniq.size) / W
    return lo[first], hi[first], np.asarray(mean, float), np.asarray(W, float), pair_of.astype(np.intp)


def _pairs(a: Index, b: Index, y: Array, std: Array | None) -> _Pairs:
    pa, pb, mean, W, k = collapse_repeats(a, b, y, std)
    w = np.ones_like(y) if std is None else 1.0 / std**2
    pe = float(np.sum(w * (y - mean[k]) ** 2))
    return _Pairs(pa, pb, mean, W, k, pe, int(y.size - mean.size))


def _subset(P: _Pairs, keep: NDArray[np.bool_], a: Index, b: Index, y: Array, std: Array | None) -> _Pairs:
    """The pairs ``keep`` (their measurements' pure error recomputed)."""
    m = keep[P.pair_of]
    return _pairs(a[m], b[m], y[m], None if std is None else std[m])


def _flag_pairs(X: Array, P: _Pairs, d: int, free: NDArray[np.bool_], *, scale: float) -> NDArray[np.bool_]:
    """Pairs whose studentized residual exceeds the Bonferroni bound over ``scale``; a node keeps d + 1 partners.

    ``t_p = e_p / sqrt(1 - h_p)`` with the leverage ``h_p`` of the pair in the fit. A pair
    with ``h_p > 1/2`` is not judged: the fit absorbs more than half of its error, so its
    residual cannot tell it from its neighbours' (an anchor-only graph of 7 anchors has
    ``h = 5/7`` everywhere: a biased pair is then seen by the lack-of-fit test, not located).
    Leverages need the dense information matrix: above 1500 free coordinates ``h = 0``.
    """
    from ..verdict.robust import outlier_threshold

    e = np.sqrt(P.weight) * (P.mean - np.linalg.norm(X[P.a] - X[P.b], axis=1))
    h = np.zeros(e.size)
    if int(free.sum()) <= 1500:
        J = _jacobian(X, P, free, np.sqrt(P.weight)).toarray()
        h = np.clip(np.einsum("pi,pi->p", J @ np.linalg.pinv(J.T @ J, hermitian=True), J), 0.0, 1.0)
    judged = h <= 0.5
    t = np.where(judged, e / np.sqrt(np.clip(1.0 - h, 1e-12, None)), 0.0)
    flag = judged & (np.abs(t) > outlier_threshold(int(judged.sum())) * scale)
    e = t
    n = X.shape[0]
    for k in np.argsort(-np.abs(e)):  # largest first; unflag where a node would drop below d + 1
        if not flag[k]:
            break
        deg = np.bincount(np.concatenate([P.a[~flag], P.b[~flag]]), minlength=n)
        if deg[P.a[k]] < d + 1 or deg[P.b[k]] < d + 1:
            flag[k] = False
    return flag



# ---------------------------------------------------------------------------------------
# the fit
# ---------------------------------------------------------------------------------------

def _jacobian(X: Array, P: _Pairs, free: NDArray[np.bool_], sw: Array) -> Any:
    from scipy.sparse import csr_matrix

    n, d = X.shape
    col = -np.ones((n, d), np.intp)
    col[free] = np.arange(int(free.sum()))
    diff = X[P.a] - X[P.b]
    u = diff / np.maximum(np.linalg.norm(diff, axis=1), 1e-12)[:, None]
    rows, cols, vals = [], [], []
    p = np.arange(P.a.size)
    for node, sign in ((P.a, 1.0), (P.b, -1.0)):
        for k in range(d):
            c = col[node, k]
            ok = c >= 0
            rows.append(p[ok])
            cols.append(c[ok])
            vals.append(sign * sw[ok] * u[ok, k])
    return csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                      shape=(P.a.size, int(free.sum())))


def _fit(X0: Array, P: _Pairs, free: NDArray[np.bool_], prior: tuple[Array, Array] | None,
         loss: str = "linear", f_scale: float = 1.0) -> tuple[Array, bool, int]:
    """Weighted least squares over the free coordinates (priors: ``(mu, 1/std)`` rows per coordinate).

    The range-graph model on the driver (:class:`selfcal.optim.steps.ResidualModel`):
    residuals ``sqrt(W_p) (|x_a - x_b| - ybar_p)`` and the prior rows, the sparse Jacobian of
    :func:`_jacobian` (two ``d``-blocks per pair), the robust loss by the driver's IRLS; the
    parametrisation keeps the fixed coordinates (known nodes, frame references) out of the
    unknowns, and a blind fit (every coordinate free, no prior) has the rigid motions
    projected off each step (:class:`selfcal.toa.engine.model.GaugeProjector`, as the TOA
    engines). The step: dense Cholesky or the sparse normal equations by SuperLU, as
    :func:`selfcal.optim.structure.lm_step` decides from the number of unknowns.

    Returns the positions, whether a stopping rule was met, and the driver's iterations.
    """
    from scipy.sparse import diags, vstack

    from ...optim.lm import levenberg_marquardt
    from ...optim.steps import ResidualModel
    from ..engine.model import GaugeProjector

    n, d = X0.shape
    sw = np.sqrt(P.weight)
    theta0 = X0[free]
    pm = None
    if prior is not None:
        mu, isd = prior
        pm = np.isfinite(mu[free])
        if not pm.any():
            pm = None

    def unpack(theta: Array) -> Array:
        X = X0.copy()
        X[free] = theta
        return X

    def fun(theta: Array) -> Array:
        X = unpack(theta)
        r = sw * (np.linalg.norm(X[P.a] - X[P.b], axis=1) - P.mean)
        if pm is not None:
            r = np.concatenate([r, (theta[pm] - prior[0][free][pm]) * prior[1][free][pm]])  # type: ignore[index]
        return r

    def jac(theta: Array) -> Any:
        J = _jacobian(unpack(theta), P, free, sw)
        if pm is not None:
            Jp = diags(prior[1][free] * pm, format="csr")[np.flatnonzero(pm)]  # type: ignore[index]
            J = vstack([J, Jp], format="csr")
        return J

    project = None
    if free.all() and pm is None:  # blind: the rigid motions are the gauge (node-major theta)
        def project(theta: Array) -> Any:
            return GaugeProjector(theta, n, d, n, False).apply

    model = ResidualModel(fun, jac, loss=loss, f_scale=f_scale, step="auto", project=project)
    sol = levenberg_marquardt(model, theta0, max_iter=500, xtol=1e-10, ftol=1e-12)
    return unpack(sol.x), bool(sol.converged), int(sol.iterations)


def _covariance(X: Array, P: _Pairs, free: NDArray[np.bool_], prior_isd: Array | None, scale: float
                ) -> tuple[Array, NDArray[np.bool_], int]:
    """Per-node covariance blocks (pseudo-inverse of the information) and the null directions.

    Returns the (n, d, d) blocks, the (n,) mask of nodes moved by a null direction beyond
    the expected gauge, and the number of null directions.
    """
    n, d = X.shape
    J = _jacobian(X, P, free, np.sqrt(P.weight)).toarray()
    F = J.T @ J
    if prior_isd is not None:
        F[np.diag_indices_from(F)] += np.where(np.isfinite(prior_isd[free]), prior_isd[free], 0.0) ** 2
    lam, V = np.linalg.eigh(F)
    null = lam <= NULL_TOL * max(lam[-1], 1e-300)
    inv = np.where(null, 0.0, 1.0 / np.where(null, 1.0, lam))
    C = (V * inv) @ V.T * scale**2
    full = np.zeros((n * d, n * d))
    idx = np.flatnonzero(free.ravel())
    full[np.ix_(idx, idx)] = C
    blocks = np.stack([full[k * d:(k + 1) * d, k * d:(k + 1) * d] for k in range(n)])
    moved = np.zeros(n, bool)
    if null.any():
        Vn = np.zeros((n * d, int(null.sum())))
        Vn[idx] = V[:, null]
        moved = np.linalg.norm(Vn.reshape(n, d, -1), axis=(1, 2)) > 1e-3
    return blocks, moved, int(null.sum())


