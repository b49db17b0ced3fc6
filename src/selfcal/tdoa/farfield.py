"""Far-field TDOA self-calibration (paper 000): the solver entry point.

``D_ij = z_i . n_j + C_j`` (rows = receiver positions, columns = far transmitters,
``|n_j| = 1``, C_j unknown per column). :func:`solve_farfield` recovers the positions (first
at the origin), the unit directions and the offsets:

1. gross-error screen (optional) and, when entries are missing or a robust loss is asked
   for, a weighted / robust fit of the structure ``D = P Q^T + 1 c^T`` (rank 3 plus
   offsets, :func:`~selfcal.tdoa.structure.lowrank_fit`) that fills (and, robustly, cleans) the matrix for the
   factorisation steps;
2. failure-mode analysis of ``Dbar`` (:mod:`selfcal.tdoa.degeneracy`);
3. overdetermined initialisation (section 2.3 (i)-(iii), :func:`~selfcal.tdoa.initialize.initialize_farfield`),
   with the nonlinear fit of A when the least-squares B is not positive definite;
4. refinement: Levenberg-Marquardt on the spheres (Algorithm 3) or alternating
   optimisation (Algorithm 2), with an optional robust loss.

Robustness (beyond the paper, its future work): with ``loss != "linear"`` the structured fit
and the refinement are iteratively re-weighted; entries whose final residual exceeds
``reject_k`` robust standard deviations are reported in ``rejected``. :func:`~selfcal.tdoa.structure.ransac_farfield`
additionally offers RANSAC over the minimal solver.

The pieces live one job per module: :mod:`.screen` (gross errors, robust structure fits,
RANSAC), :mod:`.orientation` (the transposed check), :mod:`.degeneracy` (failure modes),
:mod:`.initialize` (section 2.3), :mod:`.lm` / :mod:`.alternating` (Algorithms 3 / 2),
:mod:`.lowdim` (planar and linear arrays), :mod:`.semiblind` (known directions) and
:mod:`.result`. Steps 2-4 are
:func:`selfcal.tdoa.solve.solve_unscreened`, which the screen's deletion test re-runs on
sub-matrices; this module adds the screen (step 1) in front.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from .._checks import entry
from .result import FarfieldResult
from .screen import gross_error_screen
from .solve import solve_unscreened

__all__ = ["solve_farfield"]


@entry(matrix="array", f_scale="positive?", noise_std="positive?", max_iter="count?", tol="positive?",
       rng="rng", reject_k="positive", cone_tol="positive", allow_degenerate="bool", screen="bool",
       check_degeneracy="bool", ransac="bool")
def solve_farfield(
    matrix: Any,
    *,
    method: str = "auto",
    loss: str = "linear",
    f_scale: float | None = None,
    noise_std: float | None = None,
    offsets: str = "auto",
    direction_solver: str = "global",
    allow_degenerate: bool = False,
    screen: bool = True,
    reject_k: float = 4.0,
    max_iter: int | None = None,
    tol: float | None = None,
    cone_tol: float = 3.0,
    init_reference: str = "mean",
    check_degeneracy: bool = True,
    ransac: bool = False,
    rng: np.random.Generator | int | None = None,
    dim: int | str = 3,
    directions: Any = None,
) -> FarfieldResult:
    """Far-field TDOA self-calibration: positions, directions and offsets from D (paper 000).

    Parameters
    ----------
    matrix : (m, k) relative distances ``D_ij = z_i . n_j + C_j`` in metres (or any length
        unit; results come in the same unit). Rows = receiver positions (an antenna moved
        to m places, or m microphones), columns = k far transmitters. NaN = missing.
        Needs m >= 4 and k >= 6 for a full 3-D solution (Theorem 1).
    method : "lm" (Algorithm 3), "alternating" (Algorithm 2), "init" (section 2.3 only),
        "minimal" (Algorithm 1, 4 x 6 only) or "auto" ("minimal" for a complete 4 x 6
        matrix with the linear loss, else "lm").
    loss : "linear" (the paper's least squares) or a robust loss "huber", "soft_l1",
        "cauchy" (IRLS; then outliers are reported in ``rejected``).
    f_scale : robust loss scale (metres); default 1.345 (Huber, soft_l1) or 2.385 (Cauchy)
        x the robust noise estimate (1.4826 MAD of the residuals, dof-corrected).
    noise_std : known noise standard deviation of the entries (metres); used by the
        degeneracy thresholds (else estimated from the data).
    offsets : "reference" (C_j = D_1j, the paper's reduced cost), "free" (C_j estimated: the
        maximum-likelihood fit under i.i.d. noise on D) or "auto" (= "free"; it used to be
        "reference" for complete data with the linear loss, whose noise in row 1 is shared by every
        row: a less accurate estimate, and one that changed with whether the screen flagged anything).
    direction_solver : for "alternating": "global" or "local" (see :mod:`.refine`).
    allow_degenerate : return the partial reconstruction of a degenerate configuration
        (with ``degeneracy`` set) instead of raising.
    screen : treat gross errors (:func:`~selfcal.tdoa.screen.gross_error_screen`: a residual test at family-wise
        false-alarm rate 1 % against the Student-t tail fitted to the residuals, so the rate
        holds for heavy-tailed noise too) as missing.
    reject_k : with a robust loss, entries with ``|residual| > reject_k`` robust std are rejected.
    max_iter, tol : refinement limits (defaults 200 / 1e-12 for LM, 2000 / 1e-10 for
        alternating).
    cone_tol : threshold of the cone test (see :mod:`.degeneracy`).
    init_reference : per-column constant removed before the factorisation (Lemma 1):
        "mean" (column means; noise spread evenly, our default) or "first" (``D_1j``, the
        paper's Algorithm 1 step 1).
    check_degeneracy : run the failure-mode analysis and act on it (raise / partial result).
        With False the full 3-D pipeline runs regardless, as in the paper's experiments; the
        analysis is still reported in ``diagnostics`` but ``degeneracy`` stays None.
    ransac : screen outliers first with :func:`~selfcal.tdoa.structure.ransac_farfield` (RANSAC over the minimal
        solver); entries outside its inlier set are treated as missing and reported in
        ``rejected``. Combine with a robust loss for the best results.
    rng : random generator / seed (used by ``ransac``).
    dim : 3 (space, the paper), 2 (planar: positions and directions in one plane, e.g. a
        circular / rectangular board with sources around it in its plane; or any array with
        coplanar directions, whose positions are then seen projected onto that plane),
        1 (linear: positions on a line, or all directions parallel), or ``"auto"``: the
        numerical rank of the column-centred matrix against the noise (nested tests of rank
        r - 1 against r at false-alarm rate 1e-3, Tracy-Widom quantiles, in
        :func:`~selfcal.tdoa.analyse_degeneracy`) and, at rank 2, the
        consistency of the 2-D quadric (chi-square per dof of ``ntilde^T B2 ntilde = 1``)
        decide. What is determined (paper 000, section 2.2) is in ``result.determined``:
        planar -- the in-plane geometry up to a rotation / reflection of the plane (needs
        k >= 3 directions not all on two lines); linear -- the positions along the line up
        to one scale factor (reported with the largest ``|projection|`` of a direction = 1:
        the smallest array consistent with the data, exact when a source is at endfire);
        parallel directions -- the coordinate along the direction, scale included.
        Positions with the directions off their plane (``planar-motion``) are not determined
        (a 2 x 2 family) and raise in every mode.
    directions : optional (k, d) known unit directions n_j (d = 3 or 2; e.g. from a
        turntable's angles). Then the problem is linear (semi-blind calibration): positions
        and offsets by least squares, ``case = "known-directions"``, in the frame of the given
        directions (no rotation is left free). The only way to calibrate data whose blind
        problem is degenerate (a ``cone``: all sources at one elevation), provided the
        directions are right.

    Raises
    ------
    InputError
        Malformed matrix or options.
    DegenerateGeometryError
        ``kind`` = "too-few-receivers" / "too-few-sources", or one of the failure modes
        (with ``partial`` = the partial FarfieldResult) unless ``allow_degenerate``.

    Examples
    --------
    Eight receiver positions, twelve far-away transmitters, 0.1 mm noise:

    >>> import numpy as np
    >>> import selfcal
    >>> rng = np.random.default_rng(4)
    >>> Z = rng.normal(size=(8, 3))
    >>> N = rng.normal(size=(12, 3))
    >>> N /= np.linalg.norm(N, axis=1, keepdims=True)
    >>> D = Z @ N.T + rng.normal(size=12) + 1e-4 * rng.standard_normal((8, 12))
    >>> res = selfcal.solve_farfield(D)
    >>> res.success, res.degeneracy, res.positions.shape
    (True, None, (8, 3))
    >>> bool(res.residual_rms < 2e-4)
    True
    """
    return solve_unscreened(
        matrix, method=method, loss=loss, f_scale=f_scale, noise_std=noise_std, offsets=offsets,
        direction_solver=direction_solver, allow_degenerate=allow_degenerate, reject_k=reject_k,
        max_iter=max_iter, tol=tol, cone_tol=cone_tol, init_reference=init_reference,
        check_degeneracy=check_degeneracy, ransac=ransac, rng=rng, dim=dim, directions=directions,
        gross_screen=gross_error_screen if screen else None)
