"""The joint dense Levenberg-Marquardt of small range problems (positions and offsets damped together), with the gauge projected analytically.

The same iteration as the "dense" step of :func:`selfcal.toa.engine.schur_lm.solve_schur_lm`
(Marquardt diagonal damping ``(J^T W J + lam diag(J^T W J)) dx = -J^T W f``, the step
projected off the gauge, a damping trial accepted when the cost does not rise, the damping
updated by Nielsen's gain-ratio rule :func:`damping_after_success`, the same stopping rules), written for problems small enough that the per-iteration cost is
Python overhead, not arithmetic (12 receivers x 6 sources with both offsets: 72 ranges,
66 unknowns). What makes it cheaper than the general engine:

- the parameters stay in the receiver-major order of :mod:`selfcal.toa.engine.nls` (no split into
  kept / eliminated node sets and back); the Jacobian is one preallocated (m, n) array whose
  offset columns never change, so an iteration writes only the 2 d unit-vector columns;
- the gauge is projected without a QR per iteration: translations, rotations about the
  centroid and (with both offset kinds) the common shift ``d_i + c, o_j - c`` are mutually
  orthogonal, so the orthogonal projector off their span is "subtract the mean of each
  coordinate", "subtract the shift's component" and a d(d-1)/2-square Gram solve for the
  rotations (the same projector as ``I - Q Q^T`` with Q the orthonormal
  :func:`selfcal.toa.engine.nls.gauge_basis`, to round-off);
- each damped system is solved by one LAPACK ``posv`` call (Cholesky), least squares when
  it is not numerically positive definite;
- a mask of free parameters: the fixed ones keep their values and no gauge is projected
  (the fixed nodes hold the frame), which is the partial refit of the search's moves.

Cost per iteration O(m n^2) flops for ``J^T W J`` plus O(n^3 / 3) for the factorisation;
at 12 x 6 with both offsets 0.42-0.48 ms per iteration against 0.95-1.05 ms for the general
engine's dense step with its QR gauge basis and layout round trips (same run, same iterates,
a loaded 2-core machine); with the gain-ratio damping, 0.23 ms against 0.67 ms (same run,
six draws from perturbed truths, 1443 vs 1440 iterations). Stacking many starts into one
batched dense solve was tried and measured no faster (the stacked (n, n) products and LU
solves are flop-bound at n = 72); what pays is the bipartite block structure of the normal
equations, which :mod:`selfcal.toa.engine.batch_lm` uses to run the search's race (the same
iterates, start by start).
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from ...optim.lm import FTOL, Model, damping_after_success, levenberg_marquardt
from ...optim.steps import cholesky_solve as _solve

# FTOL (the relative cost decrease that stops) is read from this module at each call
# (tests/toa/test_varpro.py sets it to 0 for both dense engines)
from ...robust import loss_rho

Array = NDArray[np.float64]

__all__ = ["FTOL", "DenseStep", "GaugeProjector", "damping_after_success", "full_lm"]


def _rotation_generators(d: int) -> list[tuple[int, int]]:
    """(a, b) of the infinitesimal rotations ``x_a -> -x_b, x_b -> x_a`` (one in 2-D, three in 3-D)."""
    return [(0, 1)] if d == 2 else [(0, 1), (0, 2), (1, 2)]


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
    orthogonal; only the d(d-1)/2 rotation vectors need orthonormalising (Gram-Schmidt). ``apply`` gives ``(I - Q Q^T) dx`` with Q the orthonormal basis of
    :func:`selfcal.toa.engine.nls.gauge_basis`, to round-off.
    """

    def __init__(self, theta: Array, N: int, d: int, I: int, both: bool) -> None:
        self.N, self.d, self.I, self.both = N, d, I, both
        P = theta[: N * d].reshape(N, d)
        P = P - P.sum(axis=0) * (1.0 / N)
        rows: list[Array] = []
        big = 0.0
        for a, b in _rotation_generators(d):  # rotation a -> b: (-x_b, x_a) on coordinates (a, b)
            v2 = np.zeros((N, d))
            v2[:, a] = -P[:, b]
            v2[:, b] = P[:, a]
            v: Array = v2.ravel()
            big = max(big, math.sqrt(float(v @ v)))
            for q in rows:  # Gram-Schmidt (twice is enough for three vectors)
                v = v - float(q @ v) * q
            for q in rows:
                v = v - float(q @ v) * q
            nv = math.sqrt(float(v @ v))
            if nv > 1e-10 * big:  # a dependent rotation (points on a line) adds no direction
                rows.append(v / nv)
        self.Qr = np.array(rows).reshape(len(rows), N * d)

    def apply(self, dx: Array) -> Array:
        """``dx`` minus its projection on the gauge directions (in place); returns dx."""
        N, d = self.N, self.d
        X = dx[: N * d].reshape(N, d)
        X -= X.sum(axis=0) * (1.0 / N)
        flat = dx[: N * d]
        flat -= (self.Qr @ flat) @ self.Qr
        if self.both:
            off = dx[N * d:]
            shift = (off[: self.I].sum() - off[self.I:].sum()) / off.size
            off[: self.I] -= shift
            off[self.I:] += shift
        return dx


