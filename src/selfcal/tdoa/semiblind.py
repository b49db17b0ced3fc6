"""Semi-blind far-field calibration: positions and offsets by least squares given the directions."""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from .._checks import as_matrix
from ..errors import DegenerateGeometryError, InputError
from ..robust import TUNING, mad_std
from .model import loss_weight
from .result import FarfieldResult

__all__: list[str] = []

Array = NDArray[np.float64]


def _solve_known_directions(D: Array, used: NDArray[np.bool_], gross: NDArray[np.bool_], directions: Any, *,
                            loss: str) -> FarfieldResult:
    """Positions and offsets by least squares given the unit directions (see ``directions``)."""
    m, k = D.shape
    N = np.asarray(as_matrix(directions, "directions", allow_nan=False), dtype=float)
    if N.shape[0] != k or N.shape[1] not in (2, 3):
        raise InputError(f"directions: expected ({k}, 2 or 3) unit vectors (one per column of the matrix), got "
                         f"{N.shape}" + (" (transposed?)" if N.shape[::-1] == (k, 3) else ""))
    nrm = np.linalg.norm(N, axis=1)
    if np.any(np.abs(nrm - 1.0) > 1e-3):
        raise InputError(f"directions: row {int(np.argmax(np.abs(nrm - 1)))} has length "
                         f"{nrm[np.argmax(np.abs(nrm - 1))]:.4g}; directions must be unit vectors")
    d = N.shape[1]
    sv = np.linalg.svd(N, compute_uv=False)
    if sv[-1] <= 1e-9 * sv[0]:
        raise DegenerateGeometryError(f"the given directions span fewer than {d} dimensions: the positions' "
                                      "component across them is unobservable", kind="coplanar-directions")
    D0 = np.where(used, D, 0.0)
    Z, C, its = _weighted_ls(D0, used.astype(float), N)
    if loss != "linear":
        # IRLS with the loss's weights at its 95 %-efficiency scale x the robust residual std
        # (1.4826 MAD, dof-corrected), as the blind refinement does
        dof_fac = np.sqrt(used.sum() / max(int(used.sum()) - d * (m - 1) - k, 1))
        for _ in range(20):
            r = np.where(used, D0 - Z @ N.T - C, 0.0)
            sig = float(mad_std(r[used], centre=False)) * dof_fac
            if not sig > 0:
                break
            W = used * loss_weight((r / (TUNING[loss] * sig)) ** 2, loss)
            Z_new, C, n_its = _weighted_ls(D0, W, N)
            its += n_its
            step = float(np.max(np.abs(Z_new - Z)))
            Z = Z_new
            if step <= 1e-9 * sig:
                break
    C = C + Z[0] @ N.T
    Z = Z - Z[0]
    r = np.where(used, D - Z @ N.T - C, np.nan)
    rms = float(np.sqrt(np.nanmean(r**2)))
    res = FarfieldResult(Z, N.copy(), C, None, rms, True, its, "known-directions", loss, gross.copy(), True,
                         None, [], None, (), d, "known-directions",
                         "positions in the frame of the given directions (semi-blind: nothing left free but the "
                         "first position at the origin); as good as the directions are")
    return res


def _weighted_ls(D0: Array, W: Array, N: Array) -> tuple[Array, Array, int]:
    """Weighted least squares in (z_i, C_j) given the directions: ``(Z, C, iterations)``."""
    m = D0.shape[0]
    d = N.shape[1]
    # alternate the exact per-column offsets and the exact per-row positions (block coordinate
    # descent on a convex quadratic: converges to the unique minimum); complete data need one
    # round from C = column means
    Z = np.zeros((m, d))
    C = np.sum(W * D0, axis=0) / np.maximum(W.sum(0), 1e-300)
    H = np.einsum("ij,ja,jb->iab", W, N, N)
    prev = np.inf
    its = 0
    for its in range(1, 2001):  # noqa: B007
        g = np.einsum("ij,ij,ja->ia", W, D0 - C, N)
        Z = np.linalg.solve(H + 1e-12 * np.eye(d), g[..., None])[..., 0]
        C = np.sum(W * (D0 - Z @ N.T), axis=0) / np.maximum(W.sum(0), 1e-300)
        cost = float(np.sum(W * (D0 - Z @ N.T - C) ** 2))
        if its > 1 and prev - cost <= 1e-14 * max(prev, 1e-300):
            break
        prev = cost
    return Z, C, its
