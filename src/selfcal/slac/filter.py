"""Cooperative SLAC filter on raw received signals (paper 002, sections III-IV).

State (eqs. 10-16), in this order::

    [x_1, y_1, psi_1, ..., x_n, y_n, psi_n]          location states of the n agents (eq. 12)
    [delta_1 .. delta_n, (delta_anchor_1 ..)]         ranging biases (SLAC mode; eq. 15)
    [g_i for every multi-port agent i]                 [Re vec G_i; Im vec G_i] (eq. 16)

* Prediction (eqs. 20-21): the turn-rate/velocity model (eq. 14) for the location states,
  identity for the calibration states (constant, zero process noise).
* Update (eq. 22-26): ``x_hat = argmin NLL(x) + 1/2 (x - x_bar)^T P_bar^-1 (x - x_bar)`` with
  NLL the negative sum of the concentrated log-likelihoods (eqs. 18/19, 24-25) of every
  received snapshot, solved by BFGS with the analytic gradient (eq. 26). BFGS runs in
  coordinates whitened by the posterior information at the prediction, so that its identity
  start is already a good inverse Hessian (few iterations). Covariance: Laplace
  approximation, the inverse Hessian of the objective at the solution, with the likelihood
  Hessian replaced by its Fisher information (``covariance="fisher"``, default, cheap) or
  taken by central differences of the analytic gradient (``covariance="fd"``, the paper's
  numerical Hessian).
* Range model (eq. 1): the snapshot that agent i receives back from node j has round-trip
  range ``rho = |p_j - p_i| - delta_i - delta_j``; DoA in i's body frame (eq. 2):
  ``phi = atan2(y_j - y_i, x_j - x_i) - psi_i``.
* ``mode="localization"`` removes the calibration states (biases fixed to 0, G to its prior).

Beyond the paper: the anchors' ranging biases can be states too (``anchor_biases=True``),
since eq. 1 adds both ends' biases and real anchors have them as well.

Length (716 lines, above the ~600 guideline): state layout, link bookkeeping, the MAP /
Laplace update and predict / update in one class; splitting them is open in issue 17.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import scipy.linalg as sla
from numpy.typing import NDArray
from scipy.optimize import minimize

from .._checks import as_points, check_choice
from ..errors import InputError
from .antenna import basis_orders
from .likelihood import delay_expansion, fisher_blocks, link_loglik, pack_g, unpack_g
from .motion import motion_jacobian, motion_step, process_noise
from .signals import range_wavenumber

__all__ = ["SlacConfig", "UpdateInfo", "map_update", "predict_locations", "SlacFilter", "tri_solve", "inverse_from_cholesky",
           "propagate_pose_block"]

FArray = NDArray[np.float64]
CArray = NDArray[np.complex128]


@dataclass(frozen=True)
class SlacConfig:
    """Filter settings (defaults: the paper's experiment, section V).

    Attributes
    ----------
    T : update interval in seconds (0.1).
    sigma_v : control-noise density of the linear velocity, m/s^1.5 (0.015).
    sigma_omega : control-noise density of the turn rate, rad/s^1.5 (0.3 deg).
    bandwidth : signal bandwidth / sample rate B in Hz (28.2 MHz).
    bias_std : prior standard deviation of every ranging bias, metres (the paper
        initialises the biases at 0).
    g_rel_std : prior standard deviation of each sampling-matrix entry (real and imaginary
        part), relative to the RMS magnitude of the prior's entries.
    g_order_decay : prior std of the order-u coefficients scaled by ``1 / (1 + decay |u|)``
        (platform scattering adds mostly low orders; 0 = the same std for every order).
    anchor_biases : estimate anchors' biases too (beyond the paper).
    gtol : BFGS stop on the whitened gradient norm (units: prior standard deviations).
    max_iter : BFGS iteration cap per update.
    covariance : "fisher" or "fd" (see module doc).
    optimizer : "quasi-newton" (default, fast) or "bfgs" (scipy's BFGS, the paper's solver);
        both stop at the same whitened-gradient tolerance, i.e. the same MAP estimate
        (:func:`map_update`).
    first_estimates : evaluate the sampling-matrix part of the Fisher information at the prior
        G (first-estimates Jacobian, Huang et al. 2008; beyond the paper). The likelihood is
        exactly invariant to ``(psi, G) -> (psi + t, G diag(e^{j u t}))`` and to
        ``G -> kappa G``; information linearised at a moving G estimate breaks these null
        directions and makes the filter overconfident in heading (NEES far above its band).
    delay_series : evaluate the likelihood through the delay series of
        :func:`~selfcal.slac.likelihood.delay_expansion` (same values, faster).
    smoother_lag : 0 (default) = the paper's filter. K > 0 = fixed-lag smoother (beyond the
        paper, :class:`~selfcal.slac.smoother.SlacSmoother`): every step re-solves the MAP of
        the last K steps jointly (poses rolled out from the window's first pose through the
        control noises) and marginalises the oldest step into the prior. Use K >= 10
        (1 s at T = 0.1 s), 20 recommended: a shorter window does not resolve the
        heading / G ridge and can be worse than the filter (docs/slac_consistency.md).
        Cost: about K / 4 times the filter's time per step.
    """

    T: float = 0.1
    sigma_v: float = 0.015
    sigma_omega: float = float(np.deg2rad(0.3))
    bandwidth: float = 28.2e6
    bias_std: float = 0.5
    g_rel_std: float = 0.25
    g_order_decay: float = 0.0
    anchor_biases: bool = True
    gtol: float = 1e-3
    max_iter: int = 60
    covariance: str = "fisher"
    optimizer: str = "quasi-newton"
    first_estimates: bool = True
    delay_series: bool = True
    smoother_lag: int = 0


@dataclass(frozen=True)
class UpdateInfo:
    """Outcome of one MAP update."""

    iterations: int
    converged: bool
    evaluations: int
    objective: float


_LAPACK = sla.get_lapack_funcs(("potrf", "potri", "trtrs"), (np.empty((1, 1)),))
_POTRF, _POTRI, _TRTRS = _LAPACK
(_GER,) = sla.get_blas_funcs(("ger",), (np.empty((1, 1)),))


def _cholesky_lower(S: FArray) -> FArray:
    """Lower Cholesky factor by LAPACK ``dpotrf`` (no wrapper checks); LinAlgError if not PD."""
    c, info = _POTRF(S, lower=1, clean=1, overwrite_a=0)
    if info != 0:
        raise np.linalg.LinAlgError("matrix is not positive definite")
    return np.asarray(c, dtype=float)


def _safe_cholesky(M: FArray) -> FArray:
    """Lower Cholesky factor of a symmetric matrix that should be positive definite.

    Long static phases drive some variances to ~1e-10 m^2 while others stay ~1: rounding can
    then make the matrix indefinite by a hair, so a growing relative jitter is added.
    """
    S = 0.5 * (M + M.T)
    try:
        return _cholesky_lower(S)
    except np.linalg.LinAlgError:
        d = np.sqrt(np.clip(np.diag(S), 1e-300, None))
        C = S / np.outer(d, d)  # scale to unit diagonal, then regularise the correlation
        for eps in (1e-12, 1e-10, 1e-8, 1e-6, 1e-4):
            try:
                return _cholesky_lower(C + eps * np.eye(S.shape[0])) * d[:, None]
            except np.linalg.LinAlgError:
                continue
        raise


def tri_solve(C: FArray, b: FArray, *, trans: bool = False) -> FArray:
    """Solve ``C z = b`` (or ``C^T z = b``) for a lower-triangular factor C (D, D), b (D,) or (D, K).

    Direct LAPACK ``dtrtrs`` (the scipy wrapper's argument checks cost more than a 123 x 123
    solve). Used for the whitening of the MAP update (eq. 22): ``x = x_bar + C^-T u``.
    """
    z, info = _TRTRS(C, b, lower=1, trans=1 if trans else 0)
    if info != 0:
        raise np.linalg.LinAlgError("singular triangular factor")
    return np.asarray(z, dtype=float)


def inverse_from_cholesky(C: FArray) -> FArray:
    """Symmetric ``(C C^T)^-1`` (D, D) from its lower Cholesky factor C by LAPACK ``dpotri``.

    The Laplace covariance of eq. 22 (inverse Hessian) and the prior information ``P_bar^-1``.
    """
    Pi, info = _POTRI(C, lower=1)
    if info != 0:
        raise np.linalg.LinAlgError("singular Cholesky factor")
    Pi = np.tril(Pi)
    return Pi + np.tril(Pi, -1).T


def _chol_inv(P: FArray) -> FArray:
    return inverse_from_cholesky(_safe_cholesky(P))


def _quasi_newton(
    obj: Callable[[FArray], tuple[float, FArray]],
    D: int,
    gtol: float,
    max_iter: int,
    u0: FArray | None = None,
) -> tuple[FArray, int, bool, int, float]:
    """BFGS from the identity in coordinates whitened by the expected Hessian at the start.

    The same iteration as scipy's BFGS (inverse-Hessian update, same stop rule
    ``max |gradient| < gtol``) without its generic line search: the whitening makes the unit
    step the Newton step of the local quadratic model, so it is tried first and only halved
    while the Armijo condition fails. Typically one objective evaluation per iteration and no
    Python-level line-search machinery (the cost of ``scipy.optimize.minimize`` here).

    ``u0`` (D,) is the start (default: the origin of the whitened coordinates).

    Returns
    -------
    u (D,), iterations, converged, evaluations, objective value.
    """
    u = np.zeros(D) if u0 is None else np.array(u0, dtype=float)
    f, g = obj(u)
    nfev = 1
    Hi = np.eye(D)
    for it in range(max_iter):
        if D == 0 or float(np.max(np.abs(g))) < gtol:
            return u, it, True, nfev, f
        p = -Hi @ g
        slope = float(g @ p)
        if slope >= 0:  # lost descent (rounding in Hi): restart from the whitened identity
            Hi = np.eye(D)
            p = -g
            slope = float(g @ p)
        alpha = 1.0
        for _ in range(40):
            f_new, g_new = obj(u + alpha * p)
            nfev += 1
            if np.isfinite(f_new) and f_new <= f + 1e-4 * alpha * slope:
                break
            alpha *= 0.5
        else:
            return u, it, False, nfev, f
        s_ = alpha * p
        y = g_new - g
        sy = float(s_ @ y)
        if sy > 1e-12 * float(np.sqrt((s_ @ s_) * (y @ y))):
            # BFGS inverse update: (I - r s y^T) Hi (I - r y s^T) + r s s^T
            r = 1.0 / sy
            Hy = Hi @ y
            # in place by BLAS dger on the Fortran view of the C-ordered Hi (rank-1 updates)
            HiF = Hi.T
            HiF = _GER(r * r * float(y @ Hy) + r, s_, s_, a=HiF, overwrite_a=1)
            HiF = _GER(-r, s_, Hy, a=HiF, overwrite_a=1)
            Hi = _GER(-r, Hy, s_, a=HiF, overwrite_a=1).T
        u = u + s_
        f, g = f_new, g_new
    return u, max_iter, float(np.max(np.abs(g))) < gtol, nfev, f


def map_update(
    x_bar: FArray,
    P_bar: FArray,
    fun_grad: Callable[[FArray], tuple[float, FArray]],
    information: Callable[[FArray], FArray],
    *,
    gtol: float = 1e-3,
    max_iter: int = 60,
    covariance: str = "fisher",
    preconditioner: Callable[[FArray], FArray] | None = None,
    optimizer: str = "bfgs",
    x_start: FArray | None = None,
) -> tuple[FArray, FArray, UpdateInfo]:
    """MAP update of eq. 22 (BFGS with the analytic gradient), Laplace covariance.

    Parameters
    ----------
    x_bar, P_bar : (D,), (D, D) predicted mean and covariance (eq. 20-21).
    fun_grad : x -> (NLL, dNLL/dx), the negative log-likelihood of eq. 24 and its gradient.
    information : x -> (D, D) Fisher information of the likelihood at x.
    covariance : "fisher" or "fd" (Hessian of the NLL by central differences of fun_grad).
    preconditioner : x -> (D, D) information used only to whiten the BFGS coordinates
        (default: ``information``).
    optimizer : "bfgs" (``scipy.optimize.minimize`` BFGS in the whitened coordinates, the
        paper's solver) or "quasi-newton" (:func:`_quasi_newton`: the same BFGS iteration with
        unit-step-first Armijo backtracking; same stop rule, same optimum, several times less
        overhead per update).
    x_start : (D,) optional start of the iteration (warm start; default ``x_bar``). The
        whitening then uses the preconditioner information at ``x_start``.

    Returns
    -------
    x_hat (D,), P_hat (D, D), UpdateInfo.
    """
    check_choice(optimizer, "optimizer", ("bfgs", "quasi-newton"))
    Pinv = _chol_inv(P_bar)
    information_at = preconditioner or information
    H0 = Pinv + information_at(x_bar if x_start is None else x_start)
    C = _safe_cholesky(H0)
    u0 = None if x_start is None else C.T @ (np.asarray(x_start, dtype=float) - x_bar)

    def to_x(u: FArray) -> FArray:
        return x_bar + tri_solve(C, u, trans=True)

    def obj(u: FArray) -> tuple[float, FArray]:
        x = to_x(u)
        r = x - x_bar
        nll, g = fun_grad(x)
        Pr = Pinv @ r
        return float(nll + 0.5 * r @ Pr), tri_solve(C, g + Pr)

    if optimizer == "bfgs":
        res = minimize(obj, np.zeros(x_bar.size) if u0 is None else u0, jac=True, method="BFGS",
                       options={"gtol": gtol, "maxiter": max_iter})
        u_hat, nit, ok, nfev, fval = res.x, int(res.nit), bool(res.success), int(res.nfev), float(res.fun)
    else:
        u_hat, nit, ok, nfev, fval = _quasi_newton(obj, x_bar.size, gtol, max_iter, u0)
    x_hat = to_x(u_hat)
    if covariance == "fd":
        D = x_hat.size
        Hl = np.empty((D, D))
        scale = np.sqrt(np.clip(np.diag(P_bar), 1e-18, None))
        for d in range(D):
            h = 1e-4 * scale[d]
            e = np.zeros(D)
            e[d] = h
            Hl[:, d] = (fun_grad(x_hat + e)[1] - fun_grad(x_hat - e)[1]) / (2 * h)
        H = Pinv + 0.5 * (Hl + Hl.T)
    else:
        H = Pinv + information(x_hat)
    H = 0.5 * (H + H.T)
    try:
        P = _chol_inv(H)
    except np.linalg.LinAlgError:
        # an indefinite numerical Hessian: fall back on the Fisher information (always PSD)
        P = _chol_inv(Pinv + information(x_hat))
    info = UpdateInfo(nit, ok, nfev, fval)
    return x_hat, 0.5 * (P + P.T), info


def predict_locations(
    x: FArray, P: FArray, controls: FArray, T: float, sigma_v: float, sigma_omega: float
) -> tuple[FArray, FArray]:
    """Prediction of eqs. 20-21 for a state whose first ``3 n`` entries are agent poses.

    The calibration states (biases, g) have identity motion and zero process noise, so only
    the pose rows and columns of the covariance change: with the block-diagonal pose Jacobian
    F_p (eq. 14) and process noise Q_p, ``P_pp <- F_p P_pp F_p^T + Q_p``,
    ``P_pc <- F_p P_pc`` and ``P_cc`` is untouched (the same as ``F P F^T + Q`` with the full
    F = diag(F_p, I), at O(n D) instead of O(D^3) cost).

    Parameters
    ----------
    x, P : (D,), (D, D) state (m, rad) and covariance; calibration states follow the poses.
    controls : (n, 2) ``[v, omega]`` per agent (m/s, rad/s); T : s; sigma_v : m/s^1.5;
        sigma_omega : rad/s^1.5.

    Returns
    -------
    x_bar (D,), P_bar (D, D) (symmetric).
    """
    u = np.asarray(controls, dtype=float)
    n = u.shape[0]
    p = 3 * n
    poses = x[:p].reshape(n, 3)
    Fl = motion_jacobian(poses, u, T)
    Ql = process_noise(poses, u, T, sigma_v, sigma_omega)
    x_new = x.copy()
    x_new[:p] = motion_step(poses, u, T).ravel()
    Fp = sla.block_diag(*Fl)
    Qp = sla.block_diag(*Ql) + 1e-12 * np.eye(p)  # keeps P_bar positive definite for a static rover
    return x_new, propagate_pose_block(P, Fp, Qp)


def propagate_pose_block(P: FArray, Fp: FArray, Qp: FArray) -> FArray:
    """Covariance prediction (eq. 21) when only the first ``p`` states (the poses) move.

    ``P`` (D, D), pose Jacobian ``Fp`` (p, p), pose process noise ``Qp`` (p, p):
    ``P_pp <- Fp P_pp Fp^T + Qp`` (symmetrised), ``P_pc <- Fp P_pc``, ``P_cc`` unchanged.
    Returns a new (D, D) array.
    """
    p = Fp.shape[0]
    P_new = P.copy()
    rows = Fp @ P[:p]  # (p, D): [F_p P_pp, F_p P_pc]
    Ppp = rows[:, :p] @ Fp.T + Qp
    P_new[:p, :p] = 0.5 * (Ppp + Ppp.T)
    P_new[:p, p:] = rows[:, p:]
    P_new[p:, :p] = rows[:, p:].T
    return P_new


class SlacFilter:
    """Stateful cooperative SLAC / localization filter on raw OFDM snapshots.

    Parameters
    ----------
    anchors : (A, 2) known anchor positions, metres.
    ports : (n,) number of antenna ports M_i of each agent.
    G_prior : sequence of n sampling matrices (M_i, U) or None for single-port agents;
        the EM-simulation or chamber prior (section IV).
    x0 : (n, 3) initial poses ``[x, y, psi]``; P0 : (n, 3, 3) their covariances.
    probe : (N,) the known OFDM spectrum s(n).
    mode : "slac" or "localization".
    config : SlacConfig.

    Nodes are numbered agents 0..n-1 then anchors n..n+A-1 (for ``rx`` / ``tx`` indices).
    """

    def __init__(
        self,
        anchors: FArray,
        ports: Sequence[int] | NDArray[Any],
        G_prior: Sequence[CArray | None],
        x0: FArray,
        P0: FArray,
        probe: CArray,
        *,
        mode: str = "slac",
        config: SlacConfig | None = None,
    ) -> None:
        self.mode = check_choice(mode, "mode", ("slac", "localization"))
        self.config = config or SlacConfig()
        check_choice(self.config.covariance, "covariance", ("fisher", "fd"))
        check_choice(self.config.optimizer, "optimizer", ("quasi-newton", "bfgs"))
        if int(self.config.smoother_lag) < 0:
            raise InputError(f"smoother_lag must be >= 0, got {self.config.smoother_lag}")
        self.anchors = as_points(anchors, "anchors", dim=2)
        self.ports = np.asarray(ports, dtype=int)
        n = self.n = self.ports.size
        if len(G_prior) != n:
            raise InputError(f"G_prior needs one entry per agent ({n}), got {len(G_prior)}")
        x0 = np.asarray(x0, dtype=float)
        P0 = np.asarray(P0, dtype=float)
        if x0.shape != (n, 3) or P0.shape != (n, 3, 3):
            raise InputError(f"x0 must be ({n}, 3) and P0 ({n}, 3, 3); got {x0.shape}, {P0.shape}")
        self.probe = np.asarray(probe, dtype=complex)
        self.N = self.probe.size
        self.k = range_wavenumber(self.config.bandwidth, self.N)
        self._probe_power = np.abs(self.probe) ** 2
        self.S = float(np.sum(self._probe_power))
        self.G_prior = [None if g is None else np.asarray(g, dtype=complex) for g in G_prior]
        for i, g in enumerate(self.G_prior):
            if self.ports[i] > 1 and (g is None or g.shape[0] != self.ports[i]):
                raise InputError(f"agent {i} has {self.ports[i]} ports and needs a ({self.ports[i]}, U) G_prior")
        n_nodes = n + len(self.anchors)
        blocks: list[FArray] = [x0.ravel()]
        cov_blocks: list[FArray] = list(P0)
        self.bias_index = np.full(n_nodes, -1)
        self.g_index: dict[int, NDArray[np.int64]] = {}
        D = 3 * n
        if self.mode == "slac":
            nb = n_nodes if self.config.anchor_biases else n
            self.bias_index[:nb] = D + np.arange(nb)
            blocks.append(np.zeros(nb))
            cov_blocks.append(np.eye(nb) * self.config.bias_std**2)
            D += nb
            for i in range(n):
                if self.ports[i] > 1:
                    G = self.G_prior[i]
                    assert G is not None
                    g = pack_g(G)
                    self.g_index[i] = D + np.arange(g.size)
                    blocks.append(g)
                    rms = float(np.sqrt(np.mean(np.abs(G) ** 2)))
                    orders = np.abs(basis_orders(G.shape[1]))
                    per = self.config.g_rel_std * rms / (1.0 + self.config.g_order_decay * orders)
                    sd = np.tile(np.repeat(per, G.shape[0]), 2)  # matches pack_g's u * M + m layout
                    cov_blocks.append(np.diag(sd**2))
                    D += g.size
        self.x = np.concatenate(blocks)
        self.P = sla.block_diag(*cov_blocks)
        self._g_prior_packed = {i: pack_g(self.G_prior[i]) for i in self.g_index}  # type: ignore[arg-type]
        self._layout_cache: dict[tuple[bytes, bytes], list[dict[str, Any]]] = {}
        self.D = D
        self.steps = 0

    # ------------------------------------------------------------------ accessors
    @property
    def poses(self) -> FArray:
        """(n, 3) current pose estimates."""
        return self.x[: 3 * self.n].reshape(self.n, 3).copy()

    @property
    def pose_covariances(self) -> FArray:
        """(n, 3, 3) current pose covariances."""
        return np.stack([self.P[3 * i : 3 * i + 3, 3 * i : 3 * i + 3] for i in range(self.n)])

    @property
    def biases(self) -> FArray:
        """(n + A,) bias estimates (0 where not estimated)."""
        b = np.zeros(self.bias_index.size)
        m = self.bias_index >= 0
        b[m] = self.x[self.bias_index[m]]
        return b

    @property
    def bias_std(self) -> FArray:
        """(n + A,) bias standard deviations (0 where not estimated)."""
        s = np.zeros(self.bias_index.size)
        m = self.bias_index >= 0
        s[m] = np.sqrt(np.diag(self.P)[self.bias_index[m]])
        return s

    def sampling_matrix(self, i: int) -> CArray | None:
        """Current sampling matrix of agent i (its prior in localization mode)."""
        if i in self.g_index:
            return unpack_g(self.x[self.g_index[i]], int(self.ports[i]), self.G_prior[i].shape[1])  # type: ignore[union-attr,call-overload,misc,arg-type]
        return self.G_prior[i]

    # ------------------------------------------------------------------ prediction
    def predict(self, controls: FArray) -> None:
        """Eqs. 20-21 with controls (n, 2) ``[v, omega]`` (commanded velocity, gyroscope)."""
        u = np.asarray(controls, dtype=float)
        if u.shape != (self.n, 2) or not np.all(np.isfinite(u)):
            raise InputError(f"controls must be a finite ({self.n}, 2) array [v, omega]")
        c = self.config
        self.x, self.P = predict_locations(self.x, self.P, u, c.T, c.sigma_v, c.sigma_omega)

    # ------------------------------------------------------------------ update
    def _layout(self, rx: NDArray[np.int64], tx: NDArray[np.int64]) -> list[dict[str, Any]]:
        """Static per-group index arrays for this link pattern, cached while it is unchanged.

        One group per port count M; index arrays point into x extended by one dummy slot
        (index D) for constants. Also holds the scatter indices of the gradient and of the
        information matrix, and the work buffer of the group's ``X = R * conj(s)``.
        """
        key = (rx.tobytes(), tx.tobytes())
        cached = self._layout_cache.get(key)
        if cached is not None:
            return cached
        D = self.D
        W = D + 1
        layout = []
        for M in np.unique(self.ports[rx]):
            sel = np.flatnonzero(self.ports[rx] == M)
            r, t = rx[sel], tx[sel]
            prx = np.stack([3 * r, 3 * r + 1], axis=1)
            ptx = np.where((t < self.n)[:, None], np.stack([3 * t, 3 * t + 1], axis=1), D)
            brx = np.where(self.bias_index[r] >= 0, self.bias_index[r], D)
            btx = np.where(self.bias_index[t] >= 0, self.bias_index[t], D)
            gidx = None
            if M > 1 and self.mode == "slac":
                gidx = np.stack([self.g_index[int(i)] for i in r])
            tx_agent = (t < self.n)[:, None]
            lay: dict[str, Any] = dict(
                M=int(M), sel=sel, rx=r, tx=t, prx=prx, ptx=ptx, psi=3 * r + 2, brx=brx, btx=btx, gidx=gidx,
                tx_agent=tx_agent, anchor_pos=self.anchors[np.clip(t - self.n, 0, None)],
                Xbuf=np.empty((sel.size, int(M), self.N), dtype=complex),
                exp_work=(np.empty((sel.size, self.N), dtype=complex),
                          np.empty((sel.size, int(M), self.N), dtype=complex)),
            )
            idx = np.column_stack([prx, ptx, brx, btx])
            if M > 1:
                idx = np.column_stack([idx, 3 * r + 2])
            parts = [(idx[:, :, None] * W + idx[:, None, :]).ravel()]
            receivers: list[tuple[int, NDArray[np.int64]]] = []
            if gidx is not None:
                lg = idx[:, :, None] * W + gidx[:, None, :]
                gl = gidx[:, :, None] * W + idx[:, None, :]
                parts += [lg.ravel(), gl.ravel()]
                for i in np.unique(r):
                    receivers.append((int(self.g_index[int(i)][0]), np.flatnonzero(r == i)))
            lay["info_index"] = np.concatenate(parts).astype(np.int64)
            lay["receivers"] = receivers
            layout.append(lay)
        if len(self._layout_cache) >= 8:
            self._layout_cache.pop(next(iter(self._layout_cache)))
        self._layout_cache[key] = layout
        return layout

    def _groups(self, rx: NDArray[np.int64], tx: NDArray[np.int64], snaps: Sequence[CArray],
                noise_var: FArray) -> list[dict[str, Any]]:
        groups = []
        pc = self.probe.conj()
        for lay in self._layout(rx, tx):
            X = lay["Xbuf"]
            for j, l in enumerate(lay["sel"]):
                np.multiply(np.atleast_2d(snaps[l]), pc, out=X[j])
            grp = dict(lay, X=X, var=noise_var[lay["sel"]], exp=None, layout=lay)
            if self.config.delay_series:
                rho0 = self._geometry(np.append(self.x, 0.0), grp)[2]
                grp["exp"] = delay_expansion(X, rho0, self.k, work=lay["exp_work"])
            groups.append(grp)
        return groups

    def _geometry(self, xe: FArray, grp: dict[str, Any]) -> tuple[FArray, ...]:
        pr = xe[grp["prx"]]
        pt = np.where(grp["tx_agent"], xe[grp["ptx"]], grp["anchor_pos"])
        diff = pt - pr
        d = np.maximum(np.hypot(diff[:, 0], diff[:, 1]), 1e-6)  # nodes may pass each other
        rho = d - xe[grp["brx"]] - xe[grp["btx"]]
        phi = np.arctan2(diff[:, 1], diff[:, 0]) - xe[grp["psi"]]
        return diff, d, rho, phi

    def _G_of(self, xe: FArray, grp: dict[str, Any]) -> CArray:
        r = grp["rx"]
        assert isinstance(r, np.ndarray)
        M = int(grp["M"])
        if grp["gidx"] is not None and self.mode == "slac":
            U = self.G_prior[int(r[0])].shape[1]  # type: ignore[union-attr,call-overload,misc,arg-type]
            return unpack_g(xe[grp["gidx"]], M, U)
        return np.stack([self.G_prior[int(i)] for i in r])  # type: ignore[union-attr,call-overload,misc,arg-type]

    @staticmethod
    def _grad_index(grp: dict[str, Any], with_g: bool) -> NDArray[np.int64]:
        """Where each value :meth:`_fun_grad` produces for ``grp`` goes (fixed per update)."""
        parts = [grp["prx"].ravel(), grp["ptx"].ravel(), grp["brx"], grp["btx"]]
        if int(grp["M"]) > 1:
            parts += [grp["prx"].ravel(), grp["ptx"].ravel(), grp["psi"]]
            if with_g:
                parts.append(grp["gidx"].ravel())
        return np.concatenate(parts).astype(np.int64)

    def _fun_grad(self, x: FArray, groups: list[dict[str, Any]]) -> tuple[float, FArray]:
        xe = np.append(x, 0.0)
        idx_parts: list[NDArray[np.int64]] = []
        val_parts: list[FArray] = []
        total = 0.0
        for grp in groups:
            diff, d, rho, phi = self._geometry(xe, grp)
            M = int(grp["M"])
            G = self._G_of(xe, grp) if M > 1 else None
            terms = link_loglik(grp["X"], rho, grp["var"], self.k, self.S,
                                phi=phi if M > 1 else None, G=G, expansion=grp["exp"])
            total -= float(terms.value.sum())
            u = diff / d[:, None]
            gr = terms.d_rho  # minus the gradient of the NLL
            vals = [(gr[:, None] * u).ravel(), (-gr[:, None] * u).ravel(), gr, gr]
            with_g = False
            if M > 1:
                gp = terms.d_phi
                dphi = np.stack([-diff[:, 1], diff[:, 0]], axis=1) / (d**2)[:, None]
                vals += [(gp[:, None] * dphi).ravel(), (-gp[:, None] * dphi).ravel(), gp]
                if grp["gidx"] is not None and self.mode == "slac" and terms.d_G is not None:
                    with_g = True
                    v = np.swapaxes(terms.d_G, 1, 2).reshape(d.size, -1)
                    vals.append(-np.concatenate([v.real, v.imag], axis=1).ravel())
            key = "gscatter" if with_g else "scatter"
            lay = grp["layout"]
            if key not in lay:  # one index vector per group and link pattern, reused by every call
                lay[key] = self._grad_index(grp, with_g)
            idx_parts.append(lay[key])
            val_parts.append(np.concatenate(vals))
        ge = np.asarray(np.bincount(np.concatenate(idx_parts), weights=np.concatenate(val_parts),
                                    minlength=x.size + 1), dtype=float)
        return total, ge[:-1]

    def _information(self, x: FArray, groups: list[dict[str, Any]], fej: bool = True) -> FArray:
        """Fisher information (D, D) of all links at x (eqs. 18-19 mapped by the range model, eq. 1-2).

        Per link, ``J^T F J`` with the (rho, phi) Jacobian J in the pose / bias coordinates and
        the identity for g, from :func:`~selfcal.slac.likelihood.fisher_blocks`; scattered with
        the cached index arrays of :meth:`_layout`. With ``fej`` (and ``first_estimates``) the
        g part is evaluated at the prior G (first-estimates Jacobian).
        """
        D = x.size
        xe = np.append(x, 0.0)
        if fej and self.config.first_estimates and self.mode == "slac":
            for i, gi in self.g_index.items():
                xe[gi] = self._g_prior_packed[i]
        W = D + 1
        idx_parts: list[NDArray[np.int64]] = []
        val_parts: list[FArray] = []
        gg_blocks: list[tuple[int, FArray]] = []
        pp = self._probe_power
        for grp in groups:
            diff, d, rho, phi = self._geometry(xe, grp)
            M = int(grp["M"])
            G = self._G_of(xe, grp) if M > 1 else None
            terms = link_loglik(grp["X"], rho, grp["var"], self.k, self.S,
                                phi=phi if M > 1 else None, G=G, want_grad=False,
                                expansion=grp["exp"])
            fb = fisher_blocks(terms, grp["var"], self.k, pp, phi=phi if M > 1 else None, G=G)
            L_ = d.size
            u = diff / d[:, None]
            J = 6 if M == 1 else 7
            jr = np.zeros((L_, J))
            jr[:, 0:2] = -u
            jr[:, 2:4] = u
            jr[:, 4:6] = -1.0
            Hll = fb.rho_rho[:, None, None] * jr[:, :, None] * jr[:, None, :]
            idx_parts.append(grp["layout"]["info_index"])
            if M == 1:
                val_parts.append(Hll.ravel())
                continue
            dphi = np.stack([-diff[:, 1], diff[:, 0]], axis=1) / (d**2)[:, None]
            jp = np.zeros((L_, J))
            jp[:, 0:2] = -dphi
            jp[:, 2:4] = dphi
            jp[:, 6] = -1.0
            Hll += fb.phi_phi[:, None, None] * jp[:, :, None] * jp[:, None, :]
            val_parts.append(Hll.ravel())
            if grp["gidx"] is not None and self.mode == "slac":
                assert fb.phi_g is not None
                # (rho, phi) -> (pose, bias) block and its coupling with the identity-mapped g block
                Hlg = jp[:, :, None] * fb.phi_g[:, None, :]
                val_parts += [Hlg.ravel(), np.swapaxes(Hlg, 1, 2).ravel()]
                # every link of one receiver adds to the same contiguous g block: sum first
                for g0, links in grp["receivers"]:
                    gg_blocks.append((g0, fb.gg_sum(links)))
        H = np.asarray(np.bincount(np.concatenate(idx_parts), weights=np.concatenate(val_parts),
                                   minlength=W * W), dtype=float).reshape(W, W)
        for g0, blk_g in gg_blocks:
            H[g0 : g0 + blk_g.shape[0], g0 : g0 + blk_g.shape[0]] += blk_g
        return H[:-1, :-1]

    def update(
        self, rx: Sequence[int] | NDArray[Any], tx: Sequence[int] | NDArray[Any], snapshots: Sequence[CArray],
        noise_var: Sequence[float] | NDArray[Any],
    ) -> UpdateInfo:
        """MAP update (eq. 22) with the snapshots agent ``rx[l]`` received from node ``tx[l]``.

        Parameters
        ----------
        rx, tx : (L,) node indices (rx must be an agent).
        snapshots : L arrays (M_rx, N).
        noise_var : (L,) noise variances per bin and port (estimated from the known signal,
            :func:`~selfcal.slac.signals.estimate_noise_variance`).
        """
        rx_a = np.asarray(rx, dtype=int)
        tx_a = np.asarray(tx, dtype=int)
        if rx_a.size == 0:
            return UpdateInfo(0, True, 0, 0.0)
        if np.any(rx_a >= self.n) or np.any(rx_a < 0) or np.any(tx_a < 0) or np.any(tx_a >= self.bias_index.size):
            raise InputError("rx must index agents and tx agents or anchors")
        groups = self._groups(rx_a, tx_a, snapshots, np.asarray(noise_var, dtype=float))
        c = self.config
        self.x, self.P, info = map_update(
            self.x, self.P,
            lambda x: self._fun_grad(x, groups),
            lambda x: self._information(x, groups),
            gtol=c.gtol, max_iter=c.max_iter, covariance=c.covariance, optimizer=c.optimizer,
            preconditioner=lambda x: self._information(x, groups, fej=False),
        )
        self.steps += 1
        return info
