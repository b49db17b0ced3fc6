"""Running the SLAC filter over a whole log: :func:`solve_slac` and the NPZ log format.

A :class:`SlacLog` holds everything a run needs (anchors, antenna priors, controls, links,
snapshots) and optionally the ground truth; it is written to / read from an ``.npz``
archive without pickle (format: ``docs/slac_log_format.md``), or streams its snapshots
from a simulated scenario so that long N = 1024 runs need no disk.
"""

from __future__ import annotations

import io
import os
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .._checks import as_rng, check_choice, entry, has_attributes
from .._result import Result
from ..errors import InputError
from ..io import atomic_write_bytes, load_npz
from .filter import SlacConfig, SlacFilter
from .signals import SPEED_OF_LIGHT, batch_delay_search
from .validate import validate_log_arrays

__all__ = ["SlacLog", "SlacResult", "solve_slac", "LOG_VERSION"]

FArray = NDArray[np.float64]
CArray = NDArray[np.complex128]
LOG_VERSION = 1


@dataclass
class SlacLog:
    """Inputs of a SLAC run (+ optional truth). Shapes: n agents, A anchors, S steps, L links.

    anchors (A, 2); ports (n,); U; G_em, G_chamber (n, Mmax, U) complex, zero-padded;
    controls (S, n, 2); rx, tx (L,); probe (N,); T, bandwidth, carrier, sigma_v, sigma_omega;
    init_poses (n, 3), init_cov (n, 3, 3); ``snapshot_fn(step) -> list of L (M, N) arrays``
    for state index step = 1..S. Truth (optional): states (S+1, n, 3), biases (n + A,),
    G_true (n, Mmax, U).
    """

    anchors: FArray
    ports: NDArray[np.int64]
    G_em: CArray
    G_chamber: CArray
    controls: FArray
    rx: NDArray[np.int64]
    tx: NDArray[np.int64]
    probe: CArray
    T: float
    bandwidth: float
    carrier: float
    sigma_v: float
    sigma_omega: float
    init_poses: FArray
    init_cov: FArray
    snapshot_fn: Callable[[int], list[CArray]] = field(repr=False)
    names: tuple[str, ...] = ()
    states: FArray | None = None
    biases: FArray | None = None
    G_true: CArray | None = None

    @property
    def n_steps(self) -> int:
        return int(self.controls.shape[0])

    @property
    def n_agents(self) -> int:
        return int(self.ports.size)

    def prior(self, which: str) -> list[CArray | None]:
        """Per-agent prior sampling matrices ``which`` in {"em", "chamber", "true"}."""
        check_choice(which, "prior", ("em", "chamber", "true"))
        src = {"em": self.G_em, "chamber": self.G_chamber, "true": self.G_true}[which]
        if src is None:
            raise InputError("this log has no true sampling matrices")
        return [src[i, : self.ports[i]] if self.ports[i] > 1 else src[i, :1] for i in range(self.n_agents)]

    @classmethod
    def from_scenario(cls, scen: Any, *, seed: int = 0, init_std: tuple[float, float] = (0.3, 3.0)) -> SlacLog:
        """Stream a :class:`~selfcal.scenarios.rovers.RoverScenario` (snapshots drawn on demand).

        ``init_std`` = (position m, heading deg): the initial poses are the truth plus noise of
        these standard deviations (stand-in for the snapshot-based initialiser of section IV).
        """
        g = as_rng(seed)
        n = scen.n_agents
        sd = np.array([init_std[0], init_std[0], np.deg2rad(init_std[1])])
        x0 = scen.states[0] + g.standard_normal((n, 3)) * sd
        P0 = np.repeat(np.diag(sd**2)[None], n, axis=0)
        U = scen.G_true[0].shape[1]
        Mx = int(scen.ports.max())

        def pad(Gs: list[CArray]) -> CArray:
            out = np.zeros((n, Mx, U), dtype=complex)
            for i, G in enumerate(Gs):
                out[i, : G.shape[0]] = G
            return out

        def snap(step: int) -> list[CArray]:
            return scen.snapshots(step, np.random.default_rng([int(seed) % 2**32, step]))

        return cls(
            anchors=scen.anchors, ports=scen.ports, G_em=pad(scen.G_em), G_chamber=pad(scen.G_chamber),
            controls=scen.controls, rx=scen.rx, tx=scen.tx, probe=scen.probe, T=scen.T,
            bandwidth=scen.bandwidth, carrier=scen.carrier, sigma_v=scen.sigma_v,
            sigma_omega=scen.sigma_omega, init_poses=x0, init_cov=P0, snapshot_fn=snap,
            names=tuple(scen.names), states=scen.states, biases=scen.biases, G_true=pad(scen.G_true),
        )

    # ---------------------------------------------------------------- NPZ I/O
    def to_npz(self, path: str | os.PathLike[str]) -> None:
        """Materialise every snapshot and write the log atomically (format v1)."""
        M = self.ports[self.rx]
        rows = int(M.sum())
        N = self.probe.size
        sig = np.zeros((self.n_steps, rows, N), dtype=np.complex64)
        for s in range(1, self.n_steps + 1):
            sig[s - 1] = np.vstack([np.atleast_2d(r) for r in self.snapshot_fn(s)])
        arrays: dict[str, Any] = dict(
            version=np.array(LOG_VERSION), anchors=self.anchors, ports=self.ports, G_em=self.G_em,
            G_chamber=self.G_chamber, controls=self.controls, rx=self.rx, tx=self.tx, probe=self.probe,
            T=np.array(self.T), bandwidth=np.array(self.bandwidth), carrier=np.array(self.carrier),
            sigma_v=np.array(self.sigma_v), sigma_omega=np.array(self.sigma_omega),
            init_poses=self.init_poses, init_cov=self.init_cov, signals=sig,
            names=np.array(self.names if self.names else [f"agent{i}" for i in range(self.n_agents)]),
        )
        for k in ("states", "biases", "G_true"):
            v = getattr(self, k)
            if v is not None:
                arrays[f"true_{k}"] = v
        buf = io.BytesIO()
        np.savez_compressed(buf, **arrays)
        atomic_write_bytes(path, buf.getvalue())

    @classmethod
    def from_npz(cls, path: str | os.PathLike[str]) -> SlacLog:
        """Read a log written by :meth:`to_npz` (no pickle); validates shapes."""
        req = ("version", "anchors", "ports", "G_em", "G_chamber", "controls", "rx", "tx", "probe", "T",
               "bandwidth", "sigma_v", "sigma_omega", "init_poses", "init_cov", "signals")
        z = load_npz(path, req)
        validate_log_arrays(z, str(path))  # one named field per error (selfcal.slac.validate)
        try:
            version = int(z["version"])
        except (TypeError, ValueError):
            raise InputError(f"{path}: field 'version' is not an integer (got {z['version']!r})") from None
        if version != LOG_VERSION:
            raise InputError(f"{path}: log version {version} is not supported (expected {LOG_VERSION})")
        ports = z["ports"].astype(int)
        n = ports.size
        S = z["controls"].shape[0]
        rx, tx = z["rx"].astype(int), z["tx"].astype(int)
        if z["controls"].shape != (S, n, 2) or rx.shape != tx.shape or np.any(rx >= n):
            raise InputError(f"{path}: inconsistent controls / link arrays for {n} agents")
        sig = z["signals"]
        rows = int(ports[rx].sum())
        if sig.shape != (S, rows, z["probe"].size):
            raise InputError(f"{path}: signals has shape {sig.shape}, expected {(S, rows, z['probe'].size)}")
        starts = np.concatenate([[0], np.cumsum(ports[rx])])

        def snap(step: int) -> list[CArray]:
            blk = sig[step - 1].astype(complex)
            return [blk[starts[l] : starts[l + 1]] for l in range(rx.size)]

        return cls(
            anchors=z["anchors"], ports=ports, G_em=z["G_em"], G_chamber=z["G_chamber"],
            controls=z["controls"], rx=rx, tx=tx, probe=z["probe"], T=float(z["T"]),
            bandwidth=float(z["bandwidth"]), carrier=float(z.get("carrier", np.array(np.nan))),
            sigma_v=float(z["sigma_v"]), sigma_omega=float(z["sigma_omega"]),
            init_poses=z["init_poses"], init_cov=z["init_cov"], snapshot_fn=snap,
            names=tuple(str(s) for s in z.get("names", np.array([]))),
            states=z.get("true_states"), biases=z.get("true_biases"), G_true=z.get("true_G_true"),
        )


