"""Probe signals: the sound every loudspeaker plays during calibration.

A probe is described in ``setup.json`` either as a linear chirp
``{"type": "chirp", "f0": Hz, "f1": Hz, "duration": s}`` or as a WAV file
``{"wav": "probe.wav"}`` next to ``setup.json``. The chirp used everywhere in selfcal is

    x(t) = w(t) sin(2 pi (f0 t + (f1 - f0) t^2 / (2 T))),   0 <= t < T,

with ``w`` a Tukey (tapered cosine) window whose tapers take 10 % of the duration.
The taper keeps the spectrum inside [f0, f1] so the matched-filter output has low
range side lobes (which matters when the *first* significant peak is searched, see
:mod:`selfcal.acoustics.detect`).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..errors import InputError
from ..io.wav import read_wav

__all__ = ["Probe", "linear_chirp", "probe_from_spec", "TAPER"]

TAPER = 0.1  # fraction of the chirp duration in the two cosine tapers together


@dataclass(frozen=True)
class Probe:
    """A probe signal sampled at ``sample_rate``.

    Attributes
    ----------
    samples : (L,) float array
        The waveform, peak amplitude 1.
    sample_rate : float
        Hz.
    band : (float, float)
        Frequency band (Hz) holding the probe's energy; the detector weights its matched
        filter to this band.
    spec : dict
        The ``setup.json`` description it was built from (JSON-safe).
    """

    samples: NDArray[np.float64]
    sample_rate: float
    band: tuple[float, float]
    spec: dict[str, Any]

    @property
    def duration(self) -> float:
        """Length in seconds."""
        return len(self.samples) / self.sample_rate


def linear_chirp(f0: float, f1: float, duration: float, sample_rate: float) -> NDArray[np.float64]:
    """Tukey-tapered linear chirp from ``f0`` to ``f1`` Hz over ``duration`` s.

    Returns an (L,) array with ``L = round(duration * sample_rate)`` and peak 1.
    """
    from scipy.signal.windows import tukey

    n = int(round(duration * sample_rate))
    t = np.arange(n) / sample_rate
    phase = 2.0 * np.pi * (f0 * t + 0.5 * (f1 - f0) / duration * t**2)
    return np.sin(phase) * tukey(n, TAPER)


def _number(spec: dict[str, Any], key: str, where: str) -> float:
    if key not in spec:
        raise InputError(f"{where}: field 'probe.{key}' is missing")
    val = spec[key]
    if isinstance(val, bool) or not isinstance(val, (int, float)) or not np.isfinite(val) or val <= 0:
        raise InputError(f"{where}: field 'probe.{key}' must be a positive number, got {val!r}")
    return float(val)


def probe_from_spec(spec: Any, sample_rate: float, *, base_dir: Path | None = None,
                    where: str = "setup.json") -> Probe:
    """Build the probe described by a ``setup.json`` ``probe`` entry.

    Parameters
    ----------
    spec : dict
        ``{"type": "chirp", "f0", "f1", "duration"}`` or ``{"wav": file}``.
    sample_rate : float
        Hz; a WAV probe must have this rate.
    base_dir : Path, optional
        Folder a relative ``wav`` path is resolved in.
    where : str
        Name used in error messages.

    Raises
    ------
    InputError
        Unknown type, missing or non-positive fields, a band outside (0, fs/2), or an
        unreadable / wrong-rate probe WAV; the message names the field or file.
    """
    if not isinstance(spec, dict):
        raise InputError(f"{where}: field 'probe' must be an object, got {type(spec).__name__}")
    nyq = sample_rate / 2.0
    if "wav" in spec:
        name = spec["wav"]
        if not isinstance(name, str) or not name:
            raise InputError(f"{where}: field 'probe.wav' must be a file name")
        path = (base_dir or Path(".")) / name
        x, fs = read_wav(path)
        if fs != sample_rate:
            raise InputError(f"{path.name}: sample rate {fs} Hz differs from setup.json 'sample_rate' {sample_rate:g} Hz")
        peak = float(np.max(np.abs(x)))
        if peak == 0.0:
            raise InputError(f"{path.name}: probe is silent")
        # Band = the central interval holding 99 % of the probe's energy.
        n_fft = 8 * len(x)
        power = np.abs(np.fft.rfft(x, n_fft)) ** 2
        freqs = np.fft.rfftfreq(n_fft, 1.0 / fs)
        cum = np.cumsum(power) / power.sum()
        lo = float(freqs[int(np.searchsorted(cum, 0.005))])
        hi = float(freqs[min(int(np.searchsorted(cum, 0.995)), len(freqs) - 1)])
        if hi <= lo:
            raise InputError(f"{path.name}: probe has no usable bandwidth")
        return Probe(x / peak, float(fs), (lo, hi), dict(spec))
    kind = spec.get("type")
    if kind != "chirp":
        raise InputError(f"{where}: field 'probe.type' must be 'chirp' (or give 'probe.wav'), got {kind!r}")
    f0 = _number(spec, "f0", where)
    f1 = _number(spec, "f1", where)
    dur = _number(spec, "duration", where)
    if max(f0, f1) >= nyq:
        raise InputError(f"{where}: field 'probe.f1' = {max(f0, f1):g} Hz is not below the Nyquist frequency {nyq:g} Hz")
    if f0 == f1:
        raise InputError(f"{where}: fields 'probe.f0' and 'probe.f1' are equal; a chirp needs a band")
    if dur * sample_rate < 16:
        raise InputError(f"{where}: field 'probe.duration' = {dur:g} s is shorter than 16 samples")
    x = linear_chirp(f0, f1, dur, sample_rate)
    return Probe(x, float(sample_rate), (min(f0, f1), max(f0, f1)),
                 {"type": "chirp", "f0": f0, "f1": f1, "duration": dur})
