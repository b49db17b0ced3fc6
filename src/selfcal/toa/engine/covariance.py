"""Marginal covariance blocks of the TOA network from one factorization of the reduced system.

The weighted normal (Fisher) matrix of the bipartite range model (003 eq. 16-17,
:mod:`selfcal.toa.engine.nls`) is, with the nodes split into the *kept* set K (the smaller of
receivers / sources) and the *eliminated* set E::

    N = J^T W J = [[A, B], [B^T, D]],     A, D block-diagonal (m x m per node),

because every range touches one receiver and one source. The gauge (rigid motions and,
with both offset kinds, the common offset shift) is fixed by pinning g coordinates on the
K side (:func:`selfcal.toa.engine.model._make_layout`); pinned coordinates are decoupled (their
rows and columns of the reduced matrix replaced by the identity) instead of removed, so no
array is re-indexed. With ``F = B D^-1`` and the Schur complement ``S = A - B D^-1 B^T``
the pinned inverse ``C`` has the blocks

    C_KK = S^-1,        C_EE = D^-1 + F^T S^-1 F        (diagonal blocks only)

and the reported covariance is gauge-free, ``P C P`` with ``P`` the orthogonal projector
off the gauge directions ``Q`` (:func:`selfcal.toa.engine.nls.gauge_basis`), which is the
Moore-Penrose inverse ``N^+`` of 003 eq. 17 (any gauge-fixed inverse differs from ``N^+``
only along the gauge)::

    (P C P)_nn = C_nn - Q_n Y_n^T - Y_n Q_n^T + Q_n Z Q_n^T,   Y = C Q,  Z = Q^T C Q.

Selected inversion. Only the d x d (or (d+1) x (d+1) with offsets) diagonal blocks that are
asked for are formed: ``S = L L^T`` is factorised once (LAPACK ``potrf``); a requested E node
e costs one triangular solve ``X_e = L^-1 H_e`` with its m columns of ``H = B R``
(``D_e^-1 = R_e R_e^T``), its block is ``D_e^-1 + R_e X_e^T X_e R_e^T``; requested K nodes
take columns of ``L^-1`` (LAPACK ``trtri`` in place when more than a third of the K
coordinates are asked for, triangular solves with unit vectors otherwise). ``Y`` and ``Z``
need g solves with the same factor. No dense inverse of N (or of S) is ever formed.

Cost (n_K = m_K |K| reduced unknowns, n_E = m_E |E|, ``k_E`` requested E nodes, ``k_K``
requested K coordinates):

- building S: a symmetric rank-n_E update, ``O(n_K^2 n_E)`` time (BLAS ``syrk``), the
  Jacobian rows generated in column blocks of E nodes (a few tens of MB each);
- one Cholesky factorization: ``O(n_K^3 / 3)``;
- E blocks: ``O(n_K^2 m_E k_E)``; K blocks: ``O(n_K^3 / 3)`` (all) or ``O(n_K^2 k_K)``;
- gauge terms: ``O(n_K^2 g + n_K n_E g)``.

Memory: S (n_K^2 doubles) plus one column block of H and of the unit-vector components,
the weight matrix (the data's I x J) and the small per-node blocks; nothing of size
(I d) x (J d) is stored, nor the d I x J component arrays. The floor
of a dense network is therefore one dense factorization of the n_K x n_K reduced system
(9000 x 9000 at 3000 x 3000 in 3-D: 0.65 GB, ~2.4e11 flops) plus the rank-n_E update that
builds it (~7e11 flops). ``covariance="receivers"`` with receivers on the K side skips every
E solve; ``"none"`` skips everything. H is kept between the two passes when it fits in
256 MB (``_KEEP_H_DOUBLES``), rebuilt block by block above.

Why the exact blocks cost O(n^3) while the solve does not. The solve never forms S: each
conjugate-gradient step applies ``S x = A x - B D^-1 B^T x`` as two passes over the observed
pairs, O(nnz) (:mod:`selfcal.toa.engine.schur_lm`), and a well-conditioned network converges in a
few tens of such products: O(nnz x iterations) = O(n^2) for a dense I x J network. A
marginal block is a *column* of the inverse, ``C e_k``, and every column of ``S^-1`` is dense
when the bipartite graph is dense (every node is correlated with every other through the
sources they share and through the global gauge motions). Asking for all n of them is n
solves; by CG that is n x O(nnz x iterations) = O(n^3 x iterations); by one dense
factorization it is O(n^3) with BLAS-3 efficiency, which is what this module does. Neither
the sparsity of N (there is none in S: it is dense) nor the selected-inversion recurrences
(they save work only where the factor has zeros; a dense factor has none) lower the exponent,
so the exact blocks of a dense network are bounded below by ~one dense factorization of the
n_K x n_K reduced system plus the rank-n_E update that forms it and the n_K^2 n_E triangular
solve of the E blocks: about 2.7 n^3 flops for a square network with n = d I reduced
unknowns (syrk n_K^2 n_E, potrf n_K^3/3, trsm n_K^2 n_E, trtri n_K^3/3). There is no LM
factorization to share: the engine solves its damped steps by CG (and a direct step would
factor the *damped* S, not the S whose inverse is the covariance).

Measured (``benchmarks/bench_toa.py``, one BLAS thread, the shared 2-core machine at load
~4, CPU s): 1000 x 1000 the exact blocks 2.80 s (their four BLAS calls alone 2.10 s) against a
0.95 s solve and SciPy ``least_squares`` (trf, analytic sparse Jacobian) 2.24 s; 2000 x 2000
19.5 s against a 2.5 s solve and SciPy 12.3 s; 3000 x 3000 67 s (peak RSS 0.94 GB, 0.76 GB
above the data: S and one column block). So on one core the exact blocks cost ~3x
(1000^2) to ~8x (2000^2) the solve, growing like n: ``<= 0.5x`` the solve is not reachable
with exact blocks. What can be had:

- threads: the dense algebra runs inside a scoped :func:`threadpoolctl.threadpool_limits`
  (:func:`dense_threads`: the process's cores, capped by any stated limit,
  ``OPENBLAS_NUM_THREADS`` / ``OMP_NUM_THREADS`` / ... or the caller's in-process setting;
  ``threads=`` of :func:`covariance_blocks` chooses), the rest of the process keeps its setting. Level-3 BLAS scales
  with the cores on an idle machine; on an oversubscribed one (the benchmark's, load ~4 on 2
  cores) two threads were *slower* (1000 x 1000: 6.7 s wall against 6.3 s on one).
- ``covariance="local"`` (:func:`local_blocks`): each node's conditional covariance, its own
  information block inverted, O(I J d^2) (0.06 s at 1000 x 1000, 0.24 s at 2000 x 2000). It
  trades every inter-node correlation and the gauge for speed: relative error
  ``O((d + 1) / n_min)``, ``n_min`` the fewest ranges of any node (0.25 % largest, 0.11 %
  median at 1000 x 1000); without offsets only (with them a common offset trades against the
  scale, a soft global mode the conditional blocks miss).

The file is above 600 lines because this docstring is the module's cost model and the
request parsing, the exact and the approximate blocks share its helpers (one home).
"""

