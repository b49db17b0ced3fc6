"""WAV inputs (recordings' rx_<name>.wav and a probe.wav): every legitimate format is read at
full scale 1, everything else is refused in one line naming the file.

Legitimate: 8-bit unsigned, 16/24/32-bit signed PCM, 32/64-bit float, WAVE_FORMAT_EXTENSIBLE,
big-endian RIFX, RF64, a RIFF size field that is wrong (the chunks are trusted, not it).
Refused: truncated data, an empty data chunk, a non-WAV file named .wav, a compressed format,
corrupt header fields, multi-channel files, a sample rate that differs from setup.json.
The files are written here byte by byte (an independent writer), and the decoded samples are
compared with the integers written (exact: every format's scale is a power of two).
"""

from __future__ import annotations

import json
import shutil
import struct
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from selfcal.acoustics.recording import load_recording, read_wav
from selfcal.cli import main
from selfcal.errors import InputError
from selfcal.io.wav import read_wav_file

from .test_cli import check_contract, snapshot

hypothesis = pytest.importorskip("hypothesis")
from hypothesis import HealthCheck, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

FAST = settings(max_examples=60, deadline=None, suppress_health_check=list(HealthCheck), derandomize=True)
_GUID_TAIL = b"\x00\x00\x00\x00\x10\x00\x80\x00\x00\xaa\x00\x38\x9b\x71"


def riff(payload: bytes, *, tag: int = 1, channels: int = 1, rate: int = 16000, bits: int = 16,
         container: int | None = None, extensible: bool = False, big: bool = False, data_len: int | None = None,
         riff_size: int | None = None, extra_chunks: bytes = b"") -> bytes:
    """A WAV file: RIFF (or RIFX) / fmt (plain or extensible) / optional chunks / data."""
    e = ">" if big else "<"
    cont = container if container is not None else (bits + 7) // 8
    block = channels * cont
    if extensible:
        sub = struct.pack(e + "H", tag) + _GUID_TAIL
        fmt = struct.pack(e + "HHIIHH", 0xFFFE, channels, rate, rate * block, block, 8 * cont)
        fmt += struct.pack(e + "HHI", 22, bits, 0) + sub
    else:
        fmt = struct.pack(e + "HHIIHH", tag, channels, rate, rate * block, block, bits)
    n = len(payload) if data_len is None else data_len
    body = b"WAVE" + b"fmt " + struct.pack(e + "I", len(fmt)) + fmt + extra_chunks
    body += b"data" + struct.pack(e + "I", n) + payload + (b"\x00" if len(payload) % 2 else b"")
    return (b"RIFX" if big else b"RIFF") + struct.pack(e + "I", len(body) if riff_size is None else riff_size) + body


def ints(bits: int, n: int = 500, seed: int = 0) -> np.ndarray:
    """Integer samples of a ``bits``-bit format within +-half scale (no clipping)."""
    rng = np.random.default_rng(seed)
    half = 2 ** (bits - 2)
    return rng.integers(-half, half, n, dtype=np.int64)


def pcm_bytes(v: np.ndarray, cont: int, big: bool = False) -> bytes:
    out = bytearray()
    for x in v.tolist():
        out += int(x).to_bytes(cont, "big" if big else "little", signed=True)
    return bytes(out)


def _write(tmp_path: Path, data: bytes, name: str = "x.wav") -> Path:
    p = tmp_path / name
    p.write_bytes(data)
    return p


# ----------------------------------------------------------------------------- formats read correctly

@pytest.mark.parametrize("bits,cont,extensible,big", [
    (16, 2, False, False), (24, 3, False, False), (32, 4, False, False), (24, 3, True, False),
    (16, 2, False, True), (24, 3, False, True), (20, 3, True, False), (24, 4, True, False), (40, 5, False, False),
    (64, 8, False, False),
])
def test_signed_pcm_is_scaled_by_its_container(tmp_path: Path, bits: int, cont: int, extensible: bool,
                                               big: bool) -> None:
    """n / 2**(8 * container - 1): exact for every depth (a 20-bit sample in 3 bytes is left-justified)."""
    v = ints(bits) << (8 * cont - bits)  # the significant bits left-justified in the container
    p = _write(tmp_path, riff(pcm_bytes(v, cont, big), bits=bits, container=cont, extensible=extensible, big=big))
    x, fs = read_wav(p)
    assert fs == 16000.0 and x.dtype == np.float64 and x.shape == v.shape
    np.testing.assert_array_equal(x, v / 2.0 ** (8 * cont - 1))
    assert np.all((x >= -1) & (x < 1))


