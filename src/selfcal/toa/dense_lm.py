"""The dense Levenberg-Marquardt step of small range problems, with the gauge projected analytically.

The same iteration as the "dense" step of :func:`selfcal.toa.schur_lm.solve_schur_lm`
(Marquardt diagonal damping ``(J^T W J + lam diag(J^T W J)) dx = -J^T W f``, the step
projected off the gauge, a damping trial accepted when the cost does not rise, the same
stopping rules), written for problems small enough that the per-iteration cost is
Python overhead, not arithmetic (12 receivers x 6 sources with both offsets: 72 ranges,
66 unknowns). What makes it cheaper than the general engine:

- the parameters stay in the receiver-major order of :mod:`selfcal.toa.nls` (no split into
  kept / eliminated node sets and back); the Jacobian is one preallocated (m, n) array whose
  offset columns never change, so an iteration writes only the 2 d unit-vector columns;
- the gauge is projected without a QR per iteration: translations, rotations about the
  centroid and (with both offset kinds) the common shift ``d_i + c, o_j - c`` are mutually
  orthogonal, so the orthogonal projector off their span is "subtract the mean of each
  coordinate", "subtract the shift's component" and a d(d-1)/2-square Gram solve for the
  rotations (the same projector as ``I - Q Q^T`` with Q the orthonormal
  :func:`selfcal.toa.nls.gauge_basis`, to round-off);
- each damped system is solved by one LAPACK ``posv`` call (Cholesky), least squares when
  it is not numerically positive definite;
- a mask of free parameters: the fixed ones keep their values and no gauge is projected
  (the fixed nodes hold the frame), which is the partial refit of the search's moves.

Cost per iteration O(m n^2) flops for ``J^T W J`` plus O(n^3 / 3) for the factorisation;
about 0.2 ms at 12 x 6 with both offsets here, against ~1 ms for the general engine's
dense step (its QR gauge basis, layout round trips and SciPy wrappers).
"""

from __future__ import annotations

import math

import numpy as np
import scipy.linalg
from numpy.typing import NDArray
from scipy.linalg import lapack

from ..robust import loss_rho

Array = NDArray[np.float64]

__all__ = ["GaugeProjector", "solve_dense_lm"]

#: relative cost decrease that stops the iteration (SciPy's default ftol; as schur_lm)
FTOL = 1e-8
#: damping trials per iteration before giving up (as schur_lm)
TRIALS = 12


def _rotation_generators(d: int) -> list[tuple[int, int]]:
    """(a, b) of the infinitesimal rotations ``x_a -> -x_b, x_b -> x_a`` (one in 2-D, three in 3-D)."""
    return [(0, 1)] if d == 2 else [(0, 1), (0, 2), (1, 2)]


def _well_conditioned(G: Array) -> bool:
    """Whether a 1 x 1 or 3 x 3 Gram matrix is far from singular (Hadamard ratio det / prod diag)."""
    g = G.tolist()
    if len(g) == 1:
        return g[0][0] > 0.0
    (a, b, c), (_, e, f), (_, _, i) = g
    det = a * (e * i - f * f) - b * (b * i - f * c) + c * (b * f - e * c)
    prod = a * e * i
    return prod > 0.0 and det > 1e-12 * prod