from __future__ import annotations

import os
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from typing import Any

import numpy as np
import scipy.linalg
from numpy.typing import NDArray

from ...errors import DegenerateGeometryError, InputError
from .model import (
    _flags,
    _Layout,
    _make_layout,
    _node_indices,
    _pack,
    _pinned_positions,
    _unpack,
    gauge_basis,
)
from .schur_lm import Grid, _inv_blocks, diagonal_blocks, directions

__all__ = [
    "COVARIANCE_MODES",
    "normalize_covariance",
    "resolve_covariance",
    "gauge_free_blocks",
    "blocks_from_inverse",
    "covariance_blocks",
    "dense_threads",
    "is_local",
    "local_blocks",
]

Array = NDArray[np.float64]
Index = NDArray[np.intp]

COVARIANCE_MODES = ("all", "receivers", "sources", "none", "local")

#: doubles per column block of H (K coordinates x E columns): 4 M doubles = 32 MB
_BLOCK_DOUBLES = 1 << 22
#: H is kept between the two passes (instead of rebuilt) when it has at most this many
#: doubles (256 MB); larger networks rebuild it block by block (memory = S + one block)
_KEEP_H_DOUBLES = 1 << 25
#: reduced systems smaller than this (coordinates) run the dense algebra as the caller's BLAS
#: is set: one factorization takes < 10 ms there, as long as threads take to start and
#: threadpoolctl to find the BLAS libraries
_THREADS_MIN_N = 1024
#: environment variables that state a user's cap on BLAS threads (honoured, never raised)
_THREAD_ENV = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS", "BLIS_NUM_THREADS")


# ---------------------------------------------------------------------------
# BLAS threads for the dense algebra
# ---------------------------------------------------------------------------


