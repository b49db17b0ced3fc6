"""selfcal.acoustics: paper 004's acoustic system, from recordings to positions.

- :mod:`.probe`      chirp / WAV probe signals
- :mod:`.recording`  the recording format (``setup.json`` + ``rx_<name>.wav``), validation
- :mod:`.detect`     FFT matched-filter, first-significant-peak arrival-time detection
- :mod:`.room`       pyroomacoustics simulation of a conference network
- :mod:`.noise`      timing-noise model of the detections, robust residual check
- :mod:`.calibrate`  TOA matrix -> onsets, delays, positions: one model fit, outliers, dropped units
- :mod:`.geometry`   near-planarity, mirror ambiguities, known heights (2-D fallback)
- :mod:`.verdict`    004 requirements judged from the result's error bars
- :mod:`.scoring`    errors against a simulation's truth.json
- :mod:`.pipeline`   orchestration: recording -> detections -> calibration -> verdict
"""

from __future__ import annotations

from typing import Any

_EXPORTS = {
    "Probe": "probe", "linear_chirp": "probe", "probe_from_spec": "probe",
    "Setup": "recording", "Recording": "recording", "load_recording": "recording",
    "write_recording": "recording", "read_wav": "recording", "write_wav": "recording",
    "Detections": "detect", "detect_arrivals": "detect", "detect_recording": "detect",
    "simulate_conference": "room",
    "PipelineResult": "pipeline", "run_pipeline": "pipeline", "planarity": "pipeline",
    "refine_known_heights": "geometry", "calibrate_matrix": "calibrate", "truth_errors": "scoring",
    "robust_calibrate": "robust_fit", "redetect_arrivals": "detect", "error_bars": "verdict", "judge": "verdict",
    "residual_check": "noise", "detection_std": "noise",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str) -> Any:
    if name in _EXPORTS:
        import importlib

        return getattr(importlib.import_module(f".{_EXPORTS[name]}", __name__), name)
    raise AttributeError(f"module 'selfcal.acoustics' has no attribute {name!r}")
