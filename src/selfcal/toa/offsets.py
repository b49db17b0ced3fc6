"""Onset times and internal delays from a full TOA matrix: the rank-3 method of paper 004.

Model (004 eq. 3.1), rows = receivers (microphones) i = 1..I, columns = senders
(loudspeakers / acoustic events) j = 1..J, everything in **metres** (multiply measured
times by the speed c before calling; divide the offsets by c afterwards)::

    t_ij = |r_i - s_j| + tau_j + delta_i        (noise-free)

Only tau_j + delta_i is observable, so the gauge is tau_1 = 0 and the unknowns are
(eq. 3.5) ``p = [delta_1, ..., delta_I, tau_2, ..., tau_J]`` (length K = I + J - 1).

Squaring d_ij = t_ij - tau_j - delta_i = |r_i - s_j| and double-centring on receiver 1
and sender 1 removes the norms (eqs. 3.2-3.4)::

    -2 (r_i - r_1)^T (s_j - s_1) = T_ij + [A(p)]_ij + Gamma_ij,     i, j >= 2
    T_ij    = t_ij^2 - t_1j^2 - t_i1^2 + t_11^2
    A(p)    = C^{-1}(W p), W has 3 non-zeros per row: 2(t_1j - t_11) at delta_1,
              -2(t_ij - t_i1) at delta_i, -2(t_ij - t_1j) at tau_j
    Gamma_ij = 2 tau_j (delta_i - delta_1)

The left side has rank d (3 in 3-D), so the correct p makes ``T + A(p) + Gamma`` rank d.
The thesis assumes equal internal delays (Gamma = 0, sec. 3.5) and iterates (sec. 3.5.1):
rank-d truncation by SVD (3.13), error (3.14), least-squares update of p (3.11/3.15),
Frobenius norm (3.17); :func:`rank3_iteration` is that iteration (with the regularised
update 3.19-3.23). It is an alternating projection for

    minimise over p:  f(p) = sum_{k > d} sigma_k(T + A(p))^2                     (*)

and converges linearly, in thousands of iterations. :func:`rank3_lm` minimises (*) by
Levenberg-Marquardt in p with variable projection (the rank-d factor is eliminated by
the SVD): every column of the Jacobian of the corrected matrix is a rank-one matrix
u_k v_k^T, so the Gauss-Newton normal matrix is the Hadamard product
``(U~^T U~) o (V~^T V~)`` of the projected factors, O((I+J) K^2) per iteration, and it
converges quadratically on noise-free data (tens of iterations). Beyond the thesis it
offers ``model="exact"`` (keeps Gamma: distinct internal delays are recovered exactly),
``centring="mean"`` (``P D P`` instead of differences to receiver 1 / sender 1: the same
zero set, no special node), missing entries as extra unknowns, and a bound on |p| that
keeps it away from the spurious solutions at infinity. :func:`fast_offsets` (the default
method) runs it on the linear model and then on the exact model, which lands in the
right basin more often; :func:`estimate_offsets` adds the thesis's acceptance test on the
final F and restarts from new random initialisations.

Identifiability (our derivation). The rank method: the (I-1) x (J-1) matrix must have
rank <= d, a variety of codimension (I-1-d)(J-1-d), and it has to pin down K = I+J-1
offsets, so we need ``I >= d+2, J >= d+2`` and ``(I-1-d)(J-1-d) >= I+J-1``; with U units
(I = J = U, one microphone and one loudspeaker each) that is U >= 8 in 3-D and U >= 7 in
2-D. The full model (3.1) (NLS refinement) counts I*J equations against
``d(I+J) - d(d+1)/2 + I+J-1`` unknowns: ``IJ >= 4(I+J) - 7`` in 3-D (the thesis's 3.18,
U^2 - 8U + 7 >= 0, U >= 7) and ``IJ >= 3(I+J) - 4`` in 2-D (U >= 6). The rank method needs
one unit more because double centring discards the norm information.

Units of the thesis constants: the thesis works in seconds (c = 1 in the text, seconds
in its simulation). Its thresholds are on quantities in s^2 and scale with c^2: the
convergence threshold 1e-12 s^2, lambda threshold 1e-8 s^2 and acceptance 8e-7 s^2 become
``THESIS_TOL``, ``THESIS_LAM_SWITCH`` and ``THESIS_ACCEPT`` in m^2 (c = 343 m/s).

Length (1549 lines, above the ~600 guideline): the 004 rank-3 method, the thesis reference
iteration kept as the tests' reference, the fast solver and the position upgrade; the
reference iteration could move under tests/.
"""

from __future__ import annotations

import time
import warnings
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import scipy.linalg
from numpy.typing import NDArray
from scipy.linalg import cho_factor, cho_solve

from .._checks import as_matrix, as_rng, check_choice, check_dim
from ..errors import ConvergenceWarning, DegenerateGeometryError, InputError

__all__ = [
    "THESIS_SPEED",
    "THESIS_TOL",
    "THESIS_LAM_SWITCH",
    "THESIS_ACCEPT",
    "DELAY_MAX",
    "ONSET_MAX",
    "Rank3Result",
    "check_rank_identifiable",
    "double_centre",
    "thesis_T",
    "thesis_W",
    "apply_A",
    "apply_Wt",
    "gamma_term",
    "offset_matrix",
    "rank3_iteration",
    "rank3_lm",
    "fast_offsets",
    "estimate_offsets",
    "positions_from_ranges",
    "initialize_offsets_candidates",
    "initialize_offsets",
    "offset_free_positions",
    "complete_core",
    "thesis_lambda",
]

Array = NDArray[np.float64]

THESIS_SPEED = 343.0
#: convergence threshold on the change of F (3.17): 1e-12 s^2 (sec. 4.1) in m^2
THESIS_TOL = 1e-12 * THESIS_SPEED**2
#: lambda is set to 0 when ||T_hat||_F changes by less than 1e-8 s^2 (listing A.1.3), in m^2
THESIS_LAM_SWITCH = 1e-8 * THESIS_SPEED**2
#: acceptance: final F (3.17) below 8e-7 s^2 (sec. 4.3), in m^2 (about 0.094 m^2)
THESIS_ACCEPT = 8e-7 * THESIS_SPEED**2
#: initialisation ranges of the thesis (delays 0-20 ms, onsets 0-30 ms) in metres
DELAY_MAX = 0.020 * THESIS_SPEED
ONSET_MAX = 0.030 * THESIS_SPEED


def thesis_lambda(lam_seconds: float, n_receivers: int, n_senders: int, speed: float = THESIS_SPEED) -> float:
    """Convert a lambda of the thesis listing (A.1.3, seconds, scaled by I+J-1) to our ``lam`` (m^2).

    The listing solves ``(W^T W + lambda (I+J-1) I) p = W^T C(E)`` with times in seconds;
    eq. (3.23) has no (I+J-1). Our ``lam`` is the one of (3.23) in metres, so the listing's
    value maps to ``lam = lambda (I+J-1) c^2``.
    """
    return float(lam_seconds) * (n_receivers + n_senders - 1) * speed**2


# ----------------------------------------------------------------------------- building blocks


def double_centre(X: Array) -> Array:
    """``X_ij - X_1j - X_i1 + X_11`` for i, j >= 2: (I, J) -> (I-1, J-1) (the step 3.2 -> 3.4)."""
    return X[1:, 1:] - X[:1, 1:] - X[1:, :1] + X[0, 0]


def thesis_T(ranges: Array) -> Array:
    """T of (3.4)/(3.6): the double-centred squared times, (I-1, J-1), m^2."""
    return double_centre(ranges * ranges)


def thesis_W(ranges: Array) -> Array:
    """W of sec. 3.4, dense ((I-1)(J-1), I+J-1), rows in the column-major order of the C-operation.

    Row (i, j), i, j >= 2: ``2(t_1j - t_11)`` at delta_1, ``-2(t_ij - t_i1)`` at delta_i and
    ``-2(t_ij - t_1j)`` at tau_j (so that ``A(p) = C^{-1}(W p)`` is the linear part of (3.4)).
    """
    I, J = ranges.shape
    W = np.zeros(((I - 1) * (J - 1), I + J - 1))
    ii, jj = np.meshgrid(np.arange(1, I), np.arange(1, J), indexing="ij")
    rows = (ii - 1) + (I - 1) * (jj - 1)  # column-major, the C-operation of A.1.1
    W[rows, 0] = 2 * (ranges[0, jj] - ranges[0, 0])
    W[rows, ii] = -2 * (ranges[ii, jj] - ranges[ii, 0])
    W[rows, I - 1 + jj] = -2 * (ranges[ii, jj] - ranges[0, jj])
    return W


def _split(p: Array, I: int) -> tuple[Array, Array]:
    """p (3.5) -> (delta (I,), tau (J,) with tau_1 = 0)."""
    return p[:I], np.concatenate([[0.0], p[I:]])


def _w_parts(ranges: Array) -> tuple[Array, Array, Array]:
    """The three non-zero patterns of W: a_j = t_1j - t_11, B_ij = t_ij - t_i1, C_ij = t_ij - t_1j."""
    return (ranges[0, 1:] - ranges[0, 0], ranges[1:, 1:] - ranges[1:, :1], ranges[1:, 1:] - ranges[:1, 1:])


