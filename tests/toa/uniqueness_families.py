"""Random draws of the flip families of issue 27 and of generic well-posed networks.

Each family returns ``(ranges, receivers, sources, kw)`` for one seed: the truth and the
keyword arguments of :func:`selfcal.toa.solve_toa` a user would give. ``judge`` says
whether a result is right within 3 of its own error bars (after the rigid alignment onto
the truth, reflection allowed: the gauge) or flagged (not a success). Used by
``tests/toa/test_uniqueness.py`` and ``benchmarks/bench_uniqueness.py``.
"""

from __future__ import annotations

import warnings
from typing import Any

import numpy as np

from selfcal.errors import DegenerateGeometryError
from selfcal.geometry import align
from selfcal.toa import solve_toa, toa_model

NOISE = 0.01  # m: 1 cm range noise in a 10 m layout (UWB-like)


def _box(g: np.random.Generator, n: int, dim: int, lo: float = 0.0, hi: float = 10.0) -> np.ndarray:
    return g.uniform(lo, hi, (n, dim))


def generic_2d(seed: int) -> tuple:
    g = np.random.default_rng([2, seed])
    r, s = _box(g, 8, 2), _box(g, 10, 2)
    return toa_model(r, s) + g.normal(0, NOISE, (8, 10)), r, s, {"dim": 2}


def generic_3d(seed: int) -> tuple:
    g = np.random.default_rng([3, seed])
    r, s = _box(g, 8, 3), _box(g, 10, 3)
    return toa_model(r, s) + g.normal(0, NOISE, (8, 10)), r, s, {"dim": 3}


def generic_3d_noise(seed: int) -> tuple:
    Y, r, s, kw = generic_3d(seed + 10_000)
    return Y, r, s, {**kw, "noise": NOISE}


def generic_3d_offsets(seed: int) -> tuple:
    g = np.random.default_rng([33, seed])
    r, s = _box(g, 10, 3), _box(g, 14, 3)
    d = g.uniform(0, 2, 10)
    return toa_model(r, s, d) + g.normal(0, NOISE, (10, 14)), r, s, {"dim": 3, "offsets": "receivers"}


def collinear_2d(seed: int) -> tuple:
    """Receivers on a line in 2-D: each source has its mirror image through the line."""
    g = np.random.default_rng([21, seed])
    r = np.c_[g.uniform(0, 10, 6), np.full(6, 5.0)]
    s = _box(g, 8, 2)
    return toa_model(r, s) + g.normal(0, NOISE, (6, 8)), r, s, {"dim": 2}


def coplanar_3d(seed: int) -> tuple:
    """Receivers in a plane in 3-D: each source mirrored through it."""
    g = np.random.default_rng([31, seed])
    r = np.c_[_box(g, 8, 2), np.full(8, 3.0)]
    s = _box(g, 10, 3)
    return toa_model(r, s) + g.normal(0, NOISE, (8, 10)), r, s, {"dim": 3}


def parallel_planes(seed: int) -> tuple:
    """Receivers in one plane, sources in a parallel one."""
    g = np.random.default_rng([32, seed])
    r = np.c_[_box(g, 8, 2), np.full(8, 3.0)]
    s = np.c_[_box(g, 10, 2), np.full(10, 1.0)]
    return toa_model(r, s) + g.normal(0, NOISE, (8, 10)), r, s, {"dim": 3}


def collinear_3d(seed: int) -> tuple:
    """Receivers on a line in 3-D: each source free to turn about it."""
    g = np.random.default_rng([34, seed])
    r = np.c_[g.uniform(0, 10, 6), np.full(6, 5.0), np.full(6, 3.0)]
    s = _box(g, 10, 3)
    return toa_model(r, s) + g.normal(0, NOISE, (6, 10)), r, s, {"dim": 3}


def minimal_2d(seed: int) -> tuple:
    """3 x 3 in 2-D, noise-free: 9 ranges, 9 unknowns."""
    g = np.random.default_rng([22, seed])
    r, s = _box(g, 3, 2), _box(g, 3, 2)
    return toa_model(r, s), r, s, {"dim": 2}


def minimal_3d(seed: int) -> tuple:
    """4 x 6 in 3-D, noise-free: 24 ranges, 24 unknowns."""
    g = np.random.default_rng([35, seed])
    r, s = _box(g, 4, 3), _box(g, 6, 3)
    return toa_model(r, s), r, s, {"dim": 3}


def tag_one_height(seed: int) -> tuple:
    """Four ceiling anchors, two low ones, a tag walked at about one height (blind)."""
    g = np.random.default_rng([36, seed])
    r = np.array([[0.5, 0.5, 2.9], [7.5, 0.5, 2.9], [7.5, 5.5, 2.9], [0.5, 5.5, 2.9],
                  [0.5, 3.0, 0.3], [7.5, 3.0, 0.4]]) + g.normal(0, 0.05, (6, 3))
    n = 30
    s = np.c_[g.uniform(1, 7, n), g.uniform(1, 5, n), 1.2 + g.normal(0, 0.01, n)]
    return toa_model(r, s) + g.normal(0, 0.02, (6, n)), r, s, {"dim": 3}


FAMILIES = {"collinear-2d": collinear_2d, "coplanar-3d": coplanar_3d, "parallel-planes": parallel_planes,
            "collinear-3d": collinear_3d, "minimal-2d": minimal_2d, "minimal-3d": minimal_3d,
            "tag-one-height": tag_one_height}
GENERIC = {"generic-2d": generic_2d, "generic-3d": generic_3d, "generic-3d-noise": generic_3d_noise,
           "generic-3d-offsets": generic_3d_offsets}


def within(res: Any, r: np.ndarray, s: np.ndarray, k: float = 3.0) -> bool:
    """Every node within ``k`` of its own error bars (sqrt trace of its covariance) of the truth."""
    est = np.vstack([res.receivers, res.sources])
    ref = np.vstack([r, s])
    ok = np.isfinite(est).all(1)
    if ok.sum() < est.shape[1] + 1:
        return False
    X = align(est[ok], ref[ok], reflection=True).apply(est[ok])
    C = np.concatenate([res.receiver_cov, res.source_cov])[ok]
    with np.errstate(invalid="ignore"):
        bar = np.sqrt(np.trace(C, axis1=1, axis2=2))
    bar = np.where(np.isfinite(bar), bar, 0.0)
    err = np.linalg.norm(X - ref[ok], axis=1)
    return bool(np.all(err <= k * bar + 1e-6 * (1 + np.abs(ref).max())))


def draw(family: Any, seed: int) -> dict[str, Any]:
    """Solve one draw; whether it is flagged, and right within 3 error bars."""
    Y, r, s, kw = family(seed)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            res = solve_toa(Y, rng=seed, **kw)
        except DegenerateGeometryError:  # refused (exit 1 / 2 in the CLI): never a confident answer
            return {"flagged": True, "right": False, "result": None}
    return {"flagged": not res.success, "right": within(res, r, s), "result": res}
