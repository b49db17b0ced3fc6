"""Fuzz sweep over every CLI command (not a test; run by hand): malformed files, options, output paths.

``PYTHONPATH=src OPENBLAS_NUM_THREADS=1 python tests/fuzz/sweep_cli.py SEED N_PER_COMMAND`` (env
``ONLY=sweep_toa`` or ``SKIP_CHEAP=1``) prints the exit codes per command and every contract
breach (traceback, exit code other than 0/1/2, more than one stderr line, an internal error,
a run longer than 20 s or killed at 60 s, a FIFO / link at an output path changed, an input
file changed, an output aimed at an input (``CLASH`` share of the runs, default 0.1: the
input itself, a symlink to it or a file in an input folder) not refused with exit 2). Each run is
logged to ``$SWEEP_LOG`` (default: a file in the temporary folder). The defects it found are
reproduced in ``test_sweep_findings.py``.
"""
from __future__ import annotations

import collections
import json
import os
import shutil
import signal
import struct
import sys
import tempfile
import time
import traceback
from pathlib import Path

import numpy as np
from click.testing import CliRunner
from scipy.io import savemat, wavfile

from selfcal.cli import main

SEED = int(sys.argv[1]) if len(sys.argv) > 1 else 0
N_PER = int(sys.argv[2]) if len(sys.argv) > 2 else 30
rng = np.random.default_rng(SEED)
ROOT = Path(tempfile.mkdtemp(prefix="sweep"))
LOG = os.environ.get("SWEEP_LOG", str(ROOT) + ".log")
HERE = Path(__file__).resolve().parent
DATA = HERE.parents[1].parent / "shared" / "data"
counts: dict[str, collections.Counter] = collections.defaultdict(collections.Counter)
problems: list[str] = []


class Hang(BaseException):
    pass


def _alarm(*_):  # type: ignore[no-untyped-def]
    raise Hang()


signal.signal(signal.SIGALRM, _alarm)


OUT_FLAGS = {"-o", "--out", "--csv", "--plot", "--report", "--tum"}
CLASH = float(os.environ.get("CLASH", "0.1"))  # share of runs whose output is aimed at one of their inputs


def _input_bytes(paths: list[Path]) -> dict[str, bytes]:
    """The bytes of every regular file among ``paths`` and under the folders among them."""
    out: dict[str, bytes] = {}
    for p in paths:
        files = [Path(r) / n for r, _, fs in os.walk(p) for n in fs] if p.is_dir() else [p]
        for f in files[:200]:
            try:
                if f.is_file():
                    out[str(f)] = f.read_bytes()
            except OSError:
                pass
    return out