def apply_A(ranges: Array, p: Array, parts: tuple[Array, Array, Array] | None = None) -> Array:
    """``A(p) = C^{-1}(W p)`` (3.6) without forming W: (I-1, J-1). ``parts``: precomputed ``_w_parts``."""
    I = ranges.shape[0]
    delta, tau = _split(p, I)
    a, B, C = parts if parts is not None else _w_parts(ranges)
    return 2 * delta[0] * a[None, :] - 2 * delta[1:, None] * B - 2 * tau[None, 1:] * C


def apply_Wt(ranges: Array, E: Array, parts: tuple[Array, Array, Array] | None = None) -> Array:
    """``W^T C(E)`` for an (I-1, J-1) matrix E without forming W: (I+J-1,)."""
    a, B, C = parts if parts is not None else _w_parts(ranges)
    return np.concatenate([[2 * E.sum(axis=0) @ a], -2 * np.einsum("ij,ij->i", E, B),
                           -2 * np.einsum("ij,ij->j", E, C)])


def gamma_term(p: Array, I: int, J: int) -> Array:
    """Gamma of (3.6): ``2 tau_j (delta_i - delta_1)``, (I-1, J-1); zero when all delays are equal."""
    delta, tau = _split(p, I)
    return 2 * (delta[1:, None] - delta[0]) * tau[None, 1:]


def _centre(X: Array, axis: int, centring: str) -> Array:
    """Apply the centring operator along ``axis``: differences to the first entry (thesis) or to the mean."""
    if centring == "reference":
        return np.take(X, np.arange(1, X.shape[axis]), axis=axis) - np.take(X, [0], axis=axis)
    return X - X.mean(axis=axis, keepdims=True)


def offset_matrix(ranges: Array, p: Array, *, model: str = "exact", centring: str = "reference") -> Array:
    """The corrected double-centred matrix ``T + A(p) (+ Gamma(p))``, m^2.

    With ``model="exact"`` this is the double centring of ``(t - delta_i - tau_j)^2``, which
    equals ``-2 (r_i - r_1)^T (s_j - s_1)`` at the true p; ``"linear"`` drops Gamma (thesis).
    ``centring="reference"`` (thesis, receiver 1 and sender 1; shape (I-1, J-1)) or ``"mean"``
    (``P_I D P_J`` with ``P = I - 11^T/n``; shape (I, J); the same zero set, but no node is
    special, which removes the far-field local minima of the reference nodes).
    """
    I = ranges.shape[0]
    delta, tau = _split(p, I)
    if model == "exact":
        e = ranges - delta[:, None] - tau[None, :]
        D = e * e
    else:
        # Gamma and the squares of the offsets dropped; the squares are constant along a row or a
        # column and vanish under double centring
        D = ranges * ranges - 2 * ranges * (delta[:, None] + tau[None, :])
    return _centre(_centre(D, 0, centring), 1, centring)


def check_rank_identifiable(n_receivers: int, n_senders: int, dim: int = 3) -> None:
    """Raise ``DegenerateGeometryError(kind="too-few-units")`` when the rank-d method cannot determine p.

    Condition (see the module docstring): ``I >= d+2``, ``J >= d+2`` and
    ``(I-1-d)(J-1-d) >= I+J-1``; for U units with a microphone and a loudspeaker each,
    U >= 8 in 3-D and U >= 7 in 2-D (thesis 3.18 gives U >= 7 for the full 3-D model).
    """
    I, J, d = int(n_receivers), int(n_senders), int(dim)
    if I < d + 2 or J < d + 2 or (I - 1 - d) * (J - 1 - d) < I + J - 1:
        units = 8 if d == 3 else 7
        raise DegenerateGeometryError(
            f"{I} receivers x {J} senders cannot determine the {I + J - 1} offsets with the rank-{d} "
            f"method: it needs (I-1-{d})(J-1-{d}) >= I+J-1 (here {(I - 1 - d) * (J - 1 - d)} < {I + J - 1} "
            f"or a side below {d + 2}); with one microphone and one loudspeaker per unit that is at least "
            f"{units} units in {d}-D. Add units, or use solve_toa(..., method='nls') with an initial guess",
            kind="too-few-units",
        )


def _validate(ranges: Any, dim: int) -> Array:
    dim = check_dim(dim)
    R = as_matrix(ranges, "ranges", allow_nan=True, nonnegative=False, min_shape=(2, 2))
    if np.isnan(R).any():
        i, j = np.argwhere(np.isnan(R))[0]
        raise InputError(
            f"ranges: entry ({i}, {j}) is missing (NaN); the rank-{dim} offset estimation needs a complete "
            "matrix: use solve_toa(matrix, offsets='both', method='nls') (or the fast method here, which "
            "completes missing entries), or drop the incomplete rows/columns"
        )
    check_rank_identifiable(R.shape[0], R.shape[1], dim)
    return R


# ----------------------------------------------------------------------------- result


def _subsample(h: Array, n: int = 400) -> list[list[float]]:
    if h.size <= n:
        idx = np.arange(h.size)
    else:
        idx = np.unique(np.round(np.geomspace(1, h.size, n)).astype(int) - 1)
    return [[int(i), float(h[i])] for i in idx]


@dataclass(frozen=True)
class Rank3Result:
    """Offsets estimated by the rank-d method (004), in the units of the input (metres).

    Attributes
    ----------
    p : (I+J-1,) the vector (3.5) ``[delta_1..delta_I, tau_2..tau_J]``.
    receiver_offsets : (I,) internal delays delta_i.
    source_offsets : (J,) onset times tau_j, ``source_offsets[0] == 0``.
    frobenius : final Frobenius norm F (3.17), m^2: the distance of the reference-centred corrected
        matrix to rank d (for the fast method evaluated at its final p).
    history : (n,) F per iteration (3.17); for the fast method its own objective sqrt(*) in the
        chosen centring.
    steps : (n,) ``||p^(n+1) - p^(n)||`` per iteration (the thesis's second history column).
    iterations : iterations of the accepted (or best) run.
    total_iterations : iterations over every restart.
    converged : the convergence test was met (change of F below ``tol`` / step below ``xtol``).
    accepted : F <= ``accept`` (None when no acceptance test was asked for).
    restarts : number of restarts from a new random initialisation before the returned run.
    method : ``"faithful"`` (thesis iteration) or ``"fast"`` (variable-projection LM).
    model : ``"linear"`` (Gamma = 0, thesis) or ``"exact"`` (with Gamma).
    residual_rms : ``F / sqrt((I-1)(J-1))``, m^2.
    seconds : wall time of the whole call, s.
    lam : the regularisation lambda the run started with (0 for none).
    extra : method-specific details (``lam_switch_iteration``; ``completed`` matrix with NaN input).
    """

    p: Array
    receiver_offsets: Array
    source_offsets: Array
    frobenius: float
    history: Array
    steps: Array
    iterations: int
    total_iterations: int
    converged: bool
    accepted: bool | None
    restarts: int
    method: str
    model: str
    residual_rms: float
    seconds: float = 0.0
    lam: float = 0.0
    extra: dict[str, Any] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        """JSON-safe summary (the F history is log-subsampled to at most 400 points)."""
        return {
            "p": self.p.tolist(),
            "receiver_offsets": self.receiver_offsets.tolist(),
            "source_offsets": self.source_offsets.tolist(),
            "frobenius": float(self.frobenius),
            "history": _subsample(self.history),
            "iterations": int(self.iterations),
            "total_iterations": int(self.total_iterations),
            "converged": bool(self.converged),
            "accepted": self.accepted,
            "restarts": int(self.restarts),
            "method": self.method,
            "model": self.model,
            "residual_rms": float(self.residual_rms),
            "seconds": float(self.seconds),
            "lam": float(self.lam),
        }


def _result(R: Array, p: Array, F: float, hist: list[float] | Array, steps: list[float] | Array, it: int,
            converged: bool, method: str, model: str, lam: float) -> Rank3Result:
    I, J = R.shape
    delta, tau = _split(p, I)
    return Rank3Result(
        p=p.copy(), receiver_offsets=delta.copy(), source_offsets=tau.copy(), frobenius=float(F),
        history=np.asarray(hist, dtype=float), steps=np.asarray(steps, dtype=float), iterations=int(it),
        total_iterations=int(it), converged=bool(converged), accepted=None, restarts=0, method=method,
        model=model, residual_rms=float(F / np.sqrt((I - 1) * (J - 1))), lam=float(lam),
    )


def _random_p0(I: int, J: int, rng: np.random.Generator) -> Array:
    """Thesis initialisation (sec. 4.1): delays U(0, 20 ms), onsets U(0, 30 ms), in metres."""
    return np.concatenate([rng.uniform(0.0, DELAY_MAX, I), rng.uniform(0.0, ONSET_MAX, J - 1)])


# ----------------------------------------------------------------------------- faithful iteration


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
    return _replace(res, seconds=time.perf_counter() - t0, extra={"lam_switch_iteration": switched, "aborted": aborted})


