"""Diagnostic "near-planar profile": would profile-likelihood error bars cover the bent rooms? (issue 27)

The boundary desks of ``near_planar_rooms.py`` that end 3-D at exit 0 with units beyond 3
of their error bars (``KNOWN_BENT`` in ``tests/acoustics/test_near_planar.py``) have bent
ML fits: the heights enter the long ranges at second order, and the linearised (CRLB) bars
are millimetres while the heights are centimetres off. This script asks whether error
bars from the likelihood itself would cover them, per room, on the pipeline's own final
matrix and fit (``run_pipeline`` with its defaults, heights removed):

- the model is the pipeline's: ``c t_ij = |r_i - s_j| + c delta_i + c tau_j``, i.i.d.
  Gaussian ranges, variance ``sigma^2 = RSS / (m - p)`` of the 3-D fit (the variance the
  result's covariances are scaled by; ``p = 3 n - 6 + n - 1``); the gauge by inner
  constraints at the fit (no translation or rotation of the positions: the frame the
  covariances are stated in, and to first order the Procrustes frame the truth is judged in);
- ``lr_truth``: ``(RSS(truth) - RSS(fit)) / sigma^2`` with the positions at the truth
  (aligned) and the offsets refitted, against chi-square(3 n - 6) (0.9973 quantile 87 at
  n = 20);
- per unit, the **profile likelihood of its height** (its coordinate along the layout's
  normal, made gauge-free; every other parameter refitted): ``lr_unit_max`` / ``lr_unit_gt9``
  at the truth's height; the interval where the profile LR stays below ``Q`` = 9
  (chi-square(1)'s 0.9973 quantile: the 3-sigma level the tests judge error bars at) and the
  covariance widened along the normal so that 3 of its stds span the interval on each
  side (``widen_median`` / ``widen_max``: the larger half-width over 3 linearised stds,
  per unit); ``covered_crlb`` / ``covered_profile``: units within chi-square(3)'s 0.9973
  quantile of the truth (the benchmark's criterion) with the result's and the widened
  covariances;
- the **bend direction**, from the 3-D fit to the 2-D fit lifted into its frame:
  ``t_truth`` (the truth's projection on it, 0 = the 3-D fit, 1 = the 2-D fit), the profile
  LR at ``t_truth`` (the other parameters refitted) and ``t_end``, where the profile LR
  reaches ``Q``;
- ``boot_rms_mm``: a parametric bootstrap at the 2-D fit (a planar truth; 32 replicates of
  Gaussian noise ``sigma`` refitted in 3-D from the observed fit and from the replicate's
  planar truth lifted by random heights of the bending scale), the RMS height error of
  each unit; ``covered_boot``: units covered with the covariance plus that error's
  second moment (its 3 x 3 mean square);
- ``truth_rep_max_mm``: 20 replicates simulated from the *truth* (same noise), refitted in
  3-D: the median over replicates of the largest height error (the estimator's scatter at
  the truth, against the CRLB at the fit).

Run: ``OPENBLAS_NUM_THREADS=1 PYTHONPATH=src .venv/bin/python benchmarks/near_planar_profile.py
LAYOUT SEED [SEED ...]`` (15-30 s CPU per seed). One JSON line per seed.
"""

from __future__ import annotations

import json
import sys
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np
from click.testing import CliRunner
from scipy.linalg import null_space

from selfcal.acoustics import run_pipeline
from selfcal.acoustics.calibrate import sender_matrix
from selfcal.cli import main
from selfcal.geometry import align

Q = 9.0  # chi-square(1) 0.9973: 3 sigma
Q3 = 14.16  # chi-square(3) 0.9973: the benchmark's "3 error bars" of a 3-D position


