"""Command modules of the ``selfcal`` CLI, one per area (see :mod:`selfcal.cli`)."""
