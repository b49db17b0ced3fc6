"""Every figure of :mod:`selfcal.plotting` on a small result: the file's format is the suffix's, every
axis is labelled with its unit, and 3-D results get three views or 3-D axes."""

from __future__ import annotations

import re
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

from selfcal.errors import InputError
from selfcal.plotting import aoa as paoa
from selfcal.plotting import conference as pconf
from selfcal.plotting import delays as pdel
from selfcal.plotting import farfield as pff
from selfcal.plotting import save_figure
from selfcal.plotting import slac as pslac
from selfcal.plotting import toa as ptoa

MAGIC = {".png": b"\x89PNG\r\n\x1a\n", ".pdf": b"%PDF-", ".svg": b"<?xml"}
UNIT = re.compile(r"[\[(][^\])]+[\])]")  # "x [m]", "time (min)", "unit [index]", "[-]"


def check_figure(fig: Any, path: Path) -> None:
    """The written bytes start with the suffix's magic number; every axis label names a unit."""
    assert path.read_bytes()[: len(MAGIC[path.suffix])] == MAGIC[path.suffix], path
    for ax in fig.axes:
        if ax.get_label() == "<colorbar>":  # a colour bar's label is on its long axis
            label = ax.get_ylabel() or ax.get_xlabel()
            assert UNIT.search(label), f"colour bar label without unit: {label!r}"
            continue
        twin = len(ax.get_shared_x_axes().get_siblings(ax)) > 1  # a twinx panel shares the x label
        labels = [ax.get_ylabel()] + ([] if twin and not ax.get_xlabel() else [ax.get_xlabel()])
        if ax.name == "3d":
            labels.append(ax.get_zlabel())
        for label in labels:
            assert UNIT.search(label), f"axis label without unit: {label!r} in {ax.get_title()!r}"


