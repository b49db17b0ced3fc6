"""Range-only localization with odometry and per-beacon range calibration (robot + beacons).

One robot drives with odometry increments ``[dd, dpsi]`` (each composed "drive along the
heading, then turn") and ranges to beacons at known positions. The range model is

    r = s_b |p - b_b| + o_b + noise                                              (R1)

with a per-beacon scale ``s_b`` (prior N(1, scale_std^2)) and offset ``o_b`` (prior
N(0, offset_std^2)) -- eq. 1 of paper 002 extended by the scale factor that real radio
ranging shows (several percent on the CMU logs). The state is
``[x, y, psi, s_1..s_B, o_1..o_B]``.

Two estimators share one linear-Gaussian engine:

* :func:`solve_range_slac` with ``method="filter"``: a causal extended Kalman filter (the
  estimate at time t uses the data up to t). Each range is gated by a chi-square test on its
  innovation (quantile ``gate_quantile`` of chi2(1)) and the survivors are applied with a
  Huber weight on the normalised innovation (robust Kalman update, Masreliez & Martin 1977).
  Three mechanisms keep its covariances honest (measured by ``benchmarks/slac_consistency.py``):
  each heading-noise candidate runs with and without an odometry distance-scale state
  (:data:`ODO_SCALE_STD`; a wheel-radius error is a constant of the log that no random-walk
  noise density covers), mixed by predictive likelihood; an M-of-N test on each beacon's
  gate decisions re-initialises a calibration locked on a wrong value by an outlier among
  its first ranges (:data:`RECOVER_M`); and the run tests its own innovations
  (:func:`innovation_tests`: NIS level and whiteness) and reports ``FAILED_TEST`` when they
  show the covariances to be overconfident.
* ``method="smoother"``: the batch MAP estimate over the whole log, computed by the iterated
  extended Kalman smoother (Bell 1994: Gauss-Newton on the full trajectory, each iteration
  a forward Kalman pass linearised about the previous smoothed trajectory + an RTS backward
  pass) with Huber IRLS weights and the same chi-square gate on the residuals; the range
  noise is re-estimated from the causal filter's predictive innovations (robust, median
  based), the heading and odometry-distance noise factors chosen by the filter's predictive
  likelihood over grids. The range scales get a prior estimated from the log (empirical
  Bayes, :func:`selfcal.slac.scale_prior.scale_prior_eb`); the models with and without an
  odometry distance scale are both solved and averaged with their posterior probabilities
  (:func:`selfcal.slac.scale_prior.odo_scale_weight`). Its covariances are the Laplace
  marginals at the solution (of the mixture, when two models are averaged).

Use the filter online (or when the data arrive as a stream), the smoother offline when the
whole log is at hand: it is several times more accurate because the calibration learnt late
in the log also corrects the early poses.

Ranges are applied at their own times: an odometry row whose interval contains range times
is split there (each piece a fraction of the row proportional to its duration), so no range
is moved to the nearest odometry time.

Why this file is long (~770 lines, above the package's ~600 guideline): the filter, the smoother, the
calibration refit and the noise re-estimation are one engine over one private chain
structure (``_Chain``, ``_Pass``); split into modules they would share every private type.
What has a seam lives elsewhere: the inputs and the result in :mod:`selfcal.slac.range_model`,
the filter's innovation tests in :mod:`selfcal.slac.consistency` (both re-exported here), the
empirical-Bayes priors of the beacon scales and the odometry scale in :mod:`selfcal.slac.scale_prior`.
"""

from __future__ import annotations

import warnings
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy import stats
from scipy.optimize import brentq

from .._checks import entry, has_attributes
from ..errors import ConvergenceWarning, InputError
from ..geometry import wrap_angle
from ..robust import loss_rho
from .consistency import innovation_tests
from .odometry_em import odometry_noise_factors
from .range_model import RangeLog, RangeModelConfig, RangeSlacResult
from .scale_prior import ODO_SCALE_STD, SCALE_PRIOR_FLOOR, odo_scale_weight, scale_prior_eb

__all__ = ["RangeLog", "RangeModelConfig", "RangeSlacResult", "solve_range_slac", "huber_weight", "innovation_tests"]

FArray = NDArray[np.float64]
IArray = NDArray[np.int64]

#: M-of-N test on a beacon's gate decisions (track maintenance, Blackman 1986): when
#: ``RECOVER_M`` of its last ``RECOVER_N`` ranges are gated the filter's calibration of that
#: beacon is taken as locked on a wrong value (typically an outlier among its first ranges,
#: which no gate can see while the calibration is still unknown) and re-initialised. A
#: consistent filter with a share ``eps`` of outliers triggers it by chance with probability
#: about ``C(5, 4) eps^4`` per range, 5e-4 at ``eps`` = 10 %; a re-initialisation only forgets.
RECOVER_M, RECOVER_N = 4, 5
#: Level of each of the causal filter's two innovation tests (NIS level, whiteness;
#: :func:`innovation_tests`, with its tolerance 1.3): a run at the tolerance fails one of
#: them with probability <= 2 %, a consistent one far less often.
CONSISTENCY_ALPHA = 0.01


def huber_weight(e: FArray, k: float) -> FArray:
    """IRLS weight ``min(1, k / |e|)`` of the Huber loss for standardised residuals ``e``
    (``rho'`` of :func:`selfcal.robust.loss_rho` at ``z = (e / k)^2``)."""
    return loss_rho((np.asarray(e, dtype=float) / k) ** 2, "huber")[1]


