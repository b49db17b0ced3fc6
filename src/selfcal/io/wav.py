"""A strict WAV reader: every PCM depth and float format, truncation and corrupt headers named.

:func:`read_wav_file` parses the RIFF chunks itself (no trust in the sizes a header declares)
and decodes the samples with numpy, scaled to full scale 1:

* integer PCM of 1-8 bits (unsigned, offset 128), 9-64 bits (signed, little-endian or RIFX
  big-endian), in 1-8 byte containers (24-bit = 3 bytes): ``x = n / 2**(8 * container - 1)``,
  i.e. in [-1, 1) (a 12-bit sample left-justified in 16 bits is scaled by its container);
* IEEE float, 32 or 64 bit: taken as is (NaN / inf refused);
* ``WAVE_FORMAT_EXTENSIBLE`` with a PCM or float sub-format, and RF64 (``ds64`` sizes).

Refused, with one line naming the file: not RIFF/RIFX/RF64 or not WAVE, no ``fmt `` or no
``data`` chunk, a ``data`` chunk the file does not hold (truncated: the header's size and the
bytes present are named), zero channels / sample rate / block size, a block size that does
not match the channels, a compressed format (A-law, mu-law, ADPCM, MP3), an empty ``data``
chunk, and non-finite float samples.
"""

from __future__ import annotations

import math
import os
import stat
import struct
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO

import numpy as np
from numpy.typing import NDArray

from ..errors import InputError
from ._paths import _kind_name, note_input

__all__ = ["CLIP_RUN", "WavData", "read_wav", "read_wav_file"]

CLIP_RUN = 3  # this many consecutive full-scale samples mean the converter clipped

_PCM, _FLOAT, _EXTENSIBLE = 0x0001, 0x0003, 0xFFFE
_KNOWN = {0x0002: "MS ADPCM", 0x0006: "A-law", 0x0007: "mu-law", 0x0011: "IMA ADPCM", 0x0055: "MP3",
          0x0050: "MPEG", 0x0031: "GSM 6.10", 0x0161: "WMA"}
#: Highest sample rate accepted (Hz): audio converters run at most 768 kHz and ultrasonic
#: recorders a few MHz; 1e9 Hz leaves margin and refuses a header field that is garbage.
MAX_WAV_RATE = 1e9


@dataclass(frozen=True)
class WavData:
    """Decoded samples of a WAV file.

    Attributes
    ----------
    samples:
        (frames,) for one channel or (frames, channels), float64, full scale 1.
    sample_rate:
        Hz.
    channels, bits:
        Channel count and significant bits per sample (the header's).
    kind:
        ``"int"`` (PCM) or ``"float"``.
    step:
        One quantisation step at full scale, ``2**-(8 * container - 1)`` for PCM (the largest
        sample is ``1 - step``), 0 for float.
    """

    samples: NDArray[np.float64]
    sample_rate: float
    channels: int
    bits: int
    kind: str
    step: float


def _fail(label: str, what: str) -> InputError:
    return InputError(f"{label}: {what}")


def _chunks(f: BinaryIO, size: int, end: str, label: str) -> dict[bytes, tuple[int, int]]:
    """Offsets and declared sizes of the top-level chunks (the first of each id)."""
    out: dict[bytes, tuple[int, int]] = {}
    pos = 12
    f.seek(pos)
    while pos + 8 <= size:
        head = f.read(8)
        if len(head) < 8:
            break
        cid, n = head[:4], struct.unpack(end + "I", head[4:])[0]
        out.setdefault(cid, (pos + 8, n))
        if cid == b"data" and n == 0xFFFFFFFF and b"ds64" not in out:
            break  # a streaming writer's placeholder: the data runs to the end (checked below)
        pos += 8 + n + (n & 1)  # chunks are padded to an even size
        f.seek(pos)
    return out


