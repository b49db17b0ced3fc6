"""Snapshot-based initial poses (paper 002, section IV): accuracy, honesty, failure modes."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import chi2

from selfcal.errors import DegenerateGeometryError, InputError
from selfcal.experiments.slac import score_slac
from selfcal.scenarios.rovers import make_rover_scenario
from selfcal.slac.initialization import back_propagate, range_crlb_std, snapshot_initial_poses
from selfcal.slac.motion import motion_step
from selfcal.slac.run import SlacLog, solve_slac
from selfcal.slac.signals import SPEED_OF_LIGHT, batch_delay_search, ofdm_probe, snapshot


def _init(log: SlacLog, prior: str = "chamber", **kw):  # type: ignore[no-untyped-def]
    return snapshot_initial_poses(log.anchors, log.ports, log.prior(prior), log.rx, log.tx, log.snapshot_fn(1),
                                  log.probe, log.bandwidth, headings=log.init_poses[:, 2],
                                  heading_std=np.sqrt(log.init_cov[:, 2, 2]), **kw)


def test_range_crlb_matches_monte_carlo_scatter() -> None:
    B, N = 28.2e6, 64
    probe = ofdm_probe(N, rng=3)
    rng = np.random.default_rng(0)
    a = np.array([1.0 + 0.2j, 0.5 - 0.4j])  # two ports
    tau = 2 * 7.3 / SPEED_OF_LIGHT
    snaps = [snapshot(a, probe, tau, B, amplitude=0.5, phase=rng.uniform(0, 2 * np.pi), noise_var=1.0, rng=rng)
             for _ in range(400)]
    t, ys, var = batch_delay_search(snaps, probe, B)
    r = SPEED_OF_LIGHT * t / 2
    sd = range_crlb_std(ys, var, probe, B)
    emp = np.std(r)
    assert abs(np.mean(r) - 7.3) < 3 * emp / np.sqrt(r.size)  # ML delay is unbiased at this SNR
    assert 0.8 < emp / np.median(sd) < 1.25


def test_back_propagation_retraces_the_motion_model() -> None:
    rng = np.random.default_rng(1)
    x0 = np.column_stack([rng.uniform(0, 30, (5, 2)), rng.uniform(-np.pi, np.pi, 5)])
    u = np.column_stack([rng.uniform(0, 1, 5), rng.uniform(-0.5, 0.5, 5)])
    x1 = motion_step(x0, u, 0.1)
    back, P = back_propagate(x1, np.zeros((5, 3, 3)), u, 0.1, 0.015, np.deg2rad(0.3))
    assert np.allclose(back, x0, atol=1e-12)
    assert np.all(np.linalg.eigvalsh(P) >= -1e-18) and np.all(P[:, 2, 2] > 0)


@pytest.mark.parametrize("seed", [11, 12, 13])
def test_snapshot_poses_are_accurate_and_their_covariance_is_honest(seed: int) -> None:
    log = SlacLog.from_scenario(make_rover_scenario(0.05, n_subcarriers=32, rng=seed, bias_std=0.3), seed=seed)
    assert log.states is not None
    ini = _init(log, bias_std=0.5)
    err = ini.poses - log.states[1]
    err[:, 2] = (err[:, 2] + np.pi) % (2 * np.pi) - np.pi
    nees = np.einsum("ni,nij,nj->n", err, np.linalg.inv(ini.cov), err)
    assert np.all(nees < chi2.ppf(0.999, 3)), nees
    assert np.all(np.hypot(err[:, 0], err[:, 1]) < 1.0)  # biases of 0.3 m, no correction yet
    assert ini.heading_observed.tolist() == [True, False, False, False]
    assert abs(np.rad2deg(err[0, 2])) < 4.0  # the 4-port rover's heading from its DoAs
    # the dipole rovers keep the given headings
    assert np.allclose(ini.poses[1:, 2], (log.init_poses[1:, 2] + np.pi) % (2 * np.pi) - np.pi)


def test_unbiased_network_is_located_to_the_range_precision() -> None:
    log = SlacLog.from_scenario(make_rover_scenario(0.05, n_subcarriers=256, rng=5, bias_std=0.0), seed=5)
    assert log.states is not None
    ini = _init(log, bias_std=1e-4)
    err = np.hypot(*(ini.poses[:, :2] - log.states[1, :, :2]).T)
    sd = np.sqrt(ini.cov[:, 0, 0] + ini.cov[:, 1, 1])
    assert np.all(err < 4 * sd) and np.all(sd < 0.15)  # vs ~0.4 m when 0.5 m biases are unknown


def test_dipole_agent_without_heading_is_refused() -> None:
    log = SlacLog.from_scenario(make_rover_scenario(0.05, n_subcarriers=32, rng=1), seed=1)
    with pytest.raises(InputError, match="single-port"):
        snapshot_initial_poses(log.anchors, log.ports, log.prior("em"), log.rx, log.tx, log.snapshot_fn(1),
                               log.probe, log.bandwidth)


def test_agent_with_one_link_is_unobservable() -> None:
    log = SlacLog.from_scenario(make_rover_scenario(0.05, n_subcarriers=32, rng=1), seed=1)
    keep = np.flatnonzero((log.rx != 3) & (log.tx != 3))
    keep = np.append(keep, np.flatnonzero(log.rx == 3)[0])  # agent 3 hears one node only
    snaps = log.snapshot_fn(1)
    with pytest.raises(DegenerateGeometryError) as e:
        snapshot_initial_poses(log.anchors, log.ports, log.prior("em"), log.rx[keep], log.tx[keep],
                               [snaps[k] for k in keep], log.probe, log.bandwidth,
                               headings=log.init_poses[:, 2], heading_std=np.full(4, 0.1))
    assert e.value.kind == "unobservable-agent"


def test_solve_slac_from_snapshot_initialisation_tracks_all_rovers() -> None:
    log = SlacLog.from_scenario(make_rover_scenario(0.2, n_subcarriers=32, rng=11, bias_std=0.3), seed=11)
    r = solve_slac(log, mode="slac", prior="chamber", init="snapshot")
    assert np.all(score_slac(log, r)["position_rmse"] < 0.15)
    with pytest.raises(InputError, match="init"):
        solve_slac(log, init="magic", steps=1)