@dataclass
class _Chain:
    """Nodes at the union of odometry and range times; increment ``inc[n]`` drives node n-1 -> n."""

    times: FArray
    inc: FArray  # (N, 2), row 0 unused
    var: FArray  # (N, 2) odometry variances of each increment
    pose_nodes: IArray  # (P,) chain index of each pose time
    r_start: IArray  # (N + 1,) CSR pointers into the range arrays
    r_beacon: IArray
    r_value: FArray
    outside: int


def _build_chain(log: RangeLog, cfg: RangeModelConfig) -> _Chain:
    ot, odo = np.asarray(log.odo_times, dtype=float), np.asarray(log.odo, dtype=float)
    # rows at one time are one increment (their sum; the composition differs at second order only)
    ut, first = np.unique(ot, return_index=True)
    odo = np.add.reduceat(odo, first, axis=0) if ut.size < ot.size else odo
    ot = ut
    t0 = float(log.start_time)
    rt = np.asarray(log.range_times, dtype=float)
    inside = (rt > t0) & (rt <= ot[-1])
    order = np.argsort(rt[inside], kind="stable")
    rt_in = rt[inside][order]
    rb = np.asarray(log.range_beacon, dtype=np.int64)[inside][order]
    rv = np.asarray(log.ranges, dtype=float)[inside][order]
    pose_t = np.concatenate([[t0], ot])
    times = np.union1d(pose_t, rt_in)
    row = np.searchsorted(ot, times[1:], side="left")  # node n (>0) lies in odometry row row[n-1]
    row_t0 = pose_t[row]
    frac = (times[1:] - times[:-1]) / (ot[row] - row_t0)
    inc = np.zeros((times.size, 2))
    inc[1:] = odo[row] * frac[:, None]
    dd, dp = np.abs(inc[:, 0]), np.abs(inc[:, 1])
    var = np.column_stack([cfg.odo_distance**2 * dd, cfg.odo_turn**2 * dp + cfg.odo_drift**2 * dd])
    node_of_range = np.searchsorted(times, rt_in)
    r_start = np.searchsorted(node_of_range, np.arange(times.size + 1), side="left")
    return _Chain(times=times, inc=inc, var=var, pose_nodes=np.searchsorted(times, pose_t), r_start=r_start,
                  r_beacon=rb, r_value=rv, outside=int((~inside).sum()))


def _motion(x: FArray, u: FArray) -> tuple[FArray, FArray, FArray]:
    """Drive then turn: new pose, Jacobian F (3, 3) in the pose, G (3, 2) in the increment."""
    c, s = np.cos(x[2]), np.sin(x[2])
    xn = np.array([x[0] + u[0] * c, x[1] + u[0] * s, x[2] + u[1]])
    F = np.array([[1.0, 0.0, -u[0] * s], [0.0, 1.0, u[0] * c], [0.0, 0.0, 1.0]])
    G = np.array([[c, 0.0], [s, 0.0], [0.0, 1.0]])
    return xn, F, G


@dataclass
class _Pass:
    mf: FArray
    Pf: FArray
    mp: FArray | None
    Pp: FArray | None
    F: FArray | None
    innov: FArray  # (K,) innovation at the filter's prediction
    innov_var0: FArray  # (K,) H P H^T (prediction part of the innovation variance)
    used: NDArray[np.bool_]
    noise_final: float = float("nan")
    noise_used: FArray = field(default_factory=lambda: np.zeros(0))  # (K,) range noise std applied at each range
    loglik: FArray = field(default_factory=lambda: np.zeros(0))  # (N,) robust predictive log-likelihood of the ranges up to node n
    resets: int = 0  # beacon calibrations re-initialised by the M-of-N gate test