def read_wav_file(path: str | os.PathLike[str], label: str | None = None) -> WavData:
    """Read and decode a WAV file (see the module docstring for the formats).

    Parameters
    ----------
    path:
        A regular file.
    label:
        Name used in the messages (default: the file name).

    Returns
    -------
    WavData
        The samples scaled to full scale 1 and the header's rate, channels and depth.

    Raises
    ------
    InputError
        Missing, not a regular file, not a WAV file, truncated, an unsupported or corrupt
        format, or no samples; the message starts with ``label``.

    Examples
    --------
    >>> import io, tempfile, pathlib
    >>> from scipy.io import wavfile
    >>> p = pathlib.Path(tempfile.mkdtemp()) / "x.wav"
    >>> wavfile.write(p, 8000, np.array([0, 16384, -32768], dtype=np.int16))
    >>> w = read_wav_file(p)
    >>> w.samples.tolist(), w.sample_rate, w.bits
    ([0.0, 0.5, -1.0], 8000.0, 16)
    """
    p = Path(path)
    label = label or p.name
    try:
        st = os.stat(p)
    except FileNotFoundError:
        raise _fail(label, f"missing (expected in {p.parent})") from None
    except OSError as exc:
        raise _fail(label, f"cannot read ({exc.strerror or type(exc).__name__})") from None
    if not stat.S_ISREG(st.st_mode):
        raise _fail(label, f"not a regular file ({_kind_name(st.st_mode)}, in {p.parent})")
    size = st.st_size
    note_input(p, label)
    try:
        with open(p, "rb") as f:
            return _decode(f, size, label)
    except OSError as exc:
        raise _fail(label, f"cannot read ({exc.strerror or type(exc).__name__})") from None
    except MemoryError:
        raise _fail(label, f"too large to read into memory ({size} bytes)") from None


def _decode(f: BinaryIO, size: int, label: str) -> WavData:
    head = f.read(12)
    if len(head) < 12:
        raise _fail(label, f"not a readable WAV file ({size} bytes, shorter than a RIFF header)")
    magic, form = head[:4], head[8:12]
    if magic not in (b"RIFF", b"RIFX", b"RF64") or form != b"WAVE":
        if magic in (b"RIFF", b"RIFX", b"RF64"):
            what = f"a RIFF file of form {form!r}, not 'WAVE'"
        elif head[:6] == b"\x93NUMPY":
            what = "an .npy array"
        elif head[:2] == b"PK":
            what = "a zip / .npz archive"
        else:
            what = f"starts with {head[:4]!r}"
        raise _fail(label, f"not a readable WAV file ({what}; expected a RIFF/WAVE header)")
    end = ">" if magic == b"RIFX" else "<"
    chunks = _chunks(f, size, end, label)
    if b"fmt " not in chunks:
        raise _fail(label, "not a readable WAV file (corrupt header: no 'fmt ' chunk)")
    off, n = chunks[b"fmt "]
    if n < 16 or off + 16 > size:
        raise _fail(label, f"not a readable WAV file (corrupt header: 'fmt ' chunk of {n} bytes, at least 16 needed)")
    f.seek(off)
    fmt = f.read(min(n, 40))
    tag, channels, rate, _byte_rate, block, bits = struct.unpack(end + "HHIIHH", fmt[:16])
    if tag == _EXTENSIBLE:
        if len(fmt) < 40:
            raise _fail(label, "not a readable WAV file (corrupt header: WAVE_FORMAT_EXTENSIBLE 'fmt ' chunk shorter than 40 bytes)")
        tag = struct.unpack(end + "H", fmt[24:26])[0]
    if tag not in (_PCM, _FLOAT):
        name = _KNOWN.get(tag, f"format tag 0x{tag:04x}")
        raise _fail(label, f"not a readable WAV file (compressed or unknown format: {name}); give PCM (8/16/24/32-bit) or float WAV")
    if channels == 0:
        raise _fail(label, "not a readable WAV file (corrupt header: 0 channels)")
    if not 0 < rate <= MAX_WAV_RATE:
        raise _fail(label, f"not a readable WAV file (corrupt header: sample rate {rate} Hz)")
    if block == 0 or block % channels:
        raise _fail(label, f"not a readable WAV file (corrupt header: block size {block} bytes for {channels} channel(s))")
    container = block // channels
    if bits == 0 or bits > 8 * container:
        raise _fail(label, f"not a readable WAV file (corrupt header: {bits} bits per sample in {container}-byte samples)")
    if container > 8:
        raise _fail(label, f"{8 * container}-bit samples are not supported (at most 64)")
    if tag == _FLOAT and container not in (4, 8):
        raise _fail(label, f"{8 * container}-bit float samples are not supported (32 or 64)")
    if b"data" not in chunks:
        raise _fail(label, "not a readable WAV file (no 'data' chunk: no samples, or the file is truncated)")
    doff, dn = chunks[b"data"]
    if magic == b"RF64" or dn == 0xFFFFFFFF:
        dn = _rf64_data_size(f, chunks, end, label, size, doff)
    present = max(size - doff, 0)
    if dn > present:
        raise _fail(label, f"not a readable WAV file (truncated: the header declares {dn} bytes of samples, the file holds {present})")
    if dn == 0:
        raise _fail(label, "contains no samples (empty 'data' chunk)")
    frames = dn // block
    if frames == 0:
        raise _fail(label, f"contains no samples ({dn} bytes, less than one {block}-byte frame)")
    f.seek(doff)
    raw = f.read(frames * block)
    x = _samples(raw, tag, container, end, frames, channels)
    if tag == _FLOAT and not np.isfinite(x).all():
        raise _fail(label, "contains NaN or inf samples")
    step = 0.0 if tag == _FLOAT else math.ldexp(1.0, -(8 * container - 1))
    return WavData(x[:, 0] if channels == 1 else x, float(rate), int(channels), int(bits),
                   "float" if tag == _FLOAT else "int", step)


