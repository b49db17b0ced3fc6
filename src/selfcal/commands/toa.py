"""``selfcal calibrate toa``: anchor-free TOA / range self-calibration from a matrix file."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import click

from ._base import calibrate, handle_errors
from ._common import all_or_nothing, csv_option, unit_options

if TYPE_CHECKING:
    from ..toa.solve import ToaResult


@calibrate.command("toa")
@click.argument("matrix", type=click.Path(dir_okay=False, path_type=Path))
@click.option("--speed", type=float, default=None, metavar="C",
              help="Propagation speed in m/s: the matrix holds seconds; offsets are reported in seconds.")
@click.option("--offsets", type=click.Choice(["none", "receivers", "sources", "both"]), default="none",
              show_default=True, help="Unknown per-receiver (d_i) and/or per-source (o_j) offsets.")
@click.option("--dim", type=click.Choice(["2", "3"]), default="3", show_default=True, help="Dimension.")
@click.option("--loss", type=click.Choice(["linear", "huber", "soft_l1", "cauchy"]), default="linear",
              show_default=True, help="Robust loss for outliers.")
@click.option("--method", type=click.Choice(["auto", "nls", "rank3"]), default="auto", show_default=True,
              help="auto: initialise + NLS + multi-start; nls: one refinement; rank3: 004 initialiser only.")
@click.option("--seed", type=int, default=0, show_default=True, help="Random seed (initialisers, restarts).")
@click.option("--out", "out", type=click.Path(dir_okay=False, path_type=Path), required=True,
              help="Result JSON (keys per DESIGN.md).")
@click.option("--plot", "plot", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Figure of receivers and sources with 95% confidence ellipses (format from the suffix: .png, .pdf, .svg).")
@csv_option
@unit_options
@handle_errors
@all_or_nothing
def toa_command(matrix: Path, speed: float | None, offsets: str, dim: str, loss: str, method: str,
                seed: int, out: Path, plot: Path | None, csv_out: Path | None = None, unit: str | None = None,
                sample_rate: float | None = None) -> None:
    """Calibrate receivers and sources from an I x J TOA/range MATRIX (CSV or .npy, NaN = missing).

    Rows are receivers, columns are sources (a header row and a first column of names are
    kept). Metres unless --speed is given (then seconds); --unit names another unit.
    """
    import numpy as np

    from .._checks import plausible_matrix_scale
    from ..io import read_table, write_json
    from ..toa import solve_toa
    from ._common import enrich_payload, to_metres, write_nodes_csv

    table = read_table(matrix, name=str(matrix))
    M, speed, _ = to_metres(table.values, unit, speed, sample_rate, name=str(matrix))
    plausible_matrix_scale(M, speed=speed, explicit_unit=unit is not None, name=str(matrix))
    res = solve_toa(M, dim=int(dim), offsets=offsets, speed=speed, loss=loss, method=method, rng=seed)
    if plot is not None:
        _plot(res, plot)
    payload = enrich_payload(res.to_dict(), names={"receiver_names": table.row_names,
                                                   "source_names": table.col_names})
    write_json(out, payload)
    if csv_out is not None:
        write_nodes_csv(csv_out, payload, [("receiver", "receivers", "receiver_names"),
                                           ("source", "sources", "source_names")])
    unit = "s" if speed is not None else "m"
    I, J = M.shape
    tr = np.trace(res.receiver_cov, axis1=1, axis2=2)
    ts = np.trace(res.source_cov, axis1=1, axis2=2)
    lines = [
        f"selfcal calibrate toa: {I} receivers x {J} sources, {dim}-D, offsets={offsets}, "
        f"{res.n_missing} missing",
        f"  method {res.method}, converged={res.converged}, iterations={res.iterations}",
        f"  residual RMS {res.residual_rms:.4g} {unit}, noise sigma {res.sigma:.4g} {unit}",
    ]
    if np.isfinite(tr).all():
        lines.append(
            f"  predicted position std (RMS over points): receivers {np.sqrt(tr.mean()):.4g} m, "
            f"sources {np.sqrt(ts.mean()):.4g} m"
        )
    lines.append(f"  wrote {out}" + (f" and {plot}" if plot is not None else ""))
    click.echo("\n".join(lines))


def _plot(res: ToaResult, path: Path) -> None:
    from ..plotting import new_figure, plot_positions, save_figure

    fig, ax = new_figure()
    plot_positions(ax, res.receivers, cov=res.receiver_cov, label="receivers", color="C0", marker="x")
    plot_positions(ax, res.sources, cov=res.source_cov, label="sources", color="C3", marker="s")
    ax.set_title("TOA self-calibration (95% ellipses, canonical gauge)")
    ax.legend(loc="best", fontsize=8)
    save_figure(fig, path)
