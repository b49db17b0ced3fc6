"""Initialisers for anchor-free TOA calibration: MDS (paper 003) and a scalable rank method.

The range matrix has rows = receivers (sensors, ``s_n`` in 003) and columns =
transmitters (source positions, ``x_k`` in 003); entries are metres, NaN = missing.

Functions
---------
:func:`classical_mds`
    003 Algorithm 1 (eq. 7-9): double centring + truncated eigendecomposition.
:func:`estimate_receiver_distances`
    003 eq. 11: receiver-receiver distances from the reverse triangle inequality.
:func:`mds_alg2`
    003 Algorithm 2: MDS on eq. 11, then one extended MDS per source (eq. 13) aligned
    by Procrustes (eq. 14-15). Batched over sources with the same observation pattern.
:func:`rank_init`
    Rank factorisation of the double-centred squared-range matrix (Kuang, Burgess,
    Torstensson & Astrom 2013 style): rank-``d`` factorisation plus a *linear* upgrade,
    with low-rank completion of missing entries. ``O(I J d)``; scales to 1000 x 1000.
:func:`mds_multilateration`
    Receivers by MDS on eq. 11 (sub-sampled sources when large), then vectorised linear
    multilateration of every source.
:func:`initialize_toa`
    ``method="auto"`` runs the candidates that are affordable for the problem size and
    keeps the one with the smallest range residual.

Layout: one file per initialiser (:mod:`.mds_alg2`, :mod:`.multilat`, :mod:`.rank_init`),
their shared building blocks in :mod:`.mds_core`; this module is the selector and
re-exports every public name.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..._checks import as_rng, check_choice, check_dim
from ..._result import Result
from ...errors import DegenerateGeometryError
from ...geometry import canonical_gauge
from .mds_alg2 import mds_alg2
from .mds_core import (
    _validated_ranges,
    classical_mds,
    complete_distances,
    estimate_receiver_distances,
    multilaterate,
    range_residual_rms,
)
from .multilat import _EQ11_MAX_FLOPS, mds_multilateration
from .rank_init import rank_init

__all__ = [
    "INIT_METHODS",
    "InitResult",
    "classical_mds",
    "estimate_receiver_distances",
    "complete_distances",
    "mds_alg2",
    "rank_init",
    "mds_multilateration",
    "multilaterate",
    "range_residual_rms",
    "initialize_toa",
    "initialize_toa_info",
]

Array = NDArray[np.float64]

INIT_METHODS = ("auto", "alg2", "rank", "mds-multilat")

# Above this size the per-source eigendecompositions of Algorithm 2 (cost ~ J (I+1)^3) stop
# being cheap next to the rank method (the eq. 11 bound is in :mod:`.multilat`).
_ALG2_MAX_FLOPS = 3e7


# ---------------------------------------------------------------------------------------
# the entry point
# ---------------------------------------------------------------------------------------


@dataclass(frozen=True, repr=False)
class InitResult(Result):
    """An initial guess and how it was chosen.

    Follows the :class:`~selfcal._result.Result` convention (``status`` / ``success`` /
    ``message``, ``summary()``, ``to_dict()``); an initial guess carries no test of its
    own, so it is a success whenever it was produced.

    ``receivers`` (I, d) and ``sources`` (J, d) in metres, in selfcal's canonical gauge;
    ``method`` the candidate kept; ``residual_rms`` its range residual (metres);
    ``candidates`` the residual of every candidate tried (inf for a failed one).
    """

    receivers: Array
    sources: Array
    method: str
    residual_rms: float
    candidates: dict[str, float] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        """JSON-safe dict."""
        return {
            "receivers": self.receivers.tolist(),
            "sources": self.sources.tolist(),
            "method": self.method,
            "residual_rms": self.residual_rms,
            "candidates": dict(self.candidates),
        }


def _candidate_methods(shape: tuple[int, int], dim: int) -> list[str]:
    I, J = shape
    methods = ["rank"]
    if I * I * J <= _EQ11_MAX_FLOPS * 4:
        methods.append("mds-multilat")
    if J * (I + 1) ** 3 <= _ALG2_MAX_FLOPS:
        methods.append("alg2")
    return methods


def initialize_toa_info(ranges: Array, dim: int = 3, *, method: str = "auto",
                        rng: Any = None, shared: dict[str, Any] | None = None) -> InitResult:
    """Initial receivers and sources for anchor-free TOA calibration, with diagnostics.

    Parameters
    ----------
    ranges:
        (I, J) ranges in metres (rows = receivers, columns = transmitters), NaN = missing.
    dim:
        2 or 3.
    method:
        ``"alg2"`` (003 Algorithm 2), ``"rank"`` (:func:`rank_init`), ``"mds-multilat"``
        (:func:`mds_multilateration`) or ``"auto"``: every candidate affordable at this size
        (Algorithm 2 only while ``J (I+1)^3`` is small) and keep the smallest range residual.
    rng:
        Generator / seed for the randomized SVD and sub-sampling.
    shared:
        Optional dict, the same for every call on the same ``ranges`` (one search's): the eq. 11
        estimate (:func:`estimate_receiver_distances`, completed) that ``"alg2"`` and
        ``"mds-multilat"`` both start from is computed once and kept there under ``"eq11"``.

    Returns
    -------
    :class:`InitResult` in the canonical gauge (:func:`selfcal.geometry.canonical_gauge`).
    """
    dim = check_dim(dim)
    check_choice(method, "method", INIT_METHODS)
    Y = _validated_ranges(ranges, dim)
    gen = as_rng(rng)
    I, J = Y.shape
    methods = _candidate_methods(Y.shape, dim) if method == "auto" else [method]
    # large problems try only the rank method; the sub-sampled eq. 11 route is the fallback
    fallback = ["mds-multilat"] if method == "auto" and "mds-multilat" not in methods else []
    def eq11() -> Array | None:
        if shared is None:
            return None
        if "eq11" not in shared:
            shared["eq11"] = complete_distances(estimate_receiver_distances(Y))
        return shared["eq11"]

    funcs = {
        "alg2": lambda: mds_alg2(Y, dim, receiver_distances=eq11()),
        "rank": lambda: rank_init(Y, dim, rng=gen),
        "mds-multilat": lambda: mds_multilateration(
            Y, dim, rng=gen, receiver_distances=eq11() if I * I * J <= _EQ11_MAX_FLOPS else None),
    }
    scores: dict[str, float] = {}
    best: tuple[Array, Array] | None = None
    best_name = ""
    last_error: DegenerateGeometryError | None = None
    for name in methods + fallback:
        if name in fallback and best is not None:
            break
        try:
            with np.errstate(all="ignore"):
                r, s = funcs[name]()
        except (np.linalg.LinAlgError, FloatingPointError, ValueError) as exc:
            # a matrix no eigen/SVD routine can digest (e.g. one 1e300 entry): not a geometry
            exc = DegenerateGeometryError(f"initialiser {name!r} failed on this matrix ({exc}); check for "
                                          "absurd entries (solve_toa screens them)", kind="init-failed")
            if method != "auto":
                raise exc from None
            last_error = exc
            scores[name] = float("inf")
            continue
        except DegenerateGeometryError as exc:
            if method != "auto":
                raise
            last_error = exc
            scores[name] = float("inf")
            continue
        scores[name] = range_residual_rms(Y, r, s)
        if best is None or scores[name] < scores[best_name]:
            best, best_name = (r, s), name
    if best is None or not np.isfinite(scores[best_name]):
        if last_error is not None:
            raise last_error
        raise DegenerateGeometryError("no initialiser produced a finite geometry", kind="init-failed")
    r, s_opt, _ = canonical_gauge(best[0], best[1])
    assert s_opt is not None
    return InitResult(receivers=r, sources=s_opt, method=best_name, residual_rms=scores[best_name],
                      candidates=scores)


def initialize_toa(ranges: Array, dim: int = 3, *, method: str = "auto",
                   rng: Any = None, shared: dict[str, Any] | None = None) -> tuple[Array, Array]:
    """Initial (receivers (I, dim), sources (J, dim)) for the TOA NLS; see :func:`initialize_toa_info`.

    This is what :func:`selfcal.toa.solve_toa` calls for ``init="auto"``; noise-free data
    gives the exact geometry (up to a rigid motion) for ``"rank"`` and, with enough sources
    around the receivers, a start from which the NLS converges for every method.
    """
    res = initialize_toa_info(ranges, dim, method=method, rng=rng, shared=shared)
    return res.receivers, res.sources
