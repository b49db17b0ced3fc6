"""``selfcal calibrate toa``: TOA / range self-calibration from a matrix file.

Exit status: 0 = a trustworthy result, 1 = the fit failed its own test (a ``FAIL: ...``
line; the result is still written), 2 = bad input (one line on stderr, no output file).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import click

from ..toa.verdict.planarity import PLANAR_ALPHA
from ._base import calibrate, handle_errors
from ._common import csv_option, unit_options
from ._options import NOISE_STD, SEED, SPEED
from .graph import parse_room, room_option

#: ``--entries auto`` keeps per-entry arrays in the JSON up to this many matrix entries: about
#: 2 MB of text and ~1 s of conversion; a 1000 x 1000 matrix took 17 s to convert and 10 s to write
ENTRIES_JSON_MAX = 100_000


@calibrate.command("toa")
@click.argument("matrix", type=click.Path(dir_okay=False, path_type=Path))
@click.option("--speed", type=SPEED, default=None, metavar="C",
              help="Propagation speed in m/s: the matrix holds seconds; offsets are reported in seconds.")
@click.option("--offsets", type=click.Choice(["none", "receivers", "sources", "both", "auto"]), default=None,
              help="Unknown per-receiver (d_i) and/or per-source (o_j) offsets; auto = chosen by held-out "
                   "prediction (K-fold over sources). Default: the solver's default; with the moving-tag "
                   "recipe a common offset (block test), then per-anchor biases kept by held-out prediction.")
@click.option("--dim", type=click.Choice(["2", "3", "auto"]), default="auto", show_default=True,
              help="Dimension. auto: 3-D unless z is not determined by the data: 3-D needs an F test of the "
                   f"3-D fit against the 2-D one at level {PLANAR_ALPHA:g} (nominal: on planar layouts, where the "
                   "3-D model is not regular, 4 % of simulated 8 x 10 networks were called 3-D) and the 3-D "
                   "layout's thickness resolved by the fit's own error bars (a chi-square test of the "
                   "out-of-plane coordinates at the same level); the choice and its statistics are printed "
                   "and in the JSON ('selection').")
@click.option("--loss", type=click.Choice(["linear", "huber", "soft_l1", "cauchy"]), default=None,
              help="Loss of the fit. Default: the solver's robust default (outliers found on a "
                   "soft-L1 fit with a data-estimated scale, flagged by a Bonferroni rule, then "
                   "least squares on the inliers).")
@click.option("--method", type=click.Choice(["auto", "nls", "rank3"]), default="auto", show_default=True,
              help="auto: initialise + NLS + search; nls: one refinement; rank3: 004 initialiser only.")
@click.option("--noise", type=NOISE_STD, default=None, metavar="SIGMA",
              help="Measurement noise std in the matrix's units: enables the chi-square residual test.")
@click.option("--recipe", type=click.Choice(["auto", "none", "moving-tag"]), default="auto", show_default=True,
              help="Preprocessing recipe: moving-tag = columns are one moving device in time order "
                   "(multipath spikes rejected in time, under-observed positions dropped); auto = "
                   "moving-tag when a permutation test finds the columns in time order (p < 1e-3).")
@click.option("--common-offset", "common_offset", type=click.Choice(["free", "test"]), default="test",
              show_default=True,
              help="moving-tag recipe with offsets none/auto: 'test' adds one range offset common to every "
                   "entry (a UWB antenna delay) when a block jackknife t test over time blocks finds it "
                   "(p < 0.05), then per-anchor offsets when they predict held-out tag positions better; "
                   "'free' = neither.")
@click.option("--known", "known", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="CSV name,x,y,z[,std] of nodes with known positions, metres; an empty coordinate is not "
                   "known ('A3,,,2.41': only the height) (r<i>, s<j> or a receiver "
                   "index); they constrain the fit and set the frame.")
@click.option("--side", type=click.Choice(["below", "above"]), default=None,
              help="With --known nodes in one plane (ceiling anchors): the other nodes lie below / above "
                   "it (along z of the known frame). Resolves the mirror image that plane leaves; without "
                   "it the mirror is reported (exit 1).")
@click.option("--frame", "frame", default=None, metavar="origin=A,x=B,xy=C[,z=D]",
              help="Frame by reference nodes: A at the origin, B on +x, C in the xy half-plane (y>0), "
                   "D above (z>0).")
@click.option("--entries", type=click.Choice(["auto", "json", "npz"]), default="auto", show_default=True,
              help="Where the per-entry arrays (residuals, outliers mask) go: json = in the result; npz = "
                   "a binary sidecar OUT with suffix .npz (keys residuals, outliers); auto = npz above "
                   f"{ENTRIES_JSON_MAX:,} entries.")
@click.option("--seed", type=SEED, default=0, show_default=True, help="Random seed (initialisers, restarts).")
@click.option("--out", "out", type=click.Path(dir_okay=False, path_type=Path), required=True,
              help="Result JSON (keys per DESIGN.md).")
@click.option("--plot", "plot", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Figure of receivers and sources with 95% confidence ellipses (format from the suffix: .png, .pdf, .svg).")
@csv_option
@click.option("--anchors", "anchors_out", type=click.Path(dir_okay=False, path_type=Path), default=None,
              metavar="FILE", help="The receivers (anchors) as CSV name,x,y,z,std_x,std_y,std_z, or JSON for a "
                                   "configuration tool (suffix .json), in the output frame.")
@click.option("--anchor-plot", "anchor_plot", type=click.Path(dir_okay=False, path_type=Path), default=None,
              metavar="FILE", help="Installer figure: named anchors, the tag path (sources in column order), "
                                   "the --room box; plan and two elevations.")
@room_option
@unit_options
@handle_errors
def toa_command(matrix: Path, speed: float | None, offsets: str | None, dim: str | None,
                loss: str | None, method: str, noise: float | None, recipe: str, common_offset: str,
                known: Path | None, side: str | None,
                frame: str | None, entries: str, seed: int, out: Path, plot: Path | None, csv_out: Path | None = None,
                unit: str | None = None, sample_rate: float | None = None, anchors_out: Path | None = None,
                anchor_plot: Path | None = None, room: str | None = None) -> None:
    """Calibrate receivers and sources from an I x J TOA/range MATRIX (CSV or .npy, NaN = missing).

    Rows are receivers, columns are sources (a header row and a first column of names are
    kept). Metres unless --speed is given (then seconds); --unit names another unit.
    """
    import warnings

    import numpy as np

    from .._checks import plausible_matrix_scale
    from ..errors import InputError
    from ..io import read_table, staged_outputs, write_json
    from ..progress import stage
    from ..toa.frame.frame import (
        FramedToaResult,
        apply_frame,
        fit_known,
        parse_known,
        read_known_csv,
    )
    from ..toa.frame.nodes import check_frame, check_known_scale, node_names, offsets_of
    from ..toa.recipes.recipes import apply_recipe
    from ._common import enrich_payload, to_metres, write_nodes_csv

    if known is not None and frame is not None:
        raise InputError("--known and --frame are exclusive (known positions already define the frame)")
    if side is not None and known is None:
        raise InputError("--side says where the other nodes lie relative to the --known nodes' plane: give --known")
    box = parse_room(room)
    table = read_table(matrix, name=str(matrix))
    M, speed, _ = to_metres(table.values, unit, speed, sample_rate, name=str(matrix))
    plausible_matrix_scale(M, speed=speed, explicit_unit=unit is not None, name=str(matrix))
    # the model and the loss when given (None: the solver's default; the recipe's for offsets)
    model: dict[str, Any] = {"offsets": offsets, "loss": loss, "dim": dim if dim in (None, "auto") else int(dim)}
    model = {key: val for key, val in model.items() if val is not None}
    # node names: the matrix's own (header row / first column) or 0-based r<i> / s<j>;
    # --known and --frame are read and resolved against them before any work
    I, J = M.shape
    names = node_names(table.row_names, table.col_names, I, J)
    known_table = None
    dim_by_known = False
    if known is not None:
        known_table = read_known_csv(known, 2 if dim == "2" else 3)  # validated before the solve
        known_nodes = parse_known(known_table, I, J, 2 if dim == "2" else 3, receiver_names=names["receiver_names"],
                                  source_names=names["source_names"])
        check_known_scale(known_nodes, float(np.nanmax(np.abs(M))) * (speed if speed is not None else 1.0))
        # known positions that span 3-D (affine rank 3) fix a 3-D frame: z is not a question
        # for the data, and a 2-D fit could not be put in that frame
        full_known = [k.position for k in known_nodes if np.isfinite(k.position).all()]
        if dim == "auto" and _spans_3d(full_known):
            model["dim"] = 3
            dim_by_known = True
    if frame is not None:
        check_frame(frame, I, J, **names)
    sidecar = _sidecar(entries, M.shape, out, [matrix, known])  # refused before the solve
    # with --known the blind fit's verdict is superseded by the constrained fit's (judged again
    # below): its warning is held back, the others are passed on
    with warnings.catch_warnings(record=True) as blind_warnings, stage(f"fit {M.shape[0]} x {M.shape[1]}"):
        warnings.simplefilter("always")
        rec = apply_recipe(recipe, M, common_offset=common_offset, method=method, rng=seed, speed=speed,
                           noise=noise, **model)
    for w in blind_warnings:
        if not (known is not None and str(w.message).startswith("solve_toa: ")):
            warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
    res: Any = rec.result
    forced = _forced_model(rec.result, M, rec.rejected, speed, noise, dim, offsets)
    framed: FramedToaResult | None = None
    d_out = np.asarray(res.receivers).shape[1]
    # a kept common range offset (moving-tag recipe) is its own model: the refits keep it
    off_used = "common" if res.offsets == "common" else offsets_of(res)
    # the constrained / frame refits see what the blind fit used: the recipe's spikes and
    # the outliers the solver removed are left out; the default ("auto") fits the inliers
    # by least squares, as the blind fit's last step does
    loss_used = loss if loss is not None else "linear"
    M_fit = _fitted_entries(M, rec.rejected, res.outliers)
    if known_table is not None and known is not None:
        nodes = parse_known(_redim(known_table, known, d_out), I, J, d_out, receiver_names=names["receiver_names"],
                            source_names=names["source_names"])
        with stage(f"fit with {len(nodes)} known nodes"):
            framed = fit_known(M_fit, res, nodes, offsets=off_used, loss=loss_used, noise=noise, side=side)
    elif frame is not None:
        with stage("fit in the --frame"):
            framed = apply_frame(res, frame, matrix=M_fit, offsets=off_used, loss=loss_used, **names)
    if framed is not None:
        res = framed.result
    if res.residuals is None or res.outliers is None:
        sidecar = None
    payload = enrich_payload(dict(_without_entries(res).to_dict() if sidecar else res.to_dict()), names=names)
    if sidecar is not None:
        payload["n_outliers"] = int(np.sum(res.outliers)) if res.outliers is not None else 0
        payload["entries"] = {"file": sidecar.name, "arrays": ["residuals", "outliers"], "shape": [*M.shape],
                              "note": "per-entry arrays in the binary sidecar (numpy.load); --entries json keeps "
                                      "them in this file"}
    used = rec.recipe
    if recipe != "none":
        payload["recipe"] = rec.recipe_dict()
    if framed is not None:
        payload["frame"] = framed.frame.to_dict()
        es = payload["frame"].get("error_scale")
        if es:  # per receiver by the matrix's names, as everywhere in the JSON
            rn = names["receiver_names"]
            for key in ("scale", "ratio"):
                es[key] = {rn[int(k[1:])]: v for k, v in es[key].items()}
    if forced is not None:
        payload["model_test"] = forced.to_dict()
    ok, why = _trustworthy(res)
    # all artefacts staged and committed together; a FAIL (exit 1) still writes its result
    with staged_outputs():
        if plot is not None:
            from ..plotting.toa import plot_toa

            plot_toa(res, plot, user_frame=framed is not None, names=(table.row_names, table.col_names))
        write_json(out, payload)
        if sidecar is not None:
            from ..io.outputs import write_npz

            write_npz(sidecar, {"residuals": np.asarray(res.residuals, float),
                                "outliers": np.asarray(res.outliers, bool)})
        if csv_out is not None:
            write_nodes_csv(csv_out, payload, [("receiver", "receivers", "receiver_names"),
                                               ("source", "sources", "source_names")])
        _installer_outputs(res, names["receiver_names"], anchors_out, anchor_plot, box,
                           framed.frame.message if framed is not None else "canonical gauge (no frame given)")
    unit = "s" if speed is not None else "m"
    tr = np.trace(res.receiver_cov, axis1=1, axis2=2)
    ts = np.trace(res.source_cov, axis1=1, axis2=2)
    lines = [
        f"selfcal calibrate toa: {I} receivers x {J} sources, {d_out}-D, offsets={off_used}, "
        f"{int((~np.isfinite(M)).sum())} missing" + (f", recipe {used}" if used != "none" else ""),
        f"  method {res.method}, converged={res.converged}, iterations={res.iterations}",
        f"  residual RMS {res.residual_rms:.4g} {unit}, noise sigma {res.sigma:.4g} {unit}",
    ]
    if used != "none":
        auto = rec.details.get("auto")
        reason = f" (auto: columns in time order, permutation p = {auto['p_value']:.2g})" if auto else ""
        lines.append(f"  recipe {used}{reason}: {rec.n_rejected} spikes rejected, {len(rec.dropped_sources)} "
                     "tag positions dropped (too few ranges left)")
        co = rec.details.get("common_offset_test")
        if co and "p_value" in co:
            lines.append(f"  common range offset {co['value']:.4g} {'s' if speed is not None else 'm'} "
                         f"{'kept' if co['adopted'] else 'not kept'} (block jackknife t = {co['t_statistic']:.3g}, "
                         f"{co['blocks']} blocks, p = {co['p_value']:.2g}, level {co['alpha']:g})")
    lines += _offsets_choice_lines(rec.details, res, unit)
    lines += _dim_choice_lines(res)
    if dim_by_known:
        lines.append("  dim 3 (auto: the --known nodes span three dimensions)")
    counts = _counts(res)
    if counts:
        lines.append("  " + ", ".join(counts))
    if framed is not None:
        lines.append(f"  frame: {framed.frame.message}")
        if framed.frame.known_rms is not None:
            lines.append(f"  known nodes: RMS {framed.frame.known_rms:.4g} m after alignment, "
                         f"{framed.frame.known_rms_fit:.4g} m after the constrained fit")
        es = framed.frame.error_scale
        if es:
            rn = names["receiver_names"]
            grown = [f"{rn[int(k[1:])]} x{np.sqrt(v):.2g}" for k, v in es["scale"].items() if v > 1.0]
            lines.append(f"  error bars: block jackknife over {es['folds']} blocks of tag positions; stds grown where "
                         f"the data vary more than the model says: {', '.join(grown) if grown else 'none'}")
    ok_tr, ok_ts = np.isfinite(tr), np.isfinite(ts)
    if ok_tr.any() and ok_ts.any():
        lines.append(
            f"  predicted position std (RMS over points): receivers {np.sqrt(tr[ok_tr].mean()):.4g} m, "
            f"sources {np.sqrt(ts[ok_ts].mean()):.4g} m"
        )
    det = res.determinacy
    if det is not None and det.n_undetermined:
        lines.append(f"  undetermined: {det.n_undetermined} of {det.tested} nodes have a 95 % confidence region "
                     f"larger than their node set ({det.names(**names)})")
    click.echo("\n".join(lines))
    fails = _verdict_lines(res, forced, names["receiver_names"], names["source_names"])
    for line in fails:
        click.echo(line)
    if not ok:
        click.echo(f"FAIL: calibration not trustworthy ({why})")
    if fails or not ok:
        raise SystemExit(1)


def _forced_model(res: Any, M: Any, rejected: Any, speed: float | None, noise: float | None, dim: str | None,
                  offsets: str | None) -> Any:
    """The model the user fixed (not "auto") tested against the larger one (:mod:`selfcal.toa.verdict.model_test`)."""
    import numpy as np

    from ..toa.verdict.model_test import forced_model_test

    off = res.offsets
    test_dim = dim == "2"
    test_off = offsets != "auto" and off in ("none", "receivers", "sources")
    if not (test_dim or test_off) or res.residuals is None:
        return None
    c = speed if speed is not None else 1.0
    Mf = _fitted_entries(M, rejected, res.outliers)
    R, S = np.asarray(res.receivers, float), np.asarray(res.sources, float)
    ok_r, ok_s = np.isfinite(R).all(1), np.isfinite(S).all(1)

    def sub(a: Any, ok: Any) -> Any:
        return None if a is None else np.asarray(a, float)[ok] * c

    return forced_model_test(Mf[np.ix_(ok_r, ok_s)] * c, R[ok_r], S[ok_s], sub(res.receiver_offsets, ok_r),
                             sub(res.source_offsets, ok_s), offsets=str(off), noise=None if noise is None else noise * c,
                             test_dim=test_dim, test_offsets=test_off,
                             excluded=np.asarray(M, float)[np.ix_(ok_r, ok_s)] * c)


def _verdict_lines(res: Any, forced: Any, row_names: Any, col_names: Any) -> list[str]:
    """``FAIL:`` lines of the uniqueness test (ambiguous nodes, a minimal problem) and the forced-model test."""
    out = []
    u = res.uniqueness
    if u is not None and not u.passed:
        if u.ambiguous_receivers.any() or u.ambiguous_sources.any():
            kinds = sorted({a.kind for a in u.alternatives})
            what = (f"{u.names(row_names or None, col_names or None)} have alternative positions that fit the "
                    f"ranges as well ({', '.join(kinds)}; likelihood-ratio test, level {u.alpha:g}; alternatives "
                    "in the JSON under 'uniqueness')")
            if u.failed:
                out.append(f"FAIL: ambiguous: {what}; remedy: a tag position off the plane of their partners, "
                           "known heights of the ambiguous anchors on more than one level (--known rows such as "
                           "'A3,,,2.41': x, y left empty), a known node off the plane (or --side with coplanar "
                           "--known nodes)")
            else:  # a few nodes: named, their error bars widened to cover the alternative (as 'undetermined')
                click.echo(f"  ambiguous: {what}; their error bars cover the alternative")
        if u.minimal:
            out.append("FAIL: minimal problem: no spare measurement, so no other solution can be ruled out; "
                       "add measurements")
    if forced is not None and not forced.passed:
        out.append(f"FAIL: {forced.message()}")
    return out


def _sidecar(entries: str, shape: tuple[int, ...], out: Path, inputs: list[Path | None]) -> Path | None:
    """The ``.npz`` next to ``out`` that takes the per-entry arrays, or None (kept in the JSON)."""
    import math
    import os

    from ..errors import InputError

    if str(out) == "-" or entries == "json":
        return None
    if entries == "auto" and math.prod(shape) <= ENTRIES_JSON_MAX:
        return None
    path = out.with_suffix(".npz") if out.suffix.lower() != ".npz" else out.with_name(out.name + ".npz")
    real = os.path.realpath(path)
    for p in inputs:
        if p is not None and os.path.realpath(p) == real:
            raise InputError(f"the per-entry sidecar {path} would overwrite the input {p}; choose another --out")
    return path


def _without_entries(res: Any) -> Any:
    """``res`` with its per-entry arrays left out (they go to the sidecar, not through JSON)."""
    import dataclasses

    return dataclasses.replace(res, residuals=None, outliers=None)


def _installer_outputs(res: Any, names: Any, anchors_out: Path | None, anchor_plot: Path | None, box: Any,
                       frame: str) -> None:
    """``--anchors`` (the receivers as the anchor file) and ``--anchor-plot`` (the installer figure)."""
    if anchors_out is not None:
        from ..io.anchors import write_anchors

        write_anchors(anchors_out, list(names), res.receivers, res.receiver_cov, frame=frame)
    if anchor_plot is not None:
        from ..plotting.anchors import plot_anchors

        gauge = "canonical gauge" if frame.startswith("canonical") else "room frame"
        plot_anchors(res.receivers, list(names), anchor_plot, cov=res.receiver_cov, tag=res.sources, room=box,
                     title=f"anchors ({gauge})")


def _dim_choice_lines(res: Any) -> list[str]:
    """The ``--dim auto`` choice (:func:`selfcal.toa.verdict.select.choose_dim`), one line; a
    second where its bootstrap widened the 3-D answer's error bars (``bars_note``)."""
    sel = (res.selection or {}).get("dim") if isinstance(res.selection, dict) else None
    if not sel or "chosen" not in sel:
        return []
    if "f_statistic" not in sel:
        return [f"  dim {sel['chosen']} (auto: {sel.get('reason', 'the only fit')})"]
    tp = sel.get("thickness_p")
    chi = "" if tp is None or tp != tp else f", chi-square p = {tp:.2g}"
    lines = [f"  dim {sel['chosen']} (auto: 3-D vs 2-D F = {sel['f_statistic']:.3g}, p = {sel['p_value']:.2g}, "
             f"level {PLANAR_ALPHA:g}; 3-D thickness {sel['thickness']:.3g} m{chi}"
             + (", not resolved: near-planar" if sel.get("near_planar") else "")
             + (f"; {sel['reason']})" if sel.get("reason") else ")")]
    if sel.get("bars_widened") and sel.get("bars_note"):
        lines.append(f"  {sel['bars_note']}")
    return lines


