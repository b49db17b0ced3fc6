"""Exceptions, warnings and the diagnostics vocabulary shared by every solver.

Every entry point validates its input and raises one of these with a message that
says what was wrong and what would fix it; the command line turns them into one
line on stderr and exit status 2.

The vocabulary has three registries, each a ``str``/``int`` enum so that old code
comparing with plain strings keeps working (``Degeneracy.CONE == "cone"``):

* :class:`Degeneracy`: why the geometry does not determine the unknowns (the ``kind``
  of a :class:`DegenerateGeometryError`, a far-field result's ``degeneracy``), each with
  an explanation (:attr:`Degeneracy.explanation`);
* :class:`Status`: the state of a whole result (``result.status``, SciPy
  ``OptimizeResult`` style, 0 = success);
* :class:`Flag`: what happened to one measurement or node (missing, outlier, dropped).
"""

from __future__ import annotations

from enum import IntEnum, StrEnum

__all__ = [
    "SelfcalError",
    "InputError",
    "DegenerateGeometryError",
    "ConvergenceWarning",
    "Degeneracy",
    "Status",
    "Flag",
]


class Degeneracy(StrEnum):
    """Registry of degeneracy kinds: the geometry (or the data) does not fix the unknowns.

    Members compare equal to their string value (``Degeneracy.CONE == "cone"``), so a
    ``kind`` may be given or tested either way. ``Degeneracy.CONE.explanation`` is one
    sentence a user can act on.
    """

    explanation: str

    def __new__(cls, value: str, explanation: str = "") -> Degeneracy:
        obj = str.__new__(cls, value)
        obj._value_ = value
        obj.explanation = explanation
        return obj

    # counting: not enough nodes or measurements (any method)
    TOO_FEW_RECEIVERS = ("too-few-receivers", "fewer receivers than the dimension and model need")
    TOO_FEW_SOURCES = ("too-few-sources", "fewer transmitters than the dimension and model need")
    TOO_FEW_POINTS = ("too-few-points", "classical MDS needs at least d + 1 points")
    TOO_FEW_UNITS = ("too-few-units", "the rank-d offset method (004) needs (I-1-d)(J-1-d) >= I+J-1")
    TOO_FEW_MEASUREMENTS = ("too-few-measurements", "fewer observed entries than free parameters")
    TOO_FEW_BEACONS = ("too-few-beacons", "a pose from bearings needs at least three beacons")
    NO_DETECTIONS = ("no-detections", "no arrival was detected in any recording")
    # observability of one node / of the network
    UNOBSERVABLE_NODE = ("unobservable-node", "a node has too few or collinear ranges to be located")
    UNOBSERVABLE_AGENT = ("unobservable-agent", "a SLAC agent's links do not determine its position")
    DISCONNECTED = ("disconnected", "the network splits into groups that share no transmitter")
    # shape of the geometry (TOA)
    DEGENERATE_GEOMETRY = ("degenerate-geometry",
                           "the points do not span the space (collinear / coplanar in 3-D): "
                           "the normal equations are singular beyond the gauge")
    RANK_DEFICIENT = ("rank-deficient", "the double-centred squared ranges have rank below d")
    NEAR_PLANAR = ("near-planar", "the layout's thickness is not resolved by the data")
    DIMENSION_MISMATCH = ("dimension-mismatch",
                          "the rank of the data contradicts the dimension asked for (use dim='auto')")
    NO_SIGNAL = ("no-signal", "every column is constant: no position is observable")
    DEGENERATE_FRAME = ("degenerate-frame",
                        "the reference nodes of a frame coincide, are collinear or have no position")
    # far-field TDOA (paper 000, sections 2.1-2.2)
    PLANAR_MOTION = ("planar-motion", "the receiver positions are coplanar (rank 2)")
    COPLANAR_DIRECTIONS = ("coplanar-directions", "the far-field directions lie in one plane (rank 2)")
    CONE = ("cone", "the directions lie on a quadratic cone: B is not determined (Theorem 2)")
    COLLINEAR_MOTION = ("collinear-motion", "the receiver positions are collinear (rank 1)")
    PARALLEL_DIRECTIONS = ("parallel-directions", "all far-field directions are parallel (rank 1)")
    # bearings / AOA (paper 001)
    COLLINEAR_BEACONS = ("collinear-beacons", "collinear beacons leave the rotation about their line free")
    RECEIVER_ON_BEACON_PLANE = ("receiver-on-beacon-plane",
                                "the receiver lies in the beacons' plane: its offset from it is free")
    DANGER_CIRCLE = ("danger-circle", "2-D: the receiver lies on the circle through the beacons")
    DANGER_CYLINDER = ("danger-cylinder",
                       "3-D: the receiver lies on the cylinder through the beacons' circumcircle")
    NO_SOLUTION = ("no-solution", "the bearings admit no pose for the beacon triangle")
    # initialisation
    INIT_FAILED = ("init-failed", "no initialiser produced a finite geometry")
    UPGRADE_FAILED = ("upgrade-failed", "the linear upgrade of the rank initialiser failed")


