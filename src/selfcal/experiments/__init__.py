"""Reproductions of the papers' experiments and the sweep runner they share."""

from .runner import BACKENDS, run_sweep, write_rows

__all__ = ["BACKENDS", "run_sweep", "write_rows"]
