"""CMU range log (Plaza 1): selfcal's range-only SLAC beside two independent baselines.

In one process, on the same log and the same inputs (ground truth only for the first pose
and for the scores):

* FilterPy ``ExtendedKalmanFilter`` with per-beacon range-bias states (state
  ``[x, y, psi, o_1..o_B]``, model ``r = |p - b| + o``, the biases a random walk of std
  ``scale_std x dd`` per row so that they can follow the unmodelled scale error), the same
  chi-square gate as selfcal, ranges applied at the next odometry time;
* GTSAM batch graph, Levenberg-Marquardt: ``Pose2`` per odometry row, ``BetweenFactorPose2``
  per row (drive ``dd`` along x then turn ``dpsi``, i.e. Pose2 composition), a prior on the
  first pose, one ``[scale, offset]`` vector per beacon with a prior ``N([1, 0], ...)`` and a
  ``CustomFactor`` per range ``s |p - b| + o - r`` under a Huber noise model; each range
  attached to the nearest pose in time;
* selfcal's causal filter and its batch smoother (:func:`selfcal.slac.ranging.solve_range_slac`);
  with ``--ablate`` also the smoother under the variants of ``benchmarks/slac_stretch_cv.py``
  (``graph``: the graph's model -- fixed scale priors, no odometry scale, ranges at the nearest
  pose, Huber without the gate -- so that a difference of estimators shows apart from one of models).

Both baselines are written here from their documented APIs (FilterPy EKF: ``predict`` with
``F``/``Q``, ``update(z, HJacobian, Hx, R)``; GTSAM: ``NonlinearFactorGraph``,
``CustomFactor(noise, keys, error_func)``, ``LevenbergMarquardtOptimizer``). They are
optional benchmark baselines (``pip install -e '.[bench]'``), never dependencies of selfcal:
a baseline that is not importable is skipped with a message.

Noise levels: every method uses selfcal's priors (:class:`RangeModelConfig`) with the
heading-noise factor and the range noise that selfcal's smoother selected by maximum
likelihood on this log (printed), so the table compares the estimators, not their tuning.

Times: process CPU seconds (every method runs single-threaded with ``OPENBLAS_NUM_THREADS=1``,
so CPU time is robust to the load of a shared machine) and wall seconds.

Usage::

    PYTHONPATH=src OPENBLAS_NUM_THREADS=1 python benchmarks/compare_plaza.py \
        [--data ../shared/data/plaza/Plaza1.mat] [--out plaza_compare.json] [--ablate]
"""

from __future__ import annotations

import argparse
import json
import time
from typing import Any

import numpy as np
from scipy.stats import chi2

from selfcal.datasets.plaza import PlazaData, load_plaza
from selfcal.experiments.slac import score_plaza
from selfcal.slac.ranging import RangeModelConfig, solve_range_slac

BIAS_RW = 1.0
VERBOSE = False


class _Track:
    def __init__(self, times: np.ndarray, poses: np.ndarray) -> None:
        self.times, self.poses = times, poses


def _odo_sigmas(cfg: RangeModelConfig, factor: float, dd: float, dpsi: float) -> tuple[float, float]:
    sd = np.sqrt(cfg.odo_distance**2 * abs(dd)) + 1e-4
    sh = factor * np.sqrt(cfg.odo_turn**2 * abs(dpsi) + cfg.odo_drift**2 * abs(dd)) + 1e-5
    return float(sd), float(sh)


def _ranges_per_pose(data: PlazaData, nearest: bool) -> list[list[int]]:
    """Range indices per pose: nearest pose in time (GTSAM) or the next pose (EKF)."""
    t = data.pose_times
    rt = data.range_times
    ok = (rt > t[0]) & (rt <= t[-1])
    idx = np.searchsorted(t, rt, side="left")
    if nearest:
        prev = np.clip(idx - 1, 0, t.size - 1)
        cur = np.clip(idx, 0, t.size - 1)
        idx = np.where(np.abs(rt - t[prev]) < np.abs(t[cur] - rt), prev, cur)
    out: list[list[int]] = [[] for _ in t]
    for k in np.flatnonzero(ok):
        out[int(idx[k])].append(int(k))
    return out