def full_lm(
    theta0: Array, y: Array, ii: NDArray[np.intp], jj: NDArray[np.intp], I: int, J: int, d: int,
    offsets: str, loss: str, f_scale: float, max_nfev: int | None, xtol: float,
    free: NDArray[np.bool_] | None = None, max_it: int = 100,
) -> tuple[Array, bool, int]:
    """The joint LM of :func:`solve_dense_lm` (positions and offsets damped together); same
    parameters (without ``varpro``) and return."""
    has_r, has_s = offsets in ("receivers", "both"), offsets in ("sources", "both")
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
    model = _DenseRanges(y, ii, jj, I, J, d, has_r, has_s, loss, f_scale, Jf, fidx, n, rcol, scol)
    out = levenberg_marquardt(model, theta, max_iter=max_nfev or max_it, xtol=xtol, ftol=FTOL)
    return out.x, out.converged, out.iterations


class _DenseRanges(Model):
    """The range model of :func:`full_lm` on the driver: residuals, IRLS weights and unit
    vectors per evaluation; the preallocated Jacobian's unit-vector columns rewritten per
    linearisation; the dense step (:class:`DenseStep`) with the gauge projected when every
    parameter is free."""

    def __init__(self, y: Array, ii: NDArray[np.intp], jj: NDArray[np.intp], I: int, J: int, d: int,
                 has_r: bool, has_s: bool, loss: str, f_scale: float, Jf: Array,
                 fidx: NDArray[np.intp] | None, n: int, rcol: NDArray[np.intp], scol: NDArray[np.intp]) -> None:
        N = I + J
        m = y.size
        ar = np.arange(m)
        self.y, self.ii, self.I, self.d, self.N = y, ii, I, d, N
        self.has_r, self.has_s, self.both = has_r, has_s, has_r and has_s
        self.loss, self.f_scale, self.linear = loss, f_scale, loss == "linear"
        self.Jf, self.fidx, self.n = Jf, fidx, n
        self.sj, self.ri, self.oj = I + jj, N * d + ii, N * d + (I if has_r else 0) + jj
        self.ones = np.ones(m)
        self.Jflat = Jf.reshape(-1)
        self.pos_r = (ar[:, None] * n + rcol).ravel()  # flat positions of the unit-vector entries
        self.pos_s = (ar[:, None] * n + scol).ravel()
        nf = n if fidx is None else fidx.size
        self.dstep = np.arange(nf) * (nf + 1)  # flat positions of the diagonal

    def evaluate(self, t: Array) -> tuple[float, tuple[Array, Array, Array]]:
        P = t[: self.N * self.d].reshape(self.N, self.d)
        u = P[self.ii] - P[self.sj]
        dist = np.sqrt(np.einsum("mp,mp->m", u, u))
        f = dist - self.y
        if self.has_r:
            f += t[self.ri]
        if self.has_s:
            f += t[self.oj]
        u *= np.divide(1.0, dist, out=np.zeros_like(dist), where=dist > 0)[:, None]  # 0 where points coincide
        if self.linear:
            return 0.5 * float(f @ f), (f, self.ones, u)
        rho, w = loss_rho((f / self.f_scale) ** 2, self.loss)
        return 0.5 * self.f_scale**2 * float(np.sum(rho)), (f, np.asarray(w, float), u)

    def linearize(self, theta: Array, state: tuple[Array, Array, Array]) -> DenseStep:
        f, w, u = state
        uf = u.ravel()
        self.Jflat[self.pos_r] = uf
        self.Jflat[self.pos_s] = -uf
        fidx = self.fidx
        Jm = self.Jf if fidx is None else self.Jf[:, fidx]
        if self.linear:
            H = np.dot(Jm.T, Jm)
            g = np.dot(Jm.T, f)
        else:
            Jw = Jm * w[:, None]
            H = np.dot(Jm.T, Jw)
            g = np.dot(Jw.T, f)
        proj = GaugeProjector(theta, self.N, self.d, self.I, self.both) if fidx is None else None
        return DenseStep(H, g, self.dstep, proj, fidx, self.n)


class DenseStep:
    """The dense step solver: ``(H + lam diag H) x = -g`` by Cholesky (least squares if H is not
    numerically positive definite), scattered into the free parameters and projected off the gauge.

    Parameters
    ----------
    H, g : (nf, nf), (nf,) the normal matrix and gradient on the free parameters.
    dstep : flat positions of H's diagonal; proj : :class:`GaugeProjector` or None;
    fidx : indices of the free parameters in the (n,) point (None: all).
    """

    def __init__(self, H: Array, g: Array, dstep: NDArray[np.intp], proj: GaugeProjector | None,
                 fidx: NDArray[np.intp] | None, n: int) -> None:
        self.H, self.g, self.dstep, self.proj, self.fidx, self.n = H, g, dstep, proj, fidx, n
        self.hdiag = H.ravel()[dstep]
        self.gnorm = math.sqrt(float(g @ g))
        self.mg = -g

    def step(self, lam: float) -> Array | None:
        Hd = self.H.copy()
        Hd.ravel()[self.dstep] += lam * self.hdiag  # Marquardt: diag * (1 + lam)
        x = _solve(Hd, self.mg)
        if x is None:
            return None
        if self.fidx is None:
            dx = x
        else:
            dx = np.zeros(self.n)
            dx[self.fidx] = x
        if self.proj is not None:
            self.proj.apply(dx)  # no rigid drift (and no common offset shift)
        return dx

    def predicted(self, dx: Array) -> float:
        xv = dx if self.fidx is None else dx[self.fidx]
        return -(float(self.g @ xv) + 0.5 * float(xv @ (self.H @ xv)))
