"""Far-field result types: :class:`FarfieldResult` (of :func:`~selfcal.tdoa.solve_farfield`) and
:class:`FarfieldInit` (of :func:`~selfcal.tdoa.initialize.initialize_farfield`)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .._result import Result
from .degeneracy import DegeneracyReport

__all__ = ["FarfieldResult", "FarfieldInit"]

Array = NDArray[np.float64]


@dataclass(frozen=True, repr=False)
class FarfieldResult(Result):
    """Result of :func:`solve_farfield`.

    Attributes
    ----------
    positions : (m, 3) receiver positions, first row 0 (metres; D's unit). Canonical gauge:
        first position at the origin, principal axes of the positions along x, y, z (a
        proper rotation); the reconstruction is defined up to a rotation and reflection.
    directions : (k, 3) unit directions n_j (from the transmitter towards the receivers).
    offsets : (k,) C_j such that ``D_ij ~ z_i . n_j + C_j``.
    degeneracy : None or the failure mode (see :mod:`selfcal.tdoa.degeneracy`).
    residual_rms : rms of ``D_ij - z_i . n_j - C_j`` over used entries (metres).
    converged, iterations, method, loss : refinement status.
    rejected : (m, k) bool, entries treated as outliers (gross screen or robust fit).
    b_positive_definite : whether the least-squares B of the initialisation was positive
        definite (the paper's success criterion; False -> A came from the nonlinear fit).
    diagnostics : the degeneracy report (singular values, noise level, cone ratio...).
    cost_history : refinement cost after every iteration (first = initial cost).
    position_cov : (m, d, d) Gauss-Newton covariance of each position (m^2) after LM, in
        the gauge "best rotation about the first position"; for a linear array (d = 1) the
        errors after the best scaling about the first position
        (:func:`~selfcal.tdoa.covariance.linear_position_covariance`); None for other methods.
    warnings : human-readable cautions about this estimate (e.g. ``directions-collapsed``:
        the refinement drove the directions towards a common plane, see
        :data:`COLLAPSE_RATIO`); empty when there are none.
    dim : dimension of ``positions`` / ``directions`` (3 in space, 2 planar, 1 linear).
    case : ``"spatial"`` (3-D, Theorem 1), ``"planar"`` (positions and directions in one
        plane: the in-plane geometry; positions off that plane are projected onto it, the
        out-of-plane coordinate is not observable) or ``"linear"`` (positions on a line, or
        directions all parallel: one coordinate per position), or the degeneracy's name
        for a partial reconstruction.
    determined : what the data determine in this case (paper 000, section 2.2), in words.
    untestable : number of observed entries the gross-error screen could not check (too few
        spare measurements: their redundancy ``1 - h_ij`` is ~0, e.g. every entry of the
        minimal 4 x 6 problem; :func:`~selfcal.tdoa.screen.gross_error_screen`); a line in
        ``warnings`` says so when it is not 0.
    direction_cov : (k, d, d) Gauss-Newton covariance of each unit direction (unitless^2, i.e.
        rad^2 for small errors) in the frame of ``directions``, positions profiled in
        (:func:`~selfcal.tdoa.covariance.direction_covariance`); None where ``position_cov`` is
        None, for partial reconstructions, linear arrays and known directions. ``to_dict`` adds
        ``direction_std_deg`` (RMS angular error, the one-sigma cone half-angle) and in 3-D
        ``azimuth_std_deg`` / ``elevation_std_deg`` (azimuth ``atan2(n_y, n_x)``, elevation
        ``asin(n_z)`` in the result's frame).
    screen_rule : the gross-error test that ran and its false-alarm rate, in words (with the
        fitted tail: its dof and scale; :attr:`~selfcal.tdoa.screen.GrossScreen.rule`).
    dim_rule : how ``dim`` was chosen: given, or ``"auto: ..."`` with the rank test's level
        (:func:`~selfcal.tdoa.solve.dimension_rule`).
    """

    positions: Array
    directions: Array
    offsets: Array
    degeneracy: str | None
    residual_rms: float
    converged: bool
    iterations: int
    method: str
    loss: str
    rejected: NDArray[np.bool_]
    b_positive_definite: bool
    diagnostics: DegeneracyReport | None = None
    cost_history: list[float] = field(default_factory=list)
    position_cov: Array | None = None
    warnings: tuple[str, ...] = ()
    dim: int = 3
    case: str = "spatial"
    determined: str = ""
    untestable: int = 0
    dim_rule: str = ""
    direction_cov: Array | None = None
    screen_rule: str = ""

    def to_dict(self) -> dict[str, Any]:
        """JSON-safe dictionary with the DESIGN.md keys (``rejected`` as [i, j] pairs)."""
        return {
            "positions": self.positions.tolist(),
            "directions": self.directions.tolist(),
            "offsets": self.offsets.tolist(),
            "residual_rms": float(self.residual_rms),
            "degeneracy": self.degeneracy,
            "converged": bool(self.converged),
            "iterations": int(self.iterations),
            "method": self.method,
            "loss": self.loss,
            "rejected": np.argwhere(self.rejected).tolist(),
            "b_positive_definite": bool(self.b_positive_definite),
            "diagnostics": None if self.diagnostics is None else self.diagnostics.to_dict(),
            "position_cov": None if self.position_cov is None else self.position_cov.tolist(),
            "warnings": list(self.warnings),
            "dim": int(self.dim),
            "case": self.case,
            "determined": self.determined,
            "untestable": int(self.untestable),
            "dim_rule": self.dim_rule,
            "screen_rule": self.screen_rule,
            "direction_covariance": None if self.direction_cov is None else self.direction_cov.tolist(),
            **self._direction_stds(),
        }

    def _direction_stds(self) -> dict[str, Any]:
        from .covariance import direction_angle_std

        keys = ("direction_std_deg", "azimuth_std_deg", "elevation_std_deg")
        if self.direction_cov is None:
            return dict.fromkeys(keys)
        std = direction_angle_std(self.directions, self.direction_cov)

        def clean(v: Array) -> list[float | None]:
            return [float(x) if np.isfinite(x) else None for x in v]

        return {"direction_std_deg": clean(std["angle"]),
                "azimuth_std_deg": clean(std["azimuth"]) if "azimuth" in std else None,
                "elevation_std_deg": clean(std["elevation"]) if "elevation" in std else None}


@dataclass(frozen=True)
class FarfieldInit:
    """Output of :func:`initialize_farfield`: positions (m, 3) (row 0 = 0), directions (k, 3),
    B (3, 3) least-squares quadric, A (3, 3) with ``N = A Ntilde``, and whether B was
    positive definite."""

    positions: Array
    directions: Array
    B: Array
    A: Array
    b_positive_definite: bool
