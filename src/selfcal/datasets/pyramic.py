"""Loader for the Pyramic far-field TDOA recordings (EPFL, MIT licence).

The Pyramic calibration recordings hold, for each loudspeaker (each at its own fixed
elevation) and 180 array azimuths (a turntable in 2-degree steps), the GCC-PHAT delays of
microphones 1..47 against microphone 0 (seconds), the unit source directions, the
hand-measured microphone positions and the speed of sound.

What one speaker and several speakers determine (paper 000, Theorem 2)
----------------------------------------------------------------------
One speaker's 180 directions share one elevation ``e``: they lie on the quadratic cone
``n_x^2 + n_y^2 = cot^2(e) n_z^2`` about the turntable axis, so the blind problem has a
one-parameter family of solutions (the positions up to a linear stretch along the axis)
and is refused as ``[cone]``. A quadric ``n^T Omega n = 0`` containing two such circles at
elevations ``e_1``, ``e_2`` must be ``diag(a, a, f)`` with ``a cos^2 e + f sin^2 e = 0`` for
both, which has a non-zero solution only when ``|tan e_1| = |tan e_2|``. So speakers at
different absolute elevations (in the array frame) break the cone and the joint matrix
(all speakers' columns side by side, one offset per column) determines the geometry up to
a rotation; speakers at ``+e`` and ``-e`` do not. The loader therefore joins every speaker
it is given: a file with several speakers, several files, or a folder of them.

Layouts read
------------
* one speaker (the layout of ``shared/data/pyramic``): ``delays`` [n_mic - 1][n_src],
  ``sources`` [n_src][3], optional ``speaker`` (an id, or one id per source);
* several speakers in one file (the layout of the upstream ``pyramic_tdoa.json`` of the
  Pyramic dataset): ``delays`` [n_mic - 1][n_src][n_spk] and ``sources`` [3][n_src][n_spk]
  (or [n_src][n_spk][3]); the coordinate axis is the one of length 3 along which every
  vector has unit norm;
* common keys: ``microphones`` [3][n_mic] (x, y, z lists, metres), ``sound_speed_mps``,
  ``mic_ref`` (default 0).

Variants read (each else refused in one line): delays ``null`` / ``NaN`` (missing); a source
(column) with no delay at all, e.g. a turntable position one speaker skipped in the upstream
layout, is dropped with its direction (``PyramicData.skipped``); speakers with different
numbers of turntable positions, one file each (a single file holds one rectangular
[mic][source][speaker] array: pad with ``null``); ``microphones`` absent (no reference
positions: the number of microphones is that of the delays plus the reference);
``sources`` absent (no elevations, no ``--directions sources``); ``mic_ref`` absent (0);
``sound_speed_mps`` absent (``speed`` / ``--speed`` then required).
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from .._checks import MAX_ABS_ENTRY, check_magnitude, entry, non_number_leaf
from ..acoustics.recording import MAX_SPEED_OF_SOUND
from ..errors import InputError
from ..io import read_json

__all__ = ["PyramicData", "load_pyramic", "pyramic_from_dict", "join_pyramic", "simulate_pyramic"]

Array = NDArray[np.float64]
_PATTERN = "pyramic_tdoa*.json"
PathLike = str | os.PathLike[str]


@dataclass(frozen=True)
class PyramicData:
    """Pyramic far-field TDOA data of one or several speakers (columns side by side).

    Attributes
    ----------
    D : (n_mic, k) far-field relative-distance matrix in metres, ``D_ij = c * delay`` with a
        zero reference row (microphone ``mic_ref``), so that ``D_ij ~ z_i . n_j + C_j`` with
        ``z_i = m_i - m_ref`` and ``n_j = -u_j`` (C_j = 0 up to noise). k = 180 per speaker.
    delays : (n_mic - 1, k) raw TDOA in seconds (microphones other than ``mic_ref``).
    sources : (k, 3) unit source directions u_j (array frame).
    microphones : (n_mic, 3) hand-measured microphone positions (metres).
    speed : speed of sound (m/s; the first file's when files differ, see ``column_speed``).
    mic_ref : reference microphone.
    speaker : (k,) speaker id of each column.
    column_speed : (k,) speed of sound used for each column (m/s).
    skipped : number of (source, speaker) columns of the file(s) dropped because they hold no
        delay at all.

    ``microphones`` is NaN when the file gives none, ``sources`` when it gives no directions
    (:attr:`has_microphones`, :attr:`has_sources`).
    """

    D: Array
    delays: Array
    sources: Array
    microphones: Array
    speed: float
    mic_ref: int = 0
    speaker: NDArray[np.int64] | None = None
    column_speed: Array | None = None
    skipped: int = 0

    @property
    def has_microphones(self) -> bool:
        """Whether the file(s) gave the hand-measured microphone positions."""
        return bool(np.isfinite(self.microphones).all())

    @property
    def has_sources(self) -> bool:
        """Whether the file(s) gave the source directions."""
        return bool(np.isfinite(self.sources).all())

    @property
    def positions(self) -> Array:
        """(n_mic, 3) reference positions relative to the reference microphone (the z_i of the model)."""
        return self.microphones - self.microphones[self.mic_ref]

    @property
    def directions(self) -> Array:
        """(k, 3) model directions ``n_j = -u_j``."""
        return -self.sources

    @property
    def speakers(self) -> list[int]:
        """Speaker ids in the order of their first column."""
        ids = np.zeros(self.D.shape[1], dtype=np.int64) if self.speaker is None else self.speaker
        return [int(s) for s in dict.fromkeys(ids.tolist())]

    def elevations(self) -> dict[int, float]:
        """Mean source elevation of each speaker (degrees above the array's xy plane)."""
        ids = np.zeros(self.D.shape[1], dtype=np.int64) if self.speaker is None else self.speaker
        el = np.degrees(np.arcsin(np.clip(self.sources[:, 2], -1.0, 1.0)))  # NaN without sources
        return {s: float(np.mean(el[ids == s])) for s in self.speakers}


@entry(path="paths", speed="positive?")
def load_pyramic(path: PathLike | Sequence[PathLike], *, speed: float | None = None) -> PyramicData:
    """Read Pyramic TDOA data: a JSON file, a folder of them, or several files, joined.

    Parameters
    ----------
    path : a JSON file (one or several speakers), a folder (every ``pyramic_tdoa*.json``
        in it, sorted by name), or a sequence of files / folders. All speakers found are
        joined column-wise (:func:`join_pyramic`): together they can break the cone
        ambiguity that each speaker alone has (see the module docstring).
    speed : speed of sound (m/s) overriding every file's ``sound_speed_mps``.

    Returns
    -------
    PyramicData

    Raises
    ------
    InputError
        A key is missing, a shape is wrong, a folder holds no Pyramic file, or the files
        disagree on the microphones.

    Examples
    --------
    >>> data = load_pyramic("../shared/data/pyramic")   # doctest: +SKIP
    >>> data.D.shape, data.speakers                      # doctest: +SKIP
    ((48, 180), [0])
    """
    paths = [path] if isinstance(path, (str, os.PathLike)) else list(path)
    if not paths:
        raise InputError("load_pyramic: no file given")
    files: list[Path] = []
    for p in map(Path, paths):
        if p.is_dir():
            found = sorted(p.glob(_PATTERN))
            if not found:
                raise InputError(f"{p}: no Pyramic TDOA file ({_PATTERN}) in this folder")
            files += found
        else:
            files.append(p)
    seen = [f.resolve() for f in files]
    if len(set(seen)) < len(seen):
        dup = next(f for f in files if seen.count(f.resolve()) > 1)
        raise InputError(f"{dup}: given twice; each speaker's recording can be used once")
    parts = [pyramic_from_dict(read_json(f), label=str(f), speed=speed) for f in files]
    return join_pyramic(parts, labels=[str(f) for f in files])


def join_pyramic(parts: Sequence[PyramicData], *, labels: Sequence[str] | None = None) -> PyramicData:
    """Join Pyramic data sets of the same array column-wise (all their speakers together).

    The microphones (hand-measured positions) must agree; a part recorded against another
    reference microphone is re-referenced to the first part's ``mic_ref`` (a constant per
    column, absorbed by the column offset of the far-field model; see :func:`_rereference`);
    each part keeps its own speed of sound (``column_speed``). Speaker ids that repeat
    across parts (e.g. two files both labelled 0) are renumbered so that every part's
    speakers stay distinct.

    Parameters
    ----------
    parts : data sets from :func:`pyramic_from_dict` / :func:`load_pyramic`.
    labels : names for error messages (default ``part 0``, ``part 1``, ...).

    Raises
    ------
    InputError
        The parts disagree on the microphones.
    """
    if not parts:
        raise InputError("join_pyramic: nothing to join")
    names = list(labels) if labels is not None else [f"part {i}" for i in range(len(parts))]
    if len(parts) == 1:
        return parts[0]
    first = parts[0]
    ids: list[NDArray[np.int64]] = []
    used: set[int] = set()
    for name, p in zip(names, parts, strict=True):
        if p.microphones.shape != first.microphones.shape:
            raise InputError(f"{name}: {p.microphones.shape[0]} microphones but {names[0]} has "
                             f"{first.microphones.shape[0]}; only recordings of the same array can be calibrated "
                             "together")
        if p.has_microphones and first.has_microphones and not np.allclose(
                p.microphones, first.microphones, atol=1e-9, rtol=0.0):
            raise InputError(f"{name}: its microphones differ from those of {names[0]}; only recordings of the "
                             "same array can be calibrated together")
        sp = np.zeros(p.D.shape[1], dtype=np.int64) if p.speaker is None else p.speaker.copy()
        if used & set(sp.tolist()):
            shift = max(used) + 1 - int(sp.min())
            sp = sp + shift
        used |= set(sp.tolist())
        ids.append(sp)
    speeds = [np.full(p.D.shape[1], p.speed) if p.column_speed is None else p.column_speed for p in parts]
    mics = next((p.microphones for p in parts if p.has_microphones), first.microphones)
    ref = first.mic_ref
    Ds = [_rereference(p.D, ref) if p.mic_ref != ref else p.D for p in parts]
    return PyramicData(
        D=np.concatenate(Ds, axis=1),
        delays=np.concatenate([np.delete(Dp, ref, axis=0) / sp for Dp, sp in zip(Ds, speeds, strict=True)], axis=1),
        sources=np.concatenate([p.sources for p in parts], axis=0),
        microphones=mics.copy(),
        speed=first.speed,
        mic_ref=first.mic_ref,
        speaker=np.concatenate(ids),
        column_speed=np.concatenate(speeds),
        skipped=sum(p.skipped for p in parts),
    )


def _rereference(D: Array, ref: int) -> Array:
    """Columns of ``D`` against microphone ``ref``: ``D_ij - D_ref,j`` where that delay is observed.

    A recording against another reference microphone differs from one against ``ref`` by one
    constant per column, which the far-field model's column offset ``C_j`` absorbs; so files
    with different ``mic_ref`` can be joined. A column whose delay at ``ref`` is missing keeps
    its own reference (still the same model, with another ``C_j``)."""
    out = D.copy()
    ok = np.isfinite(D[ref])
    out[:, ok] = D[:, ok] - D[ref, ok]
    return out


def _flatten_speakers(p: str, delays: Array, sources: Array | None) -> tuple[Array, Array, int]:
    """(n_mic-1, n_src, n_spk) delays and their sources -> speaker-major (n_mic-1, n_spk n_src), (k, 3)."""
    n_spk = delays.shape[2]
    flat_d = delays.transpose(0, 2, 1).reshape(delays.shape[0], -1)
    if sources is None:  # no directions given: speaker-major columns, directions unknown
        return flat_d, np.full((flat_d.shape[1], 3), np.nan), n_spk
    if sources.ndim != 3:
        raise InputError(f"{p}: 'delays' has 3 axes (microphone, source, speaker) but 'sources' has shape "
                         f"{sources.shape}; expected [3][n_src][n_spk] or [n_src][n_spk][3]")
    axis = None
    for a in range(3):
        if sources.shape[a] == 3:
            nrm = np.linalg.norm(np.moveaxis(sources, a, -1), axis=-1)
            # unit vectors (NaN only where a source is missing: its column is dropped later)
            if np.all(np.isnan(nrm) | (np.abs(nrm - 1.0) < 1e-3)) and np.isfinite(nrm).any():
                axis = a
                break
    if axis is None:
        raise InputError(f"{p}: 'sources' (shape {sources.shape}) has no axis of unit (x, y, z) vectors")
    S = np.moveaxis(sources, axis, -1)  # (n_src, n_spk, 3) in the delays' order
    if S.shape[:2] != delays.shape[1:]:
        raise InputError(f"{p}: 'sources' {sources.shape} do not match 'delays' {delays.shape} "
                         "(expected one direction per source and speaker)")
    flat_s = S.transpose(1, 0, 2).reshape(-1, 3)
    return flat_d, flat_s, n_spk


def pyramic_from_dict(obj: object, *, label: str = "Pyramic JSON", speed: float | None = None) -> PyramicData:
    """Build :class:`PyramicData` from a parsed Pyramic calibration JSON (one or several speakers).

    Keys: ``delays`` [n_mic - 1][n_src] or, several speakers, [n_mic - 1][n_src][n_spk]
    (seconds, microphone i against ``mic_ref``, the reference row omitted); ``sources``
    [n_src][3] or [3][n_src][n_spk] (unit directions); ``microphones`` [3][n_mic] (x, y, z
    lists, metres); ``sound_speed_mps``; ``mic_ref`` (default 0); ``speaker`` (optional id).
    The reference microphone's row of zeros is re-inserted at ``mic_ref``, so row i of
    ``D`` is microphone i; several speakers are laid out speaker after speaker.

    Parameters
    ----------
    obj : the parsed JSON object.
    label : name used in error messages.
    speed : propagation speed (m/s) overriding ``sound_speed_mps`` (None: the file's).

    Raises
    ------
    InputError
        A key is missing, not numeric, or a shape is inconsistent.
    """
    p = label
    if not isinstance(obj, dict):
        raise InputError(f"{p}: not a Pyramic TDOA file (expected a JSON object with 'delays', 'sources', "
                         "'microphones', 'sound_speed_mps')")
    if "delays" not in obj:
        raise InputError(f"{p}: not a Pyramic TDOA file (no 'delays'; expected 'delays', 'sources', "
                         "'microphones', 'sound_speed_mps')")
    try:
        delays = _numeric(obj["delays"], p, "delays")
        sources = None if obj.get("sources") is None else _numeric(obj["sources"], p, "sources")
        mics = None if obj.get("microphones") is None else _numeric(obj["microphones"], p, "microphones")
        raw_speed = obj.get("sound_speed_mps")
        ref_raw = obj.get("mic_ref", 0)
        for key, v in (("sound_speed_mps", raw_speed), ("mic_ref", ref_raw)):
            if isinstance(v, bool) or not (v is None or isinstance(v, (int, float))):
                raise InputError(f"{p}: '{key}' must be a number, got {v!r}")
        file_speed = float(raw_speed) if raw_speed is not None else float("nan")
        ref = int(ref_raw)
        spk_raw = obj.get("speaker", None)
        if spk_raw is not None:
            bad = non_number_leaf(spk_raw)
            ints = np.asarray(spk_raw, dtype=float) if bad is None else None
            if ints is None or not np.all(np.isfinite(ints)) or np.any(ints != np.round(ints)) \
                    or np.any(np.abs(ints) > 2**53):
                raise InputError(f"{p}: 'speaker' must be integer ids, got {bad or repr(spk_raw)[:40]}")
        spk = None if spk_raw is None else np.asarray(spk_raw, dtype=np.int64)
    except InputError:
        raise
    except (KeyError, TypeError, ValueError, OverflowError) as exc:
        raise InputError(f"{p}: not a Pyramic TDOA file ({exc})") from None
    if ref != ref_raw:
        raise InputError(f"{p}: mic_ref must be an integer, got {ref_raw!r}")
    if delays.ndim not in (2, 3) or delays.shape[0] < 1:
        raise InputError(f"{p}: 'delays' must be [n_mic - 1][n_src] or [n_mic - 1][n_src][n_spk], got shape "
                         f"{delays.shape}")
    if mics is None:  # no hand-measured positions: the array size from the delays
        mics = np.full((3, delays.shape[0] + 1), np.nan)
    if mics.ndim != 2 or mics.shape[0] != 3:
        raise InputError(f"{p}: 'microphones' must be 3 lists (x, y, z), got shape {mics.shape}")
    mics = mics.T
    n_mic = mics.shape[0]
    n_spk = 1
    if delays.ndim == 3:
        if delays.shape[0] != n_mic - 1:
            raise InputError(f"{p}: 'delays' has shape {delays.shape}, expected ({n_mic - 1}, n_src, n_spk) for "
                             f"{n_mic} microphones")
        delays, sources, n_spk = _flatten_speakers(p, delays, sources)
    if sources is None:
        sources = np.full((delays.shape[1], 3), np.nan)
    if sources.ndim != 2 or sources.shape[1] != 3:
        raise InputError(f"{p}: 'sources' must be a list of [x, y, z] directions, got shape {sources.shape}")
    n_src = sources.shape[0]
    if delays.shape != (n_mic - 1, n_src):
        hint = " (transposed?)" if delays.shape == (n_src, n_mic - 1) else ""
        raise InputError(f"{p}: 'delays' has shape {delays.shape}, expected ({n_mic - 1}, {n_src}) for {n_mic} "
                         f"microphones and {n_src} sources{hint}")
    if not 0 <= ref < n_mic:
        raise InputError(f"{p}: mic_ref = {ref} is not a microphone index (0..{n_mic - 1})")
    c = file_speed if speed is None else float(speed)
    if speed is None and raw_speed is None:
        raise InputError(f"{p}: no 'sound_speed_mps' in the file; give the speed of sound (--speed, m/s)")
    if not np.isfinite(c) or c <= 0:
        raise InputError(f"{p}: the speed of sound must be a positive number (sound_speed_mps or --speed), got {c}")
    if np.isinf(delays).any():
        raise InputError(f"{p}: 'delays' must be finite or null / NaN (missing)")
    if (~np.isfinite(mics)).any() and not np.isnan(mics).all():
        raise InputError(f"{p}: 'microphones' must be finite (or absent)")
    check_magnitude(mics, f"{p}: 'microphones'")
    if c > MAX_SPEED_OF_SOUND:
        raise InputError(f"{p}: the speed of sound {c:g} m/s exceeds the physical bound {MAX_SPEED_OF_SOUND:g} m/s "
                         "of any medium; is it in m/s?")
    per = n_src // n_spk
    if spk is None:
        speaker = np.repeat(np.arange(n_spk, dtype=np.int64), per)
    elif spk.ndim == 0:
        speaker = np.repeat(int(spk) + np.arange(n_spk, dtype=np.int64), per)
    elif spk.shape == (n_spk,):
        speaker = np.repeat(spk, per)
    elif spk.shape == (n_src,):
        speaker = spk
    else:
        raise InputError(f"{p}: 'speaker' must be one id, one per speaker or one per source; got shape {spk.shape}")
    # a column without any delay (a source / speaker pair not recorded) carries nothing: dropped
    keep = np.isfinite(delays).any(axis=0)
    if not keep.any():
        raise InputError(f"{p}: 'delays' holds no number (all null / NaN)")
    bad_src = keep & ~np.isfinite(sources).all(axis=1)
    if bad_src.any() and np.isfinite(sources).any():
        j = int(np.flatnonzero(bad_src)[0])
        raise InputError(f"{p}: source {j} has delays but no finite direction in 'sources'")
    delays, sources, speaker = delays[:, keep], sources[keep], speaker[keep]
    D = np.insert(delays * c, ref, 0.0, axis=0)
    top = float(np.nanmax(np.abs(D)))
    if 0 < top < 1.0 / MAX_ABS_ENTRY:  # squares underflow: the least-squares sums lose every digit
        raise InputError(f"{p}: the relative distances (speed x delays) are at most {top:.3g} m, where the "
                         "least-squares sums underflow double precision; are the delays or the speed in the wrong unit?")
    return PyramicData(D=D, delays=delays, sources=sources, microphones=mics, speed=c,
                       mic_ref=ref, speaker=speaker, column_speed=np.full(delays.shape[1], c),
                       skipped=int((~keep).sum()))


def _numeric(value: object, p: str, key: str) -> Array:
    """A nested list of numbers (``null`` = NaN) as a float array; ragged or non-numeric: InputError."""
    bad = non_number_leaf(value)
    if bad is not None:
        raise InputError(f"{p}: '{key}' must hold numbers (or null), found {bad}")
    try:
        arr = np.asarray(value, dtype=float)
    except ValueError as exc:
        if "inhomogeneous" in str(exc) or "sequence" in str(exc):
            raise InputError(
                f"{p}: '{key}' is ragged (lists of different lengths). In one file every speaker needs the same "
                "turntable positions: pad the missing ones with null, or give each speaker its own file") from None
        raise InputError(f"{p}: '{key}' is not numeric ({exc})") from None
    except TypeError as exc:
        raise InputError(f"{p}: '{key}' is not numeric ({exc})") from None
    return arr


def simulate_pyramic(
    microphones: Array,
    elevations_deg: Sequence[float],
    *,
    speed: float = 345.08736,
    azimuth_step_deg: float = 2.0,
    noise_std: float = 0.87e-3,
    sample_rate: float | None = 192000.0,
    gross: int = 2,
    mic_ref: int = 0,
    rng: np.random.Generator | int | None = None,
) -> list[dict[str, object]]:
    """Simulated Pyramic-like recordings, one JSON object per speaker (the shared file's layout).

    Each speaker sits at one elevation (array frame) and the array turns through
    ``360 / azimuth_step_deg`` azimuths (a random common start per speaker). Delays are the
    far-field model ``-(m_i - m_ref) . u / c`` plus Gaussian noise of ``noise_std`` metres,
    rounded to whole samples of ``sample_rate`` (the GCC-PHAT peak without interpolation, as
    in the real recording: steps of c / 192 kHz = 1.8 mm, quantisation std 0.52 mm; with the
    default Gaussian part the total is the 1.0 mm residual of the shared speaker's fit with
    its own directions), and ``gross`` entries per speaker replaced by a wrong peak (0.1 to
    0.5 m off, like the real file's two).

    Parameters
    ----------
    microphones : (n_mic, 3) true positions (metres), e.g. ``load_pyramic(...).microphones``.
    elevations_deg : one elevation per speaker (degrees above the xy plane).
    speed : speed of sound (m/s); azimuth_step_deg : turntable step (degrees).
    noise_std : Gaussian delay noise (metres); sample_rate : quantisation (Hz; None = none).
    gross : gross errors per speaker; mic_ref : reference microphone; rng : seed / generator.

    Returns
    -------
    list of dicts with ``delays``, ``sources``, ``microphones``, ``sound_speed_mps``,
    ``mic_ref``, ``speaker`` -- each readable by :func:`pyramic_from_dict`.

    Examples
    --------
    >>> import numpy as np
    >>> mics = np.random.default_rng(0).uniform(-0.1, 0.1, (8, 3))
    >>> files = simulate_pyramic(mics, [13.0, -15.0], azimuth_step_deg=10.0, rng=1)
    >>> data = join_pyramic([pyramic_from_dict(f) for f in files])
    >>> data.D.shape, data.speakers
    ((8, 72), [0, 1])
    """
    gen = np.random.default_rng(rng)
    M = np.asarray(microphones, dtype=float)
    out: list[dict[str, object]] = []
    az = np.radians(np.arange(0.0, 360.0, azimuth_step_deg))
    for s, e_deg in enumerate(elevations_deg):
        e = np.radians(float(e_deg))
        a = az + gen.uniform(0.0, 2.0 * np.pi)
        U = np.column_stack([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.full(a.size, np.sin(e))])
        # each TDOA against the reference is one cross-correlation peak: noise and rounding per entry
        tau = (-(M - M[mic_ref]) @ U.T + noise_std * gen.standard_normal((len(M), a.size))) / speed
        if sample_rate is not None:
            tau = np.round(tau * sample_rate) / sample_rate
        tau = np.delete(tau, mic_ref, axis=0)
        for _ in range(int(gross)):
            i, j = gen.integers(tau.shape[0]), gen.integers(tau.shape[1])
            tau[i, j] += gen.choice([-1.0, 1.0]) * gen.uniform(0.1, 0.5) / speed
        out.append({"delays": tau.tolist(), "sources": U.tolist(), "microphones": M.T.tolist(),
                    "sound_speed_mps": float(speed), "mic_ref": int(mic_ref), "speaker": s})
    return out
