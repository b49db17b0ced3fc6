"""Numeric command-line options with a stated physical range: one mechanism for every command.

Every float option of every command is declared with ``type=Quantity(...)`` (or one of the
instances below); click then refuses, before the command runs, a value that is not a strict
decimal number, NaN, +-inf, or outside the option's range, and the ``selfcal`` group prints
that as one ``selfcal: error:`` line with exit status 2. Each range is stated next to the
instance with its reason (physics, the numerics of the solver, or the mistake it catches).

The commands' own checks (and the library's :class:`~selfcal.errors.InputError` checks) stay
in place: this module is the first gate, not the only one.
"""

from __future__ import annotations

import math
import re
from typing import Any

import click

__all__ = ["Quantity", "SPEED", "SPEED_OF_SOUND", "NOISE_STD", "SAMPLE_RATE_HZ", "JITTER_S", "JITTER_US",
           "RT60_S", "SNR_DB", "SLAC_SNR_DB", "TEMPERATURE_C", "HUMIDITY_PCT", "MINUTES", "ANGLE_RAD",
           "SIGMA_DEG", "GRID_STEP_M", "MAX_RT60_S", "SPEED_OF_LIGHT", "SEED"]

# strict decimal (no "1_0", "0x10", "infinity"); nan / inf are matched to be named as such
_NUMBER = re.compile(r"\s*[+-]?(?:\d+(?:\.\d*)?|\.\d+)(?:[eE][+-]?\d+)?\s*\Z", re.ASCII)
_NONFINITE = re.compile(r"\s*[+-]?(?:nan|inf|infinity)\s*\Z", re.IGNORECASE | re.ASCII)


def _fmt(v: float) -> str:
    return f"{v:g}"


class Quantity(click.ParamType):
    """A finite float option within a stated range (bounds open or closed), with its unit.

    Parameters
    ----------
    unit:
        Unit written after the numbers in the messages (``"s"``, ``"m/s"``, ``"dB"``).
    gt, ge, lt, le:
        Lower bound (exclusive ``gt`` / inclusive ``ge``) and upper bound (``lt`` / ``le``).
    why:
        The reason of the range, appended to the message of a value outside it.

    Examples
    --------
    >>> q = Quantity("s", gt=0, le=20, why="no room reverberates longer")
    >>> q.convert("0.4", None, None)
    0.4
    """

    name = "number"

    def __init__(self, unit: str = "", *, gt: float | None = None, ge: float | None = None,
                 lt: float | None = None, le: float | None = None, why: str = "") -> None:
        self.unit = unit
        self.gt, self.ge, self.lt, self.le = gt, ge, lt, le
        self.why = why

    def range_text(self) -> str:
        """The range in words, e.g. ``"> 0 and at most 20 s"``."""
        parts = []
        if self.gt is not None:
            parts.append(f"> {_fmt(self.gt)}")
        if self.ge is not None:
            parts.append(f">= {_fmt(self.ge)}")
        if self.lt is not None:
            parts.append(f"below {_fmt(self.lt)}")
        if self.le is not None:
            parts.append(f"at most {_fmt(self.le)}")
        text = " and ".join(parts) if parts else "finite"
        return f"{text} {self.unit}".rstrip()

    def convert(self, value: Any, param: click.Parameter | None, ctx: click.Context | None) -> Any:
        if value is None:
            return None
        if isinstance(value, bool):
            self.fail(f"{value!r} is not a number", param, ctx)
        if isinstance(value, (int, float)):
            v = float(value)
        else:
            text = str(value)
            if _NONFINITE.match(text):
                self.fail(f"{text.strip()!r} is not a finite number; give a value {self.range_text()}", param, ctx)
            if not _NUMBER.match(text):
                shown = text if len(text) <= 24 else text[:20] + "..."
                self.fail(f"{shown!r} is not a decimal number", param, ctx)
            v = float(text)
        if not math.isfinite(v):  # a decimal beyond 1.8e308 (float() gives inf)
            self.fail(f"{value!r} is beyond double precision; give a value {self.range_text()}", param, ctx)
        bad = ((self.gt is not None and not v > self.gt) or (self.ge is not None and not v >= self.ge)
               or (self.lt is not None and not v < self.lt) or (self.le is not None and not v <= self.le))
        if bad:
            why = f" ({self.why})" if self.why else ""
            self.fail(f"{_fmt(v)} {self.unit}".rstrip() + f" is outside the range: must be {self.range_text()}{why}",
                      param, ctx)
        return v

    def __repr__(self) -> str:
        return f"Quantity({self.range_text()!r})"


#: Speed of light in vacuum, m/s: nothing the solvers model propagates faster.
SPEED_OF_LIGHT = 299_792_458.0
#: Longest reverberation time (s) a simulation accepts (see :data:`RT60_S`).
MAX_RT60_S = 20.0

#: ``--speed`` (TOA / far-field matrices of times): a propagation speed > 0, at most 3e8 m/s,
#: the speed of light rounded up as users type it (radio); sound is ~343 m/s.
SPEED = Quantity("m/s", gt=0, le=3.0e8, why="a propagation speed; nothing is faster than light, 3e8 m/s")

