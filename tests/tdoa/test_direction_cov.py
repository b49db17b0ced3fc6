"""Direction uncertainties of far-field results (issue 31): the Gauss-Newton covariance of each unit
direction predicts the spread of the directions over noise draws, in 3-D and in a plane; the JSON
gives them in degrees."""

from __future__ import annotations

import numpy as np
import pytest

from selfcal.tdoa import solve_farfield


def _spread(d: int, seed: int, runs: int = 40) -> tuple[float, float, np.ndarray]:
    """(empirical mean squared angle, predicted mean trace, per-direction ratios) over ``runs`` draws."""
    rng = np.random.default_rng(seed)
    m, k, sigma = 10, 20, 2e-3
    Z = rng.uniform(-0.5, 0.5, (m, d))
    Z -= Z[0]
    N = rng.normal(size=(k, d))
    N /= np.linalg.norm(N, axis=1, keepdims=True)
    C = rng.normal(size=k)
    sq = np.zeros(k)
    pred = np.zeros(k)
    for _ in range(runs):
        D = Z @ N.T + C + sigma * rng.standard_normal((m, k))
        # free offsets: the least-squares estimate the Gauss-Newton covariance describes (the paper's
        # reference offsets C_j = D_1j, the default for complete data, carry row 1's noise into every row)
        res = solve_farfield(D, dim=d, screen=False, offsets="free")
        assert res.direction_cov is not None and res.direction_cov.shape == (k, d, d)
        U, _, Vt = np.linalg.svd(Z.T @ res.positions)  # best rotation about the first position (the gauge)
        Nh = res.directions @ (U @ Vt).T
        ang = np.arccos(np.clip(np.sum(Nh * N, axis=1), -1.0, 1.0))
        sq += ang**2
        pred += np.trace(res.direction_cov, axis1=1, axis2=2)
    return float(np.mean(sq) / runs), float(np.mean(pred) / runs), sq / pred


@pytest.mark.parametrize("d", [3, 2])
@pytest.mark.parametrize("seed", range(3))
def test_direction_covariance_predicts_the_spread(d, seed):
    # 40 draws x 20 directions: the mean squared angle error over all directions is a chi-square-like
    # sum of ~800 (3-D: 2 dof each) terms, within +-30 % of the prediction with overwhelming
    # probability if the covariance is right (the rotation about the first position that best aligns
    # the positions is the covariance's gauge; the estimate's bias at this SNR is negligible)
    emp, pred, _ = _spread(d, 10 * d + seed)
    assert 0.7 < emp / pred < 1.3, (emp, pred)


def test_json_gives_direction_stds_in_degrees():
    rng = np.random.default_rng(2)
    Z = rng.uniform(-0.5, 0.5, (8, 3))
    N = rng.normal(size=(15, 3))
    N /= np.linalg.norm(N, axis=1, keepdims=True)
    D = Z @ N.T + rng.normal(size=15) + 1e-3 * rng.standard_normal((8, 15))
    res = solve_farfield(D)
    out = res.to_dict()
    cov = np.array(out["direction_covariance"])
    assert cov.shape == (15, 3, 3)
    # a unit vector's covariance lives in its tangent plane
    assert np.allclose(np.einsum("ja,jab->jb", res.directions, cov), 0.0, atol=1e-12)
    std = np.array(out["direction_std_deg"])
    assert np.allclose(std, np.degrees(np.sqrt(np.trace(cov, axis1=1, axis2=2))))
    az, el = np.array(out["azimuth_std_deg"]), np.array(out["elevation_std_deg"])
    # azimuth and elevation errors are orthogonal on the sphere: cos^2(el) var(az) + var(el) = trace
    cos_el = np.sqrt(1.0 - res.directions[:, 2] ** 2)
    assert np.allclose((cos_el * az) ** 2 + el**2, std**2, rtol=1e-8)