def _forward(ch: _Chain, log: RangeLog, cfg: RangeModelConfig, noise: float, *, ref: FArray | None,
             weights: FArray | None, store: bool, progress: bool, var: FArray | None = None,
             adapt: bool = False, noise_seq: FArray | None = None, odo_scale: bool = False,
             scale_cov: FArray | None = None, odo_scale_std: float = ODO_SCALE_STD) -> _Pass:
    """One Kalman pass; ``ref`` None = EKF about the running estimate (gate + Huber on the
    innovations), else linearised about ``ref`` (N, D) with the given range ``weights`` (0 = out).

    ``odo_scale`` (causal filter only): one more state, the odometry's distance scale ``k``
    (``dd_true = k dd``, prior N(1, ODO_SCALE_STD^2)), the last entry of the state vector. With
    ``ref`` None, a beacon with ``RECOVER_M`` of its last ``RECOVER_N`` ranges gated has its
    calibration re-initialised (see :data:`RECOVER_M`). ``scale_cov`` (B, B): the prior
    covariance of the scales (default ``scale_std^2 I``; the smoother's empirical-Bayes prior);
    ``odo_scale_std`` the prior std of ``k``."""
    B = log.beacons.shape[0]
    D = 3 + 2 * B + (1 if odo_scale else 0)
    N = ch.times.size
    K = ch.r_value.size
    m = np.concatenate([log.start_pose, np.ones(B), np.zeros(B), [1.0] if odo_scale else []])
    prior_var = np.concatenate([[cfg.init_position_std**2] * 2, [cfg.init_heading_std**2], [cfg.scale_std**2] * B,
                                [cfg.offset_std**2] * B, [odo_scale_std**2] if odo_scale else []])
    P = np.diag(prior_var)
    if scale_cov is not None:
        P[3 : 3 + B, 3 : 3 + B] = scale_cov
    gated_hist = np.zeros((B, RECOVER_N), dtype=bool)  # ring buffer of each beacon's last gate decisions
    n_seen = np.zeros(B, dtype=np.int64)
    resets = 0
    mf = np.empty((N, D))
    Pf = np.empty((N, D, D))
    mp = np.empty((N, D)) if store else None
    Pp = np.empty((N, D, D)) if store else None
    Fs = np.zeros((N, 3, D)) if store else None  # pose rows of the transition A (the rest is I)
    innov = np.zeros(K)
    innov_var0 = np.zeros(K)
    noise_used = np.zeros(K)
    used = np.zeros(K, dtype=bool)
    gate2 = float(stats.chi2.ppf(cfg.gate_quantile, 1)) if cfg.gate_quantile < 1 else np.inf
    r2 = noise**2
    var = ch.var if var is None else var
    beac = log.beacons
    seen = 0
    ll = 0.0
    ll_nodes = np.zeros(N)
    hk = cfg.huber
    it: Iterable[int] = range(N)
    if progress:
        from ..progress import stage

        it = stage.iterate(it, "ranges" if ref is None else "smoother pass", unit="steps")
    for n in it:
        if n > 0:
            lin = m[:3] if ref is None else ref[n - 1, :3]
            u = ch.inc[n]
            kl = 1.0
            if odo_scale:  # the odometry scale at the linearisation point (EKF: the estimate)
                kl = float(m[-1] if ref is None else ref[n - 1, -1])
                u = np.array([kl * u[0], u[1]])
            xn, F, G = _motion(lin, u)
            m = m.copy()
            m[:3] = xn + F @ (m[:3] - lin)
            P = P.copy()
            if odo_scale:  # A = [[F, 0, g], [0, I, 0], [0, 0, 1]], g = d x_n / d k
                J = np.zeros((3, D))
                J[:, :3] = F
                J[:2, -1] = ch.inc[n, 0] * np.array([np.cos(lin[2]), np.sin(lin[2])])
                m[:3] += J[:, -1] * (m[-1] - kl)
                P[:3] = J @ P
                P[:, :3] = P @ J.T
            else:
                P[:3] = F @ P[:3]
                P[:, :3] = P[:, :3] @ F.T
            P[:3, :3] += (G * var[n]) @ G.T
            if store:
                mp[n] = m  # type: ignore[index]
                Pp[n] = P  # type: ignore[index]
                Fs[n, :, :3] = F  # type: ignore[index]
                if odo_scale:
                    Fs[n, :, -1] = J[:, -1]  # type: ignore[index]
        for k in range(ch.r_start[n], ch.r_start[n + 1]):
            b = ch.r_beacon[k]
            xl = m if ref is None else ref[n]
            dl = xl[:2] - beac[b]
            d = float(np.hypot(dl[0], dl[1]))
            s, o = xl[3 + b], xl[3 + B + b]
            H = np.zeros(D)
            H[:2] = s * dl / max(d, 1e-9)
            H[3 + b] = d
            H[3 + B + b] = 1.0
            y = ch.r_value[k] - (s * d + o) - H @ (m - xl)
            PH = P @ H
            c0 = float(H @ PH)
            innov[k], innov_var0[k] = y, c0
            seen += 1
            if adapt and seen >= 50 and seen % 25 == 0:  # causal: innovations up to this range only
                lo = max(0, k + 1 - cfg.noise_window)
                s_hat = _noise_from_innovations(innov[lo : k + 1], innov_var0[lo : k + 1])
                if np.isfinite(s_hat) and s_hat > 0:
                    r2 = s_hat**2
            if noise_seq is not None:
                r2 = float(noise_seq[k]) ** 2
            noise_used[k] = np.sqrt(r2)
            if ref is None:
                e2 = y * y / (c0 + r2)
                # Huber density of the standardised innovation (model selection), flat beyond
                # the gate: a gated range is an outlier whichever model is right, and scoring
                # it by its distance let the model with the widest prediction win on outliers
                # alone (the odometry-scale candidates won 0.5-1.0 of the weight on logs
                # without a scale error: filter RMSE 0.249 m against 0.226 m, 20 seeds)
                ae = np.sqrt(min(e2, gate2))
                ll -= 0.5 * np.log(c0 + r2) + (0.5 * ae * ae if ae <= hk else hk * ae - 0.5 * hk * hk)
                gated = e2 > gate2
                gated_hist[b, n_seen[b] % RECOVER_N] = gated
                n_seen[b] += 1
                if gated and gated_hist[b].sum() >= RECOVER_M:
                    # the beacon's calibration is locked on a wrong value (M-of-N test):
                    # re-initialise it (prior covariance, no correlation, mean kept)
                    cb = np.array([3 + b, 3 + B + b])
                    P = P.copy()
                    P[cb, :] = 0.0
                    P[:, cb] = 0.0
                    P[cb, cb] = prior_var[cb]
                    gated_hist[b] = False
                    resets += 1
                    PH = P @ H
                    c0 = float(H @ PH)
                    innov_var0[k] = c0
                    e2 = y * y / (c0 + r2)
                    gated = e2 > gate2
                if gated:
                    continue
                w = float(huber_weight(np.sqrt(e2), cfg.huber))
            else:
                w = float(weights[k])  # type: ignore[index]
                if w <= 0:
                    continue
            S = c0 + r2 / w
            Kg = PH / S
            m = m + Kg * y
            P = P - np.outer(Kg, PH)
            P = 0.5 * (P + P.T)
            used[k] = True
        mf[n] = m
        Pf[n] = P
        ll_nodes[n] = ll
    return _Pass(mf=mf, Pf=Pf, mp=mp, Pp=Pp, F=Fs, innov=innov, innov_var0=innov_var0, used=used,
                 noise_final=float(np.sqrt(r2)), loglik=ll_nodes, noise_used=noise_used, resets=resets)


