"""Error bars of a fit to known nodes that hold on measured ranges (``fit_known(jackknife=True)``).

The model covariance of a constrained fit assumes independent range errors. Along a UWB
flight they are serially correlated and depend on where the tag is, and a per-anchor bias
the model does not hold is the same in every range of its anchor. Two corrections, used by
:func:`selfcal.toa.frame.known.fit_known`:

- :func:`jackknife_scaled`: each free receiver's covariance times ``max(1, tr(C^-1 V) / d)``,
  ``V`` the block jackknife covariance over contiguous column blocks
  (:func:`selfcal.toa.verdict.jackknife.block_jackknife_scale`);
- :func:`bias_effect`: with one common offset in the model, per-anchor biases as a random
  effect ``b_i ~ N(c, tau^2)`` (``tau^2`` by the method of moments from the per-anchor refit,
  0 unless the offsets spread beyond their noise, chi-square at level 0.05), carried to the
  receivers by the delta method, ``C_i += tau^2 G_i G_i^T``.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..verdict.jackknife import bias_effect, scaled_receiver_cov

__all__ = ["bias_effect", "jackknife_scaled"]

Array = NDArray[np.float64]


def jackknife_scaled(sol: Any, Y: Array, kw: dict[str, Any]) -> tuple[Any, Any]:
    """``sol`` with its receivers' covariances scaled by the block jackknife, and the scale (or None)."""
    from ..engine.nls import refine_toa

    if sol.receiver_cov is None or sol.residuals is None or not np.isfinite(sol.receiver_cov).all():
        return sol, None
    per_source = {"fixed_sources", "source_prior"}

    def cols_of(v: Any, cols: NDArray[np.bool_]) -> Any:
        return tuple(a[cols] for a in v) if isinstance(v, tuple) else np.asarray(v)[cols]

    def refit(cols: NDArray[np.bool_]) -> Array:
        fkw = {k: (cols_of(v, cols) if k in per_source else v) for k, v in kw.items()}
        so = None if sol.source_offsets is None else np.asarray(sol.source_offsets)[cols]
        return refine_toa(Y[:, cols], sol.receivers, sol.sources[cols], receiver_offsets0=sol.receiver_offsets,
                          source_offsets0=so, covariance=False, **fkw).receivers

    got = scaled_receiver_cov(sol, Y, kw, refit)
    if got is None:
        return sol, None
    cov, js = got
    return dataclasses.replace(sol, receiver_cov=cov), js
