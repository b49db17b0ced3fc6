"""Issue 6 (SLAC speed): the fast paths equal the generic / reference computations.

Covers :func:`~selfcal.slac.likelihood.fisher_blocks` (against the dense
:func:`~selfcal.slac.likelihood.link_fisher`, the amplitude null direction and a
finite-difference Hessian of the expected likelihood), the buffer-reusing
:func:`~selfcal.slac.signals.batch_delay_search` (against fresh workspaces and the delay that
zeroes a finite-difference derivative of the direct objective), the pose-block prediction
(against the dense ``F P F^T + Q``), the direct LAPACK helpers, and the filter's information
assembly with cached link layouts (against ``sum_l J_l^T F_l J_l`` with finite-difference
Jacobians J_l of the range model) and its gradient (finite differences).
"""

from __future__ import annotations

import numpy as np
import pytest

from selfcal.scenarios.rovers import make_rover_scenario
from selfcal.slac.filter import (
    SlacConfig,
    SlacFilter,
    inverse_from_cholesky,
    predict_locations,
    tri_solve,
)
from selfcal.slac.likelihood import fisher_blocks, link_loglik, pack_g
from selfcal.slac.motion import motion_jacobian, process_noise
from selfcal.slac.run import SlacLog
from selfcal.slac.signals import (
    DelaySearchWorkspace,
    batch_delay_search,
    ofdm_probe,
    phasors,
    range_wavenumber,
    snapshot,
)

from .reference import link_fisher

N = 64


def _links(rng: np.random.Generator, L: int = 5, M: int = 4, U: int = 7):  # type: ignore[no-untyped-def]
    X = rng.standard_normal((L, M, N)) + 1j * rng.standard_normal((L, M, N))
    G = rng.standard_normal((L, M, U)) + 1j * rng.standard_normal((L, M, U))
    rho = rng.uniform(0.0, 3.0, L)
    phi = rng.uniform(-3.0, 3.0, L)
    var = rng.uniform(0.5, 2.0, L)
    pp = rng.uniform(0.5, 1.5, N)
    return X, G, rho, phi, var, pp


def test_fisher_blocks_equal_dense_link_fisher(rng: np.random.Generator) -> None:
    X, G, rho, phi, var, pp = _links(rng)
    k = 0.05
    t = link_loglik(X, rho, var, k, float(pp.sum()), phi=phi, G=G)
    F = link_fisher(t, var, k, pp, phi=phi, G=G)
    fb = fisher_blocks(t, var, k, pp, phi=phi, G=G)
    assert F.shape == fb.dense().shape
    np.testing.assert_allclose(fb.dense(), F, rtol=0, atol=1e-12 * np.abs(F).max())
    # the rho row is decoupled (Sd is imaginary), as the factored form assumes
    assert np.all(F[:, 0, 1:] == 0)
    # sums over a subset of links (one receiver) equal the summed dense blocks
    sub = np.array([0, 2, 3])
    np.testing.assert_allclose(fb.gg_sum(sub), F[sub, 2:, 2:].sum(axis=0), rtol=0,
                               atol=1e-12 * np.abs(F).max())
    # single-port links: rho only
    t1 = link_loglik(X[:, :1], rho, var, k, float(pp.sum()))
    fb1 = fisher_blocks(t1, var, k, pp)
    np.testing.assert_allclose(fb1.dense(), link_fisher(t1, var, k, pp), rtol=1e-14)
    assert fb1.phi_g is None and np.all(fb1.phi_phi == 0)


def test_fisher_blocks_null_direction_and_psd(rng: np.random.Generator) -> None:
    # the concentrated likelihood is invariant to G -> kappa G: zero information along g itself
    X, G, rho, phi, var, pp = _links(rng)
    k = 0.05
    t = link_loglik(X, rho, var, k, float(pp.sum()), phi=phi, G=G)
    F = fisher_blocks(t, var, k, pp, phi=phi, G=G).dense()
    for l in range(G.shape[0]):
        v = np.concatenate([[0.0, 0.0], pack_g(G[l])])
        assert np.linalg.norm(F[l] @ v) < 1e-10 * np.linalg.norm(F[l]) * np.linalg.norm(v)
        assert np.linalg.eigvalsh(F[l]).min() > -1e-10 * np.abs(F[l]).max()