def _rts(ps: _Pass) -> tuple[FArray, FArray, FArray]:
    """Rauch-Tung-Striebel backward pass over a stored forward pass.

    Returns smoothed means (N, D), covariances (N, D, D) and the pose blocks (N, 3, 3) of the
    lag-one cross-covariances ``Cov(x_n, x_{n-1}) = P_n C_{n-1}^T`` (row 0 zero).
    """
    assert ps.mp is not None and ps.Pp is not None and ps.F is not None
    N = ps.mf.shape[0]
    ms = ps.mf.copy()
    Ps = ps.Pf.copy()
    X = np.zeros((N, 3, 3))
    for n in range(N - 2, -1, -1):
        AP = ps.Pf[n].copy()
        AP[:3] = ps.F[n + 1] @ ps.Pf[n]  # A P_f (A: pose rows F, odometry-scale column g; identity elsewhere)
        C = np.linalg.solve(ps.Pp[n + 1], AP).T
        ms[n] = ps.mf[n] + C @ (ms[n + 1] - ps.mp[n + 1])
        Ps[n] = ps.Pf[n] + C @ (Ps[n + 1] - ps.Pp[n + 1]) @ C.T
        X[n + 1] = Ps[n + 1][:3] @ C[:3].T
    return ms, Ps, X


def _fixed_lag(ps: _Pass, times: FArray, lag_s: float) -> tuple[FArray, FArray]:
    """Fixed-lag RTS over a stored forward pass: the estimate of node n from the data up to
    ``times[n] + lag_s`` (the RTS recursion run back from the last node within the lag).

    Returns means (N, D) and covariances (N, D, D). Cost O(N L D^3) for L nodes per lag; online
    only the last L nodes' filter quantities are needed (here the pass is stored whole).
    """
    assert ps.mp is not None and ps.Pp is not None and ps.F is not None
    N = ps.mf.shape[0]
    gains = np.empty((max(N - 1, 0),) + ps.Pf.shape[1:])
    for n in range(N - 1):
        AP = ps.Pf[n].copy()
        AP[:3] = ps.F[n + 1] @ ps.Pf[n]  # A P_f
        gains[n] = np.linalg.solve(ps.Pp[n + 1], AP).T
    end = np.searchsorted(times, times + lag_s, side="right") - 1
    ms = np.empty_like(ps.mf)
    Ps = np.empty_like(ps.Pf)
    for n in range(N):
        m, P = ps.mf[end[n]], ps.Pf[end[n]]
        for j in range(end[n] - 1, n - 1, -1):
            C = gains[j]
            m = ps.mf[j] + C @ (m - ps.mp[j + 1])
            P = ps.Pf[j] + C @ (P - ps.Pp[j + 1]) @ C.T
        ms[n], Ps[n] = m, P
    return ms, Ps


def _noise_from_innovations(y: FArray, c0: FArray) -> float:
    """Robust range-noise std from predictive innovations: the sigma at which the median of
    ``y^2 / (c0 + sigma^2)`` equals the chi2(1) median (a robust moment estimator)."""
    med = float(stats.chi2.ppf(0.5, 1))
    if y.size < 10:
        return float("nan")

    def f(s2: float) -> float:
        return float(np.median(y**2 / (c0 + s2))) - med

    hi = float(np.median(y**2)) / med + 1e-12
    if f(1e-12) <= 0:
        return 0.0
    return float(np.sqrt(brentq(f, 1e-12, hi * 10 + 1e-9)))


def _noise_from_residuals(e: FArray, hph: FArray, sigma: float) -> float:
    """Robust range-noise std from residuals at the smoothed mode: the sigma at which the median
    of ``e^2 / (sigma^2 - h P h^T)`` equals the chi2(1) median.

    A residual at the posterior mode has variance ``sigma^2 - h P h^T`` (``P`` the posterior
    covariance of its node, ``h`` the range's Jacobian): the fit has taken up part of the noise.
    Ignoring it biases the estimate low (0.46-0.52 m for a true 0.5 m on plaza-like logs), which
    makes the next Gauss-Newton round trust the ranges too much. Ranges whose ``h P h^T`` exceeds
    half of the current ``sigma^2`` (few: weakly constrained nodes) are left out of the median.
    """
    med = float(stats.chi2.ppf(0.5, 1))
    ok = hph < 0.5 * sigma**2
    if ok.sum() < 10:
        return float("nan")
    e2, c = e[ok] ** 2, hph[ok]
    lo = float(c.max()) * (1 + 1e-9) + 1e-12

    def f(s2: float) -> float:
        return float(np.median(e2 / (s2 - c))) - med

    if f(lo * 1.0000001 + 1e-12) <= 0:
        return float(np.sqrt(lo))
    hi = float(np.median(e2)) / med + float(c.max()) + 1e-9
    while f(hi) > 0:
        hi *= 2
    return float(np.sqrt(brentq(f, lo * 1.0000001 + 1e-12, hi)))


def _residual_var(x: FArray, P: FArray, ch: _Chain, log: RangeLog) -> FArray:
    """``h P h^T`` of every range: the posterior variance of its prediction at the node states
    ``x`` (N, D) with covariances ``P`` (N, D, D)."""
    B = log.beacons.shape[0]
    node = np.repeat(np.arange(ch.times.size), np.diff(ch.r_start))
    b = ch.r_beacon
    xs = x[node]
    dl = xs[:, :2] - log.beacons[b]
    d = np.maximum(np.linalg.norm(dl, axis=1), 1e-9)
    s = xs[np.arange(b.size), 3 + b]
    idx = np.column_stack([np.zeros_like(b), np.ones_like(b), 3 + b, 3 + B + b])  # the non-zero entries of h
    h = np.column_stack([s * dl[:, 0] / d, s * dl[:, 1] / d, d, np.ones(b.size)])
    Pk = P[node[:, None, None], idx[:, :, None], idx[:, None, :]]  # (K, 4, 4)
    return np.einsum("ki,kij,kj->k", h, Pk, h)


