"""The pipeline's outputs before and after a refactoring of its internals: byte-equal JSON.

Issue 30 (the pipeline's solution typed: ``selfcal.acoustics.calibrate.Calibration`` instead
of an untyped dict) must not change a single output. This script exports the sources of a git
revision (``--rev``, default ``7c2455d``, the last commit with the dict) with ``git archive``
and runs the CLI of both trees in subprocesses on the same inputs:

- ``selfcal demo`` on the four simulated layouts (flat and boundary desks with known heights,
  tiered rows and stem microphones; 8 units, an 8 x 7 x 3 m room);
- ``selfcal pipeline`` on the demo recordings with ``--dim auto`` (the recording's
  heights.json), ``2`` and ``3`` (a refusal on the near-planar ones), without heights.json
  (3-D, the one-side rule, the near-planar 2-D answer), and with ``unit_offsets`` and a wrong
  speed of sound in setup.json (the scale from known distances).

Compared per run: the result JSON with the ``timings*`` keys removed (wall and CPU seconds
differ from run to run), the exit status, and stdout / stderr without its timing lines. A
run that differs is measured: its largest position difference after a rigid alignment, the
raw one (the free gauge of a 2-D / known-heights fit is a planar motion held at the start),
the pair offsets' and the iterations. Timing: the ``calibrate`` stage's CPU seconds of the
two trees in the same invocation (``--repeat N``: N runs each, alternating order, medians),
old over new per run and their geometric mean. Usage::

    PYTHONPATH=src python benchmarks/compare_pipeline_outputs.py [--rev 7c2455d] [--work DIR] [--repeat 3]
"""

from __future__ import annotations

import argparse
import json
import math
import os
import re
import shutil
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
LAYOUTS = {"flat": 1, "tiered": 2, "boundary": 3, "stem": 4}


def _strip(x: Any) -> Any:
    if isinstance(x, dict):
        return {k: _strip(v) for k, v in x.items() if not k.startswith("timings")}
    if isinstance(x, list):
        return [_strip(v) for v in x]
    return x


def _difference(old: Any, new: Any) -> str:
    """How far two results differ: positions after a rigid alignment (x-y for the 2-D and
    known-heights models, whose free gauge is a planar motion), pair offsets, iterations."""
    import numpy as np

    from selfcal.geometry import align

    if not (isinstance(old, dict) and isinstance(new, dict) and "receivers" in old and "receivers" in new):
        return ""

    def arr(x: Any) -> Any:
        return np.array(json.loads(json.dumps(x).replace("null", "NaN")), float)

    Pa, Pb = (np.vstack([arr(r["receivers"]), arr(r["sources"])]) for r in (old, new))
    if Pa.shape != Pb.shape:
        return f" (shapes {Pa.shape} vs {Pb.shape})"
    ok = np.isfinite(Pa).all(axis=1) & np.isfinite(Pb).all(axis=1)
    k = 2 if str(new.get("method", "")).startswith("2d") else Pa.shape[1]
    moved = float(np.abs(align(Pb[ok, :k], Pa[ok, :k], reflection=False).apply(Pb[ok, :k]) - Pa[ok, :k]).max())
    pair = [arr(r["receiver_offsets"])[:, None] + arr(r["source_offsets"])[None, :] for r in (old, new)]
    return (f" (aligned positions {moved:.1e} m, raw {float(np.nanmax(np.abs(Pa - Pb))):.1e} m, pair offsets "
            f"{float(np.nanmax(np.abs(pair[0] - pair[1]))):.1e} s, iterations {old.get('iterations')} -> "
            f"{new.get('iterations')})")


def _run(src: Path, args: list[str]) -> tuple[int, list[str]]:
    env = dict(os.environ, PYTHONPATH=str(src), OPENBLAS_NUM_THREADS="1")
    p = subprocess.run([sys.executable, "-m", "selfcal", *args], env=env, capture_output=True, text=True)
    lines = [ln for ln in (p.stdout + p.stderr).splitlines() if not re.search(r"^time|wrote|\d+\.\d+ s\b", ln)]
    return p.returncode, lines


