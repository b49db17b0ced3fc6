"""Conference-room layouts of paper 004: units (microphone + loudspeaker) on seats around tables.

Each unit has a loudspeaker (the sender) built into the desk unit and a microphone (the
receiver) 5-15 cm away from it (004 sec. 3.2: "the sender and receiver are not
necessarily at the same physical location"). Internal delays are drawn in 0-20 ms and
onset times in 0-30 ms (004 sec. 2.2, assumption 4). Three layouts:

``flat``
    every desk at one height, microphones on short goosenecks (5-15 cm, 20-60 degrees
    up): a thin network (a few cm thick) whose z is only weakly determined.
``boundary``
    every desk at one height, boundary microphones lying on the desk 5-15 cm beside the
    loudspeaker (within 1 cm of its height): a planar network, for which 3-D
    self-calibration is ill-posed (mirror ambiguity, undetermined z); use 2-D with
    known heights.
``tiered``
    table rows rising towards the back, quadratically (an amphitheatre: the back row
    at 40 % of the room height), which makes the network genuinely 3-D.
``stem``
    flat desks, microphones on stems 30-50 cm above the desk loudspeakers: two layers,
    also 3-D.
``hall``
    a large hall: the rising rows of ``tiered`` with long gooseneck microphones 5-40 cm
    from the loudspeaker (the 120-unit benchmark scene of issue 15).

Tables are 2.4 x 1.2 m with three seats on each long side (0.8 m apart, so units are
at least 0.75 m apart, 004 assumption 1), on a grid with 1.5 m aisles, centred in the
room with 0.8 m clearance to the walls.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .._checks import as_rng, check_choice
from ..errors import InputError

__all__ = ["ConferenceScene", "conference_scene", "LAYOUTS", "DESK_HEIGHT"]

LAYOUTS = ("flat", "boundary", "tiered", "stem", "hall")
DESK_HEIGHT = 0.75  # m, table top
SPEAKER_ABOVE_DESK = 0.05  # m, loudspeaker grille in the desk unit
TABLE = (2.4, 1.2)
AISLE = 1.5
WALL = 0.8
SEAT_X = (-0.8, 0.0, 0.8)
SEAT_INSET = 0.2  # unit distance from the table edge


@dataclass(frozen=True)
class ConferenceScene:
    """Ground truth of a simulated conference network (one unit = one receiver + one sender).

    Attributes
    ----------
    receivers : (U, 3) array
        Microphone positions, m.
    senders : (U, 3) array
        Loudspeaker positions, m.
    receiver_delays : (U,) array
        Internal delays of the microphones, s (0-20 ms).
    sender_onsets : (U,) array
        Onset times of the loudspeakers, s (0-30 ms).
    room : (3,) array
        Room size L x W x H, m.
    layout : str
    """

    receivers: NDArray[np.float64]
    senders: NDArray[np.float64]
    receiver_delays: NDArray[np.float64]
    sender_onsets: NDArray[np.float64]
    room: NDArray[np.float64]
    layout: str

    def to_dict(self) -> dict[str, Any]:
        """JSON-safe dictionary (the ``truth.json`` keys)."""
        return {
            "receivers": self.receivers.tolist(),
            "senders": self.senders.tolist(),
            "receiver_delays": self.receiver_delays.tolist(),
            "sender_onsets": self.sender_onsets.tolist(),
            "room": self.room.tolist(),
            "layout": self.layout,
        }


def _seats(room: NDArray[np.float64], layout: str) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.int64]]:
    """All seat positions (x, y, desk z), the unit's facing direction and table row index."""
    usable = room[:2] - 2 * WALL
    n_x = int((usable[0] + AISLE) // (TABLE[0] + AISLE))
    n_y = int((usable[1] + AISLE) // (TABLE[1] + AISLE))
    if n_x < 1 or n_y < 1:
        raise InputError(f"room {room[0]:g} x {room[1]:g} m is too small for a {TABLE[0]} x {TABLE[1]} m table")
    span = np.array([n_x * TABLE[0] + (n_x - 1) * AISLE, n_y * TABLE[1] + (n_y - 1) * AISLE])
    origin = (room[:2] - span) / 2
    pos, facing, rows = [], [], []
    # Amphitheatre: row k is raised by a k^2 with the back row at 40 % of the room height;
    # the quadratic profile keeps the tiers off any single inclined plane (a linear ramp
    # would be as planar as a flat floor).
    a = 0.4 * room[2] / max(n_y - 1, 1) ** 2
    rise = a * np.arange(n_y) ** 2
    for ky in range(n_y):
        cy = origin[1] + ky * (TABLE[1] + AISLE) + TABLE[1] / 2
        z = DESK_HEIGHT + (rise[ky] if layout in ("tiered", "hall") else 0.0)
        for kx in range(n_x):
            cx = origin[0] + kx * (TABLE[0] + AISLE) + TABLE[0] / 2
            for side in (-1.0, 1.0):
                for sx in SEAT_X:
                    pos.append((cx + sx, cy + side * (TABLE[1] / 2 - SEAT_INSET), z))
                    facing.append((0.0, -side))  # the seat is on the outside, the unit faces it
                    rows.append(ky)
    return np.array(pos), np.array(facing), np.array(rows, dtype=np.int64)


def conference_scene(
    units: int,
    room: tuple[float, float, float] | NDArray[np.float64] = (12.0, 12.0, 3.0),
    *,
    layout: str = "flat",
    rng: np.random.Generator | int | None = None,
) -> ConferenceScene:
    """Draw a conference network: ``units`` units on random seats of a table grid.

    Parameters
    ----------
    units : int
        Number of units U (>= 5).
    room : (3,) floats
        Room size L x W x H in metres.
    layout : {"flat", "boundary", "tiered", "stem", "hall"}
        See the module docstring.
    rng : Generator, int or None

    Returns
    -------
    ConferenceScene
        Microphone positions = loudspeaker positions + a 5-15 cm offset (30-50 cm vertical
        for ``stem``), delays U(0, 20 ms), onsets U(0, 30 ms) (004 sec. 2.2).

    Raises
    ------
    InputError
        Too few units, a room too small for the units, or an unknown layout.
    """
    check_choice(layout, "layout", LAYOUTS)
    gen = as_rng(rng)
    room_arr = np.asarray(room, dtype=float)
    if room_arr.shape != (3,) or not np.all(np.isfinite(room_arr)) or np.any(room_arr <= 0):
        raise InputError(f"room must be three positive lengths L x W x H in metres, got {room!r}")
    if int(units) != units or units < 5:
        raise InputError(f"units must be an integer >= 5, got {units!r}")
    seats, facing, _rows = _seats(room_arr, layout)
    if units > len(seats):
        raise InputError(f"a {room_arr[0]:g} x {room_arr[1]:g} m room seats at most {len(seats)} units; got {units}")
    pick = np.sort(gen.choice(len(seats), size=int(units), replace=False))
    desk, face = seats[pick], facing[pick]
    spk = desk + np.array([0.0, 0.0, SPEAKER_ABOVE_DESK])
    if layout == "stem":
        offset = np.column_stack([gen.uniform(-0.05, 0.05, (units, 2)), gen.uniform(0.30, 0.50, units)])
    elif layout == "boundary":
        length = gen.uniform(0.05, 0.15, units)
        az = gen.uniform(0.0, 2.0 * np.pi, units)
        offset = np.column_stack([length * np.cos(az), length * np.sin(az), gen.uniform(-0.01, 0.01, units)])
    else:
        # A gooseneck microphone 5-15 cm from the loudspeaker, leaning towards the seat.
        length = gen.uniform(0.05, 0.40 if layout == "hall" else 0.15, units)
        elev = np.radians(gen.uniform(20.0, 60.0, units))
        az = np.arctan2(face[:, 1], face[:, 0]) + np.radians(gen.uniform(-45.0, 45.0, units))
        offset = length[:, None] * np.column_stack([np.cos(elev) * np.cos(az), np.cos(elev) * np.sin(az), np.sin(elev)])
    mic = spk + offset
    if np.any(mic[:, 2] >= room_arr[2] - 0.1):
        raise InputError(f"room height {room_arr[2]:g} m is too low for the {layout} layout")
    delays = gen.uniform(0.0, 0.020, units)
    onsets = gen.uniform(0.0, 0.030, units)
    return ConferenceScene(mic, spk, delays, onsets, room_arr, layout)
