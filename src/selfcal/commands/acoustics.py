"""Acoustic commands: ``selfcal simulate conference`` and ``selfcal pipeline`` (issue 7, paper 004).

Heavy imports (numpy work, pyroomacoustics, matplotlib) happen inside the commands.
"""

from __future__ import annotations

import math
import os
import shutil
import tempfile
from pathlib import Path
from typing import Any

import click

from ._base import handle_errors, main, simulate
from ._common import (
    all_or_nothing,
    check_simulation_size,
    csv_option,
    jitter_options,
    resolve_jitter,
)
from ._options import HUMIDITY_PCT, RT60_S, SEED, SNR_DB, SPEED_OF_SOUND, TEMPERATURE_C


def parse_room(text: str) -> tuple[float, float, float]:
    """Parse ``LxWxH`` (metres) into three floats, or raise ``click.BadParameter``."""
    parts = text.lower().replace("*", "x").split("x")
    try:
        vals = tuple(float(p) for p in parts)
    except ValueError:
        vals = ()
    if len(vals) != 3 or not all(math.isfinite(v) and v > 0 for v in vals):
        raise click.BadParameter(f"expected L x W x H in metres like 12x12x3, got {text!r}")
    return vals[0], vals[1], vals[2]


#: The file ``simulate`` writes into its folder listing every file it wrote (name, size,
#: SHA-256): a later ``simulate`` into the same folder replaces it only when the folder
#: holds these files alone, unchanged, so nothing it did not write is ever deleted.
SIMULATE_MANIFEST = "simulate-manifest.json"


def _sha256(path: Path) -> str:
    import hashlib

    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def check_simulation_folder(out: Path) -> None:
    """Refuse an ``--out`` folder that holds anything an earlier ``simulate`` did not write.

    An absent or empty folder is taken. A non-empty one must hold :data:`SIMULATE_MANIFEST`
    and, besides it, only the regular files it lists, each with the size and SHA-256 it
    lists (a file edited since is the user's now).

    Raises
    ------
    InputError
        Naming the folder and the first entry that is not a file ``simulate`` wrote.
    """
    import json
    import stat

    from ..errors import InputError

    if not out.exists() and not out.is_symlink():
        return
    if not out.is_dir():
        raise InputError(f"--out {out}: exists and is not a folder; choose another --out")
    entries = sorted(out.iterdir())
    if not entries:
        return
    manifest = out / SIMULATE_MANIFEST
    why = f"--out {out}: the folder is not empty and was not written by 'selfcal simulate'"
    try:
        listed = json.loads(manifest.read_text())["files"]
        assert isinstance(listed, dict)
    except FileNotFoundError:
        raise InputError(f"{why} (no {SIMULATE_MANIFEST}; it holds {entries[0].name}); "
                         f"choose an empty or new --out") from None
    except (OSError, ValueError, KeyError, TypeError, AssertionError):
        raise InputError(f"{why} ({SIMULATE_MANIFEST} is unreadable); choose an empty or new --out") from None
    for e in entries:
        if e.name == SIMULATE_MANIFEST:
            continue
        info = listed.get(e.name)
        mode = os.lstat(e).st_mode
        if not isinstance(info, dict) or not stat.S_ISREG(mode):
            raise InputError(f"--out {out}: holds {e.name}, which 'selfcal simulate' did not write; "
                             f"refusing to replace the folder (choose an empty or new --out)")
        if os.lstat(e).st_size != info.get("size") or _sha256(e) != info.get("sha256"):
            raise InputError(f"--out {out}: {e.name} changed since 'selfcal simulate' wrote it; "
                             f"refusing to replace the folder (choose an empty or new --out)")


def _write_manifest(folder: Path) -> None:
    from ..io import write_json

    files = {p.name: {"size": p.stat().st_size, "sha256": _sha256(p)}
             for p in sorted(folder.iterdir()) if p.is_file() and p.name != SIMULATE_MANIFEST}
    write_json(folder / SIMULATE_MANIFEST, {"written_by": "selfcal simulate", "files": files})


