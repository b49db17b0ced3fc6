"""Building blocks shared by the 003 initialisers (:mod:`selfcal.toa.init.mds`).

- :func:`classical_mds`: 003 Algorithm 1 (eq. 7-9), double centring + truncated
  eigendecomposition.
- :func:`estimate_receiver_distances`: 003 eq. 11, receiver-receiver distances from the
  reverse triangle inequality; :func:`complete_distances` fills what it leaves missing.
- :func:`multilaterate`: vectorised linear multilateration of points from ranges to anchors.
- :func:`range_residual_rms`: the score by which the initialisers' candidates are ranked.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from ..._checks import as_matrix, check_dim
from ...errors import DegenerateGeometryError, InputError

__all__ = ["classical_mds", "complete_distances", "estimate_receiver_distances", "multilaterate",
           "range_residual_rms"]

Array = NDArray[np.float64]


# ---------------------------------------------------------------------------------------
# Algorithm 1
# ---------------------------------------------------------------------------------------


def _double_centre(sq: Array) -> Array:
    """``-1/2 J_n sq J_m`` with ``J_n = I - 11^T/n`` (003 eq. 7): the one double centring.

    For (..., n, m) stacks of (square or rectangular) squared-distance matrices.
    """
    row = sq.mean(axis=-1, keepdims=True)
    col = sq.mean(axis=-2, keepdims=True)
    return -0.5 * (sq - row - col + sq.mean(axis=(-1, -2), keepdims=True))


#: from this size on, the top eigenpairs alone (LAPACK ``syevr`` on a subset, one matrix at a
#: time) are cheaper than every eigenpair of the whole stack at once (``numpy.linalg.eigh``):
#: measured single-threaded, 30 x 31 x 31: 2.5 vs 2.3 ms; 120 x 121 x 121 (Algorithm 2 at 120
#: units): 99 vs 39 ms; 16 x 17 x 17: 0.4 vs 0.5 ms
SUBSET_EIG_MIN = 32


def _top_eig_coords(B: Array, dim: int) -> Array:
    """Coordinates ``U_r Sigma_r^{1/2}`` from the top-``dim`` eigenpairs of symmetric ``B``.

    Works on a stack (..., n, n). Negative eigenvalues (non-Euclidean noise) are clipped to 0,
    which is the best PSD rank-``dim`` approximation (003 eq. 8). From
    :data:`SUBSET_EIG_MIN` rows on only the top ``dim`` eigenpairs are computed.
    """
    S = 0.5 * (B + np.swapaxes(B, -1, -2))
    n = S.shape[-1]
    if n >= SUBSET_EIG_MIN and dim < n and np.isfinite(S).all():
        import scipy.linalg

        flat = S.reshape(-1, n, n)
        w = np.empty((flat.shape[0], dim))
        V = np.empty((flat.shape[0], n, dim))
        for k in range(flat.shape[0]):
            w[k], V[k] = scipy.linalg.eigh(flat[k], subset_by_index=[n - dim, n - 1], driver="evr",
                                           check_finite=False)
        w = w.reshape(S.shape[:-2] + (dim,))[..., ::-1]
        V = V.reshape(S.shape[:-2] + (n, dim))[..., :, ::-1]
    else:
        w, V = np.linalg.eigh(S)
        w = w[..., ::-1][..., :dim]
        V = V[..., :, ::-1][..., :, :dim]
    return V * np.sqrt(np.maximum(w, 0.0))[..., None, :]


def classical_mds(distances: Array, dim: int) -> Array:
    """Classical multidimensional scaling, 003 Algorithm 1 (eq. 7-9).

    Parameters
    ----------
    distances:
        (n, n) symmetric matrix of Euclidean distances (metres), zero diagonal, no NaN.
    dim:
        Embedding dimension ``r`` (2 or 3).

    Returns
    -------
    (n, dim) coordinates, centred at the origin, defined up to an orthogonal transform.
    The 003 text writes ``s_MDS = Sigma_r^{1/2} U_r^T`` (points as columns); we return its
    transpose, one point per row. The truncated SVD of eq. 8 is taken as the symmetric
    eigendecomposition (the same thing for a PSD matrix, and well defined when noise makes
    ``B`` indefinite).
    """
    dim = check_dim(dim)
    D = as_matrix(distances, "distances", allow_nan=False, nonnegative=True)
    n = D.shape[0]
    if D.shape[1] != n:
        raise InputError(f"distances: expected a square matrix, got shape {D.shape}")
    if n < dim + 1:
        raise DegenerateGeometryError(
            f"classical MDS of {n} points cannot give a {dim}-D configuration; need at least {dim + 1}",
            kind="too-few-points",
        )
    D = 0.5 * (D + D.T)
    return _top_eig_coords(_double_centre(D**2), dim)


# ---------------------------------------------------------------------------------------
# eq. 11 and distance completion
# ---------------------------------------------------------------------------------------


def estimate_receiver_distances(ranges: Array, *, block_elements: int = 4_000_000) -> Array:
    """Receiver-receiver distances by the reverse triangle inequality, 003 eq. 11.

    ``d_ij = max_k |y_ik - y_jk|`` over the transmitters ``k`` observed by both receivers
    (eq. 10 makes every term a lower bound of ``|r_i - r_j|``; equality when a transmitter
    lies on the line through the pair, outside the segment).

    Parameters
    ----------
    ranges:
        (I, J) ranges in metres, rows = receivers, NaN = missing.
    block_elements:
        Memory cap for the vectorised (block, I, J) difference tensor.

    Returns
    -------
    (I, I) symmetric matrix, zero diagonal; NaN where a pair shares no transmitter.
    """
    Y = as_matrix(ranges, "ranges")
    I, J = Y.shape
    out = np.empty((I, I))
    block = max(1, int(block_elements // max(1, I * J)))
    for a in range(0, I, block):
        diff = np.abs(Y[a : a + block, None, :] - Y[None, :, :])
        # all-NaN rows of a pair are expected (no shared transmitter): silence nanmax warnings
        diff = np.where(np.isnan(diff), -np.inf, diff)
        m = diff.max(axis=2)
        out[a : a + block] = np.where(np.isneginf(m), np.nan, m)
    out = np.fmax(out, out.T)
    np.fill_diagonal(out, 0.0)
    return out


def complete_distances(distances: Array) -> Array:
    """Fill NaN entries of a distance matrix with shortest-path lengths (triangle bound).

    The sum of known distances along a path is an upper bound of the missing distance
    (the MDS-MAP completion). Raises :class:`DegenerateGeometryError` if the graph of known
    distances is disconnected, since the relative placement of the parts is then undetermined.
    """
    from scipy.sparse.csgraph import connected_components, shortest_path

    D = np.array(distances, dtype=float)
    missing = np.isnan(D)
    if not missing.any():
        return D
    W = np.where(missing, 0.0, D)
    # csgraph treats 0 as "no edge": keep genuine zero distances as tiny positive weights
    W = np.where(~missing & (W <= 0), 1e-12, W)
    np.fill_diagonal(W, 0.0)
    ncomp, _ = connected_components(W, directed=False)
    if ncomp > 1:
        raise DegenerateGeometryError(
            f"the receivers split into {ncomp} groups that share no transmitter; their relative "
            "placement is undetermined (add transmitters heard by both groups)",
            kind="disconnected",
        )
    P = shortest_path(W, method="D", directed=False)
    return np.where(missing, P, D)


# ---------------------------------------------------------------------------------------
# linear multilateration (vectorised)
# ---------------------------------------------------------------------------------------


def multilaterate(anchors: Array, ranges: Array, *, ridge: float = 1e-9) -> Array:
    """Linear least-squares multilateration of many points at once.

    For a point ``x`` and anchors ``p_i`` with ranges ``y_i``:
    ``|x|^2 - 2 p_i^T x = y_i^2 - |p_i|^2`` is linear in ``(x, |x|^2)`` (the auxiliary
    unknown is treated as free). Solved per point over its observed anchors through
    batched (d+1) x (d+1) normal equations.

    Parameters
    ----------
    anchors: (n, d) known positions (metres).
    ranges: (m, n) ranges from each of the m points to the anchors, NaN = missing.
    ridge: relative Tikhonov term so that points with fewer than d+1 observations get the
        least-norm solution instead of a singular solve.

    Returns
    -------
    (m, d) positions.
    """
    P = np.asarray(anchors, float)
    Yr = np.asarray(ranges, float)
    n, d = P.shape
    if Yr.ndim != 2 or Yr.shape[1] != n:
        raise InputError(f"multilaterate: ranges must be (m, {n}), got {Yr.shape}")
    centre = P.mean(axis=0)
    Pc = P - centre  # conditioning: the auxiliary |x|^2 is smaller near the anchors' centroid
    M = ~np.isnan(Yr)
    A = np.hstack([-2.0 * Pc, np.ones((n, 1))])  # (n, d+1)
    b = np.where(M, Yr, 0.0) ** 2 - (Pc**2).sum(axis=1)[None, :]  # (m, n)
    Mf = M.astype(float)
    # batched normal equations as two BLAS products (einsum over m x n x (d+1)^2 is slow)
    N = (Mf @ (A[:, :, None] * A[:, None, :]).reshape(n, -1)).reshape(-1, d + 1, d + 1)
    rhs = (Mf * b) @ A
    scale = np.trace(N, axis1=1, axis2=2)[:, None, None] / (d + 1)
    N = N + ridge * np.maximum(scale, 1e-12) * np.eye(d + 1)
    z = np.linalg.solve(N, rhs[..., None])[..., 0]
    return z[:, :d] + centre


def range_residual_rms(ranges: Array, receivers: Array, sources: Array) -> float:
    """RMS of ``y_ij - |r_i - s_j|`` over the observed entries (metres); inf if not finite."""
    Y = np.asarray(ranges, float)
    r = np.asarray(receivers, float)
    s = np.asarray(sources, float)
    if not (np.isfinite(r).all() and np.isfinite(s).all()):
        return float("inf")
    D = np.sqrt(np.maximum(((r[:, None, :] - s[None, :, :]) ** 2).sum(-1), 0.0))
    res = (Y - D)[~np.isnan(Y)]
    return float(np.sqrt(np.mean(res**2)))


def _validated_ranges(ranges: Array, dim: int) -> Array:
    Y = as_matrix(ranges, "ranges", nonnegative=True, min_shape=(dim + 1, dim + 1))
    return Y
