"""Paper 002 building blocks: antenna model, signals, likelihoods, motion model, DoA."""

from __future__ import annotations

import numpy as np
import pytest

from selfcal.errors import InputError
from selfcal.slac.antenna import (
    DIPOLE_GAIN,
    basis_orders,
    dipole_response,
    fourier_basis,
    multimode_antenna,
    sampling_matrix,
)
from selfcal.slac.doa import estimate_doa
from selfcal.slac.likelihood import link_loglik, pack_g, unpack_g
from selfcal.slac.motion import control_jacobian, motion_jacobian, motion_step, process_noise
from selfcal.slac.signals import (
    SPEED_OF_LIGHT,
    batch_delay_search,
    estimate_noise_variance,
    ofdm_probe,
    range_wavenumber,
    snapshot,
)

from .reference import concentrated_loglik, link_fisher

B = 28.2e6


def test_basis_orders_match_eq8() -> None:
    assert basis_orders(13).tolist() == list(range(-6, 7))
    assert basis_orders(4).tolist() == [-2, -1, 0, 1]
    b = fourier_basis(np.linspace(-np.pi, np.pi, 400, endpoint=False), 13)
    # orthonormal on [-pi, pi): (2 pi / K) sum_k b(phi_k) b(phi_k)^H = I
    gram = (2 * np.pi / 400) * b.T @ b.conj()
    assert np.allclose(gram, np.eye(13), atol=1e-12)


@pytest.mark.parametrize("Q", [13, 17, 36])
def test_sampling_matrix_reproduces_patterns_at_nyquist(Q: int) -> None:
    ant = multimode_antenna("true")
    phis = np.linspace(-np.pi, np.pi, Q, endpoint=False)
    G0 = sampling_matrix(ant.response(phis), phis, 13)
    assert np.allclose(G0, ant.G, atol=1e-10)
    test_phis = np.random.default_rng(0).uniform(-np.pi, np.pi, 50)
    assert np.allclose(fourier_basis(test_phis, 13) @ G0.T, ant.response(test_phis), atol=1e-10)


def test_sampling_matrix_refuses_undersampling() -> None:
    phis = np.linspace(-np.pi, np.pi, 12, endpoint=False)
    with pytest.raises(InputError, match="Nyquist"):
        sampling_matrix(np.ones((12, 4)), phis, 13)


def test_dipole_is_omnidirectional_215_dbi() -> None:
    a = dipole_response().response(np.linspace(-3, 3, 7))
    assert np.allclose(a, DIPOLE_GAIN)


def test_mma_versions_differ_as_described() -> None:
    em, ch, tr = (multimode_antenna(v).G for v in ("em", "chamber", "true"))
    u = np.abs(basis_orders(13))
    assert np.all(em[:, u > 3] == 0) and np.all(ch[:, u > 3] == 0)  # no platform harmonics
    assert np.linalg.norm(tr[:, u > 3]) > 0
    assert np.linalg.norm(ch - tr) < np.linalg.norm(em - tr)
    # four distinct port patterns
    a = multimode_antenna("true").response(np.linspace(-np.pi, np.pi, 90, endpoint=False))
    c = np.corrcoef(np.abs(a).T)
    assert np.all(np.abs(c[np.triu_indices(4, 1)]) < 0.95)


def test_pack_unpack_g_roundtrip() -> None:
    G = multimode_antenna("em").G
    g = pack_g(G)
    assert g.shape == (2 * 4 * 13,)
    assert np.allclose(g[:4], G[:, 0].real)  # vec stacks columns (eq. 16)
    assert np.allclose(unpack_g(g, 4, 13), G)


def _link(rng: np.random.Generator, N: int = 64):
    ant = multimode_antenna("true")
    s = ofdm_probe(N, 3)
    R = snapshot(ant.response(0.7), s, 2 * 25.0 / SPEED_OF_LIGHT, B, amplitude=0.8, phase=1.1, noise_var=0.4, rng=rng)
    return ant, s, R


def test_batched_likelihood_equals_definition_eq18_eq19(rng: np.random.Generator) -> None:
    ant, s, R = _link(rng)
    k = range_wavenumber(B, s.size)
    X = (R * s.conj())[None]
    t = link_loglik(X, np.array([25.2]), np.array([0.4]), k, float(s.size), phi=np.array([0.6]), G=ant.G[None])
    ref = concentrated_loglik(R, s, B, 0.4, tau=2 * 25.2 / SPEED_OF_LIGHT, phi=0.6, G=ant.G)
    assert t.value[0] == pytest.approx(ref, rel=1e-10)
    t1 = link_loglik(X[:, :1], np.array([25.2]), np.array([0.4]), k, float(s.size))
    ref1 = concentrated_loglik(R[:1], s, B, 0.4, tau=2 * 25.2 / SPEED_OF_LIGHT)
    assert t1.value[0] == pytest.approx(ref1, rel=1e-10)