@dataclass(frozen=True, repr=False)
class SlacResult(Result):
    """Outcome of :func:`solve_slac` (histories indexed by state 0..S).

    Attributes: mode, method, poses (S+1, n, 3), pose_cov (S+1, n, 3, 3), biases (S+1, n+A),
    bias_std (n+A,) final, sampling_matrices {agent: (M, U)} final, ml_ranges (S, L)
    antenna-agnostic ML round-trip ranges, port_vectors {agent: (S, L_i, M)} delay-compensated
    snapshots of multi-port receivers (for DoA post-processing), iterations (S,), converged (S,),
    residual_rms (m, ML range minus the filter's predicted range). Errors against a simulated
    truth are not part of the result: :func:`selfcal.experiments.slac.score_slac`.
    """

    mode: str
    poses: FArray
    pose_cov: FArray
    biases: FArray
    bias_std: FArray
    sampling_matrices: dict[int, CArray]
    ml_ranges: FArray
    port_vectors: dict[int, CArray]
    iterations: NDArray[np.int64]
    converged_steps: NDArray[np.bool_]
    residual_rms: float
    method: str = "slac-iekf-bfgs"

    @property
    def converged(self) -> bool:
        return bool(np.mean(self.converged_steps) > 0.95) if self.converged_steps.size else True

    def to_dict(self) -> dict[str, Any]:
        return {
            "method": self.method, "mode": self.mode, "converged": self.converged,
            "iterations": int(self.iterations.sum()), "mean_iterations": float(np.mean(self.iterations)) if self.iterations.size else 0.0,
            "residual_rms": self.residual_rms, "final_poses": self.poses[-1], "final_pose_cov": self.pose_cov[-1],
            "poses": self.poses, "biases": self.biases[-1], "bias_std": self.bias_std,
            "sampling_matrices": {str(k): {"real": v.real, "imag": v.imag} for k, v in self.sampling_matrices.items()},
        }


