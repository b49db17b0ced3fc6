"""Variable projection of the offsets: Levenberg-Marquardt on the positions alone.

The range model ``y_ij = |r_i - s_j| + d_i + o_j`` is linear in the offsets. For a given
geometry the offsets minimising the (weighted) cost are a small linear least-squares problem
over the observed entries, so they can be eliminated (Golub & Pereyra 1973): the reduced
residual is ``P (dist(x) - y)`` with ``P = I - A (A^T W A)^+ A^T W`` the weighted projector
off the offset design A (0/1 columns, one per offset of the model), and because A does not
depend on the positions, ``P J_x`` is the *exact* Jacobian of the reduced residual (Kaufman's
1975 approximation drops nothing here). Each iteration:

1. the normal matrix of the full problem ``J^T W J`` is formed as in
   :func:`selfcal.toa.dense_lm.solve_dense_lm`; the offset block is eliminated (Schur
   complement), which is ``J_x^T W P J_x``, the reduced Gauss-Newton matrix;
2. the damped reduced system is solved for the position step, which is projected off the
   rigid gauge (:class:`selfcal.toa.dense_lm.GaugeProjector`, positions only);
3. at the trial positions the offsets are *re-solved* (not moved by their linearised step):
   the cost compared is the variable-projection cost ``min_z cost(x, z)``. Robust losses use
   the current IRLS weights for that solve (the fixed point is the robust stationary point).

The offset gauge (``d_i + c, o_j - c`` with both kinds) is the null vector v of ``A^T W A``;
it is handled analytically: ``A^T W A + alpha v v^T`` is positive definite on a connected
observation graph and equals the pseudo-inverse on right-hand sides orthogonal to v (all of
them here, ``v^T A^T = 0``), and the shift is set so that ``sum d - sum o`` keeps its
starting value, the convention of the dense engine (which projects the shift off each step).
Offsets "none" have nothing to project and run :func:`selfcal.toa.dense_lm.solve_dense_lm`;
so do partial refits (a ``free`` mask), where the fixed nodes already hold the frame.

References
----------
Golub, G. H. & Pereyra, V. (1973). The differentiation of pseudo-inverses and nonlinear least
squares problems whose variables separate. SIAM J. Numer. Anal. 10(2), 413-432.
Kaufman, L. (1975). A variable projection method for solving separable nonlinear least
squares problems. BIT 15, 49-57.
Hong, J. H., Zach, C. & Fitzgibbon, A. (2017). Revisiting the variable projection method for
separable nonlinear least squares problems. CVPR, 5939-5947.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray
from scipy.linalg import lapack

from ..robust import loss_rho
from .dense_lm import FTOL, TRIALS, GaugeProjector, _solve, damping_after_success, solve_dense_lm

Array = NDArray[np.float64]

__all__ = ["solve_varpro_lm"]


def solve_varpro_lm(
    theta0: Array, y: Array, ii: NDArray[np.intp], jj: NDArray[np.intp], I: int, J: int, d: int,
    offsets: str, loss: str, f_scale: float, max_nfev: int | None, xtol: float,
    free: NDArray[np.bool_] | None = None, max_it: int = 100,
) -> tuple[Array, bool, int]:
    """Levenberg-Marquardt on the positions with the offsets projected out (variable projection).

    Same call and return as :func:`selfcal.toa.dense_lm.solve_dense_lm`.

    Parameters
    ----------
    theta0 : (n,) start, receiver-major ``[r (I d), s (J d), d_i (I)?, o_j (J)?]`` (metres);
        its offsets only set the first IRLS weights (robust losses) and the offset gauge
        (``sum d - sum o``): the offsets are re-solved at the start's geometry.
    y : (m,) observed ranges (metres); ii, jj : (m,) their receiver and source indices.
    I, J, d, offsets : the model (:mod:`selfcal.toa.nls`).
    loss, f_scale : robust loss (:func:`selfcal.robust.loss_rho`) and its scale (metres).
    max_nfev : iteration cap (default ``max_it``); xtol : relative step tolerance.
    free : (n,) bool mask of fitted parameters; when given (a partial refit) or when the
        model has no offsets, the call is :func:`selfcal.toa.dense_lm.solve_dense_lm`'s.

    Returns
    -------
    (theta, converged, iterations): the point (offsets included, in the dense engine's
    gauge), whether a stopping rule was met, iterations (normal matrices formed).

    Notes
    -----
    Per iteration O(m n^2) for the normal matrix, O(p^3 + p^2 k) for eliminating the p
    offsets from it (k = (I + J) d positions) and O(k^3 / 3) per damping trial; each trial
    re-solves the offsets with the iteration's Cholesky factor (O(m + p^2)).

    Examples
    --------
    >>> import numpy as np
    >>> from selfcal.toa import nls
    >>> g = np.random.default_rng(0)
    >>> r, s = g.uniform(0, 1.5, (12, 3)), g.normal(0, 2, (6, 3))
    >>> Y = nls.toa_model(r, s, g.uniform(0, 3, 12), g.uniform(0, 30, 6))
    >>> ii, jj = np.nonzero(np.isfinite(Y))
    >>> th0 = nls._pack(r + 0.05, s - 0.05, np.zeros(12), np.zeros(6))
    >>> th, ok, nit = solve_varpro_lm(th0, Y[ii, jj], ii, jj, 12, 6, 3, "both", "linear", 1.0, None, 1e-12)
    >>> bool(ok) and float(np.abs(nls.toa_residuals(th, Y, 3, "both")).max()) < 1e-6
    True
    """
    has_r, has_s = offsets in ("receivers", "both"), offsets in ("sources", "both")
    if not (has_r or has_s) or (free is not None and not bool(np.all(free))):
        return solve_dense_lm(theta0, y, ii, jj, I, J, d, offsets, loss, f_scale, max_nfev, xtol,
                              free=free, max_it=max_it)
    both = has_r and has_s
    theta = np.array(theta0, dtype=float)
    n = theta.size
    N = I + J
    k = N * d
    p = n - k
    m = y.size
    ar = np.arange(m)
    Jf = np.zeros((m, n))
    rcol = ii[:, None] * d + np.arange(d)
    scol = I * d + jj[:, None] * d + np.arange(d)
    i_off, j_off = k, k + (I if has_r else 0)
    if has_r:
        Jf[ar, i_off + ii] = 1.0
    if has_s:
        Jf[ar, j_off + jj] = 1.0
    linear = loss == "linear"
    sj = I + jj
    ones = np.ones(m)
    # the offset gauge: v = (1_I, -1_J) spans the null space of A^T W A with both kinds
    v = np.concatenate([np.ones(I), -np.ones(J)]) if both else None
    shift0 = float(v @ theta[k:]) if v is not None else 0.0
    cell = ii * J + jj
    fixed_fac: list[Array | None] = []  # the linear loss' weights never change: one factor

    def geometry(t: Array) -> tuple[Array, Array]:
        P = t[:k].reshape(N, d)
        u = P[ii] - P[sj]
        dist = np.sqrt(np.einsum("mp,mp->m", u, u))
        u *= np.divide(1.0, dist, out=np.zeros_like(dist), where=dist > 0)[:, None]
        return dist, u

    def weights(f: Array) -> tuple[float, Array]:
        if linear:
            return 0.5 * float(f @ f), ones
        rho, w = loss_rho((f / f_scale) ** 2, loss)
        return 0.5 * f_scale**2 * float(np.sum(rho)), np.asarray(w, float)

    def offsets_at(dist: Array, w: Array, factor: Array) -> Array:
        """The weighted least-squares offsets for residual ``dist - y`` (gauge: ``v^T z = shift0``)."""
        wr = w * (y - dist)
        parts = []
        if has_r:
            parts.append(np.bincount(ii, wr, I))
        if has_s:
            parts.append(np.bincount(jj, wr, J))
        z, info = lapack.dpotrs(factor, np.concatenate(parts), lower=1)
        if v is not None:
            z = z + ((shift0 - float(v @ z)) / (I + J)) * v
        return np.asarray(z, float)

    def residual(dist: Array, z: Array) -> Array:
        f = dist - y
        if has_r:
            f = f + z[ii]
        if has_s:
            f = f + z[(I if has_r else 0) + jj]
        return f

    def offset_factor(w: Array) -> Array | None:
        """Cholesky factor of ``A^T W A (+ alpha v v^T)`` (lower), None if not positive definite."""
        if linear and fixed_fac:
            return fixed_fac[0]
        blocks = np.zeros((p, p))
        if has_r:
            blocks[np.arange(I), np.arange(I)] = np.bincount(ii, w, I)
        if has_s:
            o = I if has_r else 0
            blocks[o + np.arange(J), o + np.arange(J)] = np.bincount(jj, w, J)
        if both:
            Wm = np.bincount(cell, w, I * J).reshape(I, J)
            blocks[:I, I:] = Wm
            blocks[I:, :I] = Wm.T
            alpha = float(np.trace(blocks)) / p
            blocks += (alpha / (I + J)) * np.outer(v, v)
        c, info = lapack.dpotrf(blocks, lower=1, clean=1)
        out = c if info == 0 else None
        if linear:
            fixed_fac.append(out)
        return out

    # the start: offsets re-solved at the start's geometry (weights at the start's residuals)
    dist, u = geometry(theta)
    cost, w = weights(residual(dist, theta[k:]))
    fac = offset_factor(w)
    if fac is None:  # offsets not determined (a disconnected observation graph): the full LM
        return solve_dense_lm(theta0, y, ii, jj, I, J, d, offsets, loss, f_scale, max_nfev, xtol, max_it=max_it)
    z = offsets_at(dist, w, fac)
    f = residual(dist, z)
    c_new, w_new = weights(f)
    if c_new <= cost or not np.isfinite(cost):
        theta[k:] = z
        cost, w = c_new, w_new
    else:  # robust weights: keep the start's offsets when the re-solve does not lower the cost
        f = residual(dist, theta[k:])
    lam = 1e-4
    nu = 2.0
    converged = False
    it = 0
    cap = max_nfev or max_it
    Jflat = Jf.reshape(-1)
    pos_r = (ar[:, None] * n + rcol).ravel()
    pos_s = (ar[:, None] * n + scol).ravel()
    dstep = np.arange(k) * (k + 1)
    while it < cap:
        it += 1
        uf = u.ravel()
        Jflat[pos_r] = uf
        Jflat[pos_s] = -uf
        if linear:
            H = np.dot(Jf.T, Jf)
            g = np.dot(Jf.T, f)
        else:
            Jw = Jf * w[:, None]
            H = np.dot(Jf.T, Jw)
            g = np.dot(Jw.T, f)
        fac = offset_factor(w)
        if fac is None:
            break
        # Schur complement of the offset block: the reduced (variable projection) system
        rhs = np.concatenate([H[k:, :k], g[k:, None]], axis=1)
        X, info = lapack.dpotrs(fac, rhs, lower=1)
        Hr = H[:k, :k] - H[:k, k:] @ X[:, :k]
        gr = g[:k] - H[:k, k:] @ X[:, k]
        hdiag = Hr.ravel()[dstep].copy()
        proj = GaugeProjector(theta, N, d, I, False)
        gnorm = math.sqrt(float(gr @ gr))
        tnorm = math.sqrt(float(theta @ theta))
        mg = -gr
        improved = False
        for _ in range(TRIALS):
            Hd = Hr.copy()
            Hd.ravel()[dstep] += lam * hdiag
            x = _solve(Hd, mg)
            if x is None:
                lam, nu = lam * nu, 2.0 * nu
                continue
            dx = np.zeros(n)
            dx[:k] = x
            proj.apply(dx[:k])
            xv = dx[:k].copy()
            trial = theta.copy()
            trial[:k] += xv
            dist2, u2 = geometry(trial)
            z2 = offsets_at(dist2, w, fac)
            trial[k:] = z2
            f2 = residual(dist2, z2)
            c2, w2 = weights(f2)
            if c2 <= cost:
                dx[k:] = z2 - theta[k:]
                small = math.sqrt(float(dx @ dx)) <= xtol * (xtol + tnorm)
                rel = (cost - c2) <= FTOL * max(cost, 1e-300)
                lam = damping_after_success(lam, cost - c2, -(float(gr @ xv) + 0.5 * float(xv @ (Hr @ xv))))
                nu = 2.0
                theta, cost, f, w, u = trial, c2, f2, w2, u2
                improved = True
                converged = bool(small or rel)
                break
            lam, nu = lam * nu, 2.0 * nu
        if not improved:
            converged = gnorm <= 1e-6 * max(1.0, math.sqrt(2 * cost))
            break
        if converged:
            break
    return theta, converged, it
