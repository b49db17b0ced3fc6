"""Physical plausibility of a calibration: what the declared room and a working day allow.

A fit can be precise and still impossible: positions that span hundreds of metres in a
25 m room (a wrong basin, a wrong speed of sound, a unit mix-up), or a timing requirement
that only billions of probe repetitions could meet (the delay error is then not noise that
averages down, it is a model error). Such figures are a FAIL with the reason, not advice:

- **extent**: the positions' bounding-box diagonal beyond :data:`EXTENT_FACTOR` times the
  diagonal of the room declared in ``setup.json`` (``room``). Every unit is inside the room,
  so their extent is at most its diagonal; the factor leaves room for the gauge (a fit is
  determined up to a rigid motion, not placed in the room) and for error bars, while
  anything beyond it cannot be the room.
- **repeats**: the rounds the 1/sqrt(N) averaging would need (:class:`Verdict.rounds_needed
  <selfcal.acoustics.verdict.Verdict>`) take longer than :data:`WORKING_DAY` at the
  recording's own pace (its length per round): repeating the probes is no remedy then.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

__all__ = ["EXTENT_FACTOR", "WORKING_DAY", "extent_reason", "repeats_reason"]

#: positions may span at most this many room diagonals (gauge and error bars; module docstring)
EXTENT_FACTOR = 2.0
#: s: the longest a calibration session may take (8 h): more repeats are no remedy
WORKING_DAY = 8 * 3600.0


def extent_reason(receivers: NDArray[np.float64], sources: NDArray[np.float64],
                  room: Sequence[float] | None) -> str | None:
    """Why the positions cannot be in the declared room, or None when they can (or no room).

    Parameters
    ----------
    receivers, sources : (I, d), (J, d) arrays
        Positions, m (NaN rows ignored).
    room : sequence of 2 or 3 floats, or None
        Declared room size ``(L, W[, H])``, m.

    Returns
    -------
    str or None
        The reason (for a ``FAIL:`` line).

    Examples
    --------
    >>> import numpy as np
    >>> extent_reason(np.array([[0.0, 0, 0], [549, 0, 0]]), np.zeros((1, 3)), (25, 20, 4)) is not None
    True
    >>> extent_reason(np.array([[0.0, 0, 0], [20, 0, 0]]), np.zeros((1, 3)), (25, 20, 4)) is None
    True
    """
    if room is None:
        return None
    pts = np.vstack([np.asarray(receivers, float), np.asarray(sources, float)])
    pts = pts[np.isfinite(pts).all(axis=1)]
    if len(pts) < 2:
        return None
    extent = float(np.linalg.norm(pts.max(axis=0) - pts.min(axis=0)))
    diag = float(np.linalg.norm(np.asarray(room, float)))
    if extent <= EXTENT_FACTOR * diag:
        return None
    size = " x ".join(f"{v:g}" for v in room)
    return (f"physically impossible: the positions span {extent:.4g} m, more than {EXTENT_FACTOR:g} x the "
            f"{diag:.3g} m diagonal of the declared {size} m room; positions NOT reliable (a wrong basin, speed "
            "of sound or unit mix-up)")


def repeats_reason(rounds_needed: int | None, round_seconds: float, timing_std: float, limit: float) -> str | None:
    """Why repeating the probes cannot meet the timing requirement, or None when it can.

    Parameters
    ----------
    rounds_needed : int or None
        Rounds (probe repetitions per loudspeaker) the 1/sqrt(N) averaging needs.
    round_seconds : float
        Duration of one round in this recording, s (its length over its rounds).
    timing_std, limit : float
        The delay + onset std and the std it must reach, s.

    Returns
    -------
    str or None

    Examples
    --------
    >>> repeats_reason(6_600_776_683, 2.0, 4.3e-3, 29e-6) is not None
    True
    >>> repeats_reason(4, 2.0, 50e-6, 29e-6) is None
    True
    """
    if rounds_needed is None or not np.isfinite(round_seconds) or round_seconds <= 0:
        return None
    hours = rounds_needed * round_seconds / 3600.0
    if rounds_needed * round_seconds <= WORKING_DAY:
        return None
    return (f"requirement out of reach: delay std {timing_std * 1e6:.3g} us > {limit * 1e6:.3g} us would need "
            f"{rounds_needed:,} rounds of the probes ({hours:,.3g} h at {round_seconds:.3g} s per round, more than a "
            f"working day of {WORKING_DAY / 3600:g} h): repeating them is no remedy, the error is not noise that "
            "averages down (a wrong model, bad detections or a faulty unit)")
