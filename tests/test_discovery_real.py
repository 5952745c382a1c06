"""Effect discovery on the measured recordings in ../shared/data (fails if they are missing).

What each asserts is what discovery found on it (docs/performance.md, `recal discover`):
- Xsens multi-position (raw 16-bit counts, lab poses): cross-axis coupling (~1.2° between
  the y and z sensing axes) takes the held-out error from ~3.8 mg to ~0.17 mg;
- GENEActiv cooling (one pose, 37 -> 27 °C): an offset linear in temperature on the axis
  along gravity; the axes across gravity are reported unobserved; the still signal's drift
  against temperature shrinks;
- the three phone tables (Georgieva et al.): cross-axis terms do not earn their place on
  held-out rows against offsets and gains, for any split of the rows into blocks.
"""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import pytest

from recal.core import discovery as dc
from recal.core import discovery_data as dd
from recal.samples import RawBatch

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"


def _npz(name: str) -> dict[str, np.ndarray]:
    path = SHARED / "real" / name
    assert path.is_file(), f"measured data missing: {path} (the tests need ../shared/data)"
    with np.load(path) as z:
        return {k: z[k] for k in z.files}


def _phone(n: int) -> np.ndarray:
    path = SHARED / "static_positions" / f"phone{n}.csv"
    assert path.is_file(), f"measured data missing: {path}"
    with open(path, newline="") as f:
        rows = list(csv.reader(f))[1:]
    return np.array([[float(x) for x in r[1:4]] for r in rows])


def _report(name: str, r: dc.DiscoveryResult) -> None:
    print(f"\n{name}: {len(r.data)} windows ({r.data.dropped} moving dropped, "
          f"{int((~r.scored).sum())} unscored), held-out {r.heldout_base_mg:.3f} -> "
          f"{r.heldout_final_mg:.3f} mg; steps "
          f"{[(s.action, s.effect.label, round(s.gain, 3), round(s.se, 3)) for s in r.steps]}")
    for e in r.selected:
        print(f"  {e.label}: {e.params} observed {e.observable} {e.extra}")


def test_xsens_multiposition_cross_axis_found_and_held_out_error_falls() -> None:
    z = _npz("xsens_imutk_multipos.npz")
    # unsigned 16-bit ADC counts, zero g at mid-scale (the file's meta says so)
    v = z["acc_counts"].astype(np.float64) - 32768.0
    t_us = np.round(z["t"] * 1e6).astype(np.int64)
    result = dc.discover(dd.data_from_batch(RawBatch(t_us, v, np.zeros((len(v), 0)))))
    _report("xsens", result)
    assert result.heldout_final_mg < result.heldout_base_mg
    assert result.heldout_final_mg < 0.2 * result.heldout_base_mg
    assert [e.kind for e in result.selected] == ["cross_axis"]
    angles = result.selected[0].extra
    assert 0.5 < 90.0 - angles["theta_yz_deg"] < 2.0  # y and z sensing axes ~1.2° off square
    assert result.data.dropped >= 1  # windows straddling a rotation were screened out
    assert result.held_at_start() == ()  # ~13 orientations determine every parameter


def test_geneactiv_cooling_temperature_offset_on_the_axis_along_gravity() -> None:
    z = _npz("geneactiv_wristpy_cooling.npz")
    t_us = np.round(z["t"] * 1e6).astype(np.int64)
    aux = np.stack([z["temp"], z["batt"]], axis=1).astype(np.float64)
    raw = RawBatch(t_us, z["acc_counts"].astype(np.float64), aux, ("temp", "batt"))
    result = dc.discover(dd.data_from_batch(raw))
    _report("geneactiv", result)
    found = {(e.kind, e.covariate): e for e in result.selected}
    assert ("offset", "temp") in found
    temp_offset = found[("offset", "temp")]
    # gravity lies along -y (u ~ (0, -0.98, -0.21)): only y sees it; x and z are reported
    # unobserved and stay at zero rather than soaking up noise
    assert temp_offset.observable == {"o_temp_x": False, "o_temp_y": True, "o_temp_z": False}
    assert temp_offset.params["x_mg_per_temp"] == 0.0 == temp_offset.params["z_mg_per_temp"]
    assert abs(temp_offset.params["y_mg_per_temp"]) > 0.1
    # one pose: no gain, and no offset across gravity, is determined; the report says so
    held = set(result.held_at_start())
    assert {"s_x", "s_y", "s_z", "o_x", "o_z", "o_temp_x", "o_temp_z"} <= held, held
    assert not {"o_y", "o_temp_y"} & held, held
    assert result.heldout_final_mg < 0.8 * result.heldout_base_mg
    # drift of the still signal against temperature, on held-out windows, before and after
    temp = result.data.cov.get("temp")
    keep = result.scored
    before = np.polyfit(temp[keep], 1e3 * result.heldout_xi_base[keep], 1)[0]
    after = np.polyfit(temp[keep], 1e3 * result.heldout_xi_final[keep], 1)[0]
    print(f"  drift of |a| against temperature: {before:.3f} -> {after:.3f} mg/°C")
    assert abs(before) > 0.2
    assert abs(after) < 0.3 * abs(before)


@pytest.mark.parametrize("phone", [1, 2, 3])
def test_phone_tables_cross_axis_does_not_earn_its_place_for_any_split(phone: int) -> None:
    v = _phone(phone)
    outcome = {}
    for blocks in (5, 7, 9, 10, 13, len(v)):  # leave-block-of-rows-out, down to one row
        r = dc.discover(dd.data_from_table(v), cfg=dc.DiscoveryConfig(blocks=blocks))
        first = r.steps[0].candidates if r.steps else r.last_round
        cross = next(c for c in first if c.kind == "cross_axis")
        outcome[blocks] = (round(cross.gain, 3), round(cross.se, 3), cross.passed,
                           [s.effect.label for s in r.steps])
        assert not cross.passed
        assert not r.steps or r.steps[0].effect.kind != "cross_axis"
        assert r.heldout_final_mg <= r.heldout_base_mg
    print(f"\nphone{phone}: cross-axis first-round R, SE, passed, steps by blocks: {outcome}")
    if phone in (2, 3):  # nothing earns its place in these tables, whatever the split
        assert all(o[3] == [] for o in outcome.values())