class Status(IntEnum):
    """State of a result, as ``result.status`` (0 = success, like SciPy's ``OptimizeResult``).

    ``result.success`` is ``status == Status.SUCCESS``; the command line exits 0 for a
    success and 1 (a ``FAIL:`` line) for a result that failed its own test.
    """

    SUCCESS = 0
    #: the iterative solver stopped before its convergence criterion
    NOT_CONVERGED = 1
    #: a residual (chi-square) test rejected the fit against the noise
    FAILED_TEST = 2
    #: a partial result: the geometry is degenerate (see the result's ``degeneracy``)
    DEGENERATE = 3
    #: several solutions explain the data equally well
    AMBIGUOUS = 4


class Flag(StrEnum):
    """What happened to one measurement or node (used in masks, counts and notes)."""

    #: no value was measured (NaN in the input)
    MISSING = "missing"
    #: measured but rejected as a gross error / outlier by a robust test
    OUTLIER = "outlier"
    #: removed from the problem because it cannot be determined (too few measurements)
    DROPPED = "dropped"


class SelfcalError(Exception):
    """Base class of every error raised on purpose by selfcal."""


class InputError(SelfcalError, ValueError):
    """The input is malformed: wrong shape, NaN/inf where not allowed, negative ranges, ..."""


class DegenerateGeometryError(SelfcalError, ValueError):
    """The geometry does not determine the unknowns (too few nodes, coplanar, cone, ...).

    Parameters
    ----------
    message:
        Human-readable explanation, including what would make the problem well posed.
    kind:
        A :class:`Degeneracy` or its string value, e.g. ``"too-few-receivers"``,
        ``"planar-motion"``, ``"cone"``, ``"collinear-beacons"``. A registered string is
        turned into the enum member (which still compares equal to the string); an
        unregistered one is kept as given.
    partial:
        Optional partial reconstruction (a result object) where the theory gives one.

    Examples
    --------
    >>> err = DegenerateGeometryError("all directions on a cone", kind="cone")
    >>> err.kind == "cone", err.kind is Degeneracy.CONE
    (True, True)
    >>> str(err)
    '[cone] all directions on a cone'
    """

    def __init__(self, message: str, *, kind: Degeneracy | str, partial: object | None = None) -> None:
        super().__init__(message)
        try:
            self.kind: Degeneracy | str = Degeneracy(kind)
        except ValueError:
            self.kind = str(kind)
        self.partial = partial

    @property
    def explanation(self) -> str:
        """The registry's explanation of :attr:`kind` (empty for an unregistered kind)."""
        return self.kind.explanation if isinstance(self.kind, Degeneracy) else ""

    def __str__(self) -> str:  # the kind is part of the one-line CLI message
        return f"[{self.kind}] {super().__str__()}"


class ConvergenceWarning(UserWarning):
    """An iterative solver stopped without meeting its convergence criterion."""