def _residuals(x: FArray, ch: _Chain, log: RangeLog) -> FArray:
    """Range residuals z - h(x_node) for every range (node states ``x`` (N, D))."""
    B = log.beacons.shape[0]
    node = np.repeat(np.arange(ch.times.size), np.diff(ch.r_start))
    xs = x[node]
    b = ch.r_beacon
    d = np.linalg.norm(xs[:, :2] - log.beacons[b], axis=1)
    h = xs[np.arange(b.size), 3 + b] * d + xs[np.arange(b.size), 3 + B + b]
    return ch.r_value - h


def _refit_calibration(x: FArray, ch: _Chain, log: RangeLog, cfg: RangeModelConfig, sigma: float) -> FArray:
    """The reference trajectory ``x`` (N, D) with each beacon's (scale, offset) refitted to its
    ranges at the reference positions.

    Given the positions, (R1) is a linear regression ``r = s d + o`` per beacon; it is solved
    robustly (Huber at ``cfg.huber`` sigma, the priors of ``s`` and ``o`` as two pseudo-
    observations). The causal filter's calibration can be far off for a beacon seen only
    from far away (``s`` and ``o`` nearly collinear) and its first ranges then set a wrong
    combination that gates out all the later ones; the smoother's gate is a test of single
    ranges, so it must start from a calibration that fits the beacon's ranges as a whole.
    """
    from scipy.optimize import least_squares

    B = log.beacons.shape[0]
    out = x.copy()
    node = np.repeat(np.arange(ch.times.size), np.diff(ch.r_start))
    for b in range(B):
        k = ch.r_beacon == b
        if k.sum() < 3:
            continue
        d = np.linalg.norm(x[node[k], :2] - log.beacons[b], axis=1)
        r = ch.r_value[k]

        def f(p: FArray, d: FArray = d, r: FArray = r) -> FArray:
            return np.concatenate([(r - p[0] * d - p[1]) / sigma, [(p[0] - 1.0) / cfg.scale_std, p[1] / cfg.offset_std]])

        p0 = np.array([x[-1, 3 + b], x[-1, 3 + B + b]])
        sol = least_squares(f, p0, loss="huber", f_scale=cfg.huber, x_scale=np.array([cfg.scale_std, cfg.offset_std]))
        out[:, 3 + b], out[:, 3 + B + b] = sol.x
    return out


@dataclass
class _Smoothed:
    ms: FArray  # (N, D) smoothed means
    Ps: FArray  # (N, D, D) smoothed covariances
    weights: FArray  # (K,) final range weights (0 = gated)
    sigma: float  # range noise std
    var: FArray  # (N, 2) odometry variances
    lam: FArray  # (2,) EM factors applied to ``var``
    iterations: int
    converged: bool


def _smooth(ch: _Chain, log: RangeLog, cfg: RangeModelConfig, ref: FArray, sigma: float, var: FArray,
            scale_cov: FArray | None, odo_scale_std: float | None, progress: bool) -> _Smoothed:
    """The iterated extended Kalman smoother from the reference trajectory ``ref`` (N, D), with
    the noise levels (range ``sigma``, odometry ``var``) by expectation-maximisation.
    ``odo_scale_std`` not None: the last state is the odometry distance scale ``k`` with
    prior N(1, odo_scale_std^2) (``ref`` has its column).

    ECM: each round a Gauss-Newton solve at fixed noise, then the range noise re-estimated from
    the residuals (robust median estimator) and the two odometry variance factors by EM
    (:func:`~selfcal.slac.odometry_em.odometry_noise_factors`); the given levels are only the start.
    """
    K = ch.r_value.size
    gate2 = float(stats.chi2.ppf(cfg.gate_quantile, 1)) if cfg.gate_quantile < 1 else np.inf
    weights = np.ones(K)
    lam = np.ones(2)
    iterations, status = 0, 1
    ms, Ps = ref, np.zeros((0, 0, 0))
    for rnd in range(cfg.noise_rounds + 1 if cfg.estimate_noise else 1):
        status = 1
        for _ in range(cfg.max_iter):
            e = _residuals(ref, ch, log) / sigma
            weights = np.where(e**2 > gate2, 0.0, huber_weight(e, cfg.huber))
            ps = _forward(ch, log, cfg, sigma, ref=ref, weights=weights, store=True, progress=progress, var=var,
                          scale_cov=scale_cov, odo_scale=odo_scale_std is not None,
                          odo_scale_std=ODO_SCALE_STD if odo_scale_std is None else odo_scale_std)
            ms, Ps, Xs = _rts(ps)
            iterations += 1
            step = np.max(np.abs(ms[:, :3] - ref[:, :3]))
            ref = ms
            if step < cfg.tol:
                status = 0
                break
        if rnd == cfg.noise_rounds or not cfg.estimate_noise:
            break
        s_res = _noise_from_residuals(_residuals(ref, ch, log), _residual_var(ms, Ps, ch, log), sigma)
        # the increments as the model drives them (times the odometry scale, when estimated)
        inc = ch.inc * np.array([ms[0, -1] if odo_scale_std is not None else 1.0, 1.0])
        f_d, f_p = odometry_noise_factors(ms[:, :3], Ps[:, :3, :3], Xs, inc, var)
        f = np.array([f_d, f_p])
        f = np.where(np.isfinite(f) & (f > 0), f, 1.0)
        ds = 0.0
        if np.isfinite(s_res) and s_res > 0:
            ds = abs(np.log(s_res / sigma))
            sigma = s_res
        var = var * f[None, :]
        lam *= f
        if max(ds, float(np.max(np.abs(np.log(f))))) < cfg.noise_tol:
            break
    return _Smoothed(ms=ms, Ps=Ps, weights=weights, sigma=float(sigma), var=var, lam=lam, iterations=iterations,
                     converged=status == 0)