#: ``--speed-of-sound``: > 0 and at most the bound for sound in any condensed phase, 36.1 km/s
#: (Trachenko et al., Sci. Adv. 6, eabc8662, 2020); more is a unit mistake.
SPEED_OF_SOUND = Quantity("m/s", gt=0, le=36_100.0,
                          why="the physical bound of the speed of sound in any medium, 36.1 km/s")

#: ``--noise`` / ``--noise-std``: a standard deviation, > 0 (the chi-square test divides by it:
#: exact data have no such test) and finite. The solvers refuse one
#: whose square overflows their chi-square sums (beyond :data:`selfcal._checks.MAX_ABS_ENTRY`,
#: ~1.3e148, in the matrix's unit) with their own message.
NOISE_STD = Quantity("", gt=0, why="a standard deviation in the matrix's unit, for the chi-square test")

#: ``--sample-rate`` of a matrix in samples: > 0 and at most 1e13 Hz (100 fs ticks); timing
#: hardware samples at most ~1e11 Hz (UWB: 64 GHz), so more is a rate in the wrong unit.
SAMPLE_RATE_HZ = Quantity("Hz", gt=0, le=1e13, why="beyond any timing hardware (1e13 Hz); give it in Hz")

#: ``--jitter`` (s): a clock jitter std >= 0 and below 10 ms (detection windows are milliseconds);
#: 10 ms or more is microseconds given as seconds (``--jitter-us``), named by the command.
JITTER_S = Quantity("s", ge=0, why="a standard deviation in seconds")
#: ``--jitter-us``: the same quantity in microseconds, >= 0 (the 10 ms bound is checked by the command).
JITTER_US = Quantity("us", ge=0, why="a standard deviation in microseconds")

#: ``--rt60`` (s): > 0 and at most 20 s. Reverberation chambers (ISO 354) reach about 20 s at low
#: frequencies and the longest concert halls / cathedrals 10 s. pyroomacoustics' image-source
#: model needs order ``ceil(c * rt60 / min(room))`` for the full decay (``inverse_sabine``): at
#: 20 s in a 3 m high room that is order 2287, ~1.6e10 images per source (4/3 order^3), far beyond
#: any budget; the commands cap the order (``--max-order``), so the RT60 only sets the walls'
#: absorption, but a value beyond 20 s is a unit mistake (milliseconds given as seconds).
RT60_S = Quantity("s", gt=0, le=MAX_RT60_S,
                  why="no room reverberates longer than ~20 s; is it in milliseconds?")

#: ``--snr`` (dB, conference simulations): at least -150 dB (below, the direct sound is under the
#: float32 samples' 24-bit resolution of the noise, ``selfcal.acoustics.room.MIN_SNR_DB``) and at
#: most 200 dB (the noise is then 1e-10 of the signal, below float32 rounding: noise-free already).
SNR_DB = Quantity("dB", ge=-150.0, le=200.0,
                  why="float32 samples resolve about 144 dB: beyond, the noise or the signal is lost in rounding")
#: ``--snr-db`` (SLAC simulations): within +-200 dB (complex64 snapshots resolve ~150 dB;
#: ``selfcal.slac.validate.MAX_SNR_DB``).
SLAC_SNR_DB = Quantity("dB", ge=-200.0, le=200.0, why="complex64 snapshots resolve about 150 dB")

#: ``--temperature`` (C): [-40, 60], where the linear law c = 331.4 + 0.6 T holds within 0.5 %
#: (the range setup.json's 'temperature' accepts).
TEMPERATURE_C = Quantity("C", ge=-40.0, le=60.0, why="air temperature where c = 331.4 + 0.6 T + 0.0124 RH holds")
#: ``--humidity`` (%): a relative humidity, [0, 100].
HUMIDITY_PCT = Quantity("%", ge=0.0, le=100.0, why="a relative humidity")

#: ``--minutes`` (SLAC logs): > 0 (a length of time); the size is then checked against memory.
MINUTES = Quantity("min", gt=0, why="a duration")

#: ``--init-heading-offset`` (rad): within +-2 pi; larger magnitudes are degrees.
ANGLE_RAD = Quantity("rad", ge=-2 * math.pi, le=2 * math.pi, why="an angle in radians; degrees?")

#: ``--sigma-deg``: an angular noise std, > 0 and below 180 degrees (no bearing is more uncertain
#: than the half circle).
SIGMA_DEG = Quantity("deg", gt=0, lt=180.0, why="an angular noise std: a positive number of degrees below 180")

#: ``--step`` of paper 001's grid (m): (0, 5]; the grid spans 10 m (a coarser step has < 3 points).
GRID_STEP_M = Quantity("m", gt=0, le=5.0, why="the grid step on the 10 m wide plane")

#: ``--seed`` of every command: an integer in [0, 2**63 - 1]. numpy's ``SeedSequence`` takes only
#: non-negative entropy (a negative seed was an internal error), and a seed beyond int64 is no
#: more random than a smaller one while parts of the experiment runners store seeds as int64.
SEED = click.IntRange(0, 2**63 - 1)
