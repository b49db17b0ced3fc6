"""``selfcal calibrate tdoa-farfield`` and ``selfcal reproduce farfield`` (paper 000)."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

import click

from ._base import (
    backend_option,
    calibrate,
    handle_errors,
    reproduce,
    scheduler_option,
    seed_option,
)
from ._common import csv_option, unit_options
from ._options import NOISE_STD, SEED, SPEED

if TYPE_CHECKING:
    from ..tdoa import FarfieldResult


@calibrate.command("tdoa-farfield")
@click.argument("matrix", nargs=-1, required=True, type=click.Path(path_type=Path))
@click.option("--out", "out", type=click.Path(dir_okay=False, path_type=Path), required=True,
              help="Result JSON (positions, directions, offsets, residual_rms, degeneracy, ...).")
@click.option("--speed", type=SPEED, default=None, metavar="C",
              help="Propagation speed in m/s: the matrix holds seconds (TDOA); positions are reported in "
                   "metres, offsets and the residual in seconds. A Pyramic JSON holds seconds and its own "
                   "sound_speed_mps, which --speed overrides.")
@click.option("--dim", type=click.Choice(["1", "2", "3", "auto"]), default="auto", show_default=True,
              help="auto: decided by nested rank tests of the data against the noise (false-alarm rate 0.001 "
                   "per test; rank 2 with a consistent planar quadric -> 2, rank 1 -> 1, else 3); 3: spatial "
                   "array; 2: planar array with sources in its plane (in-plane geometry); 1: linear array "
                   "(positions along the line, up to scale). The JSON's 'dim', 'dim_rule', 'case' and "
                   "'determined' say what was chosen and what the data fix.")
@click.option("--directions", "directions", default=None, metavar="FILE|sources",
              help="Known unit directions (k x 3 or k x 2 CSV / .npy, one row per column of MATRIX), or 'sources' "
                   "for a Pyramic JSON's own (n_j = -source_j): semi-blind least squares for the positions, the "
                   "way to calibrate a degenerate (cone) set if the directions are right.")
@click.option("--method", type=click.Choice(["auto", "lm", "alternating", "init", "minimal"]), default="auto",
              show_default=True, help="Refinement: LM on the spheres (Alg. 3), alternating (Alg. 2), or none.")
@click.option("--loss", type=click.Choice(["linear", "huber", "soft_l1", "cauchy"]), default="linear",
              show_default=True, help="Robust loss for outliers (rejected entries are listed in the JSON).")
@click.option("--noise-std", type=NOISE_STD, default=None,
              help="Known noise standard deviation (matrix units) for the degeneracy thresholds.")
@click.option("--ransac", is_flag=True, help="Screen outliers with RANSAC over the minimal solver first.")
@click.option("--seed", type=SEED, default=0, show_default=True, help="Random seed (RANSAC).")
@click.option("--allow-degenerate", is_flag=True,
              help="On a degenerate geometry write the partial reconstruction instead of failing.")
@click.option("--plot", "plot", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Figure of the positions and directions (format from the suffix: .png, .pdf, .svg).")
@csv_option
@unit_options
@handle_errors
def farfield_command(matrix: tuple[Path, ...], out: Path, speed: float | None, dim: str, directions: str | None,
                     method: str, loss: str,
                     noise_std: float | None, ransac: bool, seed: int, allow_degenerate: bool,
                     plot: Path | None, csv_out: Path | None = None, unit: str | None = None,
                     sample_rate: float | None = None) -> None:
    """Self-calibrate from an m x k far-field TDOA MATRIX (CSV, .npy or Pyramic JSON; NaN = missing).

    Rows are receiver positions (microphones, antenna positions), columns far transmitters;
    entry = relative distance z_i . n_j + C_j (metres, or seconds with --speed). A .json
    file in the Pyramic calibration layout (keys delays [m-1][k] in seconds against
    microphone mic_ref, or [m-1][k][speakers] for several speakers, sources, microphones,
    sound_speed_mps) is read directly; its hand-measured microphones are not used by the
    estimate, only compared with it. Several Pyramic files (or a folder of them) are
    calibrated jointly, all speakers' columns side by side: one speaker's directions lie on
    a cone (one elevation), speakers at different elevations break it. A degenerate
    geometry (planar-motion, coplanar-directions, cone, collinear-motion,
    parallel-directions) exits with status 2 naming it, unless --allow-degenerate.
    """
    import numpy as np

    from .._checks import FARFIELD_TIMES_AS_METRES_MAX, plausible_matrix_scale
    from ..errors import DegenerateGeometryError, InputError
    from ..io import read_table, staged_outputs, write_json
    from ..tdoa import solve_farfield
    from ._common import enrich_payload, to_metres, transposed_hint, write_nodes_csv

    reference = None
    known = None
    row_names = col_names = None
    pyramic = None
    pyr = [p.is_dir() or p.suffix.lower() == ".json" for p in matrix]
    if any(pyr) and not all(pyr) or (len(matrix) > 1 and not all(pyr)):
        raise InputError("several matrices (or a folder) are read only as Pyramic JSON files; give one CSV / "
                         ".npy matrix, or Pyramic .json files")
    if all(pyr):
        from ..datasets.pyramic import load_pyramic

        pyramic = load_pyramic(list(matrix), speed=speed)
        D, seconds = pyramic.D, True
        scale: Any = pyramic.column_speed if pyramic.column_speed is not None else np.full(D.shape[1],
                                                                                           pyramic.speed)
        reference = pyramic.positions if pyramic.has_microphones else None
        if directions == "sources":
            if not pyramic.has_sources:
                raise InputError("--directions sources: the Pyramic file(s) give no 'sources' (directions) for "
                                 "every column")
            known = pyramic.directions
        if pyramic.has_sources:
            elev = "elevation(s) " + ", ".join(f"{e:.1f}" for e in pyramic.elevations().values()) + \
                " deg (file's source directions)"
        else:
            elev = "unknown elevations (no 'sources' in the file)"
        click.echo(f"selfcal calibrate tdoa-farfield: Pyramic data, {len(pyramic.speakers)} speaker(s) at "
                   f"{elev}, {D.shape[1]} columns in all")
        if pyramic.skipped:
            click.echo(f"  {pyramic.skipped} (source, speaker) column(s) without any delay skipped")
        if not pyramic.has_microphones:
            click.echo("  no 'microphones' in the file: no comparison with hand-measured positions")
    else:
        matrix_path = matrix[0]
        table = read_table(matrix_path, name=str(matrix_path))
        row_names, col_names = table.row_names, table.col_names
        M, speed, _ = to_metres(table.values, unit, speed, sample_rate, name=str(matrix_path))
        plausible_matrix_scale(M, speed=speed, explicit_unit=unit is not None, name=str(matrix_path),
                               min_span=FARFIELD_TIMES_AS_METRES_MAX)
        seconds = speed is not None
        scale = speed if speed is not None else 1.0
        D = M * scale
    if directions is not None and known is None:
        if directions == "sources":
            raise InputError("--directions sources needs a Pyramic JSON matrix (with 'sources'); give a file")
        known = read_table(Path(directions), name=str(directions)).values
    D_all = D
    keep_r, keep_c = _determinable(D)
    if keep_r.sum() < 4 or keep_c.sum() < 3:  # too little left: the solver's own refusal names the problem
        keep_r, keep_c = np.ones(D.shape[0], dtype=bool), np.ones(D.shape[1], dtype=bool)
    if not (keep_r.all() and keep_c.all()):
        gone_r, gone_c = np.flatnonzero(~keep_r), np.flatnonzero(~keep_c)
        what = "microphone" if pyramic is not None else "row"
        if gone_r.size:
            click.echo(f"  left out {what}(s) {', '.join(str(i) for i in gone_r[:20])}"
                       f"{' ...' if gone_r.size > 20 else ''}: fewer than 3 observed entries, position "
                       "undetermined (null in the JSON)")
        if gone_c.size:
            click.echo(f"  left out {gone_c.size} column(s) with fewer than 2 observed entries in the rows kept")
        D = D[np.ix_(keep_r, keep_c)]
        if known is not None:
            known = np.asarray(known, dtype=float)[keep_c] if np.ndim(known) == 2 and len(known) == keep_c.size \
                else known
        if reference is not None:
            reference = reference[keep_r]
    from ..progress import stage

    try:
        with stage(f"fit {D.shape[0]} x {D.shape[1]}"):
            res = solve_farfield(D, method=method, loss=loss, directions=known,
                                 noise_std=None if noise_std is None else noise_std * float(np.mean(scale)),
                                 allow_degenerate=allow_degenerate, ransac=ransac, rng=seed,
                                 dim="auto" if dim == "auto" else int(dim))
    except DegenerateGeometryError as exc:
        transposed_hint(exc, D_all.shape, min_rows=4, min_cols=6)
        if pyramic is not None and exc.kind == "cone":
            _pyramic_cone_hint(exc, pyramic)
        raise
    out_dict = res.to_dict()
    tunit = "s" if seconds else "m"
    if seconds:
        speed_col = np.broadcast_to(np.asarray(scale, dtype=float), (D_all.shape[1],))[keep_c]
        out_dict["offsets"] = (np.asarray(res.offsets) / speed_col).tolist()
        out_dict["residual_rms"] = float(res.residual_rms / float(np.mean(speed_col)))
        out_dict["speed"] = float(np.mean(speed_col))
    if pyramic is not None:
        out_dict["speaker"] = [int(s) for s in pyramic.speaker] if pyramic.speaker is not None else None
        out_dict["speaker_elevation_deg"] = {str(s): (e if np.isfinite(e) else None)
                                             for s, e in pyramic.elevations().items()}
    if not (keep_r.all() and keep_c.all()):
        _expand(out_dict, keep_r, keep_c)
    ref_rmse = None
    if reference is not None and res.positions.shape[1] == 3:
        from ..metrics import aligned_rmse

        ref_rmse = aligned_rmse(res.positions, reference).rmse_receivers
        out_dict["reference_rmse"] = ref_rmse
    payload = enrich_payload(
        out_dict, names={"position_names": row_names, "transmitter_names": col_names},
        units={"positions": "m", "directions": "unit vectors", "offsets": tunit, "residual_rms": tunit,
               "position_cov": "m^2", "direction_covariance": "unit vector^2 (rad^2 for small errors)",
               "direction_std_deg": "deg", "azimuth_std_deg": "deg", "elevation_std_deg": "deg"})
    with staged_outputs():  # the figure, the JSON and the CSV together, or none
        if plot is not None:
            from ..plotting.farfield import plot_farfield

            plot_farfield(res, plot, speed=out_dict.get("speed"), names=row_names)
        write_json(out, payload)
        if csv_out is not None:
            write_nodes_csv(csv_out, payload, [("position", "positions", "position_names")])
    m, k = D_all.shape
    click.echo(f"selfcal calibrate tdoa-farfield: {m} positions x {k} transmitters, {res.dim}-D ({res.case}), "
               f"method {res.method}, loss {res.loss}")
    click.echo(f"  determined: {res.determined}")
    click.echo(f"  dimension: {res.dim_rule}")
    click.echo(f"  gross errors: {res.screen_rule}")
    click.echo(f"  residual RMS {out_dict['residual_rms']:.4g} {tunit}, converged={res.converged}, "
               f"iterations={res.iterations}, rejected entries {int(res.rejected.sum())}")
    if ref_rmse is not None:
        click.echo(f"  RMS distance to the file's hand-measured microphones after rigid alignment "
                   f"{1e3 * ref_rmse:.3g} mm (not used by the estimate)")
    if res.untestable:
        click.echo(f"selfcal: warning: {res.untestable} entries cannot be checked for gross errors: too few spare "
                   "measurements (add receivers or transmitters)", err=True)
    if res.degeneracy is not None:
        click.echo(f"selfcal: warning: degenerate geometry [{res.degeneracy}]: wrote a partial reconstruction",
                   err=True)
    failure = None
    if res.degeneracy is None and not res.converged:
        failure = f"the refinement did not converge in {res.iterations} iterations"
    elif noise_std is not None and res.degeneracy is None:
        failure = _residual_failure(res, D, noise_std * float(np.mean(scale)))
    if failure is not None:
        click.echo(f"FAIL: calibration not trustworthy ({failure})")
        raise SystemExit(1)


def _determinable(D: Any) -> tuple[Any, Any]:
    """Rows with >= 3 and columns with >= 2 observed entries among each other (iterated to a fixed
    point): a receiver seen by fewer than 3 transmitters has an undetermined position (a dead
    microphone, a row of NaN), a column seen by one receiver carries nothing. The rest is solvable."""
    import numpy as np

    f = np.isfinite(D)
    r = np.ones(D.shape[0], dtype=bool)
    c = np.ones(D.shape[1], dtype=bool)
    while True:
        r2 = r & ((f & c).sum(axis=1) >= 3)
        c2 = c & ((f & r2[:, None]).sum(axis=0) >= 2)
        if r2.sum() == r.sum() and c2.sum() == c.sum():
            return r, c
        r, c = r2, c2
        if not r.any() or not c.any():
            return r, c


def _expand(d: dict[str, Any], keep_r: Any, keep_c: Any) -> None:
    """Put the result of the kept rows / columns back in the input's numbering (null for those left out)."""
    import numpy as np

    ri, ci = np.flatnonzero(keep_r), np.flatnonzero(keep_c)
    for keys, idx, n in ((("positions", "position_cov", "position_std", "position_ellipse95"), ri, keep_r.size),
                         (("directions", "offsets", "direction_covariance", "direction_std_deg", "azimuth_std_deg",
                           "elevation_std_deg"), ci, keep_c.size)):
        for key in keys:
            v = d.get(key)
            if not isinstance(v, list) or len(v) != idx.size:
                continue
            shape = np.shape(v[0]) if v else ()
            full: list[Any] = [np.full(shape, None, dtype=object).tolist() if shape else None] * n
            for i, x in zip(idx, v, strict=True):
                full[int(i)] = x
            d[key] = full
    if isinstance(d.get("rejected"), list):
        d["rejected"] = [[int(ri[i]), int(ci[j])] for i, j in d["rejected"]]