def test_fisher_blocks_match_expected_hessian_by_finite_differences(rng: np.random.Generator) -> None:
    # noise-free snapshots at the true parameters: the Fisher information equals minus the
    # Hessian of the concentrated log-likelihood (its curvature at the noise-free optimum)
    M, U = 3, 5
    G = rng.standard_normal((1, M, U)) + 1j * rng.standard_normal((1, M, U))
    s = ofdm_probe(N, rng=1)
    B = 20e6
    k = range_wavenumber(B, N)
    rho0, phi0, var = 4.0, 0.7, 0.3
    from selfcal.slac.antenna import fourier_basis

    a = G[0] @ fourier_basis(phi0, U)
    R = snapshot(a, s, 2 * rho0 / 299_792_458.0, B, amplitude=1.3, phase=0.4, noise_var=0.0, rng=0)
    X = (R * s.conj())[None]
    pp = np.abs(s) ** 2

    def L(th: np.ndarray) -> float:
        t = link_loglik(X, np.array([th[0]]), np.array([var]), k, float(pp.sum()), phi=np.array([th[1]]),
                        G=G, want_grad=False)
        return float(t.value[0])

    th0 = np.array([rho0, phi0])
    h = np.array([1e-3, 1e-3])
    Hn = np.empty((2, 2))
    for i in range(2):
        for j in range(2):
            ei = np.eye(2)[i] * h[i]
            ej = np.eye(2)[j] * h[j]
            Hn[i, j] = (L(th0 + ei + ej) - L(th0 + ei - ej) - L(th0 - ei + ej) + L(th0 - ei - ej)) / (4 * h[i] * h[j])
    t = link_loglik(X, th0[:1], np.array([var]), k, float(pp.sum()), phi=th0[1:], G=G)
    fb = fisher_blocks(t, np.array([var]), k, pp, phi=th0[1:], G=G)
    # at the noise-free optimum the Hessian of the concentrated log-likelihood is -F (eq. 18)
    np.testing.assert_allclose(fb.rho_rho[0], -Hn[0, 0], rtol=1e-4)
    np.testing.assert_allclose(fb.phi_phi[0], -Hn[1, 1], rtol=1e-4)
    assert abs(Hn[0, 1]) < 1e-4 * np.sqrt(abs(Hn[0, 0] * Hn[1, 1]))


def _old_batch_delay_search(snapshots, probe, bandwidth, oversample=2, newton=1):  # type: ignore[no-untyped-def]
    """The fresh-array implementation of 0582afd (reference)."""
    import scipy.fft

    s = np.asarray(probe, dtype=complex)
    N_ = s.size
    P = int(oversample) * N_
    rows = [np.atleast_2d(r) for r in snapshots]
    sizes = np.array([r.shape[0] for r in rows])
    starts = np.concatenate([[0], np.cumsum(sizes)[:-1]])
    Rall = np.vstack(rows)
    X = Rall * s.conj()
    Y = scipy.fft.ifft(X, n=P, axis=1, norm="forward")
    power = np.add.reduceat(Y.real**2 + Y.imag**2, starts, axis=0)
    k = np.argmax(power, axis=1)
    Lr = np.arange(power.shape[0])
    pm, p0, pp = power[Lr, (k - 1) % P], power[Lr, k], power[Lr, (k + 1) % P]
    den = pm - 2 * p0 + pp
    frac = np.where(den < 0, 0.5 * (pm - pp) / np.where(den < 0, den, -1.0), 0.0)
    tau = ((k + frac) % P) * N_ / (float(bandwidth) * P)
    n = np.arange(N_)
    w = 2j * np.pi * float(bandwidth) * n / N_
    wb = 2 * np.pi * float(bandwidth) / N_
    W3 = np.stack([np.ones(N_), w, w * w], axis=1)
    for _ in range(newton):
        Y3 = (X * phasors(np.repeat(tau * wb, sizes), N_)) @ W3
        y0, y1, y2 = Y3[:, 0], Y3[:, 1], Y3[:, 2]
        d1 = np.add.reduceat(2 * np.real(y0.conj() * y1), starts)
        d2 = np.add.reduceat(2 * (np.abs(y1) ** 2 + np.real(y0.conj() * y2)), starts)
        step = np.where(d2 < 0, -d1 / np.where(d2 < 0, d2, -1.0), 0.0)
        tau = tau + np.clip(step, -N_ / (float(bandwidth) * P), N_ / (float(bandwidth) * P))
    period = N_ / float(bandwidth)
    tau = (tau + period / 2) % period - period / 2
    yrows = np.einsum("rn,rn->r", X, phasors(np.repeat(tau * wb, sizes), N_))
    Sp = float(np.sum(np.abs(s) ** 2))
    tot = np.add.reduceat(np.sum(np.abs(Rall) ** 2, axis=1), starts)
    fit = np.add.reduceat(np.abs(yrows) ** 2, starts) / Sp
    var = np.maximum(tot - fit, 1e-300) / (sizes * (N_ - 1))
    return tau, [yrows[a : a + m] for a, m in zip(starts, sizes, strict=True)], var


