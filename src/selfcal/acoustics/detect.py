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
   exceeds ``max(rel_threshold * window maximum, k * level(lag))``, followed to its local
   maximum. Reflections arrive later and can superpose to a larger peak; the direct path
   is the first. ``level(lag)`` is a cell-averaging CFAR level: the Rayleigh parameter of
   the ``REF_TIME`` (2.5 ms) of lags before it (``mean |z|^2 = 2 sigma^2``, a guard of one
   main lobe between), never below the receiver's level ``sigma``; lags with less history
   use ``sigma``; the segment starts that many lags before the window, so the first lags
   have their history too (a burst still sounding from the previous event is measured).
   A noise burst (a cough) raises the level of the lags it covers, so an arrival inside it
   must stand out of it. Its *onset* inside a window is caught by a greatest-of CFAR: the
   lag must also exceed ``k_trail`` times the trailing level, the quietest of
   :data:`TRAIL_BLOCKS` blocks of ``REF_TIME`` after it (an ordered statistic: a direct
   path's discrete reflections fill some blocks, a burst fills all; unbiased under noise
   alone, :func:`_min_power_bias`). Under a burst's onset the peak over that level is
   Rayleigh, so ``k_trail = sqrt(2 ln(cells / BURST_FALSE_ALARM))`` over the trailing
   cells; the diffuse reverberation after a direct path lies ``~ 10 log10(DRR RT60 B / 13.8)``
   dB below its peak (27 dB + DRR at RT60 1 s, B 7.5 kHz), so a direct path more than
   ~14 dB below the reverberant field (far pairs in a large reverberant hall) becomes a
   missed detection rather than a doubtful one.
4. Sub-sample time: the correlation peak (the real part) nearest the envelope peak,
   refined by Newton steps on the band-limited correlation evaluated exactly from its
   spectrum (``c(tau) = Re sum_k Z_k exp(2 pi i k tau / n) / n``), which has no
   parabolic-interpolation bias.
5. Quality = ``20 log10(peak envelope / level(crossing))`` dB. Detections below the floor,
   without a significant peak, or at a window edge become NaN.

Quality floor by a false-alarm probability (CFAR). Under noise alone the envelope is
Rayleigh, ``P(|z| > k sigma) = exp(-k^2 / 2)`` per independent lag; a window of ``n``
lags holds about ``n B / fs`` independent cells (``B`` the probe bandwidth), so the
threshold ``k = sqrt(2 ln(cells / p_fa))`` keeps the chance of a false detection in a window
without signal at ``p_fa`` (default ``1e-6`` per window, :data:`FALSE_ALARM`). The same
principle sets the floor of a re-detection in a narrow window around a predicted time
(:func:`redetect_arrivals`): fewer cells, a lower floor.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..errors import InputError
from .probe import Probe
from .recording import Recording

__all__ = ["Detections", "detect_arrivals", "detect_recording", "matched_filter", "redetect_arrivals",
           "cfar_factor", "FALSE_ALARM"]

RAYLEIGH_P20 = float(np.sqrt(-2.0 * np.log(0.8)))  # 20th percentile of a unit Rayleigh variable
FALSE_ALARM = 1e-6  # probability of a false detection in a search window holding only noise
REF_TIME = 2.5e-3  # s, leading reference window of the CFAR noise level (~20 independent cells at 8 kHz)
BURST_FALSE_ALARM = 1e-3  # probability that a noise burst's onset passes the trailing test (one
# wrong detection for the robust fit: bursts are rare events, reverberant tails are not)
TRAIL_BLOCKS = 4  # trailing reference: this many blocks of REF_TIME after a lag (10 ms), the quietest kept


def _fft_size(n: int) -> int:
    """FFT length for a linear correlation of ``n`` samples (a fast composite size, ``scipy.fft``)."""
    import scipy.fft as sfft

    return int(sfft.next_fast_len(int(n), real=False))