def test_8bit_is_unsigned(tmp_path: Path) -> None:
    u = np.random.default_rng(1).integers(64, 192, 400).astype(np.uint8)
    x, _ = read_wav(_write(tmp_path, riff(u.tobytes(), bits=8)))
    np.testing.assert_array_equal(x, (u.astype(float) - 128) / 128)


@pytest.mark.parametrize("dtype,extensible,big", [("f4", False, False), ("f8", False, False), ("f4", True, False),
                                                  ("f8", False, True)])
def test_float_is_taken_as_is(tmp_path: Path, dtype: str, extensible: bool, big: bool) -> None:
    v = np.random.default_rng(2).uniform(-0.9, 0.9, 300).astype(dtype)
    raw = v.astype((">" if big else "<") + dtype).tobytes()
    x, _ = read_wav(_write(tmp_path, riff(raw, tag=3, bits=8 * v.itemsize, extensible=extensible, big=big)))
    np.testing.assert_array_equal(x, v.astype(np.float64))


def test_agrees_with_scipy_on_what_scipy_writes(tmp_path: Path) -> None:
    """An independent reader: scipy's wavfile for the formats it writes (int16 / int32 / float32)."""
    from scipy.io import wavfile

    rng = np.random.default_rng(3)
    for arr, scale in ((rng.integers(-2**14, 2**14, 256).astype(np.int16), 2.0**15),
                       (rng.integers(-2**30, 2**30, 256).astype(np.int32), 2.0**31),
                       (rng.uniform(-0.5, 0.5, 256).astype(np.float32), 1.0)):
        p = tmp_path / f"s{arr.dtype}.wav"
        wavfile.write(p, 22050, arr)
        fs, ref = wavfile.read(p)
        x, fs2 = read_wav(p)
        assert fs2 == fs
        np.testing.assert_array_equal(x, ref.astype(np.float64) / scale)


def test_wrong_riff_size_and_extra_chunks_are_tolerated(tmp_path: Path) -> None:
    """The RIFF size of streaming writers (0 or too large) and LIST / unknown chunks do not matter."""
    v = ints(16)
    junk = b"LIST" + struct.pack("<I", 5) + b"abcde\x00" + b"bext" + struct.pack("<I", 4) + b"1234"
    for riff_size in (0, 0xFFFFFFFF, 7):
        x, _ = read_wav(_write(tmp_path, riff(pcm_bytes(v, 2), riff_size=riff_size, extra_chunks=junk)))
        np.testing.assert_array_equal(x, v / 32768.0)


def test_rf64(tmp_path: Path) -> None:
    v = ints(16, 100)
    payload = pcm_bytes(v, 2)
    fmt = struct.pack("<HHIIHH", 1, 1, 8000, 16000, 2, 16)
    ds64 = b"ds64" + struct.pack("<I", 28) + struct.pack("<QQQI", 0, len(payload), len(v), 0)
    body = b"WAVE" + ds64 + b"fmt " + struct.pack("<I", 16) + fmt + b"data" + struct.pack("<I", 0xFFFFFFFF) + payload
    x, fs = read_wav(_write(tmp_path, b"RF64" + struct.pack("<I", 0xFFFFFFFF) + body))
    assert fs == 8000.0
    np.testing.assert_array_equal(x, v / 32768.0)


def test_multichannel_decoded_frame_by_frame(tmp_path: Path) -> None:
    v = ints(24, 300).reshape(100, 3)
    w = read_wav_file(_write(tmp_path, riff(pcm_bytes(v.ravel(), 3), bits=24, channels=3)))
    assert w.channels == 3 and w.samples.shape == (100, 3)
    np.testing.assert_array_equal(w.samples, v / 2.0**23)


# ----------------------------------------------------------------------------- refused, one line

def _v16() -> bytes:
    return pcm_bytes(ints(16, 1000), 2)


def _patch(data: bytes, at: int, new: bytes) -> bytes:
    return data[:at] + new + data[at + len(new):]