class GaugeProjector:
    """The orthogonal projector off the gauge directions at one point (formed once per iteration).

    Parameters
    ----------
    theta : (n,) point, receiver-major ``[r (I d), s (J d), d_i?, o_j?]``.
    N : number of nodes I + J; d : dimension; I : receivers.
    both : whether the common offset shift ``d_i + c, o_j - c`` is a gauge direction.

    Notes
    -----
    Translations (one unit vector per coordinate), rotations about the centroid (centred, so
    orthogonal to the translations) and the shift (on the offsets only) are mutually
    orthogonal; only the d(d-1)/2 rotations need their Gram matrix (``V^T (V V^T)^-1 V``). ``apply`` gives ``(I - Q Q^T) dx`` with Q the orthonormal basis of
    :func:`selfcal.toa.nls.gauge_basis`, to round-off.
    """

    def __init__(self, theta: Array, N: int, d: int, I: int, both: bool) -> None:
        self.N, self.d, self.I, self.both = N, d, I, both
        P = theta[: N * d].reshape(N, d)
        P = P - P.sum(axis=0) * (1.0 / N)
        gens = _rotation_generators(d)
        V = np.zeros((len(gens), N * d))
        for k, (a, b) in enumerate(gens):  # rotation a -> b: (-x_b, x_a) on coordinates (a, b)
            V[k, a::d] = -P[:, b]
            V[k, b::d] = P[:, a]
        G = V @ V.T
        ok = _well_conditioned(G)
        if ok:  # the rotations' projector V^T G^-1 V, applied as (V dx) @ (G^-1 V)
            W = np.linalg.solve(G, V)
        if not ok:  # points on a line: a dependent rotation adds no direction
            _, sv, Vt = np.linalg.svd(V, full_matrices=False)
            V = W = Vt[sv > 1e-10 * max(float(sv[0]), 1e-300)]
        self.V, self.W = V, W

    def apply(self, dx: Array) -> Array:
        """``dx`` minus its projection on the gauge directions (in place); returns dx."""
        N, d = self.N, self.d
        X = dx[: N * d].reshape(N, d)
        X -= X.sum(axis=0) * (1.0 / N)
        flat = dx[: N * d]
        flat -= (self.V @ flat) @ self.W
        if self.both:
            off = dx[N * d:]
            shift = (off[: self.I].sum() - off[self.I:].sum()) / off.size
            off[: self.I] -= shift
            off[self.I:] += shift
        return dx


def _solve(H: Array, rhs: Array) -> Array | None:
    """``H^-1 rhs`` by Cholesky (LAPACK posv); least squares when H is not numerically positive
    definite; None when not even that is finite."""
    _, x, info = lapack.dposv(H, rhs, lower=1, overwrite_a=0, overwrite_b=0)
    if info != 0:
        try:
            x = scipy.linalg.lstsq(H, rhs, check_finite=False)[0]
        except (np.linalg.LinAlgError, ValueError):
            return None
    return np.asarray(x, float) if np.isfinite(x).all() else None


