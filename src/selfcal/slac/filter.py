"""Cooperative SLAC filter on raw received signals (paper 002, sections III-IV).

The filter's predict / update loop; its parts live in their own modules:

* :mod:`~selfcal.slac.state` -- the state layout (eqs. 10-16: poses, ranging biases, packed
  sampling matrices), the prior, and the prediction (eqs. 20-21: the turn-rate/velocity model
  of eq. 14 for the poses, identity with zero process noise for the calibration states);
* :mod:`~selfcal.slac.links` -- the link bookkeeping (typed index layouts per port count) and the
  likelihood of all links with its gradient and Fisher information (eqs. 1-2, 18-19, 24-26);
* :mod:`~selfcal.slac.laplace` -- the MAP update (eq. 22) by BFGS in whitened coordinates with
  the Laplace covariance (Fisher information, ``covariance="fisher"``, default, or central
  differences of the analytic gradient, ``"fd"``, the paper's numerical Hessian);
* :mod:`~selfcal.slac.linalg` -- the Cholesky factors, triangular solves and inverses shared
  with the smoother.

``mode="localization"`` removes the calibration states (biases fixed to 0, G to its prior).
Beyond the paper: the anchors' ranging biases can be states too (``anchor_biases=True``),
since eq. 1 adds both ends' biases and real anchors have them as well.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .._checks import as_points, check_choice
from ..errors import InputError
from .laplace import UpdateInfo, map_update
from .likelihood import unpack_g
from .linalg import inverse_from_cholesky, tri_solve
from .links import LinkGroup, LinkModel
from .signals import range_wavenumber
from .state import pose_blocks, pose_means, predict_locations, propagate_pose_block, state_layout

__all__ = ["SlacConfig", "SlacFilter", "UpdateInfo", "map_update", "predict_locations", "propagate_pose_block",
           "tri_solve", "inverse_from_cholesky"]

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

    def __post_init__(self) -> None:
        """Refuse a field of the wrong type or outside its range (named, with the value).

        Positive: ``T``, ``bandwidth``, ``gtol`` and the prior stds ``bias_std`` / ``g_rel_std``
        (a zero std makes the prior covariance singular); non-negative: the control-noise
        densities and ``g_order_decay``; integers: ``max_iter >= 1``, ``smoother_lag >= 0``.
        """
        def number(name: str, *, positive: bool) -> None:
            v = getattr(self, name)
            if isinstance(v, (bool, np.bool_)) or not isinstance(v, (int, float, np.integer, np.floating)) \
                    or not np.isfinite(v) or (v <= 0 if positive else v < 0):
                raise InputError(f"SlacConfig.{name} must be a finite number {'> 0' if positive else '>= 0'}, "
                                 f"got {v!r}")

        for name in ("T", "bandwidth", "gtol", "bias_std", "g_rel_std"):
            number(name, positive=True)
        for name in ("sigma_v", "sigma_omega", "g_order_decay"):
            number(name, positive=False)
        for name, low in (("max_iter", 1), ("smoother_lag", 0)):
            v = getattr(self, name)
            if isinstance(v, (bool, np.bool_)) or not isinstance(v, (int, np.integer)) or v < low:
                raise InputError(f"SlacConfig.{name} must be an integer >= {low}, got {v!r}")
        for name in ("anchor_biases", "first_estimates", "delay_series"):
            if not isinstance(getattr(self, name), (bool, np.bool_)):
                raise InputError(f"SlacConfig.{name} must be True or False, got {getattr(self, name)!r}")
        check_choice(self.covariance, "SlacConfig.covariance", ("fisher", "fd"))
        check_choice(self.optimizer, "SlacConfig.optimizer", ("quasi-newton", "bfgs"))


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
        self.G_prior = [None if g is None else np.asarray(g, dtype=complex) for g in G_prior]
        for i, g in enumerate(self.G_prior):
            if self.ports[i] > 1 and (g is None or g.shape[0] != self.ports[i]):
                raise InputError(f"agent {i} has {self.ports[i]} ports and needs a ({self.ports[i]}, U) G_prior")
        c = self.config
        self.layout, self.x, self.P = state_layout(
            self.ports, self.G_prior, x0, P0, len(self.anchors), estimate_calibration=self.mode == "slac",
            anchor_biases=c.anchor_biases, bias_std=c.bias_std, g_rel_std=c.g_rel_std, g_order_decay=c.g_order_decay)
        self.bias_index = self.layout.bias_index
        self.g_index = self.layout.g_index
        self.D = self.layout.D
        self.links = LinkModel(self.anchors, self.ports, self.G_prior, self.probe, self.k, self.layout,
                               calibrate=self.mode == "slac", delay_series=c.delay_series,
                               first_estimates=c.first_estimates)
        self.steps = 0

    # ------------------------------------------------------------------ accessors
    @property
    def poses(self) -> FArray:
        """(n, 3) current pose estimates."""
        return pose_means(self.x, self.n)

    @property
    def pose_covariances(self) -> FArray:
        """(n, 3, 3) current pose covariances."""
        return pose_blocks(self.P, self.n)

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
    def link_groups(self, rx: NDArray[np.int64], tx: NDArray[np.int64], snaps: Sequence[CArray],
                    noise_var: FArray) -> list[LinkGroup]:
        """The link groups of one update, with delay series around the current state (:class:`LinkModel`)."""
        return self.links.groups(rx, tx, snaps, noise_var, self.x)

    def neg_loglik(self, x: FArray, groups: list[LinkGroup]) -> tuple[float, FArray]:
        """Negative log-likelihood of the links at state x and its gradient (D,) (eqs. 24, 26)."""
        return self.links.neg_loglik(x, groups)

    def information(self, x: FArray, groups: list[LinkGroup], fej: bool = True) -> FArray:
        """Fisher information (D, D) of the links at state x (first-estimates g part when ``fej``)."""
        return self.links.information(x, groups, fej)

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
        groups = self.link_groups(rx_a, tx_a, snapshots, np.asarray(noise_var, dtype=float))
        c = self.config
        self.x, self.P, info = map_update(
            self.x, self.P,
            lambda x: self.links.neg_loglik(x, groups),
            lambda x: self.links.information(x, groups),
            gtol=c.gtol, max_iter=c.max_iter, covariance=c.covariance, optimizer=c.optimizer,
            preconditioner=lambda x: self.links.information(x, groups, fej=False),
        )
        self.steps += 1
        return info
