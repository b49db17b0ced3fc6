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

__all__ = ["PyramicData", "load_pyramic", "pyramic_from_dict"]

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
    mic_ref: int = 0

    @property
    def positions(self) -> Array:
        """(48, 3) reference positions relative to the reference microphone (the z_i of the model)."""
        return self.microphones - self.microphones[self.mic_ref]

    @property
    def directions(self) -> Array:
        """(180, 3) model directions ``n_j = -u_j``."""
        return -self.sources


def load_pyramic(path: str | os.PathLike[str]) -> PyramicData:
    """Read the Pyramic JSON (the file, or the folder holding ``pyramic_tdoa_speaker0.json``).

    Parameters
    ----------
    path : the JSON file or its folder.

    Returns
    -------
    PyramicData

    Raises
    ------
    InputError
        A key is missing or a shape is wrong.

    Examples
    --------
    >>> data = load_pyramic("../shared/data/pyramic")   # doctest: +SKIP
    >>> data.D.shape                                      # doctest: +SKIP
    (48, 180)
    """
    p = Path(path)
    if p.is_dir():
        p = p / _FILE
    return pyramic_from_dict(read_json(p), label=str(p))


def pyramic_from_dict(obj: object, *, label: str = "Pyramic JSON", speed: float | None = None) -> PyramicData:
    """Build :class:`PyramicData` from the parsed Pyramic calibration JSON layout.

    Keys: ``delays`` [n_mic - 1][n_src] (seconds, microphone i against ``mic_ref``, the
    reference row omitted), ``sources`` [n_src][3] (unit directions), ``microphones``
    [3][n_mic] (x, y, z lists, metres), ``sound_speed_mps``, ``mic_ref`` (default 0). The
    reference microphone's row of zeros is re-inserted at ``mic_ref``, so row i of ``D`` is
    microphone i.

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
    missing = [key for key in ("delays", "sources", "microphones") if key not in obj]
    if missing:
        raise InputError(f"{p}: not a Pyramic TDOA file (missing keys {missing}; expected 'delays', 'sources', "
                         "'microphones', 'sound_speed_mps')")
    try:
        delays = np.asarray(obj["delays"], dtype=float)
        sources = np.asarray(obj["sources"], dtype=float)
        mics = np.asarray(obj["microphones"], dtype=float)
        file_speed = float(obj["sound_speed_mps"]) if "sound_speed_mps" in obj else float("nan")
        ref_raw = obj.get("mic_ref", 0)
        ref = int(ref_raw)
    except (KeyError, TypeError, ValueError) as exc:
        raise InputError(f"{p}: not a Pyramic TDOA file ({exc})") from None
    if ref != ref_raw:
        raise InputError(f"{p}: mic_ref must be an integer, got {ref_raw!r}")
    if mics.ndim != 2 or mics.shape[0] != 3:
        raise InputError(f"{p}: 'microphones' must be 3 lists (x, y, z), got shape {mics.shape}")
    mics = mics.T
    n_mic = mics.shape[0]
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
    if not np.isfinite(c) or c <= 0:
        raise InputError(f"{p}: the speed of sound must be a positive number (sound_speed_mps or --speed), got {c}")
    if np.isinf(delays).any() or not np.isfinite(sources).all() or not np.isfinite(mics).all():
        raise InputError(f"{p}: 'delays' must be finite or NaN (missing); 'sources' and 'microphones' finite")
    D = np.insert(delays * c, ref, 0.0, axis=0)
    return PyramicData(D=D, delays=delays, sources=sources, microphones=mics, speed=c,
                       mic_ref=ref)
