"""CMU range-only robot logs (Djugash et al., "Plaza" / gpslam ``.mat`` format): ``load_plaza(path)``.

The format (MATLAB v5) holds

* ``TL`` (B, 3) beacons ``[id, x, y]`` (metres);
* ``TD`` (K, 4) ranges ``[time s, sender id, beacon id, range m]`` (column 2 is the robot's
  radio, 2 on Plaza 1);
* ``GT`` (G, 4) ground truth ``[time s, x m, y m, heading rad]``;
* ``DR`` (M, 3) odometry increments ``[time s, delta distance m, delta heading rad]``;
* ``DRp`` a dead-reckoned path (not used, see below);
* ``init_heading_offset`` (1, 1) radians, possibly stored as an integer type.

Conventions honoured by :func:`load_plaza` (found in the data and the dataset's own MATLAB
examples; each has a test on a small synthetic file that breaks it):

1. **Heading.** The robot heading in which the odometry drives is
   ``GT(:, 4) + init_heading_offset`` (0 on Plaza 1, pi on other logs of the collection);
   :attr:`PlazaData.gt` holds the corrected heading, wrapped to ``[-pi, pi)``. The offset is
   read as a float whatever its stored type (Plaza 1 stores ``uint8``).
2. **Beacon ids.** A range's beacon is the row of ``TL`` whose ``TL(:, 1)`` equals the id in
   ``TD(:, 3)``; ids are arbitrary integers (Plaza 1: 0, 1, 6, 5) in any row order.
3. **Range order.** ``TD`` is not sorted by time (Plaza 1 has two backward jumps): rows are
   sorted by time with a stable sort (equal times keep their file order). ``DR`` and ``GT``
   are stably sorted the same way if they are not already.
4. **Odometry.** Each ``DR`` row composes as "drive ``dd`` along the current heading, then
   turn by ``dpsi``" (:func:`compose_odometry`); row ``k`` is the increment over
   ``(t_{k-1}, t_k]`` with ``t_{-1}`` the first ground-truth time (rows at or before it are
   dropped). ``DRp`` is not always the integral of ``DR`` (on Plaza 1 they part by 37 m), so
   the dead-reckoned path is integrated from ``DR`` (:meth:`PlazaData.dead_reckoning`).
5. **Units.** Headings in radians (``GT(:, 4)``, ``DR(:, 3)``); a column found to be in
   degrees by the tests of :func:`heading_units` is converted with a
   :class:`PlazaFormatWarning`, and a heading column that fits neither unit is refused
   (``load_plaza(heading_units="rad" | "deg")`` states the unit instead).
   Times may be in any unit (the model depends on distances and angles only, not on rates).
6. **Rows logged twice.** ``DR`` or ``TD`` rows that repeat the previous row exactly (time
   and values) are dropped with a :class:`PlazaFormatWarning`: an increment counted twice
   doubles the distance, a range counted twice halves its variance.
7. **No odometry.** A log whose ``DR`` distances are all zero is refused: the model has then
   no motion information and the track would stay at the first pose.
8. **Ranges are raw.** The loader does not correct them: they are several percent long
   (Plaza 1: about 7 %, a per-beacon scale plus an offset), which the range model of
   :mod:`selfcal.slac.ranging` estimates.

Ground truth is used by the estimators only for the first pose; the rest is for scoring.
"""

from __future__ import annotations

import os
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .._checks import MAX_ABS_ENTRY, entry
from ..errors import InputError
from ..geometry import wrap_angle

__all__ = ["PlazaData", "PlazaFormatWarning", "load_plaza", "compose_odometry"]

FArray = NDArray[np.float64]


def compose_odometry(start: FArray, odo: FArray) -> FArray:
    """Integrate odometry rows "drive along the heading, then turn" (convention 4).

    Parameters
    ----------
    start : (3,) initial pose ``[x, y, psi]`` (m, m, rad).
    odo : (M, 2) increments ``[dd, dpsi]`` (m, rad).

    Returns
    -------
    (M + 1, 3) poses; row 0 is ``start``, row ``k + 1`` is
    ``[x_k + dd_k cos psi_k, y_k + dd_k sin psi_k, psi_k + dpsi_k]`` (heading not wrapped).

    Examples
    --------
    >>> import numpy as np
    >>> compose_odometry(np.zeros(3), np.array([[1.0, np.pi / 2], [1.0, 0.0]])).round(6).tolist()
    [[0.0, 0.0, 0.0], [1.0, 0.0, 1.570796], [1.0, 1.0, 1.570796]]
    """
    start = np.asarray(start, dtype=float).reshape(3)
    odo = np.asarray(odo, dtype=float).reshape(-1, 2)
    psi = start[2] + np.concatenate([[0.0], np.cumsum(odo[:, 1])])
    step = odo[:, :1] * np.column_stack([np.cos(psi[:-1]), np.sin(psi[:-1])])
    xy = start[:2] + np.vstack([np.zeros((1, 2)), np.cumsum(step, axis=0)])
    return np.column_stack([xy, psi])


