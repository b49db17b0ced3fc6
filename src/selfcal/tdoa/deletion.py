"""Gross-error test for small far-field matrices: deletion residuals of the far-field model itself.

The residual test of :func:`~selfcal.tdoa.screen.gross_error_screen` fits the unconstrained
structure ``P Q^T + 1 c^T`` (``3 (m + k - 3) + k`` unknowns) and needs a third of the entries
spare. The far-field model proper, ``z_i . n_j + C_j`` with unit ``n_j``, has ``k - 3`` fewer
unknowns (``3 (m - 1) + 3 k - 3``, paper 000 Theorem 1), and in small matrices that is most of
the redundancy: 5 x 7 has 1 spare entry for the structure but 5 for the model, 20 x 6 has 45 and
48. This module tests each entry against the model:

* **redundancy.** At a fit, entry ``(i, j)`` has leverage ``h_ij = g_ij^T (J^T J)^+ g_ij``
  (J the model's Jacobian over the kept entries, :func:`~selfcal.tdoa.model.farfield_jacobian`;
  the pseudo-inverse removes the rotation gauge) and redundancy ``1 - h_ij``; the redundancies
  add up to ``n - rank J`` (the spare measurements). Where ``1 - h_ij`` is ~0 an error in the
  entry is absorbed by the fit and no test can see it.
* **the test** (one entry at a time, the classical test for one outlier): the candidate is the
  entry with the largest studentised residual ``|r| / sqrt(1 - h)`` of a robust fit (the best
  of the leave-one-row-out and leave-one-column-out least-squares fits, extended by least
  median of squares and refined by a Cauchy M-estimate: :func:`_robust_fit`), so that a large
  error cannot hide by pulling a least-squares fit. The model is
  refitted by least squares *without* the candidate and its prediction error ``e`` compared
  with ``t sigma sqrt(1 + h)`` (``h`` the candidate's leverage as a prediction); sigma is
  ``noise_std`` (t: normal quantile) or ``sqrt(RSS / dof)`` of that fit (t: Student-t with dof
  = kept entries - rank J). ``t`` is the Bonferroni quantile at ``alpha / (2 n_test)`` over the
  ``n_test`` testable entries, so a clean matrix loses any entry with probability <= alpha
  whichever entry is the candidate (for a linear model the statistic is exactly the externally
  studentised residual). A flagged entry stays out and the next candidate is tested the same
  way, until one passes.
* **untestable** entries: the minimal detectable bias of entry ij (Baarda: the error detected
  with 80 % power) is ``sigma (t + 0.84) / sqrt(1 - h_ij)``; an entry whose minimal detectable
  bias exceeds the array's extent in the data (the largest ``|D_ij - mean_i D_ij|``) cannot be
  checked in any useful sense, and with unknown noise and fewer than 2 spare measurements none
  can (4 x 6: every entry). They are reported, never flagged.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from ..robust import TUNING, mad_std
from .degeneracy import fit_quadric, rank_threshold, top_svd
from .model import farfield_jacobian, farfield_residuals
from .structure import far_field_parameters

__all__ = ["DeletionScreen", "farfield_leverages", "deletion_screen", "POWER_Z", "SMALL_TAIL_DOF"]

Array = NDArray[np.float64]
Mask = NDArray[np.bool_]

#: normal quantile of the 80 % power of Baarda's minimal detectable bias
POWER_Z = 0.8416
#: degrees of freedom of the tail assumed by the small-matrix test (``tail="fitted"``): real
#: delay residuals have ML tails of about 5 dof (GCC-PHAT, the Pyramic file), 3 is the heaviest
#: tail the stated false-alarm rate is claimed for
SMALL_TAIL_DOF = 3.0


@dataclass(frozen=True)
class DeletionScreen:
    """Outcome of :func:`deletion_screen`.

    flags : (m, k) entries found gross; untestable : (m, k) entries that cannot be checked
    (redundancy ~0, see the module docstring); tested : whether the test could run at all.
    """

    flags: Mask
    untestable: Mask
    tested: bool


def farfield_leverages(Z: Array, N: Array, used: Mask) -> tuple[Array, int]:
    """Leverage of every entry in the least-squares far-field fit of the ``used`` entries: ``(h, rank)``.

    ``h`` (m, k): ``g_ij^T (J_u^T J_u)^+ g_ij`` with ``g_ij`` the gradient of ``z_i . n_j + C_j``
    (positions, unit directions on their tangent planes, offsets; first position fixed) and
    ``J_u`` the rows of the used entries. For a used entry ``1 - h`` is its redundancy (its
    residual variance is ``sigma^2 (1 - h)``); for one left out ``1 + h`` scales the variance of
    its prediction error. ``rank``: numerical rank of ``J_u`` (the number of parameters the
    data determine; the kept entries minus it are the spare measurements).

    Parameters
    ----------
    Z : (m, 3) positions (first row fixed as the gauge), N : (k, 3) unit directions (metres,
        unitless) -- the fit at which the model is linearised.
    used : (m, k) bool, the entries in the fit.

    Returns
    -------
    h : (m, k) leverages (in [0, 1] for used entries, >= 0 for the others); rank : int.

    Examples
    --------
    >>> import numpy as np
    >>> rng = np.random.default_rng(0)
    >>> Z, N = rng.normal(size=(6, 3)), rng.normal(size=(8, 3))
    >>> N /= np.linalg.norm(N, axis=1, keepdims=True)
    >>> h, rank = farfield_leverages(Z - Z[0], N, np.ones((6, 8), dtype=bool))
    >>> rank, round(float(np.sum(1 - h)), 6)     # 3 (m - 1) + 3 k - 3 parameters, 48 - 36 spare
    (36, 12.0)
    """
    m, k = used.shape
    J = farfield_jacobian(Z, N, free_offsets=True)
    Ju = J[used.ravel()]
    _, s, Vt = np.linalg.svd(Ju, full_matrices=False)
    rank = int(np.sum(s > 1e-10 * max(float(s[0]), 1e-300))) if s.size else 0
    G = J @ (Vt[:rank].T / s[:rank])  # (mk, rank): g^T V S^-1
    h = np.sum(G * G, axis=1).reshape(m, k)
    return h, rank


def _ls_fit(D: Array, used: Mask, Z: Array, N: Array, C: Array) -> tuple[Array, Array, Array]:
    from .lm import refine_lm

    out = refine_lm(D, Z, N, C, mask=used, free_offsets=True, loss="linear", max_iter=100, tol=1e-12,
                    covariance=False)
    return out.positions, out.directions, out.offsets


def _fit_submatrix(D: Array, used: Mask, *, require_pd: bool = False) -> tuple[Array, Array, Array, float] | None:
    """Least-squares far-field fit of the used entries from scratch: (Z, N, C, RSS / dof) or None."""
    import warnings

    from ..errors import ConvergenceWarning, DegenerateGeometryError, InputError
    from .solve import solve_unscreened

    rows, cols = used.any(axis=1), used.any(axis=0)
    sub = np.where(used, D, np.nan)[np.ix_(rows, cols)]
    if require_pd and np.isfinite(sub).all():
        # clean far-field data give a positive definite quadric B (section 2.3); a sub-matrix
        # whose B is not is skipped rather than fitted (its nonlinear fit of A is the slow part)
        # (and one without a third dimension, rank <= 2 by the nested rank test, is not 3-D at all)
        X = sub - sub.mean(axis=0)
        U, s, Vt = top_svd(X, 4)
        if len(s) < 3 or not s[2] > rank_threshold(X, 3, rows=X.shape[0] - 1, cols=X.shape[1], svd=(U, s, Vt)):
            return None
        B, _, _ = fit_quadric((s[:3, None] * Vt[:3]).T / max(float(s[0]), 1e-300))
        if not np.linalg.eigvalsh(B)[0] > 0:
            return None
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", ConvergenceWarning)
            res = solve_unscreened(sub, method="lm", offsets="free")
    except (InputError, DegenerateGeometryError, np.linalg.LinAlgError):
        return None
    if not (np.isfinite(res.positions).all() and np.isfinite(res.directions).all()):
        return None
    ok = np.isfinite(sub)
    _, rank = farfield_leverages(res.positions, res.directions, ok)
    dof = int(ok.sum()) - rank
    if dof < 1:
        return None
    r = farfield_residuals(np.where(ok, sub, 0.0), res.positions, res.directions, res.offsets)[ok]
    Z = np.full((D.shape[0], 3), np.nan)
    N = np.full((D.shape[1], 3), np.nan)
    C = np.full(D.shape[1], np.nan)
    Z[rows], N[cols], C[cols] = res.positions, res.directions, res.offsets
    return Z, N, C, float(np.sum(r**2) / dof)


def _lmeds_row(y: Array, A: Array, n_par: int) -> Array:
    """Least median of squares solution of ``A x ~ y`` over every ``n_par``-subset of the rows."""
    from itertools import combinations

    best, best_med = None, np.inf
    for sub in combinations(range(len(y)), n_par):
        idx = list(sub)
        try:
            x = np.linalg.solve(A[idx], y[idx])
        except np.linalg.LinAlgError:
            continue
        med = float(np.median(np.abs(A @ x - y)))
        if med < best_med:
            best, best_med = x, med
    return np.asarray(best if best is not None else np.linalg.lstsq(A, y, rcond=None)[0], dtype=float)


def _robust_fit(D: Array, used: Mask, noise_std: float | None, extent: float,
                rng: np.random.Generator | int | None) -> tuple[Array, Array, Array] | None:
    """A fit one gross entry cannot pull: the best leave-one-row / leave-one-column-out fit.

    One gross entry (i, j) spoils every fit that contains it but neither the fit without row i
    nor the one without column j (paper 000: the far-field rank structure holds on every
    sub-matrix). The fits of the sub-matrices that stay identifiable (``m - 1 >= 4`` rows,
    ``k - 1 >= 6`` columns) are compared by their residual variance; the best one is extended
    to its left-out row (``z_i`` by least median of squares over every triple of its entries)
    or column (``(n_j, C_j)`` over every quadruple, then normalised), and a Cauchy
    M-estimate of the whole matrix starts from there.
    """
    from .lm import refine_lm

    m, k = D.shape
    best: tuple[Array, Array, Array, float] | None = None
    outs: list[tuple[str, int]] = [("row", i) for i in range(m) if m - 1 >= 4] + \
        [("col", j) for j in range(k) if k - 1 >= 6]
    for kind, idx in outs:
        u = used.copy()
        if kind == "row":
            u[idx] = False
        else:
            u[:, idx] = False
        fit = _fit_submatrix(D, u, require_pd=True)
        if fit is not None and (best is None or fit[3] < best[3]):
            best = fit
    if best is None:
        return None
    Z, N, C, _ = best
    Dz = np.where(used, D, np.nan)
    for i in np.flatnonzero(~np.isfinite(Z).all(axis=1)):
        ok = np.isfinite(Dz[i]) & np.isfinite(C)
        Z[i] = _lmeds_row(Dz[i, ok] - C[ok], N[ok], 3)
    for j in np.flatnonzero(~np.isfinite(N).all(axis=1)):
        ok = np.isfinite(Dz[:, j]) & np.isfinite(Z).all(axis=1)
        x = _lmeds_row(Dz[ok, j], np.column_stack([Z[ok], np.ones(int(ok.sum()))]), 4)
        N[j] = x[:3] / max(float(np.linalg.norm(x[:3])), 1e-300)
        C[j] = float(np.median(Dz[ok, j] - Z[ok] @ N[j]))
    if not (np.isfinite(Z).all() and np.isfinite(N).all() and np.isfinite(C).all()):
        return None
    C = C + N @ Z[0]
    Z = Z - Z[0]
    r = farfield_residuals(np.where(used, D, 0.0), Z, N, C)[used]
    scale = float(noise_std) if noise_std else float(mad_std(r, centre=False))
    scale = max(scale, 1e-9 * extent)
    out = refine_lm(D, Z, N, C, mask=used, free_offsets=True, loss="cauchy", delta=TUNING["cauchy"] * scale,
                    max_iter=200, tol=1e-12, covariance=False)
    if not (np.isfinite(out.positions).all() and np.isfinite(out.directions).all()):
        return None
    return out.positions, out.directions, out.offsets


def deletion_screen(
    D: Array,
    used: Mask,
    *,
    alpha: float,
    noise_std: float | None = None,
    rounds: int | None = None,
    rng: np.random.Generator | int | None = 0,
    tail: str = "fitted",
) -> DeletionScreen:
    """Test the ``used`` entries of a small 3-D far-field matrix one at a time (module docstring).

    Parameters
    ----------
    D : (m, k) relative distances (metres); only ``used`` entries are read.
    used : (m, k) bool, the entries to test (finite, not already flagged).
    alpha : family-wise false-alarm rate on clean data.
    noise_std : known noise standard deviation (metres) or None (estimated from the spare
        measurements).
    rounds : most entries flagged (default: half the spare measurements).
    rng : seed of the minimal-sample search (deterministic by default).
    tail : ``"fitted"`` (default): the null distribution of the studentised residual has the tail
        of a unit-variance Student-t with :data:`SMALL_TAIL_DOF` degrees of freedom (a small
        matrix has too few spare measurements to estimate its tail; the heaviest tail the stated
        rate is claimed for is assumed), widened by the Student-t factor of the estimated sigma;
        ``"gaussian"``: the Gaussian rule (Student-t on the spare measurements), whose false-alarm
        rate holds for Gaussian noise only.

    Returns
    -------
    DeletionScreen (flags and untestable entries among ``used``).
    """
    from scipy.stats import norm
    from scipy.stats import t as student

    D = np.asarray(D, dtype=float)
    used = np.asarray(used, dtype=bool).copy()
    m, k = D.shape
    none = np.zeros((m, k), dtype=bool)
    Dz = np.where(used, D, 0.0)
    colmean = Dz.sum(0) / np.maximum(used.sum(0), 1)
    extent = float(np.max(np.abs(np.where(used, D - colmean, 0.0)))) + 1e-300
    known = noise_std is not None and noise_std > 0
    sig_known = float(noise_std) if noise_std is not None else 0.0

    nu = SMALL_TAIL_DOF
    heavy = tail != "gaussian"

    def quantile(n_test: int, dof: int) -> float:
        a = alpha / (2.0 * max(n_test, 1))
        q = float(norm.isf(a)) if known else float(student.isf(a, max(dof, 1)))
        if heavy:  # the unit-variance t_nu quantile in place of the normal one
            q *= float(student.isf(a, nu)) / np.sqrt(nu / (nu - 2.0)) / float(norm.isf(a))
        return q

    # quick pass, enough for clean data: the least-squares fit of every entry and the
    # externally studentised residuals, in closed form (the deletion statistic of a linear
    # model); only a matrix with a suspect entry goes on to the robust fit and the deletions
    full = _fit_submatrix(D, used)
    if full is not None:
        Z, N, C, s2 = full
        h, rank = farfield_leverages(Z, N, used)
        # a fit whose Jacobian lost rank (a degenerate member of a distorted fit) leaves its
        # parameters undetermined, not spare measurements: count the model's parameters
        rank = max(rank, far_field_parameters(m, k))
        spare = int(used.sum()) - rank
        if spare < (1 if known else 2):
            return DeletionScreen(none, used.copy(), False)
        red = np.clip(1.0 - h, 0.0, 1.0)
        r = farfield_residuals(Dz, Z, N, C)
        sig = sig_known if known else float(np.sqrt(s2))
        q = quantile(int(used.sum()), spare - 1)
        unt = used & ((red <= 1e-9) | (sig * (q + POWER_Z) > extent * np.sqrt(red)))
        test = used & ~unt
        with np.errstate(divide="ignore", invalid="ignore"):
            if known:
                stat = np.abs(r) / (sig * np.sqrt(red))
            else:
                rss = float(np.sum(r[used] ** 2))
                s_del = (rss - r**2 / red) / (spare - 1)
                stat = np.where(s_del > 0, np.abs(r) / np.sqrt(np.maximum(s_del, 1e-300) * red), np.inf)
        if test.any() and float(np.max(stat[test])) <= q:
            return DeletionScreen(none, unt, True)
    # (no 3-D fit of the whole matrix: a planar array, a cone -- or a gross error that spoils it;
    # the robust fit below tells them apart: it fails too unless the rest is a 3-D far-field matrix)
    fit = _robust_fit(D, used, noise_std, extent, rng)
    if fit is None:
        return DeletionScreen(none, used.copy(), False)
    Z, N, C = fit
    h, rank = farfield_leverages(Z, N, used)
    spare = int(used.sum()) - max(rank, far_field_parameters(m, k))
    # with an estimated noise, the fit without the candidate needs >= 1 spare measurement
    if spare < (1 if known else 2):
        return DeletionScreen(none, used.copy(), False)
    red = np.clip(1.0 - h, 0.0, 1.0)
    r0 = np.abs(farfield_residuals(Dz, Z, N, C))
    sigma0 = sig_known if known else float(mad_std((r0 / np.sqrt(np.maximum(red, 1e-12)))[used & (red > 1e-6)],
                                                          centre=False))
    sigma0 = max(sigma0, 1e-12 * extent)
    q0 = quantile(int(used.sum()), spare - 1)
    untestable = used & ((red <= 1e-9) | (sigma0 * (q0 + POWER_Z) > extent * np.sqrt(red)))
    testable = used & ~untestable
    n_test = int(testable.sum())
    if n_test == 0:
        return DeletionScreen(none, untestable, False)
    flags = none.copy()
    max_rounds = max(spare // 2, 1) if rounds is None else int(rounds)
    stud = np.where(testable, r0 / np.sqrt(np.maximum(red, 1e-12)), -np.inf)
    for _ in range(max_rounds):
        c = np.unravel_index(int(np.argmax(stud)), stud.shape)
        if not np.isfinite(stud[c]):
            break
        used_c = used.copy()
        used_c[c] = False
        Zc, Nc, Cc = _ls_fit(D, used_c, Z, N, C)
        hc, rank_c = farfield_leverages(Zc, Nc, used_c)
        dof = int(used_c.sum()) - rank_c
        rc = farfield_residuals(Dz, Zc, Nc, Cc)
        if known:
            sigma = sig_known
        else:
            if dof < 1:
                break
            sigma = float(np.sqrt(np.sum(rc[used_c] ** 2) / dof))
        sigma = max(sigma, 1e-12 * extent)
        if not abs(rc[c]) > quantile(n_test, dof) * sigma * np.sqrt(1.0 + hc[c]):
            break
        flags[c] = True
        used, Z, N, C = used_c, Zc, Nc, Cc
        # next candidate: studentised residuals of the least-squares fit without the flagged entries
        redc = np.clip(1.0 - hc, 0.0, 1.0)
        stud = np.where(testable & used & (redc > 1e-9), np.abs(rc) / np.sqrt(np.maximum(redc, 1e-12)), -np.inf)
    return DeletionScreen(flags, untestable & ~flags, True)
