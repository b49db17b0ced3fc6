"""Figures a person reads without the JSON (issue 32): every plot kind draws the node names, the
units the data are in, the room where it is known, integer ticks for indices and a note when
the 95 % ellipses hide under the markers -- checked on the text objects of the axes."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from matplotlib.patches import Rectangle

from selfcal.plotting import aoa as paoa
from selfcal.plotting import conference as pconf
from selfcal.plotting import farfield as pff
from selfcal.plotting import toa as ptoa


def texts(fig) -> list[str]:  # type: ignore[no-untyped-def]
    out = []
    for ax in fig.axes:
        out += [t.get_text().strip() for t in ax.texts]
    return out


def labels(fig) -> list[str]:  # type: ignore[no-untyped-def]
    out = []
    for ax in fig.axes:
        out += [ax.get_xlabel(), ax.get_ylabel()] + ([ax.get_zlabel()] if ax.name == "3d" else [])
    return out


@pytest.mark.parametrize("seed", range(3))
@pytest.mark.parametrize("dim", [2, 3])
def test_toa_network_names_every_node(tmp_path: Path, dim: int, seed: int) -> None:
    from selfcal import solve_toa
    from selfcal.geometry import pairwise_distances

    g = np.random.default_rng(seed)
    r, s = g.uniform(0, 6, (6, dim)), g.uniform(0, 6, (8, dim))
    res = solve_toa(pairwise_distances(r, s) + g.normal(0, 0.01, (6, 8)), dim=dim, rng=0)
    fig = ptoa.plot_toa(res, tmp_path / "t.png")
    drawn = texts(fig)
    views = 1 if dim == 2 else 3
    # r0.. / s0..: the names --known / --frame use; in every view
    for name in [f"r{i}" for i in range(6)] + [f"s{j}" for j in range(8)]:
        assert drawn.count(name) == views, name
    assert all("[m]" in lab for lab in labels(fig))
    fig = ptoa.plot_toa(res, None, names=(tuple("ABCDEF"), tuple(f"t{j}" for j in range(8))))
    assert "A" in texts(fig) and "t7" in texts(fig)


def _pipeline(dim: int, std: float, seed: int = 0) -> SimpleNamespace:
    g = np.random.default_rng(seed)
    room = np.array([8.0, 6.0, 3.0])
    r, s = g.uniform(0, 1, (6, 3)) * room, g.uniform(0, 1, (6, 3)) * room
    return SimpleNamespace(
        receivers=r[:, :dim], sources=s[:, :dim], receiver_cov=np.tile(np.eye(dim) * std**2, (6, 1, 1)),
        source_cov=np.tile(np.eye(dim) * std**2, (6, 1, 1)), method=f"{dim}d",
        receiver_names=[f"u{i:02d}" for i in range(6)], sender_names=[f"u{i:02d}" for i in range(6)],
        receiver_offsets=np.zeros(6), source_offsets=np.zeros(6), timings={"detect": 1.0, "calibrate": 0.5}, known_heights=False)


@pytest.mark.parametrize("dim", [2, 3])
def test_conference_map_names_room_and_hidden_ellipses(tmp_path: Path, dim: int) -> None:
    res = _pipeline(dim, std=0.002)  # 2 mm: a 95 % ellipse of ~5 mm in an 8 m room
    fig = pconf.plot_map(res, tmp_path / "m.png", room=(8.0, 6.0, 3.0))
    drawn = texts(fig)
    assert all(f"u{i:02d}" in drawn for i in range(6))
    assert any("smaller than the markers" in t for t in drawn)
    rooms = [p for ax in fig.axes for p in ax.patches if isinstance(p, Rectangle) and p.get_label() == "room"]
    assert len(rooms) == (1 if dim == 2 else 3)
    assert all("[m]" in lab for lab in labels(fig))
    # ellipses of 50 cm are visible: no note
    fig = pconf.plot_map(_pipeline(dim, std=0.5), None)
    assert not any("smaller than the markers" in t for t in texts(fig))


def test_timing_has_integer_unit_ticks(tmp_path: Path) -> None:
    res = _pipeline(2, std=0.01)
    fig = pconf.plot_timing(res, tmp_path / "t.png")
    ax = fig.axes[0]
    ticks = ax.get_xticks()
    assert np.allclose(ticks, np.round(ticks)) and "[index]" in ax.get_xlabel()


@pytest.mark.parametrize("speed", [None, 343.0])
def test_farfield_colour_bar_in_the_json_unit(tmp_path: Path, speed: float | None) -> None:
    g = np.random.default_rng(0)
    n = g.normal(size=(7, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    res = SimpleNamespace(positions=g.normal(size=(5, 3)), directions=n, offsets=g.normal(size=7), dim=3,
                          case="3d", degeneracy=None, position_cov=None)
    fig = pff.plot_farfield(res, tmp_path / "f.png", speed=speed, names=[f"mic{i}" for i in range(5)])
    bars = [a.get_ylabel() for a in fig.axes if a.get_label() == "<colorbar>"]
    unit = "[s]" if speed is not None else "[m]"
    assert any("C_j" in b and unit in b for b in bars), bars
    assert all(f"mic{i}" in texts(fig) for i in range(5))
    ax3 = next(a for a in fig.axes if a.name == "3d")
    # at most 4 intervals per 3-D axis (MaxNLocator(4)): labels that do not run into each other
    for axis in (ax3.xaxis, ax3.yaxis, ax3.zaxis):
        assert len(axis.get_major_locator().tick_values(-1, 1)) <= 6


@pytest.mark.parametrize("dim", [2, 3])
def test_aoa_pose_names_the_beacons(tmp_path: Path, dim: int) -> None:
    from selfcal import solve_aoa

    g = np.random.default_rng(dim)
    B = g.uniform(-5, 5, (5, dim))
    u = B / np.linalg.norm(B, axis=1, keepdims=True)
    fig = paoa.plot_pose(B, u, solve_aoa(B, u), tmp_path / "p.png", names=[f"b{k}" for k in range(5)])
    assert all(f"b{k}" in texts(fig) for k in range(5))
    assert all("[m]" in lab for lab in labels(fig))
    fig = paoa.plot_pose(B, u, solve_aoa(B, u), None)
    assert "beacon 0" in texts(fig)