def _replace(res: Rank3Result, **kw: Any) -> Rank3Result:
    from dataclasses import replace

    return replace(res, **kw)


# ----------------------------------------------------------------------------- fast solver


def _rank1_factors(
    R: Array, p: Array, model: str, missing: tuple[Any, ...], centring: str = "reference"
) -> tuple[Array, Array]:
    """Columns of the Jacobian of the corrected matrix as rank-one pairs: dM/dx_k = U[:, k] V[:, k]^T.

    x = [p, missing t_ij]. Before centring, delta_k changes row k of D by ``-2 e_k.``, tau_l
    column l by ``-2 e_.l`` and a missing t_ij the single entry D_ij by ``2 e_ij``, with
    e = t - delta_i - tau_j (exact model, Gamma included) or e = t (linear model: the columns
    of W). Double centring maps a rank-one ``u v^T`` to ``(L u)(L v)^T``.
    """
    I, J = R.shape
    K = I + J - 1
    mi, mj = missing
    if model == "exact":
        delta, tau = _split(p, I)
        e = R - delta[:, None] - tau[None, :]
    else:
        e = R
    n = K + mi.size
    Uf = np.zeros((I, n))
    Vf = np.zeros((J, n))
    Uf[np.arange(I), np.arange(I)] = 1.0
    Vf[:, :I] = -2 * e.T
    Uf[:, I:K] = -2 * e[:, 1:]
    Vf[np.arange(1, J), np.arange(I, K)] = 1.0
    if mi.size:
        # d/dt_ij of t^2 - 2 t (delta + tau) (linear) and of (t - delta - tau)^2 (exact) agree
        delta, tau = _split(p, I)
        cols = np.arange(K, n)
        Uf[mi, cols] = 2 * (R[mi, mj] - delta[mi] - tau[mj])
        Vf[mj, cols] = 1.0
    return _centre(Uf, 0, centring), _centre(Vf, 0, centring)


def _tail(M: Array, dim: int) -> tuple[float, Array, Array, Array]:
    """Cost sum_{k>d} sigma_k^2, the leading singular vectors and the residual M - M_d.

    The leading left subspace comes from the eigendecomposition of the smaller Gram matrix
    (2-3x cheaper than an SVD); the residual is formed by projection, not from the tail
    eigenvalues, so the cost keeps its accuracy down to the rounding of M.
    """
    if M.shape[0] > M.shape[1]:
        c, Vd, Ud, r = _tail(M.T, dim)
        return c, Ud, Vd, r.T
    w, Q = np.linalg.eigh(M @ M.T)
    Ud = Q[:, -dim:]
    B = Ud.T @ M
    resid = M - Ud @ B
    Vd, _ = np.linalg.qr(B.T)
    return float(np.sum(resid * resid)), Ud, Vd, resid


def _feasible(x: Array, bound: float) -> bool:
    """Keep the search finite: |offsets| and the missing entries within twice the largest measured value.

    Without a bound LM can follow the spurious solutions at infinity (sender 1 pushed to the
    far field by ``delta_i + c, tau_j - c``, which changes only the reference column).
    """
    return bool(np.all(np.abs(x) <= bound))


def _impute(R: Array) -> Array:
    """Fill NaN with an additive row + column model of the observed entries (a starting guess only)."""
    mask = np.isnan(R)
    if not mask.any():
        return R
    row = np.nanmean(R, axis=1, keepdims=True)
    row = np.where(np.isnan(row), np.nanmean(R), row)
    col = np.nanmean(R - row, axis=0, keepdims=True)
    col = np.where(np.isnan(col), 0.0, col)
    return np.where(mask, row + col, R)


#: rank3_lm: up to this many unknowns (offsets + missing entries) the dense joint step is used
_DENSE_JOINT_MAX = 256


def _centre_adj(Y: Array, axis: int, centring: str) -> Array:
    """Adjoint of :func:`_centre` along ``axis`` (mean centring is its own adjoint)."""
    if centring == "mean":
        return Y - Y.mean(axis=axis, keepdims=True)
    return np.concatenate([-Y.sum(axis=axis, keepdims=True), Y], axis=axis)


def _centre_gram(n: int, centring: str) -> tuple[Array, Array]:
    """``C^T C = I + F S F^T`` of the centring operator C on vectors of length n: (F, S)."""
    if centring == "mean":
        return np.full((n, 1), 1.0 / np.sqrt(n)), -np.eye(1)
    F = np.zeros((n, 2))
    F[0, 0] = 1.0
    F[1:, 1] = 1.0
    return F, np.array([[n - 2.0, -1.0], [-1.0, 0.0]])


def _tail_sub(M: Array, dim: int, Q: Array | None = None) -> tuple[float, Array, Array, Array, Array]:
    """:func:`_tail` by warm-started subspace iteration: no full eigendecomposition.

    Block power iteration on ``M M^T`` with ``k = d + 4`` vectors and a Rayleigh-Ritz step,
    started from the basis ``Q`` of the previous call (the corrected matrix changes little
    between LM trials), until the leading d-subspace moves by less than 1e-13 (sine of the
    largest principal angle), at most 60 sweeps. Each sweep costs three (I x J) x k products.
    Returns (cost, Ud, Vd, residual, basis for the next call).
    """
    m, n = M.shape
    k = min(dim + 4, m, n)
    if Q is None or Q.shape != (m, k):
        Q = np.linalg.qr(M @ np.random.default_rng(0).standard_normal((n, k)))[0]
    Ud_prev: Array | None = None
    Ud = Q[:, :dim]
    for _ in range(60):
        Q = np.linalg.qr(M @ (M.T @ Q))[0]
        Ub = np.linalg.svd(Q.T @ M, full_matrices=False)[0]
        Ud = Q @ Ub[:, :dim]
        if Ud_prev is not None and np.linalg.norm(Ud - Ud_prev @ (Ud_prev.T @ Ud), 2) < 1e-13:
            break
        Ud_prev = Ud
    B = Ud.T @ M
    resid = M - Ud @ B
    Vd = np.linalg.qr(B.T)[0]
    return float(np.sum(resid * resid)), Ud, Vd, resid, Q


def _damped_pcg(jtj: Any, chol: Any, hz: Array, damp: Array, g: Array, K: int, rtol: float = 1e-10) -> Array:
    """Solve ``(J^T J + diag(damp)) dx = -g`` by conjugate gradients (offsets + missing times).

    Preconditioner: the exact damped offset block (its Cholesky factor ``chol``) and the
    damped diagonal ``hz`` of the missing-time block. Relative tolerance ``rtol``, at most 500
    iterations; the LM gain test guards the rest. (A loose, gradient-scaled tolerance far from
    the minimum was measured to cost iterations: 83 instead of 12 at 300 units.)
    """
    from scipy.sparse.linalg import LinearOperator, cg

    n = g.size

    def mat(v: Array) -> Array:
        return np.asarray(jtj(v) + damp * v)

    def prec(v: Array) -> Array:
        return np.concatenate([cho_solve(chol, v[:K], check_finite=False), v[K:] / hz])

    op = LinearOperator((n, n), matvec=mat, dtype=float)
    pc = LinearOperator((n, n), matvec=prec, dtype=float)
    x0 = prec(-g)
    dx, _ = cg(op, -g, x0=x0, rtol=rtol, maxiter=500, M=pc)
    return np.asarray(dx)