def _rf64_data_size(f: BinaryIO, chunks: dict[bytes, tuple[int, int]], end: str, label: str, size: int,
                    doff: int) -> int:
    """The data size of an RF64 file (its ``ds64`` chunk) or of a streaming placeholder (to the end)."""
    if b"ds64" in chunks:
        off, n = chunks[b"ds64"]
        if n < 24 or off + 24 > size:
            raise _fail(label, "not a readable WAV file (corrupt RF64 header: short 'ds64' chunk)")
        f.seek(off)
        return int(struct.unpack(end + "Q", f.read(24)[8:16])[0])
    if chunks[b"data"][1] == 0xFFFFFFFF:
        # RIFF written while recording, never finalised: the samples are what the file holds
        return max(size - doff, 0)
    raise _fail(label, "not a readable WAV file (corrupt RF64 header: no 'ds64' chunk)")


def _samples(raw: bytes, tag: int, container: int, end: str, frames: int, channels: int) -> NDArray[np.float64]:
    """(frames, channels) float64 at full scale 1 from the raw little/big-endian bytes."""
    if tag == _FLOAT:
        return np.frombuffer(raw, dtype=f"{end}f{container}").astype(np.float64).reshape(frames, channels)
    if container == 1:  # 8-bit and less: unsigned, offset 128
        u = np.frombuffer(raw, dtype=np.uint8).astype(np.float64)
        return ((u - 128.0) / 128.0).reshape(frames, channels)
    if container in (2, 4, 8):
        n = np.frombuffer(raw, dtype=f"{end}i{container}").astype(np.float64)
    else:  # 3, 5, 6, 7 bytes: sign-extend into int64 (the most significant byte carries the sign)
        b = np.frombuffer(raw, dtype=np.uint8).reshape(-1, container)
        if end == ">":
            b = b[:, ::-1]
        wide = np.zeros((b.shape[0], 8), dtype=np.uint8)
        wide[:, 8 - container:] = b  # left-justified in 64 bits: the sign bit lands on bit 63
        n = (wide.view("<i8")[:, 0] >> (8 * (8 - container))).astype(np.float64)
    return (n / math.ldexp(1.0, 8 * container - 1)).reshape(frames, channels)


def read_wav(path: str | Path) -> tuple[NDArray[np.float64], float]:
    """Read a mono WAV as float (full scale = 1) and refuse clipped or malformed files.

    Integer PCM of any depth (8-bit unsigned, 16, 24, 32-bit signed) is scaled by
    ``2**(bits-1)`` of its container, to [-1, 1); float files (32 / 64 bit) are taken as is
    (:func:`selfcal.io.wav.read_wav_file`). A run of :data:`CLIP_RUN` or more consecutive
    samples at full scale means clipping.

    Returns
    -------
    x : (N,) float64 array
    sample_rate : float, Hz

    Raises
    ------
    InputError
        Missing, unreadable, not a WAV file, truncated (the header declares more samples than
        the file holds), a compressed format, multi-channel, empty or clipped file (the message
        starts with the file name).
    """
    p = Path(path)
    w = read_wav_file(p, p.name)
    if w.channels != 1:
        raise InputError(f"{p.name}: has {w.channels} channels; each receiver needs a mono file")
    x, fs = w.samples, w.sample_rate
    if w.kind == "int":
        at_full = (x >= 1.0 - w.step) | (x <= -1.0)
    else:
        at_full = np.abs(x) >= 1.0
    run = _longest_run(at_full)
    if run >= CLIP_RUN:
        first = int(np.argmax(at_full))
        raise InputError(f"{p.name}: clipped ({run} consecutive samples at full scale, first at "
                         f"{first / fs:.3f} s); record at a lower level")
    return x, float(fs)


def _longest_run(mask: NDArray[np.bool_]) -> int:
    if not mask.any():
        return 0
    padded = np.concatenate(([0], mask.astype(np.int8), [0]))
    edges = np.flatnonzero(np.diff(padded))
    return int((edges[1::2] - edges[::2]).max())
