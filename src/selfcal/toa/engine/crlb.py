"""Cramér-Rao lower bound of anchor-free TOA self-calibration (gauge-free).

For Gaussian range noise ``y_ij = |r_i - s_j| + d_i + o_j + e_ij``,
``e_ij ~ N(0, sigma_ij^2)`` (003 eq. 1), the Fisher information of all unknowns
is ``F = J^T Sigma^-1 J`` with J the Jacobian of the model (003 eq. 16). F is
singular along the rigid motions (and the common offset shift), so the bound is
taken on the gauge-free part: ``F^+`` (the Moore-Penrose inverse, i.e. the bound
for estimators expressed in the minimum-norm gauge). The bound on aligned errors
therefore is ``tr`` of the per-point blocks of ``F^+``; it is the covariance the
NLS reaches asymptotically (003 eq. 17 at the true geometry), so
``RMSE / sqrt(mean trace)`` is an efficiency.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..._checks import as_points, check_choice
from ..._result import Result
from ...errors import InputError
from .covariance import covariance_blocks, is_local, normalize_covariance
from .model import OFFSET_MODES, _flags

__all__ = ["CrlbResult", "toa_crlb"]

Array = NDArray[np.float64]


@dataclass(frozen=True, repr=False)
class CrlbResult(Result):
    """Gauge-free CRLB of every point and offset (metres, metres^2).

    Follows the :class:`~selfcal._result.Result` convention (``status`` / ``success`` /
    ``message``, ``summary()``, ``to_dict()``); a bound has no iteration or test, so it is
    always a success. ``receiver_cov`` / ``source_cov`` are the convention's names for the
    position bounds (aliases of ``receiver_bounds`` / ``source_bounds``).

    Attributes
    ----------
    receiver_bounds, source_bounds: (I, d, d), (J, d, d) covariance bounds.
    receiver_offset_var, source_offset_var: (I,), (J,) offset variance bounds or None.
    receiver_trace, source_trace: (I,), (J,) traces of the position blocks (m^2).
    rmse_receivers, rmse_sources: ``sqrt(mean trace)``, the bound on the RMSE of
        003 eq. 18 (without the alignment's own small gain).
    """

    receiver_bounds: Array
    source_bounds: Array
    receiver_offset_var: Array | None
    source_offset_var: Array | None
    receiver_trace: Array
    source_trace: Array
    rmse_receivers: float
    rmse_sources: float

    @property
    def receiver_cov(self) -> Array:
        """(I, d, d) receiver position bounds (m^2), the convention's name for ``receiver_bounds``."""
        return self.receiver_bounds

    @property
    def source_cov(self) -> Array:
        """(J, d, d) source position bounds (m^2), the convention's name for ``source_bounds``."""
        return self.source_bounds

    def to_dict(self) -> dict[str, Any]:
        """JSON-safe dict (arrays as lists)."""
        def tl(a: Array | None) -> Any:
            return None if a is None else np.asarray(a).tolist()

        return {
            "receiver_bounds": tl(self.receiver_bounds),
            "source_bounds": tl(self.source_bounds),
            "receiver_offset_var": tl(self.receiver_offset_var),
            "source_offset_var": tl(self.source_offset_var),
            "receiver_trace": tl(self.receiver_trace),
            "source_trace": tl(self.source_trace),
            "rmse_receivers": self.rmse_receivers,
            "rmse_sources": self.rmse_sources,
        }


def toa_crlb(
    receivers: Array,
    sources: Array,
    sigma: float | Array,
    *,
    offsets: str = "none",
    mask: Array | None = None,
    covariance: Any = "all",
) -> CrlbResult:
    """Gauge-free Cramér-Rao bound ``(J^T Sigma^-1 J)^+`` for the TOA network (003 eq. 17 at the truth).

    Parameters
    ----------
    receivers, sources: (I, d), (J, d) true positions, metres.
    sigma: range noise std in metres, a scalar or an (I, J) matrix (per entry).
    offsets: "none" | "receivers" | "sources" | "both" - which offsets are unknown
        (their values do not enter the bound).
    mask: optional (I, J) boolean, True where a range is observed (default all).
    covariance: which blocks to compute ("all", "receivers", "sources" or indices, as in
        :func:`selfcal.toa.engine.covariance.normalize_covariance`); the others are NaN and the
        traces / RMSE bounds are then over the computed blocks only.

    Returns
    -------
    CrlbResult with the per-point (d, d) blocks; computed by the selected inversion of
    :mod:`selfcal.toa.engine.covariance` (one factorization of the Schur-reduced Fisher matrix,
    O(min(I,J)^2 max(I,J)) time for every block), the same path as the NLS covariances.

    Examples
    --------
    >>> import numpy as np
    >>> rng = np.random.default_rng(1)
    >>> b = toa_crlb(rng.uniform(0, 5, (8, 3)), rng.uniform(0, 5, (10, 3)), 0.01)
    >>> b.receiver_bounds.shape
    (8, 3, 3)
    """
    check_choice(offsets, "offsets", OFFSET_MODES)
    r = as_points(receivers, "receivers")
    d = r.shape[1]
    s = as_points(sources, "sources", dim=d)
    I, J = r.shape[0], s.shape[0]
    sig = np.broadcast_to(np.asarray(sigma, dtype=float), (I, J)) if np.ndim(sigma) == 0 else np.asarray(sigma, float)
    if sig.shape != (I, J) or not np.isfinite(sig).all() or (sig <= 0).any():
        raise InputError(f"sigma must be a positive scalar or an ({I}, {J}) array of positive stds")
    m = np.ones((I, J), bool) if mask is None else np.asarray(mask, bool)
    if m.shape != (I, J):
        raise InputError(f"mask must have shape ({I}, {J}), got {m.shape}")
    has_r, has_s = _flags(offsets)
    if is_local(normalize_covariance(covariance)):
        raise InputError("toa_crlb: covariance='local' is an approximation, not a bound; ask for 'all' or indices")
    Cr, Cs = covariance_blocks(r, s, np.where(m, 1.0 / sig**2, 0.0), offsets=offsets, covariance=covariance)
    rb, sb = Cr[:, :d, :d], Cs[:, :d, :d]
    rt = np.trace(rb, axis1=1, axis2=2)
    st = np.trace(sb, axis1=1, axis2=2)

    def rms(tr: Array) -> float:
        ok = np.isfinite(tr)
        return float(np.sqrt(tr[ok].mean())) if ok.any() else float("nan")

    return CrlbResult(
        receiver_bounds=rb,
        source_bounds=sb,
        receiver_offset_var=Cr[:, d, d].copy() if has_r else None,
        source_offset_var=Cs[:, d, d].copy() if has_s else None,
        receiver_trace=rt,
        source_trace=st,
        rmse_receivers=rms(rt),
        rmse_sources=rms(st),
    )