def rank3_lm(
    ranges: Any,
    *,
    dim: int = 3,
    model: str = "exact",
    p0: Any = None,
    max_iter: int = 100,
    xtol: float = 1e-12,
    centring: str = "mean",
    rng: np.random.Generator | int | None = None,
    abort_above: float | None = None,
) -> Rank3Result:
    """Levenberg-Marquardt with variable projection on (*): the fast solver for the 004 fixed point.

    Residual: ``N(M(p)) = M(p) - [M(p)]_d`` (the part of the corrected matrix outside its best
    rank-d approximation), with ``M = T + A(p) (+ Gamma(p))``. Jacobian (Kaufman's variable
    projection approximation, exact at zero residual): ``N(dM/dp_k) = (P u_k)(Q v_k)^T`` with
    P, Q the projectors off the leading singular subspaces, so
    ``J^T J = (U~^T U~) o (V~^T V~)`` (Hadamard) and ``J^T r = diag(U^T N(M) V)`` is the exact
    gradient of (*)/2. Marquardt damping with the usual gain-ratio update; steps that leave
    ``|p| <= 2 max t`` are refused (see :func:`_feasible`).

    Scaling. The (K x K) Gauss-Newton matrix, K = I+J-1, is formed from its block structure
    (the columns of the delays are unit vectors): two rank-I/J Gram products, ``O(I J (I+J))``,
    instead of ``O(I J K)`` per factor. The rank-d subspace comes from warm-started subspace
    iteration (:func:`_tail_sub`, ``O(I J d)`` per sweep), not from a full eigendecomposition.

    Missing entries (NaN) are extra unknowns (their times), each with its own rank-one
    Jacobian column (matrix completion inside the same projection), but no dense matrix has
    a row per missing entry: the damped Gauss-Newton system in (p, missing times) is solved by
    conjugate gradients, preconditioned by the exact (Cholesky-factored) p-block and the
    diagonal of the missing-time block; its products cost ``O(I J d)`` from the low-rank form
    of the projectors (``C^T (I - U U^T) C = I + F S F^T``). Memory ``O(I J + K^2)``. Their
    count adds to the I+J-1 unknowns of the identifiability condition. Up to
    ``_DENSE_JOINT_MAX`` unknowns in all, the dense joint step of :func:`_rank3_lm_joint`
    runs instead (cheaper there; the same iteration).

    Parameters
    ----------
    ranges : (I, J) metres; NaN = missing.
    dim : rank d (3 or 2).
    model : ``"exact"`` (keeps Gamma: distinct internal delays) or ``"linear"`` (thesis, Gamma = 0).
    p0 : initial p (metres); default the thesis random initialisation from ``rng``.
    max_iter : maximum LM iterations.
    xtol : stop when ``||dx|| <= xtol (||x|| + xtol)`` or F <= xtol ||M||_F.
    centring : ``"mean"`` (default, no special node) or ``"reference"`` (thesis (3.4)).
    rng : seed or Generator for the initialisation.
    abort_above : the early abort the thesis proposes (sec. 6.2), for restarts: once an
        iteration lowers (*) by less than 1 % while its square root (``extra["objective"]``)
        is still more than 0.1 % above this value (the best run so far), the run heads for a worse local
        minimum and stops (``converged=False``, ``extra["aborted"]=True``). None: never.

    Returns
    -------
    Rank3Result with ``method="fast"``; ``frobenius`` is sqrt of (*) with reference centring,
    the quantity F (3.17) converges to; with missing entries ``extra["completed"]`` is the
    completed (I, J) matrix.
    """
    t0 = time.perf_counter()
    check_choice(model, "model", ("exact", "linear"))
    check_choice(centring, "centring", ("reference", "mean"))
    dim = check_dim(dim)
    R0 = as_matrix(ranges, "ranges", allow_nan=True, min_shape=(2, 2))
    mask = np.isnan(R0)
    I, J = R0.shape
    K = I + J - 1
    n_miss = int(mask.sum())
    check_rank_identifiable(I, J, dim)
    if n_miss and (I - 1 - dim) * (J - 1 - dim) < K + n_miss:
        raise DegenerateGeometryError(
            f"{n_miss} missing entries leave too few equations: the rank-{dim} method needs "
            f"(I-1-{dim})(J-1-{dim}) = {(I - 1 - dim) * (J - 1 - dim)} >= I+J-1 + missing = {K + n_miss}",
            kind="too-few-measurements",
        )
    if K + n_miss <= _DENSE_JOINT_MAX:
        # small: one dense joint Gauss-Newton matrix and a full eigendecomposition are cheaper
        # than the iterative pieces below (measured crossover ~300 unknowns)
        return _rank3_lm_joint(R0, dim=dim, model=model, p0=p0, max_iter=max_iter, xtol=xtol,
                               centring=centring, rng=rng, abort_above=abort_above)
    missing = np.nonzero(mask)
    R = _impute(R0)
    bound = 2.0 * float(np.max(np.abs(R0[~mask])))
    p = _random_p0(I, J, as_rng(rng)) if p0 is None else np.array(p0, dtype=float).reshape(-1)
    if p.shape != (K,):
        raise InputError(f"p0 must have I+J-1 = {K} entries, got {p.shape}")
    Fr, Sr = _centre_gram(I, centring)
    Fc, Sc = _centre_gram(J, centring)

    def centred(X: Array) -> Array:
        return _centre(_centre(X, 0, centring), 1, centring)

    def adjoint(Y: Array) -> Array:
        return _centre_adj(_centre_adj(Y, 0, centring), 1, centring)

    def squared(pv: Array, Rt: Array) -> tuple[Array, Array, Array]:
        """D(p) of the (completed) times Rt, the p-factor e (dD/d(offset sum) = -2 e), dD/dt / 2."""
        delta, tau = _split(pv, I)
        c = delta[:, None] + tau[None, :]
        if model == "exact":
            e = Rt - c
            return e * e, e, e
        return Rt * Rt - 2 * Rt * c, Rt, Rt - c

    def times(xv: Array) -> Array:
        Rt = R.copy()
        if n_miss:
            Rt[missing] = xv[K:]
        return Rt

    def evaluate(xv: Array, Q: Array | None) -> tuple[float, Array, Array, Array, Array, Array]:
        M = centred(squared(xv[:K], times(xv))[0])
        cost, Ud, Vd, resid, Q = _tail_sub(M, dim, Q)
        return cost, Ud, Vd, resid, Q, M

    def metric(Ud: Array, Vd: Array) -> tuple[Array, Array, Array, Array]:
        """``C^T (I - Ud Ud^T) C = I + FA SA FA^T`` on rows, likewise on columns."""
        FA = np.hstack([Fr, _centre_adj(Ud, 0, centring)])
        SA = scipy.linalg.block_diag(Sr, -np.eye(dim))
        FB = np.hstack([Fc, _centre_adj(Vd, 0, centring)])
        SB = scipy.linalg.block_diag(Sc, -np.eye(dim))
        return FA, SA, FB, SB

    def gauss_newton(xv: Array, Ud: Array, Vd: Array, resid: Array) -> tuple[Array, Array, Any]:
        """p-block of J^T J from its structure, the gradient J^T r and the J^T J product."""
        _, e, ez = squared(xv[:K], times(xv))
        FA, SA, FB, SB = metric(Ud, Vd)
        W = -2.0 * e[:, 1:]  # tau columns of the receiver factors, (I, J-1)
        Vm = -2.0 * e.T  # delta columns of the source factors, (J, I)
        FW = FA.T @ W
        FV = FB.T @ Vm
        Hu = np.empty((K, K))
        Hu[:I, :I] = np.eye(I) + FA @ SA @ FA.T
        Hu[:I, I:] = W + FA @ (SA @ FW)
        Hu[I:, :I] = Hu[:I, I:].T
        Hu[I:, I:] = W.T @ W + FW.T @ SA @ FW
        BV = Vm + FB @ (SB @ FV)
        Bm = np.eye(J) + FB @ SB @ FB.T
        Hv = np.empty((K, K))
        Hv[:I, :I] = Vm.T @ Vm + FV.T @ SB @ FV
        Hv[:I, I:] = BV[1:, :].T
        Hv[I:, :I] = BV[1:, :]
        Hv[I:, I:] = Bm[1:, 1:]
        Hu *= Hv
        G = adjoint(resid)

        def jt(Gm: Array) -> Array:
            eg = e * Gm
            parts = [-2.0 * eg.sum(axis=1), -2.0 * eg.sum(axis=0)[1:]]
            if n_miss:
                parts.append(2.0 * ez[missing] * Gm[missing])
            return np.concatenate(parts)

        def jtj(v: Array) -> Array:
            tau = np.concatenate([[0.0], v[I:K]])
            X = -2.0 * e * (v[:I, None] + tau[None, :])
            if n_miss:
                X[missing] += 2.0 * ez[missing] * v[K:]
            Gm = X + FA @ (SA @ (FA.T @ X))
            Gm += (Gm @ FB) @ SB @ FB.T
            return jt(Gm)

        g = jt(G)
        if not n_miss:
            return Hu, g, None
        # diagonal of the missing-time block: (2 e_ij)^2 A_ii B_jj
        Ad = 1.0 + np.einsum("ia,ab,ib->i", FA, SA, FA)
        Bd = 1.0 + np.einsum("ja,ab,jb->j", FB, SB, FB)
        hz = 4.0 * ez[missing] ** 2 * Ad[missing[0]] * Bd[missing[1]]
        return Hu, g, (jtj, hz)

    x = np.concatenate([p, R[missing]])
    cost, Ud, Vd, resid, Q, M = evaluate(x, None)
    hist = [np.sqrt(cost)]
    steps: list[float] = []
    mu: float | None = None
    nu = 2.0
    converged = False
    it = 0
    scale = float(np.linalg.norm(M))
    diag = np.diag_indices(K)
    aborted = False
    for it in range(1, int(max_iter) + 1):  # noqa: B007 (it is the iteration count after the loop)
        H, g, coupled = gauss_newton(x, Ud, Vd, resid)
        dg = np.diag(H).copy()
        if coupled is not None:
            dg = np.concatenate([dg, coupled[1]])
        dg[dg <= 0] = 1.0
        if mu is None:
            mu = 1e-6 * float(dg.max())
        accepted = False
        dx = np.zeros_like(x)
        while mu <= 1e30:
            Hm = H.copy()
            Hm[diag] += mu * dg[:K]
            try:
                cf = cho_factor(Hm, check_finite=False)
            except np.linalg.LinAlgError:
                mu *= 10.0
                continue
            if coupled is None:
                dx = -cho_solve(cf, g, check_finite=False)
            else:
                dx = _damped_pcg(coupled[0], cf, dg[K:] * (1.0 + mu), dg * mu, g, K)
            x_try = x + dx
            if not _feasible(x_try, bound):
                mu *= nu
                nu *= 2.0
                continue
            trial = evaluate(x_try, Q)
            cost_try = trial[0]
            if cost_try < cost or cost_try == 0.0:
                Hdx = H @ dx[:K] if coupled is None else coupled[0](dx)
                pred = float(-(g @ dx) - 0.5 * dx @ Hdx)
                rho = (cost - cost_try) / (2 * pred) if pred > 0 else 0.0
                cost, Ud, Vd, resid, Q, M = trial
                x = x_try
                mu *= max(1.0 / 3.0, 1.0 - (2 * rho - 1) ** 3) if rho > 0 else 1.0
                nu = 2.0
                accepted = True
                break
            mu *= nu
            nu *= 2.0
        step = float(np.linalg.norm(dx)) if accepted else 0.0
        steps.append(step)
        slow = hist[-1] ** 2 - cost < 0.01 * cost
        hist.append(np.sqrt(cost))
        if abort_above is not None and it >= 3 and slow and np.sqrt(cost) > abort_above * (1 + 1e-3):
            aborted = True
            break
        if not accepted or step <= xtol * (np.linalg.norm(x) + xtol) or np.sqrt(cost) <= xtol * scale:
            # (no decrease even with huge damping: a stationary point of (*))
            converged = True
            break
    p = x[:K]
    Rx = times(x)
    # report the thesis's quantity: the distance to rank d of the reference-centred matrix, the
    # value F (3.17) converges to, so that the acceptance threshold means the same for both methods
    Dx = squared(p, Rx)[0]
    Mref = _centre(_centre(Dx, 0, "reference"), 1, "reference")
    F_ref = np.sqrt(_tail_sub(Mref, dim)[0])
    res = _result(Rx, p, F_ref, hist, steps, it, converged, "fast", model, 0.0)
    extra: dict[str, Any] = {"completed": Rx} if n_miss else {}
    extra["objective"] = float(np.sqrt(cost))
    extra["aborted"] = aborted
    return _replace(res, seconds=time.perf_counter() - t0, extra=extra)


