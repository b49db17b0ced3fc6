"""Range self-calibration on a measurement graph: any node may range to any other.

A range matrix is the graph of all receiver-source pairs. UWB systems also measure
anchor-to-anchor ranges (auto-positioning), tags may range to tags, and a pair is often
measured many times. :func:`solve_range_graph` takes that general form, the list of
measurements ``(a, b, range[, std])`` between ``n`` nodes, and returns every node's
position with covariances, in the user's frame (known nodes or reference nodes, the
machinery of :mod:`selfcal.toa.frame.frame`) or in the canonical gauge.

Model (003 eq. 2 on a general edge set): ``y_m = |x_a - x_b| + e_m``, ``e_m ~ N(0,
sigma_m^2)``, ``sigma_m`` the file's ``std`` when given, else a common unknown ``sigma``.

Repeated measurements. The weighted least-squares cost over the individual measurements
splits into the *pure error* ``sum_m w_m (y_m - ybar_p)^2`` (spread of the repeats about
their pair's weighted mean ``ybar_p``) and ``sum_p W_p (ybar_p - |x_a - x_b|)^2`` with
``W_p = sum w_m``; only the second depends on the positions, so the fit runs on the pair
means with weights ``W_p`` and is the least-squares fit of every measurement. The pure
error estimates the noise without any geometry (``dof = m - pairs``); the residual of the
pair means is compared with it by the lack-of-fit F test (Draper & Smith, *Applied
Regression Analysis*, sec. 2.1): a rejection says the ranges carry errors that repeats do
not show (per-pair biases, NLOS), so error bars from the repeats' spread would be too small.
The covariance is scaled by the residual noise estimate over all measurements
(``RSS / (m - n d + g)``), which contains both parts.

When do the ranges determine the nodes? A graph of ranges determines a generic
configuration up to a rigid motion and a mirror image exactly when it is *globally
rigid* in ``R^d`` (Connelly 2005; Gortler, Healy & Thurston 2010). Complete graphs are:
anchor-to-anchor ranges among all pairs of ``k >= d + 1`` anchors in general position fix
the anchors (``k = d + 1`` leaves no redundancy, so nothing checks the fit; ``k >= d + 2``
leaves ``k (k - 1) / 2 - (k d - d (d + 1) / 2)`` degrees of freedom for the residual test:
1 for 5 anchors in 3-D, 3 for 6, 6 for 7). Anchors in a plane of ``R^3`` are *not*
determined in 3-D by their mutual ranges to first order: moving one perpendicular to the
plane changes every range to it only at second order, so the out-of-plane coordinates
have no finite variance (reported as undetermined directions); their in-plane layout is
determined, and a plane configuration is its own mirror image. Tags ranging to coplanar
anchors are determined up to the mirror through the anchors' plane: known nodes that do
not all lie in that plane, or a ``z=`` reference (``--frame``) off it, fix the side. The
rank test here is the first-order one (the information matrix's null space beyond the
gauge, Asimow & Roth 1978): a generically rigid graph with a full-rank information matrix
still has a discrete ambiguity (flip of a node across its partners' hyperplane) when it
is rigid but not globally rigid (e.g. a node with only ``d`` ranges).

Engine. The fit is a sparse nonlinear least-squares problem over the free coordinates,
run by the package's one Levenberg-Marquardt driver
(:func:`selfcal.optim.lm.levenberg_marquardt`) with the range-graph model of
:func:`selfcal.toa.graph.graph_fit._fit` (sparse Jacobian of the edge residuals, fixed coordinates
left out, the rigid motions projected off a blind fit's steps, dense or sparse normal
equations as :func:`selfcal.optim.structure.lm_step` decides); the bipartite Schur engine of :mod:`selfcal.toa.sparse`
serves a graph that is bipartite (receivers x sources) as its initialiser
(:func:`selfcal.toa.sparse.solve_toa_sparse`), the dense blind solver
(:func:`selfcal.toa.solve.solve_toa`) the anchor x tag block of a mixed graph.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..._result import Result
from ...errors import DegenerateGeometryError, InputError, Status
from ..frame.nodes import FrameInfo
from .graph_checks import (
    _flat_within_errors,
    _gauge_modes,
    _mirror_ambiguous,
    _region_larger_than_set,
)
from .graph_fit import (
    NULL_TOL,
    TEST_LEVEL,
    _covariance,
    _fit,
    _flag_pairs,
    _pairs,
    _subset,
    collapse_repeats,
)
from .graph_start import _initial

__all__ = ["GraphResult", "NULL_TOL", "TEST_LEVEL", "solve_range_graph", "collapse_repeats", "simulate_range_graph"]

Array = NDArray[np.float64]
Index = NDArray[np.intp]


@dataclass(frozen=True, repr=False)
class GraphResult(Result):
    """Result of :func:`solve_range_graph` (lengths in metres).

    Attributes
    ----------
    names : tuple of str
        Node names (index order).
    positions : (n, d) array
        Node positions in the frame of ``frame`` (canonical gauge when none was given).
    position_cov : (n, d, d) array
        Covariance of each node's position in that frame (m^2); zero for coordinates the
        frame fixes, NaN for a node in an undetermined direction.
    residuals : (m,) array
        Measured minus fitted range of every measurement.
    residual_rms, noise_estimate : float
        RMS of the residuals (m); ``sqrt(weighted RSS / dof)`` with ``dof = m - n d + g``: metres
        without ``std``, in units of the given std (1 = as stated) with it.
    dof : int
        Residual degrees of freedom of the measurements (``g`` = gauge the frame leaves).
    n_measurements, n_pairs : int
        Measurements and distinct node pairs.
    pure_error_sigma : float or None
        Noise estimated from the spread of repeated measurements (None without repeats); the
        unit of ``noise_estimate``.
    pure_error_dof : int
        Degrees of freedom of that estimate (``m - pairs``).
    lack_of_fit_F, lack_of_fit_p : float or None
        Lack-of-fit F statistic of the pair means against the pure error, and its p value.
    chi2, chi2_p : float or None
        With per-measurement ``std``: the weighted RSS and its chi-square p value on ``dof``.
    undetermined_nodes : tuple of str
        Nodes that move in a direction the ranges do not see (null space of the information
        matrix beyond the gauge the frame leaves, or a 3-D node set flat within its error
        bars): not determined to first order. The result's status is then DEGENERATE.
    poorly_determined_nodes : tuple of str
        Nodes whose 95 % confidence region is larger than the whole node set (the rule of
        :mod:`selfcal.toa.verdict.determinacy`): reported, the status is not changed (a tag
        position seen by few anchors); a caller for whom such a node matters (an anchor)
        decides.
    mirror_ambiguous_nodes : tuple of str
        Nodes whose reflection through the (hyper)plane of their partners, re-fitted with
        the partners fixed, fits their ranges as well (weighted RSS increase below the
        chi-square(1) bound at 1e-3 times the noise variance): a tag ranging only to
        coplanar anchors is on either side of their plane. Status AMBIGUOUS.
    outliers : (m,) bool array
        Measurements of the pairs flagged as outliers (left out of the fit).
    outlier_pairs : int
        Number of such pairs.
    converged : bool
    iterations : int
        Linearisations of the least-squares driver, summed over the fits run.
    method : str
    frame : FrameInfo
        What the references fixed and what they left open.
    """

    names: tuple[str, ...]
    positions: Array
    position_cov: Array
    residuals: Array
    residual_rms: float
    noise_estimate: float
    dof: int
    n_measurements: int
    n_pairs: int
    pure_error_sigma: float | None
    pure_error_dof: int
    lack_of_fit_F: float | None
    lack_of_fit_p: float | None
    chi2: float | None
    chi2_p: float | None
    undetermined_nodes: tuple[str, ...]
    poorly_determined_nodes: tuple[str, ...]
    mirror_ambiguous_nodes: tuple[str, ...]
    outliers: NDArray[np.bool_]
    outlier_pairs: int
    converged: bool
    iterations: int
    method: str
    frame: FrameInfo

    @property
    def position_std(self) -> Array:
        """(n, d) standard deviation per coordinate (m)."""
        return np.sqrt(np.clip(np.diagonal(self.position_cov, axis1=1, axis2=2), 0.0, None))

    def _diagnose(self) -> tuple[Status, str]:
        if self.undetermined_nodes:
            more = ", ..." if len(self.undetermined_nodes) > 8 else ""
            return Status.DEGENERATE, ("the ranges do not determine node(s) " + ", ".join(self.undetermined_nodes[:8])
                                       + more + " (a direction the ranges do not see: too few ranges, or a node set "
                                       "flat within its error bars in 3-D, whose out-of-plane coordinates are free)")
        if self.mirror_ambiguous_nodes:
            more = ", ..." if len(self.mirror_ambiguous_nodes) > 8 else ""
            return Status.AMBIGUOUS, (f"{len(self.mirror_ambiguous_nodes)} node(s) fit their ranges as well mirrored "
                                      "through the plane of their partners (" + ", ".join(self.mirror_ambiguous_nodes[:8])
                                      + more + "): their partners are coplanar within the noise; an anchor off that "
                                      "plane resolves it")
        if not self.converged:
            return Status.NOT_CONVERGED, "the least-squares fit stopped before convergence"
        if self.chi2_p is not None and self.chi2_p < TEST_LEVEL:
            return Status.FAILED_TEST, (f"residual test against the given std failed: chi2 = {self.chi2:.4g} on "
                                        f"{self.dof} dof, p = {self.chi2_p:.3g}")
        return Status.SUCCESS, "converged" + ("" if self.chi2_p is None else
                                              f"; residual test passed (p = {self.chi2_p:.3g})")


def solve_range_graph(
    a: Any, b: Any, ranges: Any, n_nodes: int | None = None, *, std: Any = None, dim: int = 3,
    names: Sequence[str] | None = None, known: Any = None, frame: str | Mapping[str, Any] | None = None,
    rng: int | np.random.Generator | None = 0, outliers: bool = True,
) -> GraphResult:
    """Positions of every node of a range graph, with covariances, in the user's frame.

    Parameters
    ----------
    a, b : (m,) int
        The two nodes of each measurement (0-based), ``a != b``.
    ranges : (m,) float
        Measured ranges (m); a pair may appear many times, in either order.
    n_nodes : int, optional
        Number of nodes (default: the largest index + 1).
    std : (m,) float, optional
        Per-measurement std (m): weights, and a chi-square test of the fit.
    dim : 2 or 3
    names : sequence of str, optional
        Node names (default ``"0"``, ``"1"``, ...), used by ``known`` / ``frame`` and the output.
    known : mapping ``{node: (x, y[, z][, std])}`` or a CSV path, optional
        Known positions (exact, or with a std): they constrain the fit and set the frame
        (:func:`selfcal.toa.frame.frame.parse_known`; node = a name or a 0-based index).
    frame : ``"origin=A,x=B,xy=C[,z=D]"``, optional
        Frame by reference nodes (:func:`selfcal.toa.frame.frame.apply_frame`); exclusive with ``known``.
    rng : seed of the blind start.
    outliers : bool
        One soft-L1 fit at the noise scale (the given std; else the repeats' spread when it
        has 10 dof or more, else the residuals' MAD), then pairs whose studentized residual
        exceeds the Bonferroni bound (:func:`selfcal.toa.verdict.robust.outlier_threshold`,
        family-wise level :data:`selfcal.toa.verdict.robust.OUTLIER_ALPHA`; pairs of leverage above
        1/2 are not judged, a node keeps ``d + 1`` partners) are left out of a least-squares
        refit (one pass: re-judging on the refit swamped the other ranges of a spiked tag in
        simulations); False = plain least squares.

    Returns
    -------
    GraphResult

    Raises
    ------
    InputError
        Malformed measurements, an unknown node in ``known`` / ``frame``, both given.
    DegenerateGeometryError
        No blind start (no complete group of ``d + 1`` nodes and not bipartite), a node
        with fewer than ``d + 1`` ranges to the rest, degenerate references.

    Notes
    -----
    See the module docstring (model, repeats, when the ranges determine the nodes).

    Examples
    --------
    >>> import numpy as np
    >>> X = np.array([[0, 0, 3.], [5, 0, 2.8], [5, 4, 3.], [0, 4, 2.9], [2.5, 2, 0.5]])
    >>> a, b = np.triu_indices(5, 1)
    >>> y = np.linalg.norm(X[a] - X[b], axis=1)
    >>> res = solve_range_graph(a, b, y, known={"0": X[0], "1": X[1], "2": X[2], "3": X[3]})
    >>> bool(np.allclose(res.positions, X, atol=1e-6))
    True
    """
    from scipy.stats import chi2 as chi2_dist
    from scipy.stats import f as f_dist

    from ..frame.known import _affine_rank, _known_info, _rigid
    from ..frame.nodes import check_frame, parse_known

    d = int(dim)
    if d not in (2, 3):
        raise InputError(f"dim must be 2 or 3, got {dim}")
    aa, bb = np.asarray(a), np.asarray(b)
    y = np.asarray(ranges, float)
    if aa.ndim != 1 or aa.shape != bb.shape or y.shape != aa.shape or aa.size == 0:
        raise InputError("a, b and ranges must be non-empty 1-D arrays of one length")
    if not (np.issubdtype(aa.dtype, np.integer) and np.issubdtype(bb.dtype, np.integer)):
        raise InputError("a and b must be integer node indices")
    n = int(max(aa.max(), bb.max())) + 1 if n_nodes is None else int(n_nodes)
    if aa.min() < 0 or bb.min() < 0 or aa.max() >= n or bb.max() >= n:
        raise InputError(f"node index out of range for {n} nodes")
    if np.any(aa == bb):
        raise InputError(f"node {int(aa[aa == bb][0])} ranges to itself")
    if not np.isfinite(y).all():
        raise InputError("ranges must be finite")
    sd = None if std is None else np.asarray(std, float)
    if sd is not None and (sd.shape != y.shape or not np.all(sd > 0) or not np.isfinite(sd).all()):
        raise InputError("std must be finite, > 0 and one per measurement")
    nm = tuple(str(k) for k in range(n)) if names is None else tuple(str(s) for s in names)
    if len(nm) != n:
        raise InputError(f"{len(nm)} names for {n} nodes")
    if known is not None and frame is not None:
        raise InputError("give either known positions or a reference frame, not both "
                         "(known positions already define the frame)")
    # references resolved before any work
    nodes = parse_known(known, n, 0, d, receiver_names=nm, source_names=(), partial=False) if known is not None else None
    refs = check_frame(frame, n, 0, receiver_names=nm, source_names=()) if frame is not None else None
    P = _pairs(aa.astype(np.intp), bb.astype(np.intp), y, sd)
    deg = np.bincount(np.concatenate([P.a, P.b]), minlength=n)
    few = np.flatnonzero(deg < d)
    if few.size:
        raise DegenerateGeometryError(
            f"node {nm[few[0]]} ranges to {int(deg[few[0]])} other node(s); in {d}-D a node needs at least "
            f"{d + 1} (d to be rigid, one more to be unique)", kind="unobservable-node")
    X0, route = _initial(P, n, d, rng)
    free = np.ones((n, d), bool)
    prior: tuple[Array, Array] | None = None
    info = FrameInfo("canonical", message="canonical gauge (no frame given)")
    if nodes is not None:
        ref = np.array([k.position for k in nodes], float)
        est = X0[[k.index for k in nodes]]
        stds = np.array([k.std or 0.0 for k in nodes])
        rank, spread = _affine_rank(ref)
        tiny = max(1e-3 * spread, 1e-9) if spread > 0 else 1e-3
        Rm, t = _rigid(est, ref, 1.0 / np.maximum(stds, tiny * 1e-3) ** 2, allow_reflection=rank == d)
        X0 = X0 @ Rm.T + t
        before = float(np.sqrt(np.mean(np.sum((X0[[k.index for k in nodes]] - ref) ** 2, axis=1))))
        mu, isd = np.full((n, d), np.nan), np.full((n, d), np.nan)
        for k in nodes:
            if k.std is None:
                X0[k.index] = k.position
                free[k.index] = False
            else:
                mu[k.index], isd[k.index] = k.position, 1.0 / k.std
        if np.isfinite(mu).any():
            prior = (mu, isd)
    elif refs is not None:
        X0 = _to_frame(X0, frame, nm)
        for role, axes in (("origin", range(d)), ("x", range(1, d)), ("xy", range(2, d))):
            if role in refs:
                free[refs[role][1], list(axes)] = False
    # without a std the priors need the noise: a first fit without them gives it
    if prior is not None and sd is None:
        X1, _, _ = _fit(X0, P, free, None)
        r1 = np.linalg.norm(X1[P.a] - X1[P.b], axis=1) - P.mean
        s1 = np.sqrt((float(np.sum(P.weight * r1**2)) + P.pe_ss) / max(y.size - int(free.sum()), 1))
        prior = (prior[0], prior[1] * s1)
        X0 = X1
    X, conv, nfev = _fit(X0, P, free, prior)
    n_pairs_all = P.mean.size
    flagged = np.zeros(n_pairs_all, bool)
    if outliers:
        # a soft-L1 fit at the noise scale (the repeats' spread when they have the dof, else
        # the residuals' MAD), flags on it, least squares on the inliers (fit.py's rule)
        from ..verdict.robust import noise_scale

        P_all = P
        e = np.sqrt(P.weight) * (P.mean - np.linalg.norm(X[P.a] - X[P.b], axis=1))
        scale = 1.0 if sd is not None else (np.sqrt(P.pe_ss / P.pe_dof) if P.pe_dof >= 10 and P.pe_ss > 0
                                            else noise_scale(e))
        Xr, _, it = _fit(X, P, free, prior, loss="soft_l1", f_scale=max(float(scale), 1e-12))
        nfev += it
        flagged = _flag_pairs(Xr, P_all, d, free, scale=float(scale))
        if flagged.any():
            P = _subset(P_all, ~flagged, aa.astype(np.intp), bb.astype(np.intp), y, sd)
            X, conv, it = _fit(Xr, P, free, prior)
            nfev += it
        y_in = ~flagged[P_all.pair_of]
    else:
        y_in = np.ones(y.size, bool)
    rp = np.linalg.norm(X[P.a] - X[P.b], axis=1) - P.mean
    lof_ss = float(np.sum(P.weight * rp**2))
    gauge = _gauge_modes(X, free) if prior is None else 0
    n_free = int(free.sum())
    dof = int(y_in.sum() - n_free + gauge + (0 if prior is None else int(np.isfinite(prior[0][free]).sum())))
    rss = lof_ss + P.pe_ss
    sigma = float(np.sqrt(rss / dof)) if dof > 0 else float("nan")
    chi2 = chi2_p = None
    if sd is not None:
        chi2 = rss
        chi2_p = float(chi2_dist.sf(rss, dof)) if dof > 0 else None
    scale = 1.0 if sd is not None else (sigma if np.isfinite(sigma) else 0.0)
    cov, moved, n_null = _covariance(X, P, free, None if prior is None else prior[1], scale)
    # undetermined: moved by a null direction beyond the gauge, or a 95 % region larger than
    # the whole node set (the rule of selfcal.toa.verdict.determinacy: such a position says nothing)
    flat, _ = _flat_within_errors(X, P, int(y_in.sum()))
    bad = (moved if n_null > gauge else np.zeros(n, bool)) | np.full(n, flat)
    undetermined = tuple(nm[k] for k in np.flatnonzero(bad))
    loose = tuple(nm[k] for k in np.flatnonzero(_region_larger_than_set(X, cov) & ~bad))
    mirrored = tuple(nm[k] for k in np.flatnonzero(_mirror_ambiguous(X, P, scale) & ~bad))
    cov[moved & (n_null > gauge)] = np.nan
    pe_sigma = float(np.sqrt(P.pe_ss / P.pe_dof)) if P.pe_dof > 0 else None
    lof_F = lof_p = None
    lof_dof = P.mean.size - n_free + gauge
    if P.pe_dof > 0 and lof_dof > 0 and P.pe_ss > 0:
        lof_F = (lof_ss / lof_dof) / (P.pe_ss / P.pe_dof)
        lof_p = float(f_dist.sf(lof_F, lof_dof, P.pe_dof))
    if nodes is not None:
        ref = np.array([k.position for k in nodes], float)
        after = float(np.sqrt(np.mean(np.sum((X[[k.index for k in nodes]] - ref) ** 2, axis=1))))
        info = _known_info(nodes, _affine_rank(ref)[0], d, before, after, [])
    elif refs is not None:
        info = _frame_info(frame, nm, d)
    else:
        from ...geometry import canonical_gauge, rotate_covariances

        X, _, al = canonical_gauge(X)
        cov = rotate_covariances(cov, al.rotation)
    return GraphResult(
        names=nm, positions=X, position_cov=cov, residuals=y - np.linalg.norm(X[aa] - X[bb], axis=1),
        residual_rms=float(np.sqrt(np.mean((y - np.linalg.norm(X[aa] - X[bb], axis=1)) ** 2))),
        noise_estimate=sigma, dof=dof, n_measurements=int(y.size), n_pairs=int(n_pairs_all),
        pure_error_sigma=pe_sigma, pure_error_dof=P.pe_dof, lack_of_fit_F=lof_F, lack_of_fit_p=lof_p,
        chi2=chi2, chi2_p=chi2_p, undetermined_nodes=undetermined, poorly_determined_nodes=loose,
        mirror_ambiguous_nodes=mirrored,
        outliers=~y_in, outlier_pairs=int(flagged.sum()), converged=conv, iterations=nfev,
        method=f"graph:{route}+lsq", frame=info)


@dataclass(frozen=True)
class _Nodes:
    """The minimal result record :func:`selfcal.toa.frame.frame.apply_frame` reads."""

    receivers: Array
    sources: Array
    receiver_cov: Array
    source_cov: Array
    method: str = "graph"


def _to_frame(X: Array, frame: Any, names: tuple[str, ...]) -> Array:
    from ..frame.frame import apply_frame

    n, d = X.shape
    rec = _Nodes(X, np.zeros((0, d)), np.full((n, d, d), np.nan), np.zeros((0, d, d)))
    return np.asarray(apply_frame(rec, frame, receiver_names=names, source_names=()).receivers)


def _frame_info(frame: Any, names: tuple[str, ...], d: int) -> FrameInfo:
    from ..frame.frame import apply_frame

    # the message of apply_frame (what the references fixed) on a throw-away configuration
    rng = np.random.default_rng(0)
    n = len(names)
    X = rng.standard_normal((n, d))
    rec = _Nodes(X, np.zeros((0, d)), np.full((n, d, d), np.nan), np.zeros((0, d, d)))
    return dataclasses.replace(apply_frame(rec, frame, receiver_names=names, source_names=()).frame)


def simulate_range_graph(anchors: Any, tags: Any = None, *, noise: float = 0.02, repeats: int = 1,
                         anchor_pairs: bool = True, tag_ranges: bool = True,
                         rng: int | np.random.Generator | None = 0) -> tuple[Index, Index, Array]:
    """Simulated UWB measurements: anchor-to-anchor and anchor-to-tag ranges, each repeated.

    Parameters
    ----------
    anchors : (k, d) positions; tags : (t, d) positions or None.
    noise : range noise std (m); repeats : measurements per pair.
    anchor_pairs : include every anchor-anchor pair; tag_ranges : every anchor-tag pair.
    rng : seed or generator.

    Returns
    -------
    (a, b, ranges): nodes 0..k-1 are the anchors, k.. the tags.

    Examples
    --------
    >>> a, b, y = simulate_range_graph(np.eye(3) * 4, np.ones((2, 3)), repeats=2, rng=0)
    >>> a.size, int(a.max()), int(b.max())
    (18, 2, 4)
    """
    A = np.asarray(anchors, float)
    T = np.zeros((0, A.shape[1])) if tags is None else np.asarray(tags, float)
    X = np.vstack([A, T])
    k = A.shape[0]
    pairs: list[tuple[int, int]] = []
    if anchor_pairs:
        pairs += [(int(u), int(v)) for u, v in zip(*np.triu_indices(k, 1), strict=True)]
    if tag_ranges:
        pairs += [(i, k + j) for j in range(T.shape[0]) for i in range(k)]
    if not pairs:
        raise InputError("no pairs to simulate")
    p = np.array(pairs, np.intp)
    p = np.repeat(p, int(repeats), axis=0)
    g = np.random.default_rng(rng)
    y = np.linalg.norm(X[p[:, 0]] - X[p[:, 1]], axis=1) + g.normal(0, noise, p.shape[0])
    return p[:, 0].copy(), p[:, 1].copy(), y
