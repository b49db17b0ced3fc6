"""Shared pieces of the ``selfcal`` command line: the groups and the error contract.

Every command module in :mod:`selfcal.commands` attaches its commands to the groups
defined here. Contract (DESIGN.md): bad input -> one line on stderr naming the
problem, exit status 2, and no output file (outputs are written atomically, last).
"""

from __future__ import annotations

import functools
import sys
from collections.abc import Callable
from typing import Any, TypeVar

import click

from ..errors import SelfcalError
from ._common import SelfcalGroup, command_context
from ._options import SEED

F = TypeVar("F", bound=Callable[..., Any])


@click.group(cls=SelfcalGroup, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(None, "-V", "--version", package_name="selfcal")
@click.option("-q", "--quiet", is_flag=True, help="Print only errors and FAIL lines (anywhere on the line).")
@click.option("-v", "--verbose", is_flag=True, help="Print warnings and the traceback of an internal error.")
def main(quiet: bool = False, verbose: bool = False) -> None:
    """selfcal: self-calibration and localization of sensor networks.

    Exit status: 0 = trustworthy result, 1 = the result failed its own test (a FAIL: line),
    2 = bad input or an unwritable output (one line on stderr). Matrices: rows = receivers,
    columns = transmitters; point lists: one point per row.
    """


@main.group()
def calibrate() -> None:
    """Anchor-free self-calibration (TOA ranges / times, far-field TDOA)."""


@main.group()
def locate() -> None:
    """Localize a receiver from measurements to known beacons."""


@main.group()
def reproduce() -> None:
    """Reproduce the experiments of the papers (figures + JSON of the numbers)."""


@main.group()
def simulate() -> None:
    """Write simulated scenarios (recordings, matrices) with their ground truth."""


@main.group()
def slac() -> None:
    """Simultaneous localization and calibration of radio networks (paper 002)."""


def fail(message: str) -> None:
    """Print one line on stderr and exit with status 2 (the bad-input contract)."""
    click.echo(f"selfcal: error: {' '.join(str(message).split())}", err=True)
    sys.exit(2)


def handle_errors(func: F) -> F:
    """Turn selfcal's named errors (and unreadable files) into the one-line / exit-2 contract.

    Every command has it: its outputs are checked against its inputs before it runs
    (:func:`selfcal.commands._common.command_context`).
    """

    @functools.wraps(func)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        try:
            with command_context(kwargs):
                return func(*args, **kwargs)
        except SelfcalError as exc:
            fail(str(exc))
        except (FileNotFoundError, IsADirectoryError, PermissionError) as exc:
            fail(f"{exc.filename}: {exc.strerror}")

    wrapper.__selfcal_contract__ = True  # type: ignore[attr-defined]  # tests: every command has it
    return wrapper  # type: ignore[return-value]


backend_option = click.option(
    "--backend", type=click.Choice(["serial", "processes", "dask"]), default="processes", show_default=True,
    help="Where the Monte-Carlo trials run.",
)
scheduler_option = click.option(
    "--scheduler", default=None, metavar="tcp://HOST:PORT",
    help="With --backend dask: an existing Dask scheduler (default: start a LocalCluster).",
)
seed_option = click.option("--seed", type=SEED, default=0, show_default=True, help="Master random seed.")
