"""Measurement-level SLAC for logs without raw signals (ranges, optionally bearings).

The same Bayesian filter as :mod:`selfcal.slac.filter` (prediction eqs. 20-21, MAP update by
BFGS with the analytic gradient eq. 26, Laplace covariance) with Gaussian observations in
place of the concentrated signal likelihoods:

    range   r_ij = (1 + kappa_ij) |p_j - p_i| - delta_i - delta_j + noise(sigma_r)   (eq. 1)
    bearing b_ij = atan2(y_j - y_i, x_j - x_i) - psi_i + noise(sigma_b)              (eq. 2)

Calibration states: a ranging bias per node (eq. 15) and, beyond the paper, an optional
per-link scale factor ``kappa`` (real radio / UWB ranges show scale errors of several %).
Ranges whose innovation exceeds ``gate`` standard deviations are rejected (outliers).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import scipy.linalg as sla
from numpy.typing import NDArray

from .._checks import as_points, check_choice
from ..errors import InputError
from ..geometry import wrap_angle
from .laplace import map_update
from .state import pose_blocks, pose_means, predict_locations

__all__ = ["RangeConfig", "RangeFilter"]

FArray = NDArray[np.float64]


@dataclass(frozen=True)
class RangeConfig:
    """Settings of :class:`RangeFilter`.

    sigma_v (m/s^1.5), sigma_omega (rad/s^1.5): control-noise densities; sigma_range (m),
    sigma_bearing (rad): observation noise; bias_std (m), scale_std: calibration priors;
    estimate_scale: per-link scale states; gate: innovation gate in standard deviations
    (0 = off); gtol, max_iter: BFGS settings.
    """

    sigma_v: float = 0.05
    sigma_omega: float = float(np.deg2rad(1.0))
    sigma_range: float = 0.3
    sigma_bearing: float = float(np.deg2rad(5.0))
    bias_std: float = 1.0
    scale_std: float = 0.05
    estimate_scale: bool = True
    gate: float = 5.0
    gtol: float = 1e-4
    max_iter: int = 50


class RangeFilter:
    """Localization-only or SLAC filter on range (and bearing) observations.

    Parameters
    ----------
    anchors : (A, 2) known positions (nodes n..n+A-1).
    x0, P0 : (n, 3) initial poses and (n, 3, 3) covariances.
    links : sequence of (rx agent, tx node) pairs that may carry ranges (calibration states
        are created per link for the scale and per node for the biases).
    mode : "slac" or "localization".
    bias_nodes : nodes whose bias is a state (default: every node appearing in ``links``
        except, with a single agent, that agent: its bias is not separable from the anchors').
    """

    def __init__(
        self,
        anchors: FArray,
        x0: FArray,
        P0: FArray,
        links: Sequence[tuple[int, int]],
        *,
        mode: str = "slac",
        config: RangeConfig | None = None,
        bias_nodes: Sequence[int] | None = None,
    ) -> None:
        self.mode = check_choice(mode, "mode", ("slac", "localization"))
        self.cfg = config or RangeConfig()
        self.anchors = as_points(anchors, "anchors", dim=2)
        x0 = np.asarray(x0, dtype=float)
        self.n = x0.shape[0]
        if x0.shape != (self.n, 3) or np.asarray(P0).shape != (self.n, 3, 3):
            raise InputError("x0 must be (n, 3) and P0 (n, 3, 3)")
        self.links = [(int(i), int(j)) for i, j in links]
        n_nodes = self.n + self.anchors.shape[0]
        for i, j in self.links:
            if not (0 <= i < self.n and 0 <= j < n_nodes and i != j):
                raise InputError(f"link ({i}, {j}) must go from an agent to another node")
        blocks = [x0.ravel()]
        covs = [*np.asarray(P0, dtype=float)]
        D = 3 * self.n
        self.bias_index = np.full(n_nodes, -1)
        self.scale_index: dict[tuple[int, int], int] = {}
        if self.mode == "slac":
            if bias_nodes is None:
                used = sorted({j for _, j in self.links} | {i for i, _ in self.links})
                bias_nodes = [k for k in used if not (self.n == 1 and k == 0)]
            for k in bias_nodes:
                self.bias_index[int(k)] = D
                D += 1
            nb = len(bias_nodes)
            blocks.append(np.zeros(nb))
            covs.append(np.eye(nb) * self.cfg.bias_std**2)
            if self.cfg.estimate_scale:
                for lk in self.links:
                    self.scale_index[lk] = D
                    D += 1
                blocks.append(np.zeros(len(self.links)))
                covs.append(np.eye(len(self.links)) * self.cfg.scale_std**2)
        self.x = np.concatenate(blocks)
        self.P = sla.block_diag(*covs)
        self.rejected = 0

    @property
    def poses(self) -> FArray:
        return pose_means(self.x, self.n)

    @property
    def pose_covariances(self) -> FArray:
        return pose_blocks(self.P, self.n)

    def calibration(self) -> dict[str, object]:
        """Bias (per node) and scale (per link) estimates with standard deviations."""
        sd = np.sqrt(np.diag(self.P))
        out: dict[str, object] = {
            "biases": {int(k): float(self.x[i]) for k, i in enumerate(self.bias_index) if i >= 0},
            "bias_std": {int(k): float(sd[i]) for k, i in enumerate(self.bias_index) if i >= 0},
        }
        if self.scale_index:
            out["scales"] = {f"{a}-{b}": float(self.x[i]) for (a, b), i in self.scale_index.items()}
            out["scale_std"] = {f"{a}-{b}": float(sd[i]) for (a, b), i in self.scale_index.items()}
        return out

    def predict(self, controls: FArray, T: float) -> None:
        """Eqs. 20-21 with controls (n, 2) ``[v, omega]`` over ``T`` seconds."""
        self.x, self.P = predict_locations(self.x, self.P, np.asarray(controls, dtype=float), float(T),
                                           self.cfg.sigma_v, self.cfg.sigma_omega)

    def _model(self, x: FArray, obs: list[tuple[int, int, str, float]]) -> tuple[FArray, FArray, FArray]:
        """Predicted observations h (K,), Jacobian (K, D) and noise std (K,)."""
        K, D = len(obs), x.size
        h = np.empty(K)
        J = np.zeros((K, D))
        sd = np.empty(K)
        for k, (i, j, kind, _) in enumerate(obs):
            pi = x[3 * i : 3 * i + 2]
            pj = x[3 * j : 3 * j + 2] if j < self.n else self.anchors[j - self.n]
            dl = pj - pi
            d = float(np.hypot(*dl))
            if kind == "range":
                si = self.scale_index.get((i, j), -1)
                kap = x[si] if si >= 0 else 0.0
                h[k] = (1 + kap) * d
                u = dl / d
                J[k, 3 * i : 3 * i + 2] = -(1 + kap) * u
                if j < self.n:
                    J[k, 3 * j : 3 * j + 2] = (1 + kap) * u
                if si >= 0:
                    J[k, si] = d
                for node in (i, j):
                    bi = self.bias_index[node]
                    if bi >= 0:
                        h[k] -= x[bi]
                        J[k, bi] = -1.0
                sd[k] = self.cfg.sigma_range
            else:
                h[k] = np.arctan2(dl[1], dl[0]) - x[3 * i + 2]
                g = np.array([-dl[1], dl[0]]) / d**2
                J[k, 3 * i : 3 * i + 2] = -g
                if j < self.n:
                    J[k, 3 * j : 3 * j + 2] = g
                J[k, 3 * i + 2] = -1.0
                sd[k] = self.cfg.sigma_bearing
        return h, J, sd

    def update(self, observations: Sequence[tuple[int, int, str, float]]) -> int:
        """MAP update with observations ``(rx agent, tx node, "range"|"bearing", value)``.

        Returns the number of observations used (after the innovation gate).
        """
        obs = [(int(i), int(j), str(kd), float(v)) for i, j, kd, v in observations]
        for _, _, kd, v in obs:
            if kd not in ("range", "bearing") or not np.isfinite(v):
                raise InputError(f"observation kind must be 'range' or 'bearing' with a finite value, got {kd!r} {v!r}")
        if not obs:
            return 0
        if self.cfg.gate > 0:
            h, J, sd = self._model(self.x, obs)
            z = np.array([o[3] for o in obs])
            innov = z - h
            bear = np.array([o[2] == "bearing" for o in obs])
            innov[bear] = wrap_angle(innov[bear])
            S = np.einsum("kd,de,ke->k", J, self.P, J) + sd**2
            keep = np.abs(innov) <= self.cfg.gate * np.sqrt(S)
            self.rejected += int((~keep).sum())
            obs = [o for o, kp in zip(obs, keep, strict=True) if kp]
            if not obs:
                return 0
        z = np.array([o[3] for o in obs])
        bear = np.array([o[2] == "bearing" for o in obs])

        def fun_grad(x: FArray) -> tuple[float, FArray]:
            h, J, sd = self._model(x, obs)
            r = z - h
            r[bear] = wrap_angle(r[bear])
            w = r / sd**2
            return float(0.5 * np.sum(r * w)), -(J.T @ w)

        def info(x: FArray) -> FArray:
            _, J, sd = self._model(x, obs)
            return (J / sd[:, None] ** 2).T @ J

        self.x, self.P, _ = map_update(self.x, self.P, fun_grad, info, gtol=self.cfg.gtol, max_iter=self.cfg.max_iter)
        return len(obs)
