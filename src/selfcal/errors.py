"""Exceptions and warnings shared by every solver.

Every entry point validates its input and raises one of these with a message that
says what was wrong and what would fix it; the command line turns them into one
line on stderr and exit status 2.
"""

from __future__ import annotations

__all__ = ["SelfcalError", "InputError", "DegenerateGeometryError", "ConvergenceWarning"]


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
        A short machine-readable name of the degeneracy, e.g. ``"too-few-receivers"``,
        ``"planar-motion"``, ``"cone"``, ``"collinear-beacons"``.
    partial:
        Optional partial reconstruction (a result object) where the theory gives one.
    """

    def __init__(self, message: str, *, kind: str, partial: object | None = None) -> None:
        super().__init__(message)
        self.kind = kind
        self.partial = partial

    def __str__(self) -> str:  # the kind is part of the one-line CLI message
        return f"[{self.kind}] {super().__str__()}"


class ConvergenceWarning(UserWarning):
    """An iterative solver stopped without meeting its convergence criterion."""
