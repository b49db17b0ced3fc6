"""Paper 002 experiments: the rover replica (Table I, Figs. 3-4) and the Plaza real-data run.

* :func:`score_slac` -- a :func:`~selfcal.slac.run.solve_slac` run against the simulated truth
  (Table I, NEES, Fig. 3 DoA errors, Fig. 4 ranging RMSE).
* :func:`replica_trial` -- one seeded replica run in both modes (a sweep-runner trial).
* :func:`reproduce_slac` -- runs the trials, writes Table I / Fig. 3 / Fig. 4 PNGs + JSON.
* :func:`plaza_summary` / :func:`score_plaza` -- the CMU range logs (Plaza): per-beacon
  scale + offset filter and smoother, scored against ground truth (the figure is
  :func:`selfcal.plotting.slac.plot_plaza`).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..datasets.plaza import PlazaData
from ..slac.doa import estimate_doa_from_y
from ..slac.motion import wrap_angle
from ..slac.ranging import RangeModelConfig, RangeSlacResult, solve_range_slac
from ..slac.run import SlacLog, SlacResult

__all__ = ["score_plaza", "plaza_summary", "score_slac", "replica_trial", "reproduce_slac", "PAPER_TABLE_I", "PAPER_FIG3_P90"]

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


def score_slac(log: SlacLog, result: SlacResult) -> dict[str, Any]:
    """Errors of a :func:`~selfcal.slac.run.solve_slac` result against the log's truth (paper 002, section V).

    Parameters
    ----------
    log : SlacLog
        With the true states (a simulated log, :meth:`SlacLog.from_scenario`).
    result : SlacResult
        The run over the first ``len(result.poses) - 1`` steps of ``log``.

    Returns
    -------
    dict
        ``position_rmse`` (m) and ``heading_rmse_deg`` per agent (Table I), ``nees_mean`` per agent
        (3 dof), ``ranging_rmse_uncorrected`` / ``ranging_rmse_corrected`` per step (m, Fig. 4),
        ``bias_error`` / ``bias_std`` (m) when the log has true biases, and ``doa``: per multi-port
        agent and sampling matrix (EM prior, chamber prior, the filter's estimate) the DoA errors
        (deg; Fig. 3) with their median and 90th percentile.

    Raises
    ------
    InputError
        The log carries no truth.
    """
    from ..errors import InputError

    if log.states is None:
        raise InputError("the log carries no true states to score against")
    poses, covs, biases = result.poses, result.pose_cov, result.biases
    bias_std, ml, pv, Gs = result.bias_std, result.ml_ranges, result.port_vectors, result.sampling_matrices
    S = poses.shape[0] - 1
    tr = log.states[: S + 1]
    n = log.n_agents
    e_pos = np.linalg.norm(poses[:, :, :2] - tr[:, :, :2], axis=2)
    e_psi = wrap_angle(poses[:, :, 2] - tr[:, :, 2])
    err = np.concatenate([poses[:, :, :2] - tr[:, :, :2], e_psi[:, :, None]], axis=2)
    nees = np.einsum("sni,snij,snj->sn", err, np.linalg.inv(covs), err)
    names = list(log.names) if log.names else [f"agent{i}" for i in range(n)]
    out: dict[str, Any] = {
        "agents": names,
        "position_rmse": np.sqrt(np.mean(e_pos[1:] ** 2, axis=0)),
        "heading_rmse_deg": np.rad2deg(np.sqrt(np.mean(e_psi[1:] ** 2, axis=0))),
        "nees_mean": np.mean(nees[1:], axis=0),
        "nees_dof": 3,
    }
    # ranging RMSE over all links per step, without / with the bias correction (Fig. 4)
    d_true = np.stack([np.linalg.norm(np.vstack([tr[s, :, :2], log.anchors])[log.tx]
                                      - np.vstack([tr[s, :, :2], log.anchors])[log.rx], axis=1)
                       for s in range(1, S + 1)])
    corr = ml + biases[1:][:, log.rx] + biases[1:][:, log.tx]
    out["ranging_rmse_uncorrected"] = np.sqrt(np.mean((ml - d_true) ** 2, axis=1))
    out["ranging_rmse_corrected"] = np.sqrt(np.mean((corr - d_true) ** 2, axis=1))
    if log.biases is not None:
        out["true_biases"] = log.biases
        out["bias_error"] = biases[-1] - log.biases
        out["bias_std"] = bias_std
    doa: dict[str, Any] = {}
    for i, y in pv.items():
        links = np.flatnonzero(log.rx == i)
        true_phi = []
        for s in range(1, S + 1):
            p = np.vstack([tr[s, :, :2], log.anchors])
            dl = p[log.tx[links]] - p[i]
            true_phi.append(np.arctan2(dl[:, 1], dl[:, 0]) - tr[s, i, 2])
        tp = np.array(true_phi)
        sub = np.arange(0, S, max(1, S // 400))  # DoA post-processing on <= ~400 snapshots per link
        cands = {"em": log.G_em[i, : log.ports[i]], "chamber": log.G_chamber[i, : log.ports[i]]}
        G_est = Gs.get(i)
        if G_est is not None:
            cands["filter"] = G_est
        errs = {}
        for name, G in cands.items():
            e = [abs(float(wrap_angle(estimate_doa_from_y(y[s, l], G, grid=360) - tp[s, l])))
                 for s in sub for l in range(links.size)]
            errs[name] = np.rad2deg(np.array(e))
        doa[names[i]] = {k: {"p90_deg": float(np.percentile(v, 90)), "median_deg": float(np.median(v)),
                             "errors_deg": v} for k, v in errs.items()}
    out["doa"] = doa
    return out


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
        m = score_slac(log, r)
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
    from ..plotting.slac import plot_doa_cdf, plot_position_rmse, plot_ranging_rmse
    from .runner import run_sweep

    out = Path(out_dir)
    rows = run_sweep(replica_trial, [{"minutes": minutes, "subcarriers": subcarriers, "progress": progress and runs == 1,
                                     "init": init, "smoother_lag": smoother_lag}],
                     runs=runs, seed=seed, backend=backend, scheduler=scheduler, progress=progress, desc="slac replica")
    agents = rows[0]["agents"]
    table: dict[str, dict[str, Any]] = {}
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
    doa, cdfs = {}, {}
    for name in ("em", "chamber", "filter"):
        errs = np.concatenate([r["slac"]["doa"]["Dias"][name]["errors_deg"] for r in rows])
        doa[name] = {"p90_deg": float(np.percentile(errs, 90)), "median_deg": float(np.median(errs)),
                     "paper_p90_deg": PAPER_FIG3_P90[name]}
        cdfs[{"em": "EM simulation", "chamber": "chamber", "filter": "SLAC"}[name]] = errs
    plot_doa_cdf(cdfs, out / "fig3_doa_cdf.png")
    r0 = rows[0]["slac"]
    t = np.arange(1, len(r0["ranging_rmse_uncorrected"]) + 1) * 0.1 / 60
    plot_ranging_rmse(t, {"without correction": r0["ranging_rmse_uncorrected"], "SLAC": r0["ranging_rmse_corrected"]},
                      out / "fig4_ranging_rmse.png", window=50)
    plot_position_rmse(agents, {"localization": [float(table[a]["position_rmse_localization"]) for a in agents],
                                "SLAC": [float(table[a]["position_rmse_slac"]) for a in agents]},
                       out / "table1_position_rmse.png")
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
