"""``selfcal demo``: the conference system of paper 004 end to end (what ``make demo`` runs).

Simulate 20 units in a 12 x 12 x 3 m room (RT60 0.4 s, 30 dB SNR, 5 us clock jitter), detect the arrivals,
estimate onsets, internal delays and positions, print a summary table with the PASS/FAIL
line for 004's requirements (position error <= 10 cm, timing error <= 58 us) and write
``result.json``, ``map.png`` and ``timing.png``.
"""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path

import click

from ._base import handle_errors, main
from ._common import check_simulation_size, jitter_options, resolve_jitter
from ._options import RT60_S, SEED, SNR_DB


@main.command("demo")
@click.option("--out", "out", default="demo-output", show_default=True,
              type=click.Path(file_okay=False, path_type=Path), help="Output folder.")
@click.option("--seed", type=SEED, default=0, show_default=True, help="Random seed of the simulated room.")
@click.option("--units", type=int, default=20, show_default=True, help="Units (microphone + loudspeaker).")
@click.option("--room", "room_text", default="12x12x3", show_default=True, help="Room L x W x H, m.")
@click.option("--layout", type=click.Choice(["flat", "boundary", "tiered", "stem", "hall"]), default="flat",
              show_default=True,
              help="flat / boundary desks use their known heights (near-planar); tiered / stem are solved in 3-D.")
@click.option("--rt60", type=RT60_S, default=0.4, show_default=True, help="Reverberation time, s.")
@click.option("--snr", type=SNR_DB, default=30.0, show_default=True, help="Direct sound at 1 m over noise, dB.")
@jitter_options(5e-6, what="(004: units synchronised within 100 us)")
@handle_errors
def demo_cmd(out: Path, seed: int, units: int, room_text: str, layout: str, rt60: float, snr: float,
             jitter: float, jitter_us: float | None = None) -> None:
    """Simulate, detect, calibrate and check paper 004's requirements (``make demo``)."""
    from ..acoustics.pipeline import run_pipeline
    from ..io import staged_outputs, write_json
    from ..plotting.conference import plot_map, plot_timing
    from .acoustics import (
        parse_room,
        pipeline_errors,
        summarise,
        write_simulation,
    )

    room = parse_room(room_text)
    jitter = resolve_jitter(jitter, jitter_us) * 1e6  # microseconds below (messages, payload)
    check_simulation_size(units=units, sample_rate=48000, room=room, rt60=rt60)
    rec_dir = out / "recording"
    click.echo(f"selfcal demo: {units} units ({layout}), room {room_text} m, RT60 {rt60:g} s, SNR {snr:g} dB, "
               f"clock jitter {jitter:g} us, seed {seed}")
    t0 = time.perf_counter()
    truth = write_simulation(rec_dir, units=units, room=room, rt60=rt60, snr=snr, seed=seed, layout=layout,
                             sample_rate=48000, max_order=3, jitter=jitter * 1e-6)
    t_sim = time.perf_counter() - t0
    heights = rec_dir / "heights.json" if layout in ("flat", "boundary") else None
    if heights is not None:
        click.echo("desks at one height: a near-planar layout leaves z (nearly) undetermined, so the known "
                   "heights (recording/heights.json) are used: horizontal positions solved, z given")
    # the simulated clocks' jitter is declared in setup.json, as a real installation would
    result = run_pipeline(rec_dir, dim="auto" if heights is not None else 3, heights=heights, rng=seed)
    # a new result with the simulation stage timed too (results are frozen: never edited in place)
    result = dataclasses.replace(result, timings={"simulate": t_sim, **result.timings})
    errors = pipeline_errors(result, rec_dir)
    payload = result.to_dict()
    if errors is not None:
        payload["errors"] = {k: v for k, v in errors.items() if not k.startswith(("aligned_", "true_"))}
    payload["demo"] = {"units": units, "room": list(room), "layout": layout, "rt60": rt60, "snr_db": snr,
                       "clock_jitter_us": jitter, "seed": seed, "image_order": truth["max_order"]}
    with staged_outputs():
        plot_map(result, out / "map.png", errors, title=f"demo: {units} units, {layout}, seed {seed}",
                 room=truth.get("room"))
        plot_timing(result, out / "timing.png", errors)
        write_json(out / "result.json", payload)
    click.echo("-" * 78)
    for line in summarise(result, errors):
        click.echo(line)
    click.echo("-" * 78)
    if result.failed or (errors is not None and not errors["passed"]):
        raise SystemExit(1)
