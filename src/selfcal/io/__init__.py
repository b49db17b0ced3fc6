"""Readers and writers: CSV / NPY matrices, JSON results, NPZ logs (never pickle).

Matrices follow the project convention: rows = receivers, columns = transmitters
(points as rows), ``nan`` / ``NA`` / an empty CSV field = missing.

The I/O contract (DESIGN.md, "Inputs and outputs"):

* **Outputs never destroy anything.** :func:`atomic_write_bytes` writes a temporary file
  beside the target and ``os.replace``-s it, but only over a regular file or a new path.
  A symlink is written through (its target is replaced, the link stays); a directory,
  device, FIFO or socket at the path is refused with :class:`OutputError`. ``"-"`` means
  standard output. Any failure (parent is a file, disk full, read-only, name too long) is an
  :class:`OutputError` and leaves no new file behind.
* **All or nothing.** Inside :func:`staged_outputs` every write is buffered and the whole set
  is committed when the block ends without an exception (temporary files first, then the
  renames), or nothing is written.
* **Readers take real files.** :func:`read_table` sniffs the delimiter (comma, semicolon,
  tab, whitespace), a header row and a first column of names, a UTF-8 BOM, CRLF line ends,
  ``#`` comments (``np.savetxt`` output loads), and refuses what Python's ``float`` would
  misread (``1_0``); errors name the row and the column.

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
