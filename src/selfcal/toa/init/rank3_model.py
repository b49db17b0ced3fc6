"""The 004 rank-3 model: building blocks, identifiability, the result type (shared by the solvers).

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

Below the condition (e.g. 12 receivers x 6 senders in 3-D: 16 equations for 17 offsets) the
offsets satisfying the rank condition form a one-parameter family (a curve through the true
p; its Jacobian has rank 16, tested), so the method cannot give a start there; the curve is
also weakly conditioned (smallest non-zero singular value ~1e-3 of the largest), so with
20 us timing noise it passes metres away from the true offsets. ``solve_toa`` then relies on
the other initialisers (:mod:`selfcal.toa.init.scaled_starts`).

Files of the 004 method (one job each):
this module (the model), :mod:`.rank3_thesis` (the thesis iteration, the tests'
reference), :mod:`.rank3` (the fast variable-projection LM and the acceptance/restarts),
:mod:`.rank3_joint` (the dense joint LM: small cases and the reference of the scalable
one), :mod:`.offset_positions` (positions from offset-free ranges) and
:mod:`.offsets_init` (the initialiser of ``solve_toa(offsets="both")``).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..._checks import as_matrix, as_rng, check_dim
from ..._result import Result
from ...errors import DegenerateGeometryError, InputError
from ...optim.lm import Model

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


def rank_identifiable(n_receivers: int, n_senders: int, dim: int = 3) -> bool:
    """Whether the rank-d method determines p (:func:`check_rank_identifiable`'s condition)."""
    I, J, d = int(n_receivers), int(n_senders), int(dim)
    return I >= d + 2 and J >= d + 2 and (I - 1 - d) * (J - 1 - d) >= I + J - 1


def check_rank_identifiable(n_receivers: int, n_senders: int, dim: int = 3) -> None:
    """Raise ``DegenerateGeometryError(kind="too-few-units")`` when the rank-d method cannot determine p.

    Condition (see the module docstring): ``I >= d+2``, ``J >= d+2`` and
    ``(I-1-d)(J-1-d) >= I+J-1``; for U units with a microphone and a loudspeaker each,
    U >= 8 in 3-D and U >= 7 in 2-D (thesis 3.18 gives U >= 7 for the full 3-D model).
    """
    I, J, d = int(n_receivers), int(n_senders), int(dim)
    if not rank_identifiable(I, J, d):
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


@dataclass(frozen=True, repr=False)
class Rank3Result(Result):
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


def _lm_start(R0: Array, mask: NDArray[np.bool_], K: int, p0: Any, rng: Any) -> tuple[Any, Array, float, Array]:
    """The LMs' common start: missing indices, the imputed matrix, the feasible bound, the checked p0."""
    I, J = R0.shape
    p = _random_p0(I, J, as_rng(rng)) if p0 is None else np.array(p0, dtype=float).reshape(-1)
    if p.shape != (K,):
        raise InputError(f"p0 must have I+J-1 = {K} entries, got {p.shape}")
    return np.nonzero(mask), _impute(R0), 2.0 * float(np.max(np.abs(R0[~mask]))), p


def _lm_extra(Rx: Array, n_miss: int, cost: float, aborted: bool) -> dict[str, Any]:
    """The LMs' ``extra``: the completed matrix (with missing entries), the objective, the abort."""
    return {**({"completed": Rx} if n_miss else {}), "objective": float(np.sqrt(cost)), "aborted": aborted}


# ----------------------------------------------------------------------------- faithful iteration


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




class Rank3Model(Model):
    """What both linearisations of the rank-d LM share on :func:`selfcal.optim.levenberg_marquardt`:
    the cost ``(*)`` (the squared tail of the corrected matrix), its history, the feasibility
    bound (:func:`_feasible`: a trial outside it is refused like a failed solve), the stopping
    test (step below ``xtol (|x| + xtol)`` or ``sqrt(cost) <= xtol |M|_F``) and the thesis's
    early abort (sec. 6.2: once an iteration lowers (*) by less than 1 % while its square root
    is still 0.1 % above ``abort_above``, the run stops unconverged).

    Subclasses give ``evaluate`` and ``linearize``; a linearisation carries ``dg`` (the
    damped diagonal, whose largest entry times 1e-6 is the first damping) and keeps the last
    step it solved in ``last``.
    """

    def __init__(self, bound: float, scale: float, abort_above: float | None) -> None:
        self.bound, self.scale, self.abort_above = bound, scale, abort_above
        self.hist: list[float] = []
        self.steps: list[float] = []
        self.aborted = False
        self._new = 0.0

    @staticmethod
    def first_damping(lin: Any) -> float:
        return 1e-6 * float(lin.dg.max())

    def _record(self, cost: float, step: float) -> bool:
        """Append one iteration; True when the early abort fires."""
        self.steps.append(step)
        slow = self.hist[-1] ** 2 - cost < 0.01 * cost
        self.hist.append(float(np.sqrt(cost)))
        if (self.abort_above is not None and len(self.steps) >= 3 and slow
                and np.sqrt(cost) > self.abort_above * (1 + 1e-3)):
            self.aborted = True
        return self.aborted

    def accepted(self, lin: Any, cost: float, new: float, predicted: float) -> bool:
        self._new = new
        return self._record(new, float(np.linalg.norm(lin.last)))

    def small_step(self, x: Array, dx: Array, xtol: float) -> bool:
        return bool(np.linalg.norm(dx) <= xtol * (np.linalg.norm(x + dx) + xtol)
                    or np.sqrt(self._new) <= xtol * self.scale)

    def stationary(self, lin: Any, cost: float) -> bool:
        # no decrease even with huge damping: a stationary point of (*), unless the abort fires
        return not self._record(cost, 0.0)


def checked_rank_input(ranges: Any, model: str, centring: str, dim: Any) -> tuple[Any, ...]:
    """Validate the input of the rank-``dim`` offset estimators (:mod:`.rank3`, :mod:`.rank3_joint`).

    Returns ``(dim, R0, mask, I, J, K, n_miss)``: the checked dimension, the (I, J) range matrix
    (NaN = missing), its missing-entry mask, its shape, ``K = I + J - 1`` offsets and the number
    of missing entries. Raises when the missing entries leave fewer equations
    ``(I-1-dim)(J-1-dim)`` than unknowns ``I+J-1 + missing``.
    """
    from ..._checks import check_choice

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
    return dim, R0, mask, I, J, K, n_miss
