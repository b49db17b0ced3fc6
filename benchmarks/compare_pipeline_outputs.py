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
differ from run to run), the exit status, and stdout / stderr without its timing lines.
Usage::

    PYTHONPATH=src python benchmarks/compare_pipeline_outputs.py [--rev 7c2455d] [--work DIR]
"""

from __future__ import annotations

import argparse
import json
import math
import os
import re
import shutil
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
    a = ap.parse_args()
    work = a.work or Path(tempfile.mkdtemp(prefix="pipeline-outputs-"))
    old = work / "old"
    old.mkdir(parents=True, exist_ok=True)
    (work / "new").mkdir(exist_ok=True)
    tar = subprocess.run(["git", "archive", a.rev, "src"], cwd=ROOT, check=True, capture_output=True).stdout
    subprocess.run(["tar", "-x", "-C", str(old)], input=tar, check=True)
    trees = {"old": old / "src", "new": ROOT / "src"}
    differ = runs = 0

    def compare(name: str, make_args: Any, json_of: Any = None) -> None:
        nonlocal differ, runs
        out = {}
        for tag, src in trees.items():
            rc, lines = _run(src, make_args(tag))
            js = work / tag / f"{name}.json" if json_of is None else json_of(tag)
            out[tag] = (rc, lines, _strip(json.loads(js.read_text())) if js.exists() else None)
        same = out["old"] == out["new"]
        runs += 1
        differ += not same
        method = (out["new"][2] or {}).get("method", "(no result: " + (out["new"][1] or ["?"])[-1][:60] + ")")
        print(f"{name:28s} exit {out['new'][0]}  {'equal' if same else 'DIFFERENT'}  {method}", flush=True)

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
    return int(differ > 0)


if __name__ == "__main__":
    raise SystemExit(main())
