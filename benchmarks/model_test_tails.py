"""Benchmark "model-test tails": the forced-model F test's level on heavy-tailed noise, before / after.

:func:`selfcal.toa.verdict.model_test.forced_model_test` tests ``offsets="none"`` (the CLI's
default for ``calibrate toa``) against ``offsets="both"``. The F test is exact for Gaussian
noise; the heavy-tail correction (module docstring there: Box & Watson 1962, a two-moment
match) refers F to ``F(k / c, dof / c_d)``. Each draw: a generic network (uniform in a 10 m
box, 1 cm noise std of the stated law, no offsets in the truth: the forced model is right),
the forced model refined from the truth (:func:`selfcal.toa.engine.nls.refine_toa`, linear
loss, every entry: no outlier flagging, harsher than the CLI), then the test; "before" is
the Gaussian F p-value of the same statistic (``F(k, dof)``), "after" the test's own.
``--shift A``: receiver offsets ``N(0, A)`` noise stds in the truth (a power check: the
forced model is wrong).

Seeds: ``numpy.random.default_rng([2791, shape, law, seed])`` (no test uses 2791).

Run: ``OPENBLAS_NUM_THREADS=1 PYTHONPATH=src .venv/bin/python benchmarks/model_test_tails.py
--draws 200 [--laws gauss,laplace,t5,t3] [--shapes 2d-10x30,3d-12x40,3d-8x10] [--shift 0]``.
Columns: rejections at 1e-3 (the test's level) and at 1e-2 before / after, the one-sided
95 % Clopper-Pearson upper bound of the after-rate at 1e-3, medians of the kurtosis
estimate and of ``c``.
"""

from __future__ import annotations

import argparse
import time
import warnings

import numpy as np
from scipy.stats import beta
from scipy.stats import f as fdist

SHAPES = {"2d-10x30": (10, 30, 2), "3d-12x40": (12, 40, 3), "3d-8x10": (8, 10, 3)}
LAWS = ("gauss", "laplace", "t5", "t3")
NOISE = 0.01


def noise(g: np.random.Generator, shape: tuple[int, int], law: str, std: float = NOISE) -> np.ndarray:
    """Unit-variance laws scaled to ``std``: Gaussian, Laplace, Student t (nu > 2)."""
    if law == "gauss":
        return g.normal(0, std, shape)
    if law == "laplace":
        return g.laplace(0, std / np.sqrt(2), shape)
    nu = int(law[1:])
    return std * np.sqrt((nu - 2) / nu) * g.standard_t(nu, shape)


def one(shape: str, law: str, seed: int, shift: float = 0.0) -> tuple[float, float, float, float]:
    """(p before, p after, kurtosis, c) of one draw."""
    from selfcal.toa import toa_model
    from selfcal.toa.engine.nls import refine_toa
    from selfcal.toa.verdict.model_test import forced_model_test

    I, J, dim = SHAPES[shape]
    g = np.random.default_rng([2791, list(SHAPES).index(shape), LAWS.index(law), seed])
    R, S = g.uniform(0, 10, (I, dim)), g.uniform(0, 10, (J, dim))
    d = g.normal(0, shift * NOISE, I) if shift else None
    Y = toa_model(R, S, d) + noise(g, (I, J), law)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        fit = refine_toa(Y, R, S, offsets="none", covariance=False)
        t = forced_model_test(Y, fit.receivers, fit.sources, offsets="none", test_dim=False)
    before = float(fdist.sf(t.statistic, t.dof, t.dof_noise)) if t.dof else 1.0
    return before, t.p_value, t.kurtosis, t.scale


def upper95(x: int, n: int) -> float:
    """One-sided 95 % Clopper-Pearson upper bound of a rate x / n."""
    return 1.0 if x >= n else float(beta.ppf(0.95, x + 1, n - x))


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--draws", type=int, default=200)
    ap.add_argument("--first", type=int, default=0)
    ap.add_argument("--laws", default=",".join(LAWS))
    ap.add_argument("--shapes", default=",".join(SHAPES))
    ap.add_argument("--shift", type=float, default=0.0)
    a = ap.parse_args()
    print(f"{'shape':10s} {'law':8s} {'draws':>5s} {'1e-3 bef':>8s} {'aft':>4s} {'up95':>6s} "
          f"{'1e-2 bef':>8s} {'aft':>4s} {'med g2':>7s} {'med c':>6s} {'max c':>6s} {'s':>5s}")
    for shape in a.shapes.split(","):
        for law in a.laws.split(","):
            t0 = time.process_time()
            out = np.array([one(shape, law, s, a.shift) for s in range(a.first, a.first + a.draws)])
            pb, pa, g2, c = out.T
            n = len(out)
            print(f"{shape:10s} {law:8s} {n:5d} {int((pb < 1e-3).sum()):8d} {int((pa < 1e-3).sum()):4d} "
                  f"{upper95(int((pa < 1e-3).sum()), n):6.3f} {int((pb < 1e-2).sum()):8d} {int((pa < 1e-2).sum()):4d} "
                  f"{np.median(g2):7.2f} {np.median(c):6.3f} {c.max():6.3f} {time.process_time() - t0:5.0f}", flush=True)


if __name__ == "__main__":
    main()
