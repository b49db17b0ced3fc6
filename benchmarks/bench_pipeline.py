"""Benchmark "pipeline": stage times of paper 004's acoustic system (issue 7).

Cases: 20 units in a 12 x 12 x 3 m room (the demo: 48 kHz, image order 3) and 120 units in
a 30 x 30 x 12 m room (16 kHz, RT60 1 s -- Sabine's formula cannot give 0.4 s in so large a
room -- and image order 1 to keep the simulation affordable), flat desks
calibrated with known heights, plus the 120-unit amphitheatre ("tiered") in 3-D. Each case
simulates a recording directory, then times loading, detection and calibration through
:func:`selfcal.acoustics.pipeline.run_pipeline`. Requirement checked: detection +
calibration of 120 units within 60 s on 2 cores (004 allows 15 minutes for the whole
localization of > 100 units).

Run: ``OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/run_all.py --only pipeline --out /tmp/bench_pipeline``
(one BLAS thread avoids oversubscription on a shared 2-core machine).
"""

from __future__ import annotations

import json
import os
import shutil
import statistics
import tempfile
import time
import warnings
from pathlib import Path
from typing import Any

CASES: list[dict[str, Any]] = [
    {"name": "20_units_flat", "units": 20, "room": (12.0, 12.0, 3.0), "layout": "flat", "sample_rate": 48000,
     "max_order": 3, "rt60": 0.4, "repeats": 3},
    {"name": "120_units_flat", "units": 120, "room": (30.0, 30.0, 12.0), "layout": "flat", "sample_rate": 16000,
     "max_order": 1, "rt60": 1.0, "repeats": 1},
    {"name": "120_units_tiered_3d", "units": 120, "room": (30.0, 30.0, 12.0), "layout": "tiered",
     "sample_rate": 16000, "max_order": 1, "rt60": 1.0, "repeats": 1},
]
LIMIT_120 = 60.0  # s, detection + calibration (issue 7)


def _run_case(case: dict[str, Any], workdir: Path) -> dict[str, Any]:
    from selfcal.acoustics.pipeline import run_pipeline, truth_errors
    from selfcal.commands.acoustics import write_simulation

    runs = []
    for rep in range(case["repeats"]):
        rec = workdir / f"{case['name']}_{rep}"
        t0 = time.perf_counter()
        truth = write_simulation(rec, units=case["units"], room=case["room"], rt60=case["rt60"], snr=30.0, seed=rep,
                                 layout=case["layout"], sample_rate=case["sample_rate"],
                                 max_order=case["max_order"], jitter=0.0, progress=False)
        t_sim = time.perf_counter() - t0
        heights = rec / "heights.json" if case["layout"] == "flat" else None
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            res = run_pipeline(rec, dim=3 if heights is None else "auto", heights=heights, progress=False, rng=rep)
        err = truth_errors(res, truth)
        runs.append({"simulate": t_sim, **res.timings,
                     "detect_plus_calibrate": res.timings["detect"] + res.timings["calibrate"],
                     "position_max_m": err["position_max"], "timing_max_s": err["timing_max"],
                     "detections_missed": res.detections_missed, "method": res.method})
        shutil.rmtree(rec, ignore_errors=True)
    keys = ["simulate", "load", "detect", "calibrate", "detect_plus_calibrate"]
    out = {k: statistics.median(r[k] for r in runs) for k in keys}
    out.update({"units": case["units"], "room": list(case["room"]), "layout": case["layout"],
                "sample_rate": case["sample_rate"], "image_order": case["max_order"], "rt60": case["rt60"],
                "repeats": case["repeats"],
                "runs": runs})
    return out


def main(out_dir: Path) -> dict[str, Any]:
    """Time every case, write ``out_dir/pipeline.json`` and return the numbers (seconds)."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    work = Path(tempfile.mkdtemp(prefix="bench_pipeline_"))
    try:
        results = {case["name"]: _run_case(case, work) for case in CASES}
    finally:
        shutil.rmtree(work, ignore_errors=True)
    worst_120 = max(r["detect_plus_calibrate"] for r in results.values() if r["units"] == 120)
    report = {
        "cases": results,
        "requirement_120_units_detect_plus_calibrate_s": LIMIT_120,
        "worst_120_units_detect_plus_calibrate_s": worst_120,
        "meets_requirement": bool(worst_120 <= LIMIT_120),
        "cpu_count": os.cpu_count(),
        "load_average": list(os.getloadavg()),
        "openblas_num_threads": os.environ.get("OPENBLAS_NUM_THREADS"),
    }
    (out_dir / "pipeline.json").write_text(json.dumps(report, indent=2))
    return report


if __name__ == "__main__":
    import sys

    print(json.dumps(main(Path(sys.argv[1] if len(sys.argv) > 1 else "benchmarks/results")), indent=2))