def dense_threads() -> int:
    """BLAS threads the dense covariance algebra runs on by default.

    The cores this process may run on (``os.sched_getaffinity``; ``os.cpu_count`` where
    that does not exist), capped by every limit already stated: the smallest positive
    integer among the environment variables that set a BLAS thread count
    (``OPENBLAS_NUM_THREADS``, ``OMP_NUM_THREADS``, ``MKL_NUM_THREADS``,
    ``BLIS_NUM_THREADS``) and the loaded BLAS libraries' current setting (an in-process
    :func:`threadpoolctl.threadpool_limits` of the caller). A limit a user or a scheduler set
    is obeyed, never raised; an unlimited BLAS gets all the cores.

    Returns
    -------
    int, at least 1.

    Notes
    -----
    The exact blocks are ~2.7 n^3 flops of level-3 BLAS on n x n matrices (module
    docstring); such calls scale with the cores, while the matrix-free solve
    (:mod:`selfcal.toa.engine.schur_lm`) is memory-bound NumPy arithmetic. The dense algebra runs in
    a scoped :func:`threadpoolctl.threadpool_limits` (restored on return), so an explicit
    ``threads=`` of :func:`covariance_blocks` applies to it alone.

    Examples
    --------
    >>> dense_threads() >= 1
    True
    """
    try:
        cores = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):  # pragma: no cover - not Linux
        cores = os.cpu_count() or 1
    for var in _THREAD_ENV:
        v = os.environ.get(var, "").strip()
        if v.isdigit() and int(v) > 0:
            cores = min(cores, int(v))
    from threadpoolctl import threadpool_info

    current = [int(lib["num_threads"]) for lib in threadpool_info()
               if lib.get("user_api") == "blas" and int(lib.get("num_threads") or 0) > 0]
    if current:
        cores = min(cores, max(current))
    return max(int(cores), 1)


@contextmanager
def _blas_scope(n: int, threads: int | None) -> Iterator[None]:
    """BLAS limited to ``threads`` (default :func:`dense_threads`) for an n x n reduced system."""
    if threads is None and n < _THREADS_MIN_N:
        yield
        return
    from threadpoolctl import threadpool_limits

    with threadpool_limits(limits=max(int(threads if threads is not None else dense_threads()), 1),
                           user_api="blas"):
        yield


# ---------------------------------------------------------------------------
# the request
# ---------------------------------------------------------------------------


def _as_index(v: Any, name: str) -> Index | None:
    if v is None:
        return None
    a = np.asarray(v)
    if a.dtype == bool:
        a = np.flatnonzero(a)
    if a.ndim == 0:
        a = a.reshape(1)
    if a.ndim != 1 or (a.size and not np.issubdtype(a.dtype, np.integer)):
        raise InputError(f"covariance: {name} must be a 1-D list of integer indices (or a boolean mask)")
    if a.size and a.min() < 0:
        raise InputError(f"covariance: {name} indices must be >= 0, got {int(a.min())}")
    return np.unique(a.astype(np.intp))


def normalize_covariance(spec: Any) -> Any:
    """Validate a covariance request; ``False`` when nothing is asked for.

    Parameters
    ----------
    spec : ``True`` / ``"all"`` (every block), ``"receivers"``, ``"sources"``,
        ``False`` / ``None`` / ``"none"`` (no block), ``"local"`` (every block, approximated
        by each node's conditional covariance, :func:`local_blocks`), or explicit indices: a mapping
        ``{"receivers": idx, "sources": idx}`` or a pair ``(receiver_idx, source_idx)``
        (either may be None = no block of that kind; integer lists or boolean masks).

    Returns
    -------
    ``False``, a mode string, or a pair of sorted unique index arrays (truthy), so that
    ``if normalize_covariance(spec):`` asks whether anything is to be computed.

    Raises
    ------
    InputError
        For an unknown mode or malformed indices.

    Examples
    --------
    >>> normalize_covariance("none"), normalize_covariance(True)
    (False, 'all')
    """
    if spec is None or spec is False:
        return False
    if spec is True:
        return "all"
    if isinstance(spec, str):
        if spec not in COVARIANCE_MODES:
            raise InputError(f"covariance must be one of {', '.join(COVARIANCE_MODES)} or indices, got {spec!r}")
        return False if spec == "none" else spec
    if isinstance(spec, Mapping):
        unknown = set(spec) - {"receivers", "sources"}
        if unknown:
            raise InputError(f"covariance: unknown keys {sorted(unknown)} (use 'receivers' and 'sources')")
        pair = (_as_index(spec.get("receivers"), "receivers"), _as_index(spec.get("sources"), "sources"))
    elif isinstance(spec, tuple | list) and len(spec) == 2:
        pair = (_as_index(spec[0], "receivers"), _as_index(spec[1], "sources"))
    else:
        raise InputError("covariance must be True/False, 'all', 'receivers', 'sources', 'none', "
                         "{'receivers': idx, 'sources': idx} or (receiver_idx, source_idx)")
    e = np.zeros(0, np.intp)
    return (e if pair[0] is None else pair[0], e if pair[1] is None else pair[1])


