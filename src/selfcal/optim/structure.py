"""The one place that decides how a least-squares problem's linear systems are solved.

Every size threshold of the refinements is here, each with the measurement behind it:

* :func:`lm_step` -- the step solver of a driver model with the bipartite (node-block)
  structure of the range models: ``"dense"`` (the full normal matrix, dense Cholesky) up to
  :data:`DENSE_MAX_UNKNOWNS` unknowns; above, the Schur complement onto the smaller node set,
  ``"reduced"`` (formed, Cholesky) while forming it is cheap, else ``"cg"`` (matrix-free,
  Schur-Jacobi preconditioned). The TOA engine (:mod:`selfcal.toa.engine.schur_lm`), the search's
  rungs (:mod:`selfcal.toa.search`) and the constrained engine's choice between SciPy's dense
  trust region and the Schur engine (:mod:`selfcal.toa.engine.constrained`) all ask it; so does
  :class:`selfcal.optim.steps.ResidualModel` with ``step="auto"`` (the range-graph fit),
  whose non-dense answer is the sparse normal equations factored by SuperLU (a graph has no
  bipartite split to take a Schur complement over).
* :data:`TRF_EXACT_MAX` -- SciPy ``least_squares(method="trf")`` (the reference path and the
  robust constrained fits): its dense ``tr_solver="exact"`` (an SVD of the Jacobian per
  iteration) up to this many unknowns, ``"lsmr"`` above. Not a dense-vs-Schur choice (trf has
  no Schur step); its cost is O(m n^2) per iteration against O(n^3 / 3) for our dense
  Cholesky step, so its crossover is its own.
* :data:`DENSE_COVARIANCE_MAX` -- the determinacy test's dense inverse of the normal matrix
  (once per fit, not per iteration).
* :data:`FARFIELD_DIRECT_MAX`, :data:`FARFIELD_COV_MAX` -- the far-field LM (its step is always
  a Schur complement over the smaller side; direct up to this size, CG above).
"""

from __future__ import annotations

__all__ = ["DENSE_COVARIANCE_MAX", "FARFIELD_COV_MAX", "FARFIELD_DIRECT_MAX", "DENSE_MAX_UNKNOWNS", "DIRECT_MAX_ENTRIES", "DIRECT_MAX_FLOPS",
           "DIRECT_MAX_UNKNOWNS", "TRF_EXACT_MAX", "lm_step"]

#: problems of at most this many unknowns in all take the dense step (the full normal matrix
#: formed once per iteration and Cholesky-factorised per damping trial). Measured per iteration
#: on square dense networks (``benchmarks/bench_toa_minimal.py --engine``): below ~120 unknowns
#: the Schur step's bookkeeping (layout split, gauge basis, block inverses) costs more than the
#: O(n^3 / 3) factorisation it saves (12 x 6 with both offsets, 72 unknowns: 0.23 ms dense
#: against 0.67 ms Schur per iteration)
DENSE_MAX_UNKNOWNS = 120
#: reduced systems of at most this many unknowns (kept nodes x block size) are formed and
#: solved directly instead of by preconditioned CG (measured crossover of the same benchmark:
#: at 12 x 6 with both offsets a CG step costs ~150 matrix-free products for 24 unknowns) ...
DIRECT_MAX_UNKNOWNS = 200
#: ... and only while forming S stays cheap: (nK mK)^2 (nE mE) multiply-adds and
#: (nK mK) (nE mE) doubles for the dense coupling array (32 MB)
DIRECT_MAX_FLOPS = 1e8
DIRECT_MAX_ENTRIES = 4e6
#: SciPy trf's dense trust-region solver up to this many unknowns, lsmr above
TRF_EXACT_MAX = 600
#: unknowns up to which the determinacy test forms and inverts the dense normal matrix
#: (O(n^3): ~0.1 s at 1000 on one core, against solves of several seconds there)
DENSE_COVARIANCE_MAX = 1000


#: far-field LM (:mod:`selfcal.tdoa.lm`, the product of spheres, always a Schur step):
#: largest reduced system solved directly; above it the LM step uses preconditioned
#: conjugate gradients with O(m k) matrix-vector products instead. Forming the reduced system
#: costs O(n^2 p k) (n its size, p k the other side's unknowns) and factoring it O(n^3);
#: measured in bench_farfield (CPU seconds, same start, same final cost): 500 x 1000 (n = 1497)
#: 4.4 s direct against 1.9 s CG, 2000 x 200 (n = 600) 2.1 s against 1.3 s, so the direct
#: solve is kept only for small reduced systems (48 x 540: n = 141)
FARFIELD_DIRECT_MAX = 500
#: largest reduced system for which :func:`selfcal.tdoa.refine_lm` computes the covariance by default
#: (n = 2000: 32 MB and a few seconds of one core for the O(n^3) inverse)
FARFIELD_COV_MAX = 2000


def lm_step(n: int, n_kept: int | None = None, n_elim: int | None = None) -> str:
    """The step solver of a node-structured LM problem: "dense", "reduced" or "cg".

    Parameters
    ----------
    n : unknowns in all.
    n_kept, n_elim : unknowns of the kept (smaller) and eliminated node sets of the Schur
        complement (None: only the dense-or-not question is asked, answered "dense" or
        "reduced").

    Examples
    --------
    >>> lm_step(72), lm_step(300, 60, 240), lm_step(5000, 2000, 3000)
    ('dense', 'reduced', 'cg')
    """
    if n <= DENSE_MAX_UNKNOWNS:
        return "dense"
    if n_kept is None or n_elim is None:
        return "reduced"
    if (n_kept <= DIRECT_MAX_UNKNOWNS and n_kept * n_kept * n_elim <= DIRECT_MAX_FLOPS
            and n_kept * n_elim <= DIRECT_MAX_ENTRIES):
        return "reduced"
    return "cg"
