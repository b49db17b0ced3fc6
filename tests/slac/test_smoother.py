"""Fixed-lag smoother for the SLAC filter (``SlacConfig.smoother_lag``, beyond paper 002)."""

from __future__ import annotations

import numpy as np
import pytest

from selfcal.errors import InputError
from selfcal.experiments.slac import score_slac
from selfcal.scenarios.rovers import make_rover_scenario
from selfcal.slac.filter import SlacConfig, SlacFilter, map_update
from selfcal.slac.run import SlacLog, solve_slac
from selfcal.slac.signals import batch_delay_search
from selfcal.slac.smoother import SlacSmoother

N = 32


@pytest.fixture(scope="module")
def log() -> SlacLog:
    return SlacLog.from_scenario(make_rover_scenario(0.1, n_subcarriers=N, rng=11, bias_std=0.3), seed=11)


def _smoother(log: SlacLog, lag: int, steps: int, **kw: float) -> SlacSmoother:
    cfg = SlacConfig(T=log.T, sigma_v=log.sigma_v, sigma_omega=log.sigma_omega, bandwidth=log.bandwidth, **kw)  # type: ignore[arg-type]
    f = SlacFilter(log.anchors, log.ports, log.prior("chamber"), log.init_poses, log.init_cov, log.probe, config=cfg)
    sm = SlacSmoother(f, lag)
    for s in range(1, steps + 1):
        snaps = log.snapshot_fn(s)
        _, _, var = batch_delay_search(snaps, log.probe, log.bandwidth)
        sm.step(log.controls[s - 1], log.rx, log.tx, snaps, var)
    return sm


def test_window_gradient_matches_finite_differences(log: SlacLog) -> None:
    sm = _smoother(log, lag=3, steps=5)  # a full window after two marginalisations
    assert sm.window == 3
    rng = np.random.default_rng(0)
    z = sm.z.copy()
    n, p = sm.n, sm.p
    # scale of each coordinate: ~mm / mrad for poses, control-noise std for w, 1e-3 for calibration
    scale = np.concatenate([np.tile([1e-3, 1e-3, 1e-3], n), np.sqrt(np.tile(sm._qw, sm.window)),
                            np.full(z.size - p - sm._qw.size * sm.window, 1e-3)])
    z = z + 0.3 * scale * rng.standard_normal(z.size)  # away from the optimum: non-zero gradient
    _, g = sm.fun_grad(z)
    coords = [0, 2, 3 * n - 1, p, p + 1, p + 2 * n + 1, p + sm._qw.size * sm.window - 1, z.size - 1, z.size - 30]
    for c in coords:
        h = 1e-3 * scale[c]
        e = np.zeros(z.size)
        e[c] = h
        fd = (sm.fun_grad(z + e)[0] - sm.fun_grad(z - e)[0]) / (2 * h)
        assert fd == pytest.approx(g[c], rel=1e-4, abs=1e-6 * np.max(np.abs(g * scale)) / scale[c]), c
    for _ in range(3):  # random directions mix every block
        d = scale * rng.standard_normal(z.size)
        h = 1e-3
        fd = (sm.fun_grad(z + h * d)[0] - sm.fun_grad(z - h * d)[0]) / (2 * h)
        assert fd == pytest.approx(float(g @ d), rel=1e-4)


def test_window_information_is_gauss_newton_of_the_chained_jacobians(log: SlacLog) -> None:
    sm = _smoother(log, lag=3, steps=4)
    H = sm.information(sm.z, fej=False)
    assert np.allclose(H, H.T) and np.all(np.linalg.eigvalsh(H) > -1e-6 * np.max(np.abs(H)))


def test_lag_zero_is_the_filter(log: SlacLog) -> None:
    a = solve_slac(log, mode="slac", prior="chamber", steps=8)
    b = solve_slac(log, mode="slac", prior="chamber", steps=8, config=SlacConfig(smoother_lag=0))
    cfg = SlacConfig(T=log.T, sigma_v=log.sigma_v, sigma_omega=log.sigma_omega, bandwidth=log.bandwidth)
    f = SlacFilter(log.anchors, log.ports, log.prior("chamber"), log.init_poses, log.init_cov, log.probe, config=cfg)
    for s in range(1, 9):
        f.predict(log.controls[s - 1])
        snaps = log.snapshot_fn(s)
        f.update(log.rx, log.tx, snaps, batch_delay_search(snaps, log.probe, log.bandwidth)[2])
    assert np.array_equal(a.poses, b.poses) and np.array_equal(a.pose_cov, b.pose_cov)
    assert np.array_equal(a.poses[-1], f.poses) and np.array_equal(a.pose_cov[-1], f.pose_covariances)
    assert a.method == "slac-iekf-quasi-newton"