@entry(log=has_attributes("anchors", "T", "snapshot_fn", what="SlacLog (selfcal.slac.SlacLog)"), steps="count?", progress="bool")
def solve_slac(
    log: SlacLog,
    *,
    mode: str = "slac",
    prior: str = "chamber",
    config: SlacConfig | None = None,
    steps: int | None = None,
    progress: bool = False,
    init: str = "log",
) -> SlacResult:
    """Run the SLAC (or localization-only) filter over a log (paper 002, section IV).

    Parameters
    ----------
    log : SlacLog.
    mode : "slac" or "localization".
    prior : sampling-matrix prior of multi-port agents, "em" or "chamber" (or "true").
    config : SlacConfig; T, sigma_v, sigma_omega and bandwidth are taken from the log.
        ``config.smoother_lag > 0`` runs the fixed-lag smoother
        (:class:`~selfcal.slac.smoother.SlacSmoother`) instead of the filter; the reported
        pose at step s is then the window's newest pose (a filtered estimate).
    steps : run only the first ``steps`` steps.
    init : "log" (the log's ``init_poses`` / ``init_cov``) or "snapshot": the snapshot-based
        initialiser of section IV (:func:`~selfcal.slac.initialization.snapshot_initial_poses`)
        on the first snapshot, moved back to state 0 through the motion model; single-port
        agents keep the log's heading and heading variance (one snapshot cannot give them).

    Returns
    -------
    SlacResult (errors against the log's truth: :func:`selfcal.experiments.slac.score_slac`).

    Notes
    -----
    The filter does many small (~100 x 100) dense operations per step, where BLAS threads
    only add synchronisation cost: the run holds the BLAS pools at one thread
    (``threadpoolctl``, restored on return).

    Examples
    --------
    Five steps of the simulated 3-anchor / 4-rover replica (16 subcarriers):

    >>> from selfcal.scenarios.rovers import make_rover_scenario
    >>> from selfcal.slac import SlacLog, solve_slac
    >>> log = SlacLog.from_scenario(make_rover_scenario(0.02, n_subcarriers=16, rng=3), seed=3)
    >>> res = solve_slac(log, mode="slac", steps=5)
    >>> res.poses.shape, res.pose_cov.shape  # (steps + 1, agents, 3): x, y, heading
    ((6, 4, 3), (6, 4, 3, 3))
    """
    from threadpoolctl import threadpool_limits

    with threadpool_limits(limits=1, user_api="blas"):
        return _solve_slac(log, mode, prior, config, steps, progress, init)


