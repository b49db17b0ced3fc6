"""``selfcal calibrate graph``: range self-calibration from a measurement graph ``from,to,range[,std]``.

Exit status: 0 = a trustworthy result, 1 = the fit failed its own test (a ``FAIL: ...`` line;
the result is still written), 2 = bad input (one line on stderr, no output file).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import click

from ._base import calibrate, handle_errors
from ._options import SEED

_LENGTH_UNITS = {"m": 1.0, "cm": 1e-2, "mm": 1e-3}


def room_option(func: Any) -> Any:
    """``--room W,D,H`` (or ``x0,y0,z0,x1,y1,z1``): the room box drawn in the anchor figure."""
    return click.option(
        "--room", "room", default=None, metavar="W,D,H",
        help="Room box in the output frame, metres: W,D,H from the origin, or x0,y0,z0,x1,y1,z1; "
             "drawn in the figure.")(func)


def parse_room(text: str | None) -> Any:
    """The (2, 3) room box of ``--room`` (None when not given)."""
    if text is None:
        return None
    from ..errors import InputError
    from ..plotting.anchors import room_box

    try:
        vals = [float(v) for v in text.replace(";", ",").split(",") if v.strip()]
    except ValueError:
        raise InputError(f"--room {text!r}: give W,D,H or x0,y0,z0,x1,y1,z1 in metres") from None
    return room_box(vals)


@calibrate.command("graph")
@click.argument("ranges", type=click.Path(dir_okay=False, path_type=Path))
@click.option("--dim", type=click.Choice(["2", "3"]), default="3", show_default=True, help="Dimension.")
@click.option("--unit", "unit", type=click.Choice(list(_LENGTH_UNITS)), default="m", show_default=True,
              help="Unit of the ranges (and of the std column).")
@click.option("--known", "known", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="CSV name,x,y,z[,std] (metres) of nodes with known positions, by the names of the "
                   "range file (or 0-based indices in order of first appearance); they constrain the "
                   "fit and set the frame.")
@click.option("--frame", "frame", default=None, metavar="origin=A,x=B,xy=C[,z=D]",
              help="Frame by reference nodes: A at the origin, B on +x, C in the xy half-plane (y>0), "
                   "D above (z>0).")
@click.option("--tags", "tags", default=None, metavar="GLOB",
              help="Names of tag positions (a shell pattern, e.g. 't*'): drawn as the tag path, left out "
                   "of --anchors. Default: every node is an anchor.")
@room_option
@click.option("--seed", type=SEED, default=0, show_default=True,
              help="Random seed (blind start).")
@click.option("--out", "out", type=click.Path(dir_okay=False, path_type=Path), required=True,
              help="Result JSON: every node's position, covariance and std, the tests.")
@click.option("--anchors", "anchors_out", type=click.Path(dir_okay=False, path_type=Path), default=None,
              metavar="FILE", help="Anchor file: CSV name,x,y,z,std_x,std_y,std_z, or JSON for a "
                                   "configuration tool (suffix .json).")
@click.option("--csv", "csv_out", type=click.Path(dir_okay=False, path_type=Path), default=None, metavar="FILE",
              help="Every node as CSV name,x,y,z,std_x,std_y,std_z (tags included).")
@click.option("--plot", "plot", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Figure: named anchors with 95% ellipses, the tag path, the room; plan and two elevations.")
@handle_errors
def graph_command(ranges: Path, dim: str, unit: str, known: Path | None, frame: str | None, tags: str | None,
                  room: str | None, seed: int, out: Path, anchors_out: Path | None, csv_out: Path | None,
                  plot: Path | None) -> None:
    """Calibrate every node of a measurement graph RANGES: CSV from,to,range[,std], one measurement a line.

    Any node may range to any other (anchor to anchor, anchor to tag); a pair may be measured
    many times: every measurement is used, and the spread of the repeats is tested against the
    fit (lack-of-fit F test). With --known / --frame the result is in that frame.
    """
    import fnmatch

    import numpy as np

    from ..errors import InputError
    from ..io import staged_outputs, write_json
    from ..io.anchors import write_anchors
    from ..io.graph import read_range_graph
    from ..toa.frame.nodes import read_known_csv
    from ..toa.graph.graph import TEST_LEVEL, solve_range_graph

    if known is not None and frame is not None:
        raise InputError("--known and --frame are exclusive (known positions already define the frame)")
    d = int(dim)
    box = parse_room(room)
    g = read_range_graph(ranges, name=str(ranges))
    k = _LENGTH_UNITS[unit]
    known_table = read_known_csv(known, d, partial=False) if known is not None else None
    is_tag = np.array([tags is not None and fnmatch.fnmatchcase(n, tags) for n in g.names], dtype=bool)
    if tags and not is_tag.any():
        raise InputError(f"--tags {tags!r} matches none of the {g.n_nodes} node names (e.g. {g.names[0]!r})")
    from ..progress import stage

    with stage(f"fit {g.n_nodes} nodes, {len(g.ranges)} ranges"):
        res = solve_range_graph(g.a, g.b, g.ranges * k, g.n_nodes, std=None if g.std is None else g.std * k,
                                dim=d, names=g.names, known=known_table, frame=frame, rng=seed)
    names = list(res.names)
    std = res.position_std
    payload = dict(res.to_dict())
    payload.update(position_std=std, units={"positions": "m", "position_cov": "m^2", "residuals": "m"},
                   tags=[n for n, t in zip(names, is_tag, strict=True) if t],
                   anchors=[n for n, t in zip(names, is_tag, strict=True) if not t])
    A = ~is_tag
    frame_text = res.frame.message
    with staged_outputs():
        write_json(out, payload)
        if anchors_out is not None:
            write_anchors(anchors_out, [n for n, t in zip(names, A, strict=True) if t], res.positions[A],
                          res.position_cov[A], frame=frame_text)
        if csv_out is not None:
            write_anchors(csv_out, names, res.positions, res.position_cov, frame=frame_text)
        if plot is not None:
            from ..plotting.anchors import plot_anchors

            plot_anchors(res.positions[A], [n for n, t in zip(names, A, strict=True) if t], plot,
                         cov=res.position_cov[A], tag=res.positions[is_tag] if is_tag.any() else None,
                         room=box, title=f"anchors ({'room frame' if res.frame.kind != 'canonical' else 'canonical gauge'})")
    n_pairs, m = res.n_pairs, res.n_measurements
    su = "m" if g.std is None else "x the given std"
    lines = [
        f"selfcal calibrate graph: {g.n_nodes} nodes ({int(A.sum())} anchors, {int(is_tag.sum())} tag positions), "
        f"{m} measurements of {n_pairs} pairs, {d}-D",
        f"  method {res.method}, converged={res.converged}, iterations={res.iterations}",
        f"  residual RMS {res.residual_rms:.4g} m, noise estimate {res.noise_estimate:.4g} {su} on {res.dof} dof",
    ]
    if res.outlier_pairs:
        lines.append(f"  {res.outlier_pairs} pair(s) flagged as outliers ({int(res.outliers.sum())} measurements, "
                     "Bonferroni rule on a soft-L1 fit), left out of the fit")
    if res.pure_error_sigma is not None:
        line = (f"  repeats: noise {res.pure_error_sigma:.4g} {su} from their spread ({res.pure_error_dof} dof)")
        if res.lack_of_fit_p is not None:
            verdict = "exceeds it" if res.lack_of_fit_p < TEST_LEVEL else "agrees with it"
            line += (f"; the fit's misfit {verdict} (lack-of-fit F = {res.lack_of_fit_F:.3g}, "
                     f"p = {res.lack_of_fit_p:.2g}, level {TEST_LEVEL:g})")
            if res.lack_of_fit_p < TEST_LEVEL:
                line += ": ranges carry errors the repeats do not show (biases, NLOS); error bars use the misfit"
        lines.append(line)
    if res.chi2_p is not None:
        lines.append(f"  residual test against the std column: chi2 = {res.chi2:.4g} on {res.dof} dof, "
                     f"p = {res.chi2_p:.2g}")
    lines.append(f"  frame: {frame_text}")
    sa = std[A]
    ok = np.isfinite(sa).all(1)
    if ok.any():
        lines.append("  anchor std (RMS over anchors): " + ", ".join(
            f"{ax} {np.sqrt(np.mean(sa[ok, i] ** 2)):.3g} m" for i, ax in enumerate("xyz"[:d])))
    loose = set(res.poorly_determined_nodes)
    loose_anchors = [n for n, t in zip(names, A, strict=True) if t and n in loose]
    if loose:
        shown = sorted(loose, key=names.index)
        lines.append(f"  poorly determined: {len(loose)} node(s) with a 95 % region larger than the node set "
                     f"({', '.join(shown[:10])}{', ...' if len(shown) > 10 else ''})")
    wrote = [str(p) for p in (out, anchors_out, csv_out, plot) if p is not None]
    lines.append("  wrote " + ", ".join(wrote))
    click.echo("\n".join(lines))
    from ..errors import Status

    amb = set(res.mirror_ambiguous_nodes)
    tag_names = {n for n, t in zip(names, is_tag, strict=True) if t}
    if res.status == Status.AMBIGUOUS and amb <= tag_names:
        # the anchors are determined: a tag's mirror through coplanar anchors leaves their ranges unchanged
        click.echo(f"  ambiguous tag positions: {len(amb)} fit as well mirrored through their anchors' plane "
                   "(coplanar anchors); the anchor set is not affected")
    elif not res.success:
        click.echo(f"FAIL: calibration not trustworthy ({res.message})")
        raise SystemExit(1)
    if loose_anchors:
        click.echo(f"FAIL: anchor(s) {', '.join(loose_anchors)} not determined (95 % region larger than the "
                   "node set); add ranges to them")
        raise SystemExit(1)
