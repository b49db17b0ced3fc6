"""Research trials of issues 12, 16 and 29 on LPS flights and simulated ones (not part of the package).

- moving-tag recipe variants (spike-rejection threshold, one- or two-sided, loss, offsets) on
  every LPS flight of a folder plus simulated ones (:data:`RECIPE_VARIANTS`,
  :func:`score_recipe_variants`; docs/results.md, "Results on real data");
- the common-offset block test on one simulated fault or LPS file (:data:`COMMON_OFFSET_FAULTS`,
  :func:`score_common_offset`);
- the bias-model trial of issue 29 (:data:`BIAS_MODEL_FAULTS`, :func:`score_bias_model`).

Run: ``PYTHONPATH=src python benchmarks/lps_variants.py --data ../shared/data/lps --simulate 3`` or
``... --common-offset-trial lps-pa:0``.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
from numpy.typing import NDArray

from selfcal.experiments.lps import simulate_uwb_flight

Array = NDArray[np.float64]


#: spike-rejection / fit variants of the ``moving-tag`` recipe scored by
#: :func:`score_recipe_variants` (keyword arguments of :func:`selfcal.toa.recipes.recipes.moving_tag`)
RECIPE_VARIANTS: dict[str, dict[str, Any]] = {
    "2s-3.5": {"threshold": 3.5, "one_sided": False},
    "1s-3.5": {"threshold": 3.5, "one_sided": True},
    "2s-bonf": {"threshold": "bonferroni", "one_sided": False},
    "1s-bonf": {"threshold": "bonferroni", "one_sided": True},
    "1s-bonf-huber": {"threshold": "bonferroni", "one_sided": True, "loss": "huber"},
    "1s-bonf-receivers": {"threshold": "bonferroni", "one_sided": True, "offsets": "receivers"},
}


def lps_cases(data: str, n_sim: int, n_positions: int = 400) -> dict[str, tuple[Array, Array]]:
    """``{name: (ranges (6, N), true anchors (6, 3))}``: the LPS flights in ``data`` + simulated ones."""
    from pathlib import Path

    from selfcal.datasets.lps import load_lps, lps_files

    out: dict[str, tuple[Array, Array]] = {}
    for f in lps_files(Path(data)) if data else []:
        fl = load_lps(f)
        out[fl.name] = (fl.ranges, fl.anchors_true)
    for k in range(n_sim):
        sim = simulate_uwb_flight(k, n_positions=n_positions)
        out[f"sim{k}"] = (sim["ranges"], sim["anchors"])
    return out


def score_recipe_variant(ranges: Array, anchors: Array, variant: str, *, rng: int = 0) -> dict[str, Any]:
    """Anchor RMSE after rigid alignment of ``moving_tag(ranges, **RECIPE_VARIANTS[variant])``.

    Exactly what ``calibrate toa`` runs with ``--recipe moving-tag`` and the options of the
    variant. Returns rmse (m), exit status the CLI would give (0 / 1), rejected count,
    threshold, residual sum of squares and count (for an information criterion), CPU s.
    """
    import time
    import warnings

    from selfcal.metrics import aligned_rmse
    from selfcal.toa.recipes.recipes import moving_tag

    t0 = time.process_time()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        res = moving_tag(ranges, rng=rng, **RECIPE_VARIANTS[variant])
    cpu = time.process_time() - t0
    R = np.asarray(res.result.residuals, float)
    used = np.isfinite(R) & ~np.asarray(res.result.outliers, bool)
    return {
        "rmse": float(aligned_rmse(res.receivers, anchors).rmse_receivers),
        "success": bool(res.result.success), "n_rejected": res.n_rejected,
        "n_outliers": int(np.asarray(res.result.outliers).sum()),
        "threshold": res.details["threshold"], "rss": float(np.sum(R[used] ** 2)), "m": int(used.sum()),
        "cpu_s": round(cpu, 1),
    }


def score_recipe_variants(data: str, n_sim: int, variants: Sequence[str] | None = None,
                          cases: Sequence[str] | None = None) -> dict[str, dict[str, dict[str, Any]]]:
    """Every variant on every case (``{case: {variant: score_recipe_variant(...)}}``), printed as it goes."""
    import json

    table: dict[str, dict[str, dict[str, Any]]] = {}
    all_cases = {k: v for k, v in lps_cases(data, n_sim).items() if not cases or k in cases}
    for v in variants or list(RECIPE_VARIANTS):  # variant-major: every case of a variant first
        for name, (Y, A) in all_cases.items():
            row = score_recipe_variant(Y, A, v)
            table.setdefault(name, {})[v] = row
            print(json.dumps({"case": name, "variant": v, **row}), flush=True)
    return table


#: the common-offset trial's simulated faults (keyword arguments of simulate_uwb_flight)
COMMON_OFFSET_FAULTS: dict[str, dict[str, Any]] = {
    "lps-pa": {"layout": "lps", "n_positions": 500},
    "lps-common": {"layout": "lps", "n_positions": 500, "bias_std": 0.0},
    "lps-none": {"layout": "lps", "n_positions": 500, "bias_std": 0.0, "bias_mean": 0.0},
    "lps-none_ar": {"layout": "lps", "n_positions": 500, "bias_std": 0.0, "bias_mean": 0.0, "noise_corr": 0.8},
    "lps-pa_ar": {"layout": "lps", "n_positions": 500, "noise_corr": 0.8},
    "lps-pa_nlos": {"layout": "lps", "n_positions": 500, "nlos_rate": 0.002},
    "room-pa": {"n_positions": 400},
    "room-common": {"n_positions": 400, "bias_std": 0.0},
    "room-none": {"n_positions": 400, "bias_std": 0.0, "bias_mean": 0.0},
}


def score_common_offset(ranges: Array, anchors: Array, *, rng: int = 0) -> dict[str, Any]:
    """The moving-tag recipe without the common offset, then its block test (both fits scored).

    Returns the anchor RMSE without and with the common offset (whatever the test says),
    the test's decision at its level and its numbers (:func:`selfcal.toa.recipes.common_offset.block_offset_test`),
    so that other levels can be read off the p-value.
    """
    import warnings

    from selfcal.metrics import aligned_rmse
    from selfcal.toa.recipes.common_offset import block_offset_test
    from selfcal.toa.recipes.recipes import moving_tag

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        res = moving_tag(ranges, rng=rng, common_offset="free")
        keep = np.isfinite(res.result.sources).all(axis=1)
        sub = np.where(res.rejected, np.nan, np.asarray(ranges, float))[:, keep]
        base = _Columns(res.result, keep)
        com, info = block_offset_test(base, sub)
    r0 = float(aligned_rmse(res.receivers, anchors).rmse_receivers)
    r1 = float(aligned_rmse(com.receivers, anchors).rmse_receivers) if com is not None else float("nan")
    return {"rmse_without": r0, "rmse_with": r1, **{k: v for k, v in info.items() if k != "replicates"}}


class _Columns:
    """The kept columns of a result, as :func:`block_offset_test` reads them."""

    def __init__(self, res: Any, keep: NDArray[np.bool_]) -> None:
        self.receivers = res.receivers
        self.sources = res.sources[keep]
        self.residuals = res.residuals[:, keep]
        self.outliers = np.asarray(res.outliers, bool)[:, keep]
        self.dim = res.dim


#: the bias-model trial's simulated faults (issue 29; keyword arguments of simulate_uwb_flight)
BIAS_MODEL_FAULTS: dict[str, dict[str, Any]] = {
    "lps-pa10": {"layout": "lps", "n_positions": 500, "bias_std": 0.1},
    "lps-pa15": {"layout": "lps", "n_positions": 500, "bias_std": 0.15},
    "lps-none": {"layout": "lps", "n_positions": 500, "bias_std": 0.0, "bias_mean": 0.0},
    "lps-common": {"layout": "lps", "n_positions": 500, "bias_std": 0.0},
    "lps-none_nlos": {"layout": "lps", "n_positions": 500, "bias_std": 0.0, "bias_mean": 0.0, "nlos_rate": 0.002},
    "lps-pa10_ar_nlos": {"layout": "lps", "n_positions": 500, "bias_std": 0.1, "noise_corr": 0.8,
                         "nlos_rate": 0.002},
    "room-pa15": {"n_positions": 400, "bias_std": 0.15},
    "room-none": {"n_positions": 400, "bias_std": 0.0, "bias_mean": 0.0},
}


def score_bias_model(ranges: Array, anchors: Array, *, rng: int = 0) -> dict[str, Any]:
    """The moving-tag recipe's offsets chain with both anchor models scored against the truth.

    The offsets-free fit, the common-offset block test, then the held-out choice of
    per-anchor offsets (:func:`selfcal.toa.verdict.crossval.choose_receiver_offsets`); returns the
    choice, its CV RMS prediction errors and the anchor RMSE (m, after rigid alignment) of
    the kept simple model and of the per-anchor refit whatever the choice.
    """
    import dataclasses
    import warnings

    from selfcal.metrics import aligned_rmse
    from selfcal.toa.engine.nls import refine_toa
    from selfcal.toa.recipes.common_offset import choose_common_offset
    from selfcal.toa.recipes.recipes import moving_tag
    from selfcal.toa.verdict.crossval import choose_receiver_offsets

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        rr = moving_tag(ranges, common_offset="free", rng=rng)
        keep = np.isfinite(rr.result.sources).all(axis=1)
        sub = np.where(rr.rejected, np.nan, np.asarray(ranges, float))[:, keep]
        base = dataclasses.replace(rr.result, sources=rr.result.sources[keep],
                                   residuals=rr.result.residuals[:, keep],
                                   outliers=np.asarray(rr.result.outliers)[:, keep],
                                   source_cov=rr.result.source_cov[keep])
        simple, test = choose_common_offset(base, sub)
        out, cv = choose_receiver_offsets(simple, sub)
        used = np.isfinite(simple.residuals) & ~np.asarray(simple.outliers, bool)
        d0 = None if simple.receiver_offsets is None else np.asarray(simple.receiver_offsets, float)
        alt = refine_toa(np.where(used, sub, np.nan), simple.receivers, simple.sources, offsets="receivers",
                         receiver_offsets0=d0, covariance=False)
    return {"common_adopted": bool(test["adopted"]), "chosen": out.offsets,
            "best_cv": None if cv is None else cv.best,
            "cv_rmse": {} if cv is None else cv.to_dict()["cv_rmse"],
            "rmse_simple": float(aligned_rmse(simple.receivers, anchors).rmse_receivers),
            "rmse_receivers": float(aligned_rmse(alt.receivers, anchors).rmse_receivers)}


if __name__ == "__main__":  # pragma: no cover - the experiment of the issue-12 report
    import argparse

    ap = argparse.ArgumentParser(description="moving-tag recipe variants on LPS flights + simulated ones")
    ap.add_argument("--data", default="", help="LPS folder or .mat file")
    ap.add_argument("--simulate", type=int, default=3)
    ap.add_argument("--variants", default="", help="comma-separated subset of RECIPE_VARIANTS")
    ap.add_argument("--cases", default="", help="comma-separated subset of the cases")
    ap.add_argument("--common-offset-trial", default="", metavar="FAULT:SEED",
                    help="score the common-offset block test on one case (a COMMON_OFFSET_FAULTS key "
                         "and seed, or an LPS .mat file) and exit")
    a = ap.parse_args()
    if a.common_offset_trial:
        import json

        if a.common_offset_trial.endswith(".mat"):
            from selfcal.datasets.lps import load_lps

            fl = load_lps(a.common_offset_trial)
            Y, A = fl.ranges, fl.anchors_true
        else:
            fault, seed = a.common_offset_trial.split(":")
            sim = simulate_uwb_flight(int(seed), **COMMON_OFFSET_FAULTS[fault])
            Y, A = sim["ranges"], sim["anchors"]
        print(json.dumps({"case": a.common_offset_trial, **score_common_offset(Y, A)}))
        raise SystemExit(0)
    score_recipe_variants(a.data, a.simulate, [v for v in a.variants.split(",") if v] or None,
                          [c for c in a.cases.split(",") if c] or None)
