"""Reproduction of paper 001's simulation (Section 5, Table 1, Fig. 3-6) plus the ML refinement.

Setup (paper Section 5): beacons b1 = (0,0,0), b2 = (5,0,0), b3 = (0,5,0) m; the receiver on the
plane z = -3 over the 5 x 5 m square on a 0.2 m grid; fixed orientation; the angles alpha_k and
beta_k (with the receiver's x and y axes) perturbed by N(0, 1 deg^2); eq. 4 for the third cosine;
20 runs per grid point. Errors: location = |m_est - m|, orientation per axis = angle between the
estimated and the true direction of that receiver axis.

The orientation printed in the paper ("rows of A = cos[45 45 0], cos[135 45 0], cos[90 90 0]") is
garbled (those rows are not unit vectors). We read it as the angles of each receiver axis with
the global x, y, z axes: x-axis (45, 45, 90) deg, y-axis (135, 45, 90) deg, z-axis (90, 90, 0) deg,
i.e. a 45 deg turn about the vertical with the sensor panel facing the beacons (local z = up),
which is what eq. 4's positive root requires.

Methods compared on the same noisy data in every trial: ``sol1`` and ``sol2`` exactly as in the
paper (no re-orthonormalisation of A), ``ml`` (all P3P candidates refined by maximum likelihood
under the paper's noise model), and ``ml4`` (ML with the fourth beacon at (5, 5, 0) that the
paper suggests against the GDOP at the far corner). With three beacons the problem is exactly
determined (six angles, six unknowns) and has up to four exact solutions; ML then breaks ties
with the side information "nearest to the centre of the test area" (:data:`HINT`), while
Solution 1's choice is implied by its Newton starts.
"""

from __future__ import annotations

import warnings
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .._checks import as_rng

Array = NDArray[np.float64]

__all__ = [
    "BEACONS",
    "FOURTH_BEACON",
    "TRUE_ROTATION",
    "PAPER_TABLE1",
    "METHODS",
    "paper_grid",
    "aoa_trial",
    "summarize",
]

BEACONS = np.array([[0.0, 0.0, 0.0], [5.0, 0.0, 0.0], [0.0, 5.0, 0.0]])
FOURTH_BEACON = np.array([5.0, 5.0, 0.0])
_AX = np.radians(np.array([[45.0, 45.0, 90.0], [135.0, 45.0, 90.0], [90.0, 90.0, 0.0]]))
#: columns = receiver axes in the global frame (selfcal convention, R = A^T of the paper)
TRUE_ROTATION = np.cos(_AX).T
#: paper 001 Table 1: mean location error (m) and x/y/z orientation errors (deg)
PAPER_TABLE1 = {
    "sol1": {"location_m": 0.28, "x_deg": 1.3, "y_deg": 1.4, "z_deg": 1.7},
    "sol2": {"location_m": 0.26, "x_deg": 2.6, "y_deg": 2.1, "z_deg": 2.9},
}
METHODS = ("sol1", "sol2", "ml", "ml4")
#: side information that breaks exact ties between P3P candidates: the centre of the test area
HINT = np.array([2.5, 2.5, -3.0])


def paper_grid(step: float = 0.2, size: float = 5.0) -> list[dict[str, float]]:
    """Receiver positions ``{"x", "y"}`` on the z = -3 plane, ``step`` metres apart."""
    n = int(round(size / step)) + 1
    xs = np.round(np.linspace(0.0, size, n), 10)
    return [{"x": float(x), "y": float(y)} for y in xs for x in xs]


def _axis_errors(R_est: Array, R_true: Array) -> Array:
    """Angle (deg) between each estimated receiver axis (column) and the true one."""
    with np.errstate(all="ignore"):
        c = R_est / np.linalg.norm(R_est, axis=0, keepdims=True)
        cos = np.sum(c * R_true, axis=0)
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def _noisy_bearings(beacons: Array, m: Array, R: Array, sigma_deg: float, rng: np.random.Generator) -> tuple[Array, int]:
    from ..aoa.bearings import angles_to_bearings, bearings_to_angles

    g = beacons - m
    local = (g / np.linalg.norm(g, axis=1, keepdims=True)) @ R  # R^T (b - m)/|b - m|
    alpha, beta = bearings_to_angles(local)
    s = np.radians(sigma_deg)
    out = angles_to_bearings(alpha + s * rng.standard_normal(alpha.shape), beta + s * rng.standard_normal(beta.shape))
    return out.vectors, int(out.clipped.sum())


