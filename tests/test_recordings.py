"""The example recordings in recordings/ show what their README says they show."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from recal.cli import main
from recal.io import recording as rec
from recal.sim.wearer import load_truth

RECORDINGS = Path(__file__).resolve().parents[1] / "recordings"


def test_the_temperature_example_hides_an_offset_in_board_temp_that_discovery_finds(
        tmp_path: Path) -> None:
    mcap = RECORDINGS / "wearer-temp-30min.mcap"
    raw = rec.read_all_raw(mcap, "sim0")
    assert raw.aux_names == ("board_temp",)
    assert np.ptp(raw.aux[:, 0]) > 2.0  # the temperature moves enough to see the effect
    report = tmp_path / "report.json"
    assert main(["discover", str(mcap), "--json", str(report)]) == 0
    doc = json.loads(report.read_text())
    found = [(e["kind"], e["covariate"]) for e in doc["effects_selected"]]
    assert found == [("offset", "board_temp")]
    truth = load_truth(mcap.with_suffix(".truth.npz"))
    slopes_mg = [doc["effects_selected"][0]["params"][f"{ax}_mg_per_board_temp"] for ax in "xyz"]
    true_mg = 1e3 * np.asarray(truth.truth.sensor.offset_tc_g_per_c)
    np.testing.assert_allclose(slopes_mg, true_mg, atol=0.15)
    assert doc["heldout_error_mg"]["final"] < 0.5 * doc["heldout_error_mg"]["base"]