def _solve_slac(log: SlacLog, mode: str, prior: str, config: SlacConfig | None, steps: int | None,
                progress: bool, init: str) -> SlacResult:
    base = config or SlacConfig()
    cfg = SlacConfig(**{**base.__dict__, "T": log.T, "sigma_v": log.sigma_v, "sigma_omega": log.sigma_omega,
                        "bandwidth": log.bandwidth})
    x0, P0 = _initial_state(log, init, prior, cfg.bias_std)
    filt = SlacFilter(log.anchors, log.ports, log.prior(prior), x0, P0, log.probe, mode=mode, config=cfg)
    smoother = None
    if cfg.smoother_lag > 0:
        from .smoother import SlacSmoother

        smoother = SlacSmoother(filt, cfg.smoother_lag)
    S = log.n_steps if steps is None else min(int(steps), log.n_steps)
    n, L = log.n_agents, log.rx.size
    poses = np.empty((S + 1, n, 3))
    covs = np.empty((S + 1, n, 3, 3))
    biases = np.empty((S + 1, log.anchors.shape[0] + n))
    poses[0], covs[0], biases[0] = filt.poses, filt.pose_covariances, filt.biases
    ml = np.empty((S, L))
    mp_agents = [i for i in range(n) if log.ports[i] > 1]
    pv = {i: np.empty((S, int(np.sum(log.rx == i)), int(log.ports[i])), dtype=complex) for i in mp_agents}
    iters = np.zeros(S, dtype=int)
    conv = np.zeros(S, dtype=bool)
    pred_res = []
    from ..progress import stage

    for s in stage.iterate(range(1, S + 1), f"slac {mode}", unit="steps", show=None if progress else False):
        snaps = log.snapshot_fn(s)
        tau, ys, var = batch_delay_search(snaps, log.probe, log.bandwidth)
        ml[s - 1] = SPEED_OF_LIGHT * tau / 2
        for i in mp_agents:
            pv[i][s - 1] = np.stack([ys[l] for l in np.flatnonzero(log.rx == i)])
        if smoother is None:
            filt.predict(log.controls[s - 1])
            info = filt.update(log.rx, log.tx, snaps, var)
        else:
            info = smoother.step(log.controls[s - 1], log.rx, log.tx, snaps, var)
        iters[s - 1], conv[s - 1] = info.iterations, info.converged
        p = np.vstack([filt.poses[:, :2], log.anchors])
        b = filt.biases
        pred = np.linalg.norm(p[log.tx] - p[log.rx], axis=1) - b[log.rx] - b[log.tx]
        pred_res.append(ml[s - 1] - pred)
        poses[s], covs[s], biases[s] = filt.poses, filt.pose_covariances, filt.biases
    Gs = {i: filt.sampling_matrix(i) for i in mp_agents}
    res = np.concatenate(pred_res) if pred_res else np.zeros(0)
    return SlacResult(
        mode=mode, poses=poses, pose_cov=covs, biases=biases, bias_std=filt.bias_std,
        sampling_matrices={k: v for k, v in Gs.items() if v is not None}, ml_ranges=ml, port_vectors=pv,
        iterations=iters, converged_steps=conv, residual_rms=float(np.sqrt(np.mean(res**2))) if res.size else 0.0,
        method=("slac-iekf-bfgs" if filt.config.optimizer == "bfgs" else "slac-iekf-quasi-newton")
        + (f"-fixed-lag-{cfg.smoother_lag}" if smoother is not None else ""),
    )


def _initial_state(log: SlacLog, init: str, prior: str, bias_std: float) -> tuple[FArray, FArray]:
    """(n, 3) poses and (n, 3, 3) covariances at state 0 (see :func:`solve_slac`, ``init``)."""
    check_choice(init, "init", ("log", "snapshot"))
    if init == "log":
        return log.init_poses, log.init_cov
    from .initialization import back_propagate, snapshot_initial_poses

    ini = snapshot_initial_poses(log.anchors, log.ports, log.prior(prior), log.rx, log.tx, log.snapshot_fn(1),
                                 log.probe, log.bandwidth, headings=log.init_poses[:, 2],
                                 heading_std=np.sqrt(log.init_cov[:, 2, 2]), bias_std=bias_std)
    return back_propagate(ini.poses, ini.cov, log.controls[0], log.T, log.sigma_v, log.sigma_omega)
