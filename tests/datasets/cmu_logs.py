"""Seeded generator of CMU range-only robot logs (the ``Plaza1.mat`` layout) with ground truth.

Other logs of the collection (Plaza 2, Gesling, ...) differ from Plaza 1 in ways a loader and
the range-SLAC estimator must survive: another ``init_heading_offset`` (pi on some logs),
more or fewer beacons with arbitrary ids in any row order, ``TD`` not sorted by time with
several ranges at one time stamp, ranges with a per-beacon scale and offset plus multipath
outliers, a beacon listed in ``TL`` but never heard, odometry with long gaps (the encoder
increment after a gap covers the whole gap). :func:`cmu_log` draws such a log; the truth is
returned beside the ``.mat`` dict so the tests can score against it.

Noise levels are those of Plaza 1 (measured on the shared file): ranges ~0.1-0.3 m after the
scale correction, odometry at 5 Hz, ranges at ~4 Hz round-robin, a robot at ~1 m/s.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from selfcal.datasets.plaza import compose_odometry


@dataclass
class CmuTruth:
    """Ground truth of a generated log (heading in the odometry frame)."""

    times: np.ndarray  # (N + 1,) pose times
    poses: np.ndarray  # (N + 1, 3)
    beacon_ids: np.ndarray  # (B,) in TL row order
    beacons: np.ndarray  # (B, 2)
    scale: np.ndarray  # (B,)
    offset: np.ndarray  # (B,)
    heard: np.ndarray  # (B,) bool: the beacon has ranges in TD
    range_noise: float


def cmu_log(seed: int, *, n_beacons: int = 4, heading_offset: float = 0.0, duration: float = 240.0,
            ids: list[int] | None = None, silent: int = 0, unsorted: bool = True, duplicates: bool = True,
            gaps: int = 0, gap_seconds: float = 8.0, outliers: float = 0.03, range_noise: float = 0.15,
            heading_offset_dtype: Any = float, far_beacon: float = 0.0, brief: int = 0, brief_seconds: float = 15.0,
            dropouts: int = 0, dropout_seconds: float = 30.0, odo_scale: float = 1.0, stand: int = 0,
            stand_seconds: float = 30.0, dr_duplicates: float = 0.0, time_scale: float = 1.0,
            heading_degrees: bool = False, zero_odometry: bool = False,
            range_scale: tuple[float, float] = (0.02, 0.09), range_tail: str = "gauss") -> tuple[dict[str, Any], CmuTruth]:
    """A CMU-style log (``TL``, ``TD``, ``GT``, ``DR``, ``DRp``, ``init_heading_offset``) and its truth.

    Parameters
    ----------
    seed : random seed (everything is drawn from it).
    n_beacons : beacons in ``TL``; ids : their ids (default: distinct random integers 0..99).
    heading_offset : radians; ``GT(:, 4)`` is stored as the true heading minus it.
    duration : seconds of driving (odometry at 5 Hz, ~1 m/s on a smooth random path).
    silent : how many beacons (the last ``silent`` TL rows) are never heard.
    unsorted : shuffle ``TD`` in blocks (not sorted by time); duplicates : pairs of ranges
        at one time stamp (two beacons answering in one cycle).
    gaps : odometry gaps of ``gap_seconds`` (rows removed; the row after a gap holds the
        whole gap's increment, as an encoder counter does).
    outliers : fraction of ranges lengthened by multipath (2-10 m, one-sided).
    range_noise : Gaussian range noise (m).
    far_beacon : > 0 moves the last beacon this far (m) outside the path's extent.
    brief : how many beacons (the first ``brief`` heard TL rows) answer only during one
        window of ``brief_seconds``.
    dropouts : windows of ``dropout_seconds`` without any range (radio outage).
    odo_scale : the odometry's distances are this factor times the true ones (wheel radius).
    stand : stretches of ``stand_seconds`` where the robot stands still (zero increments,
        ranges keep coming).
    dr_duplicates : fraction of ``DR`` rows the logger wrote twice (identical rows).
    range_scale : (low, high) of each beacon's range-scale error ``s_b - 1`` (uniform draw; the
        draw is made in every case, so (0, 0) gives the same log with exact scales).
    time_scale : every time column is multiplied by it (1000: milliseconds).
    heading_degrees : ``GT(:, 4)`` and ``DR(:, 3)`` are written in degrees.
    zero_odometry : ``DR``'s increments are all zero (a log without working encoders).
    range_tail : distribution of the range noise: ``"gauss"`` (std ``range_noise``), ``"t3"``
        (Student t with 3 degrees of freedom, scale ``range_noise``: heavy tails, infinite
        kurtosis) or ``"laplace"`` (std ``range_noise``, kurtosis 3 above the Gaussian's).

    The options after ``heading_offset_dtype`` draw from a second generator, so a log drawn
    without them is the same as before they existed.
    """
    g = np.random.default_rng(seed)
    dt = 0.2
    n = int(duration / dt)
    # smooth random drive inside the beacons' area: speed ~1 m/s, a slowly varying turn rate
    v = 1.0 + 0.2 * np.sin(np.arange(n) / 40.0 + g.uniform(0, 6))
    w = np.convolve(g.normal(0, 0.15, n), np.ones(25) / 25, mode="same")
    g2 = np.random.default_rng([seed, 1])
    if stand:
        span = int(stand_seconds / dt)
        for s0 in np.sort(g2.choice(np.arange(20, max(21, n - span - 20)), stand, replace=False)):
            v[s0:s0 + span] = 0.0
            w[s0:s0 + span] = 0.0
    odo_true = np.column_stack([v * dt, w * dt])
    start = np.array([g.uniform(-5, 5), g.uniform(-5, 5), g.uniform(-np.pi, np.pi)])
    poses = compose_odometry(start, odo_true)
    t0 = 3000.0 + g.uniform(0, 1000)
    times = t0 + dt * np.arange(n + 1)
    # beacons around the path's extent
    lo, hi = poses[:, :2].min(0) - 15, poses[:, :2].max(0) + 15
    B = n_beacons
    beacons = g.uniform(lo, hi, (B, 2))
    if far_beacon > 0:
        ang = g2.uniform(0, 2 * np.pi)
        centre, half = (lo + hi) / 2, np.max(hi - lo) / 2
        beacons[B - 1] = centre + (half + far_beacon) * np.array([np.cos(ang), np.sin(ang)])
    bid = np.asarray(ids if ids is not None else g.choice(100, B, replace=False), dtype=np.int64)
    scale = 1.0 + g.uniform(range_scale[0], range_scale[1], B)  # default: several percent long, as on Plaza 1
    offset = g.uniform(-0.8, 0.8, B)
    heard = np.ones(B, dtype=bool)
    if silent:
        heard[B - silent:] = False
    # odometry: multiplicative distance error + heading noise per row
    odo_meas = odo_true * np.column_stack([1 + g.normal(0, 0.01, n), np.ones(n)])
    odo_meas[:, 1] += g.normal(0, 0.002, n)
    odo_meas[:, 0] *= odo_scale
    odo_meas[v == 0] = 0.0  # a standing robot's encoders do not move
    keep = np.ones(n, dtype=bool)
    if gaps:
        span = int(gap_seconds / dt)
        starts = np.sort(g.choice(np.arange(50, n - span - 50), gaps, replace=False))
        for s0 in starts:
            keep[s0:s0 + span] = False
    # the row after a removed stretch holds the stretch's increment (an encoder counter)
    acc = np.zeros(2)
    dr_rows = []
    for k in range(n):
        acc += odo_meas[k]
        if keep[k]:
            dr_rows.append([times[k + 1], acc[0], acc[1]])
            acc = np.zeros(2)
    DR = np.array(dr_rows)
    # ranges: round-robin over the heard beacons every 0.25 s at times between odometry times
    heard_idx = np.flatnonzero(heard)
    rt = np.arange(times[0] + 0.1, times[-1] - 0.1, 0.25)
    rb = heard_idx[np.arange(rt.size) % heard_idx.size]
    if duplicates:  # every 7th cycle a second beacon answers at the same time stamp
        k = np.arange(0, rt.size, 7)
        rt = np.concatenate([rt, rt[k]])
        rb = np.concatenate([rb, heard_idx[(np.arange(k.size) + 1) % heard_idx.size]])
    keep_r = np.ones(rt.size, dtype=bool)
    for b in heard_idx[:brief]:
        a = g2.uniform(times[0], times[-1] - brief_seconds)
        keep_r &= (rb != b) | ((rt >= a) & (rt < a + brief_seconds))
    for _ in range(dropouts):
        a = g2.uniform(times[0] + 10, times[-1] - dropout_seconds - 10)
        keep_r &= (rt < a) | (rt >= a + dropout_seconds)
    rt, rb = rt[keep_r], rb[keep_r]
    px = np.interp(rt, times, poses[:, 0])
    py = np.interp(rt, times, poses[:, 1])
    d = np.hypot(px - beacons[rb, 0], py - beacons[rb, 1])
    r = scale[rb] * d + offset[rb] + g.normal(0, range_noise, rt.size)
    if range_tail == "t3":  # drawn from the second generator: the rest of the log is unchanged
        r += range_noise * g2.standard_t(3, rt.size) - (r - scale[rb] * d - offset[rb])
    elif range_tail == "laplace":
        r += g2.laplace(0, range_noise / np.sqrt(2), rt.size) - (r - scale[rb] * d - offset[rb])
    elif range_tail != "gauss":
        raise ValueError(f"range_tail must be 'gauss', 't3' or 'laplace', got {range_tail!r}")
    out = g.random(rt.size) < outliers
    r[out] += g.uniform(2, 10, out.sum())
    r = np.abs(r)
    TD = np.column_stack([rt, np.full(rt.size, 2.0), bid[rb].astype(float), r])
    TD = TD[np.argsort(TD[:, 0], kind="stable")]
    if unsorted:  # blocks of rows out of order, as the logger wrote them
        blocks = np.array_split(np.arange(TD.shape[0]), max(2, TD.shape[0] // 200))
        order = np.concatenate([blocks[i] for i in g.permutation(len(blocks))])
        TD = TD[order]
    if dr_duplicates > 0:
        rep = g2.random(DR.shape[0]) < dr_duplicates
        DR = np.concatenate([DR, DR[rep]])
        DR = DR[np.argsort(DR[:, 0], kind="stable")]
    if zero_odometry:
        DR[:, 1:] = 0.0
    GT = np.column_stack([times, poses[:, 0], poses[:, 1], poses[:, 2] - heading_offset])
    if heading_degrees:
        GT[:, 3] = np.rad2deg(np.mod(GT[:, 3], 2 * np.pi))  # a compass-style 0..360 column
        DR[:, 2] = np.rad2deg(DR[:, 2])
    if time_scale != 1.0:
        GT[:, 0] *= time_scale
        DR[:, 0] *= time_scale
        TD[:, 0] *= time_scale
    tl_order = g.permutation(B)
    TL = np.column_stack([bid[tl_order].astype(float), beacons[tl_order]])
    drp = compose_odometry(start, odo_meas)
    m = {"TL": TL, "TD": TD, "GT": GT, "DR": DR, "DRp": np.column_stack([times, drp]),
         "init_heading_offset": np.array([[heading_offset]], dtype=heading_offset_dtype)}
    truth = CmuTruth(times=times * time_scale, poses=poses, beacon_ids=bid[tl_order], beacons=beacons[tl_order],
                     scale=scale[tl_order], offset=offset[tl_order], heard=heard[tl_order], range_noise=range_noise)
    return m, truth