def run(cmd: str, args: list, kind: str, limit: int = 60) -> int:
    t0 = time.time()
    args = list(args)
    outs = [k + 1 for k, a in enumerate(args[:-1]) if str(a) in OUT_FLAGS]
    ins = [Path(a) for k, a in enumerate(args) if k not in outs and str(a) not in ("-", "")
           and isinstance(a, (str, Path)) and os.path.sep in str(a) and os.path.exists(a)]
    clash = bool(outs and ins and rng.random() < CLASH)
    if clash:  # the output names an input: itself, a symlink to it, or a file inside an input folder
        victim = ins[int(rng.integers(len(ins)))]
        if victim.is_dir():
            inner = [Path(r) / n for r, _, fs in os.walk(victim) for n in fs]
            victim = inner[0] if inner and rng.random() < 0.7 else victim
        if rng.random() < 0.5:
            link = ROOT / f"clash-{len(list(ROOT.iterdir()))}"
            os.symlink(victim.resolve(), link)
            victim = link
        args[outs[int(rng.integers(len(outs)))]] = victim
        kind += "/clash"
    before = _input_bytes(ins)
    with open(LOG + ".last", "a") as fh:
        fh.write(f"{cmd} {kind} {[str(a) for a in args]}\n")
    signal.alarm(limit)
    try:
        res = CliRunner().invoke(main, [str(a) for a in args], catch_exceptions=True)
    except Hang:
        problems.append(f"HANG>{limit}s {cmd} [{kind}] {args}")
        counts[cmd]["hang"] += 1
        return -1
    finally:
        signal.alarm(0)
    dt = time.time() - t0
    err = res.stderr
    out = res.stdout
    bad = None
    if res.exception is not None and not isinstance(res.exception, SystemExit):
        bad = f"exception {type(res.exception).__name__}: {res.exception}"
        bad += " | " + "".join(traceback.format_exception(res.exception)[-3:]).replace("\n", " ")[:400]
    elif "Traceback" in out + err:
        bad = "traceback in output"
    elif res.exit_code not in (0, 1, 2):
        bad = f"exit {res.exit_code}"
    elif res.exit_code == 2:
        lines = [ln for ln in err.splitlines() if ln.strip()]
        if len(lines) != 1 or not lines[0].startswith("selfcal: error:"):
            bad = f"stderr not one line: {err[:300]!r}"
        elif "internal error" in lines[0]:
            bad = lines[0][:300]
    elif res.exit_code == 1 and not any(ln.startswith("FAIL") for ln in out.splitlines()):
        bad = "exit 1 without FAIL line"
    changed = [f for f, data in before.items() if not os.path.exists(f) or Path(f).read_bytes() != data]
    if changed and not bad:
        bad = f"an input changed: {changed[:3]}"
    if clash and res.exit_code != 2 and not bad:
        bad = f"an output named an input, exit {res.exit_code}"
    with open(LOG, "a") as fh:
        fh.write(f"{res.exit_code} | {cmd} | {kind} | {(err.strip().splitlines() or [''])[0][:250]}\n")
    counts[cmd][res.exit_code] += 1
    counts[cmd]["n"] += 1
    if dt > 20:
        problems.append(f"SLOW {dt:.0f}s {cmd} [{kind}] {args}")
    if bad:
        problems.append(f"{cmd} [{kind}] {bad} ARGS {args}")
    return res.exit_code


# ----------------------------------------------------------------------------- malformed text files

def pick(xs):
    return xs[int(rng.integers(0, len(xs)))]


def toa_matrix(I=6, J=8):
    R, S = rng.uniform(0, 10, (I, 3)), rng.uniform(0, 10, (J, 3))
    return np.linalg.norm(R[:, None] - S[None], axis=2) + 0.01 * rng.normal(size=(I, J))


