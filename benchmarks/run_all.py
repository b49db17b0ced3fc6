"""Run every ``benchmarks/bench_*.py`` and collect their JSON reports.

Each benchmark module defines ``main(out_dir: pathlib.Path) -> dict`` that writes
``<out_dir>/<name>.json`` and returns the same dict. Usage::

    python benchmarks/run_all.py --out benchmarks/results [--only toa,farfield]
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import sys
import time
import traceback
from pathlib import Path


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results"))
    ap.add_argument("--only", default="", help="comma-separated benchmark names (e.g. toa,aoa)")
    args = ap.parse_args()
    here = Path(__file__).resolve().parent
    only = {s.strip() for s in args.only.split(",") if s.strip()}
    args.out.mkdir(parents=True, exist_ok=True)
    summary: dict[str, object] = {}
    failed = False
    for path in sorted(here.glob("bench_*.py")):
        name = path.stem.removeprefix("bench_")
        if only and name not in only:
            continue
        spec = importlib.util.spec_from_file_location(path.stem, path)
        assert spec and spec.loader
        mod = importlib.util.module_from_spec(spec)
        t0 = time.perf_counter()
        try:
            spec.loader.exec_module(mod)
            summary[name] = mod.main(args.out)
        except Exception:  # a failing benchmark is reported, the others still run
            traceback.print_exc()
            summary[name] = {"error": traceback.format_exc(limit=2)}
            failed = True
        print(f"[bench] {name}: {time.perf_counter() - t0:.1f} s", file=sys.stderr)
    (args.out / "summary.json").write_text(json.dumps(summary, indent=2, default=str))
    print(json.dumps(summary, indent=2, default=str))
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