def write_simulation(out: Path, *, units: int, room: tuple[float, float, float], rt60: float, snr: float,
                     seed: int, layout: str, sample_rate: int, max_order: int | None,
                     jitter: float = 0.0, rounds: int = 1, progress: bool = True) -> dict[str, Any]:
    """Simulate a conference recording directory at ``out`` atomically; return the truth.

    The directory is built next to ``out`` and renamed into place, so ``out`` is either the
    old content or the complete new recording. An existing ``out`` is replaced only when it
    is empty or holds only the files an earlier ``simulate`` wrote
    (:func:`check_simulation_folder`, :data:`SIMULATE_MANIFEST`).
    """
    import numpy as np

    from .._checks import check_int
    from ..acoustics.recording import write_recording
    from ..acoustics.room import simulate_conference
    from ..scenarios.conference import conference_scene

    check_simulation_folder(out)
    if out.is_symlink():  # a link to a folder: the folder it points to is the output (the link stays)
        out = out.resolve()
    rng = np.random.default_rng(check_int(seed, "--seed", minimum=0))
    scene = conference_scene(units, room, layout=layout, rng=rng)
    setup, signals, truth = simulate_conference(scene, rt60=rt60, snr_db=snr, sample_rate=sample_rate,
                                                max_order=max_order, jitter=jitter, rounds=rounds,
                                                rng=rng, progress=progress)
    truth["seed"] = seed
    heights = {"receivers": scene.receivers[:, 2].tolist(), "senders": scene.senders[:, 2].tolist()}
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.", dir=out.parent))
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(tmp, 0o777 & ~umask)  # mkdtemp makes it private; the result is an ordinary folder
    try:
        write_recording(tmp, setup, signals, truth=truth, extra={"heights.json": heights})
        _write_manifest(tmp)
        if out.exists():
            check_simulation_folder(out)  # again: a file may have arrived while the simulation ran
            old = out.with_name(f".{out.name}.old-{os.getpid()}")
            os.replace(out, old)
            os.replace(tmp, out)
            shutil.rmtree(old, ignore_errors=True)
        else:
            os.replace(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    from ..io.outputs import moved_written

    moved_written(tmp, out)  # the files written are named where they now are (the last line)
    return truth


@simulate.command("conference")
@click.option("--units", type=int, default=20, show_default=True, help="Units (microphone + loudspeaker).")
@click.option("--room", "room_text", default="12x12x3", show_default=True, help="Room L x W x H in metres.")
@click.option("--rt60", type=RT60_S, default=0.4, show_default=True, help="Reverberation time, s.")
@click.option("--snr", type=SNR_DB, default=30.0, show_default=True, help="Direct sound at 1 m over noise, dB.")
@click.option("--seed", type=SEED, default=0, show_default=True, help="Random seed.")
@click.option("--layout", type=click.Choice(["flat", "boundary", "tiered", "stem", "hall"]), default="flat",
              show_default=True,
              help="flat desks (near-planar), amphitheatre tiers, stem microphones above desk loudspeakers, "
                   "or a hall (tiers, goosenecks 5-40 cm).")
@click.option("--sample-rate", type=int, default=48000, show_default=True, help="Hz.")
@click.option("--max-order", type=click.IntRange(min=0), default=3, show_default=True,
              help="Image-source order cap (speed); 0 = anechoic.")
@jitter_options(0.0)
@click.option("--rounds", type=click.IntRange(min=1), default=1, show_default=True,
              help="Events per loudspeaker (probe repetitions; their arrival times are averaged).")
@click.option("--out", "out", required=True, type=click.Path(file_okay=False, path_type=Path),
              help="Recording directory to write (setup.json, rx_*.wav, truth.json, heights.json, simulate-manifest.json); "
                   "an existing one must be empty or hold only what an earlier simulate wrote.")
@handle_errors
def simulate_conference_cmd(units: int, room_text: str, rt60: float, snr: float, seed: int, layout: str,
                            sample_rate: int, max_order: int, jitter: float, rounds: int, out: Path,
                            jitter_us: float | None = None) -> None:
    """Simulate a conference network's calibration recordings (pyroomacoustics, paper 004)."""
    room = parse_room(room_text)
    jitter = resolve_jitter(jitter, jitter_us)
    check_simulation_size(units=units, sample_rate=sample_rate, room=room, rt60=rt60, rounds=rounds)
    check_simulation_folder(out)
    truth = write_simulation(out, units=units, room=room, rt60=rt60, snr=snr, seed=seed, layout=layout,
                             sample_rate=sample_rate, max_order=max_order, jitter=jitter, rounds=rounds)
    click.echo(f"simulated {out} ({units} units, {rounds} round(s), {layout}, room {room_text}, RT60 {rt60:g} s, "
               f"SNR {snr:g} dB, "
               f"image order {truth['max_order']})")


def summarise(result: Any, errors: dict[str, Any] | None, framed: Any = None) -> list[str]:
    """Lines of the summary table printed by ``selfcal pipeline`` / ``selfcal demo``.

    The calibration's own verdict (``PASS`` / ``FAIL``, from its error bars and residual test)
    comes last; a comparison with ``truth.json`` is labelled ``truth check`` (met / MISSED),
    so it is never mistaken for the calibration's verdict. A truth check that says MISSED
    turns a ``PASS`` into a ``FAIL`` (:func:`truth_missed`; the command then exits 1).
    """
    import numpy as np

    lines = [f"method             {result.method}",
             f"detections missed  {result.detections_missed} of {result.toa_matrix.size}",
             f"residual rms       {result.residual_rms * 1e6:.2f} us"]
    fit = result.fit
    if fit is not None:
        scale = fit.scale
        detail = (f"residual scale {scale:.3g} of the noise model (limit {fit.scale_limit:.3g}), "
                  if scale is not None else "")
        lines.append(f"residual test      {detail}chi2 {fit.chi2:.4g} on {fit.dof} dof "
                     f"(timing noise {fit.noise * 1e6:.3g} us): {'ok' if fit.passed else 'REJECTED'}")
    outl = result.outliers
    if outl:
        worst = max(outl, key=lambda o: abs(o.z))
        lines.append(f"outliers           {len(outl)} detection(s) excluded, "
                     f"{sum(o.redetected for o in outl)} re-detected; worst microphone "
                     f"{result.receiver_names[worst.receiver]} / loudspeaker {result.sender_names[worst.sender]}, "
                     f"residual {worst.residual * 1e6:.3g} us")
    else:
        lines.append("outliers           none")
    dr, ds = result.dropped_receivers, result.dropped_senders
    lines.append("dropped units      " + ("none" if not (dr or ds) else
                                          "; ".join(x for x in (f"microphones {', '.join(dr)}" if dr else "",
                                                                f"loudspeakers {', '.join(ds)}" if ds else "") if x)))
    bars = result.error_bars
    if bars is not None:
        lines.append(f"error bars         position std max {np.nanmax(bars.position_std) * 100:.3g} cm, "
                     f"delay+onset std max {np.nanmax(bars.pair_std) * 1e6:.3g} us (1 sigma)")
    for note in result.notes:
        lines.append(f"note               {note}")
    if framed is not None:
        lines.append(f"frame              {framed.frame.message}")
        if framed.frame.known_rms is not None:
            lines.append(f"known units        RMS {framed.frame.known_rms * 100:.3g} cm between the known and the "
                         "moved positions")
    if errors is not None:
        tag = " (horizontal)" if errors["horizontal_only"] else ""
        lines += [
            f"position error{tag:13s} median {errors['position_median'] * 100:7.2f} cm   max {errors['position_max'] * 100:7.2f} cm",
            f"timing error       median {errors['timing_median'] * 1e6:7.2f} us   max {errors['timing_max'] * 1e6:7.2f} us"
            " (delay + onset of every receiver-sender pair)",
            f"delay/onset error  max {errors['delay_onset_max'] * 1e6:7.2f} us per unit (common shift removed)",
        ]
    for name, sec in result.timings.items():
        lines.append(f"time {name:13s} {sec:7.2f} s")
    if errors is not None:
        word = "met" if errors["passed"] else "MISSED"
        lines.append(f"truth check        004 requirements {word} against truth.json: position max "
                     f"{errors['position_max'] * 100:.2f} cm (<= 10 cm: {'yes' if errors['pass_position'] else 'no'}), "
                     f"timing max {errors['timing_max'] * 1e6:.2f} us "
                     f"(<= 58 us: {'yes' if errors['pass_timing'] else 'no'})")
    verdict = result.verdict
    missed = errors is not None and not errors["passed"]
    if verdict is not None:
        if verdict.passed and missed:  # never a PASS under a truth check that says MISSED
            lines.append("FAIL: the truth check says the 004 requirements were MISSED although the calibration's "
                         f"own error bars meet them (position std max {verdict.position_std_max * 100:.3g} cm, "
                         f"delay+onset std max {verdict.timing_std_max * 1e6:.3g} us): the error bars are not "
                         "trustworthy here (a wrong basin, a bias common to the detections, or a wrong speed of "
                         "sound)")
        elif verdict.passed:
            lines.append(f"PASS: 004 requirements met by the calibration's own error bars (position std max "
                         f"{verdict.position_std_max * 100:.3g} cm <= 5 cm, delay+onset std max "
                         f"{verdict.timing_std_max * 1e6:.3g} us <= 29 us: 10 cm / 58 us at 2 sigma)")
        else:
            for reason in verdict.reasons:
                lines.append(f"FAIL: {reason}")
    return lines


def read_truth(directory: Path) -> dict[str, Any] | None:
    """``directory/truth.json`` (a simulation's ground truth) validated, or None when absent.

    Raises
    ------
    InputError
        Not an object, a key of the scoring missing, non-numeric / non-finite / overflowing
        values, positions that are not (n, 2) or (n, 3), offsets not one per unit.
    """
    import numpy as np

    from .._checks import check_magnitude, non_number_leaf
    from ..errors import InputError
    from ..io import read_json

    path = directory / "truth.json"
    if not path.is_file():
        return None
    truth = read_json(path, "truth.json")
    if not isinstance(truth, dict):
        raise InputError("truth.json: expected an object with receivers, senders, receiver_delays, sender_onsets")
    shapes = {"receivers": 2, "senders": 2, "receiver_delays": 1, "sender_onsets": 1}
    for key, ndim in shapes.items():
        if key not in truth:
            raise InputError(f"truth.json: field '{key}' is missing")
        bad = non_number_leaf(truth[key])
        if bad is not None:
            raise InputError(f"truth.json: field '{key}' must hold numbers, found {bad}")
        try:
            a = np.asarray(truth[key], dtype=float)
        except (TypeError, ValueError):
            raise InputError(f"truth.json: field '{key}' is ragged or not numeric") from None
        if a.ndim != ndim or (ndim == 2 and a.shape[1] not in (2, 3)) or not np.isfinite(a).all():
            raise InputError(f"truth.json: field '{key}' must be {'n x 3 positions' if ndim == 2 else 'n numbers'}"
                             f", finite; got shape {a.shape}")
        check_magnitude(a, f"truth.json: field '{key}'")
    if len(truth["receivers"]) != len(truth["receiver_delays"]) or len(truth["senders"]) != len(truth["sender_onsets"]):
        raise InputError("truth.json: one receiver_delay per receiver and one sender_onset per sender are needed")
    return truth


def pipeline_errors(result: Any, directory: Path, truth: dict[str, Any] | None = None) -> dict[str, Any] | None:
    """Errors against ``directory/truth.json`` when it exists (with the truth attached)."""
    from ..acoustics.pipeline import truth_errors
    from ..errors import InputError

    truth = read_truth(directory) if truth is None else truth
    if truth is None:
        return None
    if (len(truth["receivers"]), len(truth["senders"])) != (len(result.receivers), len(result.sources)):
        raise InputError(f"truth.json: {len(truth['receivers'])} receivers and {len(truth['senders'])} senders, "
                         f"but the recording has {len(result.receivers)} and {len(result.sources)}")
    err = truth_errors(result, truth)
    err["true_receivers"] = truth["receivers"]
    err["true_senders"] = truth["senders"]
    return err


@main.command("pipeline")
@click.argument("directory", type=click.Path(path_type=Path))
@click.option("--out", "out", required=True, type=click.Path(dir_okay=False, path_type=Path), help="RESULT.json")
@click.option("--plot", "plot", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="map.png: estimated (and true) positions with 95 % ellipses.")
@click.option("--report", "report", type=click.Path(path_type=Path), default=None,
              help="report.html: one self-contained HTML report (map, per-unit table, residuals, outliers, verdict); "
                   "a path not ending in .html is a folder for report.html, map.png, timing.png, report.json.")
@click.option("--heights", "heights", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help='Known heights JSON {"receivers": [...], "senders": [...]} (m): 2-D + heights. '
                   "Default with --dim auto: the recording's own heights.json when it has one.")
@click.option("--dim", "dim", type=click.Choice(["auto", "2", "3"]), default="auto", show_default=True,
              help="auto: 3-D unless the layout is near-planar (then 2-D).")
@click.option("--known", "known", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="CSV name,x,y,z[,std] of units with known positions (a unit name = its microphone; "
                   "r<i> / s<j> = microphone i / loudspeaker j, 0-based): the result, map and report are "
                   "moved onto them (rigid motion; the fit is unchanged).")
@click.option("--frame", "frame", default=None, metavar="origin=A,x=B,xy=C[,z=D]",
              help="Frame by reference units: A at the origin, B on +x, C in the xy half-plane (y>0), "
                   "D above (z>0).")
@click.option("--seed", type=SEED, default=0, show_default=True, help="Seed of the solver's random starts.")
@jitter_options(None, what="in the residual test's timing noise (default: setup.json's declared "
                           "clock_jitter, else 0)")
@click.option("--temperature", type=TEMPERATURE_C, default=None,
              help="Air temperature, degrees C: speed of sound c = 331.4 + 0.6 T + 0.0124 RH (overrides setup.json).")
@click.option("--humidity", type=HUMIDITY_PCT, default=None, help="Relative humidity, % (with --temperature; default 0).")
@click.option("--speed-of-sound", "speed", type=SPEED_OF_SOUND, default=None, help="m/s (overrides setup.json).")
@csv_option
@handle_errors
def pipeline_cmd(directory: Path, out: Path, plot: Path | None, report: Path | None, heights: Path | None,
                 dim: str, seed: int, jitter: float | None, temperature: float | None = None,
                 humidity: float | None = None, speed: float | None = None, jitter_us: float | None = None,
                 csv_out: Path | None = None, known: Path | None = None, frame: str | None = None) -> None:
    """Recordings -> arrival times -> delays -> positions (paper 004's three stages).

    Exits with status 1 and ``FAIL:`` lines when the calibration fails its residual test or
    its error bars miss paper 004's requirements (``PipelineResult.failed``); its files are
    written all the same (committed together, before the exit).
    """
    if _pipeline_outputs(directory, out, plot, report, heights, dim, seed, jitter, temperature, humidity, speed,
                         jitter_us, csv_out, known, frame):
        raise SystemExit(1)


@all_or_nothing
def _pipeline_outputs(directory: Path, out: Path, plot: Path | None, report: Path | None, heights: Path | None,
                      dim: str, seed: int, jitter: float | None, temperature: float | None, humidity: float | None,
                      speed: float | None, jitter_us: float | None, csv_out: Path | None,
                      known: Path | None = None, frame: str | None = None) -> bool:
    """Run the pipeline and stage every output; True when the calibration failed (exit 1)."""
    from ..acoustics.pipeline import run_pipeline
    from ..acoustics.recording import speed_from_air
    from ..errors import InputError, Status
    from ..io import write_json
    from ..plotting.conference import plot_map, plot_timing
    from ._common import enrich_payload, write_nodes_csv

    jitter = resolve_jitter(jitter, jitter_us)
    if temperature is not None:
        if speed is not None:
            raise InputError("give either --temperature or --speed-of-sound, not both")
        if not -40 <= temperature <= 60 or (humidity is not None and not 0 <= humidity <= 100):
            raise InputError("--temperature must be in [-40, 60] C and --humidity in [0, 100] %")
        speed = speed_from_air(temperature, humidity or 0.0)
    elif humidity is not None:
        raise InputError("--humidity needs --temperature")
    truth = read_truth(directory) if directory.is_dir() else None  # validated before the (slow) run
    if known is not None and frame is not None:
        raise InputError("--known and --frame are exclusive (known positions already define the frame)")
    if known is not None:
        from ..toa.frame.frame import read_known_csv

        read_known_csv(known, 2 if dim == "2" else 3, partial=False)  # validated before the (slow) run
    if frame is not None:
        from ..toa.frame.frame import parse_frame

        parse_frame(frame)
    own = directory / "heights.json" if directory.is_dir() else None
    if heights is None and own is not None and own.is_file():
        if dim == "auto":  # an explicit --dim asks for the blind model
            heights = own
            click.echo(f"heights            {own} (the recording's own known heights: horizontal positions "
                       "solved, z given; --heights FILE for others, --dim 2 / 3 for a blind fit)")
        else:
            click.echo(f"heights            {own} not used: --dim {dim} asks for the blind {dim}-D fit")
    result = run_pipeline(directory, dim=dim if dim == "auto" else int(dim), heights=heights, rng=seed,
                          jitter=jitter, speed_of_sound=speed)
    framed = _room_frame(result, known, frame) if (known is not None or frame is not None) else None
    if framed is not None:
        result = framed.result
    errors = pipeline_errors(result, directory, truth)
    room = truth.get("room") if truth is not None else None  # the simulation's room: the map's outline
    payload = enrich_payload(result.to_dict(), units={"positions": "m", "offsets": "s", "residual_rms": "s",
                                                      "toa_matrix": "s", "covariances": "m^2"})
    if framed is not None:
        payload["frame"] = framed.frame.to_dict()
    if errors is not None:
        payload["errors"] = {k: v for k, v in errors.items() if not k.startswith(("aligned_", "true_"))}
    if csv_out is not None:
        write_nodes_csv(csv_out, payload, [("receiver", "receivers", "receiver_names"),
                                           ("source", "sources", "sender_names")])
    if report is not None:
        from ..acoustics.report import write_html_report

        lines = summarise(result, errors, framed)
        if report.suffix.lower() in (".html", ".htm"):
            if report.exists() and not report.is_file():
                raise InputError(f"{report}: exists and is not a regular file; choose another --report")
            write_html_report(result, report, errors, summary=lines)
        else:
            plot_map(result, report / "map.png", errors, room=room)
            plot_timing(result, report / "timing.png", errors)
            write_json(report / "report.json", {"summary": lines, **payload})
            write_html_report(result, report / "report.html", errors, summary=lines)
    if plot is not None:
        plot_map(result, plot, errors, room=room)
    if truth_missed(errors):  # the JSON's verdict agrees with the console's FAIL and the exit status
        payload.update(failed=True, success=False, status=int(Status.FAILED_TEST),
                       message="the truth check says the 004 requirements were MISSED")
    write_json(out, payload)
    for line in summarise(result, errors, framed):
        click.echo(line)
    return bool(result.failed or truth_missed(errors))


def truth_missed(errors: dict[str, Any] | None) -> bool:
    """True when a ``truth.json`` comparison (:func:`pipeline_errors`) says 004's requirements were missed."""
    return errors is not None and not errors["passed"]


def _room_frame(result: Any, known: Path | None, frame: str | None) -> Any:
    """The pipeline's result moved into the room's frame (``--known`` / ``--frame``).

    Unit names name microphones (a unit's microphone and loudspeaker share its name);
    ``r<i>`` / ``s<j>`` name microphone i / loudspeaker j (0-based).
    """
    import numpy as np

    from ..toa.frame.frame import align_known, apply_frame, parse_known, read_known_csv

    rn = tuple(result.receiver_names)
    sn = tuple(n if n not in rn else f"\0{n}" for n in result.sender_names)  # shared names: the microphone
    I, d = np.asarray(result.receivers).shape
    J = np.asarray(result.sources).shape[0]
    if known is not None:
        nodes = parse_known(read_known_csv(known, d, partial=False), I, J, d, receiver_names=rn, source_names=sn)
        return align_known(result, nodes)
    return apply_frame(result, str(frame), receiver_names=rn, source_names=sn)

