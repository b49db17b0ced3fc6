"""``selfcal locate aoa`` and ``selfcal reproduce aoa`` (paper 001)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import click

from ..errors import SelfcalError
from ._base import backend_option, handle_errors, locate, reproduce, scheduler_option, seed_option
from ._options import GRID_STEP_M, SIGMA_DEG


@locate.command("aoa")
@click.argument("beacons", type=click.Path(dir_okay=False))
@click.argument("bearings", type=click.Path(dir_okay=False))
@click.option("--out", "out", required=True, type=click.Path(dir_okay=False), help="RESULT.json")
@click.option(
    "--method", type=click.Choice(["auto", "sol1", "sol2", "p3p", "ml", "linear"]), default="auto",
    show_default=True, help="sol1/sol2: paper 001 solutions; p3p: all closed-form candidates; ml: refined.",
)
@click.option(
    "--angles", type=click.Choice(["vectors", "azel", "axes", "deg", "rad"]), default="vectors", show_default=True,
    help="What BEARINGS holds. vectors: N x d unit vectors in the receiver frame. azel: N x 2 (azimuth, "
         "elevation) per beacon in the receiver frame -- azimuth in the xy plane from +x towards +y, elevation "
         "from the xy plane towards +z (what DoA estimators such as pyroomacoustics.doa give); N x 1 azimuth "
         "in 2-D. axes: N x 2 (alpha, beta), the angles to the receiver's x and y axes (paper 001 eq. 2); "
         "they do not say on which side of the xy plane a beacon is, so every method is followed by the "
         "ML refinement over both sides. deg / rad: old spelling of 'axes' in that unit.",
)
@click.option("--unit", "unit", type=click.Choice(["deg", "rad"]), default=None,
              help="Unit of the angles with --angles azel / axes (default deg); the option every command "
                   "uses for the unit of its input values.")
@click.option("--units", "units", type=click.Choice(["deg", "rad"]), default=None,
              help="Deprecated alias of --unit (kept for old scripts; says so on stderr).")
@click.option("--sigma-deg", type=SIGMA_DEG, default=None,
              help="Angular noise std (degrees) for the ML covariance and the residual test (default: the "
                   "test assumes at most 5 degrees).")
@click.option(
    "--hint", default=None, metavar="X,Y[,Z]",
    help="Rough receiver position: picks among equally good candidates (three beacons in 3-D).",
)
@click.option("--plot", "plot", type=click.Path(dir_okay=False), default=None,
              help="PNG of the beacons, the receiver with its x/y/z axes and the measured bearing rays.")
@handle_errors
def locate_aoa(
    beacons: str, bearings: str, out: str, method: str, angles: str, unit: str | None, units: str | None,
    sigma_deg: float | None, hint: str | None, plot: str | None,
) -> None:
    """Receiver position and orientation from bearings to known BEACONS (N x d, d = 2 or 3).

    BEARINGS: N x d unit vectors in the receiver frame (a NaN row = beacon not received), or
    angles with --angles azel / axes (--unit deg or rad; --units is a deprecated alias).
    Writes position (and position_std, m), rotation (columns = receiver axes in the global
    frame; also quaternion [w, x, y, z] and yaw / pitch / roll in degrees, intrinsic z-y'-x'',
    with their stds), residual_rms (rad), method, covariance (its parameter order and units in
    covariance_parameters / covariance_units), candidates (when ambiguous) and success.
    Exit 1 with a FAIL line when the bearings do not fit the
    pose at the noise level (chi-square test; not a pose).
    """
    import numpy as np

    from .._checks import as_points, plausible_angle_unit, plausible_angles
    from ..aoa import solve_aoa
    from ..errors import InputError, Status
    from ..io import read_table, staged_outputs, write_json
    from ._common import enrich_payload

    if units is not None:
        if unit is not None and unit != units:
            raise InputError(f"--unit {unit} and --units {units} disagree; give --unit only (--units is deprecated)")
        click.echo("selfcal: warning: --units is deprecated, use --unit (the same option as every other command)",
                   err=True)
    units_given = unit is not None or units is not None  # degrees said, not assumed
    units = unit or units or "deg"
    btab = read_table(beacons, "beacons")
    b = btab.values
    u = read_table(bearings, "bearings").values
    d = b.shape[1]
    if d not in (2, 3):
        as_points(b, "beacons")  # names a list given one coordinate per row (transposed)
        raise InputError(f"beacons: expected N x 2 or N x 3 coordinates, got {b.shape}")
    if u.shape[0] != b.shape[0]:
        raise InputError(f"bearings: {u.shape[0]} rows for {b.shape[0]} beacons (one row per beacon)")
    sign_unknown = False
    units_given = units_given or angles in ("deg", "rad")
    if angles in ("deg", "rad"):
        angles, units = "axes", angles
    if angles == "vectors":
        if u.shape[1] != d:
            raise InputError(f"bearings: {u.shape[1]} columns for {d}-D beacons: unit vectors need {d} "
                             f"(angles? use --angles azel or axes with --unit deg / rad)")
        with np.errstate(over="ignore"):
            norms = np.linalg.norm(u, axis=1)  # inf for rows of 1e300s: not unit vectors either
        fin = np.isfinite(u).all(axis=1)
        dev = np.where(np.isfinite(norms), np.abs(norms - 1.0), np.inf)
        if fin.any() and np.max(dev[fin]) > 1e-2:
            i = int(np.flatnonzero(fin)[np.argmax(dev[fin])])
            raise InputError(f"bearings: row {i + 1} has length {norms[i]:.4g}, not a unit vector (1 within 1 %): "
                             "angles in degrees or radians? use --angles azel (or axes) with --unit deg / rad")
    else:
        plausible_angles(u, units)
        u_raw = u
        u, sign_unknown = _angles_to_bearings(u_raw, b, angles, units)
    if method == "linear" and d == 3:
        raise InputError("--method linear is the 2-D closed form; use p3p/sol1/sol2/ml in 3-D")
    if method in ("sol1", "sol2", "p3p") and d == 2:
        raise InputError(f"--method {method} is 3-D; in 2-D use linear, ml or auto")
    if sigma_deg is not None and not (np.isfinite(sigma_deg) and 0 < sigma_deg < 180):
        raise InputError(f"--sigma-deg must be a positive number of degrees below 180 (an angle between two "
                         f"directions is at most 180), got {sigma_deg}")
    sigma = None if sigma_deg is None else float(np.radians(sigma_deg))
    position_hint = None
    if hint is not None:
        try:
            from ._options import _NUMBER

            parts = hint.split(",")
            if not all(_NUMBER.match(v) for v in parts):  # strict decimals: no 1_0, nan, inf
                raise ValueError(hint)
            position_hint = [float(v) for v in parts]
        except ValueError:
            raise InputError(f"--hint: expected comma-separated decimal numbers, got {hint!r}") from None
        from .._checks import check_magnitude

        check_magnitude(np.asarray(position_hint), "--hint")
    def solve(u: Any, sign_unknown: bool) -> Any:
        keep = ~np.isnan(u).any(axis=1) if sign_unknown else np.ones(len(u), bool)
        return solve_aoa(b[keep], u[keep], method=method, sigma=sigma, position_hint=position_hint,
                         **({"sign_z_unknown": True} if sign_unknown else {}))

    try:
        res, deg_error = solve(u, sign_unknown), None
    except SelfcalError as exc:  # e.g. radians read as degrees: no pose (or a degenerate one)
        res, deg_error = None, exc
    if angles != "vectors" and units == "deg" and not units_given and np.nanmax(np.abs(u_raw)) <= 2 * np.pi:
        try:  # the same angles read as radians: where do they put the receiver?
            res_rad = solve(*_angles_to_bearings(u_raw, b, angles, "rad"))
        except SelfcalError:
            res_rad = None
        plausible_angle_unit(u_raw, b, None if res is None else res.position,
                             None if res_rad is None else res_rad.position,
                             rad_fits=res_rad is not None and res_rad.status not in (
                                 Status.NOT_CONVERGED, Status.FAILED_TEST),
                             degrees_error=None if deg_error is None else str(deg_error))
    if deg_error is not None:
        raise deg_error
    with staged_outputs():  # the figure and the result together, or neither
        if plot is not None:
            from ..plotting.aoa import plot_pose

            plot_pose(b, u, res, plot, names=btab.row_names)
        write_json(out, enrich_payload(res.to_dict(), names={"beacon_names": btab.row_names},
                                       units={"position": "m",
                                              "rotation": "columns = receiver axes in the global frame",
                                              "residual_rms": "rad", "covariance": "m^2 and rad^2",
                                              "position_std": "m", "quaternion": "unitless, [w, x, y, z]",
                                              "yaw_pitch_roll_deg": "deg", "yaw_pitch_roll_std_deg": "deg",
                                              "rotation_std_deg": "deg", "heading_deg": "deg",
                                              "heading_std_deg": "deg"}))
    click.echo(
        f"position {np.array2string(res.position, precision=4)}  residual {np.degrees(res.residual_rms):.3g} deg"
        f"  method {res.method}" + (f"  ({len(res.candidates)} candidates)" if res.ambiguous else "")
    )
    click.echo(f"  {res.message}")
    # an ambiguous pose (several exact candidates, all in the JSON) is an answer, not a failure
    if res.status in (Status.NOT_CONVERGED, Status.FAILED_TEST):
        click.echo(f"FAIL: pose not trustworthy ({res.message})")
        raise SystemExit(1)


def _angles_to_bearings(u: Any, b: Any, angles: str, units: str) -> tuple[Any, bool]:
    """Bearings (N x d unit vectors, NaN rows missing) from --angles azel / axes in ``units``;
    and whether the side of the xy plane is unknown (axes)."""
    import numpy as np

    from ..aoa import angles_to_bearings, azel_to_bearings
    from ..errors import InputError

    d = b.shape[1]
    sign_unknown = False
    a = np.radians(u) if units == "deg" else u
    miss = np.isnan(a).any(axis=1)
    # the ranges of the angles themselves: an elevation beyond +-90 deg or an angle to an axis
    # outside [0, 180] deg is no direction (a sign or unit mistake), never a measurement
    if angles == "azel" and d == 3 and a.shape[1] == 2 and (np.abs(a[~miss, 1]) > np.pi / 2 + 1e-9).any():
        raise InputError(f"bearings: elevations must lie within +-90 deg, got up to "
                         f"{np.degrees(np.nanmax(np.abs(a[:, 1]))):.4g} deg (column 2 is the elevation)")
    if angles == "axes" and d == 3 and a.shape[1] == 2 and ((a[~miss] < -1e-9) | (a[~miss] > np.pi + 1e-9)).any():
        raise InputError("bearings: --angles axes holds the angles to the receiver's x and y axes, each "
                         "within [0, 180] deg")
    if angles == "azel":
        a0 = np.where(np.isnan(a), 0.0, a)
        if d == 3 and a.shape[1] == 2:
            u = azel_to_bearings(a0[:, 0], a0[:, 1])
        elif d == 2 and a.shape[1] == 1:
            u = azel_to_bearings(a0[:, 0])
        else:
            raise InputError(f"--angles azel: expected N x 2 (azimuth, elevation) for 3-D beacons or N x 1 "
                             f"(azimuth) for 2-D, got {a.shape} with beacons {b.shape}")
    else:
        if d == 3 and a.shape[1] == 2:
            u = angles_to_bearings(np.where(miss, 0.0, a[:, 0]), np.where(miss, 0.0, a[:, 1])).vectors
            sign_unknown = True
        elif d == 2 and a.shape[1] == 1:
            u = np.column_stack([np.cos(a[:, 0]), np.sin(a[:, 0])])
        else:
            raise InputError(f"--angles axes: expected N x 2 (alpha, beta) for 3-D beacons or N x 1 for 2-D, "
                             f"got {a.shape} with beacons {b.shape}")
    u[miss] = np.nan
    return u, sign_unknown


@reproduce.command("aoa")
@click.option("--runs", type=int, default=20, show_default=True, help="Noise runs per grid point.")
@click.option("--step", type=GRID_STEP_M, default=0.2, show_default=True, help="Grid step on the z = -3 plane (m).")
@click.option("--sigma-deg", type=SIGMA_DEG, default=1.0, show_default=True, help="AOA noise std (deg).")
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

    from .._checks import check_runs
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
    from ..plotting.aoa import plot_error_surfaces

    check_runs(runs)  # --step and --sigma-deg: their Quantity ranges (GRID_STEP_M, SIGMA_DEG)
    # the grid has (5 / step + 1)^2 points, each run at each point one trial held in memory
    # (TRIAL_BYTES): a step of 1e-4 m would be 2.5e9 points (was a hang; 1e-300 an internal error)
    from .._checks import TRIAL_BYTES, guard_size

    n_side = 5.0 / step + 1.0
    guard_size(float(runs) * n_side * n_side * TRIAL_BYTES,
               f"--step {step:g} m ({n_side * n_side:.3g} grid points) x --runs {runs}")
    grid = [{**p, "sigma_deg": sigma_deg} for p in paper_grid(step)]
    rows = run_sweep(aoa_trial, grid, runs=runs, seed=seed, backend=backend, scheduler=scheduler, desc="aoa")
    outdir = Path(out)
    outdir.mkdir(parents=True, exist_ok=True)
    table = summarize(rows)
    both = [all(bool(r[f"{m}_ok"]) for m in METHODS) for r in rows]
    common = summarize([r for r, ok in zip(rows, both, strict=True) if ok])
    write_rows(rows, outdir / "aoa_trials.csv")
    labels = {"sol1": "Solution 1", "sol2": "Solution 2", "ml": "ML (3 beacons)", "ml4": "ML (4 beacons)"}
    plot_error_surfaces([(f"{labels[m]}: location (Fig. 3/4)", *grid_means(rows, f"{m}_loc")) for m in METHODS],
                        outdir / "location_error.png", label="mean location error [m]")
    for m in METHODS:
        plot_error_surfaces([(f"{labels[m]}: {axis}-axis orientation", *grid_means(rows, f"{m}_{axis}"))
                             for axis in "xyz"], outdir / f"orientation_{m}.png", label="mean error [deg]", cmap="magma")
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
