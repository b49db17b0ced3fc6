"""Command-line commands for this area (attached to the groups in selfcal.commands._base)."""

from __future__ import annotations