def _snaps(rng: np.random.Generator, ports: list[int], n_sub: int, B: float) -> tuple[list[np.ndarray], np.ndarray]:
    s = ofdm_probe(n_sub, rng=3)
    out = []
    for M in ports:
        a = rng.standard_normal(M) + 1j * rng.standard_normal(M)
        tau = rng.uniform(0.05, 0.4) * n_sub / B
        out.append(snapshot(a, s, tau, B, amplitude=1.0, phase=rng.uniform(0, 6), noise_var=0.05, rng=rng))
    return out, s


@pytest.mark.parametrize("n_sub", [64, 100])  # 100: not a square, phasors fall back to slicing
def test_buffered_delay_search_equals_fresh_arrays(rng: np.random.Generator, n_sub: int) -> None:
    B = 20e6
    layouts = [[4, 4, 1, 1, 1], [1, 1, 1], [2, 1, 3]]
    results = []
    for rep in range(2):  # alternate layouts: cached workspaces must be rebuilt / picked correctly
        for ports in layouts:
            snaps, s = _snaps(np.random.default_rng(len(ports) + 10 * rep), ports, n_sub, B)
            got = batch_delay_search(snaps, s, B)
            ref = _old_batch_delay_search(snaps, s, B)
            ws = DelaySearchWorkspace(np.array(ports), n_sub, 2, B)
            fresh = batch_delay_search(snaps, s, B, workspace=ws)
            np.testing.assert_allclose(got[0], ref[0], rtol=0, atol=1e-12 * n_sub / B)
            np.testing.assert_allclose(got[2], ref[2], rtol=1e-12)
            for y, yr, yf in zip(got[1], ref[1], fresh[1], strict=True):
                np.testing.assert_allclose(y, yr, rtol=1e-12, atol=0)
                np.testing.assert_array_equal(y, yf)
            np.testing.assert_array_equal(got[0], fresh[0])
            results.append((snaps, s, got))
    # results do not alias the reused buffers: earlier outputs are unchanged by later calls
    for snaps, s, got in results:
        again = _old_batch_delay_search(snaps, s, B)
        np.testing.assert_allclose(got[0], again[0], rtol=0, atol=1e-12 * n_sub / B)
        for y, yr in zip(got[1], again[1], strict=True):
            np.testing.assert_allclose(y, yr, rtol=1e-12)