def test_likelihood_gradients_match_finite_differences(rng: np.random.Generator) -> None:
    ant, s, R = _link(rng)
    k = range_wavenumber(B, s.size)
    X = (R * s.conj())[None]
    rho, phi, G = 25.1, 0.62, multimode_antenna("chamber").G

    def f(r: float, p: float, GG: np.ndarray) -> float:
        return float(link_loglik(X, np.array([r]), np.array([0.4]), k, float(s.size), phi=np.array([p]),
                                 G=GG[None], want_grad=False).value[0])

    t = link_loglik(X, np.array([rho]), np.array([0.4]), k, float(s.size), phi=np.array([phi]), G=G[None])
    h = 1e-6
    assert t.d_rho[0] == pytest.approx((f(rho + h, phi, G) - f(rho - h, phi, G)) / (2 * h), rel=1e-5)
    assert t.d_phi[0] == pytest.approx((f(rho, phi + h, G) - f(rho, phi - h, G)) / (2 * h), rel=1e-5)
    for m, u in [(0, 6), (2, 5), (3, 12)]:
        E = np.zeros_like(G)
        E[m, u] = h
        assert t.d_G[0, m, u].real == pytest.approx((f(rho, phi, G + E) - f(rho, phi, G - E)) / (2 * h), rel=1e-5, abs=1e-6)
        assert t.d_G[0, m, u].imag == pytest.approx((f(rho, phi, G + 1j * E) - f(rho, phi, G - 1j * E)) / (2 * h), rel=1e-5, abs=1e-6)


def test_multiport_fisher_matches_projected_jacobian_definition(rng: np.random.Generator) -> None:
    """link_fisher (closed-form blocks) equals (2|alpha|^2/sigma^2) Re(D^H P_e^perp D), with D the
    finite-difference Jacobian of e = vec(a(phi) s(tau)^T) wrt [rho, phi, Re vec G, Im vec G]."""
    ant, s, R = _link(rng)
    N, (M, U) = s.size, ant.G.shape
    k = range_wavenumber(B, N)
    rho, phi, var = 25.1, 0.62, 0.4
    G = multimode_antenna("chamber").G

    def e_of(th: np.ndarray) -> np.ndarray:
        GG = (th[2 : 2 + M * U] + 1j * th[2 + M * U :]).reshape(U, M).T  # vec stacks columns
        a = GG @ fourier_basis(th[1], U)
        return np.outer(a, s * np.exp(-1j * k * th[0] * np.arange(N))).ravel(order="F")

    th0 = np.concatenate([[rho, phi], G.T.ravel().real, G.T.ravel().imag])
    h = 1e-6
    Dj = np.stack([(e_of(th0 + h * ei) - e_of(th0 - h * ei)) / (2 * h) for ei in np.eye(th0.size)], axis=1)
    e = e_of(th0)
    Dp = Dj - np.outer(e, e.conj() @ Dj) / np.vdot(e, e).real
    terms = link_loglik((R * s.conj())[None], np.array([rho]), np.array([var]), k, float(N),
                        phi=np.array([phi]), G=G[None])
    alpha2 = abs(terms.c[0]) ** 2 / np.vdot(e, e).real ** 2
    ref = 2 * alpha2 / var * np.real(Dj.conj().T @ Dp)
    F = link_fisher(terms, np.array([var]), k, np.abs(s) ** 2, phi=np.array([phi]), G=G[None])[0]
    assert F.shape == (2 + 2 * M * U,) * 2
    assert np.allclose(F, ref, rtol=1e-5, atol=1e-6 * np.abs(ref).max())


