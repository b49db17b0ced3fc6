"""One sweep runner for every reproduction: seeded trials, three backends, tidy output.

A *trial* is a picklable module-level function ``trial(params: dict, seed: int) -> dict``.
:func:`run_sweep` evaluates it for every parameter set and repetition, each with its own
independent seed spawned from one master seed (so results do not depend on the backend
or on the order of execution), and returns tidy rows ``{**params, "rep": r, "seed": s, **result}``.

Backends
--------
``serial``     in this process (debugging, small sweeps)
``processes``  a local :class:`concurrent.futures.ProcessPoolExecutor`
``dask``       Dask distributed: ``scheduler="tcp://HOST:PORT"`` connects to an existing
               cluster, ``None`` starts a :class:`distributed.LocalCluster`
"""

from __future__ import annotations

import csv
import io
import os
from collections.abc import Callable, Iterable, Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path
from typing import Any

import numpy as np
from tqdm.auto import tqdm

from .._checks import check_choice
from ..io import atomic_write_bytes, to_jsonable, write_json

__all__ = ["run_sweep", "write_rows", "BACKENDS"]

BACKENDS = ("serial", "processes", "dask")
Trial = Callable[[dict[str, Any], int], dict[str, Any]]


def _tasks(grid: Sequence[dict[str, Any]], runs: int, seed: int) -> list[tuple[dict[str, Any], int, int]]:
    children = np.random.SeedSequence(seed).spawn(len(grid) * runs)
    out = []
    k = 0
    for params in grid:
        for rep in range(runs):
            out.append((dict(params), rep, int(children[k].generate_state(1, dtype=np.uint32)[0])))
            k += 1
    return out


def _call(trial: Trial, params: dict[str, Any], rep: int, seed: int) -> dict[str, Any]:
    result = trial(params, seed)
    return {**params, "rep": rep, "seed": seed, **result}


def run_sweep(
    trial: Trial,
    grid: Iterable[dict[str, Any]],
    *,
    runs: int = 1,
    seed: int = 0,
    backend: str = "serial",
    scheduler: str | None = None,
    workers: int | None = None,
    progress: bool = True,
    desc: str = "trials",
) -> list[dict[str, Any]]:
    """Run ``trial`` for every parameter dict in ``grid``, ``runs`` times each.

    Returns the tidy rows in grid order (independent of completion order).
    """
    check_choice(backend, "backend", BACKENDS)
    tasks = _tasks(list(grid), int(runs), int(seed))
    rows: list[dict[str, Any] | None] = [None] * len(tasks)
    bar = tqdm(total=len(tasks), desc=desc, disable=None if progress else True, leave=False)
    try:
        if backend == "serial":
            for k, (p, r, s) in enumerate(tasks):
                rows[k] = _call(trial, p, r, s)
                bar.update()
        elif backend == "processes":
            n = workers or max(1, (os.cpu_count() or 1))
            with ProcessPoolExecutor(max_workers=n) as ex:
                futs = {ex.submit(_call, trial, p, r, s): k for k, (p, r, s) in enumerate(tasks)}
                for f in as_completed(futs):
                    rows[futs[f]] = f.result()
                    bar.update()
        else:
            from dask.distributed import Client, LocalCluster
            from dask.distributed import as_completed as das_completed

            cluster = None
            if scheduler is None:
                cluster = LocalCluster(n_workers=workers or max(1, os.cpu_count() or 1), threads_per_worker=1, processes=True, dashboard_address=None)
                client = Client(cluster)
            else:
                client = Client(scheduler)
            try:
                dfuts = [client.submit(_call, trial, p, r, s, pure=False) for (p, r, s) in tasks]
                index = {f.key: k for k, f in enumerate(dfuts)}
                for df in das_completed(dfuts):
                    rows[index[df.key]] = df.result()
                    bar.update()
            finally:
                client.close()
                if cluster is not None:
                    cluster.close()
    finally:
        bar.close()
    return [r for r in rows if r is not None]


def write_rows(rows: Sequence[dict[str, Any]], path: str | os.PathLike[str]) -> None:
    """Write tidy rows atomically as ``.csv`` (union of keys as header) or ``.json``."""
    p = Path(path)
    if p.suffix.lower() == ".json":
        write_json(p, list(rows))
        return
    keys: list[str] = []
    for r in rows:
        for k in r:
            if k not in keys:
                keys.append(k)
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=keys)
    w.writeheader()
    for r in rows:
        w.writerow({k: to_jsonable(v) for k, v in r.items()})
    atomic_write_bytes(p, buf.getvalue().encode())
