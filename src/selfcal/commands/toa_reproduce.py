"""``selfcal reproduce toa-mds-nls`` (paper 003 Fig. 5-7) and ``selfcal reproduce lps`` (real data)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import click

from ._base import backend_option, handle_errors, reproduce, scheduler_option, seed_option

NOISE_LEVELS = (0.01, 0.03, 0.1, 0.2, 0.3, 0.5)
SOURCE_COUNTS = (3, 4, 5, 6, 8, 10, 15, 20)


@reproduce.command("toa-mds-nls")
@click.option("--runs", type=int, default=500, show_default=True, help="Monte-Carlo runs per point.")
@backend_option
@scheduler_option
@seed_option
@click.option("--out", "out_dir", type=click.Path(file_okay=False), default="results/toa-mds-nls",
              show_default=True, help="Folder for the PNG figures and the JSON of numbers.")
@handle_errors
def toa_mds_nls(runs: int, backend: str, scheduler: str | None, seed: int, out_dir: str) -> None:
    """Reproduce paper 003: Fig. 5 (one network, 95% ellipses), Fig. 6 (RMSE vs noise),
    Fig. 7 (RMSE vs number of sources), Table I set-up."""
    from .._checks import check_runs
    from ..experiments.runner import run_sweep, write_rows
    from ..experiments.toa_mds_nls import PAPER_003, example_network, summarise, trial_003
    from ..io import write_json
    from ..plotting.toa import plot_network, plot_rmse_curves

    check_runs(runs)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    rows6 = run_sweep(trial_003, [{"sigma": s, "n_sources": 10} for s in NOISE_LEVELS], runs=runs,
                      seed=seed, backend=backend, scheduler=scheduler, desc="Fig. 6 (noise)")
    rows7 = run_sweep(trial_003, [{"sigma": 0.30, "n_sources": k} for k in SOURCE_COUNTS],
                      runs=runs, seed=seed + 1, backend=backend, scheduler=scheduler,
                      desc="Fig. 7 (sources)")
    s6, s7 = summarise(rows6, "sigma"), summarise(rows7, "n_sources")
    ex = example_network(seed)

    plot_network(ex["receivers"], ex["sources"], out / "fig5_network.png", receiver_cov=ex["receiver_cov"],
                 source_cov=ex["source_cov"], true_receivers=ex["true_receivers"], true_sources=ex["true_sources"],
                 labels=("sensors (NLS)", "sources (NLS)"), markers=("^", "s"),
                 title="003 Fig. 5: NLS estimate with 95% ellipses (sigma = 0.3 m)")
    plot_rmse_curves(s6, "sigma", "range noise std (m)", "003 Fig. 6: N=8, K=10", out / "fig6_rmse_vs_noise.png",
                     logx=True)
    plot_rmse_curves(s7, "n_sources", "number of source locations K (-)", "003 Fig. 7: N=8, sigma=0.3 m",
                     out / "fig7_rmse_vs_sources.png")
    write_rows(rows6 + rows7, out / "trials.csv")
    fig5 = {k: v for k, v in ex.items() if isinstance(v, float)}
    write_json(out / "toa_mds_nls.json", {"paper": PAPER_003, "runs": runs, "seed": seed,
                                          "fig5": fig5, "fig6": s6, "fig7": s7})
    at = next(e for e in s6 if abs(e["sigma"] - 0.30) < 1e-12)
    click.echo(f"sigma=0.30 m, K=10 ({runs} runs): MDS {at['mds_rmse']:.3f} m, NLS "
               f"{at['nls_rmse']:.3f} m, sqrt(CRLB) {at['crlb_rmse']:.3f} m  -> {out}")


#: Memory one simulated LPS flight holds until it is scored (bytes, ``--simulate``).
SIM_FLIGHT_BYTES = 30e3


@reproduce.command("lps")
@click.option("--data", "data_path", required=True, type=click.Path(exists=True),
              help="The LPS folder (data4.mat, data5.mat) or one .mat file.")
@click.option("--out", "out_dir", type=click.Path(file_okay=False), default="results/lps",
              show_default=True, help="Folder for the PNG figures and the JSON of numbers.")
@click.option("--simulate", "n_sim", type=int, default=3, show_default=True,
              help="Simulated UWB flights (biases, multipath spikes, sparse positions) scored too.")
@click.option("--variants", "variants_opt", default=None, metavar="A,B,...",
              help="Comma-separated subset of the variants (default: all).")
@seed_option
@handle_errors
def lps(data_path: str, out_dir: str, n_sim: int, variants_opt: str | None, seed: int) -> None:
    """Blind anchor calibration on the LPS UWB flights, scored against motion capture.

    Every variant of :func:`selfcal.experiments.lps.calibrate_lps` runs on every flight
    and on ``--simulate`` simulated flights; the JSON also holds the leave-one-flight-out
    selection among the variants. The recommended variant (plotted) is fixed by principle
    (spike rejection only, :mod:`selfcal.toa.recipes.recipes`), not by these scores.
    """
    import warnings

    import numpy as np

    from ..datasets.lps import load_lps, lps_files
    from ..errors import DegenerateGeometryError, InputError
    from ..experiments.lps import (
        RECOMMENDED,
        calibrate_lps,
        leave_one_flight_out,
        lps_variants,
        simulate_uwb_flight,
    )
    from ..io import write_json
    from ..metrics import aligned_rmse
    from ..plotting.toa import plot_lps_flight

    if n_sim < 0:
        raise InputError(f"--simulate must be >= 0, got {n_sim}")
    # every simulated flight is held until it is scored: (6, 400) ranges, (400, 3) tag positions
    # and its anchors, ~30 kB (1e20 flights never ended)
    from .._checks import guard_size

    guard_size(float(n_sim) * SIM_FLIGHT_BYTES, f"--simulate {n_sim} simulated flights")
    variants = lps_variants()
    if variants_opt is not None:
        variants = tuple(v.strip() for v in variants_opt.split(",") if v.strip())
        bad = [v for v in variants if v not in lps_variants()]
        if bad or not variants:
            raise InputError(f"--variants: unknown {', '.join(bad) or '(empty)'}; choose among "
                             f"{', '.join(lps_variants())}")
    out = Path(out_dir)
    report: dict[str, Any] = {"recommended": RECOMMENDED, "flights": {}, "simulated": {}}
    cases: list[tuple[str, Any, Any, Any, dict[str, Any]]] = []
    for f in lps_files(data_path):
        data = load_lps(f)
        sv = np.linalg.svd(data.anchors_true - data.anchors_true.mean(0), compute_uv=False)
        # the authors' estimate is comparison only: a flight without it (NaN) is not scored
        has_authors = bool(np.isfinite(data.authors_anchors).all())
        has_tag = has_authors and bool((np.isfinite(data.authors_tag).all(1)
                                        & np.isfinite(data.tag_true).all(1)).any())
        entry = {
            **data.to_dict(),
            "authors_anchor_rmse": (aligned_rmse(data.authors_anchors, data.anchors_true).rmse_receivers
                                    if has_authors else None),
            "authors_tag_rmse": (aligned_rmse(data.authors_anchors, data.anchors_true,
                                              data.authors_tag, data.tag_true).rmse_sources
                                 if has_tag else None),
            "anchor_planarity": float(sv[-1] / sv[0]),
        }
        cases.append((data.name, data.ranges, data.anchors_true, data.tag_true, entry))
    for k in range(n_sim):
        sim = simulate_uwb_flight(seed + k)
        cases.append((f"sim{seed + k}", sim["ranges"], sim["anchors"], sim["tag"],
                      {"bias": sim["bias"].tolist(), "n_spikes": int(sim["spikes"].sum())}))
    out.mkdir(parents=True, exist_ok=True)  # only once the data have been read: bad input writes nothing
    scores: dict[str, dict[str, float]] = {}
    for name, Y, anchors, tag, entry in cases:
        entry["variants"] = {}
        scores[name] = {}
        best = None
        for v in variants:
            try:
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")
                    res = calibrate_lps(Y, v, rng=seed)
            except DegenerateGeometryError as exc:  # one variant failing is a result, not an abort
                entry["variants"][v] = {"error": str(exc)}
                scores[name][v] = float("inf")
                click.echo(f"{name} {v:17s} failed: {exc}")
                continue
            err = aligned_rmse(res["receivers"], anchors, res["sources"], tag)
            row: dict[str, Any] = {
                "anchor_rmse": err.rmse_receivers, "tag_rmse": err.rmse_sources,
                "residual_rms": res["residual_rms"], "method": res["method"],
                "receiver_offsets": res["receiver_offsets"], "converged": res["converged"],
                "n_dropped": res["n_dropped"],
            }
            row.update({k: res[k] for k in ("n_rejected", "common_offset", "profile") if k in res})
            entry["variants"][v] = row
            scores[name][v] = err.rmse_receivers
            ref = entry.get("authors_anchor_rmse")
            click.echo(f"{name} {v:17s} anchor RMSE {err.rmse_receivers:.3f} m  tag RMSE "
                       f"{err.rmse_sources:.3f} m" + (f"  (authors {ref:.3f} m)" if ref is not None else "")
                       + (f"  [{res['n_dropped']} positions dropped]" if res["n_dropped"] else ""))
            if v == RECOMMENDED:
                best = (err, res)
        (report["flights"] if name.startswith("data") or not name.startswith("sim") else report["simulated"])[name] = entry
        if best is not None:
            err, res = best
            plot_lps_flight(err.alignment.apply(res["receivers"]), err.alignment.apply(res["sources"]), anchors,
                            out / f"lps_{name}.png",
                            title=f"LPS {name} ({RECOMMENDED}): blind anchors, RMSE {err.rmse_receivers:.3f} m")
    real = [n for n in scores if not n.startswith("sim")]
    report["leave_one_flight_out"] = {
        "real_flights": leave_one_flight_out({n: scores[n] for n in real}, variants) if len(real) > 1 else None,
        "all_cases": leave_one_flight_out(scores, variants) if len(scores) > 1 else None,
    }
    write_json(out / "lps.json", report)