def test_buffered_delay_search_finds_the_stationary_point_of_the_direct_objective(rng: np.random.Generator) -> None:
    B = 20e6
    snaps, s = _snaps(rng, [4, 1, 2], N, B)
    tau, ys, _ = batch_delay_search(snaps, s, B, newton=3)
    n = np.arange(N)
    for R, t, y in zip(snaps, tau, ys, strict=True):
        X = np.atleast_2d(R) * s.conj()

        def power(tt: float, X: np.ndarray = X) -> float:
            return float(np.sum(np.abs(X @ np.exp(2j * np.pi * tt * B * n / N)) ** 2))

        h = 1e-4 / B
        assert abs(power(t + h) - power(t - h)) / (2 * h) < 1e-6 * power(t) * B
        assert power(t) >= power(t + 50 * h) and power(t) >= power(t - 50 * h)
        np.testing.assert_allclose(y, X @ np.exp(2j * np.pi * t * B * n / N), rtol=1e-10)


def test_phasors_out_equals_allocated(rng: np.random.Generator) -> None:
    th = rng.uniform(-1, 1, 6)
    for n_sub in (64, 100):
        ref = np.exp(1j * th[:, None] * np.arange(n_sub))
        out = np.empty((6, n_sub), dtype=complex)
        got = phasors(th, n_sub, out=out)
        assert got is out
        np.testing.assert_array_equal(got, phasors(th, n_sub))
        np.testing.assert_allclose(got, ref, rtol=0, atol=1e-13)


def test_pose_block_prediction_equals_dense_eq20_21(rng: np.random.Generator) -> None:
    n, D = 3, 20
    x = rng.standard_normal(D)
    A = rng.standard_normal((D, D))
    P = A @ A.T + np.eye(D)
    u = np.column_stack([rng.uniform(0, 1, n), rng.uniform(-1, 1, n)])
    T, sv, so = 0.1, 0.02, 0.01
    xb, Pb = predict_locations(x, P, u, T, sv, so)
    poses = x[: 3 * n].reshape(n, 3)
    F = np.eye(D)
    Q = np.zeros((D, D))
    Fl = motion_jacobian(poses, u, T)
    Ql = process_noise(poses, u, T, sv, so)
    for i in range(n):
        F[3 * i : 3 * i + 3, 3 * i : 3 * i + 3] = Fl[i]
        Q[3 * i : 3 * i + 3, 3 * i : 3 * i + 3] = Ql[i] + 1e-12 * np.eye(3)
    ref = F @ P @ F.T + Q
    np.testing.assert_allclose(Pb, 0.5 * (ref + ref.T), rtol=0, atol=1e-13 * np.abs(ref).max())
    np.testing.assert_array_equal(Pb[3 * n :, 3 * n :], P[3 * n :, 3 * n :])  # calibration block untouched
    np.testing.assert_array_equal(Pb, Pb.T)
    np.testing.assert_array_equal(xb[3 * n :], x[3 * n :])


def test_lapack_helpers(rng: np.random.Generator) -> None:
    A = rng.standard_normal((30, 30))
    H = A @ A.T + 30 * np.eye(30)
    C = np.linalg.cholesky(H)
    b = rng.standard_normal(30)
    np.testing.assert_allclose(C @ tri_solve(C, b), b, atol=1e-12)
    np.testing.assert_allclose(C.T @ tri_solve(C, b, trans=True), b, atol=1e-12)
    Pi = inverse_from_cholesky(C)
    np.testing.assert_array_equal(Pi, Pi.T)
    np.testing.assert_allclose(Pi @ H, np.eye(30), atol=1e-12)


@pytest.fixture(scope="module")
def small_filter():  # type: ignore[no-untyped-def]
    log = SlacLog.from_scenario(make_rover_scenario(0.05, n_subcarriers=32, rng=5, bias_std=0.3), seed=5)
    cfg = SlacConfig(T=log.T, sigma_v=log.sigma_v, sigma_omega=log.sigma_omega, bandwidth=log.bandwidth)
    f = SlacFilter(log.anchors, log.ports, log.prior("chamber"), log.init_poses, log.init_cov, log.probe,
                   mode="slac", config=cfg)
    snaps = log.snapshot_fn(1)
    _, _, var = batch_delay_search(snaps, log.probe, log.bandwidth)
    return f, log, snaps, var