def solve_dense_lm(
    theta0: Array, y: Array, ii: NDArray[np.intp], jj: NDArray[np.intp], I: int, J: int, d: int,
    offsets: str, loss: str, f_scale: float, max_nfev: int | None, xtol: float,
    free: NDArray[np.bool_] | None = None, max_it: int = 100,
) -> tuple[Array, bool, int]:
    """Levenberg-Marquardt with dense normal equations on the observed entries ``y``.

    Parameters
    ----------
    theta0 : (n,) start, receiver-major ``[r (I d), s (J d), d_i (I)?, o_j (J)?]`` (metres).
    y : (m,) observed ranges (metres); ii, jj : (m,) their receiver and source indices.
    I, J, d, offsets : the model (:mod:`selfcal.toa.nls`).
    loss, f_scale : robust loss (:func:`selfcal.robust.loss_rho`) and its scale (metres);
        robust losses run iteratively reweighted normal equations with weights rho'(z).
    max_nfev : iteration cap (default ``max_it``); xtol : relative step tolerance.
    free : (n,) bool, the parameters to fit (default all, and then the gauge is projected out
        of every step); the others are held at ``theta0`` and no gauge is projected.

    Returns
    -------
    (theta, converged, iterations) as :func:`selfcal.toa.schur_lm.solve_schur_lm`.
    """
    has_r, has_s = offsets in ("receivers", "both"), offsets in ("sources", "both")
    both = has_r and has_s
    theta = np.array(theta0, dtype=float)
    n = theta.size
    N = I + J
    m = y.size
    ar = np.arange(m)
    Jf = np.zeros((m, n))
    rcol = ii[:, None] * d + np.arange(d)
    scol = I * d + jj[:, None] * d + np.arange(d)
    k = N * d
    if has_r:
        Jf[ar, k + ii] = 1.0
        k += I
    if has_s:
        Jf[ar, k + jj] = 1.0
    fidx = None if free is None or bool(np.all(free)) else np.nonzero(free)[0]
    project = fidx is None
    i_off = N * d
    j_off = N * d + (I if has_r else 0)
    linear = loss == "linear"
    sj, ri, oj = I + jj, i_off + ii, j_off + jj
    ones = np.ones(m)

    def evaluate(t: Array) -> tuple[float, Array, Array, Array]:
        P = t[: N * d].reshape(N, d)
        u = P[ii] - P[sj]
        dist = np.sqrt(np.einsum("mp,mp->m", u, u))
        f = dist - y
        if has_r:
            f += t[ri]
        if has_s:
            f += t[oj]
        u *= np.divide(1.0, dist, out=np.zeros_like(dist), where=dist > 0)[:, None]  # 0 where points coincide
        if linear:
            return 0.5 * float(f @ f), f, ones, u
        rho, w = loss_rho((f / f_scale) ** 2, loss)
        return 0.5 * f_scale**2 * float(np.sum(rho)), f, np.asarray(w, float), u

    cost, f, w, u = evaluate(theta)
    lam = 1e-4
    converged = False
    it = 0
    cap = max_nfev or max_it
    Jflat = Jf.reshape(-1)
    pos_r = (ar[:, None] * n + rcol).ravel()  # flat positions of the unit-vector entries
    pos_s = (ar[:, None] * n + scol).ravel()
    nf = n if fidx is None else fidx.size
    dstep = np.arange(nf) * (nf + 1)  # flat positions of the diagonal
    while it < cap:
        it += 1
        uf = u.ravel()
        Jflat[pos_r] = uf
        Jflat[pos_s] = -uf
        Jm = Jf if fidx is None else Jf[:, fidx]
        if linear:
            H = np.dot(Jm.T, Jm)
            g = np.dot(Jm.T, f)
        else:
            Jw = Jm * w[:, None]
            H = np.dot(Jm.T, Jw)
            g = np.dot(Jw.T, f)
        hdiag = H.ravel()[dstep]
        proj = GaugeProjector(theta, N, d, I, both) if project else None
        gnorm = math.sqrt(float(g @ g))
        tnorm = math.sqrt(float(theta @ theta))
        mg = -g
        improved = False
        for _ in range(TRIALS):
            Hd = H.copy()
            Hd.ravel()[dstep] += lam * hdiag  # Marquardt: diag * (1 + lam)
            x = _solve(Hd, mg)
            if x is None:
                lam *= 10
                continue
            if fidx is None:
                dx = x
            else:
                dx = np.zeros(n)
                dx[fidx] = x
            if proj is not None:
                proj.apply(dx)  # no rigid drift (and no common offset shift)
            trial = theta + dx
            c2, f2, w2, u2 = evaluate(trial)
            if c2 <= cost:
                small = math.sqrt(float(dx @ dx)) <= xtol * (xtol + tnorm)
                rel = (cost - c2) <= FTOL * max(cost, 1e-300)
                theta, cost, f, w, u = trial, c2, f2, w2, u2
                lam = max(lam / 10, 1e-8)
                improved = True
                converged = bool(small or rel)
                break
            lam *= 10
        if not improved:
            # no damped step descends: a minimum up to round-off if the gradient is tiny
            converged = gnorm <= 1e-6 * max(1.0, math.sqrt(2 * cost))
            break
        if converged:
            break
    return theta, converged, it


def _batch_projectors(theta: Array, N: int, d: int) -> tuple[Array, Array]:
    """Rotation parts ``(V, W)`` of the gauge projectors of a batch (B, n) of points:
    ``V`` (B, g_rot, N d) the rotation vectors, ``W = (V V^T)^-1 V``; see :class:`GaugeProjector`."""
    B = theta.shape[0]
    P = theta[:, : N * d].reshape(B, N, d)
    P = P - P.sum(axis=1, keepdims=True) * (1.0 / N)
    gens = _rotation_generators(d)
    V = np.zeros((B, len(gens), N * d))
    for k, (a, b) in enumerate(gens):
        V[:, k, a::d] = -P[:, :, b]
        V[:, k, b::d] = P[:, :, a]
    G = V @ V.transpose(0, 2, 1)
    ok = np.array([_well_conditioned(Gb) for Gb in G])
    W = np.empty_like(V)
    if ok.any():
        W[ok] = np.linalg.solve(G[ok], V[ok])
    for b in np.nonzero(~ok)[0]:  # points on a line: the single-point projector's fallback
        gp = GaugeProjector(theta[b], N, d, 0, False)
        V[b] = 0.0
        W[b] = 0.0
        V[b, : gp.V.shape[0]] = gp.V
        W[b, : gp.W.shape[0]] = gp.W
    return V, W


