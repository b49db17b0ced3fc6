"""One sweep runner for every reproduction: seeded trials, three backends, tidy output.

A *trial* is a picklable module-level function ``trial(params: dict, seed: int) -> dict``.
:func:`run_sweep` evaluates it for every parameter set and repetition, each with its own
independent seed spawned from one master seed (so results do not depend on the backend,
the chunking or the order of execution), and returns tidy rows
``{**params, "rep": r, "seed": s, **result}``.

Backends
--------
``serial``     in this process (debugging, small sweeps)
``processes``  a local :class:`concurrent.futures.ProcessPoolExecutor`
``dask``       Dask distributed: ``scheduler="tcp://HOST:PORT"`` connects to an existing
               cluster (a malformed address, or no scheduler answering within
               ``CONNECT_TIMEOUT_S``, is an :class:`~selfcal.errors.InputError`: one line,
               exit 2 on the command line), ``None`` starts a :class:`distributed.LocalCluster`

Chunks. A trial of a few milliseconds costs about as much as one task's overhead (pickling,
scheduling, a round trip), so trials are submitted in chunks of consecutive (params, seed)
pairs, one task per chunk: ``chunk_size`` trials per task, by default enough for about four
tasks per worker (and at most 64 trials per task, so progress stays visible). Progress is a
tqdm bar updated per finished chunk, drawn only when stderr is a terminal.
"""

from __future__ import annotations

import csv
import io
import math
import os
import re
from collections.abc import Callable, Iterable, Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path
from typing import Any

import numpy as np
from tqdm.auto import tqdm

from .._checks import TRIAL_BYTES, check_choice, entry, guard_size
from .._result import jsonable
from ..errors import InputError
from ..io import atomic_write_bytes, write_json
from ..progress import enabled as progress_enabled

__all__ = ["run_sweep", "write_rows", "BACKENDS", "CONNECT_TIMEOUT_S", "check_scheduler_address"]

BACKENDS = ("serial", "processes", "dask")
#: seconds to wait for a Dask scheduler given by address before giving up
CONNECT_TIMEOUT_S = 5.0
#: at most this many trials per task (progress granularity)
MAX_CHUNK = 64
Trial = Callable[[dict[str, Any], int], dict[str, Any]]
Task = tuple[dict[str, Any], int, int]

_ADDRESS = re.compile(r"^(tcp|tls|inproc|ucx)://(\[[0-9A-Fa-f:.]+\]|[A-Za-z0-9_.-]+):(\d{1,5})$")


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


def _call_chunk(trial: Trial, chunk: list[Task]) -> list[dict[str, Any]]:
    """Run consecutive trials in one task (one round trip for the whole chunk)."""
    return [_call(trial, p, r, s) for p, r, s in chunk]


def _chunks(tasks: list[Task], size: int) -> list[list[Task]]:
    return [tasks[k : k + size] for k in range(0, len(tasks), size)]


def _chunk_size(n_tasks: int, n_workers: int, chunk_size: int | None) -> int:
    if chunk_size is not None:
        if int(chunk_size) < 1:
            raise InputError(f"chunk_size must be >= 1, got {chunk_size}")
        return int(chunk_size)
    return max(1, min(MAX_CHUNK, math.ceil(n_tasks / max(1, 4 * n_workers))))


def check_scheduler_address(address: str) -> str:
    """Validate a Dask scheduler address ``tcp://HOST:PORT`` (also tls://, inproc://, ucx://).

    Parameters
    ----------
    address : the address as given on the command line.

    Returns
    -------
    The address, stripped.

    Raises
    ------
    InputError
        When it is not ``SCHEME://HOST:PORT`` with a port in 1..65535.

    Examples
    --------
    >>> check_scheduler_address("tcp://127.0.0.1:8786")
    'tcp://127.0.0.1:8786'
    """
    a = str(address).strip()
    m = _ADDRESS.match(a)
    if m is None or not 0 < int(m.group(3)) < 65536:
        raise InputError(f"--scheduler: expected tcp://HOST:PORT (port 1-65535), got {address!r}")
    return a


def _connect(address: str, timeout: float) -> Any:
    """A :class:`distributed.Client` on ``address``, or an InputError within ``timeout`` seconds."""
    from dask.distributed import Client

    try:
        return Client(address, timeout=f"{timeout}s")
    except (OSError, TimeoutError) as exc:
        raise InputError(
            f"--scheduler: no Dask scheduler answered at {address} within {timeout:g} s "
            f"({type(exc).__name__}); start one with 'dask scheduler' or drop --scheduler"
        ) from None


