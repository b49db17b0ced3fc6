"""The bipartite range model, shared by every TOA engine (paper 003 sec. IV, 004 sec. 3).

Entry (i, j) of an I x J range matrix (metres, NaN = missing)::

    y_ij = |r_i - s_j| + d_i + o_j + e_ij

with optional per-receiver offsets ``d_i`` and per-source offsets ``o_j`` (``offsets`` in
:data:`OFFSET_MODES`). This module holds what every refinement, covariance and verdict
of :mod:`selfcal.toa` reads: the receiver-major parameter vector (:func:`_pack` /
:func:`_unpack`), the model (:func:`toa_model`), residuals and analytic Jacobian
(:func:`toa_residuals`, :func:`toa_jacobian`, 003 eq. 16), the gauge (:func:`gauge_basis`, and its projector :class:`GaugeProjector`),
the kept / eliminated layout of the Schur complement (:class:`_Layout`,
:func:`_make_layout`), the robust-loss helpers and the refinement's result record
(:class:`NlsSolution`).

It imports nothing else from :mod:`selfcal.toa`, so the engines (:mod:`.nls`,
:mod:`.constrained`, :mod:`.schur_affine`, :mod:`.covariance`, ...) import it without a
circle. :mod:`selfcal.toa.engine.nls` re-exports these names (their historical home).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import scipy.linalg
import scipy.sparse
from numpy.typing import NDArray

from ...errors import DegenerateGeometryError
from ...geometry import canonical_gauge
from ...robust import TUNING, loss_rho, mad_std

__all__ = ["OFFSET_MODES", "GaugeProjector", "NlsSolution", "gauge_basis", "least_squares_offsets", "toa_jacobian", "toa_model",
           "toa_residuals"]

Array = NDArray[np.float64]

OFFSET_MODES = ("none", "receivers", "sources", "both")


@dataclass(frozen=True)
class NlsSolution:
    """Result of :func:`refine_toa` (all lengths in metres).

    Attributes
    ----------
    receivers, sources: (I, d), (J, d) estimated positions in the canonical gauge
        (:func:`selfcal.geometry.canonical_gauge`: receiver centroid at 0, principal axes).
    receiver_offsets, source_offsets: (I,), (J,) or None. With both kinds the first
        source offset is 0 (the common shift is moved into the receiver offsets).
    receiver_cov, source_cov: (I, d, d), (J, d, d) gauge-free covariances
        ``sigma^2 (J^T J)^+`` (003 eq. 17), in the output frame.
    receiver_offset_std, source_offset_std: (I,), (J,) or None, standard deviations
        of the offsets in the minimum-norm gauge.
    residuals: (I, J) measured minus modelled range, NaN where missing.
    residual_rms: root mean square of the observed residuals.
    sigma: estimated range noise std ``sqrt(RSS / (m - n + g))`` (m residuals,
        n unknowns, g gauge freedoms); for robust losses the normal-consistent MAD of the
        residuals times sqrt(m / (m - n + g)).
    converged, iterations, cost: solver status, iterations (Jacobian evaluations)
        and the final cost ``0.5 sum rho(f^2)``.
    solver: "trf" (scipy least_squares) or "schur-lm".
    """

    receivers: Array
    sources: Array
    receiver_offsets: Array | None
    source_offsets: Array | None
    receiver_cov: Array
    source_cov: Array
    receiver_offset_std: Array | None
    source_offset_std: Array | None
    residuals: Array
    residual_rms: float
    sigma: float
    converged: bool
    iterations: int
    cost: float
    solver: str = "trf"


# ---------------------------------------------------------------------------
# model, residuals, Jacobian (receiver-major parameter vector)
# ---------------------------------------------------------------------------


def _flags(offsets: str) -> tuple[bool, bool]:
    return offsets in ("receivers", "both"), offsets in ("sources", "both")


def _unpack(
    theta: Array, I: int, J: int, d: int, offsets: str
) -> tuple[Array, Array, Array | None, Array | None]:
    """Split the parameter vector ``[r (I d), s (J d), d_i (I)?, o_j (J)?]``."""
    has_r, has_s = _flags(offsets)
    r = theta[: I * d].reshape(I, d)
    s = theta[I * d : (I + J) * d].reshape(J, d)
    k = (I + J) * d
    dr = theta[k : k + I] if has_r else None
    k += I if has_r else 0
    os_ = theta[k : k + J] if has_s else None
    return r, s, dr, os_


def _pack(r: Array, s: Array, dr: Array | None, os_: Array | None) -> Array:
    parts = [np.ravel(r), np.ravel(s)]
    if dr is not None:
        parts.append(np.ravel(dr))
    if os_ is not None:
        parts.append(np.ravel(os_))
    return np.concatenate(parts).astype(float)


def toa_model(
    receivers: Array,
    sources: Array,
    receiver_offsets: Array | None = None,
    source_offsets: Array | None = None,
) -> Array:
    """Modelled range matrix ``|r_i - s_j| + d_i + o_j`` (004 sec. 3 in metres), shape (I, J)."""
    r = np.asarray(receivers, float)
    s = np.asarray(sources, float)
    # component by component: no (I, J, d) temporary
    D = np.zeros((r.shape[0], s.shape[0]))
    for p in range(r.shape[1]):
        t = np.subtract.outer(r[:, p], s[:, p])
        t *= t
        D += t
    np.sqrt(D, out=D)
    if receiver_offsets is not None:
        D = D + np.asarray(receiver_offsets, float)[:, None]
    if source_offsets is not None:
        D = D + np.asarray(source_offsets, float)[None, :]
    return D


def least_squares_offsets(Y: Array, r: Array, s: Array, offsets: str) -> tuple[Array | None, Array | None]:
    """Offsets that best fit ``Y - |r_i - s_j|`` for a given geometry (two-way means)."""
    has_r, has_s = offsets in ("receivers", "both"), offsets in ("sources", "both")
    if not (has_r or has_s):
        return None, None
    E = np.where(np.isfinite(Y), Y - toa_model(r, s), np.nan)
    obs = np.isfinite(E)
    Z = np.where(obs, E, 0.0)
    n_r = np.maximum(obs.sum(axis=1), 1)
    n_c = np.maximum(obs.sum(axis=0), 1)
    a = np.zeros(Y.shape[0])
    b = np.zeros(Y.shape[1])
    if has_r and has_s and obs.all():
        # complete two-way table: the closed form of the alternation's limit below
        a = Z.mean(axis=1)
        b = Z.mean(axis=0) - a.mean()
        return a, b
    for _ in range(100 if has_r and has_s else 1):
        if has_r:
            a = ((Z - b[None, :]) * obs).sum(axis=1) / n_r
        if has_s:
            b = ((Z - a[:, None]) * obs).sum(axis=0) / n_c
    return (a if has_r else None), (b if has_s else None)


def toa_residuals(theta: Array, ranges: Array, dim: int, offsets: str = "none") -> Array:
    """Vector of ``model - measured`` over the observed entries (row-major order), shape (m,).

    ``theta`` is the receiver-major parameter vector ``[r.ravel(), s.ravel(), d?, o?]``.
    """
    I, J = ranges.shape
    r, s, dr, os_ = _unpack(np.asarray(theta, float), I, J, dim, offsets)
    obs = np.isfinite(ranges)
    return (toa_model(r, s, dr, os_) - ranges)[obs]


def toa_jacobian(theta: Array, ranges: Array, dim: int, offsets: str = "none") -> scipy.sparse.csr_matrix:
    """Analytic sparse Jacobian of :func:`toa_residuals` (003 eq. 16 with the sign of model - data).

    Row of entry (i, j): ``u_ij`` at r_i, ``-u_ij`` at s_j, 1 at d_i and o_j, where
    ``u_ij = (r_i - s_j) / |r_i - s_j|`` (zero when the points coincide, where the
    range is not differentiable). Shape (m, n) CSR, 2d (+1, +2) non-zeros per row.
    """
    I, J = ranges.shape
    theta = np.asarray(theta, float)
    r, s, _, _ = _unpack(theta, I, J, dim, offsets)
    ii, jj = np.nonzero(np.isfinite(ranges))
    diff = r[ii] - s[jj]
    nrm = np.linalg.norm(diff, axis=1)
    u = np.divide(diff, nrm[:, None], out=np.zeros_like(diff), where=nrm[:, None] > 0)
    has_r, has_s = _flags(offsets)
    cols = [ii[:, None] * dim + np.arange(dim), I * dim + jj[:, None] * dim + np.arange(dim)]
    vals = [u, -u]
    k = (I + J) * dim
    if has_r:
        cols.append((k + ii)[:, None])
        vals.append(np.ones((len(ii), 1)))
        k += I
    if has_s:
        cols.append((k + jj)[:, None])
        vals.append(np.ones((len(ii), 1)))
    C = np.hstack(cols)
    V = np.hstack(vals)
    m, per = C.shape
    return scipy.sparse.csr_matrix(
        (V.ravel(), C.ravel(), np.arange(0, m * per + 1, per)), shape=(m, theta.size)
    )


def gauge_basis(
    receivers: Array, sources: Array, offsets: str = "none"
) -> Array:
    """Orthonormal basis of the gauge null space of ``J^T J``, shape (n, g).

    Columns span the infinitesimal translations (d), rotations (d(d-1)/2) of all
    points and, with both kinds of offsets, the common shift ``d_i + c, o_j - c``.
    Receiver-major parameter order as in :func:`toa_residuals`.
    """
    r = np.asarray(receivers, float)
    s = np.asarray(sources, float)
    I, d = r.shape
    J = s.shape[0]
    has_r, has_s = _flags(offsets)
    P = np.vstack([r, s])
    P = P - P.mean(axis=0)
    cols = []
    for a in range(d):
        v = np.zeros_like(P)
        v[:, a] = 1.0
        cols.append(_pack(v[:I], v[I:], np.zeros(I) if has_r else None, np.zeros(J) if has_s else None))
    gens = []
    if d == 2:
        gens.append(np.array([[0.0, -1.0], [1.0, 0.0]]))
    else:
        for a, b in ((0, 1), (0, 2), (1, 2)):
            G = np.zeros((3, 3))
            G[a, b], G[b, a] = -1.0, 1.0
            gens.append(G)
    for G in gens:
        v = P @ G.T
        cols.append(_pack(v[:I], v[I:], np.zeros(I) if has_r else None, np.zeros(J) if has_s else None))
    if offsets == "both":
        cols.append(_pack(np.zeros_like(r), np.zeros_like(s), np.ones(I), -np.ones(J)))
    Q, _ = np.linalg.qr(np.column_stack(cols))
    return Q


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


def _solution(theta: Array, Y: Array, d: int, offsets: str, Cr: Array, Cs: Array, *, canonical: bool,
              shift: bool, **fields: object) -> NlsSolution:
    """The :class:`NlsSolution` of a fit ending at ``theta``: its residuals and their rms, the
    positions in the canonical gauge (``canonical``; else in the frame of the fit) with the
    covariance blocks ``Cr`` (I, d + hasR, d + hasR), ``Cs`` rotated along, the offsets' standard
    deviations, and (``shift``, with both offset kinds) the common shift moved into the receiver
    offsets so that the first source offset is 0; ``fields`` the rest (sigma, cost, status)."""
    I, J = Y.shape
    has_r, has_s = _flags(offsets)
    r, s, dr, os_ = _unpack(theta, I, J, d, offsets)
    obs = np.isfinite(Y)
    resid = np.where(obs, Y - toa_model(r, s, dr, os_), np.nan)
    if canonical:
        rc, sc, al = canonical_gauge(r, s)
        assert sc is not None
        R = al.rotation
    else:
        rc, sc, R = r.copy(), s.copy(), np.eye(d)
    if shift and offsets == "both":
        assert dr is not None and os_ is not None
        dr, os_ = dr + os_[0], os_ - os_[0]
    return NlsSolution(
        receivers=rc, sources=sc,
        receiver_offsets=None if dr is None else np.array(dr),
        source_offsets=None if os_ is None else np.array(os_),
        receiver_cov=np.einsum("ab,nbc,dc->nad", R, Cr[:, :d, :d], R),
        source_cov=np.einsum("ab,nbc,dc->nad", R, Cs[:, :d, :d], R),
        receiver_offset_std=np.sqrt(np.maximum(Cr[:, d, d], 0.0)) if has_r else None,
        source_offset_std=np.sqrt(np.maximum(Cs[:, d, d], 0.0)) if has_s else None,
        residuals=resid, residual_rms=float(np.sqrt(np.mean(resid[obs] ** 2))), **fields)  # type: ignore[arg-type]


def _check_counts(counts_r: NDArray[np.intp], counts_s: NDArray[np.intp], need_r: object, need_s: object) -> None:
    """Each node needs at least as many observed ranges as it has unknowns of its own (its free
    coordinates, its own offset): ``need_r`` / ``need_s`` an int or one per node."""
    for kind, cnt, need in (("receiver", counts_r, need_r), ("source", counts_s, need_s)):
        nd = np.broadcast_to(np.asarray(need), cnt.shape)
        bad = np.flatnonzero(cnt < nd)
        if bad.size:
            k = int(bad[0])
            raise DegenerateGeometryError(
                f"{kind} {k} has {int(cnt[k])} observed ranges but needs at least {int(nd[k])} (its unknowns of "
                "its own); drop it, fix some of its coordinates or add measurements", kind="unobservable-node")


# ---------------------------------------------------------------------------
# internal "kept / eliminated" layout for the Schur complement
# ---------------------------------------------------------------------------


@dataclass(frozen=True)
class _Layout:
    """Index bookkeeping: K = node set kept in the reduced system, E = eliminated one."""

    I: int
    J: int
    d: int
    offsets: str
    k_is_receivers: bool
    k_idx: NDArray[np.intp]  # (nK, mK) parameter indices of each kept node
    e_idx: NDArray[np.intp]  # (nE, mE)
    pins: NDArray[np.intp]  # pinned parameter indices (all on the K side)
    n: int


def _node_indices(I: int, J: int, d: int, offsets: str) -> tuple[NDArray[np.intp], NDArray[np.intp], int]:
    has_r, has_s = _flags(offsets)
    r_idx = np.arange(I * d).reshape(I, d)
    s_idx = I * d + np.arange(J * d).reshape(J, d)
    k = (I + J) * d
    if has_r:
        r_idx = np.hstack([r_idx, (k + np.arange(I))[:, None]])
        k += I
    if has_s:
        s_idx = np.hstack([s_idx, (k + np.arange(J))[:, None]])
        k += J
    return r_idx, s_idx, k


def _make_layout(r: Array, s: Array, offsets: str) -> _Layout:
    I, d = r.shape
    J = s.shape[0]
    r_idx, s_idx, n = _node_indices(I, J, d, offsets)
    k_is_r = I <= J
    k_idx, e_idx = (r_idx, s_idx) if k_is_r else (s_idx, r_idx)
    Q = gauge_basis(r, s, offsets)
    cand = k_idx.ravel()
    g = Q.shape[1]
    # the g rows of the gauge basis that are best conditioned: pinning them removes the gauge
    _, R, piv = scipy.linalg.qr(Q[cand].T, pivoting=True, mode="economic")
    diag = np.abs(np.diag(R))
    if diag.size < g or diag[g - 1] < 1e-6 * max(diag[0], 1e-300):
        raise DegenerateGeometryError(
            "the points are (nearly) collinear or coincident: the rigid-motion gauge cannot be fixed; "
            "receivers and sources together must span the space",
            kind="degenerate-geometry",
        )
    pins = np.sort(cand[piv[:g]])
    return _Layout(I, J, d, offsets, k_is_r, k_idx, e_idx, pins, n)


def _pinned_positions(lay: _Layout) -> NDArray[np.intp]:
    """Positions (in K-node-major order) of the pinned K coordinates."""
    return np.nonzero(np.isin(lay.k_idx.ravel(), lay.pins))[0]


# ---------------------------------------------------------------------------
# robust losses (rho(z), rho'(z) of z = (f / f_scale)^2, as in scipy.optimize.least_squares)
# ---------------------------------------------------------------------------


_rho = loss_rho  # the one robust-loss table (selfcal.robust)
_TUNING = TUNING  # 95 % Gaussian efficiency scales (selfcal.robust)


def _robust_sigma(f: Array) -> float:
    """Normal-consistent MAD of residuals (robust noise std), metres."""
    if f.size == 0:
        return 0.0
    return float(mad_std(f))
