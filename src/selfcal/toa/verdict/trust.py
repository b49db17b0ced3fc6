"""Is the data a geometry at all? The TOA trust tests with the noise *unknown*.

- :func:`null_parameters`: parameters of the model without geometry nested in each offsets mode.
- :func:`permutation_test` / :class:`PermutationTest`: Monte-Carlo permutation test of
  "the data fit no geometry" with a fixed cheap procedure (:func:`geometry_statistic`):
  level 0.05 by construction (19 exchangeable copies).
- :func:`geometry_test` / :class:`GeometryTest`: the permutation test and leave-one-out
  cross-validation (median PRESS) of the fit against the model without geometry; what
  :func:`selfcal.toa.solve_toa` reports as ``geometry`` when no noise level is given.
- :func:`determinacy_test` / :class:`DeterminacyTest` (home :mod:`selfcal.toa.verdict.determinacy`,
  re-exported): do the data determine the fitted geometry? Each node's 95 % confidence
  region against the size of its node set; what ``solve_toa`` reports as ``determinacy``.

Split from :mod:`selfcal.toa.result` (which re-exports every name). Why this file is above
600 lines (~650): the permutation test computes its statistic for the whole stack of permuted
copies at once (the batched starts and fits, ``_complete_*``), which must equal
:func:`geometry_statistic` copy by copy; the single-copy and the batched forms stay side by
side so that one cannot change without the other.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..._checks import check_choice
from ..._result import json_float as _num
from ...geometry import n_parameters
from ..engine.nls import OFFSET_MODES
from ..init.starts import _additive_fit
from .determinacy import (  # noqa: F401 (re-exported: the trust tests are named here)
    DETERMINED_LEVEL,
    UNDETERMINED_FAIL_FRACTION,
    DeterminacyTest,
    determinacy_test,
    fisher_blocks,
    set_scale,
)

__all__ = [
    "DETERMINED_LEVEL", "UNDETERMINED_FAIL_FRACTION", "DeterminacyTest", "determinacy_test",
    "fisher_blocks", "set_scale", "PERMUTATION_ALPHA", "PERMUTATION_COPIES", "RESIDUAL_ALPHA",
    "GeometryTest", "PermutationTest", "geometry_statistic", "geometry_statistics", "geometry_test",
    "null_parameters", "permutation_test",
]

Array = NDArray[np.float64]

#: significance level of both trust tests: a fit whose p-value is below this fails
RESIDUAL_ALPHA = 1e-3

#: Monte-Carlo copies of the permutation test of the geometry (noise unknown) and its level:
#: with B exchangeable copies the observed statistic is the smallest of the B + 1 with
#: probability 1 / (B + 1) under the null, so 19 copies give a test of level exactly 0.05
PERMUTATION_COPIES = 19
PERMUTATION_ALPHA = 0.05
#: the permutation test runs on at most this many receivers and this many sources (the
#: best-observed ones, ties at random): its cost stays that of a small network
PERMUTATION_MAX_SIDE = 16
#: the 003 initialisers (MDS + multilateration, Algorithm 2) whose best start (least-squares offsets) is the test's fixed procedure
PERMUTATION_INITS = ("mds-multilat", "alg2")
#: ... followed by at most this many iterations of the one engine from the better start
#: (the same on the data and on every copy, so the test stays exact: only its power
#: changes). Without it the unrefined MDS start of a moving tag seen by 5 anchors in 3-D
#: fitted no better than the copies: 6 of 10 clean simulated LPS-layout flights passed
#: (4 anchors: 6 of 10). With 5 / 10 / 20 iterations: 10 / 10 / 10 (4 anchors 7 / 7 / 7)
#: at 0.16 / 0.21 / 0.26 s CPU per test against 0.06 s; uniform random matrices still pass
#: at the nominal rate (12 of 200 at 20 iterations over five shapes, level 0.05). Small
#: networks, 20 seeds each, 0 / 5 / 20 iterations: 6 x 8 3-D exact with 5 % missing 15 / 18 / 19,
#: the same at 5 cm 15 / 19 / 19, 5 x 8 3-D 15 / 18 / 19, 8 x 10 and 6 x 40 20 of 20 throughout
PERMUTATION_REFINE = 5

def null_parameters(n_receivers: int, n_sources: int, offsets: str) -> int:
    """Parameters of the model *without geometry* nested in ``offsets`` (see :func:`geometry_test`).

    All points at one place leave ``d_i + o_j`` (two-way additive, ``I + J - 1``) for "both",
    ``d_i`` (``I``) for "receivers", ``o_j`` (``J``) for "sources" and one constant for "none"
    (the limit of every source far away at the same distance).
    """
    check_choice(offsets, "offsets", OFFSET_MODES)
    I, J = int(n_receivers), int(n_sources)
    return {"none": 1, "receivers": I, "sources": J, "both": I + J - 1}[offsets]


@dataclass(frozen=True)
class PermutationTest:
    """Monte-Carlo permutation test: do the data fit a geometry at all? (noise unknown)

    The statistic ``T = RSS(geometry) / RSS(no geometry)`` is computed by one *fixed*,
    cheap procedure (:func:`geometry_statistic`: the better of two 003 initialisers with
    least-squares offsets, no refinement) on the data and on ``copies`` copies without
    geometry: the fit of the model without geometry (:func:`null_parameters`) plus its
    residuals permuted at random over the observed entries (re-centred so every copy has
    the same additive fit and residual sum of squares, Freedman & Lane 1983). Under the
    null (entries exchangeable about an additive fit, e.g. a uniform random matrix) the
    B + 1 values are exchangeable, so ``p = (1 + #{T_b <= T}) / (B + 1)`` is a valid
    p-value: ``P(p <= alpha) <= alpha`` whatever the procedure's quality (Besag & Clifford
    1989). The same procedure on data and copies is what makes it exact; its quality only
    sets the power.

    Attributes
    ----------
    statistic: T of the data (dimensionless, 0 = exact geometry).
    null_min, null_median: smallest and median T of the copies.
    copies: B.
    p_value: ``(1 + #{T_b <= T}) / (B + 1)``.
    alpha: level; ``passed`` is ``p_value <= alpha``.
    receivers, sources: size of the (sub-)matrix tested (at most ``PERMUTATION_MAX_SIDE`` each).
    passed: the data fit a geometry better than every copy without one.
    """

    statistic: float
    null_min: float
    null_median: float
    copies: int
    p_value: float
    alpha: float
    receivers: int
    sources: int
    passed: bool

    def to_dict(self) -> dict[str, Any]:
        """JSON-safe dict."""
        return {"test": "permutation", "statistic": _num(self.statistic), "null_min": _num(self.null_min),
                "null_median": _num(self.null_median), "copies": int(self.copies),
                "p_value": _num(self.p_value), "alpha": float(self.alpha), "receivers": int(self.receivers),
                "sources": int(self.sources), "passed": bool(self.passed)}


@dataclass(frozen=True)
class GeometryTest:
    """Do the data fit a geometry better than offsets alone? (noise unknown)

    Two tests, both must pass:

    - the permutation test (:class:`PermutationTest`, level 0.05 by construction): the
      stated false-alarm rate on data without geometry;
    - leave-one-out cross-validation in closed form (Allen's PRESS): the linearised
      prediction error of entry k from a fit without it is ``r_k / (1 - h_k)`` (``h_k`` its
      leverage). The geometric model must predict better than the model without geometry
      (all points at one place: ``d_i + o_j``, ``d_i``, ``o_j`` or a constant,
      :func:`null_parameters`). The comparison is on the *median* squared prediction error
      (times the number of entries, to read as a PRESS): one entry of leverage near 1 (a
      node seen by few others) multiplies its term by ``1 / (1 - h)^2`` and would decide a
      sum alone.

    Attributes
    ----------
    press, press_null: ``m * median_k (r_k / (1 - h_k))^2`` of the fit and of the model
        without geometry (squared matrix units), over the entries ``observations`` where
        both leverages are below 1 - 1e-8.
    rss, rss_null: residual sums of squares over the entries used.
    n_params, n_null: free parameters of the two models.
    f_statistic, p_value: the nested-model F test of the two RSS (for information: its F
        reference law assumes a linear model and is optimistic for the nonlinear fit).
    permutation: the permutation test, or None when it could not run (too few entries).
    passed: ``press < press_null`` and the permutation test passed.
    """

    press: float
    press_null: float
    rss: float
    rss_null: float
    n_params: int
    n_null: int
    observations: int
    f_statistic: float
    p_value: float
    passed: bool
    permutation: PermutationTest | None = None

    def to_dict(self) -> dict[str, Any]:
        """JSON-safe dict."""
        return {"test": "permutation+loo-cv", "press": _num(self.press), "press_null": _num(self.press_null),
                "rss": _num(self.rss), "rss_null": _num(self.rss_null),
                "n_params": int(self.n_params), "n_null": int(self.n_null),
                "observations": int(self.observations), "f_statistic": _num(self.f_statistic),
                "p_value": _num(self.p_value), "passed": bool(self.passed),
                "permutation": None if self.permutation is None else self.permutation.to_dict()}


def _additive_leverages(obs: NDArray[np.bool_], rows: bool, cols: bool, max_unknowns: int = 2000) -> Array:
    """Leverages of the additive model's design at the observed entries (mean n / m when large).

    The design ``X`` (intercept, row and column indicators less one each) has at most three
    non-zeros a row, so ``h_k = x_k (X^T X)^+ x_k^T`` comes from the small (n, n) normal
    matrix (eigenvalues below 1e-12 of the largest cut: a singular value of X below 1e-6 of
    the largest, a disconnected pattern's extra null direction) and three entries of its
    inverse per entry: O(m + n^3) instead of the SVD of the dense (m, n) design (0.2 s at
    14,400 x 239). Above ``max_unknowns`` columns or 5e7 design entries (the former
    memory guard of the dense design, kept so the choice between the exact and the mean
    leverages is unchanged) the mean ``n / m``. A complete mask is a balanced two-way layout:
    its entries are exchangeable under row and column permutations, so every leverage is the
    same, the trace ``n`` (the design has full rank there) over ``m``: no matrix is formed.
    """
    import scipy.sparse

    I, J = obs.shape
    ii, jj = np.nonzero(obs)
    n = 1 + (I - 1 if rows else 0) + (J - 1 if cols else 0)
    H = np.full(obs.shape, np.nan)
    if n > max_unknowns or ii.size * n > 5e7 or (ii.size and obs.all()):  # before any (entries x n) array
        H[obs] = min(n / max(ii.size, 1), 1.0)
        return H
    if ii.size == 0:
        return H
    cidx = [np.zeros((ii.size, 1), np.intp)]
    vals = [np.ones((ii.size, 1))]
    k = 1
    for on, idx, size in ((rows, ii, I), (cols, jj, J)):
        if on:  # indicator of row / column idx, the first one dropped (a zero entry in column 0)
            cidx.append(np.where(idx > 0, k + idx - 1, 0)[:, None])
            vals.append((idx > 0).astype(float)[:, None])
            k += size - 1
    C, V = np.hstack(cidx), np.hstack(vals)
    X = scipy.sparse.csr_matrix((V.ravel(), C.ravel(), np.arange(0, C.size + 1, C.shape[1])), shape=(ii.size, n))
    N = np.asarray((X.T @ X).todense())
    lam, W = np.linalg.eigh(N)
    keep = lam > lam[-1] * 1e-12
    P = (W[:, keep] / lam[keep]) @ W[:, keep].T
    H[obs] = np.einsum("ka,kab,kb->k", V, P[C[:, :, None], C[:, None, :]], V)
    return H


def geometry_statistic(ranges: Any, dim: int, offsets: str) -> float:
    """``RSS(geometry) / RSS(no geometry)`` of one fixed, cheap procedure (see :class:`PermutationTest`).

    The geometry is the better of the 003 starts of :data:`PERMUTATION_INITS` (MDS +
    multilateration, Algorithm 2 of :mod:`selfcal.toa.init.mds`, in the gauge they return) with
    the least-squares offsets of ``offsets``, then :data:`PERMUTATION_REFINE` iterations of
    Levenberg-Marquardt from it (:func:`geometry_statistics` on a stack of one). ``inf`` when
    no start applies.

    Parameters
    ----------
    ranges: (I, J) ranges (metres), NaN = missing.
    dim, offsets: the model.

    Returns
    -------
    float, >= 0 (above 1 when the start fits worse than the model without geometry).

    Examples
    --------
    >>> import numpy as np
    >>> from selfcal.toa import toa_model
    >>> g = np.random.default_rng(0)
    >>> r, s = g.uniform(0, 10, (8, 2)), g.uniform(0, 10, (10, 2))
    >>> bool(geometry_statistic(toa_model(r, s), 2, "none") < 1e-6)
    True
    """
    return float(geometry_statistics(np.asarray(ranges, dtype=float)[None], dim, offsets)[0])


def geometry_statistics(stack: Array, dim: int, offsets: str) -> Array:
    """:func:`geometry_statistic` of every matrix of a stack with one missing pattern, (S,).

    The starts are those of the one-matrix initialisers, computed for the whole stack at once
    when the matrices are complete (:func:`_complete_starts`, equal to them), else matrix by
    matrix; the :data:`PERMUTATION_REFINE` iterations of every matrix then run in lockstep,
    each matrix with its own start (offsets at zero), damping and stopping
    (:func:`selfcal.toa.engine.batch_lm.solve_batch_lm` with one matrix per start; the
    iterates of one matrix do not depend on the others in the stack), where a one-matrix
    refinement would run (each node with its ``d`` (+ offset) ranges, no fewer ranges than
    unknowns). The statistic is the smaller of the start's (with least-squares offsets) and
    the refined fit's RSS ratio.

    Parameters
    ----------
    stack: (S, I, J) ranges (metres), NaN = missing, the same entries missing in every matrix.
    dim, offsets: the model.

    Returns
    -------
    (S,) statistics, ``inf`` for a matrix where no start applies.

    Notes
    -----
    One start at a time (``refine_toa``), the 5 iterations of a 16 x 16 block with both
    offsets cost ~6.6 ms of Python overhead each, 0.13 s of the permutation test's 0.15 s at
    120 units; in lockstep the 20 matrices cost about as much as three, and the stacked
    starts about as much as four matrices' (``benchmarks/bench_postsolve.py``).
    """
    from ...errors import DegenerateGeometryError, InputError
    from ..engine.batch_lm import solve_batch_lm
    from ..engine.nls import toa_model
    from ..init.mds import mds_alg2, mds_multilateration

    inits = {"mds-multilat": lambda Z: mds_multilateration(Z, dim, rng=0), "alg2": lambda Z: mds_alg2(Z, dim)}

    stack = np.asarray(stack, dtype=float)
    S = stack.shape[0]
    has_r, has_s = offsets in ("receivers", "both"), offsets in ("sources", "both")
    obs = np.isfinite(stack[0])
    out = np.full(S, np.inf)
    rss0 = np.zeros(S)
    starts: list[Array] = []
    which: list[int] = []
    # negative ranges: shifted for the initialiser only
    shifts = np.minimum(0.0, np.where(obs, stack, np.inf).min(axis=(1, 2)))
    batched = _complete_starts(stack - shifts[:, None, None], dim) if obs.all() and S > 1 else None
    if batched is not None:  # the same arithmetic as the loop below, each step once for the stack
        _complete_statistics(stack, batched, has_r, has_s, out, rss0, starts, which)
    for k in range(S if batched is None else 0):
        Y = stack[k]
        e0 = (Y - _additive_fit(Y, has_r, has_s))[obs]
        rss0[k] = float(e0 @ e0)
        if not rss0[k] > 0:
            continue
        shift = float(shifts[k])
        start = None
        for method in PERMUTATION_INITS:
            try:
                with np.errstate(all="ignore"):
                    r, s = inits[method](Y - shift) if batched is None else (batched[method][0][k],
                                                                             batched[method][1][k])
                    r, s = np.asarray(r, float), np.asarray(s, float)
                    E = Y - toa_model(r, s)
                    E = E - _additive_fit(E, has_r, has_s) if (has_r or has_s) else E
            except (DegenerateGeometryError, InputError, np.linalg.LinAlgError, ValueError, FloatingPointError):
                continue
            e = E[obs]
            if np.isfinite(e).all() and float(e @ e) / rss0[k] < out[k]:
                out[k] = float(e @ e) / rss0[k]
                # the positions; the offsets start at zero (as refine_toa's default start)
                start = np.concatenate([r.ravel(), s.ravel(), np.zeros(Y.shape[0] * has_r + Y.shape[1] * has_s)])
        if start is not None:
            starts.append(start)
            which.append(k)
    I, J = obs.shape
    # refined where the one-matrix refinement would run: every node with its d (+ offset)
    # ranges and no fewer ranges than unknowns (refine_toa refuses the rest; the start decides)
    counts_ok = (obs.sum(axis=1).min() >= dim + has_r and obs.sum(axis=0).min() >= dim + has_s
                 and int(obs.sum()) >= n_parameters(I, J, dim, offsets))
    if which and PERMUTATION_REFINE > 0 and counts_ok:
        idx = np.asarray(which)
        with np.errstate(all="ignore"), warnings.catch_warnings():
            warnings.simplefilter("ignore")
            Th, _, _, fin = solve_batch_lm(np.stack(starts), stack[idx], dim, offsets, "linear", 1.0,
                                           PERMUTATION_REFINE, 1e-10, cholesky=True)
        for row, k in enumerate(idx):
            th = Th[row]
            r, s = th[:I * dim].reshape(I, dim), th[I * dim:(I + J) * dim].reshape(J, dim)
            tail = th[(I + J) * dim:]
            d = tail[:I] if has_r else None
            o = tail[I if has_r else 0:] if has_s else None
            with np.errstate(all="ignore"):
                e = (stack[k] - toa_model(r, s, d, o))[obs]
            if fin[row] and np.isfinite(e).all():
                out[k] = min(out[k], float(e @ e) / rss0[k])
    return out


def _stack_model(r: Array, s: Array) -> Array:
    """:func:`selfcal.toa.engine.nls.toa_model` (no offsets) of a stack, (S, I, d), (S, J, d) -> (S, I, J):
    the same operations, component by component."""
    D = np.zeros(r.shape[:2] + (s.shape[1],))
    for p in range(r.shape[2]):
        t = r[:, :, None, p] - s[:, None, :, p]
        t *= t
        D += t
    return np.sqrt(D, out=D)


def _stack_additive_fit(Y: Array, rows: bool, cols: bool) -> Array:
    """:func:`selfcal.toa.init.starts._additive_fit` of a stack of complete matrices (S, I, J), at
    least one of ``rows``, ``cols``: one sweep of row then column means, the same operations
    matrix by matrix."""
    S, I, J = Y.shape
    a = Y.sum(axis=2) / J if rows else np.zeros((S, I))
    b = (Y - a[:, :, None]).sum(axis=1) / I if cols else np.zeros((S, J))
    return a[:, :, None] + b[:, None, :]


def _complete_statistics(stack: Array, batched: dict[str, tuple[Array, Array]], has_r: bool, has_s: bool,
                         out: Array, rss0: Array, starts: list[Array], which: list[int]) -> None:
    """The start statistics of :func:`geometry_statistics` for a stack of complete matrices with
    their stacked starts (:func:`_complete_starts`): ``out``, ``rss0``, ``starts`` and ``which``
    filled as the matrix-by-matrix loop fills them (the same operations; the sums of squares
    matrix by matrix, as there)."""
    S, I, J = stack.shape
    E0 = (stack - _stack_additive_fit(stack, has_r, has_s) if has_r or has_s
          else np.stack([Y - _additive_fit(Y, False, False) for Y in stack]))
    for k in range(S):
        e0 = E0[k].ravel()
        rss0[k] = float(e0 @ e0)
    fits: list[tuple[Array, Array, Array]] = []
    with np.errstate(all="ignore"):
        for method in PERMUTATION_INITS:
            r, s = batched[method]
            E = stack - _stack_model(r, s)
            E = E - _stack_additive_fit(E, has_r, has_s) if (has_r or has_s) else E
            fits.append((r, s, E))
    for k in range(S):
        if not rss0[k] > 0:
            continue
        start = None
        for r, s, E in fits:
            e = E[k].ravel()
            if np.isfinite(e).all() and float(e @ e) / rss0[k] < out[k]:
                out[k] = float(e @ e) / rss0[k]
                start = np.concatenate([r[k].ravel(), s[k].ravel(), np.zeros(I * has_r + J * has_s)])
        if start is not None:
            starts.append(start)
            which.append(k)


def _complete_starts(stack: Array, dim: int) -> dict[str, tuple[Array, Array]] | None:
    """The starts of :data:`PERMUTATION_INITS` for every matrix of a stack of complete, non-negative
    range matrices at once, or None where the one-matrix initialisers must decide.

    The same computations as :func:`selfcal.toa.init.mds.mds_multilateration` and
    :func:`selfcal.toa.init.mds.mds_alg2` on a complete matrix (tested equal): the eq. 11
    distances and their classical MDS (shared by the two), then multilateration with two
    alternations, or Algorithm 2's extended MDS per source aligned by Procrustes, each step
    one stacked call over the matrices (a complete matrix gives every source the same
    anchors, so each multilateration's normal matrix is one per matrix). Returns
    ``{method: (receivers (S, I, d), sources (S, J, d))}``; None for matrices smaller than
    the initialisers accept, or when a stacked solve fails (the one-matrix path then decides
    each matrix).
    """
    from ...errors import InputError
    from ...geometry import align
    from ..init.mds_core import _double_centre, _top_eig_coords
    from ..init.multilat import EQ11_MAX_FLOPS

    S, I, J = stack.shape
    if I < dim + 1 or J < dim + 1 or J > max(dim + 1, int(EQ11_MAX_FLOPS // max(1, I * I))):
        return None

    def multilaterate(P: Array, R: Array) -> Array:
        """Points (S, m, d) from anchors P (S, n, d) and complete ranges R (S, m, n) (mds_core.multilaterate)."""
        centre = P.mean(axis=1, keepdims=True)
        Pc = P - centre
        A = np.concatenate([-2.0 * Pc, np.ones(P.shape[:2] + (1,))], axis=2)  # (S, n, d + 1)
        b = R**2 - (Pc**2).sum(axis=2)[:, None, :]
        N = np.matmul(A.transpose(0, 2, 1), A)
        scale = np.trace(N, axis1=1, axis2=2)[:, None, None] / (dim + 1)
        N = N + 1e-9 * np.maximum(scale, 1e-12) * np.eye(dim + 1)
        z = np.linalg.solve(N, np.matmul(b, A).transpose(0, 2, 1)).transpose(0, 2, 1)
        return z[..., :dim] + centre

    try:
        with np.errstate(all="ignore"):
            D = np.abs(stack[:, :, None, :] - stack[:, None, :, :]).max(axis=3)  # eq. 11, (S, I, I)
            D = np.fmax(D, D.transpose(0, 2, 1))
            D[:, np.arange(I), np.arange(I)] = 0.0
            rec0 = _top_eig_coords(_double_centre(D**2), dim)  # classical MDS, (S, I, d)
            src = multilaterate(rec0, stack.transpose(0, 2, 1))
            rec = rec0
            for _ in range(2):
                rec = multilaterate(src, stack)
                src = multilaterate(rec, stack.transpose(0, 2, 1))
            Dk = np.zeros((S, J, I + 1, I + 1))  # Algorithm 2, eq. 13: the source as the last point
            Dk[:, :, :I, :I] = D[:, None]
            Dk[:, :, :I, I] = stack.transpose(0, 2, 1)
            Dk[:, :, I, :I] = Dk[:, :, :I, I]
            coords = _top_eig_coords(_double_centre(Dk**2), dim)  # (S, J, I + 1, d)
            ref = np.broadcast_to(rec0[:, None], (S, J, I, dim)).reshape(S * J, I, dim)
            a = align(coords[:, :, :I].reshape(S * J, I, dim), ref, reflection=True)  # eq. 14
            src2 = (np.einsum("bij,bj->bi", a.rotation, coords[:, :, I].reshape(S * J, dim))
                    + a.translation).reshape(S, J, dim)  # eq. 15
    except (InputError, np.linalg.LinAlgError, ValueError, FloatingPointError):  # InputError: align, no finite point
        return None
    return {"mds-multilat": (rec, src), "alg2": (rec0, src2)}


def _test_block(obs: NDArray[np.bool_], side: int, dim: int, g: np.random.Generator,
                complete: bool = True) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
    """The tested block: at most ``side`` rows, then ``side`` columns, with the most observed
    entries (ties at random); then, while it has missing entries, the row or column missing the
    most is removed, down to ``dim + 3`` a side (a complete block is several times cheaper to
    initialise than one that needs completing).

    Chosen from the mask only (never the values), so the entries of the block stay
    exchangeable under the null.
    """
    I, J = obs.shape

    def pick(counts: NDArray[np.intp], n: int) -> NDArray[np.intp]:
        order = g.permutation(counts.size)
        order = order[np.argsort(-counts[order], kind="stable")]
        return np.sort(order[:n])

    rows = pick(obs.sum(axis=1), min(I, side)) if I > side else np.arange(I)
    cols = pick(obs[rows].sum(axis=0), min(J, side)) if J > side else np.arange(J)
    B = obs[np.ix_(rows, cols)]
    while complete and not B.all():
        miss_r, miss_c = (~B).sum(axis=1), (~B).sum(axis=0)
        by_row = miss_r.max() * B.shape[1] >= miss_c.max() * B.shape[0]  # the larger missing fraction
        if by_row and B.shape[0] > dim + 3:
            k = int(g.choice(np.flatnonzero(miss_r == miss_r.max())))
            rows, B = np.delete(rows, k), np.delete(B, k, axis=0)
        elif B.shape[1] > dim + 3:
            k = int(g.choice(np.flatnonzero(miss_c == miss_c.max())))
            cols, B = np.delete(cols, k), np.delete(B, k, axis=1)
        elif B.shape[0] > dim + 3:
            k = int(g.choice(np.flatnonzero(miss_r == miss_r.max())))
            rows, B = np.delete(rows, k), np.delete(B, k, axis=0)
        else:
            break
    return rows, cols


def permutation_test(ranges: Any, dim: int, offsets: str, *, copies: int = PERMUTATION_COPIES,
                     alpha: float = PERMUTATION_ALPHA, seed: int = 0,
                     max_side: int = PERMUTATION_MAX_SIDE) -> PermutationTest | None:
    """Permutation test of "the data fit no geometry" (:class:`PermutationTest`).

    Parameters
    ----------
    ranges: (I, J) the entries a fit used (NaN elsewhere), metres.
    dim, offsets: the model.
    copies: B, the Monte-Carlo copies (level ``1 / (B + 1)`` is the smallest attainable).
    alpha: level.
    seed: seed of the permutations and of the sub-block (fixed: the verdict is
        reproducible; the permutations do not depend on the data, so the level holds).
    max_side: at most this many receivers and sources are tested (:func:`_test_block`).

    Returns
    -------
    PermutationTest, or None when the tested block has fewer than ``dim + 1`` spare entries
    (observations minus parameters): too few for the test to have power.

    Examples
    --------
    >>> import numpy as np
    >>> from selfcal.toa import toa_model
    >>> g = np.random.default_rng(0)
    >>> permutation_test(g.uniform(0, 10, (8, 10)), 2, "none").passed
    False
    >>> r, s = g.uniform(0, 10, (8, 2)), g.uniform(0, 10, (10, 2))
    >>> permutation_test(toa_model(r, s) + g.normal(0, 0.05, (8, 10)), 2, "none").passed
    True
    """
    g = np.random.default_rng(seed)
    Y0 = np.asarray(ranges, dtype=float)

    def block(complete: bool) -> tuple[Array, int]:
        rows, cols = _test_block(np.isfinite(Y0), int(max_side), dim, g, complete)
        B = Y0[np.ix_(rows, cols)]
        ob = np.isfinite(B)
        B = B[np.ix_(ob.sum(axis=1) > 0, ob.sum(axis=0) > 0)]
        I, J = B.shape
        spare = int(np.isfinite(B).sum()) - n_parameters(I, J, dim, offsets) if I > dim and J > dim else 0
        return B, spare

    # the complete block is cheaper; it is used while it keeps at least half the spare
    # entries (the power) of the block as it is
    Y, spare = block(False)
    if not np.isfinite(Y).all():
        Yc, spare_c = block(True)
        if 2 * spare_c >= spare:
            Y, spare = Yc, spare_c
    if spare < dim + 1:
        # fewer spare entries than one more node needs to be located with one to spare: a
        # geometry then fits almost any matrix; measured power at 5 x 5 in 3-D (1 spare entry):
        # 5 of 10 genuine networks. The verdict rests on the leave-one-out check alone.
        return None
    obs = np.isfinite(Y)
    I, J = Y.shape
    has_r, has_s = offsets in ("receivers", "both"), offsets in ("sources", "both")
    F = _additive_fit(Y, has_r, has_s)
    e = (Y - F)[obs]
    rss0 = float(e @ e)
    stack = np.empty((int(copies) + 1,) + Y.shape)
    stack[0] = Y
    for b in range(int(copies)):
        Z = np.full(Y.shape, np.nan)
        Z[obs] = g.permutation(e)
        if has_r or has_s:  # re-centred: the copy's additive fit is F, its residual RSS rss0
            Z = Z - _additive_fit(Z, has_r, has_s)
        z = Z[obs]
        if z @ z > 0:
            Z *= np.sqrt(rss0 / float(z @ z))
        stack[b + 1] = F + Z
    # the data and its copies through the same procedure, refined in lockstep
    T = geometry_statistics(stack, dim, offsets)
    t_obs, null = float(T[0]), T[1:]
    p = float((1 + np.sum(null <= t_obs)) / (copies + 1))
    return PermutationTest(float(t_obs), float(np.min(null)), float(np.median(null)), int(copies), p,
                           float(alpha), I, J, bool(p <= alpha))


def geometry_test(ranges: Any, residuals: Any, leverages: Any, dim: int, offsets: str, *,
                  alpha: float = RESIDUAL_ALPHA, permutation: bool = True) -> GeometryTest:
    """Test of the geometric model against the model without geometry (noise unknown).

    Parameters
    ----------
    ranges: (I, J) the entries the fit used (NaN elsewhere), any units.
    residuals: (I, J) measured minus modelled of the fit, same units, NaN where not used.
    leverages: (I, J) the fit's leverages (:func:`selfcal.toa.verdict.leverage.leverages`).
    dim, offsets: the fitted model.
    alpha: level of the informational F test.
    permutation: run the permutation test (:func:`permutation_test`).

    Returns
    -------
    GeometryTest (see its docstring for the rule).

    Examples
    --------
    >>> import numpy as np
    >>> from selfcal.toa import solve_toa
    >>> import warnings
    >>> with warnings.catch_warnings():
    ...     warnings.simplefilter("ignore")
    ...     res = solve_toa(np.random.default_rng(0).uniform(0, 10, (8, 10)), rng=0)
    >>> res.geometry.passed
    False
    """
    from scipy.stats import f as f_dist

    Y = np.asarray(ranges, dtype=float)
    E = np.asarray(residuals, dtype=float)
    H = np.asarray(leverages, dtype=float)
    has_r, has_s = offsets in ("receivers", "both"), offsets in ("sources", "both")
    use = np.isfinite(Y) & np.isfinite(E)
    Yu = np.where(use, Y, np.nan)
    E0 = Yu - _additive_fit(Yu, has_r, has_s)
    H0 = _additive_leverages(use, has_r, has_s)
    ok = use & np.isfinite(H) & (1 - H > 1e-8) & (1 - H0 > 1e-8)
    I, J = Y.shape
    n_ok = int(ok.sum())
    # robust PRESS: the median squared leave-one-out error, on the scale of a sum
    press = float(n_ok * np.median((E[ok] / (1 - H[ok])) ** 2)) if n_ok else float("nan")
    press0 = float(n_ok * np.median((E0[ok] / (1 - H0[ok])) ** 2)) if n_ok else float("nan")
    rss = float(np.sum(E[use] ** 2))
    rss0 = float(np.sum(E0[use] ** 2))
    n1 = n_parameters(I, J, dim, offsets)
    n0 = null_parameters(I, J, offsets)
    m = int(use.sum())
    dof, k = m - n1, max(n1 - n0, 1)
    if dof > 0 and rss > 0:
        stat = ((rss0 - rss) / k) / (rss / dof)
        p = float(f_dist.sf(stat, k, dof))
    else:
        stat, p = float("nan"), float("nan")
    perm = permutation_test(Yu, dim, offsets) if permutation else None
    cv_ok = bool(press < press0 or (press == 0.0 and press0 > 0.0))
    return GeometryTest(press, press0, rss, rss0, n1, n0, n_ok, float(stat), p,
                        cv_ok and (perm is None or perm.passed), perm)