def is_local(spec: Any) -> bool:
    """Whether a request asks for the approximate conditional blocks (``"local"``, :func:`local_blocks`)."""
    return isinstance(spec, str) and spec == "local"


def resolve_covariance(spec: Any, n_receivers: int, n_sources: int) -> tuple[Index, Index]:
    """Receiver and source indices whose blocks a request asks for (sorted, bounds-checked).

    Parameters
    ----------
    spec : any form accepted by :func:`normalize_covariance`.
    n_receivers, n_sources : I and J.

    Returns
    -------
    (receiver indices, source indices), int arrays (possibly empty).
    """
    s = normalize_covariance(spec)
    allr, alls = np.arange(n_receivers), np.arange(n_sources)
    none = np.zeros(0, np.intp)
    if s is False:
        return none, none
    if s in ("all", "local"):
        return allr, alls
    if s == "receivers":
        return allr, none
    if s == "sources":
        return none, alls
    ri, si = s
    for idx, n, kind in ((ri, n_receivers, "receiver"), (si, n_sources, "source")):
        if idx.size and idx.max() >= n:
            raise InputError(f"covariance: {kind} index {int(idx.max())} out of range (there are {n})")
    return ri, si


# ---------------------------------------------------------------------------
# Jacobian rows in column blocks of E nodes
# ---------------------------------------------------------------------------


def _kept_side(theta: Array, lay: _Layout) -> tuple[Array, Array]:
    r, s, _, _ = _unpack(theta, lay.I, lay.J, lay.d, lay.offsets)
    return (r, s) if lay.k_is_receivers else (s, r)


def _components(PK: Array, PE: Array) -> list[Array]:
    """Unit-vector components ``U_p = (x_k - x_e) / |x_k - x_e|`` (d arrays nK x nE).

    The Jacobian row of pair (k, e) is ``a = [U, 1?]`` on the kept node and ``b = [-U, 1?]``
    on the eliminated one (:mod:`selfcal.toa.engine.schur_lm`).
    """
    U, _ = directions(PK, PE, Grid(PK.shape[0], PE.shape[0]))
    return U


