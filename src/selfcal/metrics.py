"""Error metrics: aligned RMSE (paper 003 eq. 18a/18b), per-point errors, angles, efficiency."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from ._checks import entry
from .geometry import Alignment, align, wrap_angle

__all__ = ["AlignedError", "aligned_rmse", "angle_error", "rotation_angle_error",
           "aligned_direction_errors", "efficiency"]

Array = NDArray[np.float64]


@dataclass(frozen=True)
class AlignedError:
    """Errors of an estimate after rigid alignment to ground truth.

    ``rmse_receivers`` / ``rmse_sources`` follow paper 003 eq. 18a / 18b:
    ``RMSE_r = sqrt(1/N sum_i |r_i - r_i_hat|^2)`` (likewise over the K sources),
    where the estimate is first mapped by the least-squares rigid transform
    (reflection allowed) fitted on the receivers.
    """

    rmse_receivers: float
    rmse_sources: float | None
    receiver_errors: Array
    source_errors: Array | None
    alignment: Alignment


@entry(est_receivers="array", true_receivers="array", est_sources="array", true_sources="array",
       fit_on="str", reflection="bool")
def aligned_rmse(
    est_receivers: Array,
    true_receivers: Array,
    est_sources: Array | None = None,
    true_sources: Array | None = None,
    *,
    fit_on: str = "receivers",
    reflection: bool = True,
) -> AlignedError:
    """Aligned RMSE of receivers and sources (003 eq. 18a/18b).

    The rigid transform is fitted on ``fit_on`` ("receivers" or "all") and applied
    to both point sets. Shapes: receivers (I, d), sources (J, d); metres in, metres out.
    """
    er = np.asarray(est_receivers, float)
    tr = np.asarray(true_receivers, float)
    if fit_on == "all" and est_sources is not None and true_sources is not None:
        al = align(np.vstack([er, est_sources]), np.vstack([tr, true_sources]), reflection=reflection)
    else:
        al = align(er, tr, reflection=reflection)
    rerr = np.linalg.norm(al.apply(er) - tr, axis=1)
    serr = None
    srmse = None
    if est_sources is not None and true_sources is not None:
        serr = np.linalg.norm(al.apply(np.asarray(est_sources, float)) - np.asarray(true_sources, float), axis=1)
        srmse = float(np.sqrt(np.nanmean(serr**2)))
    return AlignedError(
        rmse_receivers=float(np.sqrt(np.nanmean(rerr**2))),
        rmse_sources=srmse,
        receiver_errors=rerr,
        source_errors=serr,
        alignment=al,
    )


def angle_error(a: Array, b: Array) -> Array:
    """Wrapped difference ``a - b`` of angles in radians, in (-pi, pi]."""
    d = np.asarray(a, float) - np.asarray(b, float)
    return -wrap_angle(-d)  # (-pi, pi]: the mirror of the [-pi, pi) wrap


def rotation_angle_error(R_est: Array, R_true: Array) -> Array:
    """Geodesic angle (rad) between rotation matrices (..., d, d), d in {2, 3}."""
    Re = np.asarray(R_est, float)
    Rt = np.asarray(R_true, float)
    M = np.swapaxes(Rt, -1, -2) @ Re
    d = M.shape[-1]
    if d == 2:
        return np.abs(np.arctan2(M[..., 1, 0], M[..., 0, 0]))
    tr = np.trace(M, axis1=-2, axis2=-1)
    return np.arccos(np.clip((tr - 1.0) / 2.0, -1.0, 1.0))


def aligned_direction_errors(
    positions: Array, directions: Array, true_positions: Array, true_directions: Array
) -> Array:
    """Angle (rad) between each estimated unit direction and the true one, after the rigid
    alignment (reflection allowed) fitted on the positions.

    For far-field self-calibration (paper 000): positions (m, 3) are fitted up to a rotation /
    reflection and a translation, and the directions (k, 3) share the rotation, not the
    translation. Returns (k,) angles in [0, pi].
    """
    al = align(np.asarray(positions, float), np.asarray(true_positions, float))
    N = np.asarray(directions, float) @ al.rotation.T
    N /= np.linalg.norm(N, axis=1, keepdims=True)
    T = np.asarray(true_directions, float)
    T = T / np.linalg.norm(T, axis=1, keepdims=True)
    return np.arccos(np.clip(np.sum(N * T, axis=1), -1.0, 1.0))


def efficiency(rmse: float, crlb_trace: float) -> float:
    """Efficiency ratio ``RMSE / sqrt(CRLB)`` (1 = efficient estimator); crlb_trace is the
    mean per-point trace of the Cramer-Rao bound (m^2)."""
    return float(rmse / np.sqrt(crlb_trace)) if crlb_trace > 0 else float("nan")