def _offsets_choice_lines(details: dict[str, Any], res: Any, unit: str) -> list[str]:
    """The held-out prediction choice of the offsets model (recipe or ``--offsets auto``), one line."""
    sel = details.get("offsets_choice") or (res.selection or {}).get("offsets")
    if not sel or "cv_rmse" not in sel:
        return []
    scores = ", ".join(f"{k} {v:.4g}" for k, v in sel["cv_rmse"].items())
    line = (f"  offsets model {sel['chosen']} by held-out prediction ({sel['folds']}-fold over sources (tag positions), "
            f"one-SE rule with a sign test; best {sel['best']}): RMS prediction error {scores} {unit}")
    est = (sel.get("anchor_mse") or {}).get("rmse")
    if est:  # the per-anchor model is kept only where its anchors are expected to be more accurate too
        line += "; estimated anchor RMS error " + ", ".join(f"{k} {v:.3g}" for k, v in est.items()) + f" {unit}"
    return [line]


def _fitted_entries(M: Any, rejected: Any, outliers: Any) -> Any:
    """The matrix with the recipe's rejected spikes and the solver's outliers set to NaN."""
    import numpy as np

    out = np.array(M, dtype=float)
    for mask in (rejected, outliers):
        if mask is not None and np.shape(mask) == out.shape:
            out[np.asarray(mask, bool)] = np.nan
    return out


