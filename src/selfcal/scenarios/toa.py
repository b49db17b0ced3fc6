"""Synthetic TOA / range scenarios: the 003 simulation set-up and random rooms.

Every builder returns a :class:`ToaScenario` (ground truth + the noisy range matrix, rows =
receivers, columns = transmitters, NaN = missing) and is reproducible from its ``rng``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .._checks import as_rng, check_dim
from ..errors import InputError
from ..geometry import pairwise_distances

__all__ = [
    "ToaScenario",
    "paper003_source_angles",
    "paper003_sources",
    "paper003_network",
    "random_room",
    "noisy_ranges",
]

Array = NDArray[np.float64]


@dataclass(frozen=True)
class ToaScenario:
    """A simulated anchor-free TOA problem.

    Attributes
    ----------
    receivers: (I, d) true receiver (sensor) positions, metres.
    sources: (J, d) true transmitter (source) positions, metres.
    ranges: (I, J) measured ranges, metres; NaN = missing.
    clean_ranges: (I, J) noise-free ``|r_i - s_j|`` (all entries).
    sigma: standard deviation of the additive Gaussian range noise, metres.
    name: short description of the set-up.
    """

    receivers: Array
    sources: Array
    ranges: Array
    clean_ranges: Array
    sigma: float
    name: str

    @property
    def dim(self) -> int:
        """Spatial dimension d."""
        return int(self.receivers.shape[1])

    def to_dict(self) -> dict[str, Any]:
        """JSON-safe dict (NaN -> null is done by :func:`selfcal.io.write_json`)."""
        return {
            "name": self.name,
            "sigma": self.sigma,
            "receivers": self.receivers.tolist(),
            "sources": self.sources.tolist(),
            "ranges": self.ranges.tolist(),
        }


def paper003_source_angles(n_sources: int) -> Array:
    """Source angles of 003 eq. 12a: ``phi_k = ((k-1)/K + (1 + (-1)^k)/2) pi``, k = 1..K (rad).

    Odd k walk the upper half circle from 0 in steps of 2 pi / K; even k sit on the opposite
    side, offset by pi / K, so consecutive sources alternate across the network.
    """
    if n_sources < 1:
        raise InputError(f"n_sources must be >= 1, got {n_sources}")
    k = np.arange(1, n_sources + 1)
    return ((k - 1) / n_sources + (1 + (-1.0) ** k) / 2) * np.pi


def paper003_sources(n_sources: int, radius: float = 7.0, dim: int = 2,
                     elevation: float = np.deg2rad(30.0),
                     rng: np.random.Generator | int | None = None) -> Array:
    """Source positions of 003 eq. 12b on a circle of radius ``radius`` (m) around the origin.

    In 3-D (our extension; 003 is 2-D only) the azimuths still follow eq. 12a, but each
    source gets a random elevation in ``[-elevation, elevation]`` and a random distance in
    ``[0.75, 1] * radius`` (from ``rng``). Any regular 3-D pattern we tried puts all sources
    on one quadric (sphere, cone, cylinder), which with 8-10 sources leaves the TOA problem
    (nearly) ambiguous: with sources on a sphere 70 % of the 8 x 10 runs did not converge
    to the truth, with this layout 5 % (measured, sigma = 1 cm). Returns (K, dim).
    """
    dim = check_dim(dim)
    phi = paper003_source_angles(n_sources)
    if dim == 2:
        return radius * np.column_stack([np.cos(phi), np.sin(phi)])
    gen = as_rng(rng)
    el = gen.uniform(-elevation, elevation, n_sources)
    rad = radius * gen.uniform(0.75, 1.0, n_sources)
    return rad[:, None] * np.column_stack([np.cos(el) * np.cos(phi), np.cos(el) * np.sin(phi), np.sin(el)])


def noisy_ranges(clean: Array, sigma: float, rng: np.random.Generator, *,
                 missing_fraction: float = 0.0, clip: bool = True) -> Array:
    """Add i.i.d. ``N(0, sigma^2)`` noise (003 eq. 1c) and drop a random fraction of entries.

    ``clip`` keeps ranges non-negative (a measured range cannot be negative); it only bites
    when ``sigma`` is comparable to the shortest distances.
    """
    if sigma < 0:
        raise InputError(f"sigma must be >= 0, got {sigma}")
    if not 0.0 <= missing_fraction < 1.0:
        raise InputError(f"missing_fraction must be in [0, 1), got {missing_fraction}")
    Y = clean + sigma * rng.standard_normal(clean.shape)
    if clip:
        Y = np.maximum(Y, 0.0)
    if missing_fraction > 0:
        Y = np.where(rng.random(clean.shape) < missing_fraction, np.nan, Y)
    return Y


def paper003_network(
    n_sensors: int = 8,
    n_sources: int = 10,
    *,
    area: float = 10.0,
    radius: float = 7.0,
    sigma: float = 0.30,
    dim: int = 2,
    height: float = 3.0,
    rng: np.random.Generator | int | None = None,
) -> ToaScenario:
    """The simulated network of 003 Table I (defaults are the paper's values).

    N sensors uniform in an ``area`` x ``area`` square centred at the origin (in 3-D also
    uniform in height over ``[-height/2, height/2]``), K sources by eq. 12 on a circle of
    radius ``radius`` around the centre (3-D: see :func:`paper003_sources`), ranges with
    Gaussian noise of std ``sigma``.
    A new network is drawn for each call, as in the paper's Monte Carlo runs.
    """
    dim = check_dim(dim)
    gen = as_rng(rng)
    if n_sensors < 1:
        raise InputError(f"n_sensors must be >= 1, got {n_sensors}")
    rec = gen.uniform(-area / 2, area / 2, size=(n_sensors, dim))
    if dim == 3:
        rec[:, 2] = gen.uniform(-height / 2, height / 2, size=n_sensors)
    src = paper003_sources(n_sources, radius, dim, rng=gen)
    clean = pairwise_distances(rec, src)
    Y = noisy_ranges(clean, sigma, gen)
    return ToaScenario(rec, src, Y, clean, float(sigma), f"paper003-{dim}d-N{n_sensors}-K{n_sources}")


def random_room(
    n_receivers: int,
    n_sources: int,
    *,
    dim: int = 3,
    room: tuple[float, ...] | None = None,
    sigma: float = 0.01,
    missing_fraction: float = 0.0,
    rng: np.random.Generator | int | None = None,
) -> ToaScenario:
    """Receivers and sources uniform in a random (or given) box-shaped room.

    ``room`` is the box size in metres (length, width[, height]); by default it is drawn as
    length, width ~ U(4, 12) m and height ~ U(2.5, 4) m. Both point sets fill the room, so
    transmitters are inside the receiver hull (the harder case for 003 eq. 11).
    """
    dim = check_dim(dim)
    gen = as_rng(rng)
    if room is None:
        size = [gen.uniform(4.0, 12.0), gen.uniform(4.0, 12.0)]
        if dim == 3:
            size.append(gen.uniform(2.5, 4.0))
        box = np.asarray(size)
    else:
        box = np.asarray(room, float)
        if box.shape != (dim,) or not (box > 0).all():
            raise InputError(f"room must be {dim} positive lengths, got {room!r}")
    rec = gen.uniform(0.0, 1.0, size=(n_receivers, dim)) * box
    src = gen.uniform(0.0, 1.0, size=(n_sources, dim)) * box
    clean = pairwise_distances(rec, src)
    Y = noisy_ranges(clean, sigma, gen, missing_fraction=missing_fraction)
    return ToaScenario(rec, src, Y, clean, float(sigma), f"room-{dim}d-{n_receivers}x{n_sources}")
