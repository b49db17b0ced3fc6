"""``selfcal locate aoa`` and ``selfcal reproduce aoa`` (paper 001)."""

from __future__ import annotations

from pathlib import Path

import click

from ._base import backend_option, handle_errors, locate, reproduce, scheduler_option, seed_option


@locate.command("aoa")
@click.argument("beacons", type=click.Path(dir_okay=False))
@click.argument("bearings", type=click.Path(dir_okay=False))
@click.option("--out", "out", required=True, type=click.Path(dir_okay=False), help="RESULT.json")
@click.option(
    "--method", type=click.Choice(["auto", "sol1", "sol2", "p3p", "ml", "linear"]), default="auto",
    show_default=True, help="sol1/sol2: paper 001 solutions; p3p: all closed-form candidates; ml: refined.",
)
@click.option(
    "--angles", type=click.Choice(["deg", "rad"]), default=None,
    help="BEARINGS holds angles: N x 2 (alpha, beta) with the receiver x/y axes in 3-D, N x 1 in 2-D.",
)
@click.option("--sigma-deg", type=float, default=None, help="Angular noise std for the ML covariance.")
@click.option(
    "--hint", default=None, metavar="X,Y[,Z]",
    help="Rough receiver position: picks among equally good candidates (three beacons in 3-D).",
)
@handle_errors
def locate_aoa(
    beacons: str, bearings: str, out: str, method: str, angles: str | None, sigma_deg: float | None,
    hint: str | None,
) -> None:
    """Receiver position and orientation from bearings to known BEACONS (N x d, d = 2 or 3).

    BEARINGS: N x d unit vectors in the receiver frame (a NaN row = beacon not received), or
    angles with --angles. Writes position, rotation (columns = receiver axes in the global
    frame), residual_rms (rad), method, covariance and candidates (when ambiguous).
    """
    import numpy as np

    from .._checks import plausible_angles
    from ..aoa import angles_to_bearings, solve_aoa
    from ..errors import InputError
    from ..io import read_table, write_json
    from ._common import enrich_payload

    btab = read_table(beacons, "beacons")
    b = btab.values
    u = read_table(bearings, "bearings").values
    if angles is not None:
        plausible_angles(u, angles)
        a = np.radians(u) if angles == "deg" else u
        if b.shape[1] == 3 and a.shape[1] == 2:
            u = angles_to_bearings(a[:, 0], a[:, 1]).vectors
            u[np.isnan(a).any(axis=1)] = np.nan
        elif b.shape[1] == 2 and a.shape[1] == 1:
            u = np.column_stack([np.cos(a[:, 0]), np.sin(a[:, 0])])
        else:
            raise InputError(
                f"--angles: expected N x 2 (alpha, beta) for 3-D beacons or N x 1 for 2-D, got "
                f"{a.shape} with beacons {b.shape}"
            )
    if method == "linear" and b.shape[1] == 3:
        raise InputError("--method linear is the 2-D closed form; use p3p/sol1/sol2/ml in 3-D")
    if method in ("sol1", "sol2", "p3p") and b.shape[1] == 2:
        raise InputError(f"--method {method} is 3-D; in 2-D use linear, ml or auto")
    sigma = None if sigma_deg is None else float(np.radians(sigma_deg))
    position_hint = None
    if hint is not None:
        try:
            position_hint = [float(v) for v in hint.split(",")]
        except ValueError:
            raise InputError(f"--hint: expected comma-separated numbers, got {hint!r}") from None
    res = solve_aoa(b, u, method=method, sigma=sigma, position_hint=position_hint)
    write_json(out, enrich_payload(res.to_dict(), names={"beacon_names": btab.row_names},
                                   units={"position": "m", "rotation": "columns = receiver axes in the global frame",
                                          "residual_rms": "rad", "covariance": "m^2 and rad^2"}))
    click.echo(
        f"position {np.array2string(res.position, precision=4)}  residual {np.degrees(res.residual_rms):.3g} deg"
        f"  method {res.method}" + (f"  ({len(res.candidates)} candidates)" if res.ambiguous else "")
    )


