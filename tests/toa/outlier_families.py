"""Random draws of gross-error contamination (issue 27, "outlier breakdown is reported").

Each family returns ``(ranges, receivers, sources, bad, kw)`` for one seed: the truth, the
mask of the ranges made gross, and the keyword arguments of :func:`selfcal.toa.solve_toa` a
user would give. The contaminated families draw the contaminated fraction uniformly in
10-40 % of the ranges (up to and beyond what an estimator of a node's position can hold,
:func:`selfcal.toa.fit._overflagged`), each bad range off by U(1, 5) m (100-500 noise std):
one-sided (+, a reflection, non-line-of-sight) or symmetric (either sign), 2-D and 3-D,
the noise given or unknown, offsets none or per receiver. The clean families are the
generic networks the false-alarm rate is measured on.

:func:`classify` sorts a result into the columns of the specification:
``breakdown`` (the result fails and names an outlier breakdown), ``right`` (exit 0, every
located node within 3 of its own error bars of the truth, every injected error between
located nodes in the ``outliers`` mask), ``right-unflagged`` (exit 0 and within its error
bars, but some injected errors left in the fit: the bars are inflated by them), ``wrong``
(exit 0 with a node outside, the case that must never happen), ``failed`` (exit 1 for
another reason), and counts the injected errors in the ``outliers`` mask (``flagged``). Used by
``tests/toa/test_outlier_families.py`` and ``benchmarks/outlier_sweep.py``.
"""

from __future__ import annotations

import warnings
from typing import Any

import numpy as np

from selfcal.errors import DegenerateGeometryError
from selfcal.toa import solve_toa, toa_model

NOISE = 0.01  # m: 1 cm range noise in a 10 m layout (UWB-like)


def _noise(g: np.random.Generator, shape: tuple[int, int], tails: str) -> np.ndarray:
    """Range noise of standard deviation :data:`NOISE`: Gaussian, Student t (``"t3"``, ``"t5"``) or Laplace.

    The heavy-tailed kinds are scaled to the same standard deviation (t with nu dof:
    sqrt((nu - 2) / nu) times a standard t draw; Laplace: scale NOISE / sqrt(2)): real UWB and
    acoustic ranges have heavier tails than Gaussian, and those are noise, not gross errors.
    """
    if tails == "gauss":
        return g.normal(0, NOISE, shape)
    if tails == "laplace":
        return g.laplace(0, NOISE / np.sqrt(2), shape)
    nu = int(tails[1:])
    return NOISE * np.sqrt((nu - 2) / nu) * g.standard_t(nu, shape)


def _network(g: np.random.Generator, I: int, J: int, dim: int, offsets: bool, tails: str = "gauss") -> tuple:
    r, s = g.uniform(0, 10, (I, dim)), g.uniform(0, 10, (J, dim))
    d = g.uniform(0, 2, I) if offsets else None
    return toa_model(r, s, d) + _noise(g, (I, J), tails), r, s


def _contaminate(g: np.random.Generator, Y: np.ndarray, symmetric: bool, fraction: tuple[float, float],
                 size: tuple[float, float]) -> np.ndarray:
    bad = g.random(Y.shape) < g.uniform(*fraction)
    sign = g.choice([-1.0, 1.0], bad.sum()) if symmetric else 1.0
    Y[bad] += sign * g.uniform(*size, bad.sum())
    return bad


def family(tag: int, I: int, J: int, dim: int, *, symmetric: bool, given: bool, offsets: bool = False,
           clean: bool = False, fraction: tuple[float, float] = (0.1, 0.4),
           size: tuple[float, float] = (1.0, 5.0), tails: str = "gauss") -> Any:
    """A family of draws: ``seed -> (Y, receivers, sources, bad, kw)``; ``tails``: the noise (:func:`_noise`)."""

    def one(seed: int) -> tuple:
        g = np.random.default_rng([27, tag, seed])
        Y, r, s = _network(g, I, J, dim, offsets, tails)
        bad = np.zeros(Y.shape, bool) if clean else _contaminate(g, Y, symmetric, fraction, size)
        kw: dict[str, Any] = {"dim": dim, "offsets": "receivers" if offsets else "none"}
        if given:
            kw["noise"] = NOISE
        return Y, r, s, bad, kw

    return one


