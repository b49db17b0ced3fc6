"""``calibrate toa --known`` with partly known nodes (``A3,,,2.41``: only the height):
read and checked before any work, fitted as fixed coordinates, the frame axes the user
fixed said in the output and the JSON; commands that take whole positions refuse it."""

from __future__ import annotations

import json

import numpy as np
from click.testing import CliRunner

from selfcal.cli import main

ANCHORS = np.array([[0, 0, 2.8], [5, 0, 2.9], [5, 4, 2.7], [0, 4, 2.9], [2.5, 0, 0.3], [2.5, 4, 0.4],
                    [0, 2, 1.5]])


def _scene(tmp_path, seed, n=30, noise=0.01):
    rng = np.random.default_rng(seed)
    T = np.column_stack([rng.uniform(0.5, 4.5, n), rng.uniform(0.5, 3.5, n), rng.uniform(0.3, 2.0, n)])
    D = np.linalg.norm(ANCHORS[:, None] - T[None], axis=-1) + rng.normal(0, noise, (7, n))
    path = tmp_path / "ranges.csv"
    with open(path, "w") as f:
        f.write("anchor," + ",".join(f"tag{j}" for j in range(n)) + "\n")
        for i in range(7):
            f.write(f"A{i}," + ",".join(f"{v:.5f}" for v in D[i]) + "\n")
    return path


def run(*args):
    return CliRunner().invoke(main, [str(a) for a in args], catch_exceptions=False)


def test_known_heights_set_the_rooms_z(tmp_path):
    for seed in range(2):
        rng_path = _scene(tmp_path, seed)
        known = tmp_path / "heights.csv"
        known.write_text("name,x,y,z\n" + "".join(f"A{i},,,{ANCHORS[i, 2]}\n" for i in range(7)))
        out = tmp_path / "r.json"
        r = run("calibrate", "toa", rng_path, "--known", known, "--out", out)
        assert r.exit_code == 0, r.output
        assert "frame axes fixed by them: z; x,y canonical" in r.output
        d = json.loads(out.read_text())
        assert d["frame"]["axes_fixed"] == ["z"]
        z = np.array(d["receivers"])[:, 2]
        assert np.allclose(z, ANCHORS[:, 2])  # exact known heights are held


def test_partial_known_file_checked_before_the_solve(tmp_path):
    rng_path = _scene(tmp_path, 0)
    for text, what in (("name,x,y,z\nA0,,,2.8\nB9,,,1.0\n", "unknown node 'B9'"),
                       ("name,x,y,z\nA0,,,\n", "no coordinate")):
        known = tmp_path / "k.csv"
        known.write_text(text)
        r = run("calibrate", "toa", rng_path, "--known", known, "--out", tmp_path / "x.json")
        assert r.exit_code == 2 and what in r.output, r.output
        assert not (tmp_path / "x.json").exists()


def test_graph_takes_whole_positions_only(tmp_path):
    log = tmp_path / "log.csv"
    log.write_text("from,to,range\nA0,A1,5.0\nA0,A2,6.4\nA1,A2,4.0\nA0,A3,4.0\nA1,A3,6.4\nA2,A3,5.0\n")
    known = tmp_path / "k.csv"
    known.write_text("name,x,y,z\nA0,,,2.8\n")
    r = run("calibrate", "graph", log, "--known", known, "--out", tmp_path / "g.json")
    assert r.exit_code == 2 and "whole" in r.output, r.output


def test_known_file_in_millimetres_refused_before_the_solve(tmp_path):
    rng_path = _scene(tmp_path, 0)
    known = tmp_path / "mm.csv"
    known.write_text("name,x,y,z\n" + "".join(f"A{i},,,{1000 * ANCHORS[i, 2]}\n" for i in range(7)))
    r = run("calibrate", "toa", rng_path, "--known", known, "--out", tmp_path / "x.json")
    assert r.exit_code == 2 and "unit mistake" in r.output, r.output
    assert not (tmp_path / "x.json").exists()