class Model:
    """Ranges of one matrix: residuals, Jacobian, constrained Gauss-Newton."""

    def __init__(self, Y: np.ndarray, I: int) -> None:
        self.I, self.n = I, I + Y.shape[1]
        obs = np.isfinite(Y)
        self.ii, self.jj = np.nonzero(obs)
        self.y = Y[obs]

    def resid(self, x: np.ndarray, off: np.ndarray, y: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        P = x.reshape(self.n, 3)
        diff = P[self.ii] - P[self.I + self.jj]
        rho = np.linalg.norm(diff, axis=1)
        e = (self.y if y is None else y) - rho - off[self.ii] - off[self.I + self.jj]
        return e, diff / rho[:, None]

    def jac(self, u: np.ndarray) -> np.ndarray:
        m, n = len(self.ii), self.n
        Jm = np.zeros((m, 4 * n))
        rows = np.arange(m)
        for a in range(3):
            Jm[rows, 3 * self.ii + a] = -u[:, a]
            Jm[rows, 3 * (self.I + self.jj) + a] = u[:, a]
        Jm[rows, 3 * n + self.ii] = -1.0
        Jm[rows, 3 * n + self.I + self.jj] = -1.0
        return Jm

    def fit(self, x0: np.ndarray, off0: np.ndarray, A: np.ndarray | None = None, rhs: np.ndarray | None = None,
            ref: np.ndarray | None = None, y: np.ndarray | None = None, iters: int = 60) -> tuple[np.ndarray, np.ndarray, float]:
        """Least squares over positions and offsets with ``A^T (x - ref) = rhs`` (``A`` None: free)."""
        n3 = 3 * self.n
        if A is None:
            B, xp = np.eye(n3), np.zeros(n3)
        else:
            B = null_space(A.T)
            xp = ref + A @ np.linalg.solve(A.T @ A, rhs)
        yv = B.T @ (x0 - xp)
        off = off0.copy()
        x = xp + B @ yv
        e, u = self.resid(x, off, y)
        rss = float(e @ e)
        for _ in range(iters):
            Jm = self.jac(u)
            Jr = np.hstack([Jm[:, :n3] @ B, Jm[:, n3:]])
            step = np.linalg.lstsq(Jr, -e, rcond=1e-10)[0]
            lam = 1.0
            while lam > 1e-4:
                y2, o2 = yv + lam * step[:B.shape[1]], off + lam * step[B.shape[1]:]
                x2 = xp + B @ y2
                e2, u2 = self.resid(x2, o2, y)
                if e2 @ e2 <= rss:
                    break
                lam /= 2
            else:
                break
            dec = rss - float(e2 @ e2)
            yv, off, x, e, u, rss = y2, o2, x2, e2, u2, float(e2 @ e2)
            if dec <= 1e-12 * rss:
                break
        return x, off, rss


def gauge(x: np.ndarray, n: int) -> np.ndarray:
    """(3 n, 6): translations and infinitesimal rotations of the positions."""
    P = x.reshape(n, 3)
    cen = P - P.mean(axis=0)
    G = []
    for a in range(3):
        e = np.zeros((n, 3))
        e[:, a] = 1.0
        G.append(e.ravel())
    for a in range(3):
        w = np.zeros(3)
        w[a] = 1.0
        G.append(np.cross(w, cen).ravel())
    return np.array(G).T


def degauge(v: np.ndarray, G: np.ndarray) -> np.ndarray:
    return v - G @ np.linalg.lstsq(G, v, rcond=None)[0]


def covered(err: np.ndarray, cov: np.ndarray) -> int:
    return int(sum(e @ np.linalg.solve(C, e) <= Q3 for e, C in zip(err, cov, strict=True)))


def analyse(rec: Path) -> dict:
    t0 = time.process_time()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        res = run_pipeline(rec, progress=False)
    t_pipe = time.process_time() - t0
    out: dict = {"dim": res.dim, "exit": 0 if res.success else 1, "pipeline_cpu_s": round(t_pipe, 2)}
    if res.dim != 3 or not np.isfinite(np.vstack([res.receivers, res.sources])).all():
        return out
    c = res.speed_of_sound
    T = sender_matrix(res.toa_matrix, res.event_senders, len(res.sender_names))
    I = len(res.receivers)
    mdl = Model(T * c, I)
    n = mdl.n
    x0 = np.vstack([res.receivers, res.sources]).ravel()
    off0 = np.concatenate([res.receiver_offsets, res.source_offsets]) * c
    G = gauge(x0, n)
    x_ml, off_ml, rss_ml = mdl.fit(x0, off0, G, np.zeros(6), ref=x0)
    m = len(mdl.y)
    s2 = rss_ml / (m - (4 * n - 7))
    cov = np.concatenate([res.receiver_cov, res.source_cov])
    truth = json.loads((rec / "truth.json").read_text())
    tru = np.vstack([truth["receivers"], truth["senders"]]).astype(float)
    Xt = align(tru, x_ml.reshape(n, 3), reflection=True).apply(tru).ravel()
    _, off_t, rss_t = mdl.fit(Xt, off_ml, np.eye(3 * n), np.zeros(3 * n), ref=Xt)
    P = x_ml.reshape(n, 3)
    nrm = np.linalg.svd(P - P.mean(axis=0))[2][-1]
    err = (Xt - x_ml).reshape(n, 3)
    out.update(sigma_um=round(float(np.sqrt(s2)) * 1e6, 2), dof=m - (4 * n - 7),
               lr_truth=round((rss_t - rss_ml) / s2, 1), max_height_err_mm=round(float(np.abs(err @ nrm).max()) * 1e3, 1),
               covered_crlb=covered(err, cov))

    # per-unit profile of the height
    t1 = time.process_time()
    lr_unit, wide, factor = [], cov.copy(), []
    for k in range(n):
        v = np.zeros(3 * n)
        v[3 * k: 3 * k + 3] = nrm
        v = degauge(v, G)
        scale = float(v[3 * k: 3 * k + 3] @ nrm)  # height change of unit k per unit of t
        A = np.column_stack([G, v / np.linalg.norm(v)])
        vn = np.linalg.norm(v)

        def lr(h: float, k: int = k, A: np.ndarray = A, vn: float = vn, scale: float = scale) -> float:
            x, _, r = mdl.fit(x_ml, off_ml, A, np.r_[np.zeros(6), h / scale * vn], ref=x_ml)
            return (r - rss_ml) / s2

        lr_unit.append(lr(float(err[k] @ nrm)))
        sd = float(np.sqrt(nrm @ cov[k] @ nrm))
        half = []
        for sgn in (-1.0, 1.0):
            a, b = 0.0, sgn * 3.0 * sd
            while lr(b) < Q and abs(b) < 1.0:
                a, b = b, 2.0 * b
            for _ in range(12):  # bisection to ~0.03 % of the bracket
                mid = 0.5 * (a + b)
                a, b = (mid, b) if lr(mid) < Q else (a, mid)
            half.append(abs(b))
        hw = max(half)
        factor.append(hw / 3.0 / sd)
        if hw / 3.0 > sd:
            wide[k] = cov[k] + ((hw / 3.0) ** 2 - sd**2) * np.outer(nrm, nrm)
    t_prof = time.process_time() - t1
    lr_unit_a = np.array(lr_unit)
    out.update(lr_unit_max=round(float(lr_unit_a.max()), 1), lr_unit_gt9=int((lr_unit_a > Q).sum()),
               covered_profile=covered(err, wide), profile_cpu_s=round(t_prof, 2),
               widen_median=round(float(np.median(factor)), 2), widen_max=round(float(np.max(factor)), 2))

    # the bend direction: 3-D fit -> 2-D fit lifted
    h = (P - P.mean(axis=0)) @ nrm
    V = np.zeros((3 * n, n))
    for k in range(n):
        V[3 * k: 3 * k + 3, k] = nrm
    flat = (P - np.outer(h, nrm)).ravel()
    x2, off2, rss2 = mdl.fit(flat, off_ml, V, np.zeros(n), ref=flat)
    x2 = align(x2.reshape(n, 3), P, reflection=False).apply(x2.reshape(n, 3)).ravel()
    d = degauge(x2 - x_ml, G)
    t_truth = float(degauge(Xt - x_ml, G) @ d / (d @ d))
    A = np.column_stack([G, d / np.linalg.norm(d)])
    prof: dict[float, float] = {}
    xs = x_ml
    for t in np.linspace(0.05, 1.0, 20):
        xs, _, r = mdl.fit(xs, off_ml, A, np.r_[np.zeros(6), t * np.linalg.norm(d)], ref=x_ml)
        prof[float(t)] = (r - rss_ml) / s2
    xs, _, r = mdl.fit(x_ml + min(t_truth, 1.0) * d, off_ml, A, np.r_[np.zeros(6), t_truth * np.linalg.norm(d)], ref=x_ml)
    t_end = next((t for t, v in prof.items() if v >= Q), float("inf"))
    out.update(lr_2d=round((rss2 - rss_ml) / s2, 1), t_truth=round(t_truth, 2), lr_at_t_truth=round((r - rss_ml) / s2, 1),
               t_end=t_end)

    # parametric bootstrap at the 2-D fit (a planar truth)
    rng = np.random.default_rng(0)
    e2, _ = mdl.resid(x2, off2)
    mu = mdl.y - e2
    P2 = x2.reshape(n, 3)
    bend = float(np.sqrt(np.sqrt(s2) * np.ptp(P2, axis=0).max()))
    G2 = gauge(x2, n)
    mse = np.zeros((n, 3, 3))
    B = 32
    for _ in range(B):
        yy = mu + rng.normal(0.0, np.sqrt(s2), len(mu))
        best = None
        for st in (x_ml, (P2 + np.outer(rng.normal(0.0, bend, n), nrm)).ravel()):
            xr, _, r = mdl.fit(st, off_ml, G2, np.zeros(6), ref=x2, y=yy)
            if best is None or r < best[1]:
                best = (xr, r)
        xr = best[0].reshape(n, 3)
        er = align(xr, P2, reflection=True).apply(xr) - P2
        mse += np.einsum("ki,kj->kij", er, er) / B
    boot = cov + mse
    out.update(boot_rms_mm=[round(float(np.sqrt(nrm @ M @ nrm)) * 1e3, 1) for M in mse],
               covered_boot=covered(err, boot))

    # replicates from the truth: the estimator's scatter where it matters
    e_t, _ = mdl.resid(Xt, off_t)
    mu_t = mdl.y - e_t
    Gt = gauge(Xt, n)
    Pt = Xt.reshape(n, 3)
    worst = []
    for _ in range(20):
        yy = mu_t + rng.normal(0.0, np.sqrt(s2), len(mu_t))
        best = None
        for st in (Xt, x_ml):
            xr, _, r = mdl.fit(st, off_t, Gt, np.zeros(6), ref=Xt, y=yy)
            if best is None or r < best[1]:
                best = (xr, r)
        xr = best[0].reshape(n, 3)
        worst.append(float(np.abs((align(xr, Pt, reflection=True).apply(xr) - Pt) @ nrm).max()))
    out.update(truth_rep_max_mm=round(float(np.median(worst)) * 1e3, 1), truth_rep_max_max_mm=round(max(worst) * 1e3, 1))
    return out


def simulate(layout: str, seed: int, work: Path) -> Path:
    rec = work / f"{layout}{seed}"
    res = CliRunner().invoke(main, ["simulate", "conference", "--units", "10", "--room", "8x7x3", "--rt60", "0.4",
                                    "--snr", "30", "--seed", str(seed), "--layout", layout, "--sample-rate", "16000",
                                    "--max-order", "2", "--out", str(rec)])
    assert res.exit_code == 0, res.output
    (rec / "heights.json").unlink(missing_ok=True)
    return rec


if __name__ == "__main__":
    layout, seeds = sys.argv[1], [int(s) for s in sys.argv[2:]]
    with tempfile.TemporaryDirectory() as tmp:
        for s in seeds:
            print(json.dumps({"layout": layout, "seed": s, **analyse(simulate(layout, s, Path(tmp)))}), flush=True)