CONTAMINATED = {
    "3d-plus-unknown": family(1, 12, 40, 3, symmetric=False, given=False),
    "3d-sym-unknown": family(2, 12, 40, 3, symmetric=True, given=False),
    "3d-plus-given": family(3, 12, 40, 3, symmetric=False, given=True),
    "3d-sym-given": family(4, 12, 40, 3, symmetric=True, given=True),
    "2d-plus-unknown": family(5, 10, 30, 2, symmetric=False, given=False),
    "2d-sym-given": family(6, 10, 30, 2, symmetric=True, given=True),
    "3d-offsets-plus-unknown": family(7, 12, 40, 3, symmetric=False, given=False, offsets=True),
    "3d-offsets-sym-given": family(8, 12, 40, 3, symmetric=True, given=True, offsets=True),
    # up to 25 %: within what most sources of 12 ranges can hold (4 of 12), the noise unknown
    "3d-plus-unknown-25": family(10, 12, 40, 3, symmetric=False, given=False, fraction=(0.1, 0.25)),
    "2d-sym-unknown-25": family(16, 10, 30, 2, symmetric=True, given=False, fraction=(0.1, 0.25)),
    # the case: 30 % of the ranges +5 m, the noise unknown
    "3d-30pct-5m-unknown": family(9, 12, 40, 3, symmetric=False, given=False, fraction=(0.3, 0.3), size=(5.0, 5.0)),
}
CLEAN = {
    "clean-3d-unknown": family(11, 12, 40, 3, symmetric=False, given=False, clean=True),
    "clean-3d-given": family(12, 12, 40, 3, symmetric=False, given=True, clean=True),
    "clean-2d-unknown": family(13, 10, 30, 2, symmetric=False, given=False, clean=True),
    "clean-3d-offsets-unknown": family(14, 12, 40, 3, symmetric=False, given=False, offsets=True, clean=True),
    "clean-small-3d-unknown": family(15, 8, 10, 3, symmetric=False, given=False, clean=True),
}
#: clean networks with heavy-tailed noise of 1 cm standard deviation (no gross errors): real
#: ranging noise is not Gaussian, and a breakdown must not be reported on it
HEAVY = {
    "t3-3d-unknown": family(21, 12, 40, 3, symmetric=False, given=False, clean=True, tails="t3"),
    "t5-3d-unknown": family(22, 12, 40, 3, symmetric=False, given=False, clean=True, tails="t5"),
    "laplace-3d-unknown": family(23, 12, 40, 3, symmetric=False, given=False, clean=True, tails="laplace"),
    "t3-2d-unknown": family(24, 10, 30, 2, symmetric=False, given=False, clean=True, tails="t3"),
    "t4-3d-offsets-unknown": family(25, 12, 40, 3, symmetric=False, given=False, offsets=True, clean=True,
                                    tails="t4"),
    "laplace-small-3d-unknown": family(26, 8, 10, 3, symmetric=False, given=False, clean=True, tails="laplace"),
}


def outside(res: Any, r: np.ndarray, s: np.ndarray, k: float = 3.0) -> int:
    """Located nodes further from the truth than ``k`` of their own error bars (sqrt trace cov).

    The estimate is aligned onto the truth (rotation, translation, reflection: the gauge) by
    the located nodes; 1 mm is added to each bar for the alignment's own share of the error.
    """
    from selfcal.geometry import align

    est, ref = np.vstack([res.receivers, res.sources]), np.vstack([r, s])
    ok = np.isfinite(est).all(1)
    if ok.sum() < est.shape[1] + 1:
        return int(est.shape[0])
    X = align(est[ok], ref[ok], reflection=True).apply(est[ok])
    C = np.concatenate([res.receiver_cov, res.source_cov])[ok]
    with np.errstate(invalid="ignore"):
        bar = np.sqrt(np.trace(C, axis1=1, axis2=2))
    bar = np.where(np.isfinite(bar), bar, 0.0)
    return int((np.linalg.norm(X - ref[ok], axis=1) > k * bar + 1e-3).sum())


def worst_outside(res: Any, r: np.ndarray, s: np.ndarray, k: float = 3.0) -> float:
    """The largest error (metres) of a node outside ``k`` of its error bars (0 when none), as :func:`outside`."""
    from selfcal.geometry import align

    est, ref = np.vstack([res.receivers, res.sources]), np.vstack([r, s])
    ok = np.isfinite(est).all(1)
    if ok.sum() < est.shape[1] + 1:
        return float("inf")
    X = align(est[ok], ref[ok], reflection=True).apply(est[ok])
    C = np.concatenate([res.receiver_cov, res.source_cov])[ok]
    with np.errstate(invalid="ignore"):
        bar = np.sqrt(np.trace(C, axis1=1, axis2=2))
    bar = np.where(np.isfinite(bar), bar, 0.0)
    err = np.linalg.norm(X - ref[ok], axis=1)
    out = err > k * bar + 1e-3
    return float(err[out].max()) if out.any() else 0.0


def classify(fam: Any, seed: int) -> dict[str, Any]:
    """Solve one draw and sort it (module docstring)."""
    Y, r, s, bad, kw = fam(seed)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            res = solve_toa(Y, rng=seed, **kw)
        except DegenerateGeometryError:  # refused: exit 1 in the CLI, never a confident answer
            return {"kind": "failed", "flagged": 0, "bad": int(bad.sum()), "message": "refused", "result": None}
    ok = res.success
    n_out = outside(res, r, s)
    if res.outlier_breakdown is not None:
        assert not ok and "outlier breakdown" in res.message
        kind = "breakdown"
    elif ok:
        kind = "right" if n_out == 0 else "wrong"
    else:
        kind = "failed"
    mask = np.asarray(res.outliers, bool)
    located = np.isfinite(res.receivers[:, 0])[:, None] & np.isfinite(res.sources[:, 0])[None]
    missed = int((bad & located & ~mask).sum())
    if kind == "right" and missed:
        kind = "right-unflagged"  # within its (inflated) error bars, but gross errors left in the fit
    return {"kind": kind, "flagged": int((bad & mask).sum()), "bad": int(bad.sum()), "missed": missed,
            "worst_m": worst_outside(res, r, s) if kind == "wrong" else 0.0,
            "false_flags": int((~bad & mask).sum()), "outside": n_out, "message": res.message, "result": res}
