"""Reproduction of paper 003 (Fig. 5-7).

Trials are module-level functions ``trial(params, seed) -> dict`` for
:func:`selfcal.experiments.run_sweep`. One trial draws a new 003 network (Table I),
initialises with Algorithm 2 ("MDS" in the paper's figures), refines by NLS from that
start, and reports the aligned receiver RMSE (eq. 18a) of both, with the gauge-free
CRLB of the same network for reference.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..metrics import aligned_rmse
from ..scenarios.toa import paper003_network

__all__ = [
    "PAPER_003",
    "trial_003",
    "summarise",
    "example_network",
]

Array = NDArray[np.float64]

# What the 003 text states (its figures did not survive conversion; no other numbers given).
PAPER_003 = {
    "nls_vs_noise": "NLS error close to linear in the noise level, roughly equal to the range error",
    "mds_saturation_m": 0.30,  # Fig. 7: MDS stabilises at ~30 cm with sigma = 30 cm
    "mds_floor_below_sigma_m": 0.10,  # Fig. 6: MDS stops improving below sigma ~ 10 cm
    "min_sources_for_robust": 6,
}


def trial_003(params: dict[str, Any], seed: int) -> dict[str, Any]:
    """One Monte-Carlo run of 003 sec. V-A.

    params: ``sigma`` (m), ``n_sources`` (K), optional ``n_sensors`` (N, default 8),
    ``dim`` (default 2). Returns ``mds_rmse`` / ``nls_rmse`` (receivers, eq. 18a),
    ``nls_src_rmse`` (eq. 18b), ``crlb_rmse`` (sqrt of the mean CRLB trace of the receivers),
    ``converged``.
    """
    from ..toa import solve_toa, toa_crlb
    from ..toa.init.mds import mds_alg2

    dim = int(params.get("dim", 2))
    sc = paper003_network(int(params.get("n_sensors", 8)), int(params["n_sources"]),
                          sigma=float(params["sigma"]), dim=dim, rng=seed)
    out: dict[str, Any] = {"mds_rmse": np.nan, "nls_rmse": np.nan, "nls_src_rmse": np.nan,
                           "crlb_rmse": np.nan, "converged": False}
    try:
        r0, s0 = mds_alg2(sc.ranges, dim)
    except Exception:  # a degenerate draw (e.g. K too small) counts as a failure
        return out
    out["mds_rmse"] = aligned_rmse(r0, sc.receivers).rmse_receivers
    try:
        res = solve_toa(sc.ranges, dim=dim, init=(r0, s0), method="nls", covariance=False)
        err = aligned_rmse(res.receivers, sc.receivers, res.sources, sc.sources)
        out.update(nls_rmse=err.rmse_receivers, nls_src_rmse=err.rmse_sources,
                   converged=bool(res.converged))
    except Exception:
        pass
    if sc.sigma > 0:
        try:
            out["crlb_rmse"] = toa_crlb(sc.receivers, sc.sources, sc.sigma).rmse_receivers
        except Exception:
            pass
    return out


def summarise(rows: Sequence[dict[str, Any]], key: str) -> list[dict[str, Any]]:
    """Per value of ``key``: RMS over runs (the paper's RMSE), median and 90th percentile."""
    out = []
    for v in sorted({r[key] for r in rows}):
        sub = [r for r in rows if r[key] == v]
        entry: dict[str, Any] = {key: v, "runs": len(sub)}
        for name in ("mds_rmse", "nls_rmse", "nls_src_rmse", "crlb_rmse"):
            x = np.array([r[name] for r in sub], float)
            x = x[np.isfinite(x)]
            entry[name] = float(np.sqrt(np.mean(x**2))) if x.size else None
            entry[name + "_median"] = float(np.median(x)) if x.size else None
            entry[name + "_p90"] = float(np.percentile(x, 90)) if x.size else None
        entry["failed"] = int(sum(not np.isfinite(r["nls_rmse"]) for r in sub))
        out.append(entry)
    return out


def example_network(seed: int = 0, sigma: float = 0.30) -> dict[str, Any]:
    """003 Fig. 5: one Table I network, NLS from Algorithm 2, with 95 % covariance ellipses.

    Returns estimate (aligned to the truth), truth and covariances (rotated with the
    alignment) for plotting, and the fraction of points inside their 95 % ellipse.
    """
    from scipy.stats import chi2

    from ..toa import solve_toa
    from ..toa.init.mds import mds_alg2

    sc = paper003_network(sigma=sigma, rng=seed)
    r0, s0 = mds_alg2(sc.ranges, 2)
    res = solve_toa(sc.ranges, dim=2, init=(r0, s0), method="nls")
    err = aligned_rmse(res.receivers, sc.receivers, res.sources, sc.sources)
    R = err.alignment.rotation
    rc = np.einsum("ij,njk,lk->nil", R, res.receiver_cov, R)
    scv = np.einsum("ij,njk,lk->nil", R, res.source_cov, R)
    er = err.alignment.apply(res.receivers)
    es = err.alignment.apply(res.sources)
    k95 = chi2.ppf(0.95, 2)

    def inside(e: Array, t: Array, c: Array) -> float:
        d = e - t
        m = np.einsum("ni,nij,nj->n", d, np.linalg.pinv(c), d)
        return float(np.mean(m <= k95))

    return {
        "receivers": er, "sources": es, "true_receivers": sc.receivers, "true_sources": sc.sources,
        "receiver_cov": rc, "source_cov": scv, "rmse_receivers": err.rmse_receivers,
        "rmse_sources": err.rmse_sources, "inside95_receivers": inside(er, sc.receivers, rc),
        "inside95_sources": inside(es, sc.sources, scv),
        "mean_trace_receivers": float(np.mean(np.trace(rc, axis1=1, axis2=2))),
        "mean_trace_sources": float(np.mean(np.trace(scv, axis1=1, axis2=2))),
    }