def ff_matrix(m=8, k=10):
    Z, n = rng.normal(size=(m, 3)), rng.normal(size=(k, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    return Z @ n.T + 1e-3 * rng.normal(size=(m, k))


def csv_text(M, sep=",", header=False, names=False, dup=False, uni=False):
    rows = []
    if header:
        hn = [f"s{j}" for j in range(M.shape[1])]
        if dup:
            hn[-1] = hn[0]
        if uni:
            hn = [f"ß源{j}\u200b" for j in range(M.shape[1])]
        rows.append(sep.join((["name"] if names else []) + hn))
    for i, r in enumerate(M):
        cells = [f"{v:.6g}" for v in r]
        if names:
            nm = f"r{i}" if not dup else "r0"
            if uni:
                nm = f"ñ{i}😀"
            cells = [nm] + cells
        rows.append(sep.join(cells))
    return "\n".join(rows) + "\n"


def mutate(text: str) -> bytes:
    """One random malformation of a valid CSV text."""
    k = rng.integers(0, 22)
    lines = text.splitlines()
    if k == 0:
        return b""
    if k == 1:
        return rng.bytes(int(rng.integers(1, 400)))
    if k == 2:
        return b"\xef\xbb\xbf" + text.encode()
    if k == 3:
        return text.replace(",", ":").encode()  # unknown delimiter
    if k == 4:
        i = int(rng.integers(0, len(lines)))
        lines[i] = lines[i] + ",1"
        return "\n".join(lines).encode()
    if k == 5:
        cells = [c for c in ["nan", "inf", "-inf", "NaN", "Infinity", "1e309", "-1e309"]]
        t = text.split(",")
        for _ in range(3):
            t[int(rng.integers(0, len(t)))] = str(rng.choice(cells))
        return ",".join(t).encode()
    if k == 6:
        t = text.split(",")
        t[int(rng.integers(0, len(t)))] = "1e308"
        return ",".join(t).encode()
    if k == 7:
        return (lines[0] + "\n").encode()  # one row
    if k == 8:
        return ("\n".join(ln.split(",")[0] for ln in lines) + "\n").encode()  # one column
    if k == 9:
        return text.replace("\n", "\r").encode()  # CR only
    if k == 10:
        return text.encode("utf-16")
    if k == 11:
        return text.encode() + b"\x00\x00"
    if k == 12:
        return ("\n".join(",".join(["1e300"] * 8) for _ in range(6)) + "\n").encode()
    if k == 13:
        return ("\n".join(",".join(["0"] * 8) for _ in range(6)) + "\n").encode()
    if k == 14:
        return ("\n".join(",".join(["-1"] * 8) for _ in range(6)) + "\n").encode()
    if k == 15:
        return ("#" + text.replace("\n", "\n#")).encode()  # only comments
    if k == 16:
        return ("x," * 1000 + "\n").encode()
    if k == 17:
        return ('"' + text).encode()  # unbalanced quote
    if k == 18:
        return text.replace(".", ",").replace(",", ";", 3).encode()
    if k == 19:
        return ("\n".join(",".join(["NA"] * 8) for _ in range(6)) + "\n").encode()
    if k == 20:
        return "\n".join(lines[:2] + [""] * 50 + lines[2:]).encode()
    return (text * 3).encode()


def matrix_file(d: Path, M, kind: str) -> Path:
    choice = rng.integers(0, 10)
    if choice == 0:  # npy variants
        p = d / "m.npy"
        v = rng.integers(0, 6)
        arr = [M, M.astype(np.float16), np.asfortranarray(M), M.astype(np.int32), M[None], M.astype(complex)][v]
        np.save(p, arr)
        return p
    if choice == 1:
        p = d / "m.npy"
        p.write_bytes(rng.bytes(int(rng.integers(0, 300))) if rng.random() < 0.5 else b"\x93NUMPY" + rng.bytes(100))
        return p
    if choice == 2:
        p = d / "m.csv"
        p.mkdir()
        return p
    p = d / ("m.csv" if rng.random() < 0.8 else "m.txt")
    sep = str(rng.choice([",", ";", "\t", " "]))
    txt = csv_text(M, sep=sep, header=bool(rng.random() < 0.4), names=bool(rng.random() < 0.4),
                   dup=bool(rng.random() < 0.2), uni=bool(rng.random() < 0.2))
    p.write_bytes(mutate(txt) if rng.random() < 0.7 else txt.encode())
    return p


def out_target(d: Path, kind: str = "file") -> tuple[Path, str]:
    c = rng.integers(0, 8)
    if c == 0:
        p = d / "outdir"
        p.mkdir(exist_ok=True)
        return p, "dir"
    if c == 1:
        p = d / "devnull"
        if not p.exists():
            os.symlink("/dev/null", p)
        return p, "devnull-link"
    if c == 2:
        p = d / "fifo"
        if not p.exists():
            os.mkfifo(p)
        return p, "fifo"
    if c == 3:
        p = d / "afile"
        p.write_text("x")
        return p / "sub.json", "under-file"
    return d / ("res.json" if kind == "file" else "resdir"), "ok"


def nonregular_untouched(d: Path) -> None:
    for n in ("devnull", "fifo"):
        p = d / n
        if p.exists() and os.path.islink(p) and os.readlink(p) != "/dev/null":
            problems.append(f"{d}: link {n} changed")
    if (d / "fifo").exists() and not __import__("stat").S_ISFIFO(os.lstat(d / "fifo").st_mode):
        problems.append(f"{d}: fifo replaced")


def new_dir(tag: str) -> Path:
    d = ROOT / f"{tag}-{len(list(ROOT.iterdir()))}"
    d.mkdir()
    return d


# ----------------------------------------------------------------------------- per command

def sweep_toa() -> None:
    for _ in range(N_PER):
        d = new_dir("toa")
        p = matrix_file(d, toa_matrix(int(rng.integers(3, 9)), int(rng.integers(3, 11))), "toa")
        o, ok = out_target(d)
        extra = []
        if rng.random() < 0.3:
            extra += list(pick([["--speed", "343"], ["--unit", "mm"], ["--dim", "2"], ["--offsets", "both"],
                                      ["--loss", "huber"], ["--method", "nls"], ["--noise", "0.01"],
                                      ["--frame", "origin=r0,x=r1,xy=r2"], ["--frame", "garbage"],
                                      ["--unit", "samples", "--speed", "343", "--sample-rate", "48000"]]))
        if rng.random() < 0.2:
            k = d / "known.csv"
            k.write_bytes(mutate("r0,0,0,0\nr1,1,0,0\nr2,0,1,0\n"))
            extra += ["--known", k]
        if rng.random() < 0.2:
            extra += ["--csv", out_target(d)[0]]
        if rng.random() < 0.1:
            extra += ["--plot", d / "p.xyz"]
        run("calibrate toa", ["calibrate", "toa", p, "-o", o, *extra], f"{p.name}/{ok}")
        nonregular_untouched(d)


def sweep_ff() -> None:
    pyr = DATA / "pyramic" / "pyramic_tdoa_speaker0.json"
    base = json.loads(pyr.read_text()) if pyr.exists() else None
    for _ in range(N_PER):
        d = new_dir("ff")
        if base is not None and rng.random() < 0.25:
            b = json.loads(json.dumps(base))
            key = str(rng.choice(list(b)))
            b[key] = [None, "x", 1e308, [], {}, -1, float("nan"), [[1, 2], [3]]][int(rng.integers(0, 8))]
            p = d / "p.json"
            try:
                p.write_text(json.dumps(b))
            except ValueError:
                p.write_text("{")
            if rng.random() < 0.3:
                p.write_bytes(mutate(p.read_text())[:5000])
        else:
            p = matrix_file(d, ff_matrix(int(rng.integers(2, 10)), int(rng.integers(2, 12))), "ff")
        o, ok = out_target(d)
        extra = []
        if rng.random() < 0.3:
            extra += list(pick([["--speed", "343"], ["--method", "alternating"], ["--ransac"],
                                      ["--allow-degenerate"], ["--loss", "cauchy"], ["--dim", "2"],
                                      ["--noise-std", "0.01"], ["--directions", "sources"]]))
        if rng.random() < 0.15:
            q = d / "dirs.csv"
            q.write_bytes(mutate(csv_text(rng.normal(size=(10, 3)))))
            extra += ["--directions", q]
        run("calibrate tdoa-farfield", ["calibrate", "tdoa-farfield", p, "-o", o, *extra], f"{p.name}/{ok}")
        nonregular_untouched(d)


def sweep_aoa() -> None:
    for _ in range(N_PER):
        d = new_dir("aoa")
        nb = int(rng.integers(1, 7))
        B = rng.uniform(-5, 5, (nb, 3))
        U = rng.normal(size=(nb, 3))
        U /= np.linalg.norm(U, axis=1, keepdims=True)
        b = matrix_file(d, B, "b")
        u = d / "u.csv"
        u.write_bytes(mutate(csv_text(U)) if rng.random() < 0.5 else csv_text(U).encode())
        o, ok = out_target(d)
        extra = []
        if rng.random() < 0.4:
            extra += list(pick([["--angles", "azel"], ["--angles", "axes", "--units", "rad"],
                                      ["--method", "ml"], ["--hint", "1,2,3"], ["--hint", "nan,1"],
                                      ["--sigma-deg", "2"], ["--method", "linear"]]))
        run("locate aoa", ["locate", "aoa", b, u, "-o", o, *extra], f"{b.name}/{ok}")
        nonregular_untouched(d)


def _wav_bytes(x16, rate=16000, bits=16, tag=1, channels=1):
    cont = (bits + 7) // 8
    block = channels * cont
    fmt = struct.pack("<HHIIHH", tag, channels, rate, rate * block, block, bits)
    body = b"WAVE" + b"fmt " + struct.pack("<I", 16) + fmt + b"data" + struct.pack("<I", len(x16)) + x16
    return b"RIFF" + struct.pack("<I", len(body)) + body


def sweep_pipeline(rec: Path) -> None:
    setup = json.loads((rec / "setup.json").read_text())
    for _ in range(N_PER):
        d = new_dir("pipe")
        r = d / "rec"
        shutil.copytree(rec, r)
        k = int(rng.integers(0, 10))
        wavs = sorted(r.glob("rx_*.wav"))
        target = wavs[int(rng.integers(0, len(wavs)))]
        kind = ""
        if k == 0:  # setup.json mutated
            s = json.loads(json.dumps(setup))
            key = str(rng.choice(list(s)))
            s[key] = [None, "x", 1e308, [], {}, -1, 0, True, [[1]], {"a": 1}][int(rng.integers(0, 10))]
            (r / "setup.json").write_text(json.dumps(s))
            kind = f"setup.{key}"
        elif k == 1:
            (r / "setup.json").write_bytes(mutate((r / "setup.json").read_text()))
            kind = "setup-bytes"
        elif k == 2:  # a WAV byte-mutated
            data = bytearray(target.read_bytes())
            for _ in range(int(rng.integers(1, 6))):
                data[int(rng.integers(0, 64))] = int(rng.integers(0, 256))
            target.write_bytes(bytes(data[: len(data) - int(rng.integers(0, 3)) * int(rng.integers(0, 5000))]))
            kind = "wav-bytes"
        elif k == 3:  # a WAV in another format / rate / channels
            fs, x = wavfile.read(target)
            v = int(rng.integers(0, 5))
            if v == 0:
                wavfile.write(target, fs // 2, x)
            elif v == 1:
                wavfile.write(target, fs, np.column_stack([x, x]))
            elif v == 2:
                wavfile.write(target, fs, (x / 32768).astype(np.float32))
            elif v == 3:
                wavfile.write(target, fs, (x.astype(np.int32) << 16))
            else:
                target.write_bytes(_wav_bytes(((x >> 8) + 128).astype(np.uint8).tobytes(), fs, bits=8))
            kind = f"wav-format{v}"
        elif k == 4:
            target.unlink()
            if rng.random() < 0.5:
                target.mkdir()
            kind = "wav-missing/dir"
        elif k == 5:  # heights / truth fuzz
            h = d / "h.json"
            h.write_bytes(mutate(json.dumps({"receivers": [0.7] * 6, "senders": [0.7] * 6})))
            kind = "heights"
            run("pipeline", ["pipeline", r, "--heights", h, "-o", d / "r.json"], kind)
            continue
        elif k == 6:
            (r / "truth.json").write_bytes(mutate((r / "truth.json").read_text()))
            kind = "truth"
        elif k == 7:
            (r / "probe.wav").write_bytes(_wav_bytes(rng.bytes(1000), 16000))
            s = dict(setup, probe={"wav": "probe.wav"})
            (r / "setup.json").write_text(json.dumps(s))
            kind = "probe.wav"
        elif k == 8:  # outputs
            o, kind = out_target(d)
            extra = list(pick([["--plot", out_target(d)[0]], ["--report", out_target(d)[0]],
                                     ["--csv", out_target(d)[0]], []]))
            run("pipeline", ["pipeline", r, "-o", o, *extra], "out-" + kind)
            nonregular_untouched(d)
            continue
        else:
            kind = "options"
            extra = list(pick([["--temperature", "25", "--speed-of-sound", "343"], ["--humidity", "50"],
                                     ["--dim", "2"], ["--jitter", "1e-5"], ["--seed", "-3"], ["--dim", "3"]]))
            run("pipeline", ["pipeline", r, "-o", d / "r.json", *extra], kind)
            continue
        run("pipeline", ["pipeline", r, "--heights", r / "heights.json", "-o", d / "r.json"], kind)


def sweep_slac_run(log: Path) -> None:
    z = dict(np.load(log, allow_pickle=False))
    for _ in range(N_PER):
        d = new_dir("slacrun")
        p = d / "log.npz"
        k = int(rng.integers(0, 4))
        if k == 0:
            p.write_bytes(rng.bytes(int(rng.integers(0, 500))))
        elif k == 1:
            m = dict(z)
            key = str(rng.choice(list(m)))
            m[key] = [np.array([]), np.array(np.nan), m[key].astype(np.float16) if m[key].dtype.kind == "f" else
                      m[key], np.full(m[key].shape, np.inf) if m[key].dtype.kind in "fc" else np.atleast_1d(m[key])[:1],
                      np.zeros((2, 2, 2)), np.array(["x"])][int(rng.integers(0, 6))]
            np.savez(p, **m)
        elif k == 2:
            m = dict(z)
            m.pop(str(rng.choice(list(m))))
            np.savez(p, **m)
        else:
            p.write_bytes(log.read_bytes()[: int(rng.integers(0, log.stat().st_size))])
        o, ok = out_target(d)
        run("slac run", ["slac", "run", p, "-o", o], f"k{k}/{ok}", limit=120)
        nonregular_untouched(d)


def sweep_plaza() -> None:
    sys.path.insert(0, str(HERE.parent / "datasets"))
    from cmu_logs import cmu_log  # type: ignore[import-not-found]

    for _ in range(N_PER // 2):
        d = new_dir("plaza")
        m, _ = cmu_log(int(rng.integers(0, 100)), duration=40.0)
        k = int(rng.integers(0, 5))
        p = d / "log.mat"
        if k == 0:
            p.write_bytes(rng.bytes(200))
        elif k == 1:
            key = str(rng.choice(list(m)))
            m[key] = [np.array([]), np.full((3, 4), np.nan), np.array([["a"]]), np.zeros((2, 1)), 1e308 * m[key],
                      -m[key]][int(rng.integers(0, 6))]
            savemat(p, m)
        elif k == 2:
            m.pop(str(rng.choice(list(m))))
            savemat(p, m)
        elif k == 3:
            savemat(p, m)
            p.write_bytes(p.read_bytes()[: int(rng.integers(0, p.stat().st_size))])
        else:
            savemat(p, m)
        o, ok = out_target(d)
        extra = list(pick([["--method", "filter"], ["--init-heading-offset", "0.1"], ["--csv", out_target(d)[0]],
                                 ["--tum", out_target(d)[0]], []]))
        run("slac plaza", ["slac", "plaza", p, "-o", o, "--method", "filter", *extra], f"k{k}/{ok}", limit=120)
        nonregular_untouched(d)


def sweep_cheap_commands() -> None:
    """Option / output-path fuzz for the commands that simulate or reproduce (they must fail up front)."""
    ints = ["0", "-1", "1e20", "99999999999999999999", "x", "", "2.5", "nan"]
    nums = ["0", "-1", "nan", "inf", "1e308", "x", "", "1e-300"]
    specs = {
        "simulate conference": (["simulate", "conference"], {"--units": ints, "--rt60": nums, "--snr": nums,
                                "--sample-rate": ints, "--max-order": ints, "--rounds": ints, "--room":
                                ["0x1x1", "1x1", "axbxc", "1e308x1x1", "-1x2x3", "1x1x1"], "--seed": ints}),
        "demo": (["demo"], {"--units": ints, "--rt60": nums, "--snr": nums, "--seed": ints, "--room": ["1x1x1", "q"]}),
        "slac simulate": (["slac", "simulate"], {"--minutes": nums, "--subcarriers": ints, "--snr-db": nums,
                                                "--seed": ints}),
        "reproduce aoa": (["reproduce", "aoa"], {"--runs": ints, "--step": nums, "--sigma-deg": nums,
                                                "--seed": ints, "--backend": ["x"], "--scheduler": ["tcp://nowhere:1"]}),
        "reproduce delays": (["reproduce", "delays"], {"--runs": ints, "--faithful-runs": ints, "--max-iter": ints,
                                                      "--cap-120": ints, "--noise-runs": ints}),
        "reproduce farfield": (["reproduce", "farfield"], {"--runs": ints, "--seed": ints}),
        "reproduce slac": (["reproduce", "slac"], {"--minutes": nums, "--subcarriers": ints, "--runs": ints,
                                                  "--smoother-lag": ints}),
        "reproduce toa-mds-nls": (["reproduce", "toa-mds-nls"], {"--runs": ints}),
        "reproduce lps": (["reproduce", "lps"], {"--simulate": ints, "--variants": ["x", "", ",,"]}),
    }
    for name, (base, opts) in specs.items():
        for opt, vals in opts.items():
            for v in vals:
                d = new_dir("cheap")
                o, ok = out_target(d, "dir")
                args = [*base, opt, v, "--out", o]
                if name == "reproduce lps":
                    args += ["--data", str(DATA / "lps" / "data4.mat")]
                if name in ("simulate conference",) and opt not in ("--units", "--sample-rate", "--max-order"):
                    args += ["--units", "5", "--sample-rate", "8000", "--max-order", "0"]
                if name == "slac simulate" and opt != "--minutes":
                    args += ["--minutes", "0.02"]
                if name == "slac simulate":
                    args[-3:-1] = ["-o", d / "log.npz"] if ok == "ok" else ["-o", o]
                # commands that would legitimately run for long on valid values: skip those values
                legit = _legit(name, opt, v)
                if legit:
                    continue
                run(name, args, f"{opt}={v}/{ok}", limit=60)
                nonregular_untouched(d)


def _legit(name: str, opt: str, v: str) -> bool:
    """Values that are valid and would start a long reproduction / simulation (not fuzz targets)."""
    try:
        f = float(v)
    except ValueError:
        return False
    if opt == "--smoother-lag":
        return f == f and f >= 0 and f == int(f)
    if name.startswith("reproduce") or name == "demo":
        return f == f and 0 <= f < 1e6
    if name == "simulate conference":
        return opt in ("--seed",) and f >= 0 and f == int(f) and f < 1e6
    return False


def main_() -> None:
    t0 = time.time()
    rec = ROOT / "baserec"
    res = CliRunner().invoke(main, ["simulate", "conference", "--units", "6", "--sample-rate", "16000",
                                    "--max-order", "0", "--room", "6x6x3", "--out", str(rec)])
    assert res.exit_code == 0, res.output
    log = ROOT / "base.npz"
    res = CliRunner().invoke(main, ["slac", "simulate", "--minutes", "0.05", "--subcarriers", "16", "-o", str(log)])
    assert res.exit_code == 0, res.output
    only = os.environ.get("ONLY")
    for f, a in ((sweep_toa, ()), (sweep_ff, ()), (sweep_aoa, ()), (sweep_pipeline, (rec,)),
                 (sweep_slac_run, (log,)), (sweep_plaza, ()), (sweep_cheap_commands, ())):
        t = time.time()
        if (only and f.__name__ != only) or (os.environ.get("SKIP_CHEAP") and f.__name__ == "sweep_cheap_commands"):
            continue
        f(*a)
        print(f"{f.__name__}: {time.time() - t:.0f} s", flush=True)
    print("COUNTS")
    for k, c in sorted(counts.items()):
        print(f"  {k}: n={c['n']} exit0={c[0]} exit1={c[1]} exit2={c[2]} hang={c['hang']}")
    print(f"PROBLEMS ({len(problems)}):")
    for p in problems:
        print("  " + p[:700])
    print(f"total {time.time() - t0:.0f} s")
    shutil.rmtree(ROOT, ignore_errors=True)


if __name__ == "__main__":
    main_()