def _block_ranges(nE: int, nK: int, mK: int, mE: int) -> list[tuple[int, int]]:
    per = max(1, _BLOCK_DOUBLES // max(1, nK * max(mK, mE) * mE))
    return [(e0, min(nE, e0 + per)) for e0 in range(0, nE, per)]


def _h_block(Ub: list[Array], hasK: bool, hasE: bool, wK: Array, Rc: Array, pinned: Index) -> Array:
    """``H[k p, e r] = w_ke a_ke,p (b_ke^T R_e)_r`` for one E block, pinned rows zero: (nK mK, ne mE).

    ``Ub`` are the unit-vector components of the block (d arrays nK x ne), ``Rc`` (ne, mE, mE).
    """
    d = len(Ub)
    nK, ne = wK.shape
    mK, mE = d + hasK, d + hasE
    H4 = np.empty((nK, mK, ne, mE))
    c = np.empty((nK, ne))
    wa = [wK * Ub[p] for p in range(d)] + ([wK] if hasK else [])
    for r in range(mE):
        # c_r = b^T R_e[:, r] with b = [-U, 1?]
        np.multiply(Ub[0], -Rc[None, :, 0, r], out=c)
        for q in range(1, d):
            c -= Ub[q] * Rc[None, :, q, r]
        if hasE:
            c += Rc[None, :, d, r]
        for p in range(mK):
            np.multiply(wa[p], c, out=H4[:, p, :, r])
    H: Array = H4.reshape(nK * mK, ne * mE)
    H[pinned] = 0.0
    return H


def _block_gram(Xt: Array, m: int) -> Array:
    """``out[n] = X_n^T X_n`` for the column blocks of X, given ``Xt = X.T`` (n m, rows): (n, m, m)."""
    X3 = Xt.reshape(-1, m, Xt.shape[1])
    return np.matmul(X3, np.swapaxes(X3, 1, 2))


# ---------------------------------------------------------------------------
# the blocks
# ---------------------------------------------------------------------------


def gauge_free_blocks(
    theta: Array,
    w: Array,
    lay: _Layout,
    receivers: Index | None = None,
    sources: Index | None = None,
    *,
    threads: int | None = None,
) -> tuple[Array, Array]:
    """Diagonal node blocks of ``(J^T W J)^+`` (gauge removed) by selected inversion.

    Parameters
    ----------
    theta : (n,) parameter vector, receiver-major ``[r, s, d?, o?]`` (:mod:`selfcal.toa.engine.nls`).
    w : (I, J) weights of the ranges (``1/sigma_ij^2``, or the final IRLS weights), 0 = missing.
    lay : layout of :func:`selfcal.toa.engine.model._make_layout` (kept side, pinned coordinates).
    receivers, sources : indices of the blocks to compute (None = all); the others are NaN.
    threads : BLAS threads for the dense algebra (syrk, potrf, trsm, trtri); None =
        :func:`dense_threads` above ``_THREADS_MIN_N`` reduced coordinates, the caller's
        setting below.

    Returns
    -------
    (I, m_r, m_r), (J, m_s, m_s) blocks in the parameter frame, m = d (+1 with an offset);
    unit: the inverse of the weights' unit (multiply by sigma^2 for unit weights).

    Raises
    ------
    DegenerateGeometryError
        When the normal matrix is singular beyond the gauge.

    Notes
    -----
    Costs and memory are listed in the module docstring.
    """
    nA = lay.k_idx.size
    with _blas_scope(nA, threads):
        return _gauge_free_blocks(theta, w, lay, receivers, sources)


def _gauge_free_blocks(theta: Array, w: Array, lay: _Layout, receivers: Index | None,
                       sources: Index | None) -> tuple[Array, Array]:
    I, J = lay.I, lay.J
    ri = np.arange(I) if receivers is None else np.asarray(receivers, np.intp)
    si = np.arange(J) if sources is None else np.asarray(sources, np.intp)
    want_K, want_E = (ri, si) if lay.k_is_receivers else (si, ri)
    nK, mK = lay.k_idx.shape
    nE, mE = lay.e_idx.shape
    nA = nK * mK
    PK, PE = _kept_side(theta, lay)
    wK = np.asarray(w if lay.k_is_receivers else w.T, dtype=float)
    pinned = _pinned_positions(lay)
    blocks = _block_ranges(nE, nK, mK, mE)

    r, s, _, _ = _unpack(theta, I, J, lay.d, lay.offsets)
    Q = gauge_basis(r, s, lay.offsets)
    g = Q.shape[1]
    QK = Q[lay.k_idx.ravel()]  # (nA, g)
    QE = Q[lay.e_idx.ravel()].reshape(nE, mE, g)

    # the node blocks A (K) and D (E) from component sums over the pairs, D^-1 = R R^T, and the
    # unit-vector components, all generated per column block of E nodes (memory: one block)
    hasK, hasE = mK > lay.d, mE > lay.d
    Ablk = np.zeros((nK, mK, mK))
    Dinv = np.empty((nE, mE, mE))
    Rc = np.empty((nE, mE, mE))

    def comps(e0: int, e1: int) -> list[Array]:
        return _components(PK, PE[e0:e1])

    # pass 1: A, D^-1, S = A - H H^T, t = Q_K - F Q_E
    S = np.zeros((nA, nA), order="F")
    t = QK.copy()
    keep = nA * nE * mE <= _KEEP_H_DOUBLES
    Hs: list[Array] = []
    for e0, e1 in blocks:
        Ub = comps(e0, e1)
        Ab, Db = diagonal_blocks(Ub, wK[:, e0:e1], hasK, hasE, Grid(nK, e1 - e0))
        Ablk += Ab
        Dinv[e0:e1] = _inv_blocks(Db, e0)
        Rc[e0:e1] = np.linalg.cholesky(Dinv[e0:e1])
        H = _h_block(Ub, hasK, hasE, wK[:, e0:e1], Rc[e0:e1], pinned)
        del Ub
        # S -= H H^T, lower triangle, in place (H.T is F-ordered: no copy)
        S = scipy.linalg.blas.dsyrk(-1.0, H.T, beta=1.0, c=S, trans=1, lower=1, overwrite_c=1)
        RtQE = np.einsum("eqp,eqg->epg", Rc[e0:e1], QE[e0:e1]).reshape(-1, g)
        t -= H @ RtQE
        if keep:
            Hs.append(H)
        del H
    idx = np.arange(nK)
    for p in range(mK):
        for q in range(mK):
            S[idx * mK + p, idx * mK + q] += Ablk[:, p, q]
    S[pinned, :] = 0.0
    S[:, pinned] = 0.0
    S[pinned, pinned] = 1.0  # decoupled: S^-1 keeps the kept block's inverse
    t[pinned] = 0.0
    L, info = scipy.linalg.lapack.dpotrf(S, lower=1, clean=1, overwrite_a=1)
    del S
    dl = np.abs(np.diag(L))
    if info != 0 or dl.min() <= 1e-7 * dl.max():  # not positive definite / cond(S) > ~1e14
        raise DegenerateGeometryError(
            "the normal equations are singular beyond the rigid-motion gauge: the geometry is "
            "degenerate (e.g. all points coplanar in 3-D, or too few ranges per node)",
            kind="degenerate-geometry",
        )
    YK = scipy.linalg.cho_solve((L, True), t, check_finite=False)  # pinned rows stay 0

    # pass 2: Y_E = D^-1 Q_E - F^T Y_K and the requested E blocks
    YE = np.einsum("epq,eqg->epg", Dinv, QE)
    CE = np.full((nE, mE, mE), np.nan)
    wantE = np.zeros(nE, bool)
    wantE[want_E] = True
    for b_i, (e0, e1) in enumerate(blocks):
        if keep:
            H = Hs[b_i]
        else:
            H = _h_block(comps(e0, e1), hasK, hasE, wK[:, e0:e1], Rc[e0:e1], pinned)
        Rb = Rc[e0:e1]
        YE[e0:e1] -= np.einsum("epq,eqg->epg", Rb, (H.T @ YK).reshape(e1 - e0, mE, g))
        sel = np.flatnonzero(wantE[e0:e1])
        if sel.size:
            # every node of the block asked for: solve in place of H (no fancy-indexed copy)
            every = sel.size == e1 - e0
            Hc = H if every else H[:, (sel[:, None] * mE + np.arange(mE)).ravel()]
            X = scipy.linalg.solve_triangular(L, Hc, lower=True, check_finite=False, overwrite_b=True)
            del Hc
            G = _block_gram(np.ascontiguousarray(X.T), mE)
            Rs = Rb[sel]
            CE[e0 + sel] = Dinv[e0 + sel] + Rs @ G @ np.swapaxes(Rs, 1, 2)
    Z = QK.T @ YK + np.einsum("epg,eph->gh", QE, YE)

    # the requested K blocks: columns of L^-1 (S^-1 = L^-T L^-1)
    CK = np.full((nK, mK, mK), np.nan)
    if want_K.size:
        cols = (want_K[:, None] * mK + np.arange(mK)).ravel()
        if cols.size * 3 > nA:
            Linv, info = scipy.linalg.lapack.dtrtri(L, lower=1, overwrite_c=1)
            if info != 0:
                raise DegenerateGeometryError("singular reduced normal matrix", kind="degenerate-geometry")
            # every column asked for: use L^-1 as it is (a fancy-indexed copy would double the memory)
            X = Linv if cols.size == nA else Linv[:, cols]
        else:
            E_ = np.zeros((nA, cols.size))
            E_[cols, np.arange(cols.size)] = 1.0
            X = scipy.linalg.solve_triangular(L, E_, lower=True, check_finite=False)
        CK[want_K] = _block_gram(np.ascontiguousarray(X.T), mK)
        del X
    # the pinned coordinates are not unknowns of C (its rows / columns there are 0)
    pk, pp = np.divmod(pinned, mK)
    CK[pk, pp, :] = np.where(np.isnan(CK[pk, pp, :]), np.nan, 0.0)
    CK[pk, :, pp] = np.where(np.isnan(CK[pk, :, pp]), np.nan, 0.0)

    def project(Cb: Array, Q3: Array, Y3: Array, want: Index) -> Array:
        out = np.full_like(Cb, np.nan)
        if want.size:
            Qn, Yn = Q3[want], Y3[want]
            QY = np.einsum("npg,nqg->npq", Qn, Yn)
            out[want] = Cb[want] - QY - np.swapaxes(QY, 1, 2) + np.einsum("npg,gh,nqh->npq", Qn, Z, Qn)
        return out

    PKb = project(CK, QK.reshape(nK, mK, g), YK.reshape(nK, mK, g), want_K)
    PEb = project(CE, QE, YE, want_E)
    return (PKb, PEb) if lay.k_is_receivers else (PEb, PKb)


#: :func:`blocks_from_inverse` is used while its lower bound on the smallest eigenvalue of the
#: pinned reduced system stays this many times above the pinned Cholesky's refusal (its
#: diagonal ratio 1e-7, a condition of 1e14): the selected inversion decides otherwise
_INVERSE_MARGIN = 1e3


def blocks_from_inverse(inverse: Any, theta: Array, lay: _Layout, receivers: Index | None = None,
                        sources: Index | None = None) -> tuple[Array, Array] | None:
    """:func:`gauge_free_blocks` (unit weights) from a generalised inverse of ``J^T J`` already held.

    ``N^+ = P G P`` for any generalised inverse ``G`` of ``N = J^T J`` when the gauge basis
    ``Q`` (:func:`selfcal.toa.engine.nls.gauge_basis`, ``P = I - Q Q^T``) spans N's null space;
    its diagonal node blocks are ``G_nn - Q_n Y_n^T - Y_n Q_n^T + Q_n Z Q_n^T`` with ``Y = G Q``
    and ``Z = Q^T Y``: the selected inversion's formula with its pinned inverse replaced by
    ``G``, so the blocks are the same to round-off. Used only where the selected inversion
    would not refuse the geometry, which is certified from bounds, never assumed:

    - every eliminated node's information block has condition below 1e12 (the test of
      :func:`selfcal.toa.engine.schur_lm._inv_blocks`);
    - the pinned reduced system ``S_p``, whose Cholesky factor is refused when its diagonal
      ratio falls to 1e-7, has ``lambda_min(S_p) >= min(1, lambda_min(N_ff)) >= min(1,
      s^2 / |G|)``: a Schur complement's smallest eigenvalue is at least the whole matrix's,
      ``N_ff`` (N on the unpinned coordinates) has ``lambda_min >= lambda+_min(N) s^2`` with
      ``s`` the smallest singular value of Q's pinned rows, and ``lambda+_min(N) >= 1 / |G|``
      (``inverse.norm_bound()``, an upper bound on ``|G|_2``); every Cholesky pivot lies in
      ``[lambda_min(S_p), max diag S_p]``, so the factor is accepted when that bound is
      :data:`_INVERSE_MARGIN` x 1e-14 x the largest diagonal entry.

    Parameters
    ----------
    inverse : an object with ``diagonal_blocks() -> (G_receivers, G_sources, N_receivers,
        N_sources)``, ``apply(X) -> G X`` and ``norm_bound() -> float``
        (:class:`selfcal.toa.verdict.bipartite.BipartiteInverse`), at the estimate ``theta``.
    theta, lay : as in :func:`gauge_free_blocks` (unit weights).
    receivers, sources : indices of the blocks to compute (None = all); the others are NaN.

    Returns
    -------
    (I, m_r, m_r), (J, m_s, m_s) blocks as :func:`gauge_free_blocks` returns them, or None where
    the bounds do not certify that it would accept the geometry (it then decides).
    """
    I, J = lay.I, lay.J
    r, s, _, _ = _unpack(theta, I, J, lay.d, lay.offsets)
    Q = gauge_basis(r, s, lay.offsets)
    Gr, Gs, Nr, Ns = inverse.diagonal_blocks()
    NK, NE = (Nr, Ns) if lay.k_is_receivers else (Ns, Nr)
    with np.errstate(all="ignore"):
        if not (np.linalg.cond(NE) < 1e12).all():
            return None
        sv = np.linalg.svd(Q[lay.pins], compute_uv=False)
        bound = float(inverse.norm_bound())
        low = min(1.0, float(sv.min()) ** 2 / bound) if sv.size and bound > 0 else 0.0
        top = max(1.0, float(np.max(np.einsum("npp->np", NK))))
    if not (np.isfinite(low) and low > _INVERSE_MARGIN * 1e-14 * top):
        return None
    Y = inverse.apply(Q)
    Z = Q.T @ Y
    r_idx, s_idx, _ = _node_indices(I, J, lay.d, lay.offsets)

    def project(Gb: Array, idx: NDArray[np.intp], want: Index | None) -> Array:
        out = np.full(Gb.shape, np.nan)
        sel = np.arange(Gb.shape[0]) if want is None else np.asarray(want, np.intp)
        if sel.size:
            Qn, Yn = Q[idx[sel]], Y[idx[sel]]
            QY = np.einsum("npg,nqg->npq", Qn, Yn)
            out[sel] = Gb[sel] - QY - np.swapaxes(QY, 1, 2) + np.einsum("npg,gh,nqh->npq", Qn, Z, Qn)
        return out

    return project(Gr, r_idx, receivers), project(Gs, s_idx, sources)


def local_blocks(theta: Array, w: Array, lay: _Layout) -> tuple[Array, Array]:
    """Every node's conditional covariance: its own information block inverted, O(I J d^2).

    Parameters
    ----------
    theta, w, lay : as in :func:`gauge_free_blocks`.

    Returns
    -------
    (I, m_r, m_r), (J, m_s, m_s) blocks ``A_n^-1``, ``A_n = sum_partners w a a^T`` the
    node's diagonal block of the normal matrix (:func:`selfcal.toa.engine.schur_lm.diagonal_blocks`),
    in the weights' inverse unit.

    Raises
    ------
    DegenerateGeometryError
        When a node's own ranges do not determine it (fewer than d (+1) non-collinear partners).

    Notes
    -----
    ``A_n^-1`` is the covariance of node n if every other node were known exactly. The
    exact gauge-free marginal ``(N^+)_nn`` differs by the uncertainty of the partners (a
    positive term whose relative size is the mean leverage of the node's ranges on their
    partners, the mean over its ranges of their leverage in the partner's own block,
    ``~d / (ranges of the partner)``) and by the removal of the global (gauge) motions (a
    negative term of the same order), so the relative error is ``O((d + 1) / n_min)``,
    ``n_min`` the fewest ranges of any node (within that bound on 40 random networks of
    15-200 nodes per side, largest 0.69 of it): measured (3-D, 5 % missing, largest
    block-wise relative Frobenius error over the receivers) 2.6 % at 100 x 100, 0.8 % at
    300 x 300, 0.25 % at 1000 x 1000 (median 1.1 %, 0.33 %, 0.10 %), test
    ``tests/toa/test_covariance.py``. What it trades: the exact blocks need one dense
    factorization of the Schur-reduced system (``O(n^3)``, module docstring); these blocks
    are as cheap as one Gauss-Newton product but ignore every correlation between nodes,
    so on small or sparse networks (a node whose partners are themselves poorly placed, a
    chain) they can be far too small. No cross-covariance and no gauge enters them. Only
    without offsets: with unknown offsets the nodes share soft global modes (a common
    offset against the scale) that conditional blocks miss (4-14 % at ~100 nodes, not
    O(1/n)), so other offset modes raise :class:`~selfcal.errors.InputError`.
    """
    if lay.offsets != "none":
        raise InputError("covariance='local' needs offsets='none': with unknown offsets the nodes share soft "
                         "global modes (a common offset against the scale) that conditional blocks miss "
                         "(measured 4-14 % error at ~100 nodes); ask for 'all', 'receivers', 'sources' or indices")
    PK, PE = _kept_side(theta, lay)
    wK = np.asarray(w if lay.k_is_receivers else w.T, dtype=float)
    nK, mK = lay.k_idx.shape
    nE, mE = lay.e_idx.shape
    # the node blocks from the components of one column block of E nodes at a time (memory)
    Ablk = np.zeros((nK, mK, mK))
    Dblk = np.empty((nE, mE, mE))
    for e0, e1 in _block_ranges(nE, nK, mK, mE):
        Ab, Dblk[e0:e1] = diagonal_blocks(_components(PK, PE[e0:e1]), wK[:, e0:e1], False, False,
                                          Grid(nK, e1 - e0))
        Ablk += Ab
    CK, CE = _inv_blocks(Ablk), _inv_blocks(Dblk)
    return (CK, CE) if lay.k_is_receivers else (CE, CK)


def covariance_blocks(
    receivers: Array,
    sources: Array,
    weights: Array,
    *,
    offsets: str = "none",
    covariance: Any = "all",
    threads: int | None = None,
) -> tuple[Array, Array]:
    """Gauge-free marginal blocks of ``(J^T W J)^+`` at a given geometry (003 eq. 17).

    Parameters
    ----------
    receivers, sources : (I, d), (J, d) positions, metres.
    weights : (I, J) weights ``1/sigma_ij^2`` (1/m^2), 0 where a range is missing.
    offsets : "none" | "receivers" | "sources" | "both" (which offsets are unknown; their
        values do not enter the Jacobian).
    covariance : which blocks (:func:`normalize_covariance`); the others are NaN.
    threads : BLAS threads for the dense algebra (None = :func:`dense_threads` on large
        networks, see :func:`gauge_free_blocks`).

    Returns
    -------
    (I, m_r, m_r), (J, m_s, m_s) covariance blocks, m^2 (offset entries last), NaN where not
    requested.

    Examples
    --------
    >>> import numpy as np
    >>> rng = np.random.default_rng(0)
    >>> r, s = rng.uniform(0, 5, (6, 3)), rng.uniform(0, 5, (9, 3))
    >>> Cr, Cs = covariance_blocks(r, s, np.full((6, 9), 1e4), covariance="receivers")
    >>> Cr.shape, bool(np.isnan(Cs).all())
    ((6, 3, 3), True)
    """
    r = np.asarray(receivers, float)
    s = np.asarray(sources, float)
    I, J = r.shape[0], s.shape[0]
    has_r, has_s = _flags(offsets)
    theta = _pack(r, s, np.zeros(I) if has_r else None, np.zeros(J) if has_s else None)
    lay = _make_layout(r, s, offsets)
    if is_local(normalize_covariance(covariance)):
        return local_blocks(theta, np.asarray(weights, float), lay)
    ri, si = resolve_covariance(covariance, I, J)
    return gauge_free_blocks(theta, np.asarray(weights, float), lay, ri, si, threads=threads)
