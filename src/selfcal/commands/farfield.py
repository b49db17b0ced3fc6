"""``selfcal calibrate tdoa-farfield`` and ``selfcal reproduce farfield`` (paper 000)."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import click

from ._base import (
    backend_option,
    calibrate,
    handle_errors,
    reproduce,
    scheduler_option,
    seed_option,
)
from ._common import all_or_nothing, csv_option, unit_options

if TYPE_CHECKING:
    from ..tdoa import FarfieldResult


@calibrate.command("tdoa-farfield")
@click.argument("matrix", type=click.Path(dir_okay=False, path_type=Path))
@click.option("--out", "out", type=click.Path(dir_okay=False, path_type=Path), required=True,
              help="Result JSON (positions, directions, offsets, residual_rms, degeneracy, ...).")
@click.option("--speed", type=float, default=None, metavar="C",
              help="Propagation speed in m/s: the matrix holds seconds (TDOA); lengths are reported in metres.")
@click.option("--method", type=click.Choice(["auto", "lm", "alternating", "init", "minimal"]), default="auto",
              show_default=True, help="Refinement: LM on the spheres (Alg. 3), alternating (Alg. 2), or none.")
@click.option("--loss", type=click.Choice(["linear", "huber", "soft_l1", "cauchy"]), default="linear",
              show_default=True, help="Robust loss for outliers (rejected entries are listed in the JSON).")
@click.option("--noise-std", type=float, default=None,
              help="Known noise standard deviation (matrix units) for the degeneracy thresholds.")
@click.option("--ransac", is_flag=True, help="Screen outliers with RANSAC over the minimal solver first.")
@click.option("--seed", type=int, default=0, show_default=True, help="Random seed (RANSAC).")
@click.option("--allow-degenerate", is_flag=True,
              help="On a degenerate geometry write the partial reconstruction instead of failing.")
@click.option("--plot", "plot", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Figure of the positions and directions (format from the suffix: .png, .pdf, .svg).")
@csv_option
@unit_options
@handle_errors
@all_or_nothing
def farfield_command(matrix: Path, out: Path, speed: float | None, method: str, loss: str,
                     noise_std: float | None, ransac: bool, seed: int, allow_degenerate: bool,
                     plot: Path | None, csv_out: Path | None = None, unit: str | None = None,
                     sample_rate: float | None = None) -> None:
    """Self-calibrate from an m x k far-field TDOA MATRIX (CSV or .npy, NaN = missing).

    Rows are receiver positions (microphones, antenna positions), columns far transmitters;
    entry = relative distance z_i . n_j + C_j (metres, or seconds with --speed). A degenerate
    geometry (planar-motion, coplanar-directions, cone, collinear-motion,
    parallel-directions) exits with status 2 naming it, unless --allow-degenerate.
    """
    from .._checks import FARFIELD_TIMES_AS_METRES_MAX, plausible_matrix_scale
    from ..errors import DegenerateGeometryError, InputError
    from ..io import read_table, write_json
    from ..tdoa import solve_farfield
    from ._common import enrich_payload, to_metres, transposed_hint, write_nodes_csv

    table = read_table(matrix, name=str(matrix))
    M, speed, _ = to_metres(table.values, unit, speed, sample_rate, name=str(matrix))
    scale = 1.0
    if speed is not None:
        if not (speed > 0 and speed < float("inf")):
            raise InputError(f"--speed must be a positive number, got {speed}")
        scale = speed
    plausible_matrix_scale(M, speed=speed, explicit_unit=unit is not None, name=str(matrix),
                           min_span=FARFIELD_TIMES_AS_METRES_MAX)
    try:
        res = solve_farfield(M * scale, method=method, loss=loss,
                             noise_std=None if noise_std is None else noise_std * scale,
                             allow_degenerate=allow_degenerate, ransac=ransac, rng=seed)
    except DegenerateGeometryError as exc:
        transposed_hint(exc, M.shape, min_rows=4, min_cols=6)
        raise
    if plot is not None:
        _plot(res, plot)
    payload = enrich_payload(
        res.to_dict(), names={"position_names": table.row_names, "transmitter_names": table.col_names},
        units={"positions": "m", "directions": "unit vectors", "offsets": "m", "residual_rms": "m",
               "position_cov": "m^2"})
    write_json(out, payload)
    if csv_out is not None:
        write_nodes_csv(csv_out, payload, [("position", "positions", "position_names")])
    m, k = M.shape
    click.echo(f"selfcal calibrate tdoa-farfield: {m} positions x {k} transmitters, method {res.method}, "
               f"loss {res.loss}")
    click.echo(f"  residual RMS {res.residual_rms:.4g} m, converged={res.converged}, iterations={res.iterations}, "
               f"rejected entries {int(res.rejected.sum())}")
    if res.degeneracy is not None:
        click.echo(f"selfcal: warning: degenerate geometry [{res.degeneracy}]: wrote a partial reconstruction",
                   err=True)
    click.echo(f"  wrote {out}")


def _plot(res: FarfieldResult, path: Path) -> None:
    import numpy as np

    from ..plotting import new_figure, save_figure

    fig, axes = new_figure(1, 2, size=(11.0, 5.0))
    P = res.positions
    axes[0].scatter(P[:, 0], P[:, 1], c=P[:, 2], cmap="viridis", s=25)
    axes[0].scatter([0], [0], marker="x", c="r", s=60, label="position 1 (origin)")
    axes[0].set_aspect("equal")
    axes[0].set_xlabel("x [m]")
    axes[0].set_ylabel("y [m] (colour: z)")
    axes[0].set_title("receiver positions")
    axes[0].legend(loc="best")
    n = res.directions
    az = np.degrees(np.arctan2(n[:, 1], n[:, 0]))
    el = np.degrees(np.arcsin(np.clip(n[:, 2], -1, 1)))
    axes[1].scatter(az, el, s=12)
    axes[1].set_xlabel("azimuth [deg]")
    axes[1].set_ylabel("elevation [deg]")
    axes[1].set_title("directions" + (f" [{res.degeneracy}]" if res.degeneracy else ""))
    save_figure(fig, path)


@reproduce.command("farfield")
@click.option("--runs", type=int, default=None,
              help="Monte-Carlo runs per setting (default: reduced; --full uses the paper's sizes).")
@click.option("--full", is_flag=True, help="Paper-sized experiments (10,000 minimal tests, ...).")
@backend_option
@scheduler_option
@seed_option
@click.option("--out", "out", type=click.Path(file_okay=False, path_type=Path), default=Path("farfield-output"),
              show_default=True, help="Folder for fig1..fig4 PNGs and farfield.json.")
@handle_errors
def reproduce_farfield(runs: int | None, full: bool, backend: str, scheduler: str | None, seed: int,
                       out: Path) -> None:
    """Reproduce paper 000's Fig. 1-4 (minimal solver vs relative distance, initialisation for
    several sizes, LM vs alternating convergence, error vs noise) with our numbers beside the paper's."""
    from ..errors import InputError
    from ..experiments.farfield import reproduce_all

    if runs is not None and runs < 1:
        raise InputError("--runs must be >= 1")
    summary = reproduce_all(out, runs=runs, full=full, backend=backend, scheduler=scheduler, seed=seed)
    for line in summary["report"]:
        click.echo(line)
    click.echo(f"  wrote {out}/farfield.json and fig1..fig4 PNGs")