@functools.lru_cache(maxsize=64)
def _min_power_bias(cells: float, blocks: int) -> float:
    """``E[min_b P_b] / E[P]`` of ``blocks`` independent block powers of stationary Rayleigh noise.

    A block's mean power over ``cells`` independent cells is Gamma(cells) / cells distributed
    (``mean |z|^2 = 2 sigma^2``); the expected minimum of ``blocks`` of them is
    ``int_0^inf P(X > x)^blocks dx``, below 1: dividing by it makes the trailing level unbiased
    under noise alone.
    """
    from scipy import integrate, stats

    a = max(float(cells), 1.0)
    val, _ = integrate.quad(lambda x: stats.gamma.sf(x, a, scale=1.0 / a) ** blocks, 0.0, np.inf, limit=200)
    return float(val)


def cfar_cells(n_lags: int, fs: float, band: tuple[float, float]) -> float:
    """Independent matched-filter cells in ``n_lags`` lags: ``n_lags (f1 - f0) / fs`` (at least 1)."""
    return max(float(n_lags) * (band[1] - band[0]) / fs, 1.0)


def _cfar_levels(env: NDArray[np.floating[Any]], head: int, n_lag: int, n_ref: int, guard: int,
                 cells: float) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Leading and trailing Rayleigh levels of the lags ``head .. head + n_lag - 1`` of ``env`` (E, n).

    Leading: ``sqrt(mean |z|^2 / 2)`` over the ``n_ref`` lags ending ``guard`` lags before the
    lag (cell averaging). Trailing: the same over each of :data:`TRAIL_BLOCKS` consecutive
    blocks of ``n_ref`` lags starting ``guard`` after it, the *smallest* block power kept
    (an ordered statistic: the direct path's discrete reflections fill some blocks, a noise
    burst fills all), divided by its expectation under stationary noise
    (:func:`_min_power_bias`, ``cells`` independent cells per block).
    """
    e2 = np.asarray(env, dtype=np.float64) ** 2
    cs = np.zeros((e2.shape[0], e2.shape[1] + 1))
    np.cumsum(e2, axis=1, out=cs[:, 1:])
    t = head + np.arange(n_lag)
    lead = np.sqrt(np.maximum(cs[:, t - guard] - cs[:, t - guard - n_ref], 0.0) / (2.0 * n_ref))
    first = t + guard
    blocks = np.stack([cs[:, first + (b + 1) * n_ref] - cs[:, first + b * n_ref] for b in range(TRAIL_BLOCKS)])
    low = np.maximum(blocks.min(axis=0), 0.0) / (2.0 * n_ref * _min_power_bias(cells, TRAIL_BLOCKS))
    return lead, np.sqrt(low)


def cfar_factor(n_lags: int, fs: float, band: tuple[float, float], p_fa: float = FALSE_ALARM) -> float:
    """Envelope threshold over the noise level ``k = sqrt(2 ln(cells / p_fa))`` (module docstring).

    Parameters
    ----------
    n_lags : int
        Lags searched.
    fs : float
        Hz.
    band : (f0, f1)
        Probe band, Hz (independent cells ~ ``n_lags (f1 - f0) / fs``).
    p_fa : float
        False-alarm probability per window.

    Returns
    -------
    float
        ``k`` (the quality floor is ``20 log10 k`` dB).
    """
    return float(np.sqrt(2.0 * np.log(cfar_cells(n_lags, fs, band) / p_fa)))


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


def _matched(segments: NDArray[np.floating[Any]], P: NDArray[np.inexact[Any]], n_fft: int,
             n_keep: int) -> tuple[NDArray[np.complex64], NDArray[np.complex64]]:
    """:func:`matched_filter` with the probe's weighted spectrum ``P`` given; keeps ``n_keep`` lags.

    The analytic output is the inverse FFT of the one-sided spectrum; only the bins of the
    band are non-zero, so the inverse runs on a complex array holding just the one side.
    """
    import scipy.fft as sfft

    # single precision for the filter and its envelope (the inputs are 16/24-bit audio); the
    # sub-sample refinement (_newton_refine) works on the spectrum in double precision
    G = sfft.rfft(np.asarray(segments, dtype=np.float32), n=n_fft, axis=-1)
    G *= (2.0 * P).astype(np.complex64)[None, :]
    G[:, 0] *= 0.5
    if n_fft % 2 == 0:
        G[:, -1] *= 0.5
    full = np.zeros((segments.shape[0], n_fft), dtype=np.complex64)
    full[:, : G.shape[1]] = G
    z = sfft.ifft(full, axis=-1, overwrite_x=True)[:, :n_keep]
    return z, G


def _newton_refine(G: NDArray[np.complex128], n_fft: int, tau0: NDArray[np.float64], iterations: int = 2) -> NDArray[np.float64]:
    """Maximise the band-limited correlation ``Re z(tau)`` near ``tau0`` (K,) by Newton steps.

    ``z(tau) = sum_k G_k exp(i w_k tau) / n`` over the band's bins; the phase factors of
    contiguous bins are a geometric sequence, built by a cumulative product (one complex
    exponential per event instead of one per bin). ``tau0`` should be within a few hundredths
    of a sample (a parabola through the correlation samples, :func:`_parabolic`); two Newton
    steps then reach 1e-6 samples.
    """
    active = np.flatnonzero(np.abs(G).max(axis=0) > 0)
    k0, k1 = int(active[0]), int(active[-1]) + 1
    Gk = G[:, k0:k1].astype(np.complex128)
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


def _parabolic(z: NDArray[np.complexfloating[Any, Any]], rows: NDArray[np.intp], coarse: NDArray[np.intp]) -> NDArray[np.float64]:
    """Vertex of the parabola through ``Re z`` at ``coarse - 1, coarse, coarse + 1`` (the Newton start)."""
    n = z.shape[1]
    c = np.clip(coarse, 1, n - 2)
    ym, y0, yp = (z[rows, c - 1].real.astype(float), z[rows, c].real.astype(float), z[rows, c + 1].real.astype(float))
    den = ym - 2.0 * y0 + yp
    d = np.where(den < 0, 0.5 * (ym - yp) / np.where(den < 0, den, -1.0), 0.0)
    return c + np.clip(d, -0.5, 0.5)


def detect_arrivals(
    signals: NDArray[np.floating[Any]],
    probe: Probe,
    event_times: NDArray[np.float64],
    *,
    lengths: NDArray[np.int64] | None = None,
    max_lag: float = 0.2,
    rel_threshold: float = 0.3,
    k_noise: float | None = None,
    min_quality_db: float | None = None,
    p_fa: float = FALSE_ALARM,
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
    k_noise : float, optional
        ... and above ``k_noise`` times the envelope noise level (default: the CFAR factor
        :func:`cfar_factor` for ``p_fa``).
    min_quality_db : float, optional
        Detections with a lower peak-to-noise ratio are NaN (default ``20 log10 k_noise``).
    p_fa : float
        False-alarm probability per window of the default thresholds.
    progress : bool
        tqdm bar over receivers.

    Returns
    -------
    Detections
    """
    from ..progress import stage

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
    mainlobe = int(np.ceil(2.0 * fs / (probe.band[1] - probe.band[0]))) + 2
    n_ref = max(int(round(REF_TIME * fs)), 8)
    # history before the window (leading reference of its first lags) and after it (trailing blocks)
    head = n_ref + mainlobe
    tail = mainlobe + TRAIL_BLOCKS * n_ref
    n_keep = head + n_lag + tail
    W = n_keep + L - 1
    n_fft = _fft_size(W + L)
    start = np.round(times * fs).astype(np.int64)
    idx = (start - head)[:, None] + np.arange(W)[None, :]
    win = slice(head, head + n_lag)
    cells_per_block = n_ref * (probe.band[1] - probe.band[0]) / fs
    # trailing test: a peak over the noise that follows it, Rayleigh under a burst's onset, with
    # BURST_FALSE_ALARM per burst over the cells of the trailing reference
    k_trail = float(np.sqrt(2.0 * np.log(cfar_cells(TRAIL_BLOCKS * n_ref, fs, probe.band) / BURST_FALSE_ALARM)))

    if k_noise is None:
        k_noise = cfar_factor(n_lag, fs, probe.band, p_fa)
    if min_quality_db is None:
        min_quality_db = 20.0 * float(np.log10(k_noise))
    arrival = np.full((I, E), np.nan)
    quality = np.full((I, E), np.nan)
    noise = np.zeros(I)
    rows = np.arange(E)
    P = np.conj(np.fft.rfft(probe.samples, n=n_fft)) * _band_weight(n_fft, fs, probe.band)
    for i in stage.iterate(range(I), "detect", unit="receivers", show=None if progress else False):
        if lens[i] <= 0 or not np.any(sig[i, : lens[i]]):
            continue  # a dead input: nothing to detect
        valid = (idx >= 0) & (idx < lens[i])
        seg = np.where(valid, sig[i, np.clip(idx, 0, N - 1)], 0.0)
        z_all, G = _matched(seg, P, n_fft, n_keep)
        env_all = np.abs(z_all)
        z, env = z_all[:, win], env_all[:, win]
        sigma = float(np.percentile(env[:, ::4], 20)) / RAYLEIGH_P20  # lags 4 apart: still ~1 per cell
        noise[i] = sigma
        if sigma <= 0:
            continue
        lead, trail = _cfar_levels(env_all, head, n_lag, n_ref, mainlobe, cells_per_block)
        level_lag = np.maximum(lead, sigma)
        # greatest-of CFAR: a lag must stand out of the noise before it (lead) and of the noise
        # after it (trail): a noise burst starting in the window raises the trailing level at
        # its onset, where the leading one is still quiet
        thr = np.maximum(rel_threshold * env.max(axis=1)[:, None], np.maximum(k_noise * level_lag, k_trail * trail))
        above = env >= thr
        found = above.any(axis=1)
        first = np.argmax(above, axis=1)
        # Follow the envelope up to its first local maximum after the threshold crossing.
        look = np.minimum(first[:, None] + np.arange(mainlobe + 1)[None, :], n_lag - 1)
        rise = env[rows[:, None], look]
        falling = np.diff(rise, axis=1) < 0
        peak = first + np.where(falling.any(axis=1), np.argmax(falling, axis=1), np.argmax(rise, axis=1))
        level = level_lag[rows, first]
        q = 20.0 * np.log10(env[rows, peak] / level)
        quality[i] = np.where(found, q, np.nan)
        ok = (found & (q >= min_quality_db) & (peak > 0) & (peak < n_lag - 1)
              & (start + peak + L <= lens[i]))
        if not ok.any():
            continue
        # Correlation (carrier) peak nearest the envelope peak.
        near = np.clip(peak[:, None] + np.arange(-2, 3)[None, :], 0, n_lag - 1)
        coarse = near[rows, np.argmax(z[rows[:, None], near].real, axis=1)]
        tau = np.full(E, np.nan)
        tau[ok] = _newton_refine(G[ok], n_fft, _parabolic(z_all, rows[ok], coarse[ok] + head)) - head
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


