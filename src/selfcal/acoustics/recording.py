"""The recording format: a directory with ``setup.json`` and one WAV per receiver.

Format (see ``docs/recording_format.md``)::

    DIR/setup.json
        sample_rate      Hz (positive integer)
        speed_of_sound   m/s (optional, default 343; or from temperature / humidity)
        temperature      degrees C (optional): c = 331.4 + 0.6 T + 0.0124 RH (pyroomacoustics)
        humidity         relative humidity, % (optional, with temperature; default 0)
        unit_offsets     {name: m} (optional): known distance from receiver <name> to sender <name>
        room             [L, W, H] m (optional): the room's size, for the plausibility check of the result
        receivers        list of names; receiver i is DIR/rx_<name>.wav
        senders          list of names
        probe            {"type": "chirp", "f0": Hz, "f1": Hz, "duration": s} or {"wav": "probe.wav"}
        events           list of {"sender": name, "time": s}: nominal emission times
    DIR/rx_<name>.wav    mono, 8/16/24/32-bit integer PCM or 32/64-bit float, all on one clock (t = 0 at sample 0)

The true emission of an event happens at ``time + onset(sender)`` and receiver ``i``
time-stamps the sound ``delay(i)`` late, so the direct path of event ``e`` from sender
``j`` reaches receiver ``i`` at sample time ``time_e + onset_j + |r_i - s_j| / c + delay_i``
(004 eq. 3.1). Every problem in a directory is refused with an :class:`InputError`
whose message starts with the file name and names the field.
"""

from __future__ import annotations

import io as _io
import math
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .._checks import entry, guard_recording_setup
from ..errors import InputError
from ..io import atomic_write_bytes, write_json
from ..io.wav import (  # re-exported: the recording format reads its WAVs with them
    CLIP_RUN,
    read_wav,
)
from .probe import Probe, probe_from_spec

__all__ = [
    "Setup",
    "Recording",
    "read_setup",
    "read_wav",
    "write_wav",
    "load_recording",
    "write_recording",
    "CLIP_RUN",
    "speed_from_air",
]

#: Upper bound on the speed of sound in any condensed phase, c_max = alpha (m_e / 2 m_p)^(1/2) c
#: ~ 36.1 km/s (Trachenko et al., Sci. Adv. 6, eabc8662, 2020); a larger value is a unit mistake.
MAX_SPEED_OF_SOUND = 36_100.0
_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]*$")


@dataclass(frozen=True)
class Setup:
    """Parsed and validated ``setup.json``.

    Attributes
    ----------
    sample_rate : float
        Hz.
    speed_of_sound : float
        m/s.
    receivers, senders : tuple of str
        Names, in file order (rows / columns of every matrix).
    probe : dict
        The probe description as given.
    event_senders : (E,) int array
        Index into ``senders`` of each event.
    event_times : (E,) float array
        Nominal emission times, seconds.
    clock_jitter : float
        Declared synchronisation jitter of the units' clocks, std per (receiver, event) in
        seconds (a specification of the equipment, optional field; 0 = not declared). It
        enters the residual test's timing noise.
    temperature, humidity : float or None
        Air temperature (degrees C) and relative humidity (%) when declared; ``speed_of_sound``
        then comes from them (:func:`speed_from_air`).
    unit_offsets : dict
        ``{name: m}``: known distance between receiver ``name`` and sender ``name`` (a unit's
        microphone and loudspeaker), used as scale constraints.
    room : tuple of float or None
        Declared room size ``(L, W, H)``, m (optional field): a result larger than the room
        can hold is failed (:func:`selfcal.acoustics.plausibility.extent_reason`).
    """

    sample_rate: float
    speed_of_sound: float
    receivers: tuple[str, ...]
    senders: tuple[str, ...]
    probe: dict[str, Any]
    event_senders: NDArray[np.int64]
    event_times: NDArray[np.float64]
    clock_jitter: float = 0.0
    temperature: float | None = None
    humidity: float | None = None
    unit_offsets: dict[str, float] = field(default_factory=dict)
    room: tuple[float, ...] | None = None

    def to_dict(self) -> dict[str, Any]:
        """The ``setup.json`` content (JSON-safe)."""
        return {
            "sample_rate": int(self.sample_rate) if float(self.sample_rate).is_integer() else self.sample_rate,
            "speed_of_sound": self.speed_of_sound,
            "receivers": list(self.receivers),
            "senders": list(self.senders),
            "probe": self.probe,
            "events": [
                {"sender": self.senders[int(j)], "time": float(t)}
                for j, t in zip(self.event_senders, self.event_times, strict=True)
            ],
            **({"clock_jitter": self.clock_jitter} if self.clock_jitter > 0 else {}),
            **({"temperature": self.temperature} if self.temperature is not None else {}),
            **({"humidity": self.humidity} if self.humidity is not None else {}),
            **({"unit_offsets": dict(self.unit_offsets)} if self.unit_offsets else {}),
            **({"room": list(self.room)} if self.room is not None else {}),
        }