def test_information_equals_generic_jacobian_assembly(small_filter) -> None:  # type: ignore[no-untyped-def]
    f, log, snaps, var = small_filter
    groups = f.link_groups(log.rx, log.tx, snaps, var)
    x = f.x + 0.01 * np.random.default_rng(0).standard_normal(f.D)
    H = f.information(x, groups, fej=False)
    ref = np.zeros((f.D, f.D))
    xe = np.append(x, 0.0)
    for grp in groups:
        lay = grp.layout
        M = lay.M
        _, d, rho, phi = f.links.geometry(xe, lay)
        G = f.links.G_of(xe, lay) if M > 1 else None
        t = link_loglik(grp.X, rho, grp.var, f.k, f.links.S, phi=phi if M > 1 else None, G=G,
                        expansion=grp.exp)
        Fd = link_fisher(t, grp.var, f.k, f.links.probe_power, phi=phi if M > 1 else None, G=G)
        # Jacobian of (rho, phi, g) w.r.t. x by central differences of the range model
        Jg = np.zeros((d.size, 2, f.D))
        for j in range(f.D):
            e = np.zeros(f.D + 1)
            e[j] = 1e-6
            _, _, rp, pp_ = f.links.geometry(xe + e, lay)
            _, _, rm, pm = f.links.geometry(xe - e, lay)
            Jg[:, 0, j] = (rp - rm) / 2e-6
            Jg[:, 1, j] = (pp_ - pm) / 2e-6
        for l in range(d.size):
            if M == 1:
                J = Jg[l, :1]
            else:
                Jgg = np.zeros((Fd.shape[1] - 2, f.D))
                Jgg[np.arange(Jgg.shape[0]), lay.gidx[l]] = 1.0
                J = np.vstack([Jg[l], Jgg])
            ref += J.T @ Fd[l] @ J
    np.testing.assert_allclose(H, ref, rtol=0, atol=1e-6 * np.abs(ref).max())
    # a second call with the cached layout gives the same matrix
    np.testing.assert_array_equal(f.information(x, f.link_groups(log.rx, log.tx, snaps, var), fej=False), H)


def test_filter_gradient_matches_finite_differences(small_filter) -> None:  # type: ignore[no-untyped-def]
    f, log, snaps, var = small_filter
    groups = f.link_groups(log.rx, log.tx, snaps, var)
    x = f.x + 0.005 * np.random.default_rng(1).standard_normal(f.D)
    _, g = f.neg_loglik(x, groups)
    idx = list(range(12)) + [f.D - 1, int(f.bias_index[0]), int(f.g_index[0][3])]
    for j in idx:
        h = 1e-6 * max(1.0, abs(x[j]))
        e = np.zeros(f.D)
        e[j] = h
        num = (f.neg_loglik(x + e, groups)[0] - f.neg_loglik(x - e, groups)[0]) / (2 * h)
        assert abs(num - g[j]) <= 1e-5 * max(1.0, abs(g[j])), (j, num, g[j])


def test_cached_layout_follows_changing_link_sets(small_filter) -> None:  # type: ignore[no-untyped-def]
    _, log, snaps, var = small_filter
    cfg = SlacConfig(T=log.T, sigma_v=log.sigma_v, sigma_omega=log.sigma_omega, bandwidth=log.bandwidth)

    def fresh() -> SlacFilter:
        return SlacFilter(log.anchors, log.ports, log.prior("chamber"), log.init_poses, log.init_cov, log.probe,
                          mode="slac", config=cfg)

    sub = np.flatnonzero(np.arange(log.rx.size) % 3 != 1)
    a = fresh()
    a.update(log.rx, log.tx, snaps, var)  # fills the cache with the full pattern
    a.update(log.rx[sub], log.tx[sub], [snaps[i] for i in sub], var[sub])
    b = fresh()
    b.links.cache.clear()
    b.update(log.rx, log.tx, snaps, var)
    b.links.cache.clear()
    b.update(log.rx[sub], log.tx[sub], [snaps[i] for i in sub], var[sub])
    np.testing.assert_array_equal(a.x, b.x)
    np.testing.assert_array_equal(a.P, b.P)
