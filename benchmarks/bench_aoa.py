"""Benchmark "aoa": batched pose throughput and accuracy, selfcal vs poselib's P3P.

Same random poses and bearings for everyone (3 beacons of the paper's set-up plus random
receivers below them). Speed: poses per second of selfcal's batched closed-form P3P
(``solve_aoa(method="p3p")``), the batched ML (4 beacons) and the paper's Solutions 1 and 2,
against ``poselib.p3p`` called in a Python loop (poselib is benchmark-only and optional: when it
cannot be imported the JSON says so). Accuracy: median location / rotation error on the same
noisy bearings (1 deg), the candidate nearest the truth for both P3P solvers (so that the
comparison is of the solvers, not of the disambiguation), and for ML with a fourth beacon.
Timings are medians of repeats; the ratio to poselib is measured in the same process.
"""

from __future__ import annotations

import json
import time
import warnings
from pathlib import Path
from typing import Any

import numpy as np

from selfcal.aoa import solve_aoa
from selfcal.aoa.orientation import rotvec_to_matrix
from selfcal.aoa.p3p import p3p
from selfcal.io import write_json

BEACONS = np.array([[0.0, 0, 0], [5, 0, 0], [0, 5, 0], [5, 5, 0.5]])


def _scene(B: int, sigma_deg: float, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    m = np.column_stack([rng.uniform(0, 5, B), rng.uniform(0, 5, B), rng.uniform(-4, -2, B)])
    R = rotvec_to_matrix(rng.normal(scale=0.3, size=(B, 3)))
    g = BEACONS[None] - m[:, None]
    U = np.einsum("bji,bkj->bki", R, g / np.linalg.norm(g, axis=-1, keepdims=True))
    if sigma_deg > 0:
        n = rng.normal(size=U.shape) * np.radians(sigma_deg)
        n -= np.sum(n * U, -1, keepdims=True) * U
        U = U + n
        U /= np.linalg.norm(U, axis=-1, keepdims=True)
    return m, R, U, g


def _median_time(fn: Any, repeats: int = 5) -> float:
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
    return float(np.median(ts))


def _rot_err_deg(Re: np.ndarray, Rt: np.ndarray) -> np.ndarray:
    M = np.swapaxes(Rt, -1, -2) @ Re
    return np.degrees(np.arccos(np.clip((np.trace(M, axis1=-2, axis2=-1) - 1) / 2, -1, 1)))


def _poselib_poses(U: np.ndarray) -> tuple[list[list[tuple[np.ndarray, np.ndarray]]], float]:
    import poselib

    X = np.ascontiguousarray(BEACONS[:3])
    out = []
    t0 = time.perf_counter()
    for b in range(U.shape[0]):
        poses = poselib.p3p(U[b], X)
        # poselib: x_cam = R_cw X + t  ->  selfcal: R = R_cw^T, m = -R_cw^T t
        out.append([(-p.R.T @ p.t, p.R.T) for p in poses])
    return out, time.perf_counter() - t0


def main(out_dir: Path) -> dict[str, Any]:
    """Run the benchmark, write ``out_dir/aoa.json`` and return its content."""
    rng = np.random.default_rng(0)
    B = 20000
    m, R, U, _ = _scene(B, 0.0, rng)
    U3 = U[:, :3]
    report: dict[str, Any] = {"name": "aoa", "batch": B, "beacons": BEACONS.tolist()}
    speed: dict[str, float] = {}
    t = _median_time(lambda: p3p(BEACONS[:3], U3))
    speed["selfcal_p3p_core_poses_per_s"] = B / t
    t = _median_time(lambda: solve_aoa(BEACONS[:3], U3, method="p3p"), 3)
    speed["selfcal_solve_aoa_p3p_poses_per_s"] = B / t
    Bs = 2000
    t = _median_time(lambda: solve_aoa(BEACONS, U[:Bs], method="ml"), 3)
    speed["selfcal_ml_4beacons_poses_per_s"] = Bs / t
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        t = _median_time(lambda: solve_aoa(BEACONS[:3], U3[:Bs], method="sol1"), 3)
        speed["paper_sol1_poses_per_s"] = Bs / t
        t = _median_time(lambda: solve_aoa(BEACONS[:3], U3[:Bs], method="sol2"), 3)
        speed["paper_sol2_poses_per_s"] = Bs / t
    t1 = _median_time(lambda: solve_aoa(BEACONS[:3], U3[:1], method="p3p"), 20)
    speed["selfcal_p3p_single_call_poses_per_s"] = 1.0 / t1
    try:
        import poselib  # noqa: F401

        have_poselib = True
        report["poselib_version"] = getattr(poselib, "__version__", "unknown")
    except ImportError as exc:
        have_poselib = False
        report["poselib"] = f"skipped: poselib not importable ({exc})"
    if have_poselib:
        Bp = 20000
        ts = [_poselib_poses(U3[:Bp])[1] for _ in range(3)]
        speed["poselib_p3p_loop_poses_per_s"] = Bp / float(np.median(ts))
        speed["ratio_selfcal_batched_over_poselib"] = speed["selfcal_p3p_core_poses_per_s"] / speed["poselib_p3p_loop_poses_per_s"]
    report["speed"] = speed

    # accuracy on the same noisy bearings
    rng = np.random.default_rng(1)
    Ba = 5000
    m, R, U, _ = _scene(Ba, 1.0, rng)
    acc: dict[str, Any] = {"sigma_deg": 1.0, "poses": Ba}
    pos, rot, valid = p3p(BEACONS[:3], U[:, :3])
    d = np.where(valid, np.linalg.norm(pos - m[:, None], axis=-1), np.inf)
    k = np.argmin(d, axis=1)
    ok = valid.any(axis=1)
    rows = np.arange(Ba)
    acc["selfcal_p3p_nearest"] = {
        "solved_fraction": float(ok.mean()),
        "median_location_m": float(np.median(d[rows, k][ok])),
        "median_rotation_deg": float(np.median(_rot_err_deg(rot[rows, k], R)[ok])),
    }
    ml = solve_aoa(BEACONS, U, method="ml")
    acc["selfcal_ml_4beacons"] = {
        "solved_fraction": float(np.mean(np.isfinite(ml.position).all(axis=1))),
        "median_location_m": float(np.nanmedian(np.linalg.norm(ml.position - m, axis=1))),
        "median_rotation_deg": float(np.nanmedian(_rot_err_deg(ml.rotation, R))),
    }
    if have_poselib:
        sols, _ = _poselib_poses(U[:, :3])
        le, re_, solved = [], [], []
        for b in range(Ba):
            if not sols[b]:
                solved.append(False)
                continue
            errs = [np.linalg.norm(p - m[b]) for p, _ in sols[b]]
            j = int(np.argmin(errs))
            solved.append(True)
            le.append(errs[j])
            re_.append(float(_rot_err_deg(sols[b][j][1], R[b])))
        acc["poselib_p3p_nearest"] = {
            "solved_fraction": float(np.mean(solved)),
            "median_location_m": float(np.median(le)),
            "median_rotation_deg": float(np.median(re_)),
        }
        # exact data: both find the truth among their candidates
        m0, R0, U0, _ = _scene(500, 0.0, np.random.default_rng(2))
        sols0, _ = _poselib_poses(U0[:, :3])
        acc["poselib_exact_max_location_error_m"] = float(
            max(min((np.linalg.norm(p - m0[b]) for p, _ in s), default=np.inf) for b, s in enumerate(sols0))
        )
        p0, _, v0 = p3p(BEACONS[:3], U0[:, :3])
        acc["selfcal_exact_max_location_error_m"] = float(
            np.max(np.min(np.where(v0, np.linalg.norm(p0 - m0[:, None], axis=-1), np.inf), axis=1))
        )
    report["accuracy"] = acc
    out_dir.mkdir(parents=True, exist_ok=True)
    write_json(out_dir / "aoa.json", report)
    return json.loads(json.dumps(report, default=float))


if __name__ == "__main__":
    import sys

    print(json.dumps(main(Path(sys.argv[1] if len(sys.argv) > 1 else "benchmarks/results")), indent=2))
