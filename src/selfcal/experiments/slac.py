"""Paper 002 experiments: the rover replica (Table I, Figs. 3-4) and the Plaza real-data run.

* :func:`replica_trial` -- one seeded replica run in both modes (a sweep-runner trial).
* :func:`reproduce_slac` -- runs the trials, writes Table I / Fig. 3 / Fig. 4 PNGs + JSON.
* :func:`plaza_summary` / :func:`score_plaza` / :func:`plot_plaza` -- the CMU range logs
  (Plaza): per-beacon scale + offset filter and smoother, scored against ground truth.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..datasets.plaza import PlazaData
from ..slac.motion import wrap_angle
from ..slac.ranging import RangeModelConfig, RangeSlacResult, solve_range_slac

__all__ = ["score_plaza", "plaza_summary", "plot_plaza", "replica_trial", "reproduce_slac", "PAPER_TABLE_I", "PAPER_FIG3_P90"]

FArray = NDArray[np.float64]

#: Table I of paper 002 (position m, orientation deg; localization-only, SLAC) per rover.
PAPER_TABLE_I = {
    "Dias": (0.32, 0.26, 2.1, 1.8),
    "Drake": (0.68, 0.40, 8.5, 7.9),
    "Vespucci": (0.72, 0.44, 6.6, 6.4),
    "Magellan": (0.36, 0.30, 6.6, 6.6),
}
#: Fig. 3 90th percentiles of the DoA error (deg): EM prior, chamber prior, SLAC.
PAPER_FIG3_P90 = {"em": 16.6, "chamber": 10.2, "filter": 5.6}


def score_plaza(data: PlazaData, result: RangeSlacResult) -> dict[str, float]:
    """Errors of a track against the log's ground truth (interpolated at the pose times).

    The heading truth is ``GT(:, 4) + init_heading_offset`` (applied by the loader).

    Returns
    -------
    dict with ``position_rmse`` (m), ``position_p95`` (m), ``heading_rmse_deg``, ``poses``.
    """
    t = np.asarray(result.times)
    keep = (t >= data.gt_times[0]) & (t <= data.gt_times[-1])
    gt = data.gt_at(t[keep])
    e = np.linalg.norm(result.poses[keep, :2] - gt[:, :2], axis=1)
    h = wrap_angle(result.poses[keep, 2] - gt[:, 2])
    return {"position_rmse": float(np.sqrt(np.mean(e**2))), "position_p95": float(np.percentile(e, 95)),
            "heading_rmse_deg": float(np.rad2deg(np.sqrt(np.mean(h**2)))), "poses": int(keep.sum())}


def plaza_summary(data: PlazaData, *, methods: tuple[str, ...] = ("filter", "smoother"),
                  config: RangeModelConfig | None = None, progress: bool = False) -> dict[str, Any]:
    """Run :func:`~selfcal.slac.ranging.solve_range_slac` per method on a CMU range log, score it.

    Returns
    -------
    dict: ``methods`` {name: result dict without the track + score + ``seconds``},
    ``dead_reckoning`` score, ``init_heading_offset``, and ``_results`` {name: RangeSlacResult}
    (not JSON; the command pops it for the exports and the plot).
    """
    import time
    from types import SimpleNamespace

    out: dict[str, Any] = {"methods": {}, "init_heading_offset": data.init_heading_offset,
                           "beacon_ids": [int(b) for b in data.beacon_ids], "_results": {}}
    dr = data.dead_reckoning()
    out["dead_reckoning"] = score_plaza(data, SimpleNamespace(times=data.pose_times, poses=dr))  # type: ignore[arg-type]
    for m in methods:
        t0 = time.perf_counter()
        r = solve_range_slac(data, method=m, config=config, progress=progress)
        sec = time.perf_counter() - t0
        d = {k: v for k, v in r.to_dict().items() if k not in ("times", "poses", "pose_std")}
        out["methods"][m] = {**d, **score_plaza(data, r), "seconds": sec}
        out["_results"][m] = r
    return out


def plot_plaza(path: str | Path, data: PlazaData, results: dict[str, RangeSlacResult]) -> None:
    """Tracks against ground truth, the beacons labelled with their estimated scale / offset (PNG)."""
    from ..plotting import new_figure, save_figure

    fig, ax = new_figure(size=(7, 7))
    ax.plot(data.gt[:, 0], data.gt[:, 1], "k-", lw=0.8, label="ground truth")
    dr = data.dead_reckoning()
    ax.plot(dr[:, 0], dr[:, 1], ":", color="0.5", lw=0.8, label="dead reckoning (DR)")
    ref = None
    for name, r in results.items():
        sc = score_plaza(data, r)
        ax.plot(r.poses[:, 0], r.poses[:, 1], lw=0.9, label=f"{name} ({sc['position_rmse']:.2f} m RMSE)")
        ref = r
    ax.plot(data.beacons[:, 0], data.beacons[:, 1], "r^", ms=9, label="beacons")
    for k, (bx, by) in enumerate(data.beacons):
        txt = f"id {int(data.beacon_ids[k])}"
        if ref is not None:
            txt += f"\nscale {ref.scale[k]:.3f}\u00b1{ref.scale_std[k]:.3f}\noffset {ref.offset[k]:+.2f}\u00b1{ref.offset_std[k]:.2f} m"
        ax.annotate(txt, (bx, by), textcoords="offset points", xytext=(6, 6), fontsize=7)
    ax.set_aspect("equal")
    ax.margins(0.15)  # room for the beacon labels
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    which = f" ({ref.method} calibration)" if ref is not None else ""
    ax.set_title(f"Range-only SLAC with per-beacon scale + offset{which}")
    ax.legend(fontsize=7, loc="best")
    save_figure(fig, path)


def replica_trial(params: dict[str, Any], seed: int) -> dict[str, Any]:
    """One replica run (both modes) -> Table I / Fig. 3 / Fig. 4 numbers (module-level, picklable)."""
    from ..scenarios.rovers import make_rover_scenario
    from ..slac.filter import SlacConfig
    from ..slac.run import SlacLog, solve_slac

    sc = make_rover_scenario(float(params["minutes"]), n_subcarriers=int(params["subcarriers"]), rng=seed)
    log = SlacLog.from_scenario(sc, seed=seed)
    out: dict[str, Any] = {"agents": list(sc.names)}
    for mode in ("localization", "slac"):
        r = solve_slac(log, mode=mode, prior=str(params.get("prior", "chamber")), progress=bool(params.get("progress", False)),
                       init=str(params.get("init", "snapshot")),
                       config=SlacConfig(smoother_lag=int(params.get("smoother_lag", 0))))
        m = r.metrics
        out[mode] = {
            "position_rmse": m["position_rmse"], "heading_rmse_deg": m["heading_rmse_deg"], "nees_mean": m["nees_mean"],
            "ranging_rmse_uncorrected": m["ranging_rmse_uncorrected"], "ranging_rmse_corrected": m["ranging_rmse_corrected"],
            "doa": m["doa"], "bias_error": m.get("bias_error"), "bias_std": m.get("bias_std"),
            "mean_iterations": float(r.iterations.mean()),
        }
    return out


def reproduce_slac(out_dir: str | Path, *, minutes: float = 12.5, subcarriers: int = 1024, runs: int = 1,
                   seed: int = 0, backend: str = "serial", scheduler: str | None = None,
                   progress: bool = True, init: str = "snapshot", smoother_lag: int = 0) -> dict[str, Any]:
    """Replica of section V: Table I, Fig. 3 (DoA CDFs) and Fig. 4 (ranging RMSE), PNG + JSON.

    ``init``: "snapshot" (section IV's snapshot-based initial poses, the default) or "log"
    (truth plus 0.3 m / 3 deg noise), see :func:`~selfcal.slac.run.solve_slac`.
    ``smoother_lag``: 0 = the paper's filter; K > 0 = the fixed-lag smoother (beyond the paper,
    consistent error bars, about 5x slower; ``docs/slac_consistency.md``).
    """
    from ..io import write_json
    from ..plotting import new_figure, plot_cdf, save_figure
    from .runner import run_sweep

    out = Path(out_dir)
    rows = run_sweep(replica_trial, [{"minutes": minutes, "subcarriers": subcarriers, "progress": progress and runs == 1,
                                     "init": init, "smoother_lag": smoother_lag}],
                     runs=runs, seed=seed, backend=backend, scheduler=scheduler, progress=progress, desc="slac replica")
    agents = rows[0]["agents"]
    table = {}
    for k, a in enumerate(agents):
        table[a] = {
            "position_rmse_localization": float(np.median([r["localization"]["position_rmse"][k] for r in rows])),
            "position_rmse_slac": float(np.median([r["slac"]["position_rmse"][k] for r in rows])),
            "heading_rmse_localization": float(np.median([r["localization"]["heading_rmse_deg"][k] for r in rows])),
            "heading_rmse_slac": float(np.median([r["slac"]["heading_rmse_deg"][k] for r in rows])),
            "nees_localization": float(np.median([r["localization"]["nees_mean"][k] for r in rows])),
            "nees_slac": float(np.median([r["slac"]["nees_mean"][k] for r in rows])),
            "paper": dict(zip(("pos_loc", "pos_slac", "head_loc", "head_slac"), PAPER_TABLE_I.get(a, ()), strict=False)),
        }
    doa = {}
    fig, ax = new_figure(size=(6, 4.5))
    for name in ("em", "chamber", "filter"):
        errs = np.concatenate([r["slac"]["doa"]["Dias"][name]["errors_deg"] for r in rows])
        doa[name] = {"p90_deg": float(np.percentile(errs, 90)), "median_deg": float(np.median(errs)),
                     "paper_p90_deg": PAPER_FIG3_P90[name]}
        plot_cdf(ax, errs, label={"em": "EM simulation", "chamber": "chamber", "filter": "SLAC"}[name])
    ax.set_xlabel("absolute DoA error (deg)")
    ax.set_ylabel("empirical CDF")
    ax.set_title("Fig. 3 replica: DoA error at Dias (MMA)")
    ax.legend()
    save_figure(fig, out / "fig3_doa_cdf.png")
    fig, ax = new_figure(size=(7, 4))
    r0 = rows[0]["slac"]
    t = np.arange(1, len(r0["ranging_rmse_uncorrected"]) + 1) * 0.1 / 60
    w = 50

    def smooth(v: FArray) -> FArray:
        return np.convolve(np.asarray(v), np.ones(w) / w, mode="same")

    ax.plot(t, smooth(r0["ranging_rmse_uncorrected"]), label="without correction")
    ax.plot(t, smooth(r0["ranging_rmse_corrected"]), label="SLAC")
    ax.set_xlabel("time (min)")
    ax.set_ylabel("ranging RMSE (m), 5 s average")
    ax.set_title("Fig. 4 replica")
    ax.legend()
    save_figure(fig, out / "fig4_ranging_rmse.png")
    fig, ax = new_figure(size=(7, 4))
    xs = np.arange(len(agents))
    ax.bar(xs - 0.2, [table[a]["position_rmse_localization"] for a in agents], 0.4, label="localization")
    ax.bar(xs + 0.2, [table[a]["position_rmse_slac"] for a in agents], 0.4, label="SLAC")
    ax.set_xticks(xs, agents)
    ax.set_ylabel("position RMSE (m)")
    ax.set_title("Table I replica")
    ax.legend()
    save_figure(fig, out / "table1_position_rmse.png")
    summary = {
        "minutes": minutes, "subcarriers": subcarriers, "runs": runs, "seed": seed, "init": init, "smoother_lag": smoother_lag,
        "table_I": table, "fig3_doa": doa,
        "fig4": {
            "ranging_rmse_uncorrected_mean": float(np.median([np.mean(r["slac"]["ranging_rmse_uncorrected"]) for r in rows])),
            "ranging_rmse_slac_mean": float(np.median([np.mean(r["slac"]["ranging_rmse_corrected"]) for r in rows])),
            "ranging_rmse_slac_last_minute": float(np.median([np.mean(r["slac"]["ranging_rmse_corrected"][-600:]) for r in rows])),
            "fraction_of_steps_slac_below_uncorrected": float(np.median([
                np.mean(np.asarray(r["slac"]["ranging_rmse_corrected"]) <= np.asarray(r["slac"]["ranging_rmse_uncorrected"]))
                for r in rows])),
        },
    }
    write_json(out / "slac_reproduction.json", summary)
    return summary