def filterpy_ekf(data: PlazaData, cfg: RangeModelConfig, factor: float, sigma_r: float) -> np.ndarray:
    """FilterPy EKF with per-beacon bias states; returns (P, 3) poses at the pose times."""
    from filterpy.kalman import ExtendedKalmanFilter

    B = data.beacons.shape[0]
    D = 3 + B
    ekf = ExtendedKalmanFilter(dim_x=D, dim_z=1)
    ekf.x = np.concatenate([data.start_pose, np.zeros(B)])[:, None]
    ekf.P = np.diag([cfg.init_position_std**2] * 2 + [cfg.init_heading_std**2] + [cfg.offset_std**2] * B)
    ekf.R = np.array([[sigma_r**2]])
    per_pose = _ranges_per_pose(data, nearest=False)
    gate2 = float(chi2.ppf(cfg.gate_quantile, 1))
    out = np.empty((data.pose_times.size, 3))
    out[0] = data.start_pose

    def hx(x: np.ndarray, b: int) -> np.ndarray:
        return np.array([[np.hypot(x[0, 0] - data.beacons[b, 0], x[1, 0] - data.beacons[b, 1]) + x[3 + b, 0]]])

    def H(x: np.ndarray, b: int) -> np.ndarray:
        dl = x[:2, 0] - data.beacons[b]
        J = np.zeros((1, D))
        J[0, :2] = dl / max(np.hypot(*dl), 1e-9)
        J[0, 3 + b] = 1.0
        return J

    for k, (dd, dp) in enumerate(data.odo, start=1):
        psi = float(ekf.x[2, 0])
        c, s = np.cos(psi), np.sin(psi)
        F = np.eye(D)
        F[0, 2], F[1, 2] = -dd * s, dd * c
        G = np.zeros((D, 2))
        G[0, 0], G[1, 0], G[2, 1] = c, s, 1.0
        sd, sh = _odo_sigmas(cfg, factor, dd, dp)
        ekf.F = F
        ekf.Q = G @ np.diag([sd**2, sh**2]) @ G.T
        # bias random walk: a bias state absorbs the unmodelled scale error, which changes by
        # at most scale_std x the change of range, itself at most the distance driven
        ekf.Q[3:, 3:] += np.eye(B) * (BIAS_RW * cfg.scale_std * dd) ** 2
        P = ekf.P
        ekf.x = ekf.x + np.array([dd * c, dd * s, dp] + [0.0] * B)[:, None]  # nonlinear mean
        ekf.P = F @ P @ F.T + ekf.Q
        for q in per_pose[k]:
            b = int(data.range_beacon[q])
            J = H(ekf.x, b)
            y = data.ranges[q] - hx(ekf.x, b)[0, 0]
            if y * y / float((J @ ekf.P @ J.T + ekf.R)[0, 0]) > gate2:  # the same chi-square gate as selfcal
                continue
            ekf.update(np.array([[data.ranges[q]]]), H, hx, args=(b,), hx_args=(b,))
        out[k] = ekf.x[:3, 0]
    return out