def redetect_arrivals(recording: Recording, detections: Detections, receivers: NDArray[np.intp],
                      events: NDArray[np.intp], predicted_toa: NDArray[np.float64],
                      half_width: NDArray[np.float64], *, p_fa: float = FALSE_ALARM) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Detect again near a predicted time: the strongest peak within a narrow window.

    An outlier of the calibration (a reflection picked because the direct path was
    attenuated, a noise burst) is searched for again around the arrival the calibrated
    model predicts. The window is ``predicted +- (half_width + half a main lobe)``; the
    envelope's largest peak there is refined like :func:`detect_arrivals`, and kept when it
    passes the CFAR floor of that small window (:func:`cfar_factor` with its few cells) over
    the local noise level (the leading level before the window, never below the receiver's)
    and the trailing test after it (a window inside a noise burst gives NaN).

    Parameters
    ----------
    recording : Recording
    detections : Detections
        The first pass (for the receivers' noise levels).
    receivers, events : (K,) int arrays
        Which (receiver, event) to re-detect.
    predicted_toa : (K,) array
        Predicted TOA (arrival minus nominal time), s.
    half_width : (K,) array
        Uncertainty of the prediction, s.
    p_fa : float
        False-alarm probability per window.

    Returns
    -------
    toa : (K,) array
        s, NaN when nothing passes the floor.
    quality_db : (K,) array
        dB (NaN likewise).
    """
    probe = recording.probe
    fs = probe.sample_rate
    sig = recording.signals
    ri = np.asarray(receivers, dtype=np.intp)
    ev = np.asarray(events, dtype=np.intp)
    K = len(ri)
    out_t = np.full(K, np.nan)
    out_q = np.full(K, np.nan)
    if K == 0:
        return out_t, out_q
    L = len(probe.samples)
    mainlobe = int(np.ceil(2.0 * fs / (probe.band[1] - probe.band[0]))) + 2
    n_ref = max(int(round(REF_TIME * fs)), 8)
    head = n_ref + mainlobe
    tail = mainlobe + TRAIL_BLOCKS * n_ref
    hw = np.ceil(np.asarray(half_width, float) * fs).astype(np.int64) + mainlobe // 2 + 1
    pad = int(hw.max()) + mainlobe
    n_lag = 2 * pad + 1
    n_keep = head + n_lag + tail
    W = n_keep + L - 1
    n_fft = _fft_size(W)
    t_abs = recording.setup.event_times[ev] + np.asarray(predicted_toa, float)
    centre = np.round(t_abs * fs).astype(np.int64)
    start = centre - pad
    idx = (start - head)[:, None] + np.arange(W)[None, :]
    N = sig.shape[1]
    lens = recording.lengths[ri]
    valid = (idx >= 0) & (idx < lens[:, None])
    seg = np.where(valid, sig[ri[:, None], np.clip(idx, 0, N - 1)], 0.0)
    core = valid[:, head: head + n_lag + L - 1].all(axis=1)
    P = np.conj(np.fft.rfft(probe.samples, n=n_fft)) * _band_weight(n_fft, fs, probe.band)
    z_all, G = _matched(seg, P, n_fft, n_keep)
    env_all = np.abs(z_all)
    z, env = z_all[:, head: head + n_lag], env_all[:, head: head + n_lag]
    lag = np.arange(n_lag)[None, :]
    inside = np.abs(lag - pad) <= hw[:, None]
    peak = np.argmax(np.where(inside, env, -1.0), axis=1)
    rows = np.arange(K)
    sigma = np.asarray(detections.noise, float)[ri]
    # the local noise: the leading level before the window and the trailing one after it
    # (greatest-of, as detect_arrivals), never below the receiver's level
    lead, trail = _cfar_levels(env_all, head, n_lag, n_ref, mainlobe, n_ref * (probe.band[1] - probe.band[0]) / fs)
    level = np.maximum(sigma, lead[rows, np.clip(pad - hw, 0, n_lag - 1)])
    trail_hi = trail[rows, np.clip(pad + hw, 0, n_lag - 1)]
    cells = 2 * hw + 1
    k = np.array([cfar_factor(int(c), fs, probe.band, p_fa) for c in cells])
    k_trail = float(np.sqrt(2.0 * np.log(cfar_cells(TRAIL_BLOCKS * n_ref, fs, probe.band) / BURST_FALSE_ALARM)))
    pk = env[rows, peak]
    with np.errstate(divide="ignore", invalid="ignore"):
        q = 20.0 * np.log10(pk / level)
    ok = ((sigma > 0) & (pk >= k * level) & (pk >= k_trail * trail_hi) & (peak > 0) & (peak < n_lag - 1) & core)
    if ok.any():
        near = np.clip(peak[:, None] + np.arange(-2, 3)[None, :], 0, n_lag - 1)
        coarse = near[rows, np.argmax(z[rows[:, None], near].real, axis=1)]
        tau = _newton_refine(G[ok], n_fft, _parabolic(z_all, rows[ok], coarse[ok] + head)) - head
        out_t[ok] = (start[ok] + tau) / fs - recording.setup.event_times[ev[ok]]
        out_q[ok] = q[ok]
    return out_t, out_q