@entry(trial="callable", runs="count", seed="count0", progress="bool", desc="str", chunk_size="count?",
       workers="count?")
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
    chunk_size: int | None = None,
    connect_timeout: float = CONNECT_TIMEOUT_S,
) -> list[dict[str, Any]]:
    """Run ``trial`` for every parameter dict in ``grid``, ``runs`` times each.

    Parameters
    ----------
    trial : picklable module-level ``trial(params, seed) -> dict``.
    grid : parameter dicts.
    runs : repetitions per parameter dict, each with its own spawned seed.
    seed : master seed (``numpy.random.SeedSequence``).
    backend : "serial", "processes" or "dask".
    scheduler : with ``backend="dask"``: ``tcp://HOST:PORT`` of a running scheduler
        (None: a LocalCluster of ``workers`` processes is started and stopped).
    workers : local worker processes (default: the CPU count).
    progress : show a tqdm bar (only when stderr is a terminal).
    desc : the bar's label.
    chunk_size : trials per task (default: about four tasks per worker, at most 64).
    connect_timeout : seconds to wait for ``scheduler``.

    Returns
    -------
    The tidy rows in grid order (independent of completion order, backend and chunking).

    Raises
    ------
    InputError
        For an unknown backend, a malformed or unreachable scheduler, a bad chunk size.

    Examples
    --------
    >>> rows = run_sweep(_example_trial, [{"x": 2}], runs=2, seed=1, progress=False)
    >>> [r["value"] for r in rows]
    [4, 4]
    """
    check_choice(backend, "backend", BACKENDS)
    if scheduler is not None:
        if backend != "dask":
            raise InputError("--scheduler needs --backend dask")
        scheduler = check_scheduler_address(scheduler)
    grid = list(grid)
    guard_size(float(runs) * max(len(grid), 1) * TRIAL_BYTES, f"{runs} runs x {len(grid)} settings")
    tasks = _tasks(grid, int(runs), int(seed))
    rows: list[dict[str, Any] | None] = [None] * len(tasks)
    show = bool(progress) and progress_enabled()
    bar = tqdm(total=len(tasks), desc=desc, disable=not show, leave=False)

    def store(k0: int, out: list[dict[str, Any]]) -> None:
        rows[k0 : k0 + len(out)] = out
        bar.update(len(out))

    try:
        if backend == "serial":
            for k, (p, r, s) in enumerate(tasks):
                store(k, [_call(trial, p, r, s)])
        elif backend == "processes":
            n = workers or max(1, (os.cpu_count() or 1))
            size = _chunk_size(len(tasks), n, chunk_size)
            with ProcessPoolExecutor(max_workers=n) as ex:
                futs = {ex.submit(_call_chunk, trial, c): k * size for k, c in enumerate(_chunks(tasks, size))}
                for f in as_completed(futs):
                    store(futs[f], f.result())
        else:
            from dask.distributed import Client, LocalCluster
            from dask.distributed import as_completed as das_completed

            cluster = None
            if scheduler is None:
                cluster = LocalCluster(n_workers=workers or max(1, os.cpu_count() or 1), threads_per_worker=1,
                                       processes=True, dashboard_address=None)
                client = Client(cluster)
            else:
                client = _connect(scheduler, float(connect_timeout))
            try:
                n = max(1, len(client.scheduler_info().get("workers", {})) or (workers or 1))
                size = _chunk_size(len(tasks), n, chunk_size)
                chunks = _chunks(tasks, size)
                dfuts = [client.submit(_call_chunk, trial, c, pure=False) for c in chunks]
                index = {f.key: k * size for k, f in enumerate(dfuts)}
                for df in das_completed(dfuts):
                    store(index[df.key], df.result())
            finally:
                client.close()
                if cluster is not None:
                    cluster.close()
    finally:
        bar.close()
    return [r for r in rows if r is not None]


def _example_trial(params: dict[str, Any], seed: int) -> dict[str, Any]:
    """The trial of the docstring example and the tests: ``x^2`` and one normal draw from ``seed``."""
    return {"value": params["x"] ** 2, "draw": float(np.random.default_rng(seed).normal())}


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
        w.writerow({k: jsonable(v) for k, v in r.items()})
    atomic_write_bytes(p, buf.getvalue().encode())