def _rank3_lm_joint(
    ranges: Any,
    *,
    dim: int = 3,
    model: str = "exact",
    p0: Any = None,
    max_iter: int = 100,
    xtol: float = 1e-12,
    centring: str = "mean",
    rng: np.random.Generator | int | None = None,
    abort_above: float | None = None,
) -> Rank3Result:
    """Reference: the joint LM of :func:`rank3_lm` before 2026-12 (missing entries as dense unknowns).

    Kept for the tests that compare the scalable :func:`rank3_lm` against it on small cases;
    its Hessian is (I+J-1+missing)^2 and every trial runs a full eigendecomposition.

    Residual: ``N(M(p)) = M(p) - [M(p)]_d`` (the part of the corrected matrix outside its best
    rank-d approximation), with ``M = T + A(p) (+ Gamma(p))``. Jacobian (Kaufman's variable
    projection approximation, exact at zero residual): ``N(dM/dp_k) = (P u_k)(Q v_k)^T`` with
    P, Q the projectors off the leading singular subspaces, so
    ``J^T J = (U~^T U~) o (V~^T V~)`` (Hadamard) and ``J^T r = diag(U^T N(M) V)`` is the exact
    gradient of (*)/2. Marquardt damping with the usual gain-ratio update; steps that leave
    ``|x| <= 2 max t`` are refused (see :func:`_feasible`). Missing entries (NaN) become extra unknowns, each with its own rank-one Jacobian column (matrix
    completion inside the same projection); their count adds to the I+J-1 unknowns of the
    identifiability condition.

    Parameters
    ----------
    ranges : (I, J) metres; NaN = missing.
    dim : rank d (3 or 2).
    model : ``"exact"`` (keeps Gamma: distinct internal delays) or ``"linear"`` (thesis, Gamma = 0).
    p0 : initial p (metres); default the thesis random initialisation from ``rng``.
    max_iter : maximum LM iterations.
    xtol : stop when ``||dx|| <= xtol (||x|| + xtol)`` or F <= xtol ||M||_F.
    rng : seed or Generator for the initialisation.

    centring : ``"mean"`` (default, no special node) or ``"reference"`` (thesis (3.4)).

    Returns
    -------
    Rank3Result with ``method="fast"``; ``frobenius`` is sqrt of (*) with reference centring,
    the quantity F (3.17) converges to; with missing entries ``extra["completed"]`` is the
    completed (I, J) matrix.
    """
    t0 = time.perf_counter()
    check_choice(model, "model", ("exact", "linear"))
    check_choice(centring, "centring", ("reference", "mean"))
    dim = check_dim(dim)
    R0 = as_matrix(ranges, "ranges", allow_nan=True, min_shape=(2, 2))
    mask = np.isnan(R0)
    I, J = R0.shape
    K = I + J - 1
    n_miss = int(mask.sum())
    check_rank_identifiable(I, J, dim)
    if n_miss and (I - 1 - dim) * (J - 1 - dim) < K + n_miss:
        raise DegenerateGeometryError(
            f"{n_miss} missing entries leave too few equations: the rank-{dim} method needs "
            f"(I-1-{dim})(J-1-{dim}) = {(I - 1 - dim) * (J - 1 - dim)} >= I+J-1 + missing = {K + n_miss}",
            kind="too-few-measurements",
        )
    missing = np.nonzero(mask)
    R = _impute(R0)
    bound = 2.0 * float(np.max(np.abs(R0[~mask])))
    p = _random_p0(I, J, as_rng(rng)) if p0 is None else np.array(p0, dtype=float).reshape(-1)
    if p.shape != (K,):
        raise InputError(f"p0 must have I+J-1 = {K} entries, got {p.shape}")
    x = np.concatenate([p, R[missing]])

    def unpack(xv: Array) -> tuple[Array, Array]:
        if not n_miss:
            return R, xv
        Rx = R.copy()
        Rx[missing] = xv[K:]
        return Rx, xv[:K]

    Rx, p = unpack(x)
    M = offset_matrix(Rx, p, model=model, centring=centring)
    cost, Ud, Vd, resid = _tail(M, dim)
    hist = [np.sqrt(cost)]
    steps: list[float] = []
    mu: float | None = None
    nu = 2.0
    converged = False
    aborted = False
    it = 0
    scale = float(np.linalg.norm(M))
    for it in range(1, int(max_iter) + 1):  # noqa: B007 (it is the iteration count after the loop)
        Uf, Vf = _rank1_factors(Rx, p, model, missing, centring)
        Pu = Uf - Ud @ (Ud.T @ Uf)
        Pv = Vf - Vd @ (Vd.T @ Vf)
        H = (Pu.T @ Pu) * (Pv.T @ Pv)
        g = np.einsum("ik,ik->k", Uf, resid @ Vf)
        dg = np.diag(H).copy()
        dg[dg <= 0] = 1.0
        if mu is None:
            mu = 1e-6 * float(dg.max())
        accepted = False
        dx = np.zeros_like(x)
        while mu <= 1e30:
            try:
                dx = -cho_solve(cho_factor(H + mu * np.diag(dg)), g)
            except np.linalg.LinAlgError:
                mu *= 10.0
                continue
            x_try = x + dx
            Rt, p_try = unpack(x_try)
            if not _feasible(x_try, bound):
                mu *= nu
                nu *= 2.0
                continue
            cost_try, Ud_t, Vd_t, resid_t = _tail(offset_matrix(Rt, p_try, model=model, centring=centring), dim)
            if cost_try < cost or cost_try == 0.0:
                pred = -(g @ dx) - 0.5 * dx @ (H @ dx)
                rho = (cost - cost_try) / (2 * pred) if pred > 0 else 0.0
                x, Rx, p, cost, Ud, Vd, resid = x_try, Rt, p_try, cost_try, Ud_t, Vd_t, resid_t
                mu *= max(1.0 / 3.0, 1.0 - (2 * rho - 1) ** 3) if rho > 0 else 1.0
                nu = 2.0
                accepted = True
                break
            mu *= nu
            nu *= 2.0
        step = float(np.linalg.norm(dx)) if accepted else 0.0
        steps.append(step)
        slow = hist[-1] ** 2 - cost < 0.01 * cost
        hist.append(np.sqrt(cost))
        if abort_above is not None and it >= 3 and slow and np.sqrt(cost) > abort_above * (1 + 1e-3):
            aborted = True
            break
        if not accepted or step <= xtol * (np.linalg.norm(x) + xtol) or np.sqrt(cost) <= xtol * scale:
            # (no decrease even with huge damping: a stationary point of (*))
            converged = True
            break
    # report the thesis's quantity: the distance to rank d of the reference-centred matrix, the
    # value F (3.17) converges to, so that the acceptance threshold means the same for both methods
    F_ref = np.sqrt(_tail(offset_matrix(Rx, p, model=model, centring="reference"), dim)[0])
    res = _result(Rx, p, F_ref, hist, steps, it, converged, "fast", model, 0.0)
    extra: dict[str, Any] = {"completed": Rx} if n_miss else {}
    extra["objective"] = float(np.sqrt(cost))
    extra["aborted"] = aborted
    return _replace(res, seconds=time.perf_counter() - t0, extra=extra)