BAD = {
    "truncated": (riff(_v16(), data_len=4000)[:-600], "truncated: the header declares 4000 bytes"),
    "truncated-in-header": (riff(_v16())[:30], "not a readable WAV file"),
    "zero-length": (riff(b""), "contains no samples"),
    "less-than-a-frame": (riff(b"\x01", channels=1, bits=16), "contains no samples"),
    "empty-file": (b"", "not a readable WAV file"),
    "text": (b"time,value\n0,1\n", "not a readable WAV file"),
    "npy": (b"\x93NUMPY\x01\x00v\x00{'descr': '<f8', 'fortran_order': False, 'shape': (3,), }", "npy"),
    "zip": (b"PK\x03\x04" + b"\x00" * 40, "zip"),
    "riff-not-wave": (b"RIFF\x10\x00\x00\x00AVI LIST" + b"\x00" * 8, "not a readable WAV file"),
    "no-fmt": (b"RIFF\x0c\x00\x00\x00WAVEdata\x00\x00\x00\x00", "no 'fmt ' chunk"),
    "no-data": (riff(_v16())[:36], "no 'data' chunk"),
    "short-fmt": (b"RIFF\x14\x00\x00\x00WAVEfmt \x04\x00\x00\x00\x01\x00\x01\x00", "'fmt ' chunk of 4 bytes"),
    "alaw": (riff(b"\x00" * 100, tag=6, bits=8), "A-law"),
    "mulaw": (riff(b"\x00" * 100, tag=7, bits=8), "mu-law"),
    "adpcm-extensible": (riff(b"\x00" * 100, tag=2, bits=4, container=1, extensible=True), "ADPCM"),
    "zero-channels": (riff(_v16(), channels=0), "0 channels"),
    "zero-rate": (riff(_v16(), rate=0), "sample rate 0"),
    "block-mismatch": (_patch(riff(_v16(), channels=2), 32, struct.pack("<H", 5)), "block size 5 bytes for 2"),
    "bits-beyond-container": (riff(_v16(), bits=24, container=2), "24 bits per sample"),
    "float16": (riff(_v16(), tag=3, bits=16), "16-bit float"),
    "float-nan": (riff(np.array([0.1, np.nan, 0.2], "<f4").tobytes(), tag=3, bits=32), "NaN or inf"),
    "float-inf": (riff(np.array([0.1, np.inf], "<f8").tobytes(), tag=3, bits=64), "NaN or inf"),
    "clipped": (pcm_bytes(np.array([0, 32767, 32767, 32767, 0]), 2), "clipped"),
    "stereo": (riff(_v16(), channels=2), "2 channels"),
}
BAD["clipped"] = (riff(BAD["clipped"][0]), "clipped")


@pytest.mark.parametrize("case", sorted(BAD))
def test_malformed_wav_refused_by_name(tmp_path: Path, case: str) -> None:
    data, match = BAD[case]
    p = _write(tmp_path, data, "rx_a.wav")
    with pytest.raises(InputError, match="rx_a.wav: ") as info:
        read_wav(p)
    assert match in str(info.value), str(info.value)
    assert "\n" not in str(info.value)


def test_not_a_file(tmp_path: Path) -> None:
    (tmp_path / "d.wav").mkdir()
    with pytest.raises(InputError, match="d.wav: not a regular file .a directory"):
        read_wav(tmp_path / "d.wav")
    with pytest.raises(InputError, match="missing"):
        read_wav(tmp_path / "none.wav")


@given(pos=st.integers(0, 60), byte=st.integers(0, 255), cut=st.integers(0, 200), kind=st.sampled_from(
    ["pcm16", "pcm24", "u8", "f32", "ext"]))
@FAST
def test_corrupted_headers_never_escape(tmp_path_factory, pos: int, byte: int, cut: int, kind: str) -> None:  # type: ignore[no-untyped-def]
    """Any byte of the first 60 changed, any tail cut: samples in [-1, 1] or an InputError, nothing else."""
    v = ints(16, 100)
    base = {"pcm16": riff(pcm_bytes(v, 2)), "pcm24": riff(pcm_bytes(v, 3), bits=24),
            "u8": riff((v % 256).astype(np.uint8).tobytes(), bits=8),
            "f32": riff((v / 2**15).astype("<f4").tobytes(), tag=3, bits=32),
            "ext": riff(pcm_bytes(v, 3), bits=24, extensible=True)}[kind]
    data = bytearray(base)
    data[min(pos, len(data) - 1)] = byte
    data = data[: max(len(data) - cut, 0)]
    p = tmp_path_factory.mktemp("w") / "rx.wav"
    p.write_bytes(bytes(data))
    try:
        x, fs = read_wav(p)
    except InputError as exc:
        assert str(exc).startswith("rx.wav: ") and "\n" not in str(exc)
        return
    assert fs > 0 and x.ndim == 1 and x.size > 0 and np.all(np.abs(x) <= 1.0)


# ----------------------------------------------------------------------------- recordings and the command line

@pytest.fixture(scope="module")
def recording(tmp_path_factory) -> Path:  # type: ignore[no-untyped-def]
    """A 6-unit anechoic simulation at 16 kHz (16-bit WAVs), written once."""
    d = tmp_path_factory.mktemp("rec") / "rec"
    res = CliRunner().invoke(main, ["simulate", "conference", "--units", "6", "--sample-rate", "16000",
                                    "--max-order", "0", "--room", "6x6x3", "--out", str(d)])
    assert res.exit_code == 0, res.output
    return d