def _network(dim: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    g = np.random.default_rng(seed)
    return g.uniform(0, 4, (6, dim)), g.uniform(0, 4, (8, dim))


@pytest.mark.parametrize(("dim", "suffix"), [(2, ".png"), (3, ".pdf"), (3, ".svg")])
def test_toa_network_three_views_in_3d(tmp_path: Path, suffix: str, dim: int) -> None:
    from selfcal import solve_toa
    from selfcal.geometry import pairwise_distances

    r, s = _network(dim)
    res = solve_toa(pairwise_distances(r, s), dim=dim, rng=0)
    fig = ptoa.plot_toa(res, tmp_path / f"t{suffix}")
    check_figure(fig, tmp_path / f"t{suffix}")
    assert len(fig.axes) == (1 if dim == 2 else 3)
    if dim == 3:  # the views show x-y, x-z and y-z
        assert [(a.get_xlabel()[0], a.get_ylabel()[0]) for a in fig.axes] == [("x", "y"), ("x", "z"), ("y", "z")]


def test_toa_reproduction_figures(tmp_path: Path) -> None:
    r, s = _network(3)
    cov = np.tile(np.eye(3) * 1e-3, (6, 1, 1))
    fig = ptoa.plot_network(r, s, tmp_path / "n.pdf", receiver_cov=cov, true_receivers=r + 0.01, true_sources=s)
    check_figure(fig, tmp_path / "n.pdf")
    summary = [{"sigma": x, "mds_rmse": 2 * x, "nls_rmse": x, "crlb_rmse": None if x > 0.2 else 0.9 * x}
               for x in (0.01, 0.1, 0.3)]
    fig = ptoa.plot_rmse_curves(summary, "sigma", "range noise std (m)", "t", tmp_path / "c.svg", logx=True)
    check_figure(fig, tmp_path / "c.svg")
    fig = ptoa.plot_lps_flight(r, s, r, tmp_path / "l.png", title="lps")
    check_figure(fig, tmp_path / "l.png")
    assert len(fig.axes) == 3


@pytest.mark.parametrize("dim", [1, 2, 3])
def test_farfield_sphere_and_colour_bar(tmp_path: Path, dim: int) -> None:
    g = np.random.default_rng(dim)
    n = g.normal(size=(7, dim))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    res = SimpleNamespace(positions=g.normal(size=(5, dim)), directions=n, offsets=g.normal(size=7), dim=dim,
                          case=f"{dim}d", degeneracy=None, position_cov=np.tile(np.eye(dim) * 1e-4, (5, 1, 1)))
    fig = pff.plot_farfield(res, tmp_path / "f.pdf")
    check_figure(fig, tmp_path / "f.pdf")
    assert any(a.get_label() == "<colorbar>" and "C_j" in a.get_ylabel() for a in fig.axes)
    assert any(a.name == "3d" for a in fig.axes) == (dim == 3)


def test_farfield_reproduction_figures(tmp_path: Path) -> None:
    fig1 = [{"model": "3d", "distance": d, "failure_rate": 0.1, "mean_error": 1 / d} for d in (1.0, 10.0)]
    fig1.append({"model": "far-field", "distance": None, "failure_rate": 0.0, "mean_error": 1e-15})
    check_figure(pff.plot_minimal_solver(fig1, tmp_path / "1.png"), tmp_path / "1.png")
    fig2 = [{"size": z, "distance": d, "mean_error": 0.1, "failure_rate": 0.2} for z in ("r4-s6", "r5-s8")
            for d in (1.0, 10.0)]
    check_figure(pff.plot_initialisation(fig2, tmp_path / "2.png"), tmp_path / "2.png")
    curves = {"a": np.linspace(1, 0.1, 30), "b": np.linspace(1, 0.2, 30), "c": np.linspace(1, 0.3, 30)}
    check_figure(pff.plot_convergence(curves, tmp_path / "3.png"), tmp_path / "3.png")
    fig4 = [{"distance": d, "sigma": s, "init_error": 1.0, "lm_error": 0.5, "init_error_median": 0.9,
             "lm_error_median": 0.4, "ml_error_median": 0.3, "rmse": {"crlb": 0.2}, "failure_rate": 0.0}
            for d in (1e7, 1e2) for s in (0.0, 1e-2)]
    check_figure(pff.plot_noise(fig4, tmp_path / "4.svg"), tmp_path / "4.svg")


@pytest.mark.parametrize("dim", [2, 3])
def test_aoa_pose_with_receiver_axes(tmp_path: Path, dim: int) -> None:
    from selfcal import solve_aoa

    g = np.random.default_rng(dim)
    B = g.uniform(-5, 5, (5, dim))
    u = B / np.linalg.norm(B, axis=1, keepdims=True)  # receiver at the origin, identity rotation
    res = solve_aoa(B, u)
    fig = paoa.plot_pose(B, u, res, tmp_path / "p.pdf")
    check_figure(fig, tmp_path / "p.pdf")
    ax = fig.axes[0]
    assert (ax.name == "3d") == (dim == 3)
    legend = [t.get_text() for t in ax.get_legend().get_texts()]
    assert sum("axis" in t for t in legend) == dim  # one arrow per receiver axis


def test_aoa_error_surfaces(tmp_path: Path) -> None:
    x, y = np.linspace(-1, 1, 4), np.linspace(0, 1, 3)
    z = np.outer(y, x) ** 2
    fig = paoa.plot_error_surfaces([("a", x, y, z), ("b", x, y, 2 * z)], tmp_path / "e.png",
                                   label="mean location error [m]")
    check_figure(fig, tmp_path / "e.png")
    assert sum(a.get_label() == "<colorbar>" for a in fig.axes) == 2


def test_slac_figures(tmp_path: Path) -> None:
    suffix = ".png"
    g = np.random.default_rng(1)
    poses = np.cumsum(g.normal(size=(20, 2, 3)), axis=0)
    anchors = g.uniform(-5, 5, (3, 2))
    fig = pslac.plot_trajectories(poses, anchors, tmp_path / f"t{suffix}", names=["a", "b"], truth=poses + 0.1)
    check_figure(fig, tmp_path / f"t{suffix}")
    data = SimpleNamespace(gt=poses[:, 0, :2], beacons=anchors, beacon_ids=np.arange(3),
                           dead_reckoning=lambda: poses[:, 0, :2] + 1.0)
    r = SimpleNamespace(poses=poses[:, 0, :], scale=np.ones(3), scale_std=np.full(3, 0.01), offset=np.zeros(3),
                        offset_std=np.full(3, 0.1), method="smoother")
    fig = pslac.plot_plaza(data, {"smoother": r}, tmp_path / f"p{suffix}", rmse={"smoother": 0.5})
    check_figure(fig, tmp_path / f"p{suffix}")
    fig = pslac.plot_doa_cdf({"a": g.normal(size=50), "b": g.normal(size=50)}, tmp_path / f"d{suffix}")
    check_figure(fig, tmp_path / f"d{suffix}")
    fig = pslac.plot_ranging_rmse(np.arange(100) / 600, {"a": g.random(100)}, tmp_path / f"r{suffix}", window=5)
    check_figure(fig, tmp_path / f"r{suffix}")
    fig = pslac.plot_position_rmse(["x", "y"], {"loc": [1.0, 2.0], "slac": [0.5, 0.7]}, tmp_path / f"b{suffix}")
    check_figure(fig, tmp_path / f"b{suffix}")


def _pipeline_result(dim: int) -> SimpleNamespace:
    r, s = _network(dim, seed=3)
    return SimpleNamespace(
        receivers=r, sources=s, receiver_cov=np.tile(np.eye(dim) * 1e-4, (6, 1, 1)),
        source_cov=np.tile(np.eye(dim) * 4e-4, (8, 1, 1)), method=f"{dim}d", receiver_names=[f"m{i}" for i in range(6)],
        sender_names=[f"s{j}" for j in range(8)], receiver_offsets=np.zeros(6), source_offsets=np.zeros(8),
        timings={"detect": 1.0, "calibrate": 0.5}, known_heights=False)


@pytest.mark.parametrize("dim", [2, 3])
def test_conference_map_and_timing(tmp_path: Path, dim: int) -> None:
    suffix = ".pdf" if dim == 3 else ".svg"
    from selfcal.geometry import rotation_2d

    res = _pipeline_result(dim)
    fig = pconf.plot_map(res, tmp_path / f"m{suffix}")
    check_figure(fig, tmp_path / f"m{suffix}")
    assert len(fig.axes) == (1 if dim == 2 else 3)
    # with a truth: the estimate is aligned on it (a rotated copy lands on the truth)
    Rt = np.eye(dim)
    Rt[:2, :2] = rotation_2d(0.3)
    errors = {"aligned_receivers": res.receivers, "aligned_sources": res.sources,
              "true_receivers": res.receivers @ Rt.T, "true_senders": res.sources @ Rt.T,
              "delay_errors": np.full(6, 1e-6), "onset_errors": np.full(8, -2e-6)}
    check_figure(pconf.plot_map(res, tmp_path / f"a{suffix}", errors), tmp_path / f"a{suffix}")
    for err in (None, errors):
        fig = pconf.plot_timing(res, tmp_path / f"t{suffix}", err, requirement=58e-6)
        check_figure(fig, tmp_path / f"t{suffix}")


def test_report_figures(tmp_path: Path) -> None:
    res = _pipeline_result(3)
    fig, mag = pconf.plot_report_map(res, tmp_path / "m.png")
    check_figure(fig, tmp_path / "m.png")
    assert mag >= 1 and f"x{mag:g}" in fig.axes[0].get_title()  # the magnification is printed on the map
    z = np.random.default_rng(0).normal(size=(6, 8))
    z[0, 0] = np.nan
    check_figure(pconf.plot_residuals(z, tmp_path / "r.svg"), tmp_path / "r.svg")


def test_delays_figures(tmp_path: Path) -> None:
    stat = {"n": 2, "mean": 1e-7, "min": 5e-8, "max": 2e-7}
    summary = [{"room": room, "method": m, "units": u, "frobenius_s2": stat, "frobenius_s2_filtered": stat,
                "p_error_s": stat, "p_error_s_filtered": stat}
               for room in ("large", "small") for m in ("fast", "faithful") for u in (20, 40)]
    check_figure(pdel.plot_accuracy(summary, tmp_path / "a.png", accept_s2=8e-7), tmp_path / "a.png")
    rows = [{"units": u, "method": m, "seconds": 1.0 + k, "extrapolated_seconds": 2.0 + k}
            for u in (20, 120) for m in ("fast", "faithful") for k in range(3)]
    check_figure(pdel.plot_timing(rows, tmp_path / "t.pdf", thesis_means={20: 6.6}), tmp_path / "t.pdf")
    lam = [{"lam_s": 1e-6, "history_iteration": [1, 10, 100], "history_frobenius_s2": [1e-5, 1e-6, 1e-7]}]
    check_figure(pdel.plot_lambda(lam, tmp_path / "l.png"), tmp_path / "l.png")
    noise = [{"room": "large", "sigma": s, "offset_rmse_nls_s": s, "offset_rmse_rank3_s": 2 * s,
              "offset_crlb_s": 0.9 * s} for s in (1e-6, 1e-5)]
    check_figure(pdel.plot_noise(noise, tmp_path / "n.png"), tmp_path / "n.png")


def test_unknown_suffix_is_refused_and_nothing_written(tmp_path: Path) -> None:
    fig = ptoa.plot_network(*_network(2))
    with pytest.raises(InputError, match="unknown figure format"):
        save_figure(fig, tmp_path / "x.txt")
    assert list(tmp_path.iterdir()) == []


def test_cli_plot_suffix_picks_the_format(tmp_path: Path) -> None:
    """``--plot FILE.pdf`` / ``.svg`` write that format (not PNG bytes under another name)."""
    from click.testing import CliRunner

    from selfcal.cli import main

    g = np.random.default_rng(4)
    B = np.array([[0.0, 0, 0], [5, 0, 0], [0, 5, 0], [5, 5, 1]])
    u = B - np.array([2.0, 1.0, -3.0])
    np.savetxt(tmp_path / "b.csv", B, delimiter=",")
    np.savetxt(tmp_path / "u.csv", u / np.linalg.norm(u, axis=1, keepdims=True), delimiter=",")
    r = CliRunner().invoke(main, ["locate", "aoa", str(tmp_path / "b.csv"), str(tmp_path / "u.csv"),
                                  "--out", str(tmp_path / "a.json"), "--plot", str(tmp_path / "a.pdf")])
    assert r.exit_code == 0, r.output
    assert (tmp_path / "a.pdf").read_bytes()[:5] == MAGIC[".pdf"]
    Z = g.uniform(-1.0, 1.0, (10, 3))  # a well-spread 3-D array: rank 3 + offsets, far from degenerate
    Z[0] = 0
    N = g.normal(size=(15, 3))
    N /= np.linalg.norm(N, axis=1, keepdims=True)
    np.savetxt(tmp_path / "D.csv", Z @ N.T + 0.1 * g.normal(size=15), delimiter=",")
    r = CliRunner().invoke(main, ["calibrate", "tdoa-farfield", str(tmp_path / "D.csv"), "--out",
                                  str(tmp_path / "f.json"), "--plot", str(tmp_path / "f.svg")])
    assert r.exit_code == 0, r.output
    assert (tmp_path / "f.svg").read_bytes()[:5] == MAGIC[".svg"]


def test_every_format_the_cli_accepts_is_one_matplotlib_writes(tmp_path: Path) -> None:
    from selfcal.commands._common import IMAGE_FORMATS

    fig = ptoa.plot_network(*_network(2))
    assert set(IMAGE_FORMATS) <= set(fig.canvas.get_supported_filetypes())