def fast_offsets(
    ranges: Any,
    *,
    dim: int = 3,
    model: str = "exact",
    p0: Any = None,
    max_iter: int = 100,
    rng: np.random.Generator | int | None = None,
    abort_above: float | None = None,
) -> Rank3Result:
    """One start of the default fast method: LM on the linear (Gamma = 0) model, then on ``model``.

    The linear model's objective is the distance of an affine family to the rank-d matrices,
    and from a random start it lands in the basin of the true p more often than the exact
    (quadratic) model; we measured on 12 x 12 x 2 m setups with 12 units 48/72 vs 40/72
    starts with equal delays, 64/72 vs 39/72 with distinct delays. The second stage removes
    the Gamma bias (distinct delays) and polishes to machine precision. Both stages use mean
    centring. ``iterations`` counts both stages. With missing entries only the second stage runs.
    ``abort_above`` (the early abort of :func:`rank3_lm`) applies to the last stage only (the
    linear stage's objective is biased by Gamma and not comparable).
    """
    if np.isnan(np.asarray(ranges, dtype=float)).any():
        # with missing entries the biased linear stage lets the free entries absorb Gamma and
        # leaves the exact stage in a wrong basin: exact model only
        return rank3_lm(ranges, dim=dim, model=model, p0=p0, max_iter=max_iter, rng=rng, abort_above=abort_above)
    first = rank3_lm(ranges, dim=dim, model="linear", p0=p0, max_iter=max_iter, rng=rng,
                     abort_above=abort_above if model == "linear" else None)
    if model == "linear":
        return first
    second = rank3_lm(ranges, dim=dim, model=model, p0=first.p, max_iter=max_iter, abort_above=abort_above)
    return _replace(
        second,
        iterations=first.iterations + second.iterations,
        total_iterations=first.iterations + second.iterations,
        seconds=first.seconds + second.seconds,
        history=np.concatenate([first.history, second.history]),
        steps=np.concatenate([first.steps, second.steps]),
    )


# ----------------------------------------------------------------------------- with acceptance


def estimate_offsets(
    ranges: Any,
    *,
    dim: int = 3,
    method: str = "fast",
    model: str | None = None,
    accept: float | None = THESIS_ACCEPT,
    max_restarts: int | None = None,
    early_abort: bool = True,
    lam: float = 0.0,
    max_iter: int | None = None,
    tol: float = THESIS_TOL,
    rng: np.random.Generator | int | None = None,
) -> Rank3Result:
    """Onset times and internal delays with the thesis's acceptance test and restarts (004 sec. 4.3, 6.2).

    Runs :func:`fast_offsets` (``method="fast"``, first from p = 0, then from thesis random
    starts) or :func:`rank3_iteration` (``"faithful"``, thesis random starts). A run whose final
    Frobenius norm F (3.17) exceeds ``accept`` has converged to a local minimum and is
    restarted from a new random initialisation (the thesis's future-work proposal, sec. 6.2;
    with ``early_abort`` a faithful run is stopped as soon as it is almost converged above
    ``accept``), at most ``max_restarts`` times. If no run is accepted, the one with the
    smallest F is returned with ``accepted=False`` and a :class:`ConvergenceWarning`.
    ``accept=None`` (noisy data, where no absolute threshold fits) runs all
    ``max_restarts + 1`` starts and returns the smallest F.

    Parameters
    ----------
    ranges : (I, J) times times the speed c, metres (rows = receivers); NaN = missing is
        supported by the fast method only.
    dim : 3 (thesis) or 2.
    method : ``"fast"`` or ``"faithful"``.
    model : ``"exact"`` / ``"linear"``; default ``"exact"`` for fast, ``"linear"`` for faithful
        (the faithful iteration implements only the thesis's Gamma = 0 model).
    accept : acceptance threshold on F, m^2; default 8e-7 s^2 x (343 m/s)^2 = 0.094 m^2 (thesis,
        noise-free; with timing noise F grows with the noise and the threshold must follow).
    max_restarts : restarts after rejected runs (default 30 fast, 10 faithful; 5 with accept=None).
    early_abort : the faithful iteration's early restart (``abort_above=accept``).
    lam, tol : passed to the faithful iteration.
    max_iter : iteration cap per run (default 1e6 faithful, 100 per stage fast).
    rng : seed or Generator.

    Returns
    -------
    Rank3Result; ``restarts`` says how many restarts were needed, ``total_iterations`` counts all runs.
    """
    t0 = time.perf_counter()
    check_choice(method, "method", ("fast", "faithful"))
    model = model or ("exact" if method == "fast" else "linear")
    check_choice(model, "model", ("exact", "linear"))
    if method == "faithful" and model != "linear":
        raise InputError("the faithful thesis iteration implements only model='linear' (Gamma = 0)")
    if max_restarts is None:
        max_restarts = 5 if accept is None else (30 if method == "fast" else 10)
    if max_restarts < 0:
        raise InputError(f"max_restarts must be >= 0, got {max_restarts}")
    shape = np.shape(ranges)
    gen = as_rng(rng)
    best: Rank3Result | None = None
    total = 0
    for attempt in range(int(max_restarts) + 1):
        if method == "fast":
            # p = 0 first: a deterministic start that lands in the right basin at least as often
            # as a random one; the restarts use the thesis random initialisation
            p0 = np.zeros(shape[0] + shape[1] - 1) if attempt == 0 else None
            res = fast_offsets(ranges, dim=dim, model=model, max_iter=max_iter or 100, rng=gen, p0=p0)
        else:
            res = rank3_iteration(
                ranges, dim=dim, lam=lam, tol=tol, max_iter=max_iter or 1_000_000, rng=gen,
                abort_above=accept if early_abort else None,
            )
        total += res.iterations
        ok = None if accept is None else bool(np.isfinite(res.frobenius) and res.frobenius <= accept)
        res = _replace(res, accepted=ok, restarts=attempt, total_iterations=total)
        if best is None or res.frobenius < best.frobenius:
            best = res
        if ok:
            return _replace(res, seconds=time.perf_counter() - t0)
    assert best is not None
    if accept is not None:
        warnings.warn(
            f"no run of the rank-{dim} offset estimation reached F <= {accept:g} m^2 in {max_restarts + 1} "
            f"runs (best F = {best.frobenius:.3g} m^2); noisy data need a larger 'accept' or accept=None",
            ConvergenceWarning,
            stacklevel=2,
        )
    return _replace(best, total_iterations=total, seconds=time.perf_counter() - t0)


# ----------------------------------------------------------------------------- positions


def positions_from_ranges(ranges: Any, dim: int = 3) -> tuple[Array, Array]:
    """Receiver and sender positions from an offset-free, complete (I, J) range matrix.

    Rank-d factorisation of the double-centred squared ranges ``-M/2 = X Y^T`` fixes the
    positions up to an invertible H: ``r_i = H^T x_i`` (r_1 = 0), ``s_j = s_1 + H^{-1} y_j``.
    The first column gives ``|r_i|^2 - 2 r_i^T s_1 = D_i1^2 - D_11^2``, linear in ``L = H H^T``
    and ``b = H s_1`` (the upgrade of Kuang et al. 2013); H = chol(L). Needs
    I-1 >= d(d+3)/2 (9 in 3-D, 5 in 2-D); otherwise the roles of receivers and senders are
    swapped. The result is a starting point for the NLS refinement, not a final estimate.
    """
    dim = check_dim(dim)
    D = as_matrix(ranges, "ranges", allow_nan=False, min_shape=(2, 2))
    need = dim * (dim + 3) // 2
    I, J = D.shape
    if I - 1 < need:
        if J - 1 >= need:
            s, r = positions_from_ranges(D.T, dim)
            return r, s
        raise DegenerateGeometryError(
            f"{I} x {J} ranges: the linear position upgrade needs at least {need + 1} receivers or senders "
            f"in {dim}-D; add units or give solve_toa an initial geometry",
            kind="too-few-units",
        )
    M = double_centre(D * D)
    U, s, Vt = np.linalg.svd(-0.5 * M, full_matrices=False)
    X = U[:, :dim] * np.sqrt(s[:dim])
    Y = Vt[:dim].T * np.sqrt(s[:dim])
    rhs = D[1:, 0] ** 2 - D[0, 0] ** 2
    iu = np.triu_indices(dim)
    quad = np.stack([X[:, a] * X[:, b] * (1.0 if a == b else 2.0) for a, b in zip(*iu, strict=True)], axis=1)
    sol, *_ = np.linalg.lstsq(np.hstack([quad, -2 * X]), rhs, rcond=None)
    L = np.zeros((dim, dim))
    L[iu] = sol[: len(iu[0])]
    L = L + np.triu(L, 1).T
    w, V = np.linalg.eigh(L)
    w = np.maximum(w, 1e-9 * max(float(w.max()), 1e-12))  # noise can make L indefinite: nearest PD
    L = (V * w) @ V.T
    H = np.linalg.cholesky(L)
    b = sol[len(iu[0]):]
    s1 = np.linalg.solve(H, b)
    receivers = np.vstack([np.zeros(dim), X @ H])
    sources = s1[None, :] + np.linalg.solve(H, Y.T).T
    sources = np.vstack([s1, sources])
    return receivers, sources


