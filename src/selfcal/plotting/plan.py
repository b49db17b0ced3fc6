"""Figure of :func:`selfcal.toa.plan.plan_layout`: the tag's positioning error over the room."""

from __future__ import annotations

import os
from collections.abc import Sequence
from typing import Any

import numpy as np
from matplotlib.figure import Figure

from ._common import finish, new_figure

__all__ = ["plot_plan"]


def plot_plan(plan: Any, anchors: Any, path: Any, out: str | os.PathLike[str] | None = None, *,
              names: Sequence[str] | None = None) -> Figure:
    """Map of the tag positioning error bound at the plan's height, with anchors and tag path.

    Parameters
    ----------
    plan : LayoutPlan
    anchors : (I, 3) array
    path : (J, 3) array
    out : path, optional
        Written when given (format from the suffix).
    names : sequence of str, optional
        Anchor labels (default A0, A1, ...).

    Returns
    -------
    Figure
    """
    A = np.asarray(anchors, float)
    P = np.asarray(path, float)
    labels = list(names) if names is not None else [f"A{i}" for i in range(len(A))]
    fig, ax = new_figure(size=(7.0, 5.5))
    X, Y = np.meshgrid(plan.grid_x, plan.grid_y)
    Z = np.where(np.isfinite(plan.tag_std_map), plan.tag_std_map * 100, np.nan)
    cs = ax.contourf(X, Y, Z, levels=12, cmap="viridis")
    fig.colorbar(cs, ax=ax, label=f"tag position error bound at z = {plan.height:.2f} m (cm)")
    ax.plot(P[:, 0], P[:, 1], "-", color="white", lw=0.8, alpha=0.8, label="planned tag path")
    ax.scatter(A[:, 0], A[:, 1], marker="^", s=70, color="red", edgecolor="k", zorder=3, label="anchors")
    mid = 0.5 * (plan.grid_x[0] + plan.grid_x[-1])
    for a, n, s in zip(A, labels, plan.anchor_std, strict=True):
        err = f"±{100 * s:.0f} cm" if np.isfinite(s) else "undetermined"
        right = a[0] > mid  # labels point inwards, so none leaves the map
        ax.annotate(f"{n} {err} (z {a[2]:.1f})", a[:2], xytext=(-4 if right else 4, 4), textcoords="offset points",
                    ha="right" if right else "left", fontsize=8, color="k",
                    bbox={"boxstyle": "round,pad=0.2", "fc": "white", "alpha": 0.7})
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_aspect("equal")
    title = f"plan: noise {100 * plan.noise:.0f} cm, offsets {plan.offsets}"
    if plan.ambiguities:
        title += " - AMBIGUOUS: " + ", ".join(a.kind for a in plan.ambiguities)
    ax.set_title(title, fontsize=10)
    ax.legend(loc="best", fontsize=8)
    return finish(fig, out)
