"""The focused criterion for two nested offsets models: which gives the more accurate receivers.

Held-out prediction (:mod:`selfcal.toa.verdict.crossval`) judges ranges; this module judges
what the user of an anchor calibration wants, the receivers' mean squared error, from the
refits the cross-validation already made (Claeskens & Hjort 2003). Used by
:func:`selfcal.toa.verdict.crossval.choose_receiver_offsets` (the anchor check).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

__all__ = ["AnchorMse", "anchor_mse"]

Array = NDArray[np.float64]


@dataclass(frozen=True)
class AnchorMse:
    """Estimated mean squared error of the receivers under a simple and a wider offsets model.

    From :func:`anchor_mse`; metres, per receiver (totals divided by the number of
    receivers, then square-rooted).

    Attributes
    ----------
    rmse : dict
        Model -> estimated RMS receiver error ``sqrt(MSE / I)``.
    shift : float
        RMS difference between the two models' receivers (after a rigid alignment).
    shift_noise : float
        Its delete-a-block jackknife RMS: the shift expected if the simple model were right.
    spread : dict
        Model -> jackknife RMS of its receivers over the folds (its variance part).
    """

    rmse: dict[str, float]
    shift: float
    shift_noise: float
    spread: dict[str, float]

    def to_dict(self) -> dict[str, Any]:
        """JSON-safe dictionary."""
        return {"estimator": "focused (Claeskens & Hjort 2003): simple = max(0, shift^2 - noise^2) + spread^2, "
                             "wide = spread^2, from the delete-a-block refits of the cross-validation",
                "rmse": dict(self.rmse), "shift": self.shift, "shift_noise": self.shift_noise,
                "spread": dict(self.spread)}


def anchor_mse(simple: str, wide: str, starts: Mapping[str, tuple[Any, ...]],
               refits: Mapping[str, Sequence[Array]]) -> AnchorMse | None:
    """Which of two nested offsets models gives the more accurate receivers: their estimated MSE.

    Held-out prediction judges ranges, not receivers. Where a per-receiver offset trades
    against the receiver's distance to a tag that stays on one side of it (LPS flights:
    ``d_i`` and the radial coordinate move ranges almost alike), the wider model predicts
    held-out ranges as well or better by moving receivers and offsets together, and its
    receivers can be far worse (LPS data4: CV RMS 0.1595 vs 0.1690 m, anchor RMSE 0.309 vs
    0.166 m). The focused criterion (Claeskens & Hjort 2003) compares what the user wants,
    the receivers' mean squared error:

    - ``MSE_wide = V_wide``, the wide model taken as unbiased;
    - ``MSE_simple = max(0, |R_simple - R_wide|^2 - V_diff) + V_simple``: its squared bias
      estimated by the squared shift between the two fits less the shift's own variance;

    every ``V`` the delete-a-block jackknife variance ``(K - 1) / K sum_k |x_k - mean x|^2``
    over the K refits the cross-validation already made (each without one block of
    sources: serially correlated and position-dependent errors are in it, the model
    covariance would miss them). Receivers are compared after the best rigid motion
    (Kabsch, no reflection), so the gauge is not counted as error.

    Parameters
    ----------
    simple, wide : str
        The two models (keys of ``starts`` and ``refits``).
    starts : mapping
        Model -> ``(receivers (I, d), ...)`` fit on all sources.
    refits : mapping
        Model -> the K fold refits' receivers ((I, d) arrays), the same folds for both.

    Returns
    -------
    AnchorMse or None
        None when a model has fewer than 2 refits or non-finite receivers.

    References
    ----------
    Claeskens, G. & Hjort, N. L. (2003). The focused information criterion. JASA 98, 900-916.

    Examples
    --------
    Refits without spread: the wide model's estimated error is 0, the simple one's its shift.

    >>> import numpy as np
    >>> R = np.random.default_rng(0).uniform(0, 3, (6, 3))
    >>> W = R + 0.1 * (np.arange(6) % 2)[:, None] - 0.05
    >>> est = anchor_mse("common", "receivers", {"common": (R,), "receivers": (W,)},
    ...                  {"common": [R] * 4, "receivers": [W] * 4})
    >>> round(est.rmse["receivers"], 6), bool(np.isclose(est.rmse["common"], est.shift))
    (0.0, True)
    """
    from ...geometry import align

    a, b = refits.get(simple, []), refits.get(wide, [])
    K = min(len(a), len(b))
    if K < 2:
        return None
    Rs, Rw = (np.asarray(starts[m][0], float) for m in (simple, wide))
    if not (np.isfinite(Rs).all() and np.isfinite(Rw).all()
            and all(np.isfinite(x).all() for x in (*a[:K], *b[:K]))):
        return None
    I = Rs.shape[0]

    def onto(X: Array, ref: Array) -> Array:
        return align(X, ref, reflection=False).apply(X)

    def jvar(X: Array) -> float:
        D = X - X.mean(axis=0)
        return float((K - 1) / K * np.sum(D * D))

    shift2 = float(np.sum((Rs - onto(Rw, Rs)) ** 2))
    vd = jvar(np.array([np.asarray(x) - onto(np.asarray(y), np.asarray(x)) for x, y in zip(a[:K], b[:K], strict=True)]))
    vs = jvar(np.array([onto(np.asarray(x), Rs) for x in a[:K]]))
    vw = jvar(np.array([onto(np.asarray(y), Rw) for y in b[:K]]))
    mse = {simple: max(0.0, shift2 - vd) + vs, wide: vw}
    return AnchorMse({m: float(np.sqrt(v / I)) for m, v in mse.items()}, float(np.sqrt(shift2 / I)),
                     float(np.sqrt(vd / I)), {simple: float(np.sqrt(vs / I)), wide: float(np.sqrt(vw / I))})
