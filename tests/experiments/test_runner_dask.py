"""The sweep runner on a real Dask cluster (scheduler + two worker processes on the loopback)."""

from __future__ import annotations

import socket
import time

import pytest
from click.testing import CliRunner

from selfcal.errors import InputError
from selfcal.experiments.runner import _example_trial, check_scheduler_address, run_sweep

distributed = pytest.importorskip("distributed")

GRID = [{"x": 1}, {"x": 2}, {"x": 3}]


@pytest.fixture(scope="module")
def cluster():  # type: ignore[no-untyped-def]
    """A scheduler and two single-threaded worker processes on 127.0.0.1, stopped afterwards."""
    from dask.distributed import LocalCluster

    c = LocalCluster(n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1",
                     scheduler_port=0, dashboard_address=None)
    try:
        yield c
    finally:
        c.close()


@pytest.mark.parametrize("chunk_size", [None, 1, 4])
def test_dask_scheduler_gives_the_serial_rows(cluster, chunk_size) -> None:  # type: ignore[no-untyped-def]
    """Same master seed -> the same rows in the same order, whatever the chunking."""
    serial = run_sweep(_example_trial, GRID, runs=5, seed=11, backend="serial", progress=False)
    dask = run_sweep(_example_trial, GRID, runs=5, seed=11, backend="dask", scheduler=cluster.scheduler_address,
                     progress=False, chunk_size=chunk_size)
    assert dask == serial
    assert len({r["seed"] for r in serial}) == 15  # one independent seed per trial


def test_processes_backend_chunks_give_the_serial_rows() -> None:
    serial = run_sweep(_example_trial, GRID, runs=4, seed=3, progress=False)
    procs = run_sweep(_example_trial, GRID, runs=4, seed=3, backend="processes", workers=2, chunk_size=5,
                      progress=False)
    assert procs == serial


@pytest.mark.parametrize("bad", ["localhost:8786", "tcp://", "tcp://host", "tcp://host:99999", "http://h:1", "tcp://a b:1"])
def test_malformed_scheduler_address_is_an_input_error(bad: str) -> None:
    with pytest.raises(InputError, match="tcp://HOST:PORT"):
        check_scheduler_address(bad)
    with pytest.raises(InputError):
        run_sweep(_example_trial, GRID, backend="dask", scheduler=bad, progress=False)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def test_unreachable_scheduler_fails_fast_with_one_line() -> None:
    t = time.perf_counter()
    with pytest.raises(InputError, match="no Dask scheduler answered") as exc:
        run_sweep(_example_trial, GRID, backend="dask", scheduler=f"tcp://127.0.0.1:{_free_port()}",
                  progress=False, connect_timeout=2.0)
    assert "\n" not in str(exc.value)
    assert time.perf_counter() - t < 60  # a loose guard against hanging, not a speed test


def test_cli_reports_a_bad_scheduler_on_one_line_with_exit_2(tmp_path) -> None:  # type: ignore[no-untyped-def]
    from selfcal.cli import main

    r = CliRunner().invoke(main, ["reproduce", "delays", "--quick", "--backend", "dask", "--scheduler", "nonsense",
                                  "--out", str(tmp_path / "o")])
    assert r.exit_code == 2, r.output
    lines = [ln for ln in r.output.splitlines() if ln.strip()]
    assert len(lines) == 1 and "tcp://HOST:PORT" in lines[0]