def _variants(rec: Path, work: Path) -> list[tuple[str, Path]]:
    """The demo recording without heights.json, and with unit_offsets and c = 340 m/s."""
    nh, uo = work / f"{rec.parent.name}-noheights", work / f"{rec.parent.name}-unitoffsets"
    for d in (nh, uo):
        shutil.copytree(rec, d)
    (nh / "heights.json").unlink(missing_ok=True)
    truth = json.loads((uo / "truth.json").read_text())
    setup = json.loads((uo / "setup.json").read_text())
    setup["unit_offsets"] = {n: math.dist(truth["receivers"][k], truth["senders"][k])
                             for k, n in enumerate(setup["receivers"])}
    setup["speed_of_sound"] = 340.0
    (uo / "setup.json").write_text(json.dumps(setup))
    return [("noheights", nh), ("unitoffsets", uo)]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rev", default="7c2455d")
    ap.add_argument("--work", type=Path, default=None)
    ap.add_argument("--repeat", type=int, default=1, help="runs per tree, for the calibrate stage's CPU ratio")
    a = ap.parse_args()
    work = a.work or Path(tempfile.mkdtemp(prefix="pipeline-outputs-"))
    old = work / "old"
    old.mkdir(parents=True, exist_ok=True)
    (work / "new").mkdir(exist_ok=True)
    tar = subprocess.run(["git", "archive", a.rev, "src"], cwd=ROOT, check=True, capture_output=True).stdout
    subprocess.run(["tar", "-x", "-C", str(old)], input=tar, check=True)
    trees = {"old": old / "src", "new": ROOT / "src"}
    differ = runs = 0

    ratios: list[float] = []

    def compare(name: str, make_args: Any, json_of: Any = None) -> None:
        nonlocal differ, runs
        out: dict[str, Any] = {}
        cpu: dict[str, list[float]] = {t: [] for t in trees}
        for k in range(a.repeat):  # alternating order: a drifting machine load hits both trees alike
            for tag in (list(trees) if k % 2 == 0 else list(trees)[::-1]):
                rc, lines = _run(trees[tag], make_args(tag))
                js = work / tag / f"{name}.json" if json_of is None else json_of(tag)
                raw = json.loads(js.read_text()) if js.exists() else None
                if raw is not None and "calibrate" in raw.get("timings_cpu", {}):
                    cpu[tag].append(float(raw["timings_cpu"]["calibrate"]))
                if k == 0:
                    out[tag] = (rc, lines, _strip(raw) if raw is not None else None)
        same = out["old"] == out["new"]
        runs += 1
        differ += not same
        method = (out["new"][2] or {}).get("method", "(no result: " + (out["new"][1] or ["?"])[-1][:60] + ")")
        timing = ""
        if cpu["old"] and cpu["new"]:
            ratios.append(statistics.median(cpu["old"]) / statistics.median(cpu["new"]))
            timing = f"  calibrate CPU old/new {ratios[-1]:.2f}"
        how = "" if same else _difference(out["old"][2], out["new"][2])
        print(f"{name:28s} exit {out['new'][0]}  {'equal' if same else 'DIFFERENT'}{how}{timing}  {method}", flush=True)

    for layout, seed in LAYOUTS.items():
        demo = {t: work / t / f"demo-{layout}" for t in trees}
        compare(f"demo-{layout}", lambda t, layout=layout, seed=seed, demo=demo: [
            "demo", "-o", str(demo[t]), "--layout", layout, "--units", "8", "--seed", str(seed), "--room", "8x7x3"],
            lambda t, demo=demo: demo[t] / "result.json")
        rec = demo["old"] / "recording"
        for dim in ("auto", "2", "3"):
            compare(f"pipeline-{layout}-dim{dim}", lambda t, n=f"pipeline-{layout}-dim{dim}", dim=dim, rec=rec: [
                "pipeline", str(rec), "-o", str(work / t / f"{n}.json"), "--dim", dim])
        for kind, folder in _variants(rec, work):
            compare(f"pipeline-{layout}-{kind}", lambda t, n=f"pipeline-{layout}-{kind}", folder=folder: [
                "pipeline", str(folder), "-o", str(work / t / f"{n}.json")])
    print(f"{runs} runs, {differ} different (JSON without timings, exit status, output without timing lines)")
    if ratios:
        print(f"calibrate stage CPU old/new: geometric mean {math.exp(statistics.mean(map(math.log, ratios))):.3f} "
              f"over {len(ratios)} runs (median of {a.repeat} per tree), min {min(ratios):.2f}, max {max(ratios):.2f}")
    return int(differ > 0)


if __name__ == "__main__":
    raise SystemExit(main())
