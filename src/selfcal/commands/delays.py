"""``selfcal reproduce delays`` (paper 004: onset times and internal delays)."""

from __future__ import annotations

from pathlib import Path

import click

from ._base import backend_option, handle_errors, reproduce, scheduler_option, seed_option

#: Largest iteration cap of the thesis iteration (its protocol, ``--full``).
MAX_THESIS_ITER = 1_000_000


@reproduce.command("delays")
@click.option("--runs", type=int, default=20, show_default=True,
              help="Tests per point of Fig. 4.1-4.3 for the fast solver (thesis: 20).")
@click.option("--faithful-runs", type=int, default=2, show_default=True,
              help="Tests per point for the (slow) thesis iteration; --full uses --runs.")
@click.option("--max-iter", type=int, default=50_000, show_default=True,
              help="Iteration cap of the thesis iteration in Fig. 4.1-4.3 (thesis: 1e6, --full).")
@click.option("--cap-120", type=int, default=20_000, show_default=True,
              help="Iteration cap of the thesis iteration at 120 units (Fig. 4.4); the rest is extrapolated.")
@click.option("--noise-runs", type=int, default=10, show_default=True,
              help="Runs per noise level (10 and 50 us) of the NLS / CRLB experiment (0 skips it).")
@click.option("--full", is_flag=True,
              help="Thesis protocol: 20 faithful tests per point, 1e6 iterations, 25/15 uncapped timing runs (hours).")
@click.option("--quick", is_flag=True, help="Smoke-test sizes (seconds): 12 and 16 units, 2 runs.")
@backend_option
@scheduler_option
@seed_option
@click.option("--out", "out", type=click.Path(file_okay=False, path_type=Path), default=Path("delays-output"),
              show_default=True, help="Folder for delays.json, the tidy rows and the PNG figures.")
@handle_errors
def reproduce_delays(runs: int, faithful_runs: int, max_iter: int, cap_120: int, noise_runs: int, full: bool,
                     quick: bool, backend: str, scheduler: str | None, seed: int, out: Path) -> None:
    """Reproduce 004 Fig. 4.1-4.5 (+ noise vs CRLB): figures and delays.json in --out."""
    from .._checks import check_int, check_runs
    from ..errors import InputError
    from ..experiments.delays import UNITS, reproduce_all

    for name, value, low in (("runs", runs, 1), ("faithful-runs", faithful_runs, 0), ("noise-runs", noise_runs, 0)):
        check_runs(value, f"--{name}", minimum=low)
    for name, value in (("max-iter", max_iter), ("cap-120", cap_120)):
        check_int(value, f"--{name}", minimum=1)
    # the thesis iteration's own cap is 1e6 (--full); a larger cap changes no figure (the runs that
    # reach it are extrapolated) and would run for days: refused rather than started
    for name, value in (("max-iter", max_iter), ("cap-120", cap_120)):
        if value > MAX_THESIS_ITER:
            raise InputError(f"--{name} {value} is beyond the thesis protocol's cap of {MAX_THESIS_ITER:,} "
                             "iterations (--full uses it)")
    kwargs: dict[str, object] = {}
    if quick:
        kwargs = {"units": (12, 16), "timing_runs": (2, 1), "faithful_timing_runs": (1, 1),
                  "lambda_max_iter": 3000}
        runs, faithful_runs, max_iter, cap_120, noise_runs = 2, min(faithful_runs, 1), 3000, 300, min(noise_runs, 2)
    summary = reproduce_all(out, runs=runs, faithful_runs=faithful_runs, max_iter=max_iter, cap_120=cap_120,
                            noise_runs=noise_runs, full=full, backend=backend, scheduler=scheduler, seed=seed,
                            units=kwargs.pop("units", UNITS), **kwargs)  # type: ignore[arg-type]
    for row in summary["timing"]:
        click.echo(f"{row['units']:4d} units {row['method']:9s}: median {row['seconds']['median']:.3g} s "
                   f"(to convergence, extrapolated: {row['extrapolated_seconds']['median']:.3g} s)")