def _spans_3d(points: Any) -> bool:
    """Known positions with affine rank 3 (relative singular value above 1e-6, as known.py's)."""
    import numpy as np

    P = np.asarray(points, float)
    if P.ndim != 2 or P.shape[1] != 3 or P.shape[0] < 4:
        return False
    sv = np.linalg.svd(P - P.mean(axis=0), compute_uv=False)
    return bool(sv[-1] > 1e-6 * max(sv[0], 1e-300))


def _redim(table: dict[str, tuple[float, ...]], path: Path, d: int) -> dict[str, tuple[float, ...]]:
    """Re-read the known table for the dimension actually fitted (``--dim auto`` may give 2)."""
    from ..toa.frame.frame import read_known_csv

    return table if d == 3 else read_known_csv(path, d)


def _counts(res: Any) -> list[str]:
    """Dropped nodes / outlier counts, for results that carry them."""
    import numpy as np

    out = []
    for key, label in (("dropped_receivers", "receivers dropped"), ("dropped_sources", "sources dropped")):
        v = getattr(res, key)
        if len(v):
            out.append(f"{len(v)} {label}")
    mask, broke = res.outliers, res.outlier_breakdown
    if mask is not None:
        out.append(f"{broke} ({int(np.asarray(mask).sum())} flagged)" if broke
                   else f"{int(np.asarray(mask).sum())} outliers flagged")
    return out


def _trustworthy(res: Any) -> tuple[bool, str]:
    """The result's own verdict (:class:`selfcal.toa.ToaResult` ``success`` / ``message``)."""
    return bool(res.success), str(res.message or "the fit failed its residual test")