def _convert(src: Path, dst: Path, fmt: str) -> None:
    """Copy a recording with every rx WAV re-encoded in ``fmt`` (the same samples where exact)."""
    shutil.copytree(src, dst)
    for p in sorted(dst.glob("rx_*.wav")):
        x, fs = read_wav(p)
        n16 = np.round(x * 32768).astype(np.int64)  # the 16-bit integers written by the simulation
        if fmt == "pcm24":
            data = riff(pcm_bytes(n16 << 8, 3), bits=24, rate=int(fs))
        elif fmt == "pcm32-ext":
            data = riff(pcm_bytes(n16 << 16, 4), bits=32, rate=int(fs), extensible=True)
        elif fmt == "f32":
            data = riff((n16 / 32768).astype("<f4").tobytes(), tag=3, bits=32, rate=int(fs))
        elif fmt == "f64":
            data = riff((n16 / 32768).astype("<f8").tobytes(), tag=3, bits=64, rate=int(fs))
        else:  # u8: the top 8 bits (coarser, but a legitimate file)
            data = riff(((n16 >> 8) + 128).astype(np.uint8).tobytes(), bits=8, rate=int(fs))
        p.write_bytes(data)


@pytest.mark.parametrize("fmt", ["pcm24", "pcm32-ext", "f32", "f64", "u8"])
def test_recording_in_every_format_loads_the_same_samples(recording: Path, tmp_path: Path, fmt: str) -> None:
    ref = load_recording(recording).signals
    _convert(recording, tmp_path / "r", fmt)
    got = load_recording(tmp_path / "r").signals
    assert got.shape == ref.shape
    tol = 1.0 / 128 if fmt == "u8" else 0.0  # u8 keeps the top 8 bits: within one 8-bit step
    assert np.max(np.abs(got - ref)) <= tol + 1e-12


@pytest.mark.parametrize("fmt", ["pcm24", "f32"])
def test_pipeline_reads_24bit_and_float_recordings(recording: Path, tmp_path: Path, fmt: str) -> None:
    """The same exit status and positions as the 16-bit original (the samples are identical)."""
    _convert(recording, tmp_path / "r", fmt)
    runs = {}
    for name, d in (("16", recording), (fmt, tmp_path / "r")):
        res = CliRunner().invoke(main, ["pipeline", str(d), "--heights", str(d / "heights.json"),
                                        "-o", str(tmp_path / f"{name}.json")])
        code, _, _ = check_contract(res)
        assert code in (0, 1)
        runs[name] = (code, json.loads((tmp_path / f"{name}.json").read_text()))
    assert runs["16"][0] == runs[fmt][0]
    np.testing.assert_allclose(runs["16"][1]["receivers"], runs[fmt][1]["receivers"], atol=1e-9)


@pytest.mark.parametrize("case", ["truncated", "zero-length", "text", "stereo", "rate-mismatch", "probe-rate",
                                  "probe-stereo", "alaw"])
def test_pipeline_refuses_bad_wavs_in_one_line(recording: Path, tmp_path: Path, case: str) -> None:
    d = tmp_path / "r"
    shutil.copytree(recording, d)
    target = sorted(d.glob("rx_*.wav"))[1]
    x, fs = read_wav(target)
    n16 = pcm_bytes(np.round(x * 32768).astype(np.int64), 2)
    match = target.name
    if case == "rate-mismatch":  # one receiver recorded at another rate than setup.json says
        target.write_bytes(riff(n16, rate=int(fs) // 2))
        match = "differs from setup.json"
    elif case.startswith("probe"):
        setup = json.loads((d / "setup.json").read_text())
        setup["probe"] = {"wav": "probe.wav"}
        (d / "setup.json").write_text(json.dumps(setup))
        chirp = pcm_bytes(np.round(8000 * np.sin(np.arange(800) ** 2 * 1e-3)).astype(np.int64), 2)
        (d / "probe.wav").write_bytes(riff(chirp, rate=int(fs) * 2) if case == "probe-rate" else
                                      riff(chirp * 2, channels=2, rate=int(fs)))
        match = "probe.wav"
    elif case in BAD:
        target.write_bytes(BAD[case][0])
    before = snapshot(tmp_path)
    res = CliRunner().invoke(main, ["pipeline", str(d), "-o", str(tmp_path / "out.json")])
    code, _, err = check_contract(res, before, snapshot(tmp_path))
    assert code == 2 and match in err, err