def _start_from_offsets(R: Array, res: Rank3Result, dim: int,
                        gen: np.random.Generator) -> tuple[Array, Array, Array, Array]:
    """(receivers, sources, receiver_offsets, source_offsets) from one rank-d offset estimate.

    Positions come from the offset-free ranges (completed by the rank-d fit where ``R`` is
    missing) through :func:`offset_free_positions`.
    """
    full = res.extra.get("completed", R)
    D = full - res.receiver_offsets[:, None] - res.source_offsets[None, :]
    receivers, sources = offset_free_positions(D, np.isnan(R), dim, rng=gen)
    return receivers, sources, res.receiver_offsets.copy(), res.source_offsets.copy()


def initialize_offsets(
    ranges: Any,
    dim: int = 3,
    *,
    rng: np.random.Generator | int | None = None,
    n_starts: int = 8,
) -> tuple[Array, Array, Array, Array]:
    """Starting geometry and offsets for ``solve_toa(offsets="both")`` (the NLS refinement).

    Fast rank-d estimate of the offsets (:func:`fast_offsets`, exact model, from p = 0 and then
    up to ``n_starts - 1`` thesis random initialisations, keeping the smallest F and stopping
    early at a noise-free fit or, where p is identifiable with margin, once the two best
    starts agree (:func:`_two_agree`)), then positions from the offset-free ranges
    (:func:`positions_from_ranges`). Missing (NaN) entries are completed inside the rank-d
    fit (:func:`rank3_lm`, alternating projection, no dense unknowns).

    Parameters
    ----------
    ranges : (I, J) metres (times times c), NaN = missing; rows = receivers.
    dim : 2 or 3.
    rng : seed or Generator for the random restarts.
    n_starts : maximal number of starts.

    Returns
    -------
    receivers (I, d), sources (J, d), receiver_offsets (I,), source_offsets (J,) with
    ``source_offsets[0] == 0`` (the common shift lives in the receiver offsets), metres.
    """
    dim = check_dim(dim)
    R = as_matrix(ranges, "ranges", allow_nan=True, min_shape=(2, 2))
    check_rank_identifiable(R.shape[0], R.shape[1], dim)
    gen = as_rng(rng)
    K = R.shape[0] + R.shape[1] - 1
    best = fast_offsets(R, dim=dim, p0=np.zeros(K))
    level = 1e-9 * float(np.nansum(R * R))
    stop_ok = _early_stop_ok(R.shape[0], R.shape[1], dim)
    runs = [best]
    for _ in range(max(1, int(n_starts)) - 1):
        if best.frobenius <= level:
            break  # a noise-free fit: the global minimum
        if stop_ok and _two_agree(runs, R):
            break  # the best basin was reached from two starts
        res = fast_offsets(R, dim=dim, rng=gen, abort_above=_abort_level(runs) if stop_ok else None)
        runs.append(res)
        if res.frobenius < best.frobenius:
            best = res
    start = _start_from_offsets(R, best, dim, gen)
    if np.isnan(R).any():
        # Missing entries as free unknowns of the rank-d fit widen its non-convex landscape:
        # from p = 0 or thesis random starts it lands in a wrong basin in most runs once
        # ~10 % of the entries are missing (measured: 0-2 of 8 starts on 20 x 20 and 12-unit
        # layouts). The complete core + growth start has no completion unknowns at all.
        grown = _core_and_grow(R, dim, gen, n_starts)
        if grown is not None and _model_rms(R, *grown) < _model_rms(R, *start):
            start = grown
    return start


def _same_p(a: Rank3Result, b: Rank3Result, R: Array) -> bool:
    """Two offset estimates are the same: ``||p_a - p_b|| <= 1e-6 rms(t) sqrt(K)`` (metres).

    The threshold is the one that tells distinct candidates apart
    (:func:`initialize_offsets_candidates`): far above the convergence tolerance of
    :func:`rank3_lm` (1e-12 relative), far below any offset difference that matters.
    """
    scale = float(np.sqrt(np.nanmean(R * R))) or 1.0
    return bool(np.linalg.norm(a.p - b.p) <= 1e-6 * scale * np.sqrt(a.p.size))


def _abort_level(runs: list[Rank3Result]) -> float | None:
    """Objective of the best converged run so far: later starts abort above it (thesis sec. 6.2)."""
    ok = [float(r.extra.get("objective", np.inf)) for r in runs if r.converged and np.isfinite(r.frobenius)]
    return min(ok) if ok else None


def _two_agree(runs: list[Rank3Result], R: Array) -> bool:
    """Stopping rule of the multistart: the two runs with the smallest F reached the same p.

    A basin reached from two independent starts and better than every other basin found is
    taken as the global one; further thesis random starts only re-find it (measured: all 8
    starts land on the same p at 500 units). Applied only where a noise-free F = 0
    identifies p (:func:`_early_stop_ok`).
    """
    ok = [r for r in runs if np.isfinite(r.frobenius)]
    if len(ok) < 2:
        return False
    a, b = sorted(ok, key=lambda r: r.frobenius)[:2]
    return _same_p(a, b, R)


def _early_stop_ok(I: int, J: int, dim: int) -> bool:
    """Whether a noise-free rank-d fit (F ~ 0) identifies the offsets, so the starts may stop.

    Double-centred, the corrected matrix is (I-1) x (J-1) and must have rank d: that is
    (I-1-d)(J-1-d) equations for the I+J-1 unknowns of p (3.5). With few units they barely
    outnumber the unknowns (8 units in 3-D: 16 vs 15) and F = 0 has spurious solutions besides
    the true offsets; we trust a zero F only with at least twice as many equations as unknowns
    (12 units and more in 3-D).
    """
    return (I - 1 - dim) * (J - 1 - dim) >= 2 * (I + J - 1)


def initialize_offsets_candidates(
    ranges: Any,
    dim: int = 3,
    *,
    rng: np.random.Generator | int | None = None,
    n_starts: int = 8,
    max_candidates: int = 4,
) -> list[tuple[Array, Array, Array, Array]]:
    """Several distinct starting geometries + offsets for ``solve_toa`` (the 004 rank-d initialiser).

    Runs :func:`fast_offsets` (exact model) from p = 0 and from up to ``n_starts - 1`` thesis
    random initialisations (004 sec. 3.5.1, 6.2) and keeps the *distinct* offset estimates
    (relative difference of p above 1e-6), ordered by the Frobenius norm F (3.17); each
    becomes a start through :func:`offset_free_positions`. F is the distance of the
    offset-corrected matrix to rank d, not the fit of the model ``|r_i - s_j| + delta_i +
    tau_j``: with few units (8 in 3-D) a wrong basin can have the smallest F, even F = 0 on
    exact data. The caller ranks the candidates by the fit of the full model (``solve_toa``
    after a short NLS refinement). The starts stop early at a noise-free F, or once the two
    best starts agree (:func:`_two_agree`), only when the rank-d equations clearly outnumber
    the unknowns (:func:`_early_stop_ok`).

    Parameters
    ----------
    ranges : (I, J) metres (times times c), NaN = missing; rows = receivers.
    dim : 2 or 3.
    rng : seed or Generator for the random restarts.
    n_starts : maximal number of rank-d starts (>= 1).
    max_candidates : at most this many candidates are returned (>= 1), the smallest F first.

    Returns
    -------
    list of (receivers (I, d), sources (J, d), receiver_offsets (I,), source_offsets (J,)),
    metres, ``source_offsets[0] == 0``; at least one entry. With missing entries the
    complete-core start (:func:`_core_and_grow`) is added when it fits better than the first.
    """
    dim = check_dim(dim)
    R = as_matrix(ranges, "ranges", allow_nan=True, min_shape=(2, 2))
    check_rank_identifiable(R.shape[0], R.shape[1], dim)
    gen = as_rng(rng)
    I, J = R.shape
    K = I + J - 1
    level = 1e-9 * float(np.nansum(R * R))
    stop_ok = _early_stop_ok(I, J, dim)
    runs: list[Rank3Result] = []
    for k in range(max(1, int(n_starts))):
        res = fast_offsets(R, dim=dim, p0=np.zeros(K) if k == 0 else None, rng=None if k == 0 else gen,
                           abort_above=_abort_level(runs) if stop_ok else None)
        if np.isfinite(res.frobenius):
            runs.append(res)
        if stop_ok and runs and min(r.frobenius for r in runs) <= level:
            break  # a noise-free fit that identifies p: the global minimum
        if stop_ok and _two_agree(runs, R):
            break  # the best basin was reached from two starts
    if not runs:
        raise DegenerateGeometryError("the rank-d offset estimation diverged from every start", kind="init-failed")
    runs.sort(key=lambda r: r.frobenius)
    scale = float(np.sqrt(np.nanmean(R * R))) or 1.0
    distinct: list[Rank3Result] = []
    for res in runs:
        if all(np.linalg.norm(res.p - q.p) > 1e-6 * scale * np.sqrt(K) for q in distinct):
            distinct.append(res)
        if len(distinct) >= max(1, int(max_candidates)):
            break
    out: list[tuple[Array, Array, Array, Array]] = []
    for res in distinct:
        try:
            out.append(_start_from_offsets(R, res, dim, gen))
        except DegenerateGeometryError:
            continue
    if not out:
        raise DegenerateGeometryError("no position initialiser produced a finite geometry from the "
                                      "offset-corrected ranges", kind="init-failed")
    if np.isnan(R).any():
        # see initialize_offsets: the complete core + growth start has no completion unknowns
        grown = _core_and_grow(R, dim, gen, n_starts)
        if grown is not None and _model_rms(R, *grown) < _model_rms(R, *out[0]):
            out.insert(0, grown)
    return out