def solve_dense_lm_batch(
    theta0: Array, y: Array, ii: NDArray[np.intp], jj: NDArray[np.intp], I: int, J: int, d: int,
    offsets: str, loss: str, f_scale: float, max_nfev: int | None, xtol: float, max_it: int = 100,
) -> tuple[Array, NDArray[np.bool_], NDArray[np.intp]]:
    """:func:`solve_dense_lm` on a batch of starts at once (the search's pool of starts).

    Parameters
    ----------
    theta0 : (B, n) starts, receiver-major; the other parameters as :func:`solve_dense_lm`
        (no ``free`` mask: the gauge is projected out of every step).

    Returns
    -------
    theta (B, n), converged (B,), iterations (B,): per start, the iterates of
    :func:`solve_dense_lm` from that start (to round-off: tested).

    Notes
    -----
    Each start keeps its own damping, iteration count and damping trials; one pass of the
    loop runs one damping trial of every unfinished start with stacked arrays (the normal
    matrices (B, n, n), their solves, the residuals (B, m)), so the Python overhead of an
    iteration, which is what a 12 x 6 iteration costs, is paid once per pass instead of once
    per start. Starts that begin a new iteration form their normal matrix in the same pass.
    """
    has_r, has_s = offsets in ("receivers", "both"), offsets in ("sources", "both")
    both = has_r and has_s
    theta = np.array(theta0, dtype=float, copy=True)
    if theta.ndim != 2:
        raise ValueError("theta0 must be (B, n)")
    Bn, n = theta.shape
    N = I + J
    m = y.size
    i_off = N * d
    j_off = N * d + (I if has_r else 0)
    sj, ri, oj = I + jj, i_off + ii, j_off + jj
    linear = loss == "linear"
    ar = np.arange(m)
    Jf = np.zeros((Bn, m, n))
    if has_r:
        Jf[:, ar, ri] = 1.0
    if has_s:
        Jf[:, ar, oj] = 1.0
    rcol = ii[:, None] * d + np.arange(d)
    scol = I * d + jj[:, None] * d + np.arange(d)
    pos_r = (ar[:, None] * n + rcol).ravel()
    pos_s = (ar[:, None] * n + scol).ravel()
    dpos = np.arange(n) * (n + 1)

    def evaluate(t: Array) -> tuple[Array, Array, Array, Array]:
        k = t.shape[0]
        P = t[:, : N * d].reshape(k, N, d)
        u = P[:, ii] - P[:, sj]
        dist = np.sqrt(np.einsum("bmp,bmp->bm", u, u))
        f = dist - y
        if has_r:
            f += t[:, ri]
        if has_s:
            f += t[:, oj]
        u *= np.divide(1.0, dist, out=np.zeros_like(dist), where=dist > 0)[:, :, None]
        if linear:
            return 0.5 * np.einsum("bm,bm->b", f, f), f, np.ones_like(f), u
        rho, w = loss_rho((f / f_scale) ** 2, loss)
        return 0.5 * f_scale**2 * np.sum(rho, axis=1), f, np.asarray(w, float), u

    cost, f, w, u = evaluate(theta)
    lam = np.full(Bn, 1e-4)
    converged = np.zeros(Bn, bool)
    it = np.zeros(Bn, np.intp)
    trials = np.zeros(Bn, np.intp)
    active = np.ones(Bn, bool)
    fresh = np.ones(Bn, bool)  # starts an iteration: form its normal matrix
    cap = max_nfev or max_it
    H = np.zeros((Bn, n, n))
    g = np.zeros((Bn, n))
    gnorm = np.zeros(Bn)
    tnorm = np.zeros(Bn)
    V = np.zeros((Bn, len(_rotation_generators(d)), N * d))
    W = np.zeros_like(V)
    Jflat = Jf.reshape(Bn, -1)
    while active.any():
        nb = np.nonzero(active & fresh)[0]
        if nb.size:
            over = it[nb] >= cap
            active[nb[over]] = False
            nb = nb[~over]
        if nb.size:
            it[nb] += 1
            uf = u[nb].reshape(nb.size, -1)
            Jflat[nb[:, None], pos_r] = uf
            Jflat[nb[:, None], pos_s] = -uf
            Jm = Jf[nb]
            JT = Jm.transpose(0, 2, 1)
            if linear:
                H[nb] = JT @ Jm
                g[nb] = np.einsum("bnm,bm->bn", JT, f[nb])
            else:
                Jw = Jm * w[nb][:, :, None]
                H[nb] = JT @ Jw
                g[nb] = np.einsum("bmn,bm->bn", Jw, f[nb])
            gnorm[nb] = np.sqrt(np.einsum("bn,bn->b", g[nb], g[nb]))
            tnorm[nb] = np.sqrt(np.einsum("bn,bn->b", theta[nb], theta[nb]))
            V[nb], W[nb] = _batch_projectors(theta[nb], N, d)
            trials[nb] = 0
            fresh[nb] = False
        act = np.nonzero(active)[0]
        if not act.size:
            break
        Hd = H[act].copy()
        Hd.reshape(act.size, -1)[:, dpos] += lam[act][:, None] * H[act].reshape(act.size, -1)[:, dpos]
        rhs = -g[act]
        try:
            x = np.linalg.solve(Hd, rhs[:, :, None])[:, :, 0]
        except np.linalg.LinAlgError:
            x = np.full_like(rhs, np.nan)
            for k in range(act.size):
                xk = _solve(Hd[k], rhs[k])
                if xk is not None:
                    x[k] = xk
        ok = np.isfinite(x).all(axis=1)
        trials[act] += 1
        # gauge: translations, rotations, the common shift (GaugeProjector.apply, stacked)
        X = x[:, : N * d].reshape(act.size, N, d)
        X -= X.sum(axis=1, keepdims=True) * (1.0 / N)
        flat = x[:, : N * d]
        flat -= np.einsum("bk,bkn->bn", np.einsum("bkn,bn->bk", V[act], flat), W[act])
        if both:
            off = x[:, N * d:]
            shift = (off[:, :I].sum(axis=1) - off[:, I:].sum(axis=1)) / off.shape[1]
            off[:, :I] -= shift[:, None]
            off[:, I:] += shift[:, None]
        x[~ok] = 0.0
        trial = theta[act] + x
        c2, f2, w2, u2 = evaluate(trial)
        acc = ok & (c2 <= cost[act])
        a_idx = act[acc]
        if a_idx.size:
            dxn = np.sqrt(np.einsum("bn,bn->b", x[acc], x[acc]))
            small = dxn <= xtol * (xtol + tnorm[a_idx])
            rel = (cost[a_idx] - c2[acc]) <= FTOL * np.maximum(cost[a_idx], 1e-300)
            theta[a_idx], cost[a_idx], f[a_idx], w[a_idx], u[a_idx] = trial[acc], c2[acc], f2[acc], w2[acc], u2[acc]
            lam[a_idx] = np.maximum(lam[a_idx] / 10, 1e-8)
            converged[a_idx] = small | rel
            active[a_idx[converged[a_idx]]] = False
            fresh[a_idx] = True
        r_idx = act[~acc]
        if r_idx.size:
            lam[r_idx] *= 10
            out = r_idx[trials[r_idx] >= TRIALS]  # no damped step descends
            if out.size:
                converged[out] = gnorm[out] <= 1e-6 * np.maximum(1.0, np.sqrt(2 * cost[out]))
                active[out] = False
    return theta, converged, it
