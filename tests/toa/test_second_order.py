"""Heights over coplanar partners are second-order: the thickness chi-square's factor 4 (issue 27)."""

from __future__ import annotations

import numpy as np
import pytest

from selfcal.toa.verdict.flips import coplanar_partner_nodes


@pytest.mark.parametrize("seed", range(6))
def test_plane_costs_a_quarter_of_what_the_linearised_bar_says(seed):
    """A node at height h0 over coplanar partners: the likelihood ratio of h = 0 (its own
    ranges, computed exactly) against (h0 / sigma_lin)^2 from the linearised z variance.

    ranges rho_j(h) = sqrt(d_j^2 + h^2) = d_j + h^2 / (2 d_j) + O(h^4): the misfit is
    A (h^2 - h0^2)^2, the plane costs A h0^4, the parabola at h0 says 4 A h0^4. The ratio is
    1/4 up to the O((h0 / d)^2) terms of the expansion (h0 <= 5 cm over partners 1-6 m away).
    """
    g = np.random.default_rng(seed)
    partners = np.c_[g.uniform(-3, 3, (10, 2)), np.zeros(10)]
    x = np.r_[g.uniform(-1, 1, 2), g.uniform(0.005, 0.05)]
    sigma = 1e-5  # m of range noise

    def ranges(p):
        return np.linalg.norm(p - partners, axis=1)

    y = ranges(x)
    J = (x - partners) / y[:, None]
    lin_var_z = sigma**2 / np.sum(J[:, 2] ** 2)  # the height alone (x, y held: a 1-D profile)
    plane = x * [1, 1, 0]  # the node moved into the partners' plane
    lr = np.sum((ranges(plane) - y) ** 2) / sigma**2
    assert lr / (x[2] ** 2 / lin_var_z) == pytest.approx(0.25, rel=0.05)


def test_coplanar_partner_nodes_marks_nodes_over_coplanar_partners_only():
    g = np.random.default_rng(1)
    flat = np.c_[g.uniform(0, 8, (10, 2)), np.full(10, 0.8)]  # exactly coplanar partners
    thick = np.c_[g.uniform(0, 8, (10, 2)), g.uniform(0, 3, 10)]  # 3-D partners
    nodes = np.c_[g.uniform(0, 8, (6, 2)), 0.8 + g.uniform(-0.01, 0.01, 6)]
    obs = np.ones((6, 10), bool)
    cov = np.tile(np.eye(3) * 1e-6, (10, 1, 1))  # 1 mm error bars
    kw = {"noise2": 1e-10, "point_std": np.full(6, 1e-3), "quantile": 10.83}
    assert coplanar_partner_nodes(nodes, flat, obs, partner_var=cov, **kw).all()
    assert not coplanar_partner_nodes(nodes, thick, obs, partner_var=cov, **kw).any()
    # a node measured by too few partners is not judged by the plane of the others
    obs2 = obs.copy()
    obs2[0] = False
    assert not coplanar_partner_nodes(nodes, flat, obs2, partner_var=cov, **kw)[0]
