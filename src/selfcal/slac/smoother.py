"""Fixed-lag smoother (sliding-window MAP) for the SLAC filter (beyond paper 002).

The paper's filter (:class:`~selfcal.slac.filter.SlacFilter`) summarises the posterior after
every step by one Gaussian. The multi-port likelihood is invariant to
``(psi, G) -> (psi + t, G diag(e^{j u t}))`` and ``G -> kappa G``, so the posterior is a curved
ridge and an early error along it is locked in (``docs/slac_consistency.md``). This smoother
re-solves the last K steps jointly at every step.

Window at step s with K' = min(K, s) steps (base index b = s - K'):

* unknowns ``z = [x_b (3 n), w_b .. w_{s-1} (2 n each), c (D - 3 n)]``: the agent poses at
  the window start, the control noises ``w_k = [dv, domega]`` per agent and step (variances
  ``sigma_v^2 T``, ``sigma_omega^2 T``), and the calibration states c (biases, g);
* poses in the window by the motion model (eq. 14), ``x_{k+1} = f(x_k, u_k + w_k)``, so the
  singular process noise needs no inverse;
* cost ``1/2 |[x_b; c] - m|^2_{P_m^-1} + 1/2 sum_k w_k^T Q_w^-1 w_k + sum_{k=b+1}^{s} NLL_k([x_k; c])``
  with NLL_k the negative log-likelihood of the snapshots of step k (eqs. 18-19, 24,
  :meth:`SlacFilter.neg_loglik`); its gradient by the chain rule through the rollout
  (adjoint recursion ``lambda_k = dNLL_k/dx_k + F_k^T lambda_{k+1}``, ``dJ/dw_k = B_k^T lambda_{k+1}``);
* minimised by :func:`~selfcal.slac.laplace.map_update` warm-started at the previous window's
  solution; Laplace covariance from the Fisher information chained through the rollout
  Jacobians, ``H = P_z^-1 + sum_k J_k^T I_k J_k`` (first-estimates g information as in the
  filter);
* marginalisation of the oldest step when the window is full: the terms holding only
  ``(x_b, w_b)`` and the oldest measurement are linearised at the window solution and
  ``(x_b, w_b)`` eliminated (linear prediction with the Jacobians at the smoothed estimate, then
  a Gauss-Newton update with the oldest step's gradient and information at the smoothed
  estimate), which gives the Gaussian prior ``(m, P_m)`` on ``[x_{b+1}; c]`` of the next window.

The reported estimate at step s is the window's last pose ``x_s`` with its marginal covariance
``J_s P_z J_s^T`` (and the calibration states), i.e. a filtered (not smoothed) estimate for
step s, comparable with the filter's.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import Any

import numpy as np
import scipy.linalg as sla
from numpy.typing import NDArray

from ..errors import InputError
from .filter import SlacFilter
from .laplace import UpdateInfo, map_update
from .linalg import safe_cholesky, spd_inverse
from .links import LinkGroup
from .motion import control_jacobian, motion_jacobian
from .state import propagate_pose_block

__all__ = ["SlacSmoother"]

FArray = NDArray[np.float64]
CArray = NDArray[np.complex128]


class SlacSmoother:
    """Fixed-lag sliding-window MAP smoother on top of a :class:`SlacFilter` (see module doc).

    Parameters
    ----------
    filt : the filter that defines the state layout, the priors and the per-step likelihood;
        its ``x`` / ``P`` are overwritten after every step with the estimate at the newest
        step (so its accessors ``poses``, ``pose_covariances``, ``biases``, ``bias_std``,
        ``sampling_matrix`` report the smoother's current estimate).
    lag : window length K >= 1 (steps).
    """

    def __init__(self, filt: SlacFilter, lag: int) -> None:
        if int(lag) < 1:
            raise InputError(f"smoother lag must be >= 1, got {lag}")
        self.filt = filt
        self.lag = int(lag)
        self.n = filt.n
        self.p = 3 * filt.n
        c = filt.config
        self._qw = np.tile([c.sigma_v**2 * c.T, c.sigma_omega**2 * c.T], self.n)  # (2 n,) per step
        # prior on [x_b; c] (window base and calibration)
        self.m = filt.x.copy()
        self.Pm = filt.P.copy()
        self.controls: list[FArray] = []  # u_b .. u_{s-1}, each (n, 2)
        self.groups: list[list[LinkGroup]] = []  # measurement groups of steps b+1 .. s
        self.z = self.m.copy()  # current window solution [x_b, w_b.., c] (no w yet)
        self.steps = 0

    # ------------------------------------------------------------------ layout
    @property
    def window(self) -> int:
        """Number of steps K' currently in the window."""
        return len(self.controls)

    def _split(self, z: FArray) -> tuple[FArray, FArray, FArray]:
        """``z -> (x_b (n, 3), w (K', n, 2), c (D - 3 n,))``."""
        K = self.window
        p, n = self.p, self.n
        return z[:p].reshape(n, 3), z[p : p + 2 * n * K].reshape(K, n, 2), z[p + 2 * n * K :]

    def _rollout(self, z: FArray) -> tuple[FArray, FArray, FArray]:
        """Poses (K'+1, n, 3) of the window, pose Jacobians F (K', n, 3, 3) and control Jacobians B (K', n, 3, 2)."""
        x0, w, _ = self._split(z)
        T = self.filt.config.T
        K = self.window
        U = np.asarray(self.controls).reshape(K, self.n, 2) + w  # (K, n, 2) noisy controls
        # eq. 14 as x' = x + v T cos(psi + h) sinc(h) (motion_step), unrolled: sinc(h) per step
        # and agent does not depend on the state, so it is computed once for the window
        h = U[..., 1] * T / 2.0
        vs = U[..., 0] * T * np.sinc(h / np.pi)
        X = np.empty((K + 1, self.n, 3))
        X[0] = x0
        for k in range(K):
            th = X[k, :, 2] + h[k]
            X[k + 1, :, 0] = X[k, :, 0] + vs[k] * np.cos(th)
            X[k + 1, :, 1] = X[k, :, 1] + vs[k] * np.sin(th)
            X[k + 1, :, 2] = X[k, :, 2] + U[k, :, 1] * T
        F = motion_jacobian(X[:-1], U, T)
        B = control_jacobian(X[:-1], U, T)
        return X, F, B

    def _pose_jacobians(self, F: FArray, B: FArray) -> list[FArray]:
        """``d x_k / d [x_b, w]`` (3 n, 3 n + 2 n K') for k = 0..K' (block structure, dense)."""
        n, p, K = self.n, self.p, self.window
        cols = p + 2 * n * K
        J = np.zeros((p, cols))
        J[:, :p] = np.eye(p)
        out = [J]
        for k in range(K):
            J = sla.block_diag(*F[k]) @ J
            J[:, p + 2 * n * k : p + 2 * n * (k + 1)] += sla.block_diag(*B[k])
            out.append(J)
        return out

    # ------------------------------------------------------------------ window objective
    def fun_grad(self, z: FArray) -> tuple[float, FArray]:
        """Window negative log-likelihood ``sum_k NLL_k([x_k(z); c])`` and its gradient (Dz,).

        Gradient by the adjoint recursion through the rollout (module doc). The Gaussian
        prior and control-noise terms are added by :func:`map_update`.
        """
        X, F, B = self._rollout(z)
        _, _, c = self._split(z)
        K, n, p = self.window, self.n, self.p
        total = 0.0
        lam = np.zeros((K + 1, n, 3))
        gc = np.zeros(c.size)
        for j in range(1, K + 1):
            if not self.groups[j - 1]:
                continue
            f, g = self.filt.neg_loglik(np.concatenate([X[j].ravel(), c]), self.groups[j - 1])
            total += f
            lam[j] = g[:p].reshape(n, 3)
            gc += g[p:]
        gw = np.zeros((K, n, 2))
        acc = lam[K]
        for k in range(K - 1, -1, -1):
            gw[k] = np.einsum("nij,ni->nj", B[k], acc)
            acc = lam[k] + np.einsum("nij,ni->nj", F[k], acc)
        return total, np.concatenate([acc.ravel(), gw.ravel(), gc])

    def information(self, z: FArray, fej: bool = True) -> FArray:
        """Fisher information (Dz, Dz) of the window likelihood: ``sum_k J_k^T I_k J_k``.

        ``I_k`` (D, D) is the filter's information of step k at ``[x_k; c]``
        (:meth:`SlacFilter.information`, first-estimates g part when ``fej``), ``J_k`` the
        Jacobian of ``[x_k; c]`` with respect to z (pose rows through the rollout, identity for c).
        """
        X, F, B = self._rollout(z)
        _, _, c = self._split(z)
        Js = self._pose_jacobians(F, B)
        p = self.p
        nxw = Js[0].shape[1]
        Dz = z.size
        H = np.zeros((Dz, Dz))
        for j in range(1, self.window + 1):
            if not self.groups[j - 1]:
                continue
            Ik = self.filt.information(np.concatenate([X[j].ravel(), c]), self.groups[j - 1], fej=fej)
            J = Js[j]
            Ipp, Ipc = Ik[:p, :p], Ik[:p, p:]
            H[:nxw, :nxw] += J.T @ Ipp @ J
            cross = J.T @ Ipc
            H[:nxw, nxw:] += cross
            H[nxw:, :nxw] += cross.T
            H[nxw:, nxw:] += Ik[p:, p:]
        return H

    def _prior(self) -> tuple[FArray, FArray]:
        """Gaussian prior (mean (Dz,), covariance (Dz, Dz)) on z: ``(m, P_m)`` on [x_b; c], ``N(0, Q_w)`` on w."""
        p, K = self.p, self.window
        nw = self._qw.size * K
        Dz = self.m.size + nw
        zbar = np.concatenate([self.m[:p], np.zeros(nw), self.m[p:]])
        P = np.zeros((Dz, Dz))
        idx = np.concatenate([np.arange(p), p + nw + np.arange(self.m.size - p)])
        P[np.ix_(idx, idx)] = self.Pm
        P[p : p + nw, p : p + nw] = np.diag(np.tile(self._qw, K))
        return zbar, P

    # ------------------------------------------------------------------ marginalisation
    def _marginalize_oldest(self) -> None:
        """Eliminate ``(x_b, w_b)`` and the oldest measurement step into the prior on ``[x_{b+1}; c]``.

        Linearised at the current window solution ``(x*, w*, c*)``: with ``F, B`` the motion
        Jacobians at ``(x*, u_b + w*)`` and ``y* = [f(x*, u_b + w*); c*]``,
        ``y_bar = [y*_x + F (m_x - x*) - B w*; m_c]``,
        ``P_bar = [[F P_xx F^T + B Q_w B^T, F P_xc], [P_cx F^T, P_cc]]`` (the prediction of
        eqs. 20-21 linearised at the smoothed estimate); then with the oldest step's gradient
        ``g`` and information ``I`` at y*: ``Lambda = P_bar^-1 + I``,
        ``m' = y* - Lambda^-1 (P_bar^-1 (y* - y_bar) + g)``, ``P_m' = Lambda^-1``.
        """
        n, p = self.n, self.p
        X, F, B = self._rollout(self.z)
        x0, w, c = self._split(self.z)
        Fp = sla.block_diag(*F[0])
        Bp = sla.block_diag(*B[0])
        ystar = np.concatenate([X[1].ravel(), c])
        ybar = self.m.copy()
        ybar[:p] = X[1].ravel() + Fp @ (self.m[:p] - x0.ravel()) - Bp @ w[0].ravel()
        Pb = propagate_pose_block(self.Pm, Fp, Bp @ np.diag(self._qw) @ Bp.T + 1e-12 * np.eye(p))
        Pinv = spd_inverse(Pb)
        grp = self.groups[0]
        if grp:
            _, g = self.filt.neg_loglik(ystar, grp)
            info = self.filt.information(ystar, grp)
        else:
            g = np.zeros(ystar.size)
            info = np.zeros((ystar.size, ystar.size))
        Lam = Pinv + info
        Cl = safe_cholesky(0.5 * (Lam + Lam.T))
        rhs = Pinv @ (ystar - ybar) + g
        step = np.linalg.solve(Cl.T, np.linalg.solve(Cl, rhs))
        self.m = ystar - step
        Pn = spd_inverse(Lam)
        self.Pm = 0.5 * (Pn + Pn.T)
        # drop the oldest step; the window now starts at x_{b+1}
        nw = 2 * n
        self.z = np.concatenate([X[1].ravel(), w[1:].ravel(), c])
        del self.controls[0]
        del self.groups[0]
        assert self.z.size == p + nw * self.window + c.size

    # ------------------------------------------------------------------ one step
    def step(
        self, controls: FArray, rx: Sequence[int] | NDArray[Any], tx: Sequence[int] | NDArray[Any],
        snapshots: Sequence[CArray], noise_var: Sequence[float] | NDArray[Any],
    ) -> UpdateInfo:
        """Advance by one step: controls (n, 2) ``[v, omega]`` from the previous state, then the
        snapshots of the new state (``rx``, ``tx`` (L,), ``snapshots`` L arrays (M_rx, N),
        ``noise_var`` (L,), as :meth:`SlacFilter.update`). Re-solves the window MAP and writes the
        estimate at the new step (and its covariance, D x D) into the filter's ``x`` / ``P``.
        """
        f = self.filt
        u = np.asarray(controls, dtype=float)
        if u.shape != (self.n, 2) or not np.all(np.isfinite(u)):
            raise InputError(f"controls must be a finite ({self.n}, 2) array [v, omega]")
        rx_a = np.asarray(rx, dtype=int)
        tx_a = np.asarray(tx, dtype=int)
        if np.any(rx_a >= self.n) or np.any(rx_a < 0) or np.any(tx_a < 0) or np.any(tx_a >= f.bias_index.size):
            raise InputError("rx must index agents and tx agents or anchors")
        # warm start: previous solution, zero noise on the new control
        x0, w, c = self._split(self.z)
        self.controls.append(u.copy())
        self.z = np.concatenate([x0.ravel(), w.ravel(), np.zeros(2 * self.n), c])
        X, _, _ = self._rollout(self.z)
        # measurement groups (delay series around the dead-reckoned prediction); X is copied
        # because the filter's layout cache reuses one buffer per link pattern
        f.x = np.concatenate([X[-1].ravel(), c])
        groups: list[LinkGroup] = []
        if rx_a.size:
            groups = [dataclasses.replace(g, X=np.array(g.X, copy=True))
                      for g in f.link_groups(rx_a, tx_a, snapshots, np.asarray(noise_var, dtype=float))]
        self.groups.append(groups)
        if self.window > self.lag:
            # undo the append, marginalise at the previous solution, re-append
            u_new, g_new = self.controls.pop(), self.groups.pop()
            self.z = np.concatenate([x0.ravel(), w.ravel(), c])
            self._marginalize_oldest()
            x0, w, c = self._split(self.z)
            self.controls.append(u_new)
            self.groups.append(g_new)
            self.z = np.concatenate([x0.ravel(), w.ravel(), np.zeros(2 * self.n), c])
        zbar, Pz = self._prior()
        cfg = f.config
        z_hat, Pz_hat, info = map_update(
            zbar, Pz, self.fun_grad, self.information,
            gtol=cfg.gtol, max_iter=cfg.max_iter, covariance=cfg.covariance, optimizer=cfg.optimizer,
            preconditioner=lambda z: self.information(z, fej=False), x_start=self.z,
        )
        self.z = z_hat
        X, F, B = self._rollout(z_hat)
        _, _, c = self._split(z_hat)
        Jx = self._pose_jacobians(F, B)[-1]
        nxw = Jx.shape[1]
        J = np.zeros((f.D, z_hat.size))
        J[: self.p, :nxw] = Jx
        J[self.p :, nxw:] = np.eye(c.size)
        f.x = np.concatenate([X[-1].ravel(), c])
        P = J @ Pz_hat @ J.T
        f.P = 0.5 * (P + P.T)
        f.steps += 1
        self.steps += 1
        return info
