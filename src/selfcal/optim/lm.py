"""The one Levenberg-Marquardt driver of selfcal: damping, gain ratio, stopping, batching.

Every refinement of the package (the TOA engines, far-field LM, AOA ML, the pipeline's
known-heights fit) is this loop; what differs between them is a *model* plug-in:

``model.evaluate(x) -> (cost, state)``
    the cost ``sum rho`` at ``x`` and whatever the model wants to keep of that evaluation
    (residuals, IRLS weights :func:`irls`, unit vectors ...). ``cost`` may be NaN / inf: the
    trial is then refused.
``model.linearize(x, state) -> lin``
    the linearisation at an accepted point: ``lin.gnorm`` (norm of the gradient ``J^T W f``),
    ``lin.step(lam) -> dx | None`` (the *step solver* plug-in: the damped system
    ``(H + lam diag H) dx = -g`` solved densely by Cholesky, through a Schur complement
    by Cholesky or by CG, with the *parametrisation* applied: fixed coordinates left out,
    the gauge projected off, affine constraints, projected offsets; None when the damped
    system has no finite solution) and ``lin.predicted(dx)`` (the decrease
    ``-(g^T dx + dx^T H dx / 2)`` of the quadratic model).

and optional hooks with defaults on :class:`Model`: ``retract(x, dx)`` (``x + dx``; a
manifold update for rotations and unit vectors), ``small_step(x, dx, xtol)`` (the step test,
``|dx| <= xtol (xtol + |x|)``), ``stationary(lin, cost)`` (after no damped trial
descends: ``|g| <= 1e-6 max(1, sqrt(2 cost))``) and ``accepted(lin, cost, new, predicted)``
(called after each accepted step, before the step test; the constrained engine switches
to Newton there; a true return stops the run unconverged, the rank-d early abort).

The damping rule (one for every model): Marquardt's diagonal damping ``lam diag(H)``,
``lam`` starting at ``lam0`` (``1e-4``); a trial is accepted when the cost does not rise; after
an accepted step ``lam <- max(lam max(1/3, 1 - (2 rho - 1)^3), LAM_MIN)`` with ``rho`` the
gain ratio (actual over predicted decrease), after a refused one ``lam <- lam nu``,
``nu <- 2 nu`` (``nu = 2`` again after each accepted step). Madsen, Nielsen & Tingleff,
"Methods for non-linear least squares problems" (2004), eq. 3.16: about one trial per
iteration against two for the x10 / /10 rule (12 x 6 TOA with both offsets: 1.08 vs 1.85
trials, 29 % fewer iterations).

Stopping: an accepted step with ``small_step`` or a relative cost decrease
``<= ftol`` (``1e-8``, SciPy's default) converges; ``trials`` refused trials in a row end the
run (converged when ``stationary``); ``max_iter`` iterations end it unconverged.

Batching: :func:`levenberg_marquardt_batch` runs many starts of one problem in lockstep,
each with its own damping, iterate and stopping decisions (the same iterates as one start at
a time, to round-off); its model works on stacks (leading axis = start), see there.

Robust losses: :func:`irls` turns residuals into the robust cost and the IRLS weights
``rho'(z)`` of :func:`selfcal.robust.loss_rho`; models build ``J^T W J`` with them, whose fixed
points are the stationary points of the robust cost.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from .._result import Result
from ..robust import loss_rho

Array = NDArray[np.float64]

__all__ = ["FTOL", "LAM_MIN", "TRIALS", "BatchModel", "LeastSquaresResult", "Model", "damping_after_success", "irls",
           "levenberg_marquardt", "levenberg_marquardt_batch"]

#: relative cost decrease that stops the iteration (SciPy's default ftol)
FTOL = 1e-8
#: damping trials per iteration before the run stops
TRIALS = 12
#: floor of the damping factor (relative to the diagonal)
LAM_MIN = 1e-8
#: initial damping factor
LAM0 = 1e-4


def damping_after_success(lam: Any, actual: Any, predicted: Any) -> Any:
    """Marquardt factor after an accepted step: Nielsen's gain-ratio update (scalar or stacked).

    ``lam * max(1/3, 1 - (2 rho - 1)^3)`` floored at :data:`LAM_MIN`, ``rho = actual /
    predicted`` (0 when the model predicted no decrease). Madsen, Nielsen & Tingleff (2004),
    eq. 3.16.

    Examples
    --------
    >>> round(damping_after_success(1e-2, 1.0, 1.0), 12)  # the model was exact: lam / 3
    0.003333333333
    """
    if isinstance(lam, float) and isinstance(predicted, float):
        rho = actual / predicted if predicted > 0 else 0.0
        return max(lam * max(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3), LAM_MIN)
    rho = np.divide(actual, predicted, out=np.zeros(np.shape(actual)), where=np.asarray(predicted) > 0)
    return np.maximum(lam * np.maximum(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3), LAM_MIN)


def irls(f: Array, loss: str, f_scale: float) -> tuple[float, Array]:
    """Robust cost ``f_scale^2 / 2 sum rho((f / f_scale)^2)`` and the IRLS weights ``rho'``.

    Parameters
    ----------
    f : (m,) residuals; loss, f_scale : :func:`selfcal.robust.loss_rho`'s loss and its scale.

    Returns
    -------
    cost : float; w : (m,) weights (ones for the linear loss).

    Examples
    --------
    >>> import numpy as np
    >>> irls(np.array([0.5, 3.0]), "huber", 1.0)[1].tolist()
    [1.0, 0.3333333333333333]
    """
    if loss == "linear":
        return 0.5 * float(f @ f), np.ones_like(f)
    rho, w = loss_rho((f / f_scale) ** 2, loss)
    return 0.5 * f_scale**2 * float(np.sum(rho)), np.asarray(w, float)


class Linearization(Protocol):
    """What :meth:`Model.linearize` returns (see the module docstring)."""

    gnorm: float

    def step(self, lam: float) -> Array | None: ...

    def predicted(self, dx: Array) -> float: ...


class Model:
    """Base of the driver's model plug-ins: override ``evaluate`` and ``linearize``; the hooks
    have the defaults of the module docstring."""

    def evaluate(self, x: Array) -> tuple[float, Any]:
        raise NotImplementedError

    def linearize(self, x: Array, state: Any) -> Any:
        raise NotImplementedError

    def retract(self, x: Array, dx: Array) -> Array:
        return x + dx

    def small_step(self, x: Array, dx: Array, xtol: float) -> bool:
        return math.sqrt(float(dx @ dx)) <= xtol * (xtol + math.sqrt(float(x @ x)))

    def stationary(self, lin: Any, cost: float) -> bool:
        return bool(lin.gnorm <= 1e-6 * max(1.0, math.sqrt(2 * cost)))

    def accepted(self, lin: Any, cost: float, new: float, predicted: float) -> bool | None:
        return None


class BatchModel:
    """Base of the batched driver's models (:func:`levenberg_marquardt_batch`): override
    ``evaluate`` and ``linearize``; ``small_step`` / ``retract`` left None take the defaults
    ``|dx| <= xtol (xtol + |x|)`` and ``x + dx``."""

    small_step: Callable[[Array, Array, float], NDArray[np.bool_]] | None = None
    retract: Callable[[Array, Array], Array] | None = None

    def evaluate(self, X: Array, rows: Any) -> tuple[Array, Any]:
        raise NotImplementedError

    def linearize(self, X: Array, state: Any) -> Any:
        raise NotImplementedError


@dataclass(frozen=True, repr=False)
class LeastSquaresResult(Result):
    """What the driver returns (one start: scalars; a batch: one entry per start).

    Attributes
    ----------
    x : (n,) or (S, n) the last accepted iterate(s).
    cost : float or (S,) its cost.
    converged : bool or (S,) a stopping rule met (not the iteration cap).
    iterations : int or (S,) linearisations formed.
    state : the model's evaluation state at ``x`` (one start only; None for a batch).
    finite : bool or (S,) False for a start whose start point or cost was not finite.
    history : costs of the accepted iterates, start first (one start only).
    path : the accepted iterates, start first (one start, ``history=True`` only).
    """

    x: Array
    cost: Any
    converged: Any
    iterations: Any
    state: Any = None
    finite: Any = True
    history: tuple[float, ...] = ()
    path: tuple[Array, ...] = ()

    def to_dict(self) -> dict[str, Any]:
        return {"x": self.x, "cost": self.cost, "converged": self.converged,
                "iterations": self.iterations, "finite": self.finite}


def levenberg_marquardt(
    model: Model, x0: Array, *, max_iter: int = 100, xtol: float = 1e-12, ftol: float = FTOL,
    lam0: float | Callable[[Any], float] = LAM0, trials: int = TRIALS, adaptive: bool = True,
    history: bool = False,
) -> LeastSquaresResult:
    """Minimise ``model``'s cost from ``x0`` (module docstring: damping rule and stopping).

    Parameters
    ----------
    model : the :class:`Model` plug-in.
    x0 : (n,) start.
    max_iter : iteration cap; xtol : step tolerance (``model.small_step``); ftol : relative
        cost decrease that stops.
    lam0 : initial damping factor, or a function of the first linearisation giving it;
        trials : refused trials in a row that end the run.
    adaptive : False keeps ``lam0`` and takes every step (paper 000's constant damping).
    history : keep the cost and the point of every accepted iterate.

    Returns
    -------
    LeastSquaresResult

    Examples
    --------
    >>> import numpy as np
    >>> class Line(Model):  # fit y = a t + b
    ...     t, y = np.arange(4.0), np.array([1.0, 3.1, 4.9, 7.0])
    ...     def evaluate(self, x):
    ...         f = x[0] * self.t + x[1] - self.y
    ...         return 0.5 * float(f @ f), f
    ...     def linearize(self, x, f):
    ...         J = np.column_stack([self.t, np.ones(4)])
    ...         H, g = J.T @ J, J.T @ f
    ...         class Lin:
    ...             gnorm = float(np.linalg.norm(g))
    ...             def step(self, lam):
    ...                 return np.linalg.solve(H + lam * np.diag(np.diag(H)), -g)
    ...             def predicted(self, dx):
    ...                 return -(g @ dx + 0.5 * dx @ H @ dx)
    ...         return Lin()
    >>> res = levenberg_marquardt(Line(), np.zeros(2))
    >>> bool(res.converged), np.round(res.x, 3).tolist()
    (True, [1.98, 1.03])
    """
    x = np.array(x0, dtype=float)
    cost, state = model.evaluate(x)
    lam, nu = (lam0 if not callable(lam0) else 0.0), 2.0
    converged = stop = False
    it = 0
    hist = [cost] if history else []
    path = [x] if history else []
    while it < max_iter:
        it += 1
        lin = model.linearize(x, state)
        if it == 1 and callable(lam0):
            lam = lam0(lin)
        improved = False
        for _ in range(trials):
            dx = lin.step(lam)
            if dx is None:
                lam, nu = lam * nu, 2.0 * nu
                continue
            trial = model.retract(x, dx)
            c2, s2 = model.evaluate(trial)
            if not adaptive or c2 <= cost:
                rel = (cost - c2) <= ftol * max(cost, 1e-300)
                abort = False
                if adaptive:
                    pred = lin.predicted(dx)
                    abort = bool(model.accepted(lin, cost, c2, pred))
                    lam = damping_after_success(lam, cost - c2, pred)
                    nu = 2.0
                else:
                    rel = abs(cost - c2) <= ftol * max(cost, 1e-300)
                small = model.small_step(x, dx, xtol)
                rel = rel or c2 == 0.0
                x, cost, state = trial, c2, s2
                if history:
                    hist.append(cost)
                    path.append(x)
                improved = True
                converged = bool(small or rel)
                stop = abort
                break
            lam, nu = lam * nu, 2.0 * nu
        if not improved:  # no damped step descends: a minimum up to round-off if stationary
            converged = model.stationary(lin, cost)
            break
        if stop:
            converged = False
            break
        if converged:
            break
    return LeastSquaresResult(x, cost, converged, it, state, True, tuple(hist), tuple(path))


def levenberg_marquardt_batch(
    model: BatchModel, X0: Array, *, max_iter: int = 100, xtol: float = 1e-12, ftol: float = FTOL,
    lam0: float = LAM0, trials: int = TRIALS,
) -> LeastSquaresResult:
    """:func:`levenberg_marquardt` from every row of ``X0`` in lockstep.

    Each start keeps its own damping, iterate, iteration count and stopping decisions; each
    call of the model serves every start still running. The model works on stacks:

    ``model.evaluate(X, rows) -> (cost (s,), state)``
        at the points ``X`` (s, n) of the starts ``rows`` (s,) (several problems of one shape
        may be batched: ``rows`` says whose data to use); ``state`` a tuple of arrays whose
        leading axis is the start;
    ``model.linearize(X, state) -> lin``
        at the running starts: ``lin.gnorm`` (a,), ``lin.step(lam, t) -> dx`` (t, n) for the
        subset ``t`` (indices into the running starts) still trying, non-finite rows for a
        failed solve, ``lin.predicted(dx, t)`` (t,);
    ``model.small_step(X, dX, xtol)`` (optional) -> (t,) bool, default
        ``|dx| <= xtol (xtol + |x|)``; ``model.retract(X, dX)`` (optional), default ``X + dX``.

    Returns
    -------
    LeastSquaresResult
        Arrays over the starts; ``finite`` False for a start whose point or cost stopped being
        finite (its ``x`` is then its last finite iterate).
    """
    X = np.array(X0, dtype=float, ndmin=2)
    S = X.shape[0]
    lam, nu = np.full(S, lam0), np.full(S, 2.0)
    it = np.zeros(S, np.intp)
    converged = np.zeros(S, bool)
    finite = np.isfinite(X).all(axis=1)
    with np.errstate(all="ignore"):
        cost, state = model.evaluate(X, np.arange(S))
    state = tuple(np.array(s) for s in state)  # writable copies (a broadcast view is not)
    finite &= np.isfinite(cost)
    active = finite.copy()
    small_step, retract = model.small_step, model.retract
    with np.errstate(all="ignore"):
        while active.any():
            a = np.nonzero(active)[0]
            it[a] += 1
            lin = model.linearize(X[a], tuple(s[a] for s in state))
            xnorm = np.linalg.norm(X[a], axis=1)
            trying = np.ones(a.size, bool)
            improved = np.zeros(a.size, bool)
            for _ in range(trials):
                t = np.nonzero(trying)[0]
                if t.size == 0:
                    break
                dx = lin.step(lam[a[t]], t)
                ok = np.isfinite(dx).all(axis=1)
                dx[~ok] = 0.0
                trial = X[a[t]] + dx if retract is None else retract(X[a[t]], dx)
                c2, s2 = model.evaluate(trial, a[t])
                c_old = cost[a[t]]
                acc = ok & np.isfinite(c2) & (c2 <= c_old)
                ka = np.nonzero(acc)[0]
                sa = a[t[ka]]
                gain = c_old[ka] - c2[ka]
                if small_step is None:
                    small = np.linalg.norm(dx[ka], axis=1) <= xtol * (xtol + xnorm[t[ka]])
                else:
                    small = small_step(X[sa], dx[ka], xtol)
                rel = gain <= ftol * np.maximum(c_old[ka], 1e-300)
                pred = lin.predicted(dx, t)[ka]
                lam[sa] = damping_after_success(lam[sa], gain, pred)
                nu[sa] = 2.0
                converged[sa] = small | rel
                X[sa], cost[sa] = trial[acc], c2[acc]
                for s_old, s_new in zip(state, s2, strict=True):
                    s_old[sa] = s_new[acc]
                improved[t[acc]] = True
                trying[t[acc]] = False
                sr = a[t[~acc]]
                lam[sr] *= nu[sr]
                nu[sr] *= 2.0
            stuck = ~improved
            s_stuck = a[stuck]
            # no damped step descends: a minimum up to round-off if the gradient is tiny
            converged[s_stuck] = lin.gnorm[stuck] <= 1e-6 * np.maximum(1.0, np.sqrt(2 * cost[s_stuck]))
            active[s_stuck] = False
            active[a[improved & converged[a]]] = False
            active &= it < max_iter
    return LeastSquaresResult(X, cost, converged, it, None, finite)