#: A model of the smoother's odometry-scale average (:func:`_mix`) whose posterior probability
#: is below this is not solved: it would move the mean by less than 1e-3 of the distance
#: between the two models' solutions (sub-millimetre on decimetre-level differences).
MODEL_WEIGHT_FLOOR = 1e-3


def _mix(sols: list[tuple[float, _Smoothed]]) -> _Smoothed:
    """Bayesian model average of smoother solutions ``(weight, solution)`` (weights sum to 1):
    mean ``sum w m``, covariance ``sum w (P + (m - mean)(m - mean)^T)`` per node; the noise
    levels, range weights and convergence flag of the most probable model, the iterations summed."""
    if len(sols) == 1:
        return sols[0][1]
    w = np.array([x for x, _ in sols])
    w = w / w.sum()
    ms = sum(wi * s.ms for wi, (_, s) in zip(w, sols, strict=True))
    Ps = np.zeros_like(sols[0][1].Ps)
    for wi, (_, s) in zip(w, sols, strict=True):
        d = s.ms - ms
        Ps += wi * (s.Ps + d[:, :, None] * d[:, None, :])
    top = sols[int(np.argmax(w))][1]
    return _Smoothed(ms=ms, Ps=Ps, weights=top.weights, sigma=top.sigma, var=top.var, lam=top.lam.copy(),
                     iterations=sum(s.iterations for _, s in sols), converged=all(s.converged for _, s in sols))


#: Candidate factors on the odometry distance-noise density (``odo_distance``) the smoother
#: chooses from by the causal filter's predictive likelihood, like the heading factors: the
#: prior (5 % of a metre) is a wheel-only bound, encoders are often far better.
DISTANCE_NOISE_GRID = (1.0, 0.3, 0.1)

@entry(log=has_attributes("beacons", "odo", "ranges", "range_times", "range_beacon",
                          what="RangeLog (or PlazaData)"), method="str", progress="bool")
