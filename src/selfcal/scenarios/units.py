"""Synthetic setups of paper 004: conference units with a microphone and a loudspeaker each.

Each *unit* (a Bosch DICENTIS seat in the thesis) holds one microphone (receiver) and
one loudspeaker (sender) that are close but not co-located. Measured times follow 004
eq. (3.1), rows = microphones, columns = loudspeakers::

    t_ij = |r_i - s_j| / c + tau_j + delta_i + v_ij

Placement rules (thesis sec. 2.1 and 4.2): unit positions are uniform in the room
``x_max x y_max x z_max`` (30 x 30 x 12 m or 12 x 12 x 2 m), at least 0.75 m apart
(requirement 2.1.2); the loudspeaker of a unit sits ``speaker_offset`` metres (default
0.1-0.3 m, our assumption: the thesis only says "not necessarily at the same location")
from its microphone in a random horizontal direction, kept inside the room. Internal
delays are uniform in [0, 20] ms, onset times uniform in [0, 30] ms (requirement 2.2.4),
c = 343 m/s. The thesis simulates *equal* internal delays (sec. 4.2, Gamma = 0); pass
``equal_delays=False`` for one delay per microphone.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .._checks import as_rng
from ..errors import InputError

__all__ = ["ROOMS", "SPEED_OF_SOUND", "UnitsScenario", "make_units", "true_offset_vector"]

SPEED_OF_SOUND = 343.0
#: the two rooms of 004 sec. 4.3, metres
ROOMS: dict[str, tuple[float, float, float]] = {"large": (30.0, 30.0, 12.0), "small": (12.0, 12.0, 2.0)}

Array = NDArray[np.float64]


@dataclass(frozen=True)
class UnitsScenario:
    """A simulated 004 setup.

    Attributes
    ----------
    microphones : (U, d) receiver positions, metres.
    speakers : (U, d) sender positions, metres.
    delays : (U,) internal delays delta_i, seconds.
    onsets : (U,) onset times tau_j, seconds.
    times : (U, U) measured times t_ij (eq. 3.1), seconds, rows = microphones.
    speed : speed of sound, m/s.
    noise_std : timing noise standard deviation, seconds.
    room : (d,) room size, metres.
    """

    microphones: Array
    speakers: Array
    delays: Array
    onsets: Array
    times: Array
    speed: float
    noise_std: float
    room: Array

    @property
    def ranges(self) -> Array:
        """Times times the speed: the (U, U) matrix in metres the rank-3 solvers take."""
        return self.times * self.speed

    def to_dict(self) -> dict[str, Any]:
        return {k: getattr(self, k) for k in self.__dataclass_fields__}


def true_offset_vector(delays: Array, onsets: Array) -> Array:
    """The thesis vector p (eq. 3.5) in the gauge tau_1 = 0, same units as the inputs.

    Only tau_j + delta_i is observable, so the common shift tau_1 moves into the delays:
    p = [delta_1 + tau_1, ..., delta_I + tau_1, tau_2 - tau_1, ..., tau_J - tau_1].
    """
    delays = np.asarray(delays, dtype=float)
    onsets = np.asarray(onsets, dtype=float)
    return np.concatenate([delays + onsets[0], onsets[1:] - onsets[0]])


def _place_units(n: int, room: Array, min_dist: float, rng: np.random.Generator) -> Array:
    pts = np.empty((0, room.size))
    tries = 0
    while len(pts) < n:
        cand = rng.uniform(0.0, 1.0, size=(n, room.size)) * room
        for c in cand:
            if len(pts) == n:
                break
            if len(pts) == 0 or np.min(np.linalg.norm(pts - c, axis=1)) >= min_dist:
                pts = np.vstack([pts, c])
        tries += 1
        if tries > 200:
            raise InputError(f"cannot place {n} units at least {min_dist} m apart in a room of {room.tolist()} m")
    return pts


def make_units(
    n_units: int,
    *,
    room: str | tuple[float, ...] = "small",
    speed: float = SPEED_OF_SOUND,
    noise_std: float = 0.0,
    equal_delays: bool = True,
    delay_max: float = 0.020,
    onset_max: float = 0.030,
    speaker_offset: tuple[float, float] = (0.1, 0.3),
    min_distance: float = 0.75,
    rng: np.random.Generator | int | None = None,
) -> UnitsScenario:
    """Simulate one 004 setup (thesis sec. 4.2).

    Parameters
    ----------
    n_units : number of units U (each one microphone and one loudspeaker).
    room : ``"large"`` (30 x 30 x 12 m), ``"small"`` (12 x 12 x 2 m) or explicit sizes (2 or 3 values).
    speed : speed of sound c, m/s.
    noise_std : standard deviation of the timing noise v_ij, seconds (0 in the thesis).
    equal_delays : one internal delay shared by every microphone (thesis, Gamma = 0) or one each.
    delay_max, onset_max : upper ends of the uniform delay / onset ranges, seconds.
    speaker_offset : range of the microphone-to-loudspeaker distance within a unit, metres.
    min_distance : minimal distance between units, metres (thesis requirement 2.1.2).
    rng : seed or Generator.
    """
    if n_units < 2:
        raise InputError(f"n_units must be >= 2, got {n_units}")
    gen = as_rng(rng)
    size = np.asarray(ROOMS[room] if isinstance(room, str) else room, dtype=float)
    if size.ndim != 1 or size.size not in (2, 3) or np.any(size <= 0):
        raise InputError(f"room must be 'large', 'small' or 2-3 positive sizes, got {room!r}")
    mics = _place_units(n_units, size, min_distance, gen)
    ang = gen.uniform(0.0, 2 * np.pi, n_units)
    rad = gen.uniform(*speaker_offset, n_units)
    shift = np.zeros_like(mics)
    shift[:, 0] = rad * np.cos(ang)
    shift[:, 1] = rad * np.sin(ang)
    # keep the loudspeaker inside the room by mirroring a shift that would leave it
    out = (mics + shift < 0) | (mics + shift > size)
    shift[out] *= -1
    speakers = np.clip(mics + shift, 0.0, size)
    if equal_delays:
        delays = np.full(n_units, gen.uniform(0.0, delay_max))
    else:
        delays = gen.uniform(0.0, delay_max, n_units)
    onsets = gen.uniform(0.0, onset_max, n_units)
    dist = np.linalg.norm(mics[:, None, :] - speakers[None, :, :], axis=-1)
    times = dist / speed + onsets[None, :] + delays[:, None]
    if noise_std > 0:
        times = times + gen.normal(0.0, noise_std, times.shape)
    return UnitsScenario(mics, speakers, delays, onsets, times, float(speed), float(noise_std), size)
