"""The thesis iteration of paper 004 (sec. 3.5.1 / 3.7): alternating projection, Gamma = 0.

Kept faithful to the thesis (its thresholds in :mod:`.rank3_model`) as the reference of the
fast solver (:mod:`.rank3`) in the tests and in ``benchmarks/bench_delays.py``. Paper
reference code: the one iterative refinement of the package that does not run on the driver
(:mod:`selfcal.optim.lm`), on purpose -- its regularised update (3.23) with the lambda switch
is the thesis's algorithm, reproduced as published, not a damped least-squares loop.
"""

from __future__ import annotations

import time
from dataclasses import replace
from typing import Any

import numpy as np

from ..._checks import as_rng
from ...errors import InputError
from .rank3_model import (
    THESIS_LAM_SWITCH,
    THESIS_TOL,
    Array,
    Rank3Result,
    _random_p0,
    _result,
    _validate,
    _w_parts,
    apply_A,
    apply_Wt,
    thesis_T,
    thesis_W,
)

__all__ = ["rank3_iteration"]


def rank3_iteration(
    ranges: Any,
    *,
    dim: int = 3,
    lam: float = 0.0,
    lam_switch: float = THESIS_LAM_SWITCH,
    tol: float = THESIS_TOL,
    max_iter: int = 1_000_000,
    p0: Any = None,
    abort_above: float | None = None,
    almost_tol: float = 100 * THESIS_TOL,
    rng: np.random.Generator | int | None = None,
) -> Rank3Result:
    """The thesis iteration of 004 sec. 3.5.1 / 3.7 (Gamma = 0), one run from one initialisation.

    Per iteration n: ``T_hat = T + A(p)`` (3.12); best rank-d approximation ``T~ = U S_d V^T``
    by SVD (3.13); ``E = T~ - T`` (3.14); ``p <- (W^T W + lam I)^+ W^T C(E)`` (3.11/3.15, with
    lam > 0 the regularised update 3.23); ``F = ||E - A(p)||_F`` (3.17). While lam > 0 the
    monitored norm is ``||T + A(p)||_F`` (the listing) and lam is set to 0 once it changes by
    less than ``lam_switch``; with lam = 0 the run stops when F changes by less than ``tol``.
    The factorisation of W^T W is computed once (eigendecomposition, so the pseudo-inverse
    of 3.11 and every (W^T W + lam I)^-1 come from the same factors); W is never formed
    in the loop (``apply_A``, ``apply_Wt`` use its three non-zeros per row).

    Parameters
    ----------
    ranges : (I, J) times times the speed, metres, complete. Rows = receivers.
    dim : rank d of the geometry (3 as in the thesis, or 2).
    lam : regularisation lambda of (3.23), m^2 (``thesis_lambda`` converts the listing's value).
    lam_switch : threshold on the change of ``||T_hat||_F`` that sets lam to 0, m^2.
    tol : convergence threshold on the change of F (3.17), m^2 (thesis 1e-12 s^2).
    max_iter : maximum number of iterations (thesis 1e6).
    p0 : (I+J-1,) initial p in metres; default: thesis random initialisation from ``rng``.
    abort_above : the early abort the thesis proposes as future work (sec. 6.2): once F changes by
        less than ``almost_tol`` (almost converged) and F is still above ``abort_above``, the run
        heads for a local minimum and stops (``converged=False``, ``extra["aborted"]=True``), so
        that :func:`estimate_offsets` can restart it. None: never abort.
    almost_tol : the higher threshold on the change of F that says "almost converged", m^2.
    rng : seed or Generator for the initialisation.

    Returns
    -------
    Rank3Result with ``method="faithful"``, ``model="linear"``.
    """
    t0 = time.perf_counter()
    R = _validate(ranges, dim)
    I, J = R.shape
    K = I + J - 1
    if p0 is None:
        p = _random_p0(I, J, as_rng(rng))
    else:
        p = np.array(p0, dtype=float).reshape(-1)
        if p.shape != (K,):
            raise InputError(f"p0 must have I+J-1 = {K} entries, got {p.shape}")
    if lam < 0 or not np.isfinite(lam):
        raise InputError(f"lam must be finite and >= 0, got {lam}")
    T = thesis_T(R)
    W = thesis_W(R)
    evals, evecs = np.linalg.eigh(W.T @ W)
    cutoff = evals.max() * K * np.finfo(float).eps

    def solver(reg: float) -> Array:
        # (W^T W + reg I)^+ from the one eigendecomposition: the pseudo-inverse of (3.11) when reg = 0
        d = evals + reg
        inv = np.where(d > cutoff, 1.0 / np.where(d > cutoff, d, 1.0), 0.0)
        return (evecs * inv) @ evecs.T

    parts = _w_parts(R)  # W's entries do not change between iterations
    G = solver(lam)
    lam0 = float(lam)
    switched: int | None = None
    aborted = False
    A = apply_A(R, p, parts)
    hist: list[float] = []
    steps: list[float] = []
    F_prev = 0.0
    converged = False
    n = 0
    for n in range(1, int(max_iter) + 1):  # noqa: B007 (n is the iteration count after the loop)
        That = T + A
        U, s, Vt = np.linalg.svd(That, full_matrices=False)
        E = (U[:, :dim] * s[:dim]) @ Vt[:dim] - T
        p_new = G @ apply_Wt(R, E, parts)
        A = apply_A(R, p_new, parts)
        F = float(np.linalg.norm(E - A))
        steps.append(float(np.linalg.norm(p_new - p)))
        p = p_new
        hist.append(F)
        if lam == 0.0:
            change = abs(F_prev - F)
            if change < tol:
                converged = True
                break
            if abort_above is not None and change < almost_tol and F > abort_above:
                aborted = True
                break
            F_prev = F
        else:
            F_that = float(np.linalg.norm(T + A))
            if abs(F_prev - F_that) < lam_switch:
                switched = n
                lam = 0.0
                G = solver(0.0)
                F_prev = F  # from here on the monitored norm is F (3.17)
            else:
                F_prev = F_that
    res = _result(R, p, hist[-1] if hist else np.nan, hist, steps, n, converged, "faithful", "linear", lam0)
    return replace(res, seconds=time.perf_counter() - t0, extra={"lam_switch_iteration": switched, "aborted": aborted})