@reproduce.command("aoa")
@click.option("--runs", type=int, default=20, show_default=True, help="Noise runs per grid point.")
@click.option("--step", type=float, default=0.2, show_default=True, help="Grid step on the z = -3 plane (m).")
@click.option("--sigma-deg", type=float, default=1.0, show_default=True, help="AOA noise std (deg).")
@backend_option
@scheduler_option
@seed_option
@click.option("--out", "out", type=click.Path(file_okay=False), default="aoa_reproduction", show_default=True)
@handle_errors
def reproduce_aoa(
    runs: int, step: float, sigma_deg: float, backend: str, scheduler: str | None, seed: int, out: str
) -> None:
    """Paper 001 Section 5: Table 1 and the error surfaces of Fig. 3-6, plus ML (3 and 4 beacons)."""
    import numpy as np

    from ..errors import InputError
    from ..experiments.aoa import (
        METHODS,
        PAPER_TABLE1,
        aoa_trial,
        grid_means,
        paper_grid,
        summarize,
    )
    from ..experiments.runner import run_sweep, write_rows
    from ..io import write_json
    from ..plotting import new_figure, plot_heatmap, save_figure

    if runs < 1 or not (0 < step <= 5):
        raise InputError("--runs must be >= 1 and --step in (0, 5]")
    grid = [{**p, "sigma_deg": sigma_deg} for p in paper_grid(step)]
    rows = run_sweep(aoa_trial, grid, runs=runs, seed=seed, backend=backend, scheduler=scheduler, desc="aoa")
    outdir = Path(out)
    outdir.mkdir(parents=True, exist_ok=True)
    table = summarize(rows)
    both = [all(bool(r[f"{m}_ok"]) for m in METHODS) for r in rows]
    common = summarize([r for r, ok in zip(rows, both, strict=True) if ok])
    write_rows(rows, outdir / "aoa_trials.csv")
    labels = {"sol1": "Solution 1", "sol2": "Solution 2", "ml": "ML (3 beacons)", "ml4": "ML (4 beacons)"}
    fig, axes = new_figure(1, len(METHODS), size=(4.2 * len(METHODS), 3.6))
    for ax, m in zip(axes, METHODS, strict=True):
        x, y, z = grid_means(rows, f"{m}_loc")
        plot_heatmap(ax, x, y, z, label="mean location error [m]")
        ax.set_title(f"{labels[m]}: location (Fig. 3/4)")
    save_figure(fig, outdir / "location_error.png")
    for m in METHODS:
        fig, axes = new_figure(1, 3, size=(12.6, 3.6))
        for ax, axis in zip(axes, "xyz", strict=True):
            x, y, z = grid_means(rows, f"{m}_{axis}")
            plot_heatmap(ax, x, y, z, label="mean error [deg]", cmap="magma")
            ax.set_title(f"{labels[m]}: {axis}-axis orientation")
        save_figure(fig, outdir / f"orientation_{m}.png")
    report = {
        "paper": "001",
        "setup": {"runs": runs, "step_m": step, "sigma_deg": sigma_deg, "seed": seed,
                  "grid_points": len(grid), "trials": len(rows)},
        "table1": table,
        "table1_common_trials": common,
        "common_trial_fraction": float(np.mean(both)),
        "paper_table1": PAPER_TABLE1,
        "clipped_bearings_fraction": float(np.mean([r["clipped"] for r in rows]) / 4.0),
    }
    write_json(outdir / "aoa_reproduction.json", report)
    click.echo(f"{'':14s}{'paper sol1':>11s}{'paper sol2':>11s}" + "".join(f"{m:>9s}" for m in METHODS))
    for key in ("location_m", "x_deg", "y_deg", "z_deg"):
        click.echo(
            f"{key:14s}{PAPER_TABLE1['sol1'][key]:11.2f}{PAPER_TABLE1['sol2'][key]:11.2f}"
            + "".join(f"{table[m][key]:9.2f}" for m in METHODS)
        )
    click.echo("solved        " + " " * 22 + "".join(f"{table[m]['solved_fraction']:9.2f}" for m in METHODS))
    click.echo(f"wrote {outdir}/aoa_reproduction.json and figures")
