"""The installer's anchor figure (issue 29): names and units are drawn, three views, room and path."""

from __future__ import annotations

import numpy as np
import pytest

from selfcal.errors import InputError
from selfcal.plotting.anchors import plot_anchors, room_box


def test_names_units_views_room_and_tag_path_are_drawn(tmp_path):
    rng = np.random.default_rng(0)
    A = rng.uniform(0, 4, (6, 3))
    names = [f"anchor-{i}" for i in range(6)]
    cov = np.tile(np.eye(3) * 1e-4, (6, 1, 1))
    tag = np.column_stack([np.linspace(1, 3, 50), np.full(50, 2.0), np.full(50, 1.0)])
    fig = plot_anchors(A, names, tmp_path / "a.svg", cov=cov, tag=tag, room=room_box([5, 4, 3]))
    axes = fig.axes
    assert [ax.get_title() for ax in axes] == ["plan (x-y)", "elevation (x-z)", "elevation (y-z)"]
    for ax in axes:
        assert sorted(t.get_text() for t in ax.texts) == sorted(names)  # every anchor named in every view
        assert ax.get_xlabel().endswith("[m]") and ax.get_ylabel().endswith("[m]")
    labels = axes[0].get_legend_handles_labels()[1]
    assert "room" in labels and "tag path" in labels and any("95 % ellipses" in t for t in labels)
    # the room outline spans the box in the plan view
    room_line = next(line for line in axes[0].lines if line.get_label() == "room")
    assert np.allclose(sorted(set(room_line.get_xdata())), [0, 5]) and np.allclose(sorted(set(room_line.get_ydata())), [0, 4])
    assert (tmp_path / "a.svg").read_text().count("anchor-0") >= 3


def test_room_box_refuses_a_bad_box():
    with pytest.raises(InputError):
        room_box([5, 4])
    with pytest.raises(InputError):
        room_box([0, 0, 0, -1, 4, 3])