def _pyramic_cone_hint(exc: Any, data: Any) -> None:
    """Re-raise a ``[cone]`` refusal on Pyramic data saying which speakers were given and what breaks it."""
    from ..errors import DegenerateGeometryError

    elev = data.elevations()
    msg = exc.args[0] if exc.args else str(exc)
    listed = ", ".join(f"speaker {s} at {e:.1f} deg" for s, e in elev.items())
    raise DegenerateGeometryError(
        f"{msg} Pyramic data given: {listed}. One speaker's directions (one elevation) always lie on a cone; "
        "speakers at different absolute elevations break it: give their files together "
        "(calibrate tdoa-farfield a.json b.json ..., or their folder), or use --directions sources (semi-blind, "
        "as good as the file's directions)", kind=exc.kind, partial=getattr(exc, "partial", None)) from None


def _residual_failure(res: FarfieldResult, D: object, sigma: float) -> str | None:
    """Chi-square test of the residuals against a given noise std: a message when it fails.

    ``sum r^2 / sigma^2 ~ chi2(n_obs - n_par)`` at the least-squares solution, n_par =
    d(m-1) + (d-1)k + k - d(d-1)/2 (positions, directions, offsets, minus the rotations);
    fails above the 0.999 quantile.
    """
    import numpy as np
    from scipy.stats import chi2

    Dm = np.asarray(D, dtype=float)
    used = np.isfinite(Dm) & ~res.rejected
    # the statistic is chi-square at the least-squares (ML) solution with free offsets; the
    # paper's reference offsets (C_j = D_1j) are not that solution, so refine to it first
    Z, N = res.positions, res.directions
    fit = np.where(used, Dm - Z @ N.T, np.nan)
    C = np.nanmean(fit, axis=0)
    if res.case in ("spatial", "planar") and res.loss == "linear":
        from ..tdoa import refine_lm

        out = refine_lm(Dm, Z - Z[0], N, C + Z[0] @ N.T, mask=used, free_offsets=True, covariance=False)
        Z, N, C = out.positions, out.directions, out.offsets
    r = np.where(used, Dm - Z @ N.T - C[None, :], 0.0)
    m, k = Dm.shape
    d = res.dim
    n_par = d * (m - 1) + (d - 1) * k + k - d * (d - 1) // 2 if res.case != "known-directions" else d * (m - 1) + k
    dof = int(used.sum()) - n_par
    if dof <= 0 or sigma <= 0:
        return None
    with np.errstate(over="ignore"):
        stat = float(np.sum((r / sigma) ** 2))  # sigma**2 underflows for sigma < 1e-154
    q = float(chi2.ppf(0.999, dof))
    if stat > q:
        return (f"residual RMS {float(np.sqrt(np.sum(r**2) / used.sum())):.3g} m against the given noise "
                f"{sigma:.3g} m: chi-square {stat:.4g} > its 0.999 quantile {q:.4g} with {dof} dof")
    return None


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
    from .._checks import check_runs
    from ..experiments.farfield import reproduce_all

    if runs is not None:
        check_runs(runs)
    summary = reproduce_all(out, runs=runs, full=full, backend=backend, scheduler=scheduler, seed=seed)
    for line in summary["report"]:
        click.echo(line)
