"""LPS real-data trials: calibration variants, simulated UWB flights, leave-one-flight-out.

Trials and summaries only; the recipe users run lives in :mod:`selfcal.toa.recipes.recipes`
(``calibrate toa --recipe moving-tag``). Every variant is blind: it sees the range
matrix only (no ground truth, no authors' estimate).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
from numpy.typing import NDArray

__all__ = [
    "RECOMMENDED",
    "calibrate_lps",
    "leave_one_flight_out",
    "lps_variants",
    "simulate_uwb_flight",
]

Array = NDArray[np.float64]

# the variant ``selfcal reproduce lps`` plots and recommends: chosen by principle, not by
# its score on the shared flights (see selfcal.toa.recipes.recipes): spike rejection only
RECOMMENDED = "clean"


def lps_variants() -> tuple[str, ...]:
    """Names of the calibration variants compared on LPS (see :func:`calibrate_lps`)."""
    return ("none", "none-huber", "receivers-huber", "clean", "clean-huber", "clean-profile",
            "clean-profile-mad", "profile")


def calibrate_lps(ranges: Array, variant: str = "none", *, rng: int = 0) -> dict[str, Any]:
    """Blind anchor-free calibration of one LPS flight (no ground truth, no authors' estimate).

    Tag positions (columns) with fewer than 4 observed ranges cannot be located in 3-D and
    are dropped first by every variant (``n_dropped``; NaN rows in ``sources``).

    Variants
    --------
    ``none``             offsets="none", linear loss (003 eq. 2), started by ``initialize_toa``
                         (negative raw ranges clipped to 0 for this model).
    ``none-huber``       the same with a Huber loss (the UWB ranges have outliers).
    ``receivers-huber``  per-anchor offsets (ranging bias) + Huber loss, started from ``none``
                         with zero offsets.
    ``clean``            the moving-tag recipe (:func:`selfcal.toa.recipes.recipes.moving_tag`):
                         multipath spikes removed in time (robust local quadratic, one-sided
                         at the Bonferroni threshold of :func:`~selfcal.toa.recipes.recipes.spike_threshold`,
                         the recipe's defaults), then ``none``. The recommended variant.
    ``clean-huber``      ``clean`` with a Huber loss.
    ``clean-profile``    ``clean``, then per-anchor offsets whose common component is chosen
                         by :func:`selfcal.toa.recipes.preprocess.fit_offsets_profile_common` (minimum
                         over the common offset of the trimmed RMS of the 70 % smallest
                         residuals).
    ``clean-profile-mad`` the same, profiling the MAD instead (ablation).
    ``profile``          the trimmed profile on the raw ranges (ablation).

    Returns receivers (6, 3), sources (N, 3), receiver_offsets or None, residual_rms,
    method, converged, n_dropped, and for the cleaning variants ``n_rejected`` /
    ``common_offset``.
    """
    from .._checks import check_choice
    from ..toa import solve_toa
    from ..toa.init.mds import initialize_toa_info
    from ..toa.recipes.preprocess import fit_offsets_profile_common, reject_range_outliers

    check_choice(variant, "variant", lps_variants())
    Y = np.asarray(ranges, float)
    extra: dict[str, Any] = {}
    keep = np.isfinite(Y).sum(axis=0) >= 4
    extra["n_dropped"] = int((~keep).sum())
    if variant.startswith("clean"):
        # the moving-tag recipe's defaults: one-sided (a blocked or reflected path only
        # lengthens a range), at the solver's Bonferroni false-alarm rule
        from ..toa.recipes.recipes import spike_threshold

        rej = reject_range_outliers(Y, threshold=spike_threshold(Y, True), one_sided=True)
        extra["n_rejected"] = rej.n_rejected
        keep &= np.isfinite(rej.ranges).sum(axis=0) >= 4
        extra["n_dropped"] = int((~keep).sum())
        Y = rej.ranges[:, keep]
    else:
        Y = Y[:, keep]
    Yc = np.where(np.isnan(Y), np.nan, np.maximum(Y, 0.0))
    info = initialize_toa_info(Yc, 3, rng=rng)
    base = solve_toa(Yc, dim=3, init=(info.receivers, info.sources), method="nls", covariance=False,
                     loss="linear")
    res: Any
    if variant in ("none", "clean"):
        res = base
    elif variant in ("none-huber", "clean-huber"):
        res = solve_toa(Yc, dim=3, loss="huber", init=(base.receivers, base.sources), method="nls",
                        covariance=False)
    elif variant == "receivers-huber":
        res = solve_toa(Y, dim=3, offsets="receivers", loss="huber",
                        init=(base.receivers, base.sources, np.zeros(Y.shape[0]), None),
                        method="nls", covariance=False)
    else:  # clean-profile, clean-profile-mad, profile
        scale = "mad" if variant.endswith("-mad") else "trimmed"
        res = fit_offsets_profile_common(Y, base.receivers, base.sources, scale=scale)
        extra["common_offset"] = res.common
        extra["profile"] = {"grid": res.grid.tolist(), "scale": res.profile.tolist(), "kind": scale}
    sources = np.full((keep.size, 3), np.nan)
    sources[keep] = res.sources
    return {
        "receivers": res.receivers, "sources": sources,
        "receiver_offsets": res.receiver_offsets, "residual_rms": float(res.residual_rms),
        "method": f"{info.method}+{res.method}", "converged": bool(res.converged), **extra,
    }


def simulate_uwb_flight(
    seed: int,
    n_positions: int = 400,
    *,
    bias_mean: float = -0.17,
    bias_std: float = 0.05,
    noise: float = 0.04,
    spike_rate: float = 0.05,
    spike_mean: float = 0.4,
    missing: float = 0.005,
    sparse_positions: int = 2,
    layout: str = "room",
    noise_corr: float = 0.0,
    nlos_rate: float = 0.0,
    nlos_mean: float = 0.3,
) -> dict[str, Array]:
    """A simulated LPS-like flight: 6 UWB anchors, one tag on a smooth trajectory.

    Model (documented for the LPS system, shared/data/README.md): per-anchor ranging bias
    ``b_i ~ N(bias_mean, bias_std^2)``, Gaussian noise, multipath / NLOS returns as
    positive spikes (probability ``spike_rate`` per range, exponential length excess of
    mean ``spike_mean``, in short bursts of 1-3 samples), missing ranges, and a few tag
    positions with only 2 ranges.

    Options for the faults of issue 12's trials (all off by default, so a seed draws the
    same flight as before):

    - ``layout="room"``: anchors near the corners of an 8 x 6 x 3 m room, the tag in its
      interior (ranges 2.4-6.8 m: a common range offset is barely separable from the
      scale); ``"lps"``: the Lund LPS geometry, anchors in a ~2.4 x 2.0 x 1.2 m volume and
      the tag flying through and around it (ranges ~0.2-3.5 m, as on data4 / data5).
    - ``noise_corr``: AR(1) coefficient of the range noise along time (marginal std
      ``noise``); the residuals of the measured flights have lag-1 autocorrelation ~0.8.
    - ``nlos_rate``: per anchor and sample, the rate at which a non-line-of-sight segment
      starts (10-40 consecutive samples with one positive excess ~ Exp(``nlos_mean``)).

    Returns
    -------
    dict with ``ranges`` (6, N), ``anchors`` (6, 3), ``tag`` (N, 3), ``bias`` (6,),
    ``spikes`` (6, N) bool.
    """
    from .._checks import check_choice

    check_choice(layout, "layout", ("room", "lps"))
    rng = np.random.default_rng(seed)
    box = np.array([8.0, 6.0, 3.0]) if layout == "room" else np.array([2.4, 2.0, 1.2])
    # anchors near the walls / corners at mixed heights (a 3-D, non-coplanar set)
    corners = np.array([[0, 0, 0], [1, 0, 1], [1, 1, 0], [0, 1, 1], [0.5, 0, 0.9], [0.5, 1, 0.1]], float)
    anchors = (corners + rng.uniform(-0.08, 0.08, corners.shape)).clip(0, 1) * box
    t = np.linspace(0, 1, n_positions)
    tag = np.zeros((n_positions, 3))
    for a in range(3):
        f = rng.uniform(1, 4, 3)
        ph = rng.uniform(0, 2 * np.pi, 3)
        amp = rng.uniform(0.1, 0.3, 3)
        tag[:, a] = (0.5 + (amp[:, None] * np.sin(2 * np.pi * f[:, None] * t + ph[:, None])).sum(0) / 2)
    if layout == "room":
        tag = (0.15 + 0.7 * tag.clip(0, 1)) * box
    else:  # through and around the anchor volume (1.3x its size), as the LPS drone flies
        tag = (0.5 + 1.86 * (tag.clip(0, 1) - 0.5)) * box
    D = np.linalg.norm(anchors[:, None] - tag[None], axis=2)
    bias = rng.normal(bias_mean, bias_std, 6)
    white = rng.standard_normal(D.shape)
    if noise_corr:
        from scipy.signal import lfilter

        white = lfilter([np.sqrt(1 - noise_corr**2)], [1.0, -noise_corr], white, axis=1)
    Y = D + bias[:, None] + noise * white
    spikes = np.zeros(D.shape, bool)
    starts = rng.random(D.shape) < spike_rate / 2
    for i, j in zip(*np.nonzero(starts), strict=True):
        spikes[i, j : j + rng.integers(1, 4)] = True
    Y[spikes] += rng.exponential(spike_mean, int(spikes.sum()))
    Y[rng.random(D.shape) < missing] = np.nan
    for j in rng.choice(n_positions, sparse_positions, replace=False):
        Y[rng.choice(6, 4, replace=False), j] = np.nan
    if nlos_rate:
        g = np.random.default_rng([seed, 1])
        for i, j in zip(*np.nonzero(g.random(D.shape) < nlos_rate), strict=True):
            seg = slice(j, j + int(g.integers(10, 41)))
            Y[i, seg] += g.exponential(nlos_mean)
            spikes[i, seg] = True
    return {"ranges": Y, "anchors": anchors, "tag": tag, "bias": bias, "spikes": spikes}


def leave_one_flight_out(scores: Mapping[str, Mapping[str, float]],
                         candidates: Sequence[str]) -> dict[str, Any]:
    """Leave-one-flight-out selection among ``candidates``.

    ``scores[flight][variant]`` is the anchor RMSE. For each held-out flight, the variant
    with the smallest median RMSE over the *other* flights is selected and scored on the
    held-out one. Returns per held-out flight the selected variant and its score, and the
    median held-out score of the selection rule.
    """
    flights = list(scores)
    rows: dict[str, dict[str, Any]] = {}
    for f in flights:
        others = [g for g in flights if g != f]
        med = {v: float(np.median([scores[g][v] for g in others])) for v in candidates}
        pick = min(candidates, key=lambda v: med[v])
        rows[f] = {"selected": pick, "held_out_rmse": float(scores[f][pick])}
    held = [float(r["held_out_rmse"]) for r in rows.values()]
    return {"per_flight": rows, "median_held_out_rmse": float(np.median(held)) if held else None}


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

    from ..datasets.lps import load_lps, lps_files

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

    from ..metrics import aligned_rmse
    from ..toa.recipes.recipes import moving_tag

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

    from ..metrics import aligned_rmse
    from ..toa.recipes.common_offset import block_offset_test
    from ..toa.recipes.recipes import moving_tag

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
            from ..datasets.lps import load_lps

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

    from ..metrics import aligned_rmse
    from ..toa.engine.nls import refine_toa
    from ..toa.recipes.common_offset import choose_common_offset
    from ..toa.recipes.recipes import moving_tag
    from ..toa.verdict.crossval import choose_receiver_offsets

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
