"""Calibration of the far-field covariances over noise draws (issue 31 follow-up).

For one case (dimension, offsets mode, noise law, loss, size) it draws ``runs`` matrices from one
random geometry, solves each with :func:`selfcal.tdoa.solve_farfield` (defaults: screen on) and
reports, after aligning the truth in the covariance's gauge (first position at the origin, the
rotation about it that best maps the true positions onto the estimate; in 1-D the best scale):

* ``pos_mean_mah/dim``: mean squared Mahalanobis distance of the position errors under
  ``position_cov`` per dimension (1 when calibrated), ``pos_cov95``: share inside the 95 % region;
* ``dir_mean_mah/dim``, ``dir_cov95``: the same for the directions under ``direction_cov``
  (tangent dimension d - 1);
* ``draws_with_rejections`` (screen / robust rejections), ``refused`` (draws the solver refused,
  e.g. the rank test calling planar heavy-tailed data 3-D).

Usage (one line per case)::

    OPENBLAS_NUM_THREADS=1 PYTHONPATH=src python benchmarks/farfield_cov_calibration.py \\
        DIM OFFSETS NOISE RUNS [LOSS [screen|noscreen [MxK]]]

NOISE: gauss, t3, t5 (Student-t scaled to the same variance), laplace. Defaults: linear loss,
screen on, 10 x 20, noise std 2 mm against a 1 m array.
"""

from __future__ import annotations

import sys
import time
import warnings

import numpy as np
from scipy import stats

from selfcal.tdoa import solve_farfield


def noise(rng: np.random.Generator, kind: str, shape: tuple[int, int], sigma: float) -> np.ndarray:
    if kind == "gauss":
        return sigma * rng.standard_normal(shape)
    if kind.startswith("t"):
        nu = float(kind[1:])
        return sigma * rng.standard_t(nu, shape) / np.sqrt(nu / (nu - 2))
    if kind == "laplace":
        return sigma * rng.laplace(size=shape) / np.sqrt(2)
    raise ValueError(kind)


def run(d: int, offsets: str, kind: str, runs: int, m: int = 10, k: int = 20, loss: str = "linear",
        screen: bool = True, sigma: float = 2e-3, seed: int = 0) -> dict[str, float]:
    rng = np.random.default_rng(seed)
    Z = rng.uniform(-0.5, 0.5, (m, d))
    Z -= Z[0]
    N = rng.normal(size=(k, d))
    N /= np.linalg.norm(N, axis=1, keepdims=True)
    if d == 1:
        N = rng.uniform(-1, 1, (k, 1))
        N[0] = 1.0
    C = rng.normal(size=k)
    pm, dm = [], []
    rejected = refused = 0
    for _ in range(runs):
        D = Z @ N.T + C + noise(rng, kind, (m, k), sigma)
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                res = solve_farfield(D, dim=d, offsets=offsets, loss=loss, screen=screen)
        except Exception:
            refused += 1
            continue
        rejected += int(res.rejected.any())
        Zh = res.positions
        if d == 1:
            E = Zh - float(Z[:, 0] @ Zh[:, 0] / (Z[:, 0] @ Z[:, 0])) * Z
        else:
            U, _, Vt = np.linalg.svd(Zh.T @ Z)
            R = U @ Vt
            E = Zh - Z @ R.T
        pm.append([float(E[i] @ np.linalg.pinv(res.position_cov[i]) @ E[i]) for i in range(1, m)])
        if res.direction_cov is not None and d > 1:
            En = res.directions - N @ R.T
            dm.append([float(En[j] @ np.linalg.pinv(res.direction_cov[j], rcond=1e-8, hermitian=True) @ En[j])
                       for j in range(k)])
    p = np.array(pm)
    out = {"pos_mean_mah/dim": float(p.mean() / d), "pos_cov95": float(np.mean(p < stats.chi2.ppf(0.95, d)))}
    if dm:
        q = np.array(dm)
        out["dir_mean_mah/dim"] = float(q.mean() / (d - 1))
        out["dir_cov95"] = float(np.mean(q < stats.chi2.ppf(0.95, d - 1)))
    out["draws_with_rejections"] = rejected
    out["refused"] = refused
    return out


if __name__ == "__main__":
    d, off, kind, runs = int(sys.argv[1]), sys.argv[2], sys.argv[3], int(sys.argv[4])
    loss = sys.argv[5] if len(sys.argv) > 5 else "linear"
    scr = (sys.argv[6] != "noscreen") if len(sys.argv) > 6 else True
    mk = [int(x) for x in sys.argv[7].split("x")] if len(sys.argv) > 7 else [10, 20]
    t = time.process_time()
    o = run(d, off, kind, runs, m=mk[0], k=mk[1], loss=loss, screen=scr)
    print(d, off, kind, loss, f"{mk[0]}x{mk[1]}", {key: round(v, 3) for key, v in o.items()},
          f"cpu {time.process_time() - t:.1f}s")
