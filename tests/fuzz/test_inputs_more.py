"""More malformed inputs through the command line: JSON leaves of the wrong type, ragged and
deep nesting, non-finite / overflowing / underflowing numbers, empty files, BOMs, CRLF / CR line
ends, unicode and newline file names, special files as inputs, symlinked output folders.

Contract (DESIGN.md, "Inputs and outputs"): exit 0, 1 (a ``FAIL:`` line) or 2 (exactly one
``selfcal: error:`` line, not an internal error); never a traceback; a failed run leaves the
folder as it was. Cases marked "before:" are reproducers of defects this file was written for.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest

from selfcal.datasets.pyramic import simulate_pyramic

from .test_cli import check_contract, invoke, snapshot

_MICS = np.random.default_rng(0).uniform(-0.1, 0.1, (6, 3))
_P1 = simulate_pyramic(_MICS, [13.0], azimuth_step_deg=30.0, rng=1)[0]


def _j(o: object) -> bytes:
    return json.dumps(o).encode()


def _with(**kw: object) -> bytes:
    return _j({**_P1, **kw})


_D = _P1["delays"]
PYRAMIC = {
    # wrong leaf types: numpy reads "1e-3" as 0.001 and true as 1 (before: both ran the solver)
    "delays-strings": (_with(delays=[[str(x) for x in r] for r in _D]), "must hold numbers"),
    "delays-bools": (_with(delays=[[True for _ in r] for r in _D]), "must hold numbers"),
    "delays-dict": (_with(delays={"a": 1}), "must hold numbers"),
    "mics-string": (_with(microphones="abc"), "must hold numbers"),
    "sources-bools": (_with(sources=[[True, False, False] for _ in _P1["sources"]]), "must hold numbers"),
    # speaker ids (before: 1.5 truncated to 1 silently, "a" an int() message)
    "speaker-float": (_with(speaker=1.5), "integer ids"),
    "speaker-string": (_with(speaker="a"), "integer ids"),
    "speaker-huge": (_with(speaker=10**30), "integer ids"),
    # non-finite / out-of-range numbers (before: an infinite microphone and 1e300 ones passed;
    # a speed of 1e-308 m/s gave exit 0 on 1e-311 m distances)
    "mics-inf": (_j({**_P1, "microphones": [[1e300] * 6] * 3}).replace(b"1e+300", b"Infinity", 1), "finite"),
    "mics-huge": (_with(microphones=[[1e300] * 6] * 3), "overflow"),
    "speed-1e308": (_with(sound_speed_mps=1e308), "physical bound"),
    "speed-1e-308": (_with(sound_speed_mps=1e-308), "underflow"),
    "delays-1e-300": (_with(delays=[[1e-300 for _ in r] for r in _D]), "underflow"),
    "delay-1e400": (_j(_P1).replace(b"0.0", b"1e400", 1), "finite"),
    "speed-Infinity": (_with(sound_speed_mps=1).replace(b'"sound_speed_mps": 1', b'"sound_speed_mps": Infinity'),
                       "positive number"),
    # shapes and nesting
    "delays-ragged": (_with(delays=[r[: i + 1] for i, r in enumerate(_D)]), "ragged"),
    "delays-mixed-depth": (_with(delays=[[1.0, [2.0]], [3.0, 4.0]]), "ragged"),
    "mics-ragged": (_with(microphones=[_P1["microphones"][0], _P1["microphones"][1][:-1], _P1["microphones"][2]]),
                    "ragged"),
    "delays-4d": (_with(delays=[[[[1.0]]]]), "must be"),
    "deep-nesting": (b'{"delays": ' + b"[" * 50000 + b"]" * 50000 + b"}", "nested too deeply"),
    "one-column": (_with(delays=[r[:1] for r in _D], sources=_P1["sources"][:1]), "too-few-sources"),
    # not JSON / not an object
    "empty": (b"", "malformed json"),
    "whitespace-crlf": (b" \r\n\r\n", "malformed json"),
    "utf16": (json.dumps(_P1).encode("utf-16"), "malformed json"),
    "top-level-list": (b"[]", "not a pyramic"),
    "trailing-garbage": (_j(_P1) + b" x", "malformed json"),
}


@pytest.mark.parametrize("case", sorted(PYRAMIC))
def test_pyramic_json_malformed(tmp_path: Path, case: str) -> None:
    content, match = PYRAMIC[case]
    p = tmp_path / "pyramic_tdoa_x.json"
    p.write_bytes(content)
    before = snapshot(tmp_path)
    res = invoke(["calibrate", "tdoa-farfield", p, "--directions", "sources", "-o", tmp_path / "r.json"])
    code, _, err = check_contract(res, before, snapshot(tmp_path))
    assert code == 2 and match in err.lower(), err


@pytest.mark.parametrize("variant", ["bom", "crlf", "bom-crlf", "cr"])
def test_pyramic_json_bom_and_line_ends_are_read(tmp_path: Path, variant: str) -> None:
    """A UTF-8 BOM (Windows editors) and CRLF / CR line ends are the same JSON."""
    body = json.dumps(_P1, indent=1).encode()
    if "crlf" in variant:
        body = body.replace(b"\n", b"\r\n")
    if variant == "cr":
        body = body.replace(b"\n", b"\r")
    if "bom" in variant:
        body = b"\xef\xbb\xbf" + body
    p = tmp_path / "pyramic_tdoa_x.json"
    p.write_bytes(body)
    res = invoke(["calibrate", "tdoa-farfield", p, "--directions", "sources", "-o", tmp_path / "r.json"])
    assert check_contract(res)[0] == 0
    ref = tmp_path / "ref.json"
    p.write_bytes(json.dumps(_P1).encode())
    assert invoke(["calibrate", "tdoa-farfield", p, "--directions", "sources", "-o", ref]).exit_code == 0
    a, b = json.loads((tmp_path / "r.json").read_text()), json.loads(ref.read_text())
    assert np.allclose(a["positions"], b["positions"], atol=1e-12)


def _toa_csv() -> bytes:
    g = np.random.default_rng(0)
    R, S = g.uniform(0, 10, (6, 3)), g.uniform(0, 10, (8, 3))
    M = np.linalg.norm(R[:, None] - S[None], axis=2) + 0.01 * g.normal(size=(6, 8))
    return "\n".join(",".join(f"{v:.6f}" for v in r) for r in M).encode() + b"\n"


@pytest.mark.parametrize("variant", ["bom", "crlf", "cr", "bom-crlf-names", "unicode-names"])
def test_csv_bom_line_ends_and_unicode_names_give_the_same_result(tmp_path: Path, variant: str) -> None:
    csv = _toa_csv()
    body = csv
    if variant == "bom":
        body = b"\xef\xbb\xbf" + csv
    elif variant == "crlf":
        body = csv.replace(b"\n", b"\r\n")
    elif variant == "cr":
        body = csv.replace(b"\n", b"\r")
    elif variant in ("bom-crlf-names", "unicode-names"):
        head = ",".join(["", *[f"s\u00fc{j}\u2713" for j in range(8)]]).encode()
        rows = [f"r\u00e9{i},".encode() + ln for i, ln in enumerate(csv.strip().split(b"\n"))]
        eol = b"\r\n" if variant == "bom-crlf-names" else b"\n"
        body = (b"\xef\xbb\xbf" if variant == "bom-crlf-names" else b"") + eol.join([head, *rows]) + eol
    (tmp_path / "ref.csv").write_bytes(csv)
    p = tmp_path / "m \u540d\u524d.csv"  # a unicode file name with a space
    p.write_bytes(body)
    res = invoke(["calibrate", "toa", p, "-o", tmp_path / "r \u2713.json"])
    code = check_contract(res)[0]
    ref = invoke(["calibrate", "toa", tmp_path / "ref.csv", "-o", tmp_path / "ref.json"])
    assert code == ref.exit_code
    a = json.loads((tmp_path / "r \u2713.json").read_text())
    b = json.loads((tmp_path / "ref.json").read_text())
    assert np.allclose(a["receivers"], b["receivers"], atol=1e-9)
    if "names" in variant:
        assert a["receiver_names"][0] == "r\u00e90" and a["source_names"][1] == "s\u00fc1\u2713"


@pytest.mark.parametrize("kind", ["fifo", "devzero", "dir", "symlink-loop", "newline-name"])
@pytest.mark.parametrize("command", ["plaza", "lps", "slac-run", "farfield"])
def test_special_files_as_inputs(tmp_path: Path, kind: str, command: str) -> None:
    """FIFOs and /dev/zero are refused before any read (a read would block or never end)."""
    d = tmp_path / "w"
    d.mkdir()
    p = d / "special"
    if kind == "fifo":
        os.mkfifo(p)
    elif kind == "devzero":
        p = Path("/dev/zero")
    elif kind == "dir":
        p.mkdir()
    elif kind == "symlink-loop":
        p.symlink_to(p)
    else:
        p = d / "a\nb.mat"
        p.write_bytes(b"not a file of any kind")
    args = {"plaza": ["slac", "plaza", p, "-o", d / "r.json"],
            "lps": ["reproduce", "lps", "--data", p, "-o", d / "out", "--simulate", "0"],
            "slac-run": ["slac", "run", p, "-o", d / "r.json"],
            "farfield": ["calibrate", "tdoa-farfield", p, "-o", d / "r.json"]}[command]
    before = snapshot(d)
    res = invoke(args)
    assert check_contract(res, before, snapshot(d))[0] == 2


def test_simulate_conference_into_a_symlinked_folder_keeps_the_link(tmp_path: Path) -> None:
    """before: the link was renamed aside (a stale ``.out.old-PID`` link left behind) and a new
    real folder put in its place; now the folder it points to is the output."""
    target = tmp_path / "target"
    target.mkdir()
    link = tmp_path / "out"
    link.symlink_to(target)
    res = invoke(["simulate", "conference", "--units", "5", "--room", "5x5x3", "--max-order", "0", "--out", link])
    assert check_contract(res)[0] == 0
    assert link.is_symlink() and (target / "setup.json").is_file()
    assert sorted(q.name for q in tmp_path.iterdir()) == ["out", "target"]


@pytest.mark.parametrize("heights,match", [
    ({"receivers": ["1", "1"], "senders": [1, 1]}, "found '1'"),     # before: read as numbers
    ({"receivers": [True, 1.2], "senders": [1, 1]}, "found True"),   # before: true read as 1 m
    ({"receivers": [1e300, 1.2], "senders": [1, 1]}, "overflow"),
])
def test_pipeline_heights_json_leaf_types(tmp_path: Path, heights: dict, match: str) -> None:  # type: ignore[type-arg]
    from .test_cli import _tiny_recording

    rec = _tiny_recording(tmp_path)
    (tmp_path / "h.json").write_text(json.dumps(heights))
    before = snapshot(tmp_path)
    res = invoke(["pipeline", rec, "-o", tmp_path / "r.json", "--heights", tmp_path / "h.json"])
    code, _, err = check_contract(res, before, snapshot(tmp_path))
    assert code == 2 and match in err, err


_TRUTH = {"receivers": [[0, 0, 1], [1, 0, 1]], "senders": [[0, 0, 0.8], [1, 0, 0.8]],
          "receiver_delays": [0.0, 1e-4], "sender_onsets": [0.0, 2e-4]}


@pytest.mark.parametrize("truth,match", [
    ({k: v for k, v in _TRUTH.items() if k != "receivers"}, "'receivers' is missing"),  # before: KeyError
    ({**_TRUTH, "sender_onsets": ["x", "y"]}, "must hold numbers"),                   # before: ValueError
    ([1, 2], "expected an object"),                                                   # before: TypeError
    ({**_TRUTH, "receivers": [[0, 0, 1]]}, "one receiver_delay per receiver"),        # before: align's message
    ({**_TRUTH, "receivers": [[0, 0, 1], [1, 0]]}, "ragged"),
])
def test_pipeline_truth_json_validated_before_the_run(tmp_path: Path, truth: object, match: str) -> None:
    """A recording folder's truth.json (scores only) is checked before the calibration runs:
    one line, exit 2, nothing written (before: an internal error after the whole run)."""
    from .test_cli import _tiny_recording

    rec = _tiny_recording(tmp_path)
    (rec / "truth.json").write_text(json.dumps(truth))
    before = snapshot(tmp_path)
    res = invoke(["pipeline", rec, "-o", tmp_path / "r.json"])
    code, _, err = check_contract(res, before, snapshot(tmp_path))
    assert code == 2 and match in err, err


def test_boolean_npy_matrix_is_refused(tmp_path: Path) -> None:
    """A saved mask is not a range matrix: True / False were read as ranges of 1 m / 0 m."""
    f = tmp_path / "mask.npy"
    np.save(f, np.random.default_rng(0).random((8, 10)) > 0.5)
    res = invoke(["calibrate", "toa", str(f), "-o", str(tmp_path / "r.json")])
    code, _, err = check_contract(res)
    assert code == 2 and "boolean" in err
    assert not (tmp_path / "r.json").exists()
