"""SLAC filter speed: a baseline git revision vs the current code, interleaved.

Exports ``src/`` of the baseline revision (``git archive``, default 0582afd, the code before
the issue-6 speed work) into a temporary directory and starts two worker processes, one
importing the baseline and one importing the current ``src/``. Both build the same paper-002
replica scenario (4 rovers, 3 anchors, 24 links per step, N = 1024) and draw the snapshots
before timing. Timed blocks are then run alternately (baseline, current, baseline, ...) so
that both see the same load of a shared machine; the report gives the median filter steps/s
of each, their ratio, and the largest difference of the pose trajectories and pose
covariances (asserted below ``--tol``).

Usage::

    PYTHONPATH=src python benchmarks/compare_slac.py [--baseline 0582afd] [--steps 60] [--repeats 5]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

_WORKER = r"""
import json, sys, time
import numpy as np
from selfcal.scenarios.rovers import make_rover_scenario
from threadpoolctl import threadpool_limits
from selfcal.slac.filter import SlacConfig, SlacFilter
from selfcal.slac.run import SlacLog
from selfcal.slac.signals import batch_delay_search

threadpool_limits(limits=1, user_api="blas")
steps = int(sys.argv[1])
sc = make_rover_scenario(steps * 0.1 / 60 + 0.01, n_subcarriers=1024, rng=0)
log = SlacLog.from_scenario(sc, seed=0)
snaps = [log.snapshot_fn(s) for s in range(1, steps + 1)]
print(json.dumps({"ready": True}), flush=True)
for line in sys.stdin:
    mode = line.strip()
    if not mode:
        break
    cfg = SlacConfig(T=log.T, sigma_v=log.sigma_v, sigma_omega=log.sigma_omega, bandwidth=log.bandwidth)
    f = SlacFilter(log.anchors, log.ports, log.prior("chamber"), log.init_poses, log.init_cov, log.probe,
                   mode=mode, config=cfg)
    poses, covs = [], []
    t0 = time.perf_counter()
    for s in range(1, steps + 1):
        f.predict(log.controls[s - 1])
        _, _, var = batch_delay_search(snaps[s - 1], log.probe, log.bandwidth)
        f.update(log.rx, log.tx, snaps[s - 1], var)
        poses.append(f.x[: 3 * f.n].tolist())
        covs.append(np.diag(f.P)[: 3 * f.n].tolist())
    rate = steps / (time.perf_counter() - t0)
    print(json.dumps({"rate": rate, "poses": poses, "covs": covs, "x": f.x.tolist()}), flush=True)
"""


class _Worker:
    def __init__(self, src: Path, steps: int) -> None:
        env = dict(os.environ, PYTHONPATH=str(src), OPENBLAS_NUM_THREADS="1", OMP_NUM_THREADS="1")
        self.proc = subprocess.Popen([sys.executable, "-c", _WORKER, str(steps)], stdin=subprocess.PIPE,
                                     stdout=subprocess.PIPE, text=True, env=env)
        self._read()

    def _read(self) -> dict:
        assert self.proc.stdout is not None
        line = self.proc.stdout.readline()
        if not line:
            raise RuntimeError("worker died")
        return json.loads(line)

    def run(self, mode: str) -> dict:
        assert self.proc.stdin is not None
        self.proc.stdin.write(mode + "\n")
        self.proc.stdin.flush()
        return self._read()

    def close(self) -> None:
        assert self.proc.stdin is not None
        self.proc.stdin.write("\n")
        self.proc.stdin.flush()
        self.proc.wait(timeout=60)


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--baseline", default="0582afd", help="git revision of the baseline (default 0582afd)")
    ap.add_argument("--steps", type=int, default=60, help="filter steps per timed block")
    ap.add_argument("--repeats", type=int, default=5, help="timed blocks per mode and code version")
    ap.add_argument("--modes", nargs="+", default=["slac", "localization"])
    ap.add_argument("--tol", type=float, default=1e-10, help="max allowed |pose difference|")
    ap.add_argument("--out", type=Path, default=None, help="write the report as JSON here")
    args = ap.parse_args(argv)
    repo = Path(__file__).resolve().parents[1]
    out: dict = {"baseline": args.baseline, "steps_per_block": args.steps, "repeats": args.repeats}
    with tempfile.TemporaryDirectory(prefix="slac_baseline_") as tmp:
        archive = subprocess.run(["git", "-C", str(repo), "archive", args.baseline, "src"], check=True,
                                 capture_output=True).stdout
        subprocess.run(["tar", "-x", "-C", tmp], input=archive, check=True)
        base = _Worker(Path(tmp) / "src", args.steps)
        cur = _Worker(repo / "src", args.steps)
        try:
            for mode in args.modes:
                rb: list[float] = []
                rc: list[float] = []
                dpose = dcov = dx = 0.0
                for _ in range(args.repeats):  # interleaved: both see the same machine load
                    b = base.run(mode)
                    c = cur.run(mode)
                    rb.append(b["rate"])
                    rc.append(c["rate"])
                    dpose = max(dpose, float(np.max(np.abs(np.subtract(b["poses"], c["poses"])))))
                    dcov = max(dcov, float(np.max(np.abs(np.subtract(b["covs"], c["covs"])))))
                    dx = max(dx, float(np.max(np.abs(np.subtract(b["x"], c["x"])))))
                out[mode] = {
                    "baseline_steps_per_s_median": float(np.median(rb)),
                    "current_steps_per_s_median": float(np.median(rc)),
                    "speedup_of_medians": float(np.median(rc) / np.median(rb)),
                    "median_pairwise_speedup": float(np.median(np.array(rc) / np.array(rb))),
                    "baseline_all": rb, "current_all": rc,
                    "max_abs_pose_diff": dpose, "max_abs_pose_var_diff": dcov, "max_abs_state_diff": dx,
                }
        finally:
            base.close()
            cur.close()
    if args.out is not None:
        args.out.write_text(json.dumps(out, indent=2))
    for mode in args.modes:
        r = out[mode]
        print(f"{mode:13s} baseline {r['baseline_steps_per_s_median']:7.1f} steps/s   current "
              f"{r['current_steps_per_s_median']:7.1f} steps/s   x{r['speedup_of_medians']:.2f}   "
              f"max |dpose| {r['max_abs_pose_diff']:.1e}  max |dvar| {r['max_abs_pose_var_diff']:.1e}")
    for mode in args.modes:
        assert out[mode]["max_abs_pose_diff"] <= args.tol, f"{mode}: poses differ from the baseline"
    return out


if __name__ == "__main__":
    main()