@dataclass(frozen=True)
class Recording:
    """A loaded recording directory.

    Attributes
    ----------
    setup : Setup
    probe : Probe
    signals : (I, N) float32 array
        Receiver signals on one clock, zero-padded to the longest file (full scale = 1).
    lengths : (I,) int array
        Samples actually recorded per receiver (windows beyond are "missed").
    directory : Path
    """

    setup: Setup
    probe: Probe
    signals: NDArray[np.float32]
    lengths: NDArray[np.int64]
    directory: Path = field(default_factory=Path)


def _names(raw: dict[str, Any], key: str, where: str) -> tuple[str, ...]:
    if key not in raw:
        raise InputError(f"{where}: field '{key}' is missing (a list of names)")
    val = raw[key]
    if not isinstance(val, list) or not val:
        raise InputError(f"{where}: field '{key}' must be a non-empty list of names")
    out = []
    for k, name in enumerate(val):
        if not isinstance(name, str) or not _NAME.match(name):
            raise InputError(f"{where}: field '{key}[{k}]' = {name!r} is not a valid name "
                             "(letters, digits, '_', '.', '-')")
        out.append(name)
    if len(set(out)) != len(out):
        dup = next(n for n in out if out.count(n) > 1)
        raise InputError(f"{where}: field '{key}' lists {dup!r} twice")
    return tuple(out)


def _positive(raw: dict[str, Any], key: str, where: str, default: float | None = None) -> float:
    if key not in raw:
        if default is None:
            raise InputError(f"{where}: field '{key}' is missing")
        return default
    val = raw[key]
    if isinstance(val, bool) or not isinstance(val, (int, float)) or not math.isfinite(val) or val <= 0:
        raise InputError(f"{where}: field '{key}' must be a positive number, got {val!r}")
    return float(val)


