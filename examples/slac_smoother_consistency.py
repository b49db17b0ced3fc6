"""Does a fixed-lag smoother make full-G SLAC consistent? (beyond paper 002)

Full-G SLAC (chamber prior, snapshot initialisation, 0.3 m ranging biases) on the replica
scenario for the paper's filter (lag 0) and the fixed-lag smoother
(``SlacConfig(smoother_lag=K)``, :class:`selfcal.slac.smoother.SlacSmoother`). Prints per seed
and lag the time-averaged pose NEES per rover (3 dof: 95 % band <= 9.35 for one rover and one
run) and its position (2 dof) and heading (1 dof) parts, position / heading RMSE, the 4-port
rover's DoA p90 with the estimated G, and the speed. See ``docs/slac_consistency.md``.

Run: PYTHONPATH=src .venv/bin/python examples/slac_smoother_consistency.py [LAGS] [SEEDS] [MINUTES] [N]
     defaults: 0,5,10,20  11,12,13  0.5  32
     full replica: ... slac_smoother_consistency.py 0,20 0,3757552657 12.5 1024   (~6 min per smoother run)
"""

import sys
import time

import numpy as np
from scipy.stats import chi2

from selfcal.experiments.slac import score_slac
from selfcal.scenarios.rovers import make_rover_scenario
from selfcal.slac.filter import SlacConfig
from selfcal.slac.motion import wrap_angle
from selfcal.slac.run import SlacLog, solve_slac

lags = [int(v) for v in (sys.argv[1] if len(sys.argv) > 1 else "0,5,10,20").split(",")]
seeds = [int(v) for v in (sys.argv[2] if len(sys.argv) > 2 else "11,12,13").split(",")]
minutes = float(sys.argv[3]) if len(sys.argv) > 3 else 0.5
n_sub = int(sys.argv[4]) if len(sys.argv) > 4 else 32
hi = chi2.ppf(0.975, 3)


def fmt(a: np.ndarray, d: int) -> str:
    return " / ".join(f"{v:.{d}f}" for v in a)


print(f"{minutes} min, N = {n_sub}; NEES band for one rover and run (3 dof, 95 %): <= {hi:.2f}")
print("seed lag | NEES per rover | position part | heading part | pos RMSE (m) | heading RMSE (deg) | DoA p90 (deg) | steps/s")
for seed in seeds:
    for lag in lags:
        sc = make_rover_scenario(minutes, n_subcarriers=n_sub, rng=seed, bias_std=0.3)
        log = SlacLog.from_scenario(sc, seed=seed)
        assert log.states is not None
        t0 = time.perf_counter()
        r = solve_slac(log, mode="slac", prior="chamber", init="snapshot", config=SlacConfig(smoother_lag=lag))
        rate = log.n_steps / (time.perf_counter() - t0)
        m = score_slac(log, r)
        tr = log.states
        e = np.concatenate([r.poses[1:, :, :2] - tr[1:, :, :2],
                            wrap_angle(r.poses[1:, :, 2] - tr[1:, :, 2])[:, :, None]], axis=2)
        C = r.pose_cov[1:]
        pos = np.einsum("sni,snij,snj->sn", e[..., :2], np.linalg.inv(C[..., :2, :2]), e[..., :2]).mean(0)
        hd = (e[..., 2] ** 2 / C[..., 2, 2]).mean(0)
        ok = "in band" if np.all(m["nees_mean"] <= hi) else "OUT"
        print(f"{seed:4d} {lag:3d} | {fmt(m['nees_mean'], 1)} ({ok}) | {fmt(pos, 1)} | {fmt(hd, 1)} | "
              f"{fmt(m['position_rmse'], 3)} | {fmt(m['heading_rmse_deg'], 2)} | "
              f"{m['doa']['Dias']['filter']['p90_deg']:.2f} | {rate:.1f}", flush=True)
