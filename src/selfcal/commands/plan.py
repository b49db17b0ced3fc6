"""``selfcal plan``: predicted anchor error bars, tag positioning error and ambiguities of a layout.

Exit status: 0 = the layout has no ambiguity, 1 = it has one (named on a ``FAIL:`` line;
the outputs are still written), 2 = bad input.
"""

from __future__ import annotations

from pathlib import Path

import click

from ._base import handle_errors, main
from ._options import Quantity

RANGE_NOISE_M = Quantity("m", gt=0, le=10.0, why="a range noise std in metres (UWB: 0.03-0.1)")
HEIGHT_M = Quantity("m", ge=-1000.0, le=1000.0, why="a height in metres")
MAX_RANGE_M = Quantity("m", gt=0, le=1e4, why="a radio range in metres")


@main.command("plan")
@click.argument("anchors", type=click.Path(dir_okay=False, path_type=Path))
@click.argument("path", type=click.Path(dir_okay=False, path_type=Path))
@click.option("--room", "room_text", default=None, metavar="LxWxH",
              help="Room size in metres (origin at a corner), e.g. 8x6x3: the map covers its floor plan.")
@click.option("--noise", type=RANGE_NOISE_M, default=0.05, show_default=True, metavar="SIGMA",
              help="Range noise std in metres (UWB two-way ranging: 0.03-0.1).")
@click.option("--offsets", type=click.Choice(["none", "receivers", "both"]), default="receivers",
              show_default=True, help="Offset model of the calibration: receivers = a bias per anchor.")
@click.option("--height", type=HEIGHT_M, default=None, help="Height of the map (default: the path's median).")
@click.option("--max-range", "max_range", type=MAX_RANGE_M, default=None, help="Ranges beyond this (m) are not measured.")
@click.option("--out", "out", type=click.Path(dir_okay=False, path_type=Path), required=True, help="Result JSON.")
@click.option("--plot", "plot", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Map of the tag positioning error with anchors and path (.png, .pdf, .svg).")
@handle_errors
def plan_command(anchors: Path, path: Path, room_text: str | None, noise: float, offsets: str,
                 height: float | None, max_range: float | None, out: Path, plot: Path | None) -> None:
    """Predict what calibrating ANCHORS (CSV name,x,y,z) from a tag walked along PATH (CSV x,y,z) gives.

    Each anchor's error bar is the Cramér-Rao bound of the self-calibration (the covariance
    ``calibrate toa`` would report); the map is the tag's positioning error bound over the
    room at the path's height; ambiguities (a tag path in one plane, coplanar anchors) are named.
    """
    import numpy as np

    from ..errors import InputError
    from ..io import read_table, staged_outputs, write_json
    from ..toa.frame.nodes import read_known_csv
    from ..toa.plan import plan_layout
    from .acoustics import parse_room

    table = read_known_csv(anchors, 3, partial=False)
    names = list(table)
    A = np.array([v[:3] for v in table.values()], float)
    P = np.asarray(read_table(path, name=str(path)).values, float)
    if P.ndim != 2 or P.shape[1] != 3:
        raise InputError(f"{path}: expected one tag position x,y,z per row, got {P.shape[1]} columns")
    if not np.isfinite(P).all():
        raise InputError(f"{path}: missing or non-finite coordinates")
    room = None
    if room_text is not None:
        try:
            room = parse_room(room_text)
        except click.BadParameter as exc:
            raise InputError(f"--room: {exc.message}") from None
    plan = plan_layout(A, P, noise=noise, offsets=offsets, room=room, height=height, max_range=max_range)
    payload = {"anchors": {n: {"position": a.tolist(), "std": float(s) if np.isfinite(s) else None} for n, a, s in
                           zip(names, A, plan.anchor_std, strict=True)}, **plan.to_dict()}
    with staged_outputs():
        if plot is not None:
            from ..plotting.plan import plot_plan

            plot_plan(plan, A, P, plot, names=names)
        write_json(out, payload)
    m = plan.tag_std_map[np.isfinite(plan.tag_std_map)]
    lines = [f"selfcal plan: {len(A)} anchors, {len(P)} tag positions, noise {noise:g} m, offsets {offsets}",
             "  predicted anchor std (m): " + ", ".join(f"{n} {s:.3g}" for n, s in zip(names, plan.anchor_std,
                                                                                      strict=True))]
    if not plan.determined:
        lines.append("  the layout does not determine the calibration: its Fisher information is singular beyond "
                     "the rigid motions (no finite error bar)")
    if m.size:
        lines.append(f"  tag positioning error at z = {plan.height:.2f} m: median {np.median(m):.3g} m, "
                     f"worst {m.max():.3g} m over the map")
    for a in plan.ambiguities:
        lines.append(f"  ambiguity ({a.kind}): {a.message}")
    lines.append(f"  wrote {out}" + (f" and {plot}" if plot is not None else ""))
    click.echo("\n".join(lines))
    if plan.ambiguities or not plan.determined:
        why = [a.kind for a in plan.ambiguities] + ([] if plan.determined else ["not determined"])
        click.echo(f"FAIL: the layout is ambiguous ({', '.join(why)})")
        raise SystemExit(1)