def parse_setup(raw: Any, where: str = "setup.json") -> Setup:
    """Validate the decoded JSON of ``setup.json`` and return a :class:`Setup`.

    Raises
    ------
    InputError
        Naming ``where`` and the offending field.
    """
    if not isinstance(raw, dict):
        raise InputError(f"{where}: top level must be an object with fields sample_rate, receivers, senders, probe, events")
    fs = _positive(raw, "sample_rate", where)
    if not float(fs).is_integer():
        raise InputError(f"{where}: field 'sample_rate' must be a whole number of Hz, got {fs:g}")
    temp = hum = None
    if "temperature" in raw:
        temp = raw["temperature"]
        if isinstance(temp, bool) or not isinstance(temp, (int, float)) or not math.isfinite(temp) or not -40 <= temp <= 60:
            raise InputError(f"{where}: field 'temperature' must be degrees C in [-40, 60], got {temp!r}")
        temp = float(temp)
        if "speed_of_sound" in raw:
            raise InputError(f"{where}: give either field 'speed_of_sound' or 'temperature', not both")
    if "humidity" in raw:
        hum = raw["humidity"]
        if isinstance(hum, bool) or not isinstance(hum, (int, float)) or not math.isfinite(hum) or not 0 <= hum <= 100:
            raise InputError(f"{where}: field 'humidity' must be a relative humidity in % [0, 100], got {hum!r}")
        hum = float(hum)
        if temp is None:
            raise InputError(f"{where}: field 'humidity' needs field 'temperature'")
    c = (speed_from_air(temp, hum or 0.0) if temp is not None
         else _positive(raw, "speed_of_sound", where, default=343.0))
    if c > MAX_SPEED_OF_SOUND:
        raise InputError(f"{where}: field 'speed_of_sound' = {c:g} m/s exceeds the physical bound "
                         f"{MAX_SPEED_OF_SOUND:g} m/s of any medium; is it in m/s?")
    receivers = _names(raw, "receivers", where)
    senders = _names(raw, "senders", where)
    if "probe" not in raw:
        raise InputError(f"{where}: field 'probe' is missing")
    probe = raw["probe"]
    if not isinstance(probe, dict):
        raise InputError(f"{where}: field 'probe' must be an object")
    events = raw.get("events")
    if not isinstance(events, list) or not events:
        raise InputError(f"{where}: field 'events' must be a non-empty list of {{'sender': name, 'time': s}}")
    index = {n: j for j, n in enumerate(senders)}
    ev_s, ev_t = [], []
    for k, ev in enumerate(events):
        if not isinstance(ev, dict) or "sender" not in ev or "time" not in ev:
            raise InputError(f"{where}: field 'events[{k}]' must be an object with 'sender' and 'time'")
        if ev["sender"] not in index:
            raise InputError(f"{where}: field 'events[{k}].sender' = {ev['sender']!r} is not one of 'senders'")
        t = ev["time"]
        if isinstance(t, bool) or not isinstance(t, (int, float)) or not math.isfinite(t) or t < 0:
            raise InputError(f"{where}: field 'events[{k}].time' must be a number >= 0 (seconds), got {t!r}")
        ev_s.append(index[ev["sender"]])
        ev_t.append(float(t))
    guard_recording_setup(fs, ev_t, probe, len(receivers), where)  # sizes refused before allocation
    jit = raw.get("clock_jitter", 0.0)
    if isinstance(jit, bool) or not isinstance(jit, (int, float)) or not math.isfinite(jit) or jit < 0:
        raise InputError(f"{where}: field 'clock_jitter' must be a number >= 0 (seconds), got {jit!r}")
    offs: dict[str, float] = {}
    if "unit_offsets" in raw:
        uo = raw["unit_offsets"]
        if not isinstance(uo, dict):
            raise InputError(f"{where}: field 'unit_offsets' must be an object {{name: metres}}")
        for name, dist in uo.items():
            if name not in receivers or name not in senders:
                raise InputError(f"{where}: field 'unit_offsets.{name}' names no unit (a receiver and a sender "
                                 "of that name)")
            if isinstance(dist, bool) or not isinstance(dist, (int, float)) or not math.isfinite(dist) or dist <= 0:
                raise InputError(f"{where}: field 'unit_offsets.{name}' must be a positive distance in m, got {dist!r}")
            offs[name] = float(dist)
    room = None
    if "room" in raw:
        rm = raw["room"]
        if (not isinstance(rm, list) or len(rm) not in (2, 3)
                or not all(not isinstance(v, bool) and isinstance(v, (int, float)) and math.isfinite(v) and v > 0
                           for v in rm)):
            raise InputError(f"{where}: field 'room' must be [L, W, H] (or [L, W]): positive lengths in m, got {rm!r}")
        room = tuple(float(v) for v in rm)
    return Setup(fs, c, receivers, senders, dict(probe), np.array(ev_s, dtype=np.int64), np.array(ev_t),
                 clock_jitter=float(jit), temperature=temp, humidity=hum, unit_offsets=offs, room=room)


def speed_from_air(temperature: float, humidity: float = 0.0, pressure: float = 101.325) -> float:
    """Speed of sound in air, m/s, from temperature (C), relative humidity (%) and pressure (kPa).

    ``c = 331.4 + 0.6 T + 0.0124 RH`` (:func:`pyroomacoustics.parameters.calculate_speed_of_sound`,
    Kleeman & Kuc, Springer Handbook of Robotics, 2008, eq. 21.7; pressure has no first-order
    effect). 25 C dry: 346.4 m/s; 20 C, 50 %: 344.0 m/s.

    Examples
    --------
    >>> round(speed_from_air(25.0), 1)
    346.4
    """
    from pyroomacoustics.parameters import calculate_speed_of_sound

    return float(calculate_speed_of_sound(float(temperature), float(humidity), float(pressure)))


