"""Paper 002 experiments: the rover replica (Table I, Figs. 3-4) and the Plaza real-data run.

* :func:`replica_trial` -- one seeded replica run in both modes (a sweep-runner trial).
* :func:`reproduce_slac` -- runs the trials, writes Table I / Fig. 3 / Fig. 4 PNGs + JSON.
* :func:`run_plaza` -- measurement-level localization / SLAC on CMU Plaza with odometry.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..datasets.plaza import PlazaData
from ..slac.measurement import RangeConfig, RangeFilter
from ..slac.motion import wrap_angle

__all__ = ["run_plaza", "plaza_summary", "replica_trial", "reproduce_slac", "PAPER_TABLE_I", "PAPER_FIG3_P90"]

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


def run_plaza(data: PlazaData, *, mode: str = "slac", config: RangeConfig | None = None,
              init_std: tuple[float, float] = (0.1, 2.0)) -> dict[str, Any]:
    """Filter the Plaza log with odometry controls and beacon ranges.

    The pose starts at the first ground-truth pose (std ``init_std`` = (m, deg)); odometry
    increments become controls ``v = dd / dt``, ``omega = dpsi / dt`` of eq. 14; a range that
    falls inside an odometry interval is applied after predicting to its time.

    Returns
    -------
    dict with ``times`` (G,), ``poses`` (G, 3), ``position_rmse`` (m), ``heading_rmse``
    (deg) against GT at the filter times, ``calibration`` and ``rejected``.
    """
    x0 = data.gt[0].copy()
    sd = np.array([init_std[0], init_std[0], np.deg2rad(init_std[1])])
    B = data.beacons.shape[0]
    links = [(0, 1 + b) for b in range(B)]
    filt = RangeFilter(data.beacons, x0[None], np.diag(sd**2)[None], links, mode=mode, config=config)
    G = data.gt_times.size
    poses = np.empty((G, 3))
    poses[0] = x0
    r_idx = 0
    K = data.range_times.size
    used = 0
    for k in range(G - 1):
        t0, t1 = data.gt_times[k], data.gt_times[k + 1]
        dt = t1 - t0
        v = data.odo[k, 0] / dt
        w = data.odo[k, 1] / dt
        t = t0
        while r_idx < K and data.range_times[r_idx] <= t1:
            tr = data.range_times[r_idx]
            if tr > t:
                filt.predict(np.array([[v, w]]), tr - t)
                t = tr
            same = [r_idx]
            while r_idx + len(same) < K and data.range_times[r_idx + len(same)] == tr:
                same.append(r_idx + len(same))
            if tr >= t0:
                used += filt.update([(0, 1 + int(data.range_beacon[q]), "range", float(data.ranges[q])) for q in same])
            r_idx += len(same)
        if t1 > t:
            filt.predict(np.array([[v, w]]), t1 - t)
        poses[k + 1] = filt.poses[0]
    gt = data.gt_at(data.gt_times)
    e_pos = np.linalg.norm(poses[:, :2] - gt[:, :2], axis=1)
    e_psi = wrap_angle(poses[:, 2] - gt[:, 2])
    cal = filt.calibration()
    ids = data.beacon_ids
    biases = {str(int(ids[k - 1])) if k >= 1 else "robot": v for k, v in cal["biases"].items()}  # type: ignore[attr-defined]
    out: dict[str, Any] = {
        "mode": mode, "times": data.gt_times, "poses": poses,
        "position_rmse": float(np.sqrt(np.mean(e_pos**2))), "heading_rmse": float(np.rad2deg(np.sqrt(np.mean(e_psi**2)))),
        "position_errors": e_pos, "biases": biases, "ranges_used": used, "rejected": filt.rejected,
    }
    if "scales" in cal:
        out["scale_factors"] = {str(int(ids[int(k.split("-")[1]) - 1])): v for k, v in cal["scales"].items()}  # type: ignore[attr-defined]
    return out


def plaza_summary(data: PlazaData, config: RangeConfig | None = None) -> dict[str, Any]:
    """Both modes on Plaza; the JSON contract of ``selfcal slac plaza``."""
    loc = run_plaza(data, mode="localization", config=config)
    sl = run_plaza(data, mode="slac", config=config)
    return {
        "position_rmse_localization": loc["position_rmse"], "position_rmse_slac": sl["position_rmse"],
        "heading_rmse_localization": loc["heading_rmse"], "heading_rmse_slac": sl["heading_rmse"],
        "biases": sl["biases"], "scale_factors": sl.get("scale_factors"),
        "ranges_used": {"localization": loc["ranges_used"], "slac": sl["ranges_used"]},
        "rejected": {"localization": loc["rejected"], "slac": sl["rejected"]},
        "method": "slac-measurement-level", "units": {"position": "m", "heading": "deg", "biases": "m"},
        "_tracks": {"times": sl["times"], "localization": loc["poses"], "slac": sl["poses"]},
    }


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
