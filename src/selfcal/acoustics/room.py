"""Room simulation with pyroomacoustics: a conference network playing probes in a shoebox room.

Each sender plays the probe once, in turn. Room impulse responses come from the image
source model (pyroomacoustics ``ShoeBox``) with a uniform wall absorption chosen by
Sabine's formula for a target RT60 (``pra.inverse_sabine``); the image-source order is
capped (default 3) because only the direct path and the early reflections decide the
arrival-time detection, and the cost grows with the cube of the order. Each event's
sound is delayed by its nominal time, the sender's onset and the receiver's internal
delay (004 eq. 3.1) with an exact band-limited (FFT phase-ramp) fractional delay, and
white sensor noise is added at the requested SNR.

SNR convention: ``snr_db = 10 log10(P_1m / sigma^2)``, where ``P_1m`` is the mean power
of the probe's direct sound at 1 m from the loudspeaker and ``sigma^2`` the noise variance
of every microphone. A receiver 10 m away therefore sees the direct sound 20 dB lower.

pyroomacoustics builds each image with a centred windowed-sinc fractional-delay filter of
``frac_delay_length`` taps, so every impulse response is late by
``frac_delay_length // 2`` samples; :func:`simulate_conference` removes that group delay so
that ``truth.json`` arrival times are exact.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from .._checks import as_rng, check_positive, entry, instance_of
from ..errors import InputError
from ..scenarios.conference import ConferenceScene
from .probe import probe_from_spec
from .recording import Setup

__all__ = ["simulate_conference", "event_spacing", "pra_group_delay", "DEFAULT_PROBE"]

DEFAULT_PROBE: dict[str, Any] = {"type": "chirp", "f0": 500.0, "f1": 12000.0, "duration": 0.05}
MAX_OFFSET = 0.050  # s: onset (<= 30 ms) + internal delay (<= 20 ms), 004 sec. 2.2
#: Lowest simulated SNR (dB): below about -144 dB (a float32 sample's 24-bit mantissa) the direct
#: sound is lost in the rounding of the noise, and 10**(snr/10) underflows long before -1e308.
MIN_SNR_DB = -150.0


def pra_group_delay() -> int:
    """Samples by which every pyroomacoustics impulse response is late (its centred sinc)."""
    import pyroomacoustics as pra

    return int(pra.constants.get("frac_delay_length")) // 2


def event_spacing(room: NDArray[np.float64], probe_duration: float, speed: float) -> float:
    """Seconds between two nominal emissions so that windows of successive events do not overlap.

    ``probe + max onset + max delay + 1.2 * (room diagonal / c) + 30 ms``.
    """
    return float(probe_duration + MAX_OFFSET + 1.2 * np.linalg.norm(room) / speed + 0.03)


@entry(scene=instance_of(lambda: ConferenceScene, "ConferenceScene (selfcal.scenarios.conference.conference_scene)"),
       rng="rng", progress="bool")
def simulate_conference(
    scene: ConferenceScene,
    *,
    rt60: float = 0.4,
    snr_db: float = 30.0,
    sample_rate: int = 48000,
    probe: dict[str, Any] | None = None,
    speed: float = 343.0,
    max_order: int | None = 3,
    jitter: float = 0.0,
    rounds: int = 1,
    occlusions: dict[tuple[int, int], float] | None = None,
    missing_events: tuple[int, ...] = (),
    rng: np.random.Generator | int | None = None,
    progress: bool = False,
) -> tuple[Setup, NDArray[np.float32], dict[str, Any]]:
    """Simulate the calibration recordings of a conference network.

    Parameters
    ----------
    scene : ConferenceScene
        Positions (m), internal delays and onsets (s), room size.
    rt60 : float
        Target reverberation time, s (absorption by ``pra.inverse_sabine``).
    snr_db : float
        Direct-sound-at-1-m to noise ratio, dB (module docstring).
    sample_rate : int
        Hz.
    probe : dict, optional
        ``setup.json`` probe entry (default: 0.5-12 kHz chirp, 50 ms; the band is clipped to
        0.45 fs).
    speed : float
        Speed of sound, m/s.
    max_order : int or None
        Cap of the image-source order (None: the order Sabine's formula asks for).
    jitter : float
        Standard deviation (s) of a random timing error per (receiver, event): the
        residual synchronisation error of wireless units' clocks (004 sec. 2.2: clocks
        agree within 100 us). A constant clock offset is indistinguishable from an internal
        delay; only the part that changes from event to event hurts.
    rounds : int
        Events per sender: every sender plays the probe once per round, rounds one after
        the other (the recording format allows several events per sender; their TOAs are
        averaged, so the jitter's share of the timing std falls as 1 / sqrt(rounds)).
    occlusions : dict, optional
        ``{(receiver, sender): dB}``: the direct path of that pair attenuated by ``dB``
        (an obstacle between them; the reflections are kept), for fault tests.
    missing_events : tuple of int
        Events listed in setup.json but never played (a loudspeaker that stayed silent).
    rng : Generator, int or None
        Noise generator.
    progress : bool
        Show a tqdm bar over the events.

    Returns
    -------
    setup : Setup
        ``rounds`` events per sender: round by round, senders in order.
    signals : (U, N) float32
        Receiver signals scaled so that the loudest sample is 0.5 (common gain).
    truth : dict
        ``scene.to_dict()`` plus ``speed_of_sound``, ``rt60``, ``snr_db``, ``absorption``,
        ``max_order``, ``sample_rate``, ``clock_jitter`` and ``arrival_times`` (U x E, s, direct
        path, jitter included) and ``rounds``.
    """
    import pyroomacoustics as pra

    from ..progress import stage

    gen = as_rng(rng)
    check_positive(rt60, "rt60", allow_none=False)
    check_positive(speed, "speed", allow_none=False)
    if max_order is not None and (isinstance(max_order, bool) or not isinstance(max_order, (int, np.integer))
                                  or max_order < 0):
        raise InputError(f"max_order must be None or an integer >= 0 (0 = anechoic), got {max_order!r}")
    if not np.isfinite(snr_db):
        raise InputError(f"snr must be finite dB, got {snr_db!r}")
    if snr_db < MIN_SNR_DB:
        raise InputError(f"snr {snr_db:g} dB is below {MIN_SNR_DB:g} dB: the direct sound would lie under the "
                         f"float32 samples' resolution of the noise (24-bit mantissa, ~144 dB)")
    from .._checks import check_int, guard_size

    check_int(sample_rate, "sample_rate", minimum=1)
    check_int(rounds, "rounds", minimum=1)
    fs = int(sample_rate)
    # the memory of the signals, refused before any is made (as the CLI does: same formula)
    n_units = max(len(scene.receivers), len(scene.senders))
    spacing = event_spacing(np.asarray(scene.room, dtype=float), float(DEFAULT_PROBE["duration"]), float(speed))
    n_total = (0.1 + spacing * (float(n_units) * float(rounds) + 1)) * fs
    guard_size(n_units * n_total * 4.0 + n_units**2 * (float(rt60) + spacing) * fs * 8.0,
               f"simulate_conference: {n_units} units at {fs} Hz, {int(rounds)} round(s), rt60 {float(rt60):g} s")
    spec = dict(probe) if probe is not None else dict(DEFAULT_PROBE)
    if probe is None:
        spec["f1"] = min(float(spec["f1"]), 0.45 * fs)
    prb = probe_from_spec(spec, fs, where="probe")
    room_dim = scene.room
    for pts, label in ((scene.receivers, "receiver"), (scene.senders, "sender")):
        if np.any(pts <= 0.0) or np.any(pts >= room_dim):
            raise InputError(f"a {label} lies outside the {room_dim.tolist()} m room")
    try:
        absorption, needed = pra.inverse_sabine(rt60, room_dim.tolist(), c=speed)
    except ValueError as exc:
        raise InputError(f"rt60 = {rt60:g} s is not reachable in this room ({exc})") from None
    order = int(needed if max_order is None else min(needed, max_order))

    def impulse_responses(image_order: int) -> Any:
        """The room's impulse responses ``rir[receiver][sender]`` up to ``image_order`` reflections."""
        box = pra.ShoeBox(room_dim.tolist(), fs=fs, materials=pra.Material(absorption), max_order=image_order,
                          air_absorption=False)
        box.set_sound_speed(speed)
        for s_pos in scene.senders:
            box.add_source(s_pos)
        box.add_microphone_array(scene.receivers.T)
        box.compute_rir()
        return box.rir

    room_rir = impulse_responses(order)
    delay0 = pra_group_delay()
    direct: dict[tuple[int, int], NDArray[np.float64]] = {}
    if occlusions:
        free_rir = impulse_responses(0)  # the direct paths alone
        for (i, j), db in occlusions.items():
            direct[(int(i), int(j))] = (1.0 - 10.0 ** (-float(db) / 20.0)) * np.asarray(free_rir[int(i)][int(j)])

    U = len(scene.senders)
    if not np.isfinite(jitter) or jitter < 0:
        raise InputError(f"jitter must be a finite standard deviation >= 0 s, got {jitter!r}")
    if int(rounds) != rounds or rounds < 1:
        raise InputError(f"rounds must be an integer >= 1, got {rounds!r}")
    K = int(rounds)
    E = U * K
    ev_sender = np.tile(np.arange(U, dtype=np.int64), K)  # round by round, senders in order
    shake = jitter * gen.standard_normal((U, E))
    spacing = event_spacing(room_dim, prb.duration, speed)
    times: NDArray[np.float64] = 0.1 + spacing * np.arange(E, dtype=np.float64)
    n_total = int(np.ceil((times[-1] + spacing) * fs))
    signals = np.zeros((U, n_total), dtype=np.float32)
    x = prb.samples
    for j in stage.iterate(range(U), "simulate", unit="senders", show=None if progress else False):
        rirs = [room_rir[i][j] for i in range(U)]
        lh = max(len(h) for h in rirs)
        h = np.zeros((U, lh))
        for i, r in enumerate(rirs):
            h[i, : len(r)] = r
            if (i, j) in direct:
                g = direct[(i, j)]
                h[i, : min(len(g), lh)] -= g[:lh]
        n_conv = lh + len(x) - 1
        n_fft = int(2 ** np.ceil(np.log2(n_conv + 2)))
        conv = np.fft.rfft(h, n_fft) * np.fft.rfft(x, n_fft)[None, :]
        k_bins = np.arange(conv.shape[-1])
        for e in np.flatnonzero(ev_sender == j):
            if int(e) in missing_events:
                continue
            start = (times[e] + scene.sender_onsets[j] + scene.receiver_delays + shake[:, e]) * fs - delay0
            n0 = np.floor(start).astype(np.int64)
            frac = start - n0
            wet = np.fft.irfft(conv * np.exp(-2j * np.pi * k_bins[None, :] * frac[:, None] / n_fft),
                               n_fft)[:, : n_conv + 1]
            for i in range(U):
                a, b = max(n0[i], 0), min(n0[i] + wet.shape[1], n_total)
                signals[i, a:b] += wet[i, a - n0[i] : b - n0[i]].astype(np.float32)
    p_1m = float(np.mean(x**2)) / (4.0 * np.pi) ** 2
    sigma = np.sqrt(p_1m / 10.0 ** (snr_db / 10.0))
    for row in signals:  # row by row: a float64 noise matrix would double the peak memory
        row += np.float32(sigma) * gen.standard_normal(n_total, dtype=np.float32)
    signals *= np.float32(0.5 / np.abs(signals).max())

    dist = np.linalg.norm(scene.receivers[:, None, :] - scene.senders[None, :, :], axis=-1)
    arrivals = (times[None, :] + scene.sender_onsets[ev_sender][None, :] + scene.receiver_delays[:, None]
                + dist[:, ev_sender] / speed + shake)
    names_r = tuple(f"u{k:03d}" for k in range(U))
    # the simulated clocks' jitter is declared in setup.json as the equipment's specification
    setup = Setup(float(fs), float(speed), names_r, names_r, prb.spec, ev_sender, times,
                  clock_jitter=float(jitter), room=tuple(float(v) for v in scene.room))
    truth = scene.to_dict() | {
        "speed_of_sound": speed, "rt60": rt60, "snr_db": snr_db, "absorption": float(absorption),
        "max_order": order, "sample_rate": fs, "arrival_times": arrivals.tolist(), "clock_jitter": jitter,
        "rounds": K, "occlusions": [[int(i), int(j), float(db)] for (i, j), db in (occlusions or {}).items()],
        "missing_events": [int(e) for e in missing_events],
    }
    return setup, signals, truth