def read_setup(directory: str | Path) -> Setup:
    """Read and validate ``DIR/setup.json`` (see module docstring)."""
    path = Path(directory) / "setup.json"
    if not Path(directory).is_dir():
        raise InputError(f"{directory}: not a directory (expected a recording directory with setup.json)")
    if not path.exists():
        raise InputError(f"setup.json: missing in {directory}")
    from ..io import read_json  # refuses directories / FIFOs / devices; JSON errors named

    return parse_setup(read_json(path, name="setup.json"))


def write_wav(path: str | Path, x: NDArray[np.floating[Any]], sample_rate: float, *, bits: int = 16) -> None:
    """Write a mono WAV atomically: ``bits=16`` (integer PCM, full scale 1) or ``bits=32`` (float).

    Samples beyond full scale are refused rather than silently clipped.
    """
    from scipy.io import wavfile

    x = np.asarray(x, dtype=np.float64)
    if np.abs(x).max(initial=0.0) >= 1.0:
        raise InputError(f"{Path(path).name}: samples reach full scale; scale the signal below 1")
    buf = _io.BytesIO()
    if bits == 16:
        wavfile.write(buf, int(sample_rate), np.round(x * 32767.0).astype(np.int16))
    elif bits == 32:
        wavfile.write(buf, int(sample_rate), x.astype(np.float32))
    else:
        raise InputError(f"bits must be 16 or 32, got {bits}")
    atomic_write_bytes(path, buf.getvalue())


@entry(directory="path")
def load_recording(directory: str | Path) -> Recording:
    """Read ``setup.json``, the probe and every ``rx_<name>.wav`` of a recording directory.

    Returns
    -------
    Recording
        Signals (I, N) float32, zero-padded to the longest file.

    Raises
    ------
    InputError
        Malformed ``setup.json`` (field named), a missing / clipped / unreadable WAV, or a
        WAV whose sample rate differs from ``sample_rate`` (file named).
    """
    d = Path(directory)
    setup = read_setup(d)
    probe = probe_from_spec(setup.probe, setup.sample_rate, base_dir=d)
    sigs = []
    for name in setup.receivers:
        x, fs = read_wav(d / f"rx_{name}.wav")
        if fs != setup.sample_rate:
            raise InputError(f"rx_{name}.wav: sample rate {fs:g} Hz differs from setup.json "
                             f"field 'sample_rate' = {setup.sample_rate:g} Hz")
        sigs.append(x.astype(np.float32))
    lengths = np.array([len(s) for s in sigs], dtype=np.int64)
    signals = np.zeros((len(sigs), int(lengths.max())), dtype=np.float32)
    for i, s in enumerate(sigs):
        signals[i, : len(s)] = s
    return Recording(setup, probe, signals, lengths, d)


def write_recording(directory: str | Path, setup: Setup, signals: NDArray[np.floating[Any]], *,
                    truth: dict[str, Any] | None = None, bits: int = 16,
                    extra: dict[str, Any] | None = None) -> None:
    """Write a recording directory: ``setup.json``, ``rx_<name>.wav`` and optional JSON files.

    Parameters
    ----------
    directory : path
    setup : Setup
    signals : (I, N) array, full scale 1
    truth : dict, optional
        Written to ``truth.json``.
    bits : 16 or 32
    extra : dict, optional
        ``{file name: JSON-able object}`` written alongside (e.g. ``heights.json``).
    """
    d = Path(directory)
    d.mkdir(parents=True, exist_ok=True)
    sig = np.asarray(signals)
    if sig.shape[0] != len(setup.receivers):
        raise InputError(f"signals has {sig.shape[0]} rows for {len(setup.receivers)} receivers")
    for name, x in zip(setup.receivers, sig, strict=True):
        write_wav(d / f"rx_{name}.wav", x, setup.sample_rate, bits=bits)
    for fname, obj in (extra or {}).items():
        write_json(d / fname, obj)
    if truth is not None:
        write_json(d / "truth.json", truth)
    # setup.json last: a directory with a setup.json is complete.
    write_json(d / "setup.json", setup.to_dict())