def test_map_update_warm_start_at_the_prior_mean_changes_nothing() -> None:
    rng = np.random.default_rng(1)
    A = rng.standard_normal((5, 5))
    Info = A @ A.T + np.eye(5)
    t = rng.standard_normal(5)

    def fg(x: np.ndarray) -> tuple[float, np.ndarray]:
        r = x - t
        return float(0.5 * r @ Info @ r + 0.1 * np.sum(r**4)), Info @ r + 0.4 * r**3

    x_bar, P_bar = np.zeros(5), np.eye(5)
    for opt in ("quasi-newton", "bfgs"):
        a = map_update(x_bar, P_bar, fg, lambda x: Info, optimizer=opt)
        b = map_update(x_bar, P_bar, fg, lambda x: Info, optimizer=opt, x_start=x_bar.copy())
        assert np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1])
        c = map_update(x_bar, P_bar, fg, lambda x: Info, optimizer=opt, x_start=t.copy(), gtol=1e-8, max_iter=200)
        d = map_update(x_bar, P_bar, fg, lambda x: Info, optimizer=opt, gtol=1e-8, max_iter=200)
        assert np.allclose(c[0], d[0], atol=1e-6)


def test_lag_one_matches_the_filter_and_known_g_smoother_tracks(log: SlacLog) -> None:
    steps = 25
    f1 = solve_slac(log, mode="slac", prior="chamber", steps=8)
    s1 = solve_slac(log, mode="slac", prior="chamber", steps=8, config=SlacConfig(smoother_lag=1))
    # lag 1 is an iterated filter with the prediction relinearised at the update: same estimates
    assert np.allclose(f1.poses, s1.poses, atol=2e-3)
    cfg = dict(g_rel_std=1e-6)
    r0 = solve_slac(log, mode="slac", prior="true", steps=steps, config=SlacConfig(**cfg))  # type: ignore[arg-type]
    r5 = solve_slac(log, mode="slac", prior="true", steps=steps, config=SlacConfig(smoother_lag=5, **cfg))  # type: ignore[arg-type]
    assert r5.method.endswith("fixed-lag-5")
    m0, m5 = score_slac(log, r0), score_slac(log, r5)
    e0, e5 = m0["position_rmse"], m5["position_rmse"]
    assert np.all(e5 <= 1.25 * e0 + 0.01), (e0, e5)
    assert np.all(m5["heading_rmse_deg"] <= 1.25 * m0["heading_rmse_deg"] + 0.2)
    assert np.max(np.abs(r5.poses[:, :, :2] - r0.poses[:, :, :2])) < 0.1
    assert np.all(m5["nees_mean"] < 9.35)


def test_smoother_rejects_bad_input(log: SlacLog) -> None:
    f = SlacFilter(log.anchors, log.ports, log.prior("chamber"), log.init_poses, log.init_cov, log.probe)
    with pytest.raises(InputError):
        SlacSmoother(f, 0)
    with pytest.raises(InputError):
        SlacFilter(log.anchors, log.ports, log.prior("chamber"), log.init_poses, log.init_cov, log.probe,
                   config=SlacConfig(smoother_lag=-1))
    sm = SlacSmoother(f, 2)
    with pytest.raises(InputError):
        sm.step(np.zeros((1, 2)), log.rx, log.tx, log.snapshot_fn(1), np.ones(log.rx.size))


def test_window_rollout_is_the_motion_model(log: SlacLog) -> None:
    from selfcal.slac.motion import motion_step

    sm = _smoother(log, lag=4, steps=6)
    X, F, B = sm._rollout(sm.z)
    x0, w, _ = sm._split(sm.z)
    x = x0.copy()
    for k in range(sm.window):
        x = motion_step(x, sm.controls[k] + w[k], log.T)
        assert np.allclose(X[k + 1], x, rtol=0, atol=1e-12)
    # the reported pose is the window's newest pose
    assert np.allclose(sm.filt.poses, X[-1])


def test_cli_slac_run_with_smoother_lag(tmp_path) -> None:  # type: ignore[no-untyped-def]
    import json

    from click.testing import CliRunner

    from selfcal.cli import main

    logp, outp = tmp_path / "log.npz", tmp_path / "res.json"
    r = CliRunner().invoke(main, ["slac", "simulate", "--minutes", "0.02", "--subcarriers", "16", "--seed", "3",
                                  "--out", str(logp)])
    assert r.exit_code == 0, r.output
    r = CliRunner().invoke(main, ["slac", "run", str(logp), "--smoother-lag", "3", "--out", str(outp)])
    assert r.exit_code == 0, r.output
    d = json.loads(outp.read_text())
    assert d["method"].endswith("fixed-lag-3") and len(d["poses"]) == 13
    r = CliRunner().invoke(main, ["slac", "run", str(logp), "--smoother-lag", "-1", "--out", str(outp)])
    assert r.exit_code != 0


def test_localization_mode_smoother_matches_the_filter(log: SlacLog) -> None:
    # no calibration states: the window holds poses and control noises only
    a = solve_slac(log, mode="localization", steps=15)
    b = solve_slac(log, mode="localization", steps=15, config=SlacConfig(smoother_lag=4))
    assert np.max(np.abs(a.poses[:, :, :2] - b.poses[:, :, :2])) < 0.05
    assert np.allclose(np.sqrt(a.pose_cov[-1, :, 0, 0]), np.sqrt(b.pose_cov[-1, :, 0, 0]), rtol=0.2)
