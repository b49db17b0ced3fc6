"""`selfcal reproduce slac` on a short replica: files, recorded settings, the Fig. 3 ordering."""

from __future__ import annotations

import json
from pathlib import Path

from click.testing import CliRunner

from selfcal.cli import main


def test_reproduce_slac_writes_table_and_figures(tmp_path: Path) -> None:
    out = tmp_path / "slac"
    res = CliRunner().invoke(main, ["reproduce", "slac", "--minutes", "0.3", "--subcarriers", "32", "--backend",
                                    "serial", "--out", str(out)])
    assert res.exit_code == 0, res.output
    d = json.loads((out / "slac_reproduction.json").read_text())
    assert d["init"] == "snapshot" and d["smoother_lag"] == 0
    assert set(d["table_I"]) == {"Dias", "Drake", "Vespucci", "Magellan"}
    for row in d["table_I"].values():
        assert row["position_rmse_slac"] < 0.5
    # SLAC's calibrated response beats the EM-simulation prior (Fig. 3)
    assert d["fig3_doa"]["filter"]["p90_deg"] < d["fig3_doa"]["em"]["p90_deg"]
    for png in ("fig3_doa_cdf.png", "fig4_ranging_rmse.png", "table1_position_rmse.png"):
        assert (out / png).stat().st_size > 0


def test_reproduce_slac_refuses_negative_lag(tmp_path: Path) -> None:
    res = CliRunner().invoke(main, ["reproduce", "slac", "--smoother-lag", "-1", "--out", str(tmp_path / "x")])
    assert res.exit_code == 2
    assert not (tmp_path / "x").exists()
