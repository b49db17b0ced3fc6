"""What a range graph leaves undetermined: flat node sets, mirror-ambiguous nodes, regions larger
than the node set, the gauge the frame leaves (used by :mod:`selfcal.toa.graph.graph`)."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from .graph_fit import TEST_LEVEL, _fit, _Pairs

Array = NDArray[np.float64]
Index = NDArray[np.intp]


__all__: list[str] = []


def _mirror_ambiguous(X: Array, P: _Pairs, scale: float) -> NDArray[np.bool_]:
    """Nodes whose mirror placement through their partners' hyperplane fits as well (see GraphResult)."""
    from scipy.stats import chi2

    from ..sparse import _gauss_newton

    n, d = X.shape
    node = np.concatenate([P.a, P.b])
    other = np.concatenate([P.b, P.a])
    dist = np.concatenate([P.mean, P.mean])
    w = np.concatenate([P.weight, P.weight])
    order = np.argsort(node, kind="stable")
    node, other, dist, w = node[order], other[order], dist[order], w[order]
    starts = np.searchsorted(node, np.arange(n + 1))
    xm = X.copy()
    for k in range(n):
        Q = X[other[starts[k]:starts[k + 1]]]
        if Q.shape[0] < d:
            continue
        c = Q.mean(0)
        nv = np.linalg.svd(Q - c, full_matrices=False)[2][-1]
        xm[k] = X[k] - 2.0 * ((X[k] - c) @ nv) * nv
    anc = X[other]
    x0, _ = _gauss_newton(node, anc, dist, X.copy(), n, d, 5)
    x1, _ = _gauss_newton(node, anc, dist, xm, n, d, 5)
    rss = [np.bincount(node, w * (np.linalg.norm(z[node] - anc, axis=1) - dist) ** 2, minlength=n) for z in (x0, x1)]
    apart = np.linalg.norm(x1 - x0, axis=1) > 10.0 * max(scale, 1e-9) / np.sqrt(np.maximum(
        np.bincount(node, w, minlength=n), 1e-300))
    return np.asarray(apart & (rss[1] - rss[0] < chi2.ppf(1 - TEST_LEVEL, 1) * scale**2), dtype=bool)


def _region_larger_than_set(X: Array, cov: Array) -> NDArray[np.bool_]:
    """Nodes whose 95 % confidence ellipsoid's largest semi-axis exceeds the node set's radius."""
    from scipy.stats import chi2

    d = X.shape[1]
    radius = float(np.max(np.linalg.norm(X - X.mean(0), axis=1)))
    lam = np.linalg.eigvalsh(0.5 * (cov + np.swapaxes(cov, 1, 2)))[:, -1]
    return np.sqrt(chi2.ppf(0.95, d) * np.clip(lam, 0.0, None)) > radius


def _flat_within_errors(X: Array, P: _Pairs, n_meas: int) -> tuple[bool, float | None]:
    """Whether a 3-D node set is flat within its errors: ``(flat, p value)``.

    At a planar configuration the ranges determine no out-of-plane coordinate to first
    order (module docstring); a noisy fit bends the set off the plane by about
    ``sqrt(noise x size)`` (second order), where the linearised covariance is finite but
    says nothing. The nested models are compared instead: the best planar (2-D) fit against
    the 3-D fit, blind both, by the F test of the extra ``n - 3`` coordinates against the
    3-D noise estimate; the set is called flat when the plane is not rejected (p >= 1e-3).
    A set whose thinnest principal spread exceeds a quarter of the middle one is never
    flat at any noise that leaves a usable fit (its heights are far beyond
    ``sqrt(noise x size)``), so the two fits are spared there.
    """
    from scipy.stats import f as f_dist

    n, d = X.shape
    if d < 3 or n < 4:
        return False, None
    c = X.mean(0)
    _, sv, Vt = np.linalg.svd(X - c, full_matrices=False)
    if sv[2] > 0.25 * sv[1]:
        return False, None
    all3, all2 = np.ones((n, 3), bool), np.ones((n, 2), bool)
    X3, _, _ = _fit(X, P, all3, None)
    X2, _, _ = _fit((X - c) @ Vt[:2].T, P, all2, None)
    rss3, rss2 = (float(np.sum(P.weight * (np.linalg.norm(Z[P.a] - Z[P.b], axis=1) - P.mean) ** 2))
                  for Z in (X3, X2))
    q = n - 3
    dof = n_meas - (3 * n - 6)
    if dof <= 0:
        return True, None
    s2 = (rss3 + P.pe_ss) / dof
    F = max(rss2 - rss3, 0.0) / q / max(s2, 1e-300)
    p = float(f_dist.sf(F, q, dof))
    return p >= TEST_LEVEL, p


def _gauge_modes(X: Array, free: NDArray[np.bool_]) -> int:
    """Dimension of the rigid motions that leave every fixed coordinate unchanged (the residual gauge)."""
    n, d = X.shape
    modes = [np.tile(np.eye(d)[k], n) for k in range(d)]
    c = X.mean(0)
    for p in range(d):
        for q in range(p + 1, d):
            G = np.zeros((d, d))
            G[p, q], G[q, p] = -1.0, 1.0
            modes.append(((X - c) @ G.T).ravel())
    B = np.array(modes).T  # (n d, g)
    fixed = ~free.ravel()
    if not fixed.any():
        return B.shape[1]
    # motions whose fixed coordinates stay: the null space of B's fixed rows
    sv = np.linalg.svd(B[fixed], compute_uv=False)
    tol = 1e-9 * max(float(np.abs(X).max()), 1.0)
    return int(B.shape[1] - (sv > tol).sum())


