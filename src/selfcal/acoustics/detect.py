"""Arrival-time detection: matched filter in a window after each nominal emission time.

For receiver ``i`` and event ``e`` (nominal time ``t_e``) the direct sound starts somewhere
in ``[t_e, t_e + max_lag]`` with ``max_lag = max onset + max internal delay + max flight
time`` (004 sec. 2.2: onsets <= 30 ms, delays <= 20 ms). Per window:

1. Matched filter by FFT, band-weighted: ``Z(f) = 2 X(f) P*(f) W(f)`` for f > 0, with
   ``W`` a Hann taper over the probe band; its inverse FFT is the *analytic* matched-filter
   output ``z(tau)`` whose real part is the correlation and whose modulus is its envelope.
   The taper lowers the range side lobes, which would otherwise pass for early arrivals.
2. Noise level ``sigma`` of the envelope per receiver from a low percentile of all its
   windows (Rayleigh statistics: the 20th percentile is 0.668 sigma), robust to the
   windows' signal content.
3. The *first* significant peak, not the strongest: the earliest lag whose envelope
   exceeds ``max(rel_threshold * window maximum, k_noise * sigma)``, followed to its
   local maximum. Reflections arrive later and can superpose to a larger peak; the
   direct path is the first.
4. Sub-sample time: the correlation peak (the real part) nearest the envelope peak,
   refined by Newton steps on the band-limited correlation evaluated exactly from its
   spectrum (``c(tau) = Re sum_k Z_k exp(2 pi i k tau / n) / n``), which has no
   parabolic-interpolation bias.
5. Quality = ``20 log10(peak envelope / sigma)`` dB. Detections below ``min_quality_db``,
   without a significant peak, or at a window edge become NaN.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..errors import InputError
from .probe import Probe
from .recording import Recording

__all__ = ["Detections", "detect_arrivals", "detect_recording", "matched_filter"]

RAYLEIGH_P20 = float(np.sqrt(-2.0 * np.log(0.8)))  # 20th percentile of a unit Rayleigh variable


@dataclass(frozen=True)
class Detections:
    """Detected direct-path arrivals per (receiver, event).

    Attributes
    ----------
    arrival_times : (I, E) array
        Absolute arrival times on the recording clock, s; NaN = missed or doubtful.
    toa : (I, E) array
        ``arrival_times - nominal event time``, s: flight time + onset + internal delay.
    quality_db : (I, E) array
        Peak envelope over the envelope noise level, dB (NaN where no peak at all).
    noise : (I,) array
        Envelope noise level sigma per receiver (matched-filter units).
    """

    arrival_times: NDArray[np.float64]
    toa: NDArray[np.float64]
    quality_db: NDArray[np.float64]
    noise: NDArray[np.float64]

    @property
    def missed(self) -> int:
        """Number of NaN detections."""
        return int(np.isnan(self.toa).sum())

    def to_dict(self) -> dict[str, Any]:
        """JSON-safe dictionary."""
        return {"arrival_times": self.arrival_times, "toa": self.toa, "quality_db": self.quality_db,
                "detections_missed": self.missed}


def _band_weight(n_fft: int, fs: float, band: tuple[float, float]) -> NDArray[np.float64]:
    """Hann taper over the probe band on the one-sided FFT grid (zero outside)."""
    f = np.fft.rfftfreq(n_fft, 1.0 / fs)
    lo, hi = band
    w = np.zeros_like(f)
    inside = (f >= lo) & (f <= hi)
    w[inside] = np.sin(np.pi * (f[inside] - lo) / (hi - lo)) ** 2
    return w


def matched_filter(segments: NDArray[np.floating[Any]], probe: Probe, n_fft: int) -> tuple[NDArray[np.complex128], NDArray[np.complex128]]:
    """Band-weighted analytic matched filter of each row of ``segments`` (K, W).

    Returns
    -------
    z : (K, n_fft) complex
        Analytic matched-filter output; ``z[:, tau]`` belongs to the probe starting at
        sample ``tau`` of the segment.
    spectrum : (K, n_fft // 2 + 1) complex
        One-sided spectrum ``2 X P* W`` whose inverse gives ``z`` (used for sub-sample
        refinement).
    """
    X = np.fft.rfft(segments, n=n_fft, axis=-1)
    P = np.fft.rfft(probe.samples, n=n_fft)
    G = X * (np.conj(P) * _band_weight(n_fft, probe.sample_rate, probe.band))[None, :]
    G *= 2.0
    G[:, 0] *= 0.5
    full = np.zeros((segments.shape[0], n_fft), dtype=np.complex128)
    full[:, : G.shape[1]] = G
    if n_fft % 2 == 0:
        full[:, n_fft // 2] *= 0.5
    return np.fft.ifft(full, axis=-1), G


def _newton_refine(G: NDArray[np.complex128], n_fft: int, tau0: NDArray[np.float64], iterations: int = 3) -> NDArray[np.float64]:
    """Maximise the band-limited correlation ``Re z(tau)`` near ``tau0`` (K,) by Newton steps.

    ``z(tau) = sum_k G_k exp(i w_k tau) / n`` over the band's bins; the phase factors of
    contiguous bins are a geometric sequence, built by a cumulative product (one complex
    exponential per event instead of one per bin).
    """
    active = np.flatnonzero(np.abs(G).max(axis=0) > 0)
    k0, k1 = int(active[0]), int(active[-1]) + 1
    Gk = G[:, k0:k1]
    w = 2.0 * np.pi * np.arange(k0, k1) / n_fft
    Gw = Gk * w
    Gw2 = Gw * w
    tau = tau0.astype(np.float64).copy()
    for _ in range(iterations):
        ratio = np.exp(1j * (2.0 * np.pi / n_fft) * tau)
        steps = np.empty((len(tau), k1 - k0), dtype=np.complex128)
        steps[:, 0] = np.exp(1j * w[0] * tau)
        steps[:, 1:] = ratio[:, None]
        e = np.cumprod(steps, axis=1)
        d1 = -np.einsum("ek,ek->e", Gw, e).imag
        d2 = -np.einsum("ek,ek->e", Gw2, e).real
        step = np.where(d2 < 0, -d1 / np.where(d2 < 0, d2, -1.0), 0.0)
        tau = tau + np.clip(step, -0.5, 0.5)
    return np.clip(tau, tau0 - 1.0, tau0 + 1.0)


def detect_arrivals(
    signals: NDArray[np.floating[Any]],
    probe: Probe,
    event_times: NDArray[np.float64],
    *,
    lengths: NDArray[np.int64] | None = None,
    max_lag: float = 0.2,
    rel_threshold: float = 0.3,
    k_noise: float = 6.0,
    min_quality_db: float = 20.0,
    progress: bool = True,
) -> Detections:
    """Detect the direct-path arrival of every event at every receiver (module docstring).

    Parameters
    ----------
    signals : (I, N) array
        Receiver signals on one clock, sampled at ``probe.sample_rate``.
    probe : Probe
    event_times : (E,) array
        Nominal emission times, s.
    lengths : (I,) int array, optional
        Valid samples per receiver (default N); windows beyond are missed.
    max_lag : float
        Search window after each nominal time, s (max onset + max delay + max flight time).
    rel_threshold : float
        A peak is significant above this fraction of the window's largest envelope peak.
    k_noise : float
        ... and above ``k_noise`` times the envelope noise level (6: false-alarm rate
        exp(-18) per lag).
    min_quality_db : float
        Detections with a lower peak-to-noise ratio are NaN.
    progress : bool
        tqdm bar over receivers.

    Returns
    -------
    Detections
    """
    from tqdm import tqdm

    sig = np.asarray(signals)
    if sig.ndim != 2:
        raise InputError(f"signals must be (receivers, samples), got shape {sig.shape}")
    fs = probe.sample_rate
    times = np.asarray(event_times, dtype=float)
    I, N = sig.shape
    E = len(times)
    lens = np.full(I, N, dtype=np.int64) if lengths is None else np.asarray(lengths, dtype=np.int64)
    L = len(probe.samples)
    n_lag = int(np.ceil(max_lag * fs)) + 1
    W = n_lag + L - 1
    n_fft = int(2 ** np.ceil(np.log2(W + L)))
    start = np.round(times * fs).astype(np.int64)
    idx = start[:, None] + np.arange(W)[None, :]
    mainlobe = int(np.ceil(2.0 * fs / (probe.band[1] - probe.band[0]))) + 2

    arrival = np.full((I, E), np.nan)
    quality = np.full((I, E), np.nan)
    noise = np.zeros(I)
    rows = np.arange(E)
    for i in tqdm(range(I), desc="detect", unit="rx", disable=None if progress else True, leave=False):
        valid = idx < lens[i]
        seg = np.where(valid, sig[i, np.minimum(idx, N - 1)], 0.0).astype(np.float64)
        z, G = matched_filter(seg, probe, n_fft)
        env = np.abs(z[:, :n_lag])
        sigma = float(np.percentile(env, 20)) / RAYLEIGH_P20
        noise[i] = sigma
        if sigma <= 0:
            continue
        thr = np.maximum(rel_threshold * env.max(axis=1), k_noise * sigma)
        above = env >= thr[:, None]
        found = above.any(axis=1)
        first = np.argmax(above, axis=1)
        # Follow the envelope up to its first local maximum after the threshold crossing.
        look = np.minimum(first[:, None] + np.arange(mainlobe + 1)[None, :], n_lag - 1)
        rise = env[rows[:, None], look]
        falling = np.diff(rise, axis=1) < 0
        peak = first + np.where(falling.any(axis=1), np.argmax(falling, axis=1), np.argmax(rise, axis=1))
        # Correlation (carrier) peak nearest the envelope peak.
        near = np.clip(peak[:, None] + np.arange(-2, 3)[None, :], 0, n_lag - 1)
        coarse = near[rows, np.argmax(z[rows[:, None], near].real, axis=1)]
        tau = _newton_refine(G, n_fft, coarse.astype(np.float64))
        q = 20.0 * np.log10(env[rows, peak] / sigma)
        quality[i] = np.where(found, q, np.nan)
        ok = found & (q >= min_quality_db) & (peak > 0) & (peak < n_lag - 1) & (start + peak + L <= lens[i])
        arrival[i] = np.where(ok, (start + tau) / fs, np.nan)
    return Detections(arrival, arrival - times[None, :], quality, noise)


def detect_recording(recording: Recording, *, max_lag: float | None = None, progress: bool = True,
                     **kwargs: Any) -> Detections:
    """:func:`detect_arrivals` on a loaded recording directory.

    ``max_lag`` defaults to the time to the next event (at most 0.5 s), i.e. the largest
    window in which this event's sound cannot be confused with the next one's.
    """
    setup = recording.setup
    times = setup.event_times
    if max_lag is None:
        order = np.sort(times)
        gaps = np.diff(order)
        max_lag = float(min(0.5, gaps.min())) if len(gaps) else 0.5
        max_lag = max(max_lag - recording.probe.duration, 0.01)
    return detect_arrivals(recording.signals, recording.probe, times, lengths=recording.lengths,
                           max_lag=max_lag, progress=progress, **kwargs)