def test_range_fisher_matches_monte_carlo_error() -> None:
    """The Fisher information of the delay predicts the ML ranging error (CRLB at high SNR)."""
    g = np.random.default_rng(7)
    N = 64
    s = ofdm_probe(N, 1)
    k = range_wavenumber(B, N)
    errs, info = [], []
    for _ in range(150):
        R = snapshot(np.array([1.0]), s, 2 * 20.0 / SPEED_OF_LIGHT, B, amplitude=2.0, phase=g.uniform(0, 6),
                     noise_var=1.0, rng=g)
        tau, _, var = batch_delay_search([R], s, B, oversample=16)
        r = SPEED_OF_LIGHT * tau[0] / 2
        X = (R * s.conj())[None]
        for _ in range(4):  # Newton on the analytic gradient
            t = link_loglik(X, np.array([r]), var, k, float(N))
            t2 = link_loglik(X, np.array([r + 1e-4]), var, k, float(N))
            r -= t.d_rho[0] / ((t2.d_rho[0] - t.d_rho[0]) / 1e-4)
        errs.append(r - 20.0)
        info.append(link_fisher(link_loglik(X, np.array([r]), var, k, float(N)), var, k, np.abs(s) ** 2)[0, 0, 0])
    assert np.std(errs) == pytest.approx(np.sqrt(1 / np.mean(info)), rel=0.2)
    assert abs(np.mean(errs)) < 3 * np.std(errs) / np.sqrt(len(errs)) + 1e-3


def test_noise_variance_from_known_signal(rng: np.random.Generator) -> None:
    ant, s, _ = _link(rng)
    v = [estimate_noise_variance(snapshot(ant.response(0.3), s, 1e-7, B, amplitude=1.0, phase=0.0, noise_var=0.4,
                                          rng=rng), s, B) for _ in range(30)]
    assert np.mean(v) == pytest.approx(0.4, rel=0.05)


def test_coherent_ml_doa_with_true_response(rng: np.random.Generator) -> None:
    ant = multimode_antenna("true")
    s = ofdm_probe(128, 0)
    for phi in (-2.5, -0.4, 0.9, 3.0):
        R = snapshot(ant.response(phi), s, 3e-7, B, amplitude=1.0, phase=0.5, noise_var=0.5, rng=rng)
        est = estimate_doa(R, s, B, ant.G)
        assert abs((est - phi + np.pi) % (2 * np.pi) - np.pi) < np.deg2rad(1.5)


@pytest.mark.parametrize("omega", [0.3, -0.8, 1e-9, 0.0])
def test_motion_model_matches_eq14_and_limit(omega: float) -> None:
    x = np.array([1.0, -2.0, 0.7])
    v, T = 0.8, 0.1
    out = motion_step(x, np.array([v, omega]), T)
    if abs(omega) > 1e-6:
        ref = x + np.array([-v / omega * np.sin(x[2]) + v / omega * np.sin(x[2] + omega * T),
                            v / omega * np.cos(x[2]) - v / omega * np.cos(x[2] + omega * T), omega * T])
    else:
        ref = x + np.array([v * T * np.cos(x[2]), v * T * np.sin(x[2]), 0.0])
    assert np.allclose(out, ref, atol=1e-12)


@pytest.mark.parametrize("omega", [0.5, 2e-5, 0.0])
def test_motion_jacobians_match_finite_differences(omega: float) -> None:
    x = np.array([1.0, -2.0, 0.7])
    u = np.array([0.8, omega])
    T, h = 0.5, 1e-6
    F = motion_jacobian(x, u, T)
    Bm = control_jacobian(x, u, T)
    for d in range(3):
        e = np.zeros(3)
        e[d] = h
        assert np.allclose(F[:, d], (motion_step(x + e, u, T) - motion_step(x - e, u, T)) / (2 * h), atol=1e-8)
    for d in range(2):
        e = np.zeros(2)
        e[d] = h
        assert np.allclose(Bm[:, d], (motion_step(x, u + e, T) - motion_step(x, u - e, T)) / (2 * h), atol=1e-7)


def test_process_noise_matches_sampled_controls() -> None:
    g = np.random.default_rng(3)
    x, u, T = np.array([0.0, 0.0, 0.3]), np.array([0.5, 0.2]), 0.1
    sv, sw = 0.2, 0.3
    Q = process_noise(x, u, T, sv, sw)
    samples = np.array([motion_step(x, u + g.standard_normal(2) * np.array([sv, sw]) * np.sqrt(T), T)
                        for _ in range(20000)])
    assert np.allclose(np.cov(samples.T), Q, rtol=0.08, atol=1e-9)


def test_round_trip_shorter_than_biases_gives_small_negative_range() -> None:
    """Delays are N/B-periodic; a negative round trip must not wrap to ~c N / (2B)."""
    s = ofdm_probe(256, 0)
    R = snapshot(np.array([1.0]), s, 2 * (-0.3) / SPEED_OF_LIGHT, B, amplitude=1.0, phase=0.0, noise_var=0.01, rng=0)
    tau, _, _ = batch_delay_search([R], s, B)
    assert SPEED_OF_LIGHT * tau[0] / 2 == pytest.approx(-0.3, abs=0.05)