def aoa_trial(params: dict[str, Any], seed: int) -> dict[str, Any]:
    """One run at one grid point: location and per-axis orientation errors of every method.

    ``params``: ``x``, ``y`` (receiver on z = ``z``, default -3), optional ``sigma_deg`` (1).
    Returns flat keys ``<method>_loc`` (m), ``<method>_x/_y/_z`` (deg), ``<method>_ok`` (1/0),
    ``<method>_ncand`` and ``clipped`` (bearings clipped by eq. 3-4).
    """
    from ..aoa.ml import refine_ml
    from ..aoa.p3p import p3p
    from ..aoa.pose import _count_distinct
    from ..aoa.solution1 import solution1
    from ..aoa.solution2 import solution2
    from ..errors import SelfcalError

    rng = as_rng(seed)
    m = np.array([params["x"], params["y"], params.get("z", -3.0)])
    sigma = float(params.get("sigma_deg", 1.0))
    b4 = np.vstack([BEACONS, FOURTH_BEACON])
    U4, clipped = _noisy_bearings(b4, m, TRUE_ROTATION, sigma, rng)
    U = U4[:3]
    out: dict[str, Any] = {"clipped": clipped}

    def record(name: str, pos: Array, R: Array, ok: bool, ncand: int) -> None:
        err = _axis_errors(R, TRUE_ROTATION) if ok else np.full(3, np.nan)
        out[f"{name}_loc"] = float(np.linalg.norm(pos - m)) if ok else float("nan")
        out[f"{name}_x"], out[f"{name}_y"], out[f"{name}_z"] = (float(e) for e in err)
        out[f"{name}_ok"] = int(ok)
        out[f"{name}_ncand"] = int(ncand)

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        s1 = solution1(BEACONS, U[None])
        ncand1 = int(_count_distinct(s1["roots"], s1["root_ok"])[0])
        record("sol1", s1["position"][0], s1["A"][0].T, bool(s1["converged"][0]), ncand1)
        s2 = solution2(BEACONS, U[None])
        ok2 = bool(s2["converged"][0]) and bool(np.isfinite(s2["A"][0]).all())
        record("sol2", s2["position"][0], s2["A"][0].T, ok2, 1)
        for name, bb, UU in (("ml", BEACONS, U), ("ml4", b4, U4)):
            try:
                pos, rot, valid = p3p(bb[:3], UU[None, :3])
                k = np.flatnonzero(valid[0])
                if k.size == 0:
                    raise SelfcalError("no P3P solution")
                r = refine_ml(bb, np.repeat(UU[None], k.size, 0), pos[0, k], rot[0, k], noise="angles")
                cost = r["residual_rms"]
                tie = cost <= cost.min() * (1 + 1e-6) + 1e-9
                # equally good candidates (three beacons): nearest to the test area's centre
                j = int(np.argmin(np.where(tie, np.linalg.norm(r["position"] - HINT, axis=1), np.inf)))
                ncand = int(_count_distinct(r["position"][None], tie[None])[0])
                record(name, r["position"][j], r["rotation"][j], bool(r["converged"][j]), ncand)
            except SelfcalError:
                record(name, m, TRUE_ROTATION, False, 0)
    return out


def summarize(rows: list[dict[str, Any]], methods: tuple[str, ...] = METHODS) -> dict[str, Any]:
    """Table 1 (means over solved trials), medians and failure rates per method."""
    table: dict[str, Any] = {}
    for meth in methods:
        ok = np.array([r[f"{meth}_ok"] for r in rows], bool)
        entry: dict[str, Any] = {"solved_fraction": float(ok.mean()) if ok.size else float("nan")}
        for key, col in (("location_m", "loc"), ("x_deg", "x"), ("y_deg", "y"), ("z_deg", "z")):
            v = np.array([r[f"{meth}_{col}"] for r in rows], float)[ok]
            entry[key] = float(np.mean(v)) if v.size else float("nan")
            entry[f"{key}_median"] = float(np.median(v)) if v.size else float("nan")
        entry["ambiguous_fraction"] = float(np.mean([r[f"{meth}_ncand"] > 1 for r in rows]))
        table[meth] = entry
    return table


def grid_means(rows: list[dict[str, Any]], key: str) -> tuple[Array, Array, Array]:
    """Per-grid-point mean of ``key`` over the solved runs: x (nx,), y (ny,), Z (ny, nx)."""
    xs = np.unique([r["x"] for r in rows])
    ys = np.unique([r["y"] for r in rows])
    acc = np.zeros((len(ys), len(xs)))
    cnt = np.zeros((len(ys), len(xs)))
    meth = key.split("_")[0]
    for r in rows:
        v = r[key]
        if r[f"{meth}_ok"] and np.isfinite(v):
            i, j = np.searchsorted(ys, r["y"]), np.searchsorted(xs, r["x"])
            acc[i, j] += v
            cnt[i, j] += 1
    with np.errstate(all="ignore"):
        return xs, ys, acc / cnt