@dataclass(frozen=True)
class PlazaData:
    """A CMU range-only log as arrays (seconds, metres, radians), conventions applied.

    Attributes
    ----------
    beacon_ids : (B,) int
        ``TL(:, 1)`` in file order.
    beacons : (B, 2)
        Beacon positions.
    range_times, range_beacon, ranges : (K,)
        Range times (sorted, stable), index into ``beacons``, raw range (m).
    gt_times : (G,); gt : (G, 3)
        Ground truth ``[x, y, heading]`` with heading ``GT(:, 4) + init_heading_offset``.
    odo_times : (M,); odo : (M, 2)
        End time and ``[dd, dpsi]`` of each odometry increment after the first GT time.
    init_heading_offset : float
        Radians, as read from the file.
    ranges_dropped : int
        Beacon-to-beacon rows of ``TD`` left out.
    """

    beacon_ids: NDArray[np.int64]
    beacons: FArray
    range_times: FArray
    range_beacon: NDArray[np.int64]
    ranges: FArray
    gt_times: FArray
    gt: FArray
    odo_times: FArray
    odo: FArray
    init_heading_offset: float = 0.0
    ranges_dropped: int = 0

    @property
    def start_time(self) -> float:
        """Time of the first pose (the first ground-truth row)."""
        return float(self.gt_times[0])

    @property
    def start_pose(self) -> FArray:
        """(3,) first ground-truth pose with the corrected heading."""
        return self.gt[0].copy()

    @property
    def pose_times(self) -> FArray:
        """(M + 1,) times of the estimated poses: the start, then each odometry row's end."""
        return np.concatenate([[self.start_time], self.odo_times])

    def dead_reckoning(self) -> FArray:
        """(M + 1, 3) path integrated from ``DR`` alone, starting at :attr:`start_pose`."""
        return compose_odometry(self.start_pose, self.odo)

    def gt_at(self, times: FArray) -> FArray:
        """Ground truth interpolated at ``times`` (K,) -> (K, 3); heading unwrapped, then wrapped."""
        t = np.asarray(times, dtype=float)
        psi = np.unwrap(self.gt[:, 2])
        out = np.column_stack([np.interp(t, self.gt_times, self.gt[:, 0]), np.interp(t, self.gt_times, self.gt[:, 1]),
                               np.interp(t, self.gt_times, psi)])
        out[:, 2] = wrap_angle(out[:, 2])
        return out


class PlazaFormatWarning(UserWarning):
    """A CMU range log deviates from the documented layout in a way the loader can repair."""


DEG = float(np.rad2deg(1.0))  # 57.3: a degree column read as radians is this factor too large
R_FIT, R_MARGIN = 0.7, 0.3  # mean resultant length that "explains the motion", and the margin over the other unit


def _resultant(a: FArray) -> float:
    return float(np.abs(np.mean(np.exp(1j * a)))) if a.size else 0.0


