"""Pyramic: several speakers calibrated jointly (simulated on the real array), the real speaker honestly refused.

The simulation uses the hand-measured 48-microphone layout of the shared file as the truth,
the real turntable (180 azimuths in 2-degree steps, one elevation per speaker), Gaussian
delay noise plus the real recording's quantisation to 192 kHz samples (together the 1.0 mm
residual of the shared speaker fitted with its own directions) and two gross GCC-PHAT errors
per speaker, as in the real file.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
from click.testing import CliRunner

from selfcal.cli import main
from selfcal.datasets.pyramic import join_pyramic, load_pyramic, pyramic_from_dict, simulate_pyramic
from selfcal.errors import DegenerateGeometryError, InputError
from selfcal.geometry import align
from selfcal.tdoa import farfield_crlb, solve_farfield

C = 345.08736
STEP = C / 192000.0  # one sample at 192 kHz, metres


@pytest.fixture(scope="module")
def real(shared_data):
    return load_pyramic(shared_data / "pyramic")


def _aligned_mse(est, ref):
    al = align(est, ref, reflection=True)
    return float(np.mean(np.sum((al.apply(est) - ref) ** 2, axis=1)))


def _sigma_total(noise_std):
    # variance of Gaussian noise rounded to a grid of STEP: sigma^2 + STEP^2 / 12 (Sheppard)
    return float(np.sqrt(noise_std**2 + STEP**2 / 12.0))


def _joint(mics, elev, seed, step=6.0, noise=0.87e-3):
    files = simulate_pyramic(mics, elev, azimuth_step_deg=step, noise_std=noise, rng=seed)
    return join_pyramic([pyramic_from_dict(f) for f in files])


def test_simulation_matches_the_real_residual(real):
    # the simulated noise is calibrated on the real file: its residual with its own directions
    res = solve_farfield(real.D, directions=real.directions)
    assert 0.8e-3 < res.residual_rms < 1.2e-3  # measured 1.0117 mm
    data = _joint(real.microphones, [13.16], 0, step=2.0)
    sim = solve_farfield(data.D, directions=data.directions)
    assert abs(sim.residual_rms - res.residual_rms) < 0.15e-3


@pytest.mark.parametrize("elev", [[13.16, -15.5, 1.0], [13.16, 25.0], [-8.0, 13.16, 30.0]])
def test_speakers_at_different_elevations_calibrate_blind_to_the_crlb(real, elev):
    # speakers at different |elevation|: no common quadric cone, the blind problem is determined.
    # 4 seeds, 60 azimuths per speaker (6-degree steps, to keep the default suite fast): the
    # mean aligned MSE over seeds against the CRLB trace; an efficient estimator gives a ratio
    # near 1 whose spread over 4 seeds x 144 coordinates is about 10 %: 0.6 .. 1.6 is generous
    mics = real.microphones
    Z = mics - mics[0]
    ratios = []
    for seed in range(4):
        data = _joint(mics, elev, seed)
        res = solve_farfield(data.D)
        assert res.degeneracy is None and res.converged and res.case == "spatial"
        assert res.rejected.sum() >= 2 * len(elev) - 1  # the planted gross errors (two may coincide)
        bound = np.trace(farfield_crlb(Z, data.directions, _sigma_total(0.87e-3)).sum(0)) / len(Z)
        ratios.append(_aligned_mse(res.positions, Z) / bound)
    assert 0.6 < np.mean(ratios) < 1.6, ratios


@pytest.mark.slow
def test_three_speakers_full_turntable_reach_the_crlb_over_many_seeds(real):
    mics = real.microphones
    Z = mics - mics[0]
    mse, bound = [], []
    for seed in range(20):
        data = _joint(mics, [13.16, -15.5, 1.0], 100 + seed, step=2.0)
        res = solve_farfield(data.D)
        mse.append(_aligned_mse(res.positions, Z))
        bound.append(np.trace(farfield_crlb(Z, data.directions, _sigma_total(0.87e-3)).sum(0)) / len(Z))
    assert 0.8 < np.mean(mse) / np.mean(bound) < 1.25


@pytest.mark.parametrize("elev", [[13.16], [13.16, -13.16], [13.16, 13.16]])
def test_speakers_on_one_cone_are_refused(real, elev):
    # one elevation, or +e / -e (the same cone n_x^2 + n_y^2 = cot^2(e) n_z^2): not determined
    data = _joint(real.microphones, elev, 3)
    with pytest.raises(DegenerateGeometryError) as info:
        solve_farfield(data.D)
    assert info.value.kind == "cone"


def test_cli_joins_files_folders_and_the_multi_speaker_layout(tmp_path, real):
    files = simulate_pyramic(real.microphones, [13.16, -15.5, 1.0], azimuth_step_deg=6.0, rng=7)
    folder = tmp_path / "pyr"
    folder.mkdir()
    for s, f in enumerate(files):
        (folder / f"pyramic_tdoa_speaker{s}.json").write_text(json.dumps(f))
    # the upstream single-file layout: delays [mic][source][speaker], sources [xyz][source][speaker]
    nested = {
        "delays": np.stack([np.array(f["delays"]) for f in files], axis=-1).tolist(),
        "sources": np.stack([np.array(f["sources"]).T for f in files], axis=-1).tolist(),
        "microphones": files[0]["microphones"], "sound_speed_mps": C, "mic_ref": 0,
    }
    (tmp_path / "all.json").write_text(json.dumps(nested))
    one = [str(folder / "pyramic_tdoa_speaker0.json")]
    runs = {"files": [str(folder / f"pyramic_tdoa_speaker{s}.json") for s in range(3)], "folder": [str(folder)],
            "nested": [str(tmp_path / "all.json")]}
    Z = real.microphones - real.microphones[0]
    bound = np.sqrt(np.trace(farfield_crlb(Z, load_pyramic(folder).directions, _sigma_total(0.87e-3)).sum(0))
                    / len(Z))
    positions = {}
    for name, args in runs.items():
        out = tmp_path / f"{name}.json"
        r = CliRunner().invoke(main, ["calibrate", "tdoa-farfield", *args, "--out", str(out)])
        assert r.exit_code == 0, r.output
        assert "3 speaker(s)" in r.output
        res = json.loads(out.read_text())
        assert res["case"] == "spatial" and len(res["directions"]) == 180 and len(set(res["speaker"])) == 3
        # one draw: within 3x the CRLB rms (the rms error over 144 coordinates rarely exceeds 1.5x)
        assert res["reference_rmse"] < 3 * bound, (res["reference_rmse"], bound)
        positions[name] = np.array(res["positions"])
    # the three layouts hold the same data: the same answer (up to the column order)
    assert np.sqrt(_aligned_mse(positions["files"], positions["nested"])) < 1e-6
    assert np.sqrt(_aligned_mse(positions["folder"], positions["files"])) < 1e-9
    # one speaker alone: refused as a cone, naming the remedy
    r = CliRunner().invoke(main, ["calibrate", "tdoa-farfield", *one, "--out", str(tmp_path / "one.json")])
    assert r.exit_code == 2 and "[cone]" in r.output and "different absolute elevations" in r.output


def test_real_speaker_is_refused_honestly_and_semi_blind_is_reported(tmp_path, shared_data):
    src = shared_data / "pyramic" / "pyramic_tdoa_speaker0.json"
    out = tmp_path / "r.json"
    r = CliRunner().invoke(main, ["calibrate", "tdoa-farfield", str(src), "--out", str(out)])
    assert r.exit_code == 2 and "[cone]" in r.output and "speaker 0 at 13.2 deg" in r.output
    assert not out.exists() and "Traceback" not in r.output
    r = CliRunner().invoke(main, ["calibrate", "tdoa-farfield", str(shared_data / "pyramic"), "--directions",
                                  "sources", "--out", str(out)])
    assert r.exit_code == 0, r.output
    # semi-blind with the file's own directions: 12.2 mm from the hand-measured layout (measured);
    # it is reported, not hidden: the directions of the turntable set-up are that far off
    assert 5e-3 < json.loads(out.read_text())["reference_rmse"] < 20e-3


def test_joining_refuses_different_arrays_and_repeated_files(tmp_path, real):
    a, b = simulate_pyramic(real.microphones, [10.0, 20.0], azimuth_step_deg=30.0, rng=1)
    b["microphones"] = (np.array(b["microphones"]) * 1.01).tolist()
    with pytest.raises(InputError, match="microphones differ"):
        join_pyramic([pyramic_from_dict(a), pyramic_from_dict(b)])
    p = tmp_path / "pyramic_tdoa_a.json"
    p.write_text(json.dumps(a))
    with pytest.raises(InputError, match="given twice"):
        load_pyramic([p, p])


# --------------------------------------------------------------------------- layout variants
def _upstream(files):
    """The upstream single-file layout: delays [mic][source][speaker], sources [xyz][source][speaker]."""
    return {"sound_speed_mps": files[0]["sound_speed_mps"], "mic_ref": 0,
            "delays": np.stack([np.array(f["delays"]) for f in files], axis=-1).tolist(),
            "sources": np.stack([np.array(f["sources"]).T for f in files], axis=-1).tolist(),
            "microphones": files[0]["microphones"]}


def _small_files():
    mics = np.random.default_rng(0).uniform(-0.1, 0.1, (8, 3))
    return mics, simulate_pyramic(mics, [13.0, -15.0], azimuth_step_deg=30.0, gross=0, rng=1)


def test_loader_reads_the_variants_of_the_upstream_layout():
    mics, files = _small_files()  # 2 speakers x 12 positions
    up = _upstream(files)
    full = pyramic_from_dict(up)
    assert full.D.shape == (8, 24) and full.skipped == 0 and full.speakers == [0, 1]
    # a (source, speaker) pair never recorded (all null) is dropped with its direction; a single
    # missing delay stays missing
    d = np.array(up["delays"], dtype=object)
    d[:, 5, 1] = None
    d[3, 7, 0] = None
    part = pyramic_from_dict({**up, "delays": d.tolist()})
    assert part.skipped == 1 and part.D.shape == (8, 23) and np.isnan(part.D).sum() == 1
    assert np.allclose(part.sources, np.delete(full.sources, 12 + 5, axis=0))
    # absent metadata: mic_ref 0, no microphones (size from the delays), no sources
    no_ref = {key: v for key, v in up.items() if key != "mic_ref"}
    assert np.array_equal(pyramic_from_dict(no_ref).D, full.D)
    no_mics = pyramic_from_dict({key: v for key, v in up.items() if key != "microphones"})
    assert not no_mics.has_microphones and no_mics.D.shape == (8, 24) and np.array_equal(no_mics.D, full.D)
    no_src = pyramic_from_dict({key: v for key, v in up.items() if key != "sources"})
    assert not no_src.has_sources and np.array_equal(no_src.D, full.D)
    assert all(np.isnan(e) for e in no_src.elevations().values())
    # the speed: required from somewhere
    no_speed = {key: v for key, v in up.items() if key != "sound_speed_mps"}
    with pytest.raises(InputError, match="--speed"):
        pyramic_from_dict(no_speed)
    assert np.allclose(pyramic_from_dict(no_speed, speed=C).D, full.D)


def test_loader_refuses_ragged_and_directionless_columns_in_one_line():
    mics, files = _small_files()
    up = _upstream(files)
    rag = {**up, "delays": [[row[:1] if j == 3 else row for j, row in enumerate(m)] for m in up["delays"]]}
    with pytest.raises(InputError, match="ragged.*pad the missing ones with null, or give each speaker its own file"):
        pyramic_from_dict(rag)
    s = np.array(up["sources"], dtype=object)
    s[:, 2, 0] = None
    with pytest.raises(InputError, match="source 2 has delays but no finite direction"):
        pyramic_from_dict({**up, "sources": s.tolist()})


def test_speakers_with_different_turntable_positions_join(tmp_path):
    mics, files = _small_files()
    half = {**files[1], "delays": np.array(files[1]["delays"])[:, ::2].tolist(),
            "sources": np.array(files[1]["sources"])[::2].tolist()}
    for i, f in enumerate([files[0], half]):
        (tmp_path / f"pyramic_tdoa_{i}.json").write_text(json.dumps(f))
    data = load_pyramic(tmp_path)
    assert data.D.shape == (8, 18) and list(np.bincount(data.speaker)) == [12, 6]


def test_cli_on_incomplete_upstream_files(tmp_path, real):
    files = simulate_pyramic(real.microphones, [13.16, -15.5, 1.0], azimuth_step_deg=12.0, rng=3)
    up = _upstream(files)
    d = np.array(up["delays"], dtype=object)
    d[:, 4, 2] = None
    bare = {key: v for key, v in up.items() if key not in ("microphones", "mic_ref")}
    p = tmp_path / "pyramic_tdoa.json"
    p.write_text(json.dumps({**bare, "delays": d.tolist()}))
    r = CliRunner().invoke(main, ["calibrate", "tdoa-farfield", str(p), "--out", str(tmp_path / "o.json")])
    assert r.exit_code == 0, r.output
    assert "1 (source, speaker) column(s) without any delay skipped" in r.output
    assert "no 'microphones' in the file" in r.output
    res = json.loads((tmp_path / "o.json").read_text())
    assert len(res["directions"]) == 89 and "reference_rmse" not in res
    rag = {**up, "delays": [[row[:2] if j == 1 else row for j, row in enumerate(m)] for m in up["delays"]]}
    p.write_text(json.dumps(rag))
    r = CliRunner().invoke(main, ["calibrate", "tdoa-farfield", str(p), "--out", str(tmp_path / "o2.json")])
    assert r.exit_code == 2 and "ragged" in r.output and "Traceback" not in r.output
    assert len([ln for ln in r.output.splitlines() if ln.startswith("selfcal: error")]) == 1