def gtsam_batch(data: PlazaData, cfg: RangeModelConfig, factor: float, sigma_r: float) -> np.ndarray:
    """GTSAM LM over Pose2 + odometry + robust range CustomFactors with per-beacon [scale, offset]."""
    import gtsam

    X = lambda k: gtsam.symbol("x", k)  # noqa: E731
    C = lambda b: gtsam.symbol("c", b)  # noqa: E731
    graph = gtsam.NonlinearFactorGraph()
    init = gtsam.Values()
    p0 = gtsam.Pose2(*data.start_pose)
    graph.add(gtsam.PriorFactorPose2(X(0), p0, gtsam.noiseModel.Diagonal.Sigmas(
        np.array([cfg.init_position_std] * 2 + [cfg.init_heading_std]))))
    init.insert(X(0), p0)
    pose = p0
    for k, (dd, dp) in enumerate(data.odo, start=1):
        sd, sh = _odo_sigmas(cfg, factor, dd, dp)
        step = gtsam.Pose2(float(dd), 0.0, float(dp))  # drive along x, then turn
        graph.add(gtsam.BetweenFactorPose2(X(k - 1), X(k), step, gtsam.noiseModel.Diagonal.Sigmas(
            np.array([sd, 1e-3, sh]))))
        pose = pose.compose(step)
        init.insert(X(k), pose)
    B = data.beacons.shape[0]
    for b in range(B):
        graph.add(gtsam.PriorFactorVector(C(b), np.array([1.0, 0.0]), gtsam.noiseModel.Diagonal.Sigmas(
            np.array([cfg.scale_std, cfg.offset_std]))))
        init.insert(C(b), np.array([1.0, 0.0]))
    robust = gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Huber.Create(cfg.huber),
                                            gtsam.noiseModel.Isotropic.Sigma(1, sigma_r))

    def make_error(beacon: np.ndarray, r: float):  # type: ignore[no-untyped-def]
        def error(this: gtsam.CustomFactor, v: gtsam.Values, Hs: list[np.ndarray] | None) -> np.ndarray:
            p = v.atPose2(this.keys()[0])
            so = v.atVector(this.keys()[1])
            dl = np.array([p.x() - beacon[0], p.y() - beacon[1]])
            d = float(np.hypot(*dl))
            if Hs is not None:
                u = dl / max(d, 1e-9)
                R = p.rotation().matrix()  # d(translation) / d(local x, y) = R
                Hs[0] = np.array([[*(so[0] * (u @ R)), 0.0]])
                Hs[1] = np.array([[d, 1.0]])
            return np.array([so[0] * d + so[1] - r])

        return error

    for k, qs in enumerate(_ranges_per_pose(data, nearest=True)):
        for q in qs:
            b = int(data.range_beacon[q])
            graph.add(gtsam.CustomFactor(robust, [X(k), C(b)], make_error(data.beacons[b], float(data.ranges[q]))))
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(100)
    if VERBOSE:
        params.setVerbosityLM("SUMMARY")
    res = gtsam.LevenbergMarquardtOptimizer(graph, init, params).optimize()
    out = np.empty((data.pose_times.size, 3))
    for k in range(out.shape[0]):
        p = res.atPose2(X(k))
        out[k] = [p.x(), p.y(), p.theta()]
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default="../shared/data/plaza/Plaza1.mat")
    ap.add_argument("--out", default=None, help="JSON of the table")
    ap.add_argument("--ablate", action="store_true",
                    help="also the smoother under the model variants of benchmarks/slac_stretch_cv.py "
                         "(k-select, k-off, fixed, graph = the GTSAM graph's model)")
    a = ap.parse_args()
    data = load_plaza(a.data)
    cfg = RangeModelConfig()
    rows: list[dict[str, Any]] = []

    def row(name: str, poses: np.ndarray, sec: tuple[float, float], times: np.ndarray | None = None) -> None:
        sc = score_plaza(data, _Track(data.pose_times if times is None else times, poses))  # type: ignore[arg-type]
        rows.append({"method": name, "position_rmse_m": sc["position_rmse"], "heading_rmse_deg": sc["heading_rmse_deg"],
                     "cpu_seconds": sec[0], "wall_seconds": sec[1]})
        print(f"  {name}: {sc['position_rmse']:.3f} m, {sec[0]:.1f} s CPU", flush=True)

    def clock() -> tuple[float, float]:
        return time.process_time(), time.perf_counter()

    def since(t: tuple[float, float]) -> tuple[float, float]:
        return time.process_time() - t[0], time.perf_counter() - t[1]

    row("dead reckoning (DR)", data.dead_reckoning(), (0.0, 0.0))
    for m in ("filter", "smoother"):
        t0 = clock()
        r = solve_range_slac(data, method=m, config=cfg)
        row(f"selfcal {m}", r.poses, since(t0), r.times)
        if m == "smoother":
            factor, sigma = r.heading_noise_factor, float(r.noise_estimate)
    if a.ablate:
        # the variants (benchmarks/ is on sys.path when run as a script)
        from slac_stretch_cv import solve

        from selfcal.slac.ranging import RangeLog

        for v in ("k-select", "k-off", "fixed", "graph"):
            t0 = clock()
            r = solve(RangeLog.from_dataset(data), v)
            row(f"selfcal smoother, {v}", r.poses, since(t0), r.times)
    print(f"noise used by the baselines (selfcal's ML on this log): heading factor {factor}, range {sigma:.3f} m")
    for name, fn in (("FilterPy EKF + per-beacon bias states", filterpy_ekf),
                     ("GTSAM LM, Pose2 + robust range CustomFactor (scale + offset)", gtsam_batch)):
        try:
            t0 = clock()
            poses = fn(data, cfg, factor, sigma)
            row(name, poses, since(t0))
        except ImportError as exc:
            print(f"skipping {name}: {exc.name or exc} not importable (pip install -e '.[bench]')")
    w = max(len(r["method"]) for r in rows)
    print(f"{'method':<{w}}  position RMSE (m)  heading RMSE (deg)  CPU (s)  wall (s)")
    for r in rows:
        print(f"{r['method']:<{w}}  {r['position_rmse_m']:17.3f}  {r['heading_rmse_deg']:18.2f}  "
              f"{r['cpu_seconds']:7.1f}  {r['wall_seconds']:8.1f}")
    if a.out:
        with open(a.out, "w") as fh:
            json.dump({"data": a.data, "rows": rows, "heading_noise_factor": factor, "range_noise": sigma}, fh, indent=1)


if __name__ == "__main__":
    main()