def heading_units(GT: FArray, DR: FArray, step: float = 0.5) -> tuple[str, str, dict[str, float]]:
    """Decide whether the heading columns of a CMU log are in radians or degrees.

    Parameters
    ----------
    GT : (G, 4) ``[time, x, y, heading]`` sorted by time; DR : (M, 3) ``[time, dd, dpsi]``.
    step : metres of ground-truth travel per direction sample.

    Returns
    -------
    (gt_unit, dr_unit, stats) : each unit "rad", "deg" or "?" (undecided), and the statistics.

    Notes
    -----
    *Ground-truth heading.* The robot drives along its heading (convention 4), so the
    direction of motion ``phi`` of the ground-truth track (sampled every ``step`` metres)
    minus the heading is a constant (the ``init_heading_offset``) plus noise. Its mean
    resultant length ``R = |mean exp(i (phi - h))|`` is near 1 for the right unit whatever
    the constant. Read in the wrong unit a degree column turns 57 times too fast (``R`` near
    the Rayleigh level ``1 / sqrt(n)``), while a radian column read as degrees turns 57 times
    too slowly (nearly constant: ``R`` stays high on a straight drive). So the evidence for
    degrees is ``R_deg`` high *and* well above ``R_rad``: degrees when ``R_deg >= 0.7`` and
    ``R_deg - R_rad >= 0.3``, radians when ``R_rad >= 0.7`` otherwise, undecided else (a
    radian column fits with ``R_rad`` near 1: 0.997 on Plaza 1, 1.00 on simulated logs).

    *Odometry heading.* The odometry's total turn ``sum |Delta psi_DR|`` between the direction
    samples against the ground truth's ``sum |wrap(Delta h)|``: about 1 in radians (the
    odometry's heading error is a few percent), 57.3 in degrees. Degrees are decided when the
    ratio is within a factor 2 of 57.3 and the ground truth turned more than half a radian in
    total (radians within a factor 2 of 1; undecided otherwise).
    """
    t, xy = GT[:, 0], GT[:, 1:3]
    seg = np.linalg.norm(np.diff(xy, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    out: dict[str, float] = {"travel_m": float(s[-1])}
    if s[-1] < 2 * step:
        return "?", "?", out
    idx = np.unique(np.searchsorted(s, np.arange(0.0, s[-1], step)))
    idx = idx[idx < t.size]
    d = np.diff(xy[idx], axis=0)
    phi = np.arctan2(d[:, 1], d[:, 0])
    h = GT[idx[:-1], 3]
    r_rad, r_deg = _resultant(phi - h), _resultant(phi - np.deg2rad(h))
    out.update(r_rad=r_rad, r_deg=r_deg, n=float(phi.size))
    gt_unit = "deg" if (r_deg >= R_FIT and r_deg - r_rad >= R_MARGIN) else ("rad" if r_rad >= R_FIT else "?")
    hh = GT[idx, 3] if gt_unit != "deg" else np.deg2rad(GT[idx, 3])
    turn_gt = float(np.sum(np.abs(np.angle(np.exp(1j * np.diff(hh))))))
    cum = np.concatenate([[0.0], np.cumsum(DR[:, 2])])
    at = np.searchsorted(DR[:, 0], t[idx], side="right")  # DR rows up to each sample's time
    turn_dr = float(np.sum(np.abs(np.diff(cum[at]))))
    out.update(turn_gt=turn_gt, turn_dr=turn_dr)
    dr_unit = "?"
    if turn_gt > 0.5 and gt_unit != "?" and turn_dr > 0:
        ratio = turn_dr / turn_gt
        out["turn_ratio"] = ratio
        dr_unit = "deg" if abs(np.log(ratio / DEG)) < np.log(2) else ("rad" if abs(np.log(ratio)) < np.log(2) else "?")
    return gt_unit, dr_unit, out


def _drop_repeated_rows(a: FArray, name: str, p: Path) -> FArray:
    """Rows equal to the previous row in every column (after the stable time sort) are dropped."""
    if a.shape[0] < 2:
        return a
    rep = np.concatenate([[False], np.all(a[1:] == a[:-1], axis=1)])
    if rep.any():
        warnings.warn(f"{p}: {name} has {int(rep.sum())} rows that repeat the previous row exactly (time and "
                      "values); they are taken as logged twice and dropped", PlazaFormatWarning, stacklevel=3)
    return a[~rep]


def _field(m: dict[str, Any], key: str, width: int, p: Path) -> FArray:
    if key not in m:
        raise InputError(f"{p}: missing variable {key!r} (a CMU range log has TL, TD, GT, DR, init_heading_offset)")
    a = m[key]
    if hasattr(a, "toarray"):  # a MATLAB sparse matrix (scipy.sparse): the same numbers
        a = a.toarray()
    a = np.asarray(a)
    if a.ndim != 2 or a.shape[0] < 1 or a.shape[1] < width:
        raise InputError(f"{p}: {key} must be a (rows, {width}) array, got shape {a.shape}")
    if not np.issubdtype(a.dtype, np.number) or np.iscomplexobj(a):
        raise InputError(f"{p}: {key} must be real numbers, got dtype {a.dtype}")
    a = a[:, :width].astype(float)
    bad = ~np.isfinite(a)
    if bad.any():
        r, c = np.argwhere(bad)[0]
        raise InputError(f"{p}: {key} has a non-finite value at row {r + 1}, column {c + 1}")
    big = np.abs(a) > MAX_ABS_ENTRY  # squares and sums of such values overflow float64
    if big.any():
        r, c = np.argwhere(big)[0]
        raise InputError(f"{p}: {key} row {r + 1}, column {c + 1} = {a[r, c]:.3g} is beyond {MAX_ABS_ENTRY:.2g}, "
                         f"which double precision cannot process; is the file corrupt?")
    return a


def _heading_offset(value: float, name: str) -> float:
    """A heading offset in radians: finite and within one turn (beyond 2 pi it is most likely
    degrees, e.g. 180 for pi; 1e308 rad has no meaningful angle since its ulp exceeds 2 pi)."""
    if not np.isfinite(value):
        raise InputError(f"{name} is not finite")
    if abs(value) > 2 * np.pi + 1e-9:
        hint = f" (180 deg = pi rad; {value:g} deg = {np.deg2rad(value):.4g} rad)" if abs(value) <= 360 else ""
        raise InputError(f"{name} = {value:.4g} rad exceeds one turn (2 pi); give radians, not degrees{hint}")
    return value


#: Values of ``load_plaza(heading_units=...)``: detect (default), or the unit of both heading columns.
HEADING_UNITS = ("auto", "rad", "deg")


def _heading_columns(GT: FArray, DR: FArray, p: Path, units: str = "auto") -> tuple[FArray, FArray]:
    if units != "auto":  # the caller's word wins over the detection (no test, no warning)
        if units == "deg":
            GT, DR = GT.copy(), DR.copy()
            GT[:, 3] = np.deg2rad(GT[:, 3])
            DR[:, 2] = np.deg2rad(DR[:, 2])
        return GT, DR
    gt_u, dr_u, st = heading_units(GT, DR)
    beyond = float(np.max(np.abs(GT[:, 3])))
    if gt_u == "deg":
        warnings.warn(f"{p}: GT heading column is in degrees (it fits the direction of motion as degrees, mean "
                      f"resultant {st['r_deg']:.2f}, not as radians, {st['r_rad']:.2f}); converted to radians",
                      PlazaFormatWarning, stacklevel=3)
        GT = GT.copy()
        GT[:, 3] = np.deg2rad(GT[:, 3])
    elif gt_u == "?" and beyond > 2 * np.pi + 1e-9 and "r_rad" in st:
        raise InputError(f"{p}: GT heading column reaches {beyond:.4g}, beyond one turn, and fits the direction of "
                         f"motion neither as radians (mean resultant {st['r_rad']:.2f}) nor as degrees "
                         f"({st['r_deg']:.2f}); give headings in radians")
    if dr_u == "deg":
        warnings.warn(f"{p}: DR heading increments are in degrees (their total turn is {st['turn_ratio']:.1f} x the "
                      "ground truth's); converted to radians", PlazaFormatWarning, stacklevel=3)
        DR = DR.copy()
        DR[:, 2] = np.deg2rad(DR[:, 2])
    return GT, DR


@entry(path="path")  # heading_units: checked in the body against its choices
def load_plaza(path: str | os.PathLike[str], *, init_heading_offset: float | None = None,
               heading_units: str | None = None) -> PlazaData:
    """Load a CMU range-only log (``Plaza1.mat`` and others of the collection) and validate it.

    Parameters
    ----------
    path : str or path-like
        The user's copy of the ``.mat`` file.
    init_heading_offset : float, optional
        Radians; required only when the file lacks ``init_heading_offset`` (a value in the
        file wins over nothing, and giving both raises unless they agree).
    heading_units : {"auto", "rad", "deg"}, optional
        Unit of the heading columns ``GT(:, 4)`` and ``DR(:, 3)``. ``"auto"`` (default, or
        None) decides it per column with :func:`heading_units` (a degree column is converted
        with a :class:`PlazaFormatWarning`); ``"rad"`` or ``"deg"`` is taken as given for both
        columns, without the test or the warning.

    Returns
    -------
    PlazaData
        The log with conventions 1-5 of the module docstring applied.

    Raises
    ------
    InputError
        One line naming the file and the field: missing file or variable, unreadable file,
        wrong shape, non-numeric or non-finite values, negative ranges, duplicate beacon ids,
        ranges to beacons that ``TL`` does not list, no odometry after the first GT time.

    Examples
    --------
    >>> from selfcal.datasets import load_plaza
    >>> d = load_plaza("../shared/data/plaza/Plaza1.mat")  # doctest: +SKIP
    >>> d.beacons.shape, d.init_heading_offset  # doctest: +SKIP
    ((4, 2), 0.0)
    """
    p = Path(path)
    units = "auto" if heading_units is None else heading_units
    if not isinstance(units, str) or units not in HEADING_UNITS:
        raise InputError(f"heading_units must be one of {', '.join(map(repr, HEADING_UNITS))}, got {heading_units!r}")
    if not p.exists():
        raise InputError(f"{p}: file not found")
    if not p.is_file():
        raise InputError(f"{p}: {'is a directory' if p.is_dir() else 'not a regular file'}; give a .mat file")
    try:
        from scipy.io import loadmat

        m = loadmat(p)
    except Exception as exc:  # scipy raises several types for non-MAT input
        raise InputError(f"{p}: not a readable MATLAB file ({type(exc).__name__})") from None
    TL = _field(m, "TL", 3, p)
    TD = _field(m, "TD", 4, p)
    GT = _field(m, "GT", 4, p)
    DR = _field(m, "DR", 3, p)
    if init_heading_offset is not None:
        init_heading_offset = _heading_offset(float(init_heading_offset), "--init-heading-offset")
    if "init_heading_offset" in m:
        o = np.asarray(m["init_heading_offset"])
        if o.size != 1 or not np.issubdtype(o.dtype, np.number) or np.iscomplexobj(o):
            raise InputError(f"{p}: init_heading_offset must be one real number, got shape {o.shape} dtype {o.dtype}")
        offset = _heading_offset(float(o.astype(float).ravel()[0]), f"{p}: init_heading_offset")  # convention 1
        if init_heading_offset is not None and not np.isclose(float(wrap_angle(init_heading_offset - offset)), 0.0):
            raise InputError(f"{p}: init_heading_offset={init_heading_offset} disagrees with the file's {offset}")
    elif init_heading_offset is not None:
        offset = init_heading_offset
    else:
        raise InputError(f"{p}: missing variable 'init_heading_offset' (pass init_heading_offset= if the log has none)")
    if np.any(TL[:, 0] != np.round(TL[:, 0])):
        raise InputError(f"{p}: TL column 1 (beacon ids) must hold integers")
    ids = TL[:, 0].astype(np.int64)
    if np.unique(ids).size != ids.size:
        raise InputError(f"{p}: TL lists a beacon id twice")
    lookup = {int(b): k for k, b in enumerate(ids)}
    sender_is_beacon = np.isin(TD[:, 1], ids)
    dropped = 0
    if sender_is_beacon.any() and not sender_is_beacon.all():
        dropped = int(sender_is_beacon.sum())
        TD = TD[~sender_is_beacon]
    unknown = sorted({float(b) for b in TD[:, 2]} - {float(b) for b in ids})
    if unknown:
        raise InputError(f"{p}: TD refers to beacons {unknown[:5]} that TL does not list")
    if np.any(TD[:, 3] < 0):
        raise InputError(f"{p}: TD column 4 (ranges) has negative values")
    TD = TD[np.argsort(TD[:, 0], kind="stable")]  # convention 3
    GT = GT[np.argsort(GT[:, 0], kind="stable")]
    DR = DR[np.argsort(DR[:, 0], kind="stable")]
    DR = _drop_repeated_rows(DR, "DR", p)  # convention 6
    TD = _drop_repeated_rows(TD, "TD", p)
    if not np.any(DR[:, 1] != 0):  # convention 7
        raise InputError(f"{p}: DR distances are all zero (no odometry): the model has no motion information and "
                         "would keep the robot at its first pose; a range-only track is not supported")
    GT, DR = _heading_columns(GT, DR, p, units)  # convention 5
    t0 = GT[0, 0]
    DR = DR[DR[:, 0] > t0]  # convention 4: increments after the start pose
    if DR.shape[0] < 1:
        raise InputError(f"{p}: DR has no odometry after the first GT time {t0}")
    inside = (TD[:, 0] > t0) & (TD[:, 0] <= DR[-1, 0])
    if not inside.any():  # nothing to calibrate with: the run would be dead reckoning reported as a result
        raise InputError(f"{p}: no TD range falls in the span of the odometry (first GT time {t0:.6g} s to the last "
                         f"DR time {DR[-1, 0]:.6g} s; ranges span {TD[:, 0].min():.6g} .. {TD[:, 0].max():.6g} s); "
                         "are the time columns in the same clock?")
    gt = GT[:, 1:4].copy()
    gt[:, 2] = wrap_angle(gt[:, 2] + offset)  # convention 1
    return PlazaData(
        beacon_ids=ids, beacons=TL[:, 1:3].copy(), range_times=TD[:, 0].copy(),
        range_beacon=np.array([lookup[int(b)] for b in TD[:, 2]], dtype=np.int64), ranges=TD[:, 3].copy(),
        gt_times=GT[:, 0].copy(), gt=gt, odo_times=DR[:, 0].copy(), odo=DR[:, 1:3].copy(),
        init_heading_offset=offset, ranges_dropped=dropped,
    )
