"""Do the data determine the fitted TOA geometry? The determinacy test of every result.

- :func:`set_scale`: the robust RMS radius of a node set (the yardstick).
- :func:`fisher_blocks`: each node's position covariance at the estimate, in the gauge of
  the well-placed nodes (weighted S-transformation), infinite along directions the data do
  not determine (dense, small networks).
- :func:`determinacy_test` / :class:`DeterminacyTest`: a node is undetermined when its 95 %
  confidence semi-axis exceeds its set's radius; the verdict rule (fail when most nodes are
  undetermined or the determined ones alone are not identifiable, else name them).

:func:`selfcal.toa.solve_toa` runs it after the fit test (:mod:`selfcal.toa.fit`) and
reports it as ``determinacy`` (``undetermined_receivers`` / ``undetermined_sources``).
Split from :mod:`selfcal.toa.verdict.trust` (which re-exports the names) to keep both below ~600
lines. Measured rates: ``benchmarks/bench_toa_determined.py`` and docs/design.md.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..._result import json_float as _num
from ...optim.structure import DENSE_COVARIANCE_MAX

__all__ = [
    "DENSE_MAX_UNKNOWNS",
    "DETERMINED_LEVEL",
    "UNDETERMINED_FAIL_FRACTION",
    "DeterminacyTest",
    "determinacy_test",
    "fisher_blocks",
    "set_scale",
]

Array = NDArray[np.float64]


#: confidence level of the determinacy test's per-node region
DETERMINED_LEVEL = 0.95
#: the result fails its test when more than this fraction of the tested nodes is undetermined
UNDETERMINED_FAIL_FRACTION = 0.5
#: nodes per chunk of the pairwise distances of :func:`set_scale` (memory chunk x n doubles)
_SCALE_CHUNK = 512


@dataclass(frozen=True)
class DeterminacyTest:
    """Does the data determine the fitted geometry? Each node's confidence region against its set's size.

    A node is *undetermined* when the largest semi-axis of its 95 % confidence ellipsoid
    (from the result's own gauge-free covariance, 003 eq. 17 at the estimate),
    ``extent_n = sqrt(chi2_d^-1(0.95) * lambda_max(C_n))``, exceeds the size of its node set
    (:func:`set_scale`, the robust RMS radius of the receivers or of the sources): the data
    then cannot place the node inside the array it belongs to, so its position (which side
    of the others, which of the mirror / far-field minima) is not known. Scale-free: a rigid
    motion or a change of units changes neither side's ratio.

    Verdict: ``failed`` when more than :data:`UNDETERMINED_FAIL_FRACTION` (half) of the
    tested nodes are undetermined (the geometry as a whole is not determined), or when the
    determined nodes do not form a network their own ranges can identify (the count
    condition of :func:`selfcal._checks.check_toa_counts` on the determined receivers x
    determined sources: d + 1 of each, at least as many ranges as unknowns): their
    placement then rests on nodes the data do not place. Either way the result fails its
    own test. Otherwise the result keeps its status and names the undetermined nodes (a
    warning): those are not to be used, the rest is determined.

    Attributes
    ----------
    receiver_extent, source_extent: (I,), (J,) 95 % semi-axes (metres); NaN where the node
        was dropped or its covariance block was not computed.
    receiver_scale, source_scale: sizes of the two node sets (metres, :func:`set_scale`).
    undetermined_receivers, undetermined_sources: (I,), (J,) bool masks.
    level: the confidence level (0.95).
    noise: the noise std the covariance is scaled to (matrix units of the fit, metres).
    noise_source: "given" (the caller's ``noise``) or "estimated" (the fit's residuals).
    tested: nodes with a finite covariance block.
    failed: more than half of the tested nodes are undetermined, or the determined core is
        not identifiable by its own ranges.
    skipped: why nothing was tested (e.g. ``covariance=False``), else None.
    core: why the determined nodes are not an identifiable network (None when they are, or
        when no observation mask was given).
    """

    receiver_extent: Array
    source_extent: Array
    receiver_scale: float
    source_scale: float
    undetermined_receivers: NDArray[np.bool_]
    undetermined_sources: NDArray[np.bool_]
    level: float
    noise: float
    noise_source: str
    tested: int
    failed: bool
    skipped: str | None = None
    core: str | None = None

    @property
    def n_undetermined(self) -> int:
        """Number of undetermined nodes (receivers + sources)."""
        return int(self.undetermined_receivers.sum() + self.undetermined_sources.sum())

    def names(self, receiver_names: Any = None, source_names: Any = None) -> str:
        """``"receivers 0, 3; sources 5"``: the undetermined nodes (caller's numbering, or the
        given node names, e.g. the matrix's own)."""
        parts = []
        for label, mask, nm in (("receivers", self.undetermined_receivers, receiver_names),
                                ("sources", self.undetermined_sources, source_names)):
            idx = np.flatnonzero(mask)
            if idx.size:
                def show(i: int, nm: Any = nm) -> str:
                    return str(nm[i]) if nm is not None and i < len(nm) else str(i)

                shown = ", ".join(show(int(i)) for i in idx[:12]) + (f", ... ({idx.size})" if idx.size > 12 else "")
                parts.append(f"{label} {shown}")
        return "; ".join(parts)

    def embedded(self, keep_receivers: Any = None, keep_sources: Any = None) -> DeterminacyTest:
        """The test written into a larger numbering (a recipe that fitted a subset of columns).

        Parameters
        ----------
        keep_receivers, keep_sources: (I_full,), (J_full,) bool masks of the rows / columns
            this test's nodes are, in order; None = unchanged.

        Returns
        -------
        DeterminacyTest with NaN extents and False flags at the other positions.
        """
        import dataclasses

        def put(a: Any, keep: Any, fill: Any) -> Any:
            if keep is None:
                return a
            k = np.asarray(keep, bool)
            out = np.full(k.shape, fill, dtype=np.asarray(a).dtype)
            out[k] = a
            return out

        return dataclasses.replace(
            self, receiver_extent=put(self.receiver_extent, keep_receivers, np.nan),
            source_extent=put(self.source_extent, keep_sources, np.nan),
            undetermined_receivers=put(self.undetermined_receivers, keep_receivers, False),
            undetermined_sources=put(self.undetermined_sources, keep_sources, False))

    def to_dict(self) -> dict[str, Any]:
        """JSON-safe dict (extents and scales in metres)."""
        def lst(a: Array) -> list[float | None]:
            return [_num(v) for v in np.asarray(a, float)]

        return {"test": "determinacy", "level": float(self.level), "noise": _num(self.noise),
                "noise_source": self.noise_source, "receiver_scale": _num(self.receiver_scale),
                "source_scale": _num(self.source_scale), "receiver_extent": lst(self.receiver_extent),
                "source_extent": lst(self.source_extent),
                "undetermined_receivers": [int(i) for i in np.flatnonzero(self.undetermined_receivers)],
                "undetermined_sources": [int(j) for j in np.flatnonzero(self.undetermined_sources)],
                "n_undetermined": self.n_undetermined, "tested": int(self.tested),
                "fail_fraction": UNDETERMINED_FAIL_FRACTION, "failed": bool(self.failed), "skipped": self.skipped,
                "core": self.core}


def set_scale(points: Any) -> float:
    """Robust RMS radius of a node set: ``median_a median_{b != a} |x_a - x_b| / sqrt(2)`` (metres).

    For any set the RMS pairwise distance is ``sqrt(2)`` times the RMS distance from the
    centroid, so this is the RMS radius with both means replaced by medians: invariant under
    rigid motions and relabelling, and not inflated by a few nodes placed far away (a
    far-field source of a bad fit would otherwise set the scale it is judged by). Rows with
    NaN are ignored; O(n^2) time in chunks of :data:`_SCALE_CHUNK` rows.

    Parameters
    ----------
    points: (n, d) positions.

    Returns
    -------
    float; NaN with fewer than two finite rows.

    Examples
    --------
    >>> import numpy as np
    >>> round(set_scale(np.array([[0.0, 0], [1, 0], [0, 1], [1, 1]])), 4)
    0.7071
    """
    P = np.asarray(points, dtype=float)
    P = P[np.isfinite(P).all(axis=1)]
    n = P.shape[0]
    if n < 2:
        return float("nan")
    med = np.empty(n)
    # each row's smallest distance is the node to itself (0): the median of the n - 1 others
    # is taken at sorted positions 1 + (n - 2) // 2 and 1 + (n - 1) // 2 (equal when n - 1 is odd)
    k1, k2 = 1 + (n - 2) // 2, 1 + (n - 1) // 2
    for a in range(0, n, _SCALE_CHUNK):
        D = np.linalg.norm(P[a:a + _SCALE_CHUNK, None, :] - P[None, :, :], axis=-1)
        D = np.partition(D, sorted({0, k1, k2}), axis=1)
        med[a:a + D.shape[0]] = 0.5 * (D[:, k1] + D[:, k2])
    return float(np.median(med) / math.sqrt(2.0))


def determinacy_test(receivers: Any, sources: Any, receiver_cov: Any, source_cov: Any, *,
                     noise: float = float("nan"), cov_scale: float = 1.0, noise_source: str = "estimated",
                     level: float = DETERMINED_LEVEL, skipped: str | None = None, observed: Any = None,
                     offsets: str = "none") -> DeterminacyTest:
    """Test whether the data determine each fitted node (:class:`DeterminacyTest` states the rule).

    Parameters
    ----------
    receivers, sources: (I, d), (J, d) fitted positions (metres; NaN rows = dropped nodes).
    receiver_cov, source_cov: (I, d, d), (J, d, d) the fit's gauge-free covariances (m^2;
        NaN blocks are not tested, blocks with an infinite entry are undetermined).
    noise: the noise std the covariances are expressed at (for the report).
    cov_scale: factor applied to the covariances first: ``(noise_given / sigma_fit)^2`` when
        the caller gave the noise (the fit's covariances are scaled by its own estimate).
    noise_source: "given" or "estimated".
    level: confidence level of the per-node region.
    skipped: a reason to test nothing (the covariance was not computed).
    observed: optional (I, J) bool, the entries the fit used: enables the core check (the
        determined nodes must be identifiable from their own ranges, model ``offsets``).
    offsets: the fitted offsets mode (for the core check).

    Returns
    -------
    DeterminacyTest

    Notes
    -----
    Cost: one ``d x d`` eigenvalue problem per node and the O(n^2) scales of
    :func:`set_scale`; no covariance is computed here (what the fit computed is used, so
    ``covariance=False`` or ``"local"`` is what the test sees).

    Examples
    --------
    >>> import numpy as np
    >>> r = np.array([[0.0, 0], [4, 0], [0, 4], [4, 4]])
    >>> t = determinacy_test(r, r + 1, np.tile(np.eye(2) * 1e-4, (4, 1, 1)),
    ...                      np.tile(np.eye(2), (4, 1, 1)) * np.array([1e-4, 1e-4, 1e-4, 400])[:, None, None])
    >>> t.names(), t.failed
    ('sources 3', False)
    """
    from scipy.stats import chi2

    R, S = np.asarray(receivers, float), np.asarray(sources, float)
    Cr, Cs = np.asarray(receiver_cov, float), np.asarray(source_cov, float)
    d = R.shape[1]
    q = float(chi2.ppf(level, d))
    rho_r, rho_s = set_scale(R), set_scale(S)

    def extent(P: Array, C: Array) -> Array:
        out = np.full(P.shape[0], np.nan)
        flat = C.reshape(C.shape[0], -1)
        inf = np.isfinite(P).all(axis=1) & ~np.isnan(flat).any(axis=1) & np.isinf(flat).any(axis=1)
        ok = np.isfinite(P).all(axis=1) & np.isfinite(flat).all(axis=1)
        if skipped is None and ok.any():
            lam = np.linalg.eigvalsh(0.5 * (C[ok] + np.swapaxes(C[ok], 1, 2)))[:, -1]
            out[ok] = np.sqrt(q * float(cov_scale) * np.maximum(lam, 0.0))
        if skipped is None:
            out[inf] = np.inf  # a direction the data do not determine at all (singular_blocks)
        return out

    er, es = extent(R, Cr), extent(S, Cs)
    with np.errstate(invalid="ignore"):
        ur = ~np.isnan(er) & (er > rho_r) if np.isfinite(rho_r) else np.zeros(er.shape, bool)
        us = ~np.isnan(es) & (es > rho_s) if np.isfinite(rho_s) else np.zeros(es.shape, bool)
    tested = int((~np.isnan(er)).sum() + (~np.isnan(es)).sum())
    n_bad = int(ur.sum() + us.sum())
    failed = bool(tested > 0 and n_bad > UNDETERMINED_FAIL_FRACTION * tested)
    core = None
    if observed is not None and n_bad and skipped is None:
        from ..._checks import check_toa_counts
        from ...errors import DegenerateGeometryError

        kr = np.isfinite(R).all(axis=1) & ~ur
        ks = np.isfinite(S).all(axis=1) & ~us
        sub = np.asarray(observed, bool)[np.ix_(kr, ks)]
        try:
            check_toa_counts(sub.shape, int(sub.sum()), d, offsets)
        except DegenerateGeometryError as exc:
            core = f"the determined nodes alone are not identifiable: {exc.args[0]}"
            failed = True
    if skipped is None and tested == 0:
        skipped = "no covariance block is finite (no redundant measurement, or none was computed)"
    return DeterminacyTest(er, es, rho_r, rho_s, ur, us, float(level), float(noise), noise_source, tested,
                           failed, skipped, core)


#: unknowns up to which :func:`fisher_blocks` forms and inverts the dense normal matrix;
#: larger networks use the fit's own covariance blocks (minimum-norm gauge); the value and its
#: reason are in :mod:`selfcal.optim.structure`
DENSE_MAX_UNKNOWNS = DENSE_COVARIANCE_MAX
#: eigenvalues of the gauge-lifted normal matrix below this fraction of the largest are
#: directions the data do not determine at all (the relative cut of ``leverage._normal_pinv``)
SINGULAR_RCOND = 1e-12
#: a node moves along an undetermined direction when its squared share of the unit
#: eigenvector exceeds this (eigenvector noise is ~sqrt(eps) ~ 1e-8 in amplitude)
SINGULAR_SHARE = 1e-8


def fisher_blocks(ranges: Any, receivers: Any, sources: Any, receiver_offsets: Any, source_offsets: Any,
                  offsets: str, sigma: float) -> tuple[Array, Array] | None:
    """Position covariance blocks at the estimate in the gauge of the well-placed nodes.

    The fit's covariance is the Moore-Penrose inverse ``sigma^2 N^+`` (003 eq. 17), the
    gauge in which *all* coordinates have minimum norm. One nearly undetermined node (a
    source far away, whose range trades with its onset) then drags the whole network: its
    error of, say, 100 m is shared out as a translation of every node by ~100 m / n, and
    every node looks undetermined. The determinacy test uses the weighted inner constraints
    instead (Baarda's S-transformation): the gauge component is removed so that
    ``G^T W dx = 0``, ``G`` the gauge generators (:func:`selfcal.toa.engine.nls.gauge_basis`: rigid
    motions, the common offset shift), ``W`` each node's weight ``1 / tr(C_n|rest)``, the
    inverse of its *conditional* variance (its own information block inverted: how well
    the node is placed by the others). A far-field source weighs ~0 and no longer sets the
    frame; on a network of similar nodes this is the minimum-norm gauge.

    ``N = J^T J`` (003 eq. 16) is lifted, ``M = N + c Q Q^T`` (``c`` its largest
    diagonal entry): ``M^-1`` differs from ``N^+`` only along the gauge, which the
    S-transformation ``T = I - G (G^T W G)^-1 G^T W`` removes. A singular M (cond above
    1 / :data:`SINGULAR_RCOND`) is eigendecomposed: the directions below the cut give the
    nodes they move (squared share above :data:`SINGULAR_SHARE`) an infinite variance.

    Parameters
    ----------
    ranges: (I, J) the entries the fit used (NaN elsewhere).
    receivers, sources, receiver_offsets, source_offsets: the fit (metres; offsets or None).
    offsets: the offsets mode.
    sigma: range noise std (metres).

    Returns
    -------
    (Cr, Cs): (I, d, d), (J, d, d) blocks (m^2; ``inf`` diagonal for nodes moved by an
    undetermined direction), or None above :data:`DENSE_MAX_UNKNOWNS` unknowns.
    """
    from .leverage import normal_equations

    r, s = np.asarray(receivers, float), np.asarray(sources, float)
    I, d = r.shape
    J = s.shape[0]
    has_r, has_s = offsets in ("receivers", "both"), offsets in ("sources", "both")
    n = (I + J) * d + (I if has_r else 0) + (J if has_s else 0)
    if n > DENSE_MAX_UNKNOWNS:
        return None
    # J^T J and its lifted inverse: those of the final fit's leverages (leverage.normal_equations)
    ne = normal_equations(np.isfinite(np.asarray(ranges, float)), r, s, receiver_offsets, source_offsets, offsets)
    Q = ne.Q
    # the parameters of each node: d coordinates (+ its offset)
    node = np.concatenate([np.repeat(np.arange(I), d), I + np.repeat(np.arange(J), d),
                           np.arange(I) if has_r else np.zeros(0, int),
                           I + np.arange(J) if has_s else np.zeros(0, int)]).astype(np.intp)
    blk = ne.block()  # the bipartite generalised inverse (bipartite.BipartiteInverse), else the lifted one
    diag = None if blk is None else blk.diagonal_blocks()
    w = np.zeros(I + J)
    # each node's information block inverted (its conditional covariance), one side at a time
    # (the blocks of a side have one size); a singular block falls back to the node-by-node loop
    for side, (first, count) in enumerate(((0, I), (I, J))):
        if not count:
            continue
        if diag is not None:
            Nb = diag[2 + side]
        else:
            idx = np.stack([np.flatnonzero(node == k) for k in range(first, first + count)])
            Nb = ne.N[idx[:, :, None], idx[:, None, :]]
        try:
            tr = np.trace(np.linalg.inv(Nb)[:, :d, :d], axis1=1, axis2=2)
            w[first:first + count] = np.where(np.isfinite(tr) & (tr > 0), 1.0 / np.where(tr > 0, tr, 1.0), 0.0)
        except np.linalg.LinAlgError:
            for k in range(first, first + count):
                try:
                    t = float(np.trace(np.linalg.inv(Nb[k - first])[:d, :d]))
                    w[k] = 1.0 / t if np.isfinite(t) and t > 0 else 0.0
                except np.linalg.LinAlgError:
                    w[k] = 0.0
    Wd = w[node]
    GW = Q.T * Wd  # (g, n)
    K = np.linalg.lstsq(GW @ Q, GW, rcond=None)[0]  # (G^T W G)^-1 G^T W
    bad = np.zeros(n, bool)
    if diag is not None and blk is not None:
        # any generalised inverse G of N gives the same T G T^T (bipartite.BipartiteInverse)
        KC = blk.apply(np.asarray(K.T, dtype=float)).T  # K G (g, n), G symmetric
        Cbs = (diag[0][:, :d, :d], diag[1][:, :d, :d])
    else:
        # M = N + c Q Q^T, c N's largest diagonal entry (any c > 0 lifts the gauge; N's scale keeps
        # M well-conditioned), inverted once and shared with the final fit's leverages
        # (leverage.lifted_inverse)
        N = ne.N
        Cl, dl, c = ne.lifted()
        if Cl is not None and dl is not None and dl.min() > np.sqrt(SINGULAR_RCOND) * dl.max():
            C = Cl
        else:
            lam, V = np.linalg.eigh(N + (c or 1.0) * (Q @ Q.T))
            ok = lam > SINGULAR_RCOND * lam[-1]
            C = (V[:, ok] / lam[ok]) @ V[:, ok].T
            # the undetermined directions in the same gauge (orthogonal to the gauge they would
            # carry a translation of every node, ~1/n each), normalised
            Vn = V[:, ~ok] - Q @ (K @ V[:, ~ok])
            Vn /= np.maximum(np.linalg.norm(Vn, axis=0), np.finfo(float).tiny)
            bad = (Vn**2).sum(axis=1) > SINGULAR_SHARE
        KC = K @ C  # (g, n)
        Cbs = tuple(C[ix[:, :, None], ix[:, None, :]] for ix in
                    (np.arange(I)[:, None] * d + np.arange(d), I * d + np.arange(J)[:, None] * d + np.arange(d)))
    # diagonal blocks of T C T^T, T = I - Q K, without forming it: O(g n^2)
    KCK = KC @ K.T  # (g, g)
    s2 = float(sigma) ** 2

    def blocks(first: int, count: int, Cb: Array) -> Array:
        idx = first + np.arange(count)[:, None] * d + np.arange(d)  # (count, d)
        Qn = Q[idx]  # (count, d, g)
        X = np.einsum("nag,gnb->nab", Qn, KC[:, idx])
        B = (Cb - X - np.swapaxes(X, 1, 2) + np.einsum("nag,gh,nbh->nab", Qn, KCK, Qn)) * s2
        inf = bad[idx].any(axis=1)
        B[inf] = np.where(np.eye(d, dtype=bool), np.inf, 0.0)
        return B

    return blocks(0, I, Cbs[0]), blocks(I * d, J, Cbs[1])
