"""``selfcal slac simulate|run|plaza`` and ``selfcal reproduce slac`` (paper 002)."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

import click

from ._base import backend_option, handle_errors, reproduce, scheduler_option, seed_option, slac
from ._common import all_or_nothing
from ._options import ANGLE_RAD, MINUTES, SLAC_SNR_DB, Quantity


@slac.command("simulate")
@click.option("--minutes", type=MINUTES, default=1.0, show_default=True, help="Length of the replica run.")
@click.option("--subcarriers", type=int, default=128, show_default=True,
              help="N (1024 in the paper; the log stores every snapshot, size ~ 0.34 MB x N x minutes).")
@click.option("--snr-db", type=SLAC_SNR_DB, default=30.0, show_default=True, help="Post-integration SNR at 10 m.")
@seed_option
@click.option("--out", "out", type=click.Path(dir_okay=False, path_type=Path), required=True, help="LOG.npz")
@handle_errors
def simulate_cmd(minutes: float, subcarriers: int, snr_db: float, seed: int, out: Path) -> None:
    """Simulate the 3-anchor / 4-rover replica and write an NPZ log (docs/slac_log_format.md)."""
    from ..errors import InputError
    from ..scenarios.rovers import make_rover_scenario
    from ..slac.run import SlacLog
    from ..slac.validate import check_simulation_request

    if subcarriers < 8:
        raise InputError("--subcarriers must be >= 8")
    check_simulation_request(minutes, subcarriers, snr_db)  # before anything is allocated
    sc = make_rover_scenario(minutes, n_subcarriers=subcarriers, snr_db=snr_db, rng=seed)
    SlacLog.from_scenario(sc, seed=seed).to_npz(out)
    click.echo(f"replica log {out}: {sc.n_steps} steps, {sc.rx.size} links, N = {subcarriers}")


@slac.command("run")
@click.argument("log_path", type=click.Path(path_type=Path))
@click.option("--mode", type=click.Choice(["slac", "localization"]), default="slac", show_default=True)
@click.option("--prior", type=click.Choice(["em", "chamber"]), default="chamber", show_default=True,
              help="Antenna-response prior of multi-port agents.")
@click.option("--out", "out", type=click.Path(dir_okay=False, path_type=Path), required=True, help="RESULT.json")
@click.option("--plot", "plot", type=click.Path(file_okay=False, path_type=Path), default=None,
              help="Folder for trajectory / ranging PNGs.")
@click.option("--init", type=click.Choice(["snapshot", "log"]), default="snapshot", show_default=True,
              help="Initial poses: snapshot-based estimate (paper 002 section IV) or the log's init_poses.")
@click.option("--smoother-lag", type=click.IntRange(min=0), default=0, show_default=True,
              help="0: the paper's filter; K > 0: fixed-lag smoother over the last K steps (consistent "
                   "error bars with antenna calibration, ~5x slower at K = 20; docs/slac_consistency.md).")
@handle_errors
@all_or_nothing
def run_cmd(log_path: Path, mode: str, prior: str, out: Path, plot: Path | None, init: str,
            smoother_lag: int) -> int:
    """Run the SLAC or localization-only filter (or fixed-lag smoother) over an NPZ log."""
    import numpy as np

    from ..io import write_json
    from ..slac.filter import SlacConfig
    from ..slac.run import SlacLog, solve_slac

    log = SlacLog.from_npz(log_path)
    res = solve_slac(log, mode=mode, prior=prior, progress=sys.stderr.isatty(), init=init,
                     config=SlacConfig(smoother_lag=smoother_lag))
    d = res.to_dict()
    m: dict[str, Any] = {}
    if log.states is not None:  # a simulated log: errors against its truth
        from .._result import jsonable
        from ..experiments.slac import score_slac

        m = jsonable(score_slac(log, res))
    d["metrics"] = m
    if m:
        for key in ("doa",):
            for agent in m.get(key, {}).values():
                for v in agent.values():
                    v.pop("errors_deg", None)
        # jsonable wrote NaN (no usable ranging) as None: back to NaN for the mean, null in the JSON
        m["ranging_rmse_uncorrected_mean"] = float(np.mean(np.asarray(m.pop("ranging_rmse_uncorrected"), float)))
        m["ranging_rmse_corrected_mean"] = float(np.mean(np.asarray(m.pop("ranging_rmse_corrected"), float)))
    if plot is not None:
        from ..plotting.slac import plot_trajectories

        plot_trajectories(res.poses, log.anchors, plot / f"trajectories_{mode}.png", names=log.names,
                          truth=log.states)
    write_json(out, d)
    if not res.success:  # exit 1 says it failed its own test; returning (not sys.exit) commits the files
        click.echo(f"FAIL: {res.method}: {res.message}")
        return 1
    return 0


@slac.command("plaza")
@click.argument("path", type=click.Path(path_type=Path))
@click.option("--out", "out", type=click.Path(dir_okay=False, path_type=Path), required=True, help="RESULT.json")
@click.option("--method", type=click.Choice(["filter", "smoother", "fixed-lag", "both"]), default="both",
              show_default=True,
              help="filter: causal robust EKF (online use); smoother: batch MAP over the whole log (offline, "
                   "more accurate); fixed-lag: each pose smoothed by the next --lag seconds of data (online with "
                   "that delay, for logs too long or streams too open-ended to smooth whole); both: filter and "
                   "smoother.")
@click.option("--lag", "lag_s", type=Quantity("s", gt=0, le=1e7, why="a look-ahead in seconds (1e7 s is 4 months)"),
              default=30.0,
              show_default=True, help="Seconds of look-ahead of --method fixed-lag.")
@click.option("--csv", "csv_path", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Trajectory CSV (time, x, y, heading, stds) of the smoother (or the one method run).")
@click.option("--tum", "tum_path", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Same trajectory in the TUM format (timestamp tx ty tz qx qy qz qw).")
@click.option("--plot", "plot", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="PNG: tracks, ground truth, beacons with the estimated scale / offset.")
@click.option("--init-heading-offset", type=ANGLE_RAD, default=None,
              help="Radians, only for a log without the init_heading_offset variable.")
@click.option("--heading-units", type=click.Choice(["auto", "rad", "deg"]), default="auto", show_default=True,
              help="Unit of the log's heading columns (GT(:, 4), DR(:, 3)); auto = decided from the motion.")
@handle_errors
def plaza_cmd(path: Path, out: Path, method: str, csv_path: Path | None, tum_path: Path | None,
              plot: Path | None, init_heading_offset: float | None, heading_units: str = "auto",
              lag_s: float = 30.0) -> None:
    """Range-only SLAC (per-beacon range scale + offset) on a CMU range log (e.g. Plaza1.mat).

    Ground truth is used for the first pose and for the scores only. Exit 1 with a FAIL line
    if the smoother stops at its iteration limit.
    """
    import sys

    from ..datasets.plaza import load_plaza
    from ..experiments.slac import plaza_summary, score_plaza
    from ..io import staged_outputs, write_json
    from ..plotting.slac import plot_plaza
    from ..slac.export import write_trajectory_csv, write_trajectory_tum

    data = load_plaza(path, init_heading_offset=init_heading_offset, heading_units=heading_units)
    methods = ("filter", "smoother") if method == "both" else (method,)
    from ..slac.ranging import RangeModelConfig

    s = plaza_summary(data, methods=methods, progress=True, config=RangeModelConfig(lag_s=float(lag_s)))
    results = s.pop("_results")
    main = results["smoother" if "smoother" in results else methods[0]]
    with staged_outputs():  # every artefact of the run together, or none
        if csv_path is not None:
            write_trajectory_csv(csv_path, main)
        if tum_path is not None:
            write_trajectory_tum(tum_path, main)
        if plot is not None:
            plot_plaza(data, results, plot, rmse={k: score_plaza(data, r)["position_rmse"] for k, r in results.items()})
        write_json(out, s)
    for m, d in s["methods"].items():
        click.echo(f"{m}: position RMSE {d['position_rmse']:.3f} m, heading RMSE {d['heading_rmse_deg']:.2f} deg, "
                   f"scale {', '.join(f'{v:.3f}' for v in d['scale'])}, {d['seconds']:.1f} s")
    if not main.success:
        click.echo(f"FAIL: {main.method}: {main.message}")  # stdout, like every FAIL line (-q keeps it)
        sys.exit(1)


#: Steps of the moving average in Fig. 4 of ``reproduce slac`` (``experiments.slac``, window=50).
FIG4_WINDOW_STEPS = 50


@reproduce.command("slac")
@click.option("--minutes", type=MINUTES, default=12.5, show_default=True)
@click.option("--subcarriers", type=int, default=1024, show_default=True)
@click.option("--runs", type=int, default=1, show_default=True)
@click.option("--out", "out", type=click.Path(file_okay=False, path_type=Path), default=Path("slac_out"), show_default=True)
@backend_option
@scheduler_option
@seed_option
@click.option("--init", type=click.Choice(["snapshot", "log"]), default="snapshot", show_default=True,
              help="Initial poses: snapshot-based estimate (paper 002 section IV) or the log's init_poses.")
@click.option("--smoother-lag", type=click.IntRange(min=0), default=0, show_default=True,
              help="0: the paper's filter; K > 0: fixed-lag smoother over the last K steps.")
@handle_errors
def reproduce_slac_cmd(minutes: float, subcarriers: int, runs: int, out: Path, backend: str,
                       scheduler: str | None, seed: int, init: str, smoother_lag: int) -> None:
    """Paper 002 replica: Table I, Fig. 3 (DoA CDF), Fig. 4 (ranging RMSE) -> PNG + JSON in --out."""
    import json

    from .._checks import check_runs
    from ..errors import InputError
    from ..experiments.slac import reproduce_slac
    from ..slac.validate import check_simulation_request

    if subcarriers < 8:  # --minutes: MINUTES (> 0); --runs: check_runs
        raise InputError("--subcarriers must be >= 8")
    from ..slac.validate import STEP_SECONDS

    # Fig. 4 plots a 50-step (5 s) moving average of the ranging RMSE (experiments.slac): a
    # shorter run has no point of it (was an internal error of the plot)
    if minutes * 60.0 / STEP_SECONDS < FIG4_WINDOW_STEPS:
        raise InputError(f"--minutes {minutes:g} is shorter than Fig. 4's {FIG4_WINDOW_STEPS}-step moving average "
                         f"({FIG4_WINDOW_STEPS * STEP_SECONDS:g} s = {FIG4_WINDOW_STEPS * STEP_SECONDS / 60:.4f} min)")
    check_runs(runs)
    check_simulation_request(minutes, subcarriers, 30.0)  # each run simulates such a log
    s = reproduce_slac(out, minutes=minutes, subcarriers=subcarriers, runs=runs, seed=seed, backend=backend,
                       scheduler=scheduler, init=init, smoother_lag=smoother_lag)
    click.echo(json.dumps({"table_I": s["table_I"], "fig3_doa": s["fig3_doa"], "fig4": s["fig4"]}, indent=1))