def solve_range_slac(log: RangeLog | Any, *, method: str = "smoother", config: RangeModelConfig | None = None,
                     progress: bool = False) -> RangeSlacResult:
    """Localize a robot from odometry + beacon ranges and calibrate each beacon's scale and offset.

    Parameters
    ----------
    log : RangeLog or an object with :class:`~selfcal.datasets.plaza.PlazaData`'s attributes.
    method : "filter" (causal robust EKF), "smoother" (batch MAP by the iterated extended
        Kalman smoother) or "fixed-lag" (the filter's poses each smoothed by the next
        ``config.lag_s`` seconds of data); see the module docstring for when to use which.
    config : RangeModelConfig (priors, robust loss, gate).
    progress : a tqdm bar on a terminal (stderr) only.

    Returns
    -------
    RangeSlacResult
        Poses at the start time and each odometry row's end, their stds, per-beacon scale and
        offset of model (R1) with stds, the range-noise estimate and the gate's bookkeeping.

    Notes
    -----
    Motion: ``x' = x + dd cos psi, y' = y + dd sin psi, psi' = psi + dpsi`` with
    ``var(dd) = a^2 |dd|`` and ``var(dpsi) = b^2 |dpsi| + c^2 |dd|`` (paper 002 eq. 14 in
    increment form). Range (R1) with Jacobian ``[s u^T, 0, .., d (at s_b), .., 1 (at o_b)]``,
    ``u`` the unit vector from the beacon. Filter: predict, then per range the chi-square gate
    ``y^2 / S > chi2_1(q)`` and the Huber-weighted update ``R = sigma^2 / w``. Smoother:
    Gauss-Newton iterations of the iterated extended Kalman smoother; each range's weight is
    Huber's ``min(1, k / |e|)`` of its standardised residual, 0 beyond the gate.

    References
    ----------
    - Bell, B. M., "The iterated Kalman smoother as a Gauss-Newton method", SIAM J. Optim. 4 (1994).
    - Masreliez, C. J. and Martin, R. D., "Robust Bayesian estimation for the linear model and
      robustifying the Kalman filter", IEEE TAC 22 (1977).
    - Djugash, J. and Singh, S., "Motion-aided network SLAM with range", IJRR 31 (2012) (the logs).

    Examples
    --------
    >>> import numpy as np
    >>> from selfcal.slac.ranging import RangeLog, solve_range_slac
    >>> beacons = np.array([[0.0, 0.0], [20.0, 0.0], [0.0, 20.0]])
    >>> t = np.arange(1, 101) * 0.5
    >>> odo = np.column_stack([np.full(100, 0.2), np.full(100, 0.03)])
    >>> from selfcal.datasets.plaza import compose_odometry
    >>> truth = compose_odometry(np.array([5.0, 5.0, 0.0]), odo)
    >>> rb = np.tile(np.arange(3), 100)
    >>> rt = np.repeat(t, 3)
    >>> r = 1.05 * np.linalg.norm(truth[np.repeat(np.arange(1, 101), 3), :2] - beacons[rb], axis=1) + 0.2
    >>> log = RangeLog(beacons, np.arange(3), 0.0, truth[0], t, odo, rt, rb, r)
    >>> res = solve_range_slac(log, method="smoother")
    >>> bool(np.max(np.linalg.norm(res.poses[:, :2] - truth[:, :2], axis=1)) < 0.1)
    True
    """
    if method not in ("filter", "smoother", "fixed-lag"):
        raise InputError(f"method must be 'filter', 'smoother' or 'fixed-lag', got {method!r}")
    if not isinstance(log, RangeLog):
        log = RangeLog.from_dataset(log)
    cfg = config or RangeModelConfig()
    ch = _build_chain(log, cfg)
    B = log.beacons.shape[0]
    K = ch.r_value.size
    gate2 = float(stats.chi2.ppf(cfg.gate_quantile, 1)) if cfg.gate_quantile < 1 else np.inf
    z_d, z_t = np.abs(ch.inc[:, 0]), np.abs(ch.inc[:, 1])
    grid = tuple(cfg.heading_noise_grid) or (1.0,)
    # the candidates are compared at one range-noise sequence: the causal estimate of the
    # widest candidate (whose innovations carry the least model misfit). Each candidate
    # adapting its own noise lets a too-stiff heading model hide its misfit in an inflated
    # range noise, and its likelihood then wins (a smoother 10x too confident in heading)
    def _var(g: float, h: float = 1.0) -> FArray:
        return np.column_stack([(h * cfg.odo_distance) ** 2 * z_d, g**2 * (cfg.odo_turn**2 * z_t + cfg.odo_drift**2 * z_d)])

    # the smoother also chooses the odometry distance-noise factor by the same predictive
    # likelihood (its EM does not move a weakly observed variance from its start)
    dgrid = DISTANCE_NOISE_GRID if method == "smoother" else (1.0,)

    wide = int(np.argmax(grid))
    # the causal filter's candidates: each heading factor without and with the odometry-scale
    # state (ODO_SCALE_STD), mixed by their predictive likelihoods like the heading factors
    # (the extra state costs accuracy where the odometry has no scale error: the product of a
    # beacon's range scale and the odometry scale is all a far beacon's range rate sees)
    # The range-noise sequence is the one of the widest candidate without the scale state:
    # with it, the prediction variance early on includes the scale's prior spread, which a
    # log without a scale error does not show, so its median-based noise estimate comes out
    # low and every candidate compared at it is overconfident (20 seeds: far-beacon coverage
    # 0.92, gaps 0.94, RMSE +10-30 %); without it, a scale error inflates the estimate and
    # the scale candidates end conservative (odometry-scale fault: coverage 0.99) -- the
    # side a filter that must not be silently wrong should err on.
    kappa = (False, True) if method == "filter" else (False,)
    ref_pass = _forward(ch, log, cfg, cfg.range_noise, ref=None, weights=None, store=False, progress=progress,
                        var=_var(grid[wide]), adapt=cfg.estimate_noise, odo_scale=False)
    cands = [(i, ks, h) for h in range(len(dgrid)) for ks in kappa for i in range(len(grid))]
    passes = [ref_pass if (i, ks, h) == (wide, False, 0) else
              _forward(ch, log, cfg, cfg.range_noise, ref=None, weights=None, store=False, progress=progress,
                       var=_var(grid[i], dgrid[h]), noise_seq=ref_pass.noise_used, odo_scale=ks)
              for i, ks, h in cands]
    LL = np.stack([np.asarray(p.loglik) for p in passes])  # (C, N)
    best = int(np.argmax(LL[:, -1]))
    fw = passes[best]
    g_best = grid[cands[best][0]]
    h_best = dgrid[cands[best][2]]
    ll_heading = np.array([max(LL[c, -1] for c, (i, _, _) in enumerate(cands) if i == j) for j in range(len(grid))])
    sigma_hat = _noise_from_innovations(fw.innov, fw.innov_var0)
    iterations, status = 1, 0
    lam = np.ones(2)
    scale_weight = 0.0
    scale_prior_std = np.array([0.0, cfg.scale_std])
    odo_prior = ODO_SCALE_STD if method == "filter" else 0.0
    smoother_k = False
    tests: dict[str, float] = {}
    if method == "filter":
        # multiple-model mixture with the causal weights p(model | ranges up to node n)
        W = np.exp(LL - LL.max(axis=0))
        W /= W.sum(axis=0)
        D = 3 + 2 * B + 1
        for p, (_, ks, _) in zip(passes, cands, strict=True):
            if not ks:  # the scale known to be 1: its entries are (1, variance 0)
                p.mf = np.concatenate([p.mf, np.ones((p.mf.shape[0], 1))], axis=1)
                p.Pf = np.pad(p.Pf, ((0, 0), (0, 1), (0, 1)))
        x_nodes = np.einsum("gn,gnd->nd", W, np.stack([p.mf for p in passes]))
        P_nodes = np.zeros((x_nodes.shape[0], D, D))
        for w, p in zip(W, passes, strict=True):
            dx = p.mf - x_nodes
            P_nodes += w[:, None, None] * (p.Pf + dx[:, :, None] * dx[:, None, :])
        cal_x, cal_P = x_nodes[-1], P_nodes[-1]
        used = int(fw.used.sum())
        rejected = int((~fw.used).sum())
        scale_weight = float(sum(W[c, -1] for c, (_, ks, _) in enumerate(cands) if ks))
        nu = fw.innov / np.sqrt(fw.innov_var0 + fw.noise_used**2)
        tests = innovation_tests(nu[fw.used], ch.r_beacon[fw.used], gate2, alpha=CONSISTENCY_ALPHA)
    elif method == "fixed-lag":
        # the causal robust EKF of the best heading candidate (no scale state: the RTS recursion
        # assumes A = blockdiag(F, I)), each pose then smoothed by the ranges of the next lag_s
        # seconds; the calibration is the filter's at the end of the log
        ps = _forward(ch, log, cfg, cfg.range_noise, ref=None, weights=None, store=True, progress=progress,
                      var=_var(g_best), noise_seq=ref_pass.noise_used, odo_scale=False)
        x_nodes, P_nodes = _fixed_lag(ps, ch.times, float(cfg.lag_s))
        cal_x, cal_P = ps.mf[-1], ps.Pf[-1]
        used = int(ps.used.sum())
        rejected = int((~ps.used).sum())
    else:
        sigma = sigma_hat if (cfg.estimate_noise and np.isfinite(sigma_hat) and sigma_hat > 0) else cfg.range_noise
        var = _var(g_best, h_best)
        ref0 = _refit_calibration(fw.mf, ch, log, cfg, sigma)
        if cfg.scale_prior == "empirical" and K:
            # empirical Bayes (type-II maximum likelihood, scale_prior_eb) of the range scales'
            # prior and the Bayes factor of the odometry distance scale k (odo_scale_weight),
            # from the data's own information about them (a first solve under the wide fixed
            # priors), then the MAP again under those priors: a scale error the data do not
            # show shrinks to none
            first = _smooth(ch, log, cfg, np.column_stack([ref0, np.ones(ref0.shape[0])]), sigma, var, None,
                            ODO_SCALE_STD, progress)
            scale_cov, scale_prior_std = scale_prior_eb(first.ms[0, 3 : 3 + B], first.Ps[0, 3 : 3 + B, 3 : 3 + B],
                                                         cfg.scale_std)
            # a beacon without ranges keeps the fixed prior (nothing learnt about it)
            silent = np.bincount(ch.r_beacon, minlength=B) == 0
            scale_cov[silent, :] = 0.0
            scale_cov[:, silent] = 0.0
            scale_cov[silent, silent] = cfg.scale_std**2
            # the odometry distance scale: both models (k ~ N(1, ODO_SCALE_STD^2) and k = 1) solved
            # and mixed by their posterior probabilities (Bayesian model averaging, like the
            # filter's candidates); a model below MODEL_WEIGHT_FLOOR is not solved
            scale_weight = odo_scale_weight(float(first.ms[0, -1]), float(first.Ps[0, -1, -1]))
            sols: list[tuple[float, _Smoothed]] = []
            for prior_k, w_m in ((ODO_SCALE_STD, scale_weight), (SCALE_PRIOR_FLOOR, 1.0 - scale_weight)):
                if w_m < MODEL_WEIGHT_FLOOR:
                    continue
                ref_m = first.ms if prior_k == ODO_SCALE_STD else np.column_stack([first.ms[:, :-1], np.ones(first.ms.shape[0])])
                sols.append((w_m, _smooth(ch, log, cfg, ref_m, first.sigma, first.var, scale_cov, prior_k, progress)))
            sm = _mix(sols)
            odo_prior = ODO_SCALE_STD if scale_weight >= 0.5 else SCALE_PRIOR_FLOOR
            sm.iterations += first.iterations
            sm.lam *= first.lam
            smoother_k = True
        else:
            sm = _smooth(ch, log, cfg, ref0, sigma, var, None, None, progress)
        if sm.sigma != sigma:
            sigma_hat = sm.sigma
        lam, iterations, status, weights = sm.lam, sm.iterations, 0 if sm.converged else 1, sm.weights
        lam = lam * np.array([h_best**2, 1.0])  # the distance factor chosen from the grid, then EM's
        x_nodes, P_nodes = sm.ms, sm.Ps
        cal_x, cal_P = sm.ms[0], sm.Ps[0]
        used = int((weights > 0).sum())
        rejected = int((weights == 0).sum())
    sd_nodes = np.sqrt(np.maximum(np.diagonal(P_nodes, axis1=1, axis2=2), 0.0))
    pn = ch.pose_nodes
    poses = x_nodes[pn, :3].copy()
    poses[:, 2] = wrap_angle(poses[:, 2])
    cal_sd = np.sqrt(np.maximum(np.diag(cal_P), 0.0))
    res = RangeSlacResult(
        method=method, times=ch.times[pn].copy(), poses=poses, pose_std=sd_nodes[pn, :3].copy(),
        beacon_ids=np.asarray(log.beacon_ids).copy(),
        scale=cal_x[3 : 3 + B].copy(), scale_std=cal_sd[3 : 3 + B].copy(),
        offset=cal_x[3 + B : 3 + 2 * B].copy(), offset_std=cal_sd[3 + B : 3 + 2 * B].copy(),
        noise=float(cfg.range_noise), noise_estimate=float(sigma_hat),
        heading_noise_factor=float(g_best * np.sqrt(lam[1])), odometry_noise_factor=lam.copy(), heading_noise_loglik=ll_heading,
        ranges_used=used, ranges_rejected=rejected, ranges_outside=ch.outside, iterations=iterations,
        converged=status == 0, pose_cov=P_nodes[pn, :2, :2].copy(),
        calibration_cov=np.array([cal_P[np.ix_([3 + b, 3 + B + b], [3 + b, 3 + B + b])] for b in range(B)]),
        odometry_scale=float(cal_x[-1]) if method == "filter" or smoother_k else 1.0,
        odometry_scale_std=float(cal_sd[-1]) if method == "filter" or smoother_k else 0.0,
        odometry_scale_prior_std=float(odo_prior),
        odometry_scale_weight=scale_weight, scale_prior_std=scale_prior_std, innovation_test=tests, calibration_resets=int(fw.resets),
    )
    if method == "filter" and not res.success:
        warnings.warn(f"solve_range_slac: {res.message}", ConvergenceWarning, stacklevel=2)
    return res
