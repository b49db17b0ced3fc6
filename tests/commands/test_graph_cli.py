"""``selfcal calibrate graph``: a UWB log from,to,range by names -> the anchor file in the room
frame, the JSON, the installer figure (issue 29)."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest
from click.testing import CliRunner

from selfcal.cli import main
from selfcal.toa.graph.graph import simulate_range_graph

ANCHORS = np.array([[0, 0, 2.8], [5, 0, 2.9], [5, 4, 2.7], [0, 4, 2.9], [2.5, 0, 0.3], [2.5, 4, 0.4],
                    [0, 2, 1.5]])


def _log(tmp_path, seed, tags=20, anchor_pairs=True, std=False):
    rng = np.random.default_rng(seed)
    t = np.linspace(0, 2 * np.pi, tags)
    T = np.column_stack([2.5 + 1.5 * np.cos(t), 2 + 1.2 * np.sin(t), 1 + 0.4 * np.sin(3 * t)]) if tags else None
    a, b, y = simulate_range_graph(ANCHORS, T, noise=0.02, repeats=2, anchor_pairs=anchor_pairs, rng=rng)
    names = [f"A{i}" for i in range(7)] + [f"t{j:03d}" for j in range(tags)]
    path = tmp_path / "log.csv"
    with open(path, "w") as f:
        f.write("from,to,range" + (",std" if std else "") + "\n")
        for u, v, r in zip(a, b, y, strict=True):
            f.write(f"{names[u]},{names[v]},{r:.5f}" + (",0.02" if std else "") + "\n")
    return path, T


def _known(tmp_path, idx):
    p = tmp_path / "known.csv"
    p.write_text("name,x,y,z\n" + "".join(f"A{i},{ANCHORS[i, 0]},{ANCHORS[i, 1]},{ANCHORS[i, 2]}\n" for i in idx))
    return p


def run(*args):
    return CliRunner().invoke(main, ["calibrate", "graph", *map(str, args)])


@pytest.mark.parametrize("seed", range(2))
def test_log_to_anchor_file_in_the_room_frame(tmp_path, seed):
    """Known A0..A3 by name: the anchor CSV holds all 7 anchors (no tags) in the room, within
    6 x their stated std (+1 mm for the CSV's rounding); the JSON names every node."""
    log, T = _log(tmp_path, seed)
    out, anchors, fig = tmp_path / "r.json", tmp_path / "anchors.csv", tmp_path / "anchors.png"
    res = run(log, "--known", _known(tmp_path, range(4)), "--tags", "t*", "--room", "5,4,3",
              "--out", out, "--anchors", anchors, "--plot", fig)
    assert res.exit_code == 0, res.output
    rows = list(csv.DictReader(anchors.open()))
    assert [r["name"] for r in rows] == [f"A{i}" for i in range(7)]
    assert list(rows[0]) == ["name", "x", "y", "z", "std_x", "std_y", "std_z"]
    P = np.array([[float(r[k]) for k in "xyz"] for r in rows])
    S = np.array([[float(r[f"std_{k}"]) for k in "xyz"] for r in rows])
    assert np.all(np.abs(P - ANCHORS) <= 6 * S + 1e-3)
    doc = json.loads(out.read_text())
    assert doc["names"][:8] == [f"A{i}" for i in range(7)] + ["t000"]
    assert doc["anchors"] == [f"A{i}" for i in range(7)] and len(doc["tags"]) == 20
    assert fig.read_bytes()[:4] == b"\x89PNG"
    assert "frame fully determined by 4 known nodes" in res.output


def test_anchor_json_for_a_configuration_tool_and_frame_by_names(tmp_path):
    """Anchor-only log with a std column, --frame by names: the JSON form of --anchors."""
    log, _ = _log(tmp_path, 5, tags=0, std=True)
    out, anchors = tmp_path / "r.json", tmp_path / "anchors.json"
    res = run(log, "--frame", "origin=A0,x=A1,xy=A3,z=A4", "--out", out, "--anchors", anchors)
    assert res.exit_code == 0, res.output
    doc = json.loads(anchors.read_text())
    assert doc["format"] == "selfcal-anchors/1" and doc["units"] == "m"
    assert [a["name"] for a in doc["anchors"]] == [f"A{i}" for i in range(7)]
    assert doc["anchors"][0]["position"] == [0.0, 0.0, 0.0]
    assert "residual test against the std column" in res.output


def test_unknown_known_name_exit_2_before_work(tmp_path, monkeypatch):
    import selfcal.toa.graph.graph as graph

    monkeypatch.setattr(graph, "_initial", lambda *a, **k: (_ for _ in ()).throw(AssertionError("solved")))
    log, _ = _log(tmp_path, 1, tags=0)
    k = tmp_path / "k.csv"
    k.write_text("name,x,y,z\nA0,0,0,2.8\nB9,1,1,1\n")
    out = tmp_path / "r.json"
    res = run(log, "--known", k, "--out", out)
    assert res.exit_code == 2 and "'B9'" in res.output and not out.exists()


def test_coplanar_ceiling_anchors_alone_fail_their_own_test(tmp_path):
    """Anchor-only ranges among anchors in one plane, in 3-D: exit 1 with a FAIL line saying
    which nodes are not determined (the result is still written)."""
    flat = ANCHORS.copy()
    flat[:, 2] = 2.8
    a, b, y = simulate_range_graph(flat, None, noise=0.02, repeats=3, rng=0)
    log = tmp_path / "log.csv"
    log.write_text("from,to,range\n" + "".join(f"A{u},A{v},{r:.5f}\n" for u, v, r in zip(a, b, y, strict=True)))
    out = tmp_path / "r.json"
    res = run(log, "--out", out)
    assert res.exit_code == 1 and "FAIL" in res.output and "A0" in res.output
    assert out.exists()


def test_bad_room_and_unmatched_tags_are_bad_input(tmp_path):
    log, _ = _log(tmp_path, 2, tags=5)
    out = tmp_path / "r.json"
    assert run(log, "--room", "5,4", "--out", out).exit_code == 2
    res = run(log, "--tags", "x*", "--out", out)
    assert res.exit_code == 2 and "matches none" in res.output


def test_tags_mirrored_under_coplanar_anchors_do_not_fail_the_anchor_file(tmp_path):
    """Ceiling anchors (one plane) and a tag log: the tags are mirror-ambiguous, the anchors
    are not; with --tags the command says so and exits 0, without it (every node an anchor)
    it fails."""
    flat = ANCHORS.copy()
    flat[:, 2] = 2.8
    rng = np.random.default_rng(0)
    T = np.column_stack([rng.uniform(0.5, 4.5, 15), rng.uniform(0.5, 3.5, 15), rng.uniform(0.3, 2.0, 15)])
    a, b, y = simulate_range_graph(flat, T, noise=0.02, anchor_pairs=False, rng=0)
    names = [f"A{i}" for i in range(7)] + [f"t{j:02d}" for j in range(15)]
    log = tmp_path / "log.csv"
    log.write_text("from,to,range\n" + "".join(f"{names[u]},{names[v]},{r:.5f}\n" for u, v, r in zip(a, b, y, strict=True)))
    known = tmp_path / "known.csv"
    known.write_text("name,x,y,z\n" + "".join(f"A{i},{flat[i, 0]},{flat[i, 1]},{flat[i, 2]}\n" for i in range(4)))
    out = tmp_path / "r.json"
    res = run(log, "--known", known, "--tags", "t*", "--out", out)
    assert res.exit_code == 0 and "ambiguous tag positions" in res.output
    res = run(log, "--known", known, "--out", out)
    assert res.exit_code == 1 and "mirrored" in res.output


def test_centimetres_give_the_same_anchors_in_metres(tmp_path):
    """The same log in cm with --unit cm: the anchor file (metres) agrees with the metre run to
    round-off of the 5-decimal log (the fit is scale-equivariant)."""
    log, _ = _log(tmp_path, 3, tags=10)
    cm = tmp_path / "log_cm.csv"
    lines = log.read_text().splitlines()
    cm.write_text("\n".join([lines[0]] + [",".join(p[:2] + [f"{float(p[2]) * 100:.3f}"])
                                          for p in (ln.split(",") for ln in lines[1:])]) + "\n")
    known = _known(tmp_path, range(4))
    outs = []
    for path, extra in ((log, []), (cm, ["--unit", "cm"])):
        anchors = tmp_path / f"a_{path.stem}.csv"
        res = run(path, *extra, "--known", known, "--tags", "t*", "--out", tmp_path / "r.json", "--anchors", anchors)
        assert res.exit_code == 0, res.output
        outs.append(np.array([[float(r[k]) for k in "xyz"] for r in csv.DictReader(anchors.open())]))
    assert np.max(np.abs(outs[0] - outs[1])) < 1e-3
