"""SLAC filter speed on the paper-002 replica (3 anchors, 4 rovers, 24 links per step).

Reports filter steps per second (prediction + per-link ML delay / noise estimation + MAP
update + Laplace covariance) at N = 1024 in both modes, the median over repeated blocks,
and the real-time factor (steps/s x T). Snapshots are drawn before timing. The SLAC mode is
also timed with scipy's BFGS (``optimizer="bfgs"``, the paper's solver) in the same process,
interleaved with the default, so that their ratio is robust to the load of a shared machine.
"""

from __future__ import annotations

import json
import os
import time
from pathlib import Path

import numpy as np


def _time_mode(log, mode: str, steps: int, snaps: list, repeats: int,  # type: ignore[no-untyped-def]
               optimizer: str = "quasi-newton") -> list[float]:
    from selfcal.slac.filter import SlacConfig, SlacFilter
    from selfcal.slac.signals import batch_delay_search

    rates = []
    cfg = SlacConfig(T=log.T, sigma_v=log.sigma_v, sigma_omega=log.sigma_omega, bandwidth=log.bandwidth,
                     optimizer=optimizer)
    for _ in range(repeats):
        f = SlacFilter(log.anchors, log.ports, log.prior("chamber"), log.init_poses, log.init_cov, log.probe,
                       mode=mode, config=cfg)
        t0 = time.perf_counter()
        for s in range(1, steps + 1):
            f.predict(log.controls[s - 1])
            _, _, var = batch_delay_search(snaps[s - 1], log.probe, log.bandwidth)
            f.update(log.rx, log.tx, snaps[s - 1], var)
        rates.append(steps / (time.perf_counter() - t0))
    return rates


def main(out_dir: Path) -> dict:
    from threadpoolctl import threadpool_limits

    from selfcal.scenarios.rovers import make_rover_scenario
    from selfcal.slac.run import SlacLog

    threadpool_limits(limits=1, user_api="blas")  # process-wide for the benchmark run
    steps = int(os.environ.get("SELFCAL_BENCH_SLAC_STEPS", "60"))
    repeats = 3
    out: dict = {"name": "slac", "subcarriers": 1024, "links_per_step": 24, "steps_per_block": steps,
                 "repeats": repeats, "target_steps_per_s": 100.0}
    sc = make_rover_scenario(steps * 0.1 / 60 + 0.01, n_subcarriers=1024, rng=0)
    log = SlacLog.from_scenario(sc, seed=0)
    snaps = [log.snapshot_fn(s) for s in range(1, steps + 1)]
    r = _time_mode(log, "localization", steps, snaps, repeats)
    out["localization_steps_per_s_median"] = float(np.median(r))
    out["localization_steps_per_s_all"] = r
    out["localization_realtime_factor"] = float(np.median(r) * log.T)
    fast: list[float] = []
    slow: list[float] = []
    for _ in range(repeats):  # interleaved: both see the same machine load
        fast += _time_mode(log, "slac", steps, snaps, 1)
        slow += _time_mode(log, "slac", steps, snaps, 1, optimizer="bfgs")
    out["slac_steps_per_s_median"] = float(np.median(fast))
    out["slac_steps_per_s_all"] = fast
    out["slac_realtime_factor"] = float(np.median(fast) * log.T)
    out["slac_scipy_bfgs_steps_per_s_median"] = float(np.median(slow))
    out["slac_speedup_vs_scipy_bfgs"] = float(np.median(np.array(fast) / np.array(slow)))
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "slac.json").write_text(json.dumps(out, indent=2))
    return out


if __name__ == "__main__":
    print(json.dumps(main(Path("/tmp/bench_slac")), indent=2))
