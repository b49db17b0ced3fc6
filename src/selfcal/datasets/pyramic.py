"""Loader for the Pyramic far-field TDOA recording (EPFL, MIT licence).

The JSON holds, for one loudspeaker at a fixed elevation and 180 array azimuths, the
GCC-PHAT delays of microphones 1..47 against microphone 0 (seconds), the unit source
directions, the hand-measured microphone positions and the speed of sound.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from ..errors import InputError
from ..io import read_json

__all__ = ["PyramicData", "load_pyramic"]

Array = NDArray[np.float64]
_FILE = "pyramic_tdoa_speaker0.json"


@dataclass(frozen=True)
class PyramicData:
    """One Pyramic speaker data set.

    Attributes
    ----------
    D : (48, 180) far-field relative-distance matrix in metres, ``D_ij = c * delay`` with a
        zero first row (microphone 0 is the reference), so that ``D_ij ~ z_i . n_j + C_j``
        with ``z_i = m_i - m_0`` and ``n_j = -u_j`` (C_j = 0 up to noise).
    delays : (47, 180) raw TDOA in seconds (microphone i+1 against microphone 0).
    sources : (180, 3) unit source directions u_j (array frame).
    microphones : (48, 3) hand-measured microphone positions (metres).
    speed : speed of sound (m/s).
    """

    D: Array
    delays: Array
    sources: Array
    microphones: Array
    speed: float

    @property
    def positions(self) -> Array:
        """(48, 3) reference positions relative to microphone 0 (the z_i of the model)."""
        return self.microphones - self.microphones[0]

    @property
    def directions(self) -> Array:
        """(180, 3) model directions ``n_j = -u_j``."""
        return -self.sources


def load_pyramic(path: str | os.PathLike[str]) -> PyramicData:
    """Read the Pyramic JSON (the file, or the folder holding ``pyramic_tdoa_speaker0.json``).

    Raises :class:`~selfcal.errors.InputError` when a key is missing or a shape is wrong.
    """
    p = Path(path)
    if p.is_dir():
        p = p / _FILE
    obj = read_json(p)
    try:
        delays = np.asarray(obj["delays"], dtype=float)
        sources = np.asarray(obj["sources"], dtype=float)
        mics = np.asarray(obj["microphones"], dtype=float)
        speed = float(obj["sound_speed_mps"])
        ref = int(obj.get("mic_ref", 0))
    except (KeyError, TypeError, ValueError) as exc:
        raise InputError(f"{p}: not a Pyramic TDOA file ({exc})") from None
    if mics.ndim != 2 or mics.shape[0] != 3:
        raise InputError(f"{p}: 'microphones' must be 3 lists (x, y, z), got shape {mics.shape}")
    mics = mics.T
    n_mic, n_src = mics.shape[0], sources.shape[0]
    if delays.shape != (n_mic - 1, n_src) or sources.shape != (n_src, 3):
        raise InputError(f"{p}: delays {delays.shape} / sources {sources.shape} do not match {n_mic} microphones")
    if ref != 0:
        raise InputError(f"{p}: only mic_ref = 0 is supported, got {ref}")
    if not np.isfinite(speed) or speed <= 0:
        raise InputError(f"{p}: sound_speed_mps must be positive, got {speed}")
    D = np.vstack([np.zeros((1, n_src)), delays * speed])
    return PyramicData(D=D, delays=delays, sources=sources, microphones=mics, speed=speed)
