"""Readers and writers: CSV / NPY matrices, JSON results, NPZ logs (never pickle).

Matrices follow the project convention: rows = receivers, columns = transmitters
(points as rows), ``nan`` / ``NA`` / an empty CSV field = missing.

The I/O contract (DESIGN.md, "Inputs and outputs"): outputs never destroy anything and are
written all together or not at all (:mod:`selfcal.io.outputs`); readers take real files and
refuse what they would misread (:mod:`selfcal.io.inputs`).

Two modules by job: :mod:`selfcal.io.inputs` (the readers) and :mod:`selfcal.io.outputs`
(the writers); everything is re-exported here (``from selfcal.io import write_json``).
"""

from __future__ import annotations

import os  # noqa: F401  (tests patch ``selfcal.io.os.fsync`` to simulate a full disk)

from .inputs import MISSING_TOKENS, Table, load_npz, read_json, read_matrix, read_table
from .outputs import (
    OutputError,
    SerializationError,
    atomic_write_bytes,
    check_output_path,
    staged_outputs,
    stdout_target,
    write_csv_rows,
    write_json,
    write_matrix,
)

__all__ = [
    "OutputError",
    "SerializationError",
    "Table",
    "read_table",
    "read_matrix",
    "write_matrix",
    "write_json",
    "read_json",
    "atomic_write_bytes",
    "check_output_path",
    "staged_outputs",
    "stdout_target",
    "load_npz",
    "MISSING_TOKENS",
    "write_csv_rows",
]
