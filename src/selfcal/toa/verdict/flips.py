"""Flip candidates of a TOA fit: nodes whose measured partners (nearly) span less than the space.

A node's ranges fix it only up to the isometries that fix its partners. When the partners
lie on a hyperplane (a line in 2-D, a plane in 3-D) the reflection through it leaves
every range of the node unchanged: the node has an exact alternative position, whatever
the noise. When they lie on a line in 3-D every rotation about the line does too (the
rotation by 180 degrees is the candidate tested). When they are only *nearly* coplanar,
the reflection changes the node's range to partner ``j`` by at most ``2 |z_j|`` (``z_j``
the partner's distance from the plane), so the flipped node misfits by at most
``4 sum z_j^2 = 4 lambda_min`` (``lambda_min`` the smallest eigenvalue of the partners'
centred scatter); and the partners' own error bars say whether their out-of-plane spread
is resolved at all. This module finds those nodes for every node of a fit at once
(one product of the observation mask with the partners' moments, O(I J d^2)), reflects
them and refits each flipped node alone (its own offset free, every other parameter held:
Gauss-Newton with Levenberg damping, vectorised over the candidates). The
likelihood-ratio decision is :mod:`selfcal.toa.verdict.uniqueness`'s.

References
----------
Flip ambiguities: Moore, Leonard, Rus, Teller, "Robust distributed network localization
with noisy range measurements", SenSys 2004 (flip and flex ambiguities of a node with
(nearly) collinear neighbours); Kannan, Fidan, Mao, "Robust distributed sensor network
localization based on analysis of flip ambiguities", GLOBECOM 2008.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

__all__ = ["FlipCandidates", "coplanar_partner_nodes", "flip_candidates", "refit_nodes"]

Array = NDArray[np.float64]

#: Gauss-Newton iterations of a flipped node refitted alone (a d- or (d+1)-unknown problem
#: started at an exact reflection: it converges in a few; more only costs)
NODE_ITERATIONS = 8


@dataclass(frozen=True)
class FlipCandidates:
    """Nodes of one kind (receivers or sources) with a flip candidate.

    Attributes
    ----------
    index: (k,) node indices.
    position: (k, d) the fitted positions; flipped: (k, d) their reflections.
    normal: (k, d) unit normals of the partners' (near-)null direction used.
    thickness2: (k,) ``lambda_min``: the partners' squared out-of-plane spread (m^2).
    exact: (k,) partners span less than the space to the solver's precision.
    """

    index: NDArray[np.intp]
    position: Array
    flipped: Array
    normal: Array
    thickness2: Array
    exact: NDArray[np.bool_]


def flip_candidates(points: Array, partners: Array, observed: NDArray[np.bool_], *, noise2: float,
                    partner_var: Array | None, point_std: Array | None, quantile: float,
                    bound: float, skip: NDArray[np.bool_] | None = None) -> FlipCandidates:
    """The nodes ``points`` whose partners (nearly) span less than the space, and their flips.

    Parameters
    ----------
    points: (n, d) the nodes (receivers, or sources); partners: (p, d) the other kind.
    observed: (n, p) bool, the entries the fit used (node i measured partner j).
    noise2: range noise variance (m^2); a partner's covariance where it is unknown is ``noise2 I``.
    partner_var: (p, d, d) partner covariances (m^2), NaN where unknown; None = none.
    point_std: (n,) the nodes' own error bars ``sqrt(trace C)`` (m), NaN where unknown.
    quantile: a direction ``v`` is (nearly) null when ``lambda_v <= quantile * sum_j v^T C_j v``:
        the partners' spread along ``v`` is not resolved by their own error bars (under a
        coplanar truth ``lambda_v / sum_j v^T C_j v`` is about ``chi2(p - d) / p``, below
        ``chi2(1)``'s quantile at the same level for every ``p > d``).
    bound: RSS (m^2): a direction is also a candidate when ``4 lambda_v <= bound`` (the flip
        misfits by less than what the test tolerates, whatever the error bars).
    skip: (n,) nodes not to flip (known, fixed nodes).

    Returns
    -------
    FlipCandidates; a node whose reflection moves it by less than 3 of its error bars
    (it lies in its partners' plane) is no candidate: both positions are the same answer.
    """
    idx, pos, flipped, normal, lam_min, exact, moved = _reflections(
        points, partners, observed, noise2=noise2, partner_var=partner_var, point_std=point_std,
        quantile=quantile, bound=bound, skip=skip)
    return FlipCandidates(idx[moved], pos[moved], flipped[moved], normal[moved], lam_min[moved], exact[moved])


def coplanar_partner_nodes(points: Array, partners: Array, observed: NDArray[np.bool_], *, noise2: float,
                           partner_var: Array | None, point_std: Array | None, quantile: float,
                           bound: float = 0.0, skip: NDArray[np.bool_] | None = None) -> NDArray[np.bool_]:
    """The nodes whose partners are coplanar within their own error bars (same criteria as
    :func:`flip_candidates`, every such node: its flip candidates and the rest).

    Such a node's height ``h`` above its partners' plane is not determined to first order
    by the data in the way its linearised (Cramér-Rao) covariance says:

    - its sign is free: the reflection through the plane changes no range by more than the
      partners' unresolved spread (the flip, tested by :mod:`.uniqueness`);
    - its size enters each range at second order, ``rho_j + h^2 / (2 rho_j)``: the misfit
      is a double well ``A (h^2 - h0^2)^2`` symmetric about the plane, whose curvature at the
      fitted ``h0`` (the linearised variance ``1 / (8 A h0^2)``) describes one well only; a
      node within 1.5 error bars of the plane has its mirror inside its own 3-sigma region;
    - the plane itself (the partners' heights) is bent by the same second-order freedom:
      a whole layout thinner than about ``sqrt(noise x extent)`` comes back bent by that much,
      with linearised bars several times smaller (the boundary desks of
      ``tests/acoustics/test_near_planar.py``: heights 1-2 cm off against 2-8 mm bars).

    :func:`selfcal.toa.verdict.select.dimension_test` therefore does not count these
    nodes' bars as evidence of a resolved thickness.

    Returns
    -------
    (n,) bool
    """
    idx = _reflections(points, partners, observed, noise2=noise2, partner_var=partner_var,
                       point_std=point_std, quantile=quantile, bound=bound, skip=skip)[0]
    out = np.zeros(len(np.asarray(points)), bool)
    out[idx] = True
    return out


def _reflections(points: Array, partners: Array, observed: NDArray[np.bool_], *, noise2: float,
                 partner_var: Array | None, point_std: Array | None, quantile: float, bound: float,
                 skip: NDArray[np.bool_] | None) -> tuple[NDArray[np.intp], Array, Array, Array, Array,
                                                          NDArray[np.bool_], NDArray[np.bool_]]:
    """Every node with a near-null partner direction: (index, position, reflection, normal,
    lambda_min, exact, moved); ``moved``: the reflection leaves its 3-error-bar region."""
    P = np.asarray(points, float)
    Q = np.asarray(partners, float)
    W = np.asarray(observed, float)
    n, d = P.shape
    cnt = W.sum(1)
    ok = cnt >= 1
    if skip is not None:
        ok &= ~np.asarray(skip, bool)
    safe = np.maximum(cnt, 1.0)[:, None]
    c = (W @ Q) / safe  # (n, d) partner centroids
    M2 = (W @ np.einsum("pi,pj->pij", Q, Q).reshape(Q.shape[0], d * d)).reshape(n, d, d)
    S = M2 - safe[:, :, None] * np.einsum("ni,nj->nij", c, c)  # centred scatter, sum over partners
    S = 0.5 * (S + np.transpose(S, (0, 2, 1)))
    lam, V = np.linalg.eigh(S)  # ascending
    lam = np.maximum(lam, 0.0)
    scale2 = max(float(np.max(lam)) if lam.size else 0.0, 1e-300)
    eps_lam = 1e-12 * scale2
    # each partner's covariance (m^2); where unknown, the range noise's (a partner known to
    # about one range error)
    C = np.broadcast_to(noise2 * np.eye(d), (Q.shape[0], d, d)).copy()
    if partner_var is not None:
        Cp = np.asarray(partner_var, float)
        fin = np.isfinite(Cp).all(axis=(1, 2))
        C[fin] = Cp[fin]
    Csum = (W @ C.reshape(C.shape[0], d * d)).reshape(n, d, d)
    pv = np.einsum("nik,nij,njk->nk", V, Csum, V)  # summed partner variance along each eigenvector
    null = (lam <= quantile * pv) | (4.0 * lam <= bound) | (lam <= eps_lam)
    null &= ok[:, None]
    # never the widest direction (a reflection along it is no flip), except for a node with a
    # single partner: every direction is then free (undetermined: the determinacy test says so)
    null[:, -1] &= cnt <= 1
    cand = null.any(1)
    idx = np.flatnonzero(cand)
    if idx.size == 0:
        z = np.zeros((0, d))
        return idx, z, z, z, np.zeros(0), np.zeros(0, bool), np.zeros(0, bool)
    off = P[idx] - c[idx]
    Vn = V[idx] * null[idx][:, None, :]  # columns of the near-null directions
    proj = np.einsum("kij,kj->ki", Vn, np.einsum("kji,kj->ki", Vn, off))  # off projected onto them
    h = np.linalg.norm(proj, axis=1)
    normal = proj / np.maximum(h, 1e-300)[:, None]
    # in 3-D a node whose partners lie on a line: reflecting through the plane holding the
    # line and perpendicular to ``off`` is the rotation by 180 degrees about the line
    flipped = P[idx] - 2.0 * h[:, None] * normal
    std = np.full(idx.size, np.nan) if point_std is None else np.asarray(point_std, float)[idx]
    floor = 1e-9 * np.sqrt(scale2 / max(float(cnt.max()), 1.0))
    moved = 2.0 * h > np.where(np.isfinite(std), 3.0 * std, 0.0) + floor
    lam_min = lam[idx, 0]
    return idx, P[idx], flipped, normal, lam_min, lam_min <= eps_lam, moved


def refit_nodes(start: Array, partners: Array, y: Array, observed: NDArray[np.bool_], partner_offset: Array,
                offset0: Array | None, *, iterations: int = NODE_ITERATIONS) -> tuple[Array, Array | None, Array]:
    """Refit k nodes, each alone against its fixed partners (Gauss-Newton, Levenberg damping).

    Parameters
    ----------
    start: (k, d) starting positions; partners: (p, d) fixed partner positions.
    y: (k, p) ranges between each node and each partner (metres; entries not ``observed`` ignored).
    observed: (k, p) bool.
    partner_offset: (p,) the partners' offsets (zeros when the model has none), held.
    offset0: (k,) the nodes' own offsets (fitted with them), or None (the model has none).
    iterations: Gauss-Newton steps.

    Returns
    -------
    (positions (k, d), offsets (k,) or None, rss (k,)): each node's residual sum of squares
    over its observed entries at the refitted position.
    """
    X = np.array(start, float)
    k, d = X.shape
    W = np.asarray(observed, float)
    Yv = np.where(observed, y, 0.0)
    b = None if offset0 is None else np.array(offset0, float)
    npar = d + (0 if b is None else 1)

    def resid(X: Array, b: Array | None) -> tuple[Array, Array]:
        D = X[:, None, :] - partners[None]
        rho = np.linalg.norm(D, axis=-1)
        model = rho + partner_offset[None] + (0.0 if b is None else b[:, None])
        return (Yv - model) * W, D / np.maximum(rho, 1e-300)[..., None]

    r, U = resid(X, b)
    rss = np.sum(r**2, axis=1)
    mu = np.full(k, 1e-3)
    for _ in range(iterations):
        Jm = U * W[..., None]  # d model / d position
        if b is not None:
            Jm = np.concatenate([Jm, W[..., None]], axis=-1)
        A = np.einsum("kpi,kpj->kij", Jm, Jm)
        g = np.einsum("kpi,kp->ki", Jm, r)
        diag = np.einsum("kii->ki", A)
        A = A + (mu[:, None] * np.maximum(diag, 1e-300))[..., None] * np.eye(npar)[None]
        try:
            step = np.linalg.solve(A, g[..., None])[..., 0]
        except np.linalg.LinAlgError:
            break
        Xn = X + step[:, :d]
        bn = None if b is None else b + step[:, d]
        rn, Un = resid(Xn, bn)
        rssn = np.sum(rn**2, axis=1)
        better = np.isfinite(rssn) & (rssn <= rss)
        X = np.where(better[:, None], Xn, X)
        if b is not None and bn is not None:
            b = np.where(better, bn, b)
        r = np.where(better[:, None], rn, r)
        U = np.where(better[:, None, None], Un, U)
        rss = np.where(better, rssn, rss)
        mu = np.where(better, mu * 0.3, mu * 10.0)
    return X, b, rss