def _model_rms(R: Array, receivers: Array, sources: Array, d: Array, o: Array) -> float:
    """RMS of ``t_ij - |r_i - s_j| - delta_i - tau_j`` over the observed entries (inf if not finite)."""
    return _range_rms(R - d[:, None] - o[None, :], ~np.isnan(R), receivers, sources)


def complete_core(missing: NDArray[np.bool_], dim: int) -> tuple[NDArray[np.intp], NDArray[np.intp]] | None:
    """Rows and columns of a complete sub-matrix on which the rank-d method is identifiable.

    Greedy: drop the row or column with the largest fraction of missing entries until
    none is missing (ties: the first such row / column). Returns (row indices, column
    indices), or None when the complete part left is too small for
    :func:`check_rank_identifiable`. The missing counts are updated incrementally:
    O(I + J) per dropped row or column, O((I + J)^2) in all.
    """
    miss = np.asarray(missing, bool)
    I, J = miss.shape
    alive_r = np.ones(I, bool)
    alive_c = np.ones(J, bool)
    rc = miss.sum(axis=1).astype(float)
    cc = miss.sum(axis=0).astype(float)
    nr, nc = I, J
    while nr and nc and (rc[alive_r] > 0).any():
        fr = np.where(alive_r, rc / nc, -np.inf)
        fc = np.where(alive_c, cc / nr, -np.inf)
        if fr.max() >= fc.max():
            k = int(np.argmax(fr))
            alive_r[k] = False
            cc -= miss[k] & alive_c
            nr -= 1
        else:
            k = int(np.argmax(fc))
            alive_c[k] = False
            rc -= miss[:, k] & alive_r
            nc -= 1
    rows, cols = np.flatnonzero(alive_r), np.flatnonzero(alive_c)
    d = dim
    if nr < d + 2 or nc < d + 2 or (nr - 1 - d) * (nc - 1 - d) < nr + nc - 1:
        return None
    return rows, cols


def _locate_with_offset(anchors: Array, rho: Array) -> tuple[Array, float] | None:
    """Point x and offset b with ``rho_k = |x - a_k| + b`` from >= d+2 anchors, linear (Bancroft form).

    Squaring ``rho_k - b = |x - a_k|`` gives ``rho_k^2 - |a_k|^2 = -2 a_k^T x + 2 rho_k b + w``
    with ``w = |x|^2 - b^2``: linear in (x, b, w); exact on noise-free data when the
    (d+2)-column system has full rank.
    """
    n, d = anchors.shape
    if n < d + 2:
        return None
    A = np.column_stack([-2.0 * anchors, 2.0 * rho, np.ones(n)])
    y = rho * rho - np.einsum("kd,kd->k", anchors, anchors)
    sol, _, rank, _ = np.linalg.lstsq(A, y, rcond=None)
    if rank < d + 2 or not np.isfinite(sol).all():
        return None
    return sol[:d], float(sol[d])


def _core_and_grow(
    R: Array, dim: int, rng: np.random.Generator, n_starts: int
) -> tuple[Array, Array, Array, Array] | None:
    """Start with missing entries: rank-d on a complete core, then add the other nodes one by one.

    The core (:func:`complete_core`) is solved by :func:`initialize_offsets`; each node outside
    it is then placed, with its offset, from its measurements to the nodes already placed
    (:func:`_locate_with_offset`: receiver i from ``t_ij - tau_j = |r_i - s_j| + delta_i``,
    sender j likewise), alternating sides until nothing more can be placed.
    """
    missing = np.isnan(R)
    core = complete_core(missing, dim)
    if core is None:
        return None
    rows, cols = core
    try:
        rc, sc, dc, oc = initialize_offsets(R[np.ix_(rows, cols)], dim, rng=rng, n_starts=n_starts)
    except DegenerateGeometryError:
        return None
    I, J = R.shape
    r = np.full((I, dim), np.nan)
    s = np.full((J, dim), np.nan)
    d = np.full(I, np.nan)
    o = np.full(J, np.nan)
    r[rows], s[cols], d[rows], o[cols] = rc, sc, dc, oc
    progress = True
    while progress and (np.isnan(d).any() or np.isnan(o).any()):
        progress = False
        for i in np.flatnonzero(np.isnan(d)):
            use = ~missing[i] & ~np.isnan(o)
            got = _locate_with_offset(s[use], R[i, use] - o[use])
            if got is not None:
                r[i], d[i] = got
                progress = True
        for j in np.flatnonzero(np.isnan(o)):
            use = ~missing[:, j] & ~np.isnan(d)
            got = _locate_with_offset(r[use], R[use, j] - d[use])
            if got is not None:
                s[j], o[j] = got
                progress = True
    if np.isnan(d).any() or np.isnan(o).any():
        return None
    # the gauge of the result: source_offsets[0] == 0, the common shift in the receiver offsets
    d, o = d + o[0], o - o[0]
    return r, s, d, o


def _range_rms(D: Array, observed: NDArray[np.bool_], receivers: Array, sources: Array) -> float:
    """RMS of ``D_ij - |r_i - s_j|`` over the observed entries; inf for a non-finite geometry."""
    if not (np.isfinite(receivers).all() and np.isfinite(sources).all()):
        return float("inf")
    pred = np.linalg.norm(receivers[:, None, :] - sources[None, :, :], axis=-1)
    res = (D - pred)[observed]
    return float(np.sqrt(np.mean(res * res))) if res.size else float("inf")


def offset_free_positions(
    D: Array, missing: NDArray[np.bool_], dim: int, *, rng: np.random.Generator | int | None = None
) -> tuple[Array, Array]:
    """Positions from the offset-corrected ranges ``D = t - delta_i - tau_j`` (the last step of the init).

    Candidates: the linear upgrade :func:`positions_from_ranges` on the completed matrix
    (then up to 5 re-completions of the missing entries from the current geometry, each
    kept only if it lowers the misfit), and the 003 initialisers
    (:func:`selfcal.toa.mds.initialize_toa_info`) on the observed entries. The candidate
    with the smallest RMS of ``D_ij - |r_i - s_j|`` over the observed entries wins.

    Why several: the linear upgrade solves for ``L = H H^T`` from the squared norms of one
    side, which is (near-)singular when that side lies near a quadric, e.g. a plane
    (microphones on stems at one height, loudspeakers on flat desks): clamping an
    indefinite L then returns positions of 1e6-1e36 m. Those are scored (inf or huge misfit)
    and lose against the MDS family, which has no such degeneracy.

    Parameters
    ----------
    D : (I, J) metres, complete (missing entries completed by the rank-d fit).
    missing : (I, J) bool, the entries that were not measured.
    dim : 2 or 3.
    rng : seed or Generator for the randomised initialisers.

    Returns
    -------
    receivers (I, d), sources (J, d), metres, in an arbitrary gauge.
    """
    observed = ~missing
    cands: list[tuple[float, Array, Array]] = []
    try:
        r, s = positions_from_ranges(np.abs(D), dim)
        score = _range_rms(D, observed, r, s)
        for _ in range(5 if missing.any() else 0):
            # with noise a completed entry can be poorly determined by the rank alone: replace
            # the completed entries by the distances of the current geometry and re-solve
            pred = np.linalg.norm(r[:, None, :] - s[None, :, :], axis=-1)
            r2, s2 = positions_from_ranges(np.abs(np.where(missing, pred, D)), dim)
            score2 = _range_rms(D, observed, r2, s2)
            if not score2 < score:
                break
            r, s, score = r2, s2, score2
        cands.append((score, r, s))
    except (DegenerateGeometryError, np.linalg.LinAlgError):
        pass
    if not cands or not cands[0][0] <= 1e-9 * (1.0 + float(np.abs(D[observed]).max())):
        from . import mds

        try:
            info = mds.initialize_toa_info(np.where(observed, np.abs(D), np.nan), dim, rng=rng)
            cands.append((info.residual_rms, info.receivers, info.sources))
        except DegenerateGeometryError:
            pass
    if not cands:
        raise DegenerateGeometryError(
            "no position initialiser produced a finite geometry from the offset-corrected ranges",
            kind="init-failed",
        )
    _, receivers, sources = min(cands, key=lambda c: c[0])
    return receivers, sources
