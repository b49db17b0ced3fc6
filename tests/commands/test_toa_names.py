"""Node names through ``selfcal calibrate toa``: the matrix's names (or 0-based r<i> / s<j>)
are usable in ``--known`` and ``--frame``, checked before any work, and the same in the
JSON, the CSV and the messages (issue 29)."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest
from click.testing import CliRunner

from selfcal.cli import main

ANCHORS = np.array([[0, 0, 2.8], [5, 0, 2.9], [5, 4, 2.7], [0, 4, 2.9], [2.5, 0, 0.3], [2.5, 4, 0.4],
                    [0, 2, 1.5]])


def _scene(tmp_path, seed, names=True, n=30, noise=0.01):
    rng = np.random.default_rng(seed)
    T = np.column_stack([rng.uniform(0.5, 4.5, n), rng.uniform(0.5, 3.5, n), rng.uniform(0.3, 2.0, n)])
    D = np.linalg.norm(ANCHORS[:, None] - T[None], axis=-1) + rng.normal(0, noise, (7, n))
    path = tmp_path / "ranges.csv"
    with open(path, "w") as f:
        if names:
            f.write("anchor," + ",".join(f"tag{j}" for j in range(n)) + "\n")
        for i in range(7):
            f.write((f"A{i}," if names else "") + ",".join(f"{v:.5f}" for v in D[i]) + "\n")
    return path, T


def _known(tmp_path, names):
    path = tmp_path / "known.csv"
    path.write_text("name,x,y,z\n" + "".join(f"{nm},{ANCHORS[i, 0]},{ANCHORS[i, 1]},{ANCHORS[i, 2]}\n"
                                            for nm, i in names))
    return path


def run(*args):
    return CliRunner().invoke(main, ["calibrate", "toa", *map(str, args)])


@pytest.mark.parametrize("seed", range(3))
def test_known_by_the_matrix_names_puts_every_anchor_in_the_room(tmp_path, seed):
    """Known A0..A3 (names of the matrix's first column): the other anchors land where they are.

    The tolerance 0.1 m is ~7 x the predicted anchor std at 1 cm range noise (~0.015 m here):
    a wrong name mapping or frame moves anchors by metres.
    """
    m, _ = _scene(tmp_path, seed)
    known = _known(tmp_path, [(f"A{i}", i) for i in range(4)])
    out, csv_out = tmp_path / "r.json", tmp_path / "r.csv"
    res = run(m, "--known", known, "--out", out, "--csv", csv_out)
    assert res.exit_code == 0, res.output
    doc = json.loads(out.read_text())
    assert doc["receiver_names"] == [f"A{i}" for i in range(7)]
    assert doc["source_names"][:2] == ["tag0", "tag1"]
    R = np.array(doc["receivers"])
    assert np.max(np.linalg.norm(R - ANCHORS, axis=1)) < 0.1
    rows = list(csv.DictReader(csv_out.open()))
    assert [r["name"] for r in rows[:7]] == [f"A{i}" for i in range(7)]


def test_zero_based_indices_without_names(tmp_path):
    """Without names the nodes are r<i> / s<j> (0-based) in --known, JSON and CSV alike."""
    m, _ = _scene(tmp_path, 7, names=False)
    known = _known(tmp_path, [("r0", 0), ("1", 1), ("r2", 2), ("r3", 3)])
    out, csv_out = tmp_path / "r.json", tmp_path / "r.csv"
    res = run(m, "--known", known, "--out", out, "--csv", csv_out)
    assert res.exit_code == 0, res.output
    doc = json.loads(out.read_text())
    assert doc["receiver_names"][0] == "r0" and doc["source_names"][0] == "s0"
    assert np.max(np.linalg.norm(np.array(doc["receivers"]) - ANCHORS, axis=1)) < 0.1
    rows = list(csv.DictReader(csv_out.open()))
    assert rows[0]["name"] == "r0" and rows[7]["name"] == "s0"


def test_frame_by_names(tmp_path):
    """--frame origin=A0,x=A1,xy=A3,z=A2: A0 at 0, A1 on +x, A3 in the xy plane, the same
    distances as the truth (a rigid motion of it)."""
    m, _ = _scene(tmp_path, 11)
    out = tmp_path / "r.json"
    res = run(m, "--frame", "origin=A0,x=A1,xy=A3,z=A4", "--out", out)
    assert res.exit_code == 0, res.output
    assert "origin=A0" in res.output
    R = np.array(json.loads(out.read_text())["receivers"])
    assert np.allclose(R[0], 0) and np.allclose(R[1, 1:], 0) and R[1, 0] > 0 and abs(R[3, 2]) < 1e-12
    D, Dt = (np.linalg.norm(X[:, None] - X[None], axis=-1) for X in (R, ANCHORS))
    assert np.max(np.abs(D - Dt)) < 0.1


@pytest.mark.parametrize("opt, value, word", [
    ("--known", None, "A9"), ("--frame", "origin=A0,x=B7,xy=A2", "B7")])
def test_unknown_names_refused_before_any_work(tmp_path, monkeypatch, opt, value, word):
    """An unknown node: exit 2, one line naming it and the input's names, and no solve ran."""
    import selfcal.toa.recipes.recipes as recipes

    def boom(*a, **k):
        raise AssertionError("the solve ran before the names were checked")

    monkeypatch.setattr(recipes, "apply_recipe", boom)
    m, _ = _scene(tmp_path, 1)
    if value is None:
        value = tmp_path / "k.csv"
        value.write_text("name,x,y,z\nA0,0,0,2.8\nA9,1,1,1\n")
    out = tmp_path / "r.json"
    res = run(m, opt, value, "--out", out)
    assert res.exit_code == 2
    assert f"'{word}'" in res.output and "A0, A1" in res.output
    assert not out.exists()


def test_anchor_file_and_installer_figure_from_a_matrix(tmp_path):
    """--anchors (CSV and JSON) holds the receivers by the matrix's names in the known frame;
    --anchor-plot draws them with names and units, the tag path and the --room box."""
    m, _ = _scene(tmp_path, 4)
    known = _known(tmp_path, [(f"A{i}", i) for i in range(4)])
    out, anchors, fig = tmp_path / "r.json", tmp_path / "anchors.json", tmp_path / "anchors.png"
    res = run(m, "--known", known, "--out", out, "--anchors", anchors, "--anchor-plot", fig, "--room", "5,4,3")
    assert res.exit_code == 0, res.output
    doc = json.loads(anchors.read_text())
    assert [a["name"] for a in doc["anchors"]] == [f"A{i}" for i in range(7)]
    P = np.array([a["position"] for a in doc["anchors"]])
    S = np.array([a["std"] for a in doc["anchors"]])
    assert np.all(np.abs(P - ANCHORS) <= 6 * S + 1e-9)
    assert fig.read_bytes()[:4] == b"\x89PNG"
    res = run(m, "--out", out, "--anchors", tmp_path / "a.csv")
    assert res.exit_code == 0
    assert (tmp_path / "a.csv").read_text().splitlines()[0] == "name,x,y,z,std_x,std_y,std_z"
